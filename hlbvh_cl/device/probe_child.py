"""The kernel probe's child process (``python -m hlbvh_cl.device.probe_child DEVICE
PROFILE [VARIANT]``, started by hlbvh_cl.device.probe): builds, refits, traces and
renders small scenes with one kernel variant, checks the hits against a
float64 brute force (Moller & Trumbore 1997), and prints its verdict as one
JSON record after probe.REPORT.  Only the probe runs it, so that a compiler
that aborts takes down this process and not the caller's.
"""
from __future__ import annotations

import json
import os
import sys

from .discovery import devices
from .probe import REPORT
from .runtime import install_runtime
from .profile import Profile, Variant


def _compile_target(rt) -> dict:
    import numpy as np
    import pyopencl as cl
    flags_buffer = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 4)
    rt.run(rt.kernel("device/probe.cl", "compile_target"), 1, flags_buffer, local_size=1)
    flags = np.zeros(1, np.int32)
    cl.enqueue_copy(rt.queue, flags, flags_buffer)
    return {"x86": bool(flags[0] & 1), "avx": bool(flags[0] & 2), "avx512": bool(flags[0] & 4),
            "reported_width": int(rt.device.cl_device.native_vector_width_float)}


def _brute_force_t(vertices, faces, origins, directions):
    """Closest t per ray in float64 (Moller & Trumbore 1997), inf on a miss."""
    import numpy as np
    v = np.asarray(vertices, np.float64)[np.asarray(faces)]
    e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    o, d = np.asarray(origins, np.float64)[:, None], np.asarray(directions, np.float64)[:, None]
    p = np.cross(d, e2)
    det = np.einsum("rtk,tk->rt", p, e1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o - v[:, 0]
        u = np.einsum("rtk,rtk->rt", s, p) * inv
        q = np.cross(s, e1)
        w = np.einsum("rtk,rtk->rt", d, q) * inv
        t = np.einsum("tk,rtk->rt", e2, q) * inv
    hit = (det != 0) & (u >= 0) & (w >= 0) & (u + w <= 1) & (t >= 0)
    return np.where(hit, t, np.inf).min(axis=1)


def _probe_variant(rt) -> dict:
    """Builds, refits, traces and renders small scenes with ``rt``'s variant;
    returns {"ok": ..., "reason": ..., "mrays_per_s": ...}."""
    import numpy as np
    import trimesh

    from ..mesh import Mesh
    from ..render.camera import Camera
    from ..render.renderer import Renderer
    from ..query.rays import RayQuery
    from ..scene import Scene

    sphere = trimesh.creation.icosphere(subdivisions=2)
    ground_v = np.array([[-3, -3, -1.5], [3, -3, -1.5], [3, 3, -1.5], [-3, 3, -1.5]], float)
    ground_f = np.array([[0, 1, 2], [0, 2, 3]])
    meshes = [Mesh(sphere.vertices, sphere.faces), Mesh(ground_v, ground_f)]
    vertices = np.concatenate([sphere.vertices, ground_v])
    faces = np.concatenate([sphere.faces, ground_f + len(sphere.vertices)])

    rng = np.random.default_rng(7)
    # rays aimed inside random triangles from outside (all hit), rays pointing
    # away (all miss), and a 16 x 16 view (packets of coherent rays)
    aims = vertices[faces[rng.integers(0, len(faces), 256)]]
    weights = rng.dirichlet((4, 4, 4), 256)[:, :, None]
    targets = (aims * weights).sum(axis=1)
    starts = rng.normal(size=(256, 3))
    starts = 4 * starts / np.linalg.norm(starts, axis=1, keepdims=True)
    away = -starts
    xs, ys = np.meshgrid(np.linspace(-0.6, 0.6, 16), np.linspace(-0.6, 0.6, 16))
    view = np.stack([xs.ravel(), ys.ravel(), -np.ones(256)], axis=1)
    origins = np.concatenate([starts, starts, np.tile([0.1, 0.2, 4.0], (256, 1))])
    directions = np.concatenate([targets - starts, away, view])
    expected = _brute_force_t(vertices, faces, origins, directions)

    def compare(what, scene, expect):
        hits = scene.intersect(origins, directions)
        hit, hit_expected = np.isfinite(hits.t), np.isfinite(expect)
        strict = slice(0, 512)  # the aimed and the away rays cannot graze an edge
        if (hit[strict] != hit_expected[strict]).any() or \
                (hit[512:] != hit_expected[512:]).mean() > 0.01:
            return f"{what}: hits differ from a float64 brute force on " \
                   f"{int((hit != hit_expected).sum())} of {len(hit)} rays"
        both = hit & hit_expected
        error = np.abs(hits.t[both] - expect[both]) / np.maximum(expect[both], 1e-30)
        if len(error) and error.max() > 1e-4:
            return f"{what}: t differs from a float64 brute force by up to {error.max():.2g}"
        if (scene.occluded(origins, directions) != hit).any():
            return f"{what}: occluded disagrees with intersect"
        return None

    device = rt.device.id
    for builder, bits in (("hlbvh", 30), ("lbvh", 63)):
        scene = Scene(meshes, device=device, builder=builder, morton_bits=bits)
        problem = compare(f"{builder} {bits}-bit", scene, expected)
        if problem:
            return {"ok": False, "reason": problem}
    moved = sphere.vertices * 1.25
    scene.update_vertices(0, moved)
    problem = compare("refit", scene, _brute_force_t(np.concatenate([moved, ground_v]), faces,
                                                       origins, directions))
    if problem:
        return {"ok": False, "reason": problem}
    for shading in ("diffuse", "ao"):
        image = Renderer(scene).render(Camera((0.5, 3.0, 2.0), (0, 0, 0)), 12, 8,
                                       shading=shading, ao_samples=2)
        if image.shape != (8, 12, 3) or not image.any():
            return {"ok": False, "reason": f"the {shading} render came back empty"}

    if rt.device.simulator:  # never a default: no ranking needed
        return {"ok": True, "reason": None, "mrays_per_s": None}
    # speed: camera rays on a 20K-triangle sphere (ranks devices)
    dense = trimesh.creation.icosphere(subdivisions=5)
    scene = Scene([Mesh(dense.vertices, dense.faces)], device=device)
    xs, ys = np.meshgrid(np.linspace(-1, 1, 256), np.linspace(-1, 1, 256))
    view = np.stack([xs.ravel(), ys.ravel(), -2 * np.ones(xs.size)], axis=1)
    eye = np.tile([0.0, 0.0, 3.0], (len(view), 1))
    milliseconds = []
    with scene.borrow() as built:
        query = RayQuery(built.runtime)
        for _ in range(4):  # the first run pays for compilation
            query.intersect(built.tree, eye, view)
            milliseconds.append(query.last_kernel_ms)
    fastest = sorted(milliseconds[1:])[1]
    return {"ok": True, "reason": None, "mrays_per_s": len(view) / max(fastest, 1e-3) * 1e-3}


def report(record: dict) -> None:
    """Prints one record for the parent (probe._last_json), after REPORT:
    the driver writes to the same stdout, and its diagnostics (PoCL's under
    POCL_VECTORIZER_REMARKS=1) end without a newline, so that a record
    printed after them shares their line."""
    print(REPORT + json.dumps(record), flush=True)


def _injected_fault(variant: Variant) -> None:
    """For the tests of this module: HLBVH_CL_PROBE_FAULT=NAME:abort (or
    :hang, :killed) makes the child die as a crashing compiler would (or
    hang, or die as the OOM killer ends it) while it probes variant NAME (*
    for every variant); :noise writes a driver's remark without a newline
    to its stdout, and :silent makes it exit 0 with no verdict."""
    import signal
    import time
    name, _, action = os.environ.get("HLBVH_CL_PROBE_FAULT", "").partition(":")
    if name in (variant.name, "*"):
        if action == "noise":
            os.write(1, b"<unknown>:0:0: loop not vectorized")  # as PoCL's remarks, at the fd
        if action == "silent":
            sys.exit(0)
        if action == "abort":
            sys.stderr.write("LLVM ERROR: injected by HLBVH_CL_PROBE_FAULT\n")
            sys.stderr.flush()
            os.abort()
        if action == "hang":
            time.sleep(3600)
        if action == "killed":
            os.kill(os.getpid(), signal.SIGKILL)


def main(argv: list[str] | None = None) -> int:
    """``python -m hlbvh_cl.device.probe_child DEVICE_ID PROFILE [VARIANT]``: prints one
    record with the compiler's target and, with VARIANT, one with its verdict."""

    device_id, profile_name, *rest = argv if argv is not None else sys.argv[1:]
    found = [d for d in devices() if d.id == device_id]
    if not found:
        report({"ok": False, "reason": f"no device {device_id} in the child"})
        return 1
    profile = Profile(profile_name)
    variant = Variant.parse(rest[0]) if rest else Variant(1, builtins=False)
    rt = install_runtime(found[0], profile, variant)
    report({"target": _compile_target(rt)})
    if rest:
        _injected_fault(variant)
        try:
            verdict = _probe_variant(rt)
        except Exception as error:  # a build error, a bad result: the verdict says which
            lines = [line for line in str(error).splitlines() if line.strip()]
            errors = [line.strip() for line in lines[1:] if "error" in line.lower()]
            reason = f"{type(error).__name__}: {lines[0] if lines else ''}"
            verdict = {"ok": False, "reason": reason + (f" ({errors[0]})" if errors else "")}
        report(verdict)
    return 0


if __name__ == "__main__":
    sys.exit(main())
