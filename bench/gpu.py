"""The GPU measurements of issue 57, in one run of a few minutes: what to record whenever a session is lent a GPU.

  build      the reference scene's rebuild: wall and device milliseconds
             (target <= 10 ms on a GPU), and its stages
  camera     3M camera rays (2048 x 1536) of the reference scene, numpy in
             and out: wall Mrays/s against the traversal kernel's own
             (target: wall >= 30 % of kernel)
  small      the latency of a 1K-ray intersect call (target <= 0.5 ms)
  other path off zero copy (GPUs, Intel's runtime), the same two through
             the engine's other copy path, for the A/B: pinned staging
             buffers whose copies overlap the kernels, which queries take
             only on request (hlbvh_cl/query/engine.py's staging says why)
  on device  the same two with rays made on the device (Camera.rays with
             scene=) and results left there as pyopencl arrays
             (docs/queries.md, "Rays and points on the device")
  path       path-traced samples per second of scenes/materials.toml at
             1280 x 720, max depth 8 (the path tracer's figure on a GPU)
  interop    what the device offers for sharing memory with CUDA frameworks
             (docs/devices.md, "Sharing device memory"): its external-memory
             and semaphore extensions, and the memory handle types it
             imports (CL_DEVICE_EXTERNAL_MEMORY_IMPORT_HANDLE_TYPES_KHR)

It runs on any device (a CPU runtime gives the CPU's figures) and prints
one table; the JSON goes to bench/results/gpu.json, and with --docs the
figures go into bench/RESULTS.md's "gpu" section.

    python -m bench.gpu [--devices nvidia] [--quick] [--docs]
"""
from __future__ import annotations

import ctypes
import ctypes.util
import sys
import time

import pyopencl as cl

from hlbvh_cl.io.scenefile import load
from hlbvh_cl.query.rays import RayQuery

from .common import (BENCH, arguments, devices_or_exit, finish, machine_info, say, stopwatch,
                     summary, table, write_section)

SCENES = BENCH.parent / "scenes"

#: Issue 57's targets.
TARGETS = {"build_ms": 10.0, "wall_share_of_kernel": 0.30, "small_call_ms": 0.5}


def timed(job, repeats: int) -> list[float]:
    job()  # warm: kernels compiled, pools filled
    out = []
    for _ in range(repeats):
        started = time.perf_counter()
        job()
        out.append(time.perf_counter() - started)
    return out


#: cl_khr_external_memory's device query, and the handle types' names
#: (OpenCL registry, cl_ext.h).
IMPORT_HANDLE_TYPES = 0x204F
HANDLE_TYPES = {0x2060: "opaque fd", 0x2061: "opaque win32", 0x2062: "opaque win32 kmt",
                0x2063: "opaque win32 name", 0x2067: "dma-buf"}


def interop(cl_device: cl.Device) -> dict:
    """The device's external-memory and semaphore extensions, and the
    handle types it imports, asked of the OpenCL library through ctypes
    (pyopencl does not wrap cl_khr_external_memory)."""
    extensions = sorted(e for e in cl_device.extensions.split()
                        if "external" in e or "semaphore" in e)
    found = {"extensions": extensions, "import_handle_types": []}
    if "cl_khr_external_memory" not in extensions:
        return found
    # no device here exposes the extension, so this path first runs on a
    # lent GPU: whatever goes wrong is recorded, not raised, so that the
    # run's other measurements still come back
    try:
        library = ctypes.CDLL(ctypes.util.find_library("OpenCL") or "libOpenCL.so.1")
        size = ctypes.c_size_t(0)
        query = library.clGetDeviceInfo
        query.argtypes = [ctypes.c_void_p, ctypes.c_uint, ctypes.c_size_t, ctypes.c_void_p,
                          ctypes.POINTER(ctypes.c_size_t)]
        device = ctypes.c_void_p(cl_device.int_ptr)
        status = query(device, IMPORT_HANDLE_TYPES, 0, None, ctypes.byref(size))
        if status != 0:
            raise RuntimeError(f"clGetDeviceInfo returned {status}")
        types = (ctypes.c_uint * (size.value // 4))()
        query(device, IMPORT_HANDLE_TYPES, size, types, None)
        found["import_handle_types"] = [HANDLE_TYPES.get(t, hex(t)) for t in types]
    except Exception as error:  # noqa: BLE001 -- see above
        found["import_handle_types"] = [f"(query failed: {error})"]
    return found


def measure(device: str, quick: bool) -> dict:
    repeats = 2 if quick else 7
    size = (256, 192) if quick else (2048, 1536)
    loaded = load(SCENES / ("bunny.toml" if quick else "reference.toml"), device)
    scene = loaded.scene
    found = {"triangles": scene.stats.triangles}
    builds = []

    def rebuild():
        scene.rebuild()
        builds.append(scene.stats)
    walls = timed(rebuild, repeats)
    found["build"] = {"wall_ms": summary([w * 1e3 for w in walls]),
                      "device_ms": summary([s.device_ms for s in builds[1:]]),
                      "stages_ms": {k: summary([s.times_ms[k] for s in builds[1:]])
                                    for k in builds[-1].times_ms}}
    origins, directions = loaded.camera.rays(*size)
    count = len(origins)
    on_device = loaded.camera.rays(*size, scene=scene)
    small_on_device = [array[:1024].copy() for array in on_device]
    with scene.borrow() as built:
        query = RayQuery(built.runtime)
        kernel_ms = []

        def camera():
            query.intersect(built.tree, origins, directions)
            kernel_ms.append(query.last_kernel_ms)
        walls = timed(camera, repeats)
        wall_rate = count / summary(walls)["median"] / 1e6
        kernel_rate = count / (summary(kernel_ms[1:])["median"] * 1e-3) / 1e6
        found["camera"] = {"rays": count, "wall_mrays_per_s": wall_rate,
                           "kernel_mrays_per_s": kernel_rate,
                           "wall_share_of_kernel": wall_rate / kernel_rate}
        small_o, small_d = origins[:1024].copy(), directions[:1024].copy()
        walls = timed(lambda: query.intersect(built.tree, small_o, small_d), 20 * repeats)
        found["small"] = {"rays": 1024, "call_ms": summary([w * 1e3 for w in walls])}
        found["engine"] = {"zero_copy": query.zero_copy, "staging": query.staging}
        if not query.zero_copy:  # the A/B of the engine's two copy paths
            query.staging = not query.staging
            kernel_ms.clear()
            walls = timed(camera, repeats)
            walls_small = timed(lambda: query.intersect(built.tree, small_o, small_d),
                                20 * repeats)
            found["other_path"] = {
                "staging": query.staging,
                "camera_wall_mrays_per_s": count / summary(walls)["median"] / 1e6,
                "small_call_ms": summary([w * 1e3 for w in walls_small])}
            query.staging = not query.staging
        kernel_ms.clear()

        def camera_on_device():
            query.intersect(built.tree, *on_device)
            kernel_ms.append(query.last_kernel_ms)
        walls = timed(camera_on_device, repeats)
        wall_rate = count / summary(walls)["median"] / 1e6
        kernel_rate = count / (summary(kernel_ms[1:])["median"] * 1e-3) / 1e6
        walls_small = timed(lambda: query.intersect(built.tree, *small_on_device), 20 * repeats)
        found["on_device"] = {"rays": count, "wall_mrays_per_s": wall_rate,
                              "kernel_mrays_per_s": kernel_rate,
                              "wall_share_of_kernel": wall_rate / kernel_rate,
                              "small_call_ms": summary([w * 1e3 for w in walls_small])}
    materials = load(SCENES / "materials.toml", device)
    renderer = materials.renderer()
    width, height, spp = (160, 90, 1) if quick else (1280, 720, 4)
    options = {"shading": "path", "spp": spp, "max_depth": 8}
    walls = timed(lambda: renderer.render(materials.camera, width, height, hdr=True, **options),
                  max(1, repeats // 2))
    found["path"] = {"size": [width, height], "spp": spp,
                     "msamples_per_s": width * height * spp / summary(walls)["median"] / 1e6}
    with scene.borrow() as built:
        found["interop"] = interop(built.runtime.device.cl_device)
    return found


def main(argv=None) -> dict:
    args = arguments(__doc__.splitlines()[0], argv)
    elapsed = stopwatch()
    devices = [d.id for d in devices_or_exit(args.devices)]
    say(f"devices: {', '.join(devices)}")
    results = {"command": " ".join(["python -m bench.gpu",
                                     *(sys.argv[1:] if argv is None else argv)]),
               "machine": machine_info(), "targets": TARGETS, "quick": args.quick,
               "devices": {}}
    rows = []
    for device in devices:
        found = measure(device, args.quick)
        results["devices"][device] = found
        rows.append([device, f"{found['build']['wall_ms']['median']:.1f} / "
                             f"{found['build']['device_ms']['median']:.1f}",
                     f"{found['camera']['wall_mrays_per_s']:.1f} / "
                     f"{found['camera']['kernel_mrays_per_s']:.1f} "
                     f"({100 * found['camera']['wall_share_of_kernel']:.0f} %)",
                     f"{found['small']['call_ms']['median']:.3f}"
                     + (f" ({_path_name(found['other_path'])}: "
                        f"{found['other_path']['small_call_ms']['median']:.3f}, "
                        f"{found['other_path']['camera_wall_mrays_per_s']:.1f} Mrays/s)"
                        if "other_path" in found else ""),
                     f"{found['on_device']['wall_mrays_per_s']:.1f} "
                     f"({100 * found['on_device']['wall_share_of_kernel']:.0f} %) / "
                     f"{found['on_device']['small_call_ms']['median']:.3f}",
                     f"{found['path']['msamples_per_s']:.2f}",
                     _interop_text(found["interop"])])
    print(table(["device", "build ms (wall / device)", "camera Mrays/s (wall / kernel)",
                 "1K-ray call ms (the other copy path: call ms, camera)",
                 "on device: camera Mrays/s (% of kernel) / 1K-ray call ms",
                 "path Msamples/s", "external memory"], rows,
                title=f"issue 57's measurements (targets: {TARGETS})"))
    results = finish(results, "gpu", args, elapsed)
    if args.docs:
        print(f"wrote {write_section(BENCH / 'RESULTS.md', markdown(results), 'gpu')}")
    return results


def markdown(results: dict) -> str:
    """bench/RESULTS.md's section of a run: one table per device."""
    machine = results["machine"]
    lines = ["<!-- begin gpu -->", "", "## GPU: issue 57's measurements", "",
             f"Measured on {machine['date']} with `{results['command']}`: "
             f"{machine['processor']}, {machine['cpus']} logical CPUs, "
             f"{machine['platform']}; pyopencl {machine['pyopencl']}. Medians; "
             f"targets {results['targets']}.", ""]
    for device, found in results["devices"].items():
        info = next((d for d in machine["devices"] if d["id"] == device), {})
        build, camera, on_device = found["build"], found["camera"], found["on_device"]
        stages = ", ".join(f"{name} {value['median']:.2f}"
                           for name, value in build["stages_ms"].items())
        rows = [
            (f"rebuild of the scene's {found['triangles']:,} triangles, ms (wall / device)",
             f"{build['wall_ms']['median']:.1f} / {build['device_ms']['median']:.1f} "
             f"({stages})"),
            (f"{camera['rays']:,} camera rays, numpy in and out, Mrays/s (wall / kernel)",
             f"{camera['wall_mrays_per_s']:.1f} / {camera['kernel_mrays_per_s']:.1f} "
             f"({100 * camera['wall_share_of_kernel']:.1f} %)"),
            ("the same, rays made on the device and results left there",
             f"{on_device['wall_mrays_per_s']:.1f} / {on_device['kernel_mrays_per_s']:.1f} "
             f"({100 * on_device['wall_share_of_kernel']:.1f} %)"),
            ("1K-ray call, ms: numpy / on the device",
             f"{found['small']['call_ms']['median']:.3f} / "
             f"{on_device['small_call_ms']['median']:.3f}")]
        if "other_path" in found:
            other = found["other_path"]
            rows.append((f"{_path_name(other)}: camera Mrays/s, 1K-ray call ms",
                         f"{other['camera_wall_mrays_per_s']:.1f}, "
                         f"{other['small_call_ms']['median']:.3f}"))
        path = found["path"]
        rows += [(f"path tracing, materials scene, {path['size'][0]}x{path['size'][1]}, "
                  f"{path['spp']} spp, depth 8, Msamples/s", f"{path['msamples_per_s']:.2f}"),
                 ("external memory", _interop_text(found["interop"]))]
        lines += [f"**{device}** ({info.get('name', '?')}, driver {info.get('driver', '?')}, "
                  f"{info.get('compute_units', '?')} compute units)", "",
                  "| what | figure |", "| --- | --- |",
                  *(f"| {what} | {figure} |" for what, figure in rows), ""]
    lines += ["*JSON: `gpu.json`*", "", "<!-- end gpu -->"]
    return "\n".join(lines) + "\n"


def _path_name(other: dict) -> str:
    return "staging on (pinned buffers)" if other["staging"] else "staging off (device buffers)"


def _interop_text(found: dict) -> str:
    return ", ".join(found["extensions"] + found["import_handle_types"]) or "none"


if __name__ == "__main__":
    main()
