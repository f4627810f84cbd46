"""A material's BSDF on its own (kernels/render/sampling.cl): samples of it
and its values, on the device, the same code the path integrator runs.
Tests check sampling against evaluation with them, as Mitsuba 3's chi2
tests do; a user can check a material the same way.

    sample_bsdf(material, wo, count)  -> directions, weights (f cos / pdf), pdfs
    eval_bsdf(material, wo, wi)       -> f cos, pdfs
    sample_envmap(emitter, count)     -> directions, radiance, pdfs
    eval_envmap(emitter, wi)          -> radiance, pdfs
    sample_lights(renderer, point, count) -> directions, radiance, pdfs, reaches
    turn_angles(u)                    -> sin and cos of 2 pi u, as the samplers take them

``material`` is a materials.py spec; ``wo`` the unit direction towards the
viewer and ``normal`` the surface's (default +z), turned towards wo for a
BSDF with sides as the integrator turns it.  Delta lobes have density 0.
``emitter`` is an "envmap" spec (emitters.py, envmap.py); its densities are
per solid angle, before the integrator's chance of picking the map.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from ..core import inputs, layout
from ..core.paths import kernel_of
from ..device.runtime import runtime
from .envmap import check_envmap
from .integrators.path import envmap_params, light_params, light_tables, upload_table
from .materials import check_material

KERNEL = kernel_of(__name__)


def _setup(material, wo, normal, device):
    rt = runtime(device)
    record = np.ascontiguousarray(check_material("material", material).reshape(1))
    table = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                      hostbuf=record)
    vectors = []
    for name, value in (("normal", normal), ("wo", wo)):
        vector = inputs.vector3(name, value)
        length = float(np.linalg.norm(vector))
        if not length > 0:
            raise ValueError(f"{name} is the zero vector")
        vectors += [np.float32(x) for x in vector / length]
    return rt, table, vectors


def sample_bsdf(material, wo, count: int, seed: int = 0, normal=(0.0, 0.0, 1.0),
                device=None) -> dict[str, np.ndarray]:
    """``count`` samples: "directions" (count, 3), "weights" (count, 3) and
    "pdfs" (count,), float32; a zero weight where the BSDF gives none."""
    count = inputs.integer("count", count, 1, 1 << 26)
    seed = inputs.integer("seed", seed, 0, 2**32 - 1)
    rt, table, vectors = _setup(material, wo, normal, device)
    out = {"directions": np.empty((count, 3), np.float32),
           "weights": np.empty((count, 3), np.float32), "pdfs": np.empty(count, np.float32)}
    buffers = {name: cl.Buffer(rt.context, cl.mem_flags.WRITE_ONLY, array.nbytes)
               for name, array in out.items()}
    rt.run(rt.kernel(KERNEL, "bsdf_samples"), count, table, *vectors, np.uint32(count),
           np.uint32(seed), buffers["directions"], buffers["weights"], buffers["pdfs"])
    for name, array in out.items():
        cl.enqueue_copy(rt.queue, array, buffers[name])
    return out


def eval_bsdf(material, wo, wi, normal=(0.0, 0.0, 1.0), device=None) -> dict[str, np.ndarray]:
    """f cos ("values", (N, 3)) and the density ("pdfs", (N,)) towards each
    unit direction of ``wi`` (N, 3)."""
    wi = np.ascontiguousarray(wi, np.float32).reshape(-1, 3)
    rt, table, vectors = _setup(material, wo, normal, device)
    count = len(wi)
    out = {"values": np.empty((count, 3), np.float32), "pdfs": np.empty(count, np.float32)}
    directions = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                           hostbuf=wi)
    buffers = {name: cl.Buffer(rt.context, cl.mem_flags.WRITE_ONLY, array.nbytes)
               for name, array in out.items()}
    rt.run(rt.kernel(KERNEL, "bsdf_values"), count, table, *vectors, np.uint32(count),
           directions, buffers["values"], buffers["pdfs"])
    for name, array in out.items():
        cl.enqueue_copy(rt.queue, array, buffers[name])
    return out


def _envmap_setup(emitter, device):
    rt = runtime(device)
    if not isinstance(emitter, dict) or emitter.get("type") != "envmap":
        raise ValueError(f"emitter must be an envmap spec such as {{'type': 'envmap', "
                         f"'filename': 'sky.exr'}}, got {inputs.describe(emitter)}")
    envmap = check_envmap("emitter", {k: v for k, v in emitter.items() if k != "type"})
    params = np.zeros((), layout.PATH_PARAMS)
    envmap_params(params, envmap)
    flags = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
    return rt, [params, cl.Buffer(rt.context, flags, hostbuf=envmap.image),
                cl.Buffer(rt.context, flags, hostbuf=envmap.tables[0])]


def _launch(rt, name, count, arguments, out) -> dict[str, np.ndarray]:
    """Run kernel ``name`` over ``count`` items with ``arguments`` and then
    one write-only buffer per array of ``out``, and read them back."""
    buffers = {key: cl.Buffer(rt.context, cl.mem_flags.WRITE_ONLY, array.nbytes)
               for key, array in out.items()}
    rt.run(rt.kernel(KERNEL, name), count, *arguments, *buffers.values())
    for key, array in out.items():
        cl.enqueue_copy(rt.queue, array, buffers[key])
    return out


def sample_envmap(emitter, count: int, seed: int = 0, device=None) -> dict[str, np.ndarray]:
    """``count`` directions drawn as the path integrator's light samples
    draw them from an environment map: "directions" (count, 3) unit, world
    frame, the way light arrives from; "radiance" (count, 3) along each;
    "pdfs" (count,) their solid-angle densities; float32."""
    count = inputs.integer("count", count, 1, 1 << 26)
    seed = inputs.integer("seed", seed, 0, 2**32 - 1)
    rt, arguments = _envmap_setup(emitter, device)
    return _launch(rt, "envmap_samples", count, [*arguments, np.uint32(count), np.uint32(seed)],
                   {"directions": np.empty((count, 3), np.float32),
                    "radiance": np.empty((count, 3), np.float32),
                    "pdfs": np.empty(count, np.float32)})


def eval_envmap(emitter, wi, device=None) -> dict[str, np.ndarray]:
    """The radiance ("radiance", (N, 3)) an environment map sends from each
    unit direction of ``wi`` (N, 3), and the density ("pdfs", (N,)) with
    which sample_envmap draws it."""
    wi = np.ascontiguousarray(wi, np.float32).reshape(-1, 3)
    rt, arguments = _envmap_setup(emitter, device)
    count = len(wi)
    directions = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                           hostbuf=wi)
    return _launch(rt, "envmap_values", count, [*arguments, np.uint32(count), directions],
                   {"radiance": np.empty((count, 3), np.float32),
                    "pdfs": np.empty(count, np.float32)})


def sample_lights(renderer, point, count: int, seed: int = 0) -> dict[str, np.ndarray]:
    """``count`` light samples that the path integrator's next-event
    estimation draws at ``point`` (world) in ``renderer``'s scene with its
    emitters: "directions" (count, 3) unit, towards the light; "radiance"
    (count, 3) arriving from it; "pdfs" (count,), the density with which
    the sample was drawn, per solid angle (0: no sample, such as a point on
    a light's back; a delta light's: the chance of picking it); "reaches"
    (count,), the distance to the light (inf for an environment map or a
    directional light); float32.  The lights are picked by power as in a
    render (an environment map against the scene's surface area; a constant
    environment draws none, its share going to the other lights)."""
    count = inputs.integer("count", count, 1, 1 << 26)
    seed = inputs.integer("seed", seed, 0, 2**32 - 1)
    x = np.asarray(inputs.vector3("point", point), np.float64)
    look = renderer.look()
    # as a render: in the tree's frame (coordinates times its scale), where
    # the directional lights' power follows the scene's bounds
    with renderer.scene.borrow() as built:
        rt, tree = built.runtime, built.tree
        tables = light_tables(look, tree.scale, tree.bounds_lo, tree.bounds_hi)
        buffers = [upload_table(rt, tables[name])
                   for name in ("materials", "vertices", "normals", "cdf", "owners", "deltas",
                                "envmap_image", "envmap_cdf")]
        out = _launch(rt, "light_samples", count,
                      [light_params(look, tables), *buffers,
                       *[np.float32(v) for v in x * tree.scale], np.uint32(count),
                       np.uint32(seed)],
                      {"directions": np.empty((count, 3), np.float32),
                       "radiance": np.empty((count, 3), np.float32),
                       "pdfs": np.empty(count, np.float32),
                       "reaches": np.empty(count, np.float32)})
        out["reaches"] /= np.float32(tree.scale)
    return out


def turn_angles(u, device=None) -> dict[str, np.ndarray]:
    """sin and cos of 2 pi u ("sin", "cos"; float32 like ``u``) for each u
    of ``u`` in [0, 2], as the path integrator's samplers compute the
    angles they draw (kernels/render/angles.h)."""
    u = np.ascontiguousarray(u, np.float32).reshape(-1)
    if not np.all((u >= 0.0) & (u <= 2.0)):
        bad = int(np.flatnonzero(~((u >= 0.0) & (u <= 2.0)))[0])
        raise ValueError(f"u[{bad}] must be in [0, 2], got {u[bad]!r}")
    rt, count = runtime(device), len(u)
    if count == 0:
        return {"sin": np.empty(0, np.float32), "cos": np.empty(0, np.float32)}
    turns = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                      hostbuf=u)
    return _launch(rt, "turn_angles", count, [np.uint32(count), turns],
                   {"sin": np.empty(count, np.float32), "cos": np.empty(count, np.float32)})
