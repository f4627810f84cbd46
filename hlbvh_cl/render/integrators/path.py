"""The path integrator ("path"): unidirectional path tracing, as pbrt-v4's
PathIntegrator and Mitsuba 3's ``path`` (kernels/render/integrators/path.cl).

Each sample of a pixel follows one path from the camera.  At each vertex x
(a closest hit) with throughput T it adds:

- the radiance the vertex sees emitted: an area emitter's front side, or the
  environment where the ray escapes, times T and, past the camera's ray,
  the power-heuristic weight of the BSDF sample against a light sample of
  that direction (Veach 1997, eq. 9.13);
- next-event estimation: one light sample (materials.py, emitters.py:
  the environment, constant or a map (envmap.py), a delta light or a
  triangle, by power), T * f * cos * L / p_light
  times its weight against the BSDF's density, where its shadow ray is
  free;

then samples the BSDF for the next direction (diffuse: cosine-distributed,
so T takes the albedo).  ``max_depth`` is Mitsuba's: the most segments a
path has (1: only what the camera sees emitting; 2: direct light; -1: no
limit), and from ``rr_depth`` on a path goes on with probability
q = min(max channel of T, 0.95) and T /= q (Russian roulette, Mitsuba's
rule), which keeps the estimate unbiased.

The stages run as a wavefront (Laine, Karras & Aila 2013): the path states
live in a device buffer, and per bounce the host enqueues the surface
stage, the shadow rays (query/rays.cl's any-hit walk), their resolve, and
the next closest hits (its closest-hit walk).  Paths that end take empty
rays, which cost one node.  No bounce waits on the host, but to stop when
every path of a pass has ended the host reads each bounce's count of live
paths, two bounces behind the device.

Shading uses the geometric normal (Mitsuba's ``face_normals``).
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from ...core import layout
from ...core.paths import kernel_of
from ...device.runtime import Runtime
from ..emitters import luminance
from .base import Integrator, Look, Step
from .direct import ray_offset

KERNEL = kernel_of(__name__)

#: Bounces at most when max_depth is -1 (no limit): Russian roulette ends a
#: path long before, with probability 1 - 0.95^(1024 - 5) at the least.
UNLIMITED_BOUNCES = 1024

#: How many bounces the host runs ahead of its count of live paths.
LOOKAHEAD = 2

#: DeltaLight.type (kernels/render/integrators/path.h).
LIGHT_POINT, LIGHT_DIRECTIONAL = 0, 1


def light_tables(look: Look, scale: float, bounds_lo, bounds_hi) -> dict:
    """The light sampling tables, in a tree's frame (coordinates times
    ``scale``): "materials", PathMaterial records with their emission;
    "vertices", float32 (K, 9) of the emissive triangles; "cdf", their
    float32 CDF by power; "owners", the mesh of each; "deltas", DeltaLight
    records; "envmap_image" and "envmap_cdf", the environment map's pixels
    and CDFs (envmap.py; stand-ins without one); and the chances a light
    sample picks the environment or a delta light (emitters.py)."""
    materials = look.materials.copy()
    vertices, weights, owners = [], [], []
    for mesh, radiance in sorted(look.emitters.area.items()):
        triangles = np.asarray(look.emissive[mesh], np.float64) * scale
        area = 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0],
                                             triangles[:, 2] - triangles[:, 0]), axis=1)
        keep = area > 0
        vertices.append(triangles[keep].reshape(-1, 9))
        weights.append(area[keep] * luminance(radiance))
        owners.append(np.full(int(keep.sum()), mesh, np.int32))
        materials[mesh]["radiance"] = radiance
    weights = np.concatenate(weights) if weights else np.zeros(0)
    triangle_power = float(weights.sum())
    lo, hi = np.asarray(bounds_lo, np.float64), np.asarray(bounds_hi, np.float64)
    radius = 0.5 * float(np.linalg.norm(hi - lo)) or 1.0
    environment, envmap = look.emitters.environment, look.emitters.envmap
    # the luminance integrated over the sphere, times R^2
    environment_power = radius * radius * (
        envmap.tables[1] if envmap is not None
        else 0.0 if environment is None else luminance(environment) * 4.0 * np.pi)
    deltas = np.zeros(max(1, len(look.emitters.deltas)), layout.DELTA_LIGHT)
    delta_powers = []
    for k, (kind, vector, value) in enumerate(look.emitters.deltas):
        point = kind == "point"
        deltas[k]["type"] = LIGHT_POINT if point else LIGHT_DIRECTIONAL
        deltas[k]["position"] = vector * scale if point else vector
        # In the frame lengths are times `scale`: a point light's irradiance
        # I / d^2 stays the user's with I times scale^2; a directional
        # light's irradiance and every radiance need nothing.
        deltas[k]["value"] = value * (scale * scale) if point else value
        delta_powers.append(luminance(deltas[k]["value"]) * (4.0 if point else radius * radius))
    total = environment_power + triangle_power + sum(delta_powers)
    chance = (lambda power: power / total) if total > 0 else (lambda power: 0.0)
    for k, power in enumerate(delta_powers):
        deltas[k]["probability"] = chance(power)
    if triangle_power > 0:
        for mesh, radiance in look.emitters.area.items():
            materials[mesh]["emitter_pdf"] = chance(triangle_power) * luminance(radiance) \
                / triangle_power
        cdf = np.cumsum(weights) / triangle_power
        cdf[-1] = 1.0
    else:
        cdf = np.zeros(0)
    if envmap is not None:
        envmap_image, envmap_cdf = envmap.image, envmap.tables[0]
    else:  # none: stand-ins, since OpenCL has no empty buffers
        envmap_image, envmap_cdf = np.zeros(4, np.float32), np.zeros(4, np.float32)
    return {"materials": materials, "envmap_image": envmap_image, "envmap_cdf": envmap_cdf,
            "vertices": (np.concatenate(vertices).astype(np.float32) if vertices
                         else np.zeros((0, 9), np.float32)),
            "cdf": cdf.astype(np.float32),
            "owners": np.concatenate(owners) if owners else np.zeros(0, np.int32),
            "deltas": deltas, "delta_count": len(look.emitters.deltas),
            "environment_probability": chance(environment_power),
            "delta_probability": sum(chance(power) for power in delta_powers)}


def envmap_params(params: np.ndarray, envmap) -> None:
    """PathParams' environment map fields: its size and rotation (width 0
    without one: the environment is constant)."""
    if envmap is None:
        params["envmap_width"] = params["envmap_height"] = 0
        params["envmap_to_world"] = np.eye(3).reshape(-1)
        return
    params["envmap_height"], params["envmap_width"] = envmap.image.shape[:2]
    params["envmap_to_world"] = envmap.to_world.reshape(-1)


class Path(Integrator):
    """Path tracing with next-event estimation and MIS (the module's
    definitions)."""

    modes = ("path",)

    #: Bytes per pixel of a pass of the integrator's own buffers.
    PER_PIXEL = {"path states": layout.PATH_STATE.itemsize, "shadow rays": layout.RAY.itemsize,
                 "occluded": 1, "pending light": 16}

    def __init__(self):
        self._pixels = 0
        self._tables: dict[str, cl.Buffer] = {}
        self.last_bounces: list[int] = []

    def buffer_sizes(self, pixels: int) -> dict[str, int]:
        return {name: size * pixels for name, size in self.PER_PIXEL.items()}

    def passes(self, settings) -> int:
        return 0  # the bounces are counted as they happen (last_bounces)

    def radiance(self, settings) -> bool:
        return True

    def prepare(self, rt: Runtime, settings, tree, look: Look, pixels: int) -> None:
        self.rt, self.settings = rt, settings
        self._kernels = {name: rt.kernel(KERNEL, name) for name in
                         ("path_start", "path_surface", "path_unoccluded", "path_finish")}
        if pixels > self._pixels:
            context, rw = rt.context, cl.mem_flags.READ_WRITE
            self.states = cl.Buffer(context, rw, pixels * layout.PATH_STATE.itemsize)
            self.shadow = cl.Buffer(context, rw, pixels * layout.RAY.itemsize)
            self.occluded = cl.Buffer(context, rw, pixels)
            self.pending = cl.Buffer(context, rw, pixels * 16)  # float4
            self.live = cl.Buffer(context, rw, 4 * UNLIMITED_BOUNCES)
            self._pixels = pixels
        tables = light_tables(look, tree.scale, tree.bounds_lo, tree.bounds_hi)
        for name in ("materials", "vertices", "cdf", "owners", "deltas", "envmap_image",
                     "envmap_cdf"):
            data = np.ascontiguousarray(tables[name])
            # at least one element: OpenCL has no empty buffers
            self._tables[name] = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY
                                           | cl.mem_flags.COPY_HOST_PTR,
                                           hostbuf=data if data.nbytes else np.zeros(4, np.uint8))
        params = np.zeros((), layout.PATH_PARAMS)
        environment = look.emitters.environment
        params["environment"] = environment if environment is not None else 0.0
        params["environment_probability"] = tables["environment_probability"]
        params["delta_probability"] = tables["delta_probability"]
        params["ray_offset"] = ray_offset(tree.bounds_lo, tree.bounds_hi)
        params["light_triangles"] = len(tables["cdf"])
        params["delta_lights"] = tables["delta_count"]
        params["max_depth"] = settings.max_depth
        params["rr_depth"] = settings.rr_depth
        envmap_params(params, look.emitters.envmap)
        self._params = params
        self._live = np.zeros(UNLIMITED_BOUNCES, np.uint32)
        self.last_bounces = []

    def shade(self, step: Step) -> None:
        rt, band, kernels, events = step.rt, step.band, self._kernels, step.events
        count, sample = np.uint32(band.count), np.uint32(step.sample)
        stream, first_pixel = np.uint32(step.stream), np.uint32(int(band.first_row) * band.width)
        tables = self._tables
        bounces = self.settings.max_depth if self.settings.max_depth > 0 else UNLIMITED_BOUNCES
        events["shade"].append(rt.run(kernels["path_start"], band.count, count, self.states))
        events["shade"].append(cl.enqueue_fill_buffer(rt.queue, self.live, np.uint32(0), 0,
                                                      4 * bounces))
        reads = []
        for depth in range(bounces):
            if depth > 0:
                events["closest"].append(step.query.enqueue_intersect(
                    step.tree, step.rays, step.hits, band.count, step.overflow))
            events["shade"].append(rt.run(
                kernels["path_surface"], band.count, step.rays, step.hits, self.states,
                tables["materials"], tables["vertices"], tables["cdf"], tables["owners"],
                tables["deltas"], tables["envmap_image"], tables["envmap_cdf"], self._params,
                count, first_pixel, stream,
                np.int32(depth), self.shadow, self.pending, self.live))
            events["occluded"].append(step.query.enqueue_occluded(
                step.tree, self.shadow, self.occluded, band.count, step.overflow))
            events["resolve"].append(rt.run(
                kernels["path_unoccluded"], band.count, self.occluded, self.pending, count,
                self.states))
            reads.append(cl.enqueue_copy(rt.queue, self._live[depth:depth + 1], self.live,
                                         src_offset=4 * depth, is_blocking=False))
            if depth >= LOOKAHEAD:
                rt.wait([reads[depth - LOOKAHEAD]])
                if self._live[depth - LOOKAHEAD] == 0:
                    break  # every path ended: what is enqueued after it finds none
        rt.wait(reads)
        self.last_bounces.append(int(self._live[:len(reads)].sum()))
        events["resolve"].append(rt.run(kernels["path_finish"], band.count, self.states, count,
                                        sample, step.accum))
        step.done(events["resolve"][-1])
