"""Build times per stage, tree quality and refit, with both builders.

    python -m bench.build [--quick] [--devices pocl,intel] [--docs]

On every working OpenCL device (or the ones given) it builds, with HLBVH
and plain LBVH:
  - one surface tessellated ever finer (common.surface), 1K to 3M triangles;
  - the bunny, the armadillo and Lucy as they are;
  - the reference scene (scenes/reference.toml, 2.9M triangles).
Each scene is built once when constructed (which pays for compiling the
kernels the first time a device meets them: reported apart as "first"),
rebuilt once to warm up, then rebuilt ``repeats`` times; stage times are the
device's (Scene.stats.times_ms), "wall" the host's around a rebuild.  Then its
largest mesh is refitted (Scene.update_vertices) as often.  In the full run,
a fresh process with the kernel caches off times a user's very first build.

Writes <out>/build.json and <out>/build.png (with --docs, docs/bench_build.png).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

import hlbvh_cl
import hlbvh_cl.io.scenefile

from . import plots
from .common import (MESHES, SCENES, arguments, cpu_seconds, devices_or_exit, finish,
                     machine_info, progress, ratio, say, spread, stage_times, stopwatch, summary,
                     surface, table)

BUILDERS = ("hlbvh", "lbvh")


@dataclass(frozen=True)
class Config:
    sizes: tuple[int, ...]        # the surface series, in triangles
    meshes: tuple[str, ...]       # files in scenes/meshes, built as they are
    scene: str                    # file in scenes/
    repeats: int                  # timed rebuilds (and refits) per scene and builder
    cold_compile: bool            # also time a first build with the kernel caches off


FULL = Config(sizes=tuple(int(n) for n in np.geomspace(1e3, 3e6, 8)),
              meshes=("bunny.ply", "armadillo.ply", "lucy.ply"), scene="reference.toml",
              repeats=7, cold_compile=True)
QUICK = Config(sizes=(1_000, 4_000, 16_000), meshes=("bunny_small.ply",),
               scene="bunny_small.toml", repeats=1, cold_compile=False)


@dataclass
class Case:
    name: str
    kind: str                 # "surface", "mesh" or "scene"
    meshes: list | None       # None: read from the scene file at ``path``
    path: Path | None = None

    def make_scene(self, device_id: str, builder: str):
        """The scene, built once, and the seconds spent reading files."""
        if self.meshes is None:
            loaded = hlbvh_cl.io.scenefile.load(self.path, device=device_id, builder=builder)
            return loaded.scene, loaded.load_seconds
        return hlbvh_cl.Scene(self.meshes, device=device_id, builder=builder), 0.0


def make_cases(config: Config) -> list[Case]:
    cases = [Case(mesh.name, "surface", [mesh]) for mesh in map(surface, config.sizes)]
    cases += [Case(name, "mesh", [hlbvh_cl.Mesh.load(MESHES / name)]) for name in config.meshes]
    return cases + [Case(config.scene, "scene", None, SCENES / config.scene)]


def _moved(vertices: np.ndarray) -> np.ndarray:
    """The mesh scaled by 1% about its centroid: every box changes, the topology stays."""
    centre = vertices.mean(axis=0, dtype=np.float64)
    return ((vertices - centre) * 1.01 + centre).astype(np.float32)


def measure(case: Case, device_id: str, builder: str, repeats: int) -> dict:
    """Build, rebuild ``repeats`` times and refit ``repeats`` times one scene."""
    elapsed = stopwatch()
    scene, load_seconds = case.make_scene(device_id, builder)
    construct_s = elapsed() - load_seconds
    first = scene.stats
    scene.rebuild()  # warm-up: scratch buffers, caches
    builds = []
    cpu_before, rebuilding = cpu_seconds(), stopwatch()
    for _ in range(repeats):
        scene.rebuild()
        builds.append(scene.stats)
    cores_used = (cpu_seconds() - cpu_before) / rebuilding()
    last = builds[-1]

    # Refit the largest mesh, alternately moved and back, after one warm-up.
    geom_id = int(np.argmax([m.triangle_count for m in scene.meshes]))
    original = scene.meshes[geom_id].vertices
    poses, refits = [_moved(original), original], []
    for i in range(repeats + 1):
        scene.update_vertices(geom_id, poses[i % 2])
        if i:
            refits.append(scene.stats.refit_ms)
    times = stage_times(builds)
    refit = {key: summary([r[key] for r in refits]) for key in refits[0]}
    return {
        "case": case.name, "kind": case.kind, "builder": builder, "triangles": last.triangles,
        "meshes": len(scene.meshes), "nodes": last.nodes, "leaves": last.leaves,
        "depth": last.depth, "wide_nodes": last.wide_nodes, "clusters": last.clusters,
        "sah_cost": last.sah_cost,
        "deterministic": all(b.sah_cost == last.sah_cost and b.nodes == last.nodes
                             for b in builds + [first]),
        "load_s": load_seconds, "construct_s": construct_s,
        "loadavg_1min": os.getloadavg()[0],  # others' work on a shared machine skews times
        "cores_used": cores_used,  # CPU seconds / wall seconds over the timed rebuilds
        "first_build_ms": {"device": first.device_ms, "wall": first.wall_ms},
        "times_ms": times,
        "triangles_per_s": last.triangles / (times["wall"]["median"] * 1e-3),
        "refit": {"geom_id": geom_id, "ms": refit, "sah_cost_after": scene.stats.sah_cost,
                  "wall_vs_rebuild": ratio(refit["wall"]["median"], times["wall"]["median"])},
    }


def bench_device(device_id: str, cases: list[Case], config: Config, bar) -> dict:
    results, errors = [], []
    for case in cases:
        for builder in BUILDERS:
            bar.set_postfix_str(f"{device_id} {case.name} {builder}")
            try:
                results.append(measure(case, device_id, builder, config.repeats))
            except Exception as error:  # a broken kernel must not hide the other figures
                errors.append({"case": case.name, "builder": builder,
                               "error": f"{type(error).__name__}: {error}",
                               "traceback": traceback.format_exc()})
            bar.update()
    costs: dict[str, dict] = {}
    for r in results:
        costs.setdefault(r["case"], {})[r["builder"]] = r["sah_cost"]
    out = {"cases": results, "errors": errors,
           "sah_ratios": {name: ratio(c["hlbvh"], c["lbvh"]) for name, c in costs.items()
                          if c.keys() >= set(BUILDERS)}, "cold_compile_ms": None}
    if config.cold_compile:
        try:
            out["cold_compile_ms"] = cold_compile(device_id)
        except Exception as error:
            out["cold_compile_ms"] = {"error": f"{type(error).__name__}: {error}"}
    return out


def cold_compile(device_id: str) -> dict:
    """First build of each builder in a fresh process with pyopencl's and
    PoCL's on-disk kernel caches off: what a user's very first build costs."""
    env = dict(os.environ, PYOPENCL_NO_CACHE="1", POCL_KERNEL_CACHE="0")
    done = subprocess.run([sys.executable, "-m", "bench.build", "--compile-probe", device_id],
                          env=env, capture_output=True, text=True, timeout=900,
                          cwd=Path(__file__).resolve().parent.parent)
    if done.returncode != 0:
        raise RuntimeError(f"compile probe failed: {done.stderr.strip()[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def compile_probe(device_id: str) -> dict:
    """In cold_compile's process: each builder built once, then rebuilt once."""
    mesh = hlbvh_cl.Mesh.load(MESHES / "knight.ply")  # 1,000 triangles: the build is negligible
    probe = {}
    for builder in BUILDERS:
        elapsed = stopwatch()
        scene = hlbvh_cl.Scene([mesh], device=device_id, builder=builder)
        construct_ms, first = elapsed() * 1e3, scene.stats.wall_ms
        scene.rebuild()
        probe[builder] = {"scene_ms": construct_ms, "first_build_wall": first,
                          "rebuild_wall": scene.stats.wall_ms}
    return probe


def format_device(device_id: str, result: dict) -> str:
    cases = result["cases"]
    stages = list(cases[0]["times_ms"])[:-2] if cases else []
    out = [f"=== {device_id} ===", table(
        ["case", "builder", "triangles", "first", "wall", *stages, "Mtri/s", "cores"],
        [[r["case"], r["builder"], r["triangles"], r["first_build_ms"]["wall"],
          spread(r["times_ms"]["wall"]), *[r["times_ms"][s]["median"] for s in stages],
          r["triangles_per_s"] / 1e6, f"{r['cores_used']:.2f}"] for r in cases],
        title="build ms: the first build (with compilation), then median (min-max) of the "
              "rebuilds; stages and device = device time; cores = CPU time / wall time")]
    out.append(table(
        ["case", "builder", "SAH cost", "nodes", "leaves", "depth", "HLBVH/LBVH SAH",
         "refit ms", "refit / rebuild"],
        [[r["case"], r["builder"], f"{r['sah_cost']:.2f}", r["nodes"], r["leaves"], r["depth"],
          (f"{result['sah_ratios'][r['case']]:.3f}"
           if r["builder"] == "hlbvh" and result["sah_ratios"].get(r["case"]) else None),
          spread(r["refit"]["ms"]["wall"]), f"{r['refit']['wall_vs_rebuild']:.3f}"]
         for r in cases],
        title="tree quality (SAH cost with C_t = C_i = 1, relative to the root's area) and "
              "refit after update_vertices, wall ms"))
    if result["cold_compile_ms"]:
        out.append(f"first builds with the kernel caches off: {result['cold_compile_ms']}")
    out += [f"FAILED {e['case']} {e['builder']}: {e['error']}" for e in result["errors"]]
    return "\n\n".join(out)


def main(argv=None) -> dict:
    args = arguments(__doc__.splitlines()[0], argv,
                     (["--compile-probe"], {"metavar": "DEVICE", "help": "(cold_compile's child)"}))
    if args.compile_probe:
        print(json.dumps(compile_probe(args.compile_probe)))
        return {}
    config = QUICK if args.quick else FULL
    elapsed = stopwatch()
    chosen = devices_or_exit(args.devices)
    say(f"devices: {', '.join(d.id for d in chosen)}")
    cases = make_cases(config)
    results = {"config": asdict(config), "quick": args.quick, "machine": machine_info(),
               "devices": {}}
    with progress(len(chosen) * len(BUILDERS) * len(cases), "build bench",
                  enabled=not args.no_progress) as bar:
        for device in chosen:
            results["devices"][device.id] = bench_device(device.id, cases, config, bar)
            say(format_device(device.id, results["devices"][device.id]))
    return finish(results, "build", args, elapsed, plots.build)


if __name__ == "__main__":
    main()
