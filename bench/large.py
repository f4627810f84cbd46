"""A 10M-triangle build, its memory, and a scene too large for the device.

    python bench/large.py [--device pocl] [--split 10] [--repeats 3] [--out bench/results]

Lucy (99,970 triangles) with every edge split in 10 is 9,997,000 triangles.
The scene is built once (with kernel compilation), warmed up, and rebuilt
``repeats`` times; printed are the stage times, the device-memory estimate of
hlbvh_cl.build.build_memory, and the process's peak resident memory
(ru_maxrss).  On PoCL's CPU device, device buffers are host memory, so that
peak is the real peak of the build.

Then a scene larger than the device is asked for, twice: check_fits on a
hypothetical triangle count, and a Scene of the same 10M-triangle mesh
repeated until its estimate exceeds CL_DEVICE_GLOBAL_MEM_SIZE.  Both must
raise hlbvh_cl.DeviceMemoryError before anything is allocated (the resident
memory does not grow).  Writes <out>/large.json.
"""
from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # common.py

from common import (MESHES, current_rss_bytes, machine_info, peak_rss_bytes,  # noqa: E402
                    quiet_compiler_warnings, stopwatch, summary, table, write_json)

from hlbvh_cl import DeviceMemoryError, Mesh, Scene  # noqa: E402
from hlbvh_cl.build import build_memory, check_fits  # noqa: E402
from hlbvh_cl.scene import STAGES  # noqa: E402
from hlbvh_cl.device import runtime  # noqa: E402
from hlbvh_cl.split import split_edges  # noqa: E402

MORTON_BITS = 30
GIB = 2**30


def _memory_checkpoint(label: str, log: list) -> dict:
    log.append({"after": label, "peak_rss_bytes": peak_rss_bytes(),
                "rss_bytes": current_rss_bytes()})
    return log[-1]


def _estimate_bytes(vertex_count: int, triangle_count: int) -> int:
    return sum(build_memory(vertex_count, triangle_count, MORTON_BITS).values())


def largest_fitting(global_mem_size: int, vertices_per_triangle: float) -> int:
    """The most triangles whose build estimate fits ``global_mem_size``
    (vertices in the given proportion), by bisection on build_memory."""
    low, high = 1, 1
    while _estimate_bytes(int(high * vertices_per_triangle), high) <= global_mem_size:
        low, high = high, high * 2
    while high - low > 1:
        middle = (low + high) // 2
        if _estimate_bytes(int(middle * vertices_per_triangle), middle) <= global_mem_size:
            low = middle
        else:
            high = middle
    return low


def _expect_device_memory_error(attempt) -> dict:
    """Run ``attempt``; it must raise DeviceMemoryError without allocating."""
    rss_before = current_rss_bytes()
    elapsed = stopwatch()
    try:
        attempt()
    except DeviceMemoryError as error:
        return {"raised": "DeviceMemoryError", "message": str(error), "seconds": elapsed(),
                "rss_before_bytes": rss_before, "rss_after_bytes": current_rss_bytes()}
    return {"raised": None, "message": "no error: the scene fit", "seconds": elapsed(),
            "rss_before_bytes": rss_before, "rss_after_bytes": current_rss_bytes()}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="pocl")
    parser.add_argument("--mesh", default="lucy.ply", help="a file in scenes/meshes")
    parser.add_argument("--split", type=int, default=10, help="edge split factor k (k*k triangles each)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    args = parser.parse_args(argv)
    quiet_compiler_warnings()
    memory_log: list[dict] = []
    _memory_checkpoint("start", memory_log)

    elapsed = stopwatch()
    source = Mesh.load(MESHES / args.mesh)
    vertices, faces = split_edges(source.vertices, source.faces, args.split)
    mesh = Mesh(vertices, faces, name=f"{source.name} split {args.split}")
    del vertices, faces
    split_s = elapsed()
    _memory_checkpoint("split", memory_log)
    print(f"mesh       {mesh.name}: {mesh.triangle_count:,} triangles, {mesh.vertex_count:,} "
          f"vertices (split in {split_s:.1f} s)")

    rt = runtime(args.device)
    device = rt.device
    estimate = build_memory(mesh.vertex_count, mesh.triangle_count, MORTON_BITS)
    estimate_total = sum(estimate.values())
    print(f"device     {device}: {device.global_mem_size / GIB:.2f} GiB global memory, "
          f"{device.max_mem_alloc_size / GIB:.2f} GiB per allocation")
    print(table(["buffer", "MiB"], [[name, nbytes / 2**20] for name, nbytes in estimate.items()]
                + [["total (build_memory)", estimate_total / 2**20]],
                title="device memory estimate of the build"))

    before_scene = _memory_checkpoint("runtime, before Scene()", memory_log)
    elapsed = stopwatch()
    scene = Scene([mesh], device=args.device)
    construct_s = elapsed()
    first = copy.deepcopy(scene.stats)
    after_first = _memory_checkpoint("first build", memory_log)
    scene.rebuild()  # warm-up
    builds = []
    for _ in range(args.repeats):
        scene.rebuild()
        builds.append(copy.deepcopy(scene.stats))
    after_rebuilds = _memory_checkpoint(f"{args.repeats + 1} rebuilds", memory_log)
    times = {key: summary([b["times_ms"][key] for b in builds]) for key in STAGES + ("total", "wall")}
    last = builds[-1]
    print(table(["stage", "median ms", "min", "max"],
                [[key, t["median"], t["min"], t["max"]] for key, t in times.items()],
                title=f"build of {last['triangles']:,} triangles ({last['builder']}), "
                      f"{args.repeats} rebuilds after a warm-up; first build (with compilation) "
                      f"{first['times_ms']['wall']:.0f} ms wall, Scene() {construct_s:.1f} s"))
    print(f"tree       {last['nodes']:,} nodes, {last['leaves']:,} leaves, depth {last['depth']}, "
          f"SAH {last['sah_cost']:.2f}, {last['clusters']:,} clusters; "
          f"{last['triangles'] / times['wall']['median'] / 1e3:.1f} Mtriangles/s")
    del scene
    _memory_checkpoint("scene released", memory_log)
    print(table(["after", "peak RSS MiB", "RSS MiB"],
                [[m["after"], m["peak_rss_bytes"] / 2**20,
                  m["rss_bytes"] / 2**20 if m["rss_bytes"] is not None else None]
                 for m in memory_log],
                title="process memory (ru_maxrss is the peak so far)"))
    before = before_scene["rss_bytes"]
    first_peak, rebuild_peak = after_first["peak_rss_bytes"], after_rebuilds["peak_rss_bytes"]
    growth = {"first_build_bytes": first_peak - before if before is not None else None,
              "rebuilds_bytes": rebuild_peak - before if before is not None else None}
    if before is not None:
        print(f"peak growth over the RSS before Scene(): first build "
              f"{growth['first_build_bytes'] / GIB:.2f} GiB, with rebuilds "
              f"{growth['rebuilds_bytes'] / GIB:.2f} GiB; build_memory estimate "
              f"{estimate_total / GIB:.2f} GiB")

    # Too large for the device: the estimate exceeds CL_DEVICE_GLOBAL_MEM_SIZE.
    vertices_per_triangle = mesh.vertex_count / mesh.triangle_count
    fits = largest_fitting(device.global_mem_size, vertices_per_triangle)
    hypothetical = int(fits * 1.25)
    hypothetical_vertices = int(hypothetical * vertices_per_triangle)
    by_count = _expect_device_memory_error(
        lambda: check_fits(rt, hypothetical_vertices, hypothetical, MORTON_BITS))
    by_count.update(triangles=hypothetical, vertices=hypothetical_vertices,
                    estimate_bytes=_estimate_bytes(hypothetical_vertices, hypothetical))
    copies = fits // mesh.triangle_count + 1
    by_scene = _expect_device_memory_error(lambda: Scene([mesh] * copies, device=args.device))
    by_scene.update(triangles=copies * mesh.triangle_count, copies=copies,
                    estimate_bytes=_estimate_bytes(copies * mesh.vertex_count,
                                                   copies * mesh.triangle_count))
    print(f"\nlargest build that fits {device.id} by the estimate: {fits:,} triangles")
    for label, outcome in (("check_fits", by_count), (f"Scene([mesh] * {copies})", by_scene)):
        growth = ((outcome["rss_after_bytes"] - outcome["rss_before_bytes"]) / 2**20
                  if outcome["rss_before_bytes"] is not None else float("nan"))
        print(f"{label}: {outcome['triangles']:,} triangles, estimate "
              f"{outcome['estimate_bytes'] / GIB:.2f} GiB -> {outcome['raised']} in "
              f"{outcome['seconds'] * 1e3:.2f} ms, RSS grew {growth:.1f} MiB\n    {outcome['message']}")

    result = {
        "machine": machine_info(), "device": device.id, "mesh": mesh.name, "split": args.split,
        "triangles": mesh.triangle_count, "vertices": mesh.vertex_count, "split_s": split_s,
        "construct_s": construct_s,
        "first_build_ms": {"total": first["times_ms"]["total"], "wall": first["times_ms"]["wall"]},
        "times_ms": times, "repeats": args.repeats,
        "tree": {k: last[k] for k in ("builder", "nodes", "leaves", "depth", "sah_cost", "clusters")},
        "estimate_bytes": estimate, "estimate_total_bytes": estimate_total,
        "device_global_mem_size": device.global_mem_size,
        "device_max_mem_alloc_size": device.max_mem_alloc_size,
        "peak_rss_bytes": peak_rss_bytes(), "memory": memory_log, "peak_growth": growth,
        "too_large": {"largest_fitting_triangles": fits, "check_fits": by_count, "scene": by_scene},
    }
    path = write_json(args.out / "large.json", result)
    print(f"\npeak RSS {result['peak_rss_bytes'] / GIB:.2f} GiB; wrote {path}")
    return result


if __name__ == "__main__":
    main()
