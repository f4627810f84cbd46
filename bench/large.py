"""A 10M-triangle build and the process memory it takes.

    python -m bench.large [--quick] [--devices pocl] [--triangles 10000000] [--repeats 5]

One surface (common.surface) of about 10M triangles is built once (with
kernel compilation), warmed up and rebuilt ``repeats`` times on the first
device given.  Printed: the stage times, the tree, and the process's peak
resident memory (ru_maxrss) before and after; on a CPU device, device
buffers are host memory, so that growth is the build's real peak.
Writes <out>/large.json.
"""
from __future__ import annotations

import hlbvh_cl

from .common import (arguments, devices_or_exit, finish, machine_info, peak_rss_bytes, say,
                     stage_times, stopwatch, surface, table)

GIB = 2**30


def main(argv=None) -> dict:
    args = arguments(__doc__.splitlines()[0], argv,
                     (["--triangles"], {"type": int, "default": 10_000_000}),
                     (["--repeats"], {"type": int, "default": 5}))
    triangles, repeats = (100_000, 1) if args.quick else (args.triangles, args.repeats)
    device = devices_or_exit(args.devices or "pocl")[0]
    elapsed = stopwatch()
    mesh = surface(triangles)
    say(f"mesh       {mesh.name}: {mesh.triangle_count:,} triangles, {mesh.vertex_count:,} "
        f"vertices (made in {elapsed():.1f} s); device {device.id}, "
        f"{device.global_mem_size / GIB:.2f} GiB global memory")

    rss_before = peak_rss_bytes()
    building = stopwatch()
    scene = hlbvh_cl.Scene([mesh], device=device.id)
    construct_s, first = building(), scene.stats
    rss_first = peak_rss_bytes()
    scene.rebuild()  # warm-up
    builds = []
    for _ in range(repeats):
        scene.rebuild()
        builds.append(scene.stats)
    rss_rebuilds = peak_rss_bytes()
    last = builds[-1]
    times = stage_times(builds)
    say(table(["stage", "median ms", "min", "max"],
              [[key, t["median"], t["min"], t["max"]] for key, t in times.items()],
              title=f"build of {last.triangles:,} triangles ({last.builder}), {repeats} "
                    f"rebuilds after a warm-up; first build (with compilation) "
                    f"{first.wall_ms:.0f} ms wall, Scene() {construct_s:.1f} s"))
    say(f"tree       {last.nodes:,} nodes, {last.leaves:,} leaves, depth {last.depth}, "
        f"SAH {last.sah_cost:.2f}; {last.triangles / times['wall']['median'] / 1e3:.1f} "
        f"Mtriangles/s")
    say(f"peak RSS   {rss_before / GIB:.2f} GiB before Scene(), {rss_first / GIB:.2f} after the "
        f"first build, {rss_rebuilds / GIB:.2f} after the rebuilds")
    result = {
        "machine": machine_info(), "device": device.id, "mesh": mesh.name,
        "triangles": mesh.triangle_count, "vertices": mesh.vertex_count,
        "construct_s": construct_s, "repeats": repeats,
        "first_build_ms": {"device": first.device_ms, "wall": first.wall_ms}, "times_ms": times,
        "tree": {"builder": last.builder, "nodes": last.nodes, "leaves": last.leaves,
                 "depth": last.depth, "sah_cost": last.sah_cost},
        "rss_bytes": {"before": rss_before, "first_build": rss_first,
                           "rebuilds": rss_rebuilds},
    }
    return finish(result, "large", args, elapsed)


if __name__ == "__main__":
    main()
