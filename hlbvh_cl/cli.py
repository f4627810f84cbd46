"""The ``hlbvh-cl`` command.

    hlbvh-cl devices              list the OpenCL devices and their ids
    hlbvh-cl info SCENE.toml      load a scene file, build its BVH, print the stats

A user's mistake (a bad scene file, an unknown device) ends with a one-line
error and exit code 2, never a traceback.
"""
from __future__ import annotations

import argparse
import sys
import time

from . import Scene, devices
from .device import DeviceMemoryError, KernelBuildError


def _cmd_devices(args) -> int:
    found = devices()
    if not found:
        print("no OpenCL device found; install PoCL: pip install pocl-binary-distribution")
        return 1
    for d in found:
        state = "ok" if d.problem is None else f"cannot compile kernels: {d.problem}"
        print(f"{d.id:10s} {d.type:4s} {d.name} [{d.platform}, driver {d.driver_version}, "
              f"{d.compute_units} compute units] {state}")
    if args.require and not any(d.problem is None and args.require in d.id for d in found):
        print(f"hlbvh-cl: error: no working device whose id contains {args.require!r}",
              file=sys.stderr)
        return 1
    return 0


def load_scene(path, device=None, builder: str = "hlbvh", morton_bits: int = 30):
    """Read a scene file and build its Scene: (scene, description, load_seconds)."""
    from .scenefile import load_scene_file
    started = time.perf_counter()
    description = load_scene_file(path)
    loaded = time.perf_counter() - started
    meshes = [entry.mesh for entry in description.meshes]
    if description.ground is not None:
        meshes.append(description.ground.mesh)
    return Scene(meshes, device=device, builder=builder, morton_bits=morton_bits), description, loaded


def _cmd_info(args) -> int:
    scene, description, loaded = load_scene(args.scene, args.device, args.builder, args.morton_bits)
    if args.repeat > 1:  # the first build pays for kernel compilation
        for _ in range(args.repeat - 1):
            scene.rebuild()
    s = scene.stats
    print(f"scene      {description.path}  ({len(scene.meshes)} meshes, loaded in {loaded:.2f} s)")
    print(f"device     {scene.device}")
    print(f"builder    {s['builder']} ({s['morton_bits']}-bit Morton codes, {s['clusters']} clusters)")
    print(f"triangles  {s['triangles']:,}")
    print(f"nodes      {s['nodes']:,}   leaves {s['leaves']:,}   depth {s['depth']}")
    print(f"SAH cost   {s['sah_cost']:.2f}  (C_t = C_i = 1, relative to the root's area)")
    times = s["times_ms"]
    stages = "  ".join(f"{k} {v:.1f}" for k, v in times.items() if k not in ("total", "wall"))
    print(f"build ms   {stages}")
    print(f"           device total {times['total']:.1f}, wall {times['wall']:.1f}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="hlbvh-cl", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    listing = sub.add_parser("devices", help="list OpenCL devices")
    listing.add_argument("--require", metavar="ID", default=None,
                         help="exit 1 unless a working device's id contains ID (e.g. pocl)")
    listing.set_defaults(run=_cmd_devices)
    info = sub.add_parser("info", help="build a scene file's BVH and print its stats")
    info.add_argument("scene")
    info.add_argument("--device", default=None, help="device id, index or name (default: auto)")
    info.add_argument("--builder", default="hlbvh", choices=["hlbvh", "lbvh"])
    info.add_argument("--morton-bits", type=int, default=30, choices=[30, 63])
    info.add_argument("--repeat", type=int, default=2,
                      help="builds to run; the stats are the last one's (default 2)")
    info.set_defaults(run=_cmd_info)
    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except (ValueError, TypeError, FileNotFoundError, DeviceMemoryError, KernelBuildError,
            RuntimeError) as error:
        print(f"hlbvh-cl: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
