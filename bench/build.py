"""Build benchmark: HLBVH vs LBVH build times, tree quality, refit, and sort peers.

    python bench/build.py [--quick] [--devices pocl,intel] [--out bench/results]

On every working OpenCL device (or the ones given) it builds, with both
builders:
  - a scaling series: the first faces of Lucy, split with split_edges where
    more triangles are needed, from 1K to 3M triangles (geometric sizes);
  - the bunny, the armadillo and Lucy as they are;
  - the reference scene (scenes/reference.toml, 2.91M triangles).
Each scene is built once when constructed (that build pays for kernel
compilation the first time a device meets a kernel: reported apart, as
"first"), rebuilt once more to warm up, then rebuilt ``repeats`` times; the
per-stage times are the device's profiling events (scene.stats["times_ms"]),
"wall" the host's time around a build.  Then its largest mesh is refitted
(scene.update_vertices) as often and compared with a rebuild.  Last, our
radix sort is timed against pyopencl's RadixSort and numpy on the same 3M
keys (bench/sort.py).

Writes <out>/build.json and <out>/build.png and prints one set of tables per
device.  Figures are medians (min-max) of one run on a shared machine.
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import subprocess
import sys
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # common.py and sort.py

import numpy as np  # noqa: E402
from common import (MESHES, SCENES, cpu_seconds, machine_info, peak_rss_bytes, pick_devices,  # noqa: E402
                    progress, pyplot, quiet_compiler_warnings, ratio, save_figure, stopwatch,
                    summary, table, write_json)

from hlbvh_cl import Mesh, Scene  # noqa: E402
from hlbvh_cl.build import BUILDERS  # noqa: E402
from hlbvh_cl.scene import STAGES  # noqa: E402
from hlbvh_cl.cli import load_scene  # noqa: E402
from hlbvh_cl.split import split_edges  # noqa: E402

TIME_KEYS = STAGES + ("total", "wall")


@dataclass(frozen=True)
class Config:
    sizes: tuple[int, ...]        # scaling series, in triangles
    scaling_mesh: str             # file in scenes/meshes the series is cut from
    meshes: tuple[str, ...]       # files in scenes/meshes, built as they are
    scene: str                    # file in scenes/
    repeats: int                  # timed rebuilds (and refits) per scene and builder
    sort_n: int
    sort_repeats: int
    cold_compile: bool            # also time a first build with the kernel caches off


def _geometric_sizes(low: float, high: float, count: int) -> tuple[int, ...]:
    """count sizes from low to high in equal ratios, rounded to 2 significant digits."""
    sizes = []
    for size in np.geomspace(low, high, count):
        digits = int(np.floor(np.log10(size))) - 1
        sizes.append(int(round(size / 10**digits) * 10**digits))
    return tuple(sizes)


FULL = Config(sizes=_geometric_sizes(1e3, 3e6, 8), scaling_mesh="lucy.ply",
              meshes=("bunny.ply", "armadillo.ply", "lucy.ply"), scene="reference.toml",
              repeats=7, sort_n=3_000_000, sort_repeats=5, cold_compile=True)
QUICK = Config(sizes=(1_000, 4_000, 16_000), scaling_mesh="lucy_small.ply",
               meshes=("bunny_small.ply", "lucy_small.ply"), scene="bunny_small.toml",
               repeats=1, sort_n=20_000, sort_repeats=1, cold_compile=False)


# ---------------------------------------------------------------- scenes

def compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop the vertices no face uses and renumber the faces."""
    used, renumbered = np.unique(faces, return_inverse=True)
    return vertices[used], renumbered.reshape(faces.shape).astype(np.int32)


def mesh_part(mesh: Mesh, triangles: int) -> Mesh:
    """The first faces of ``mesh``, split by the smallest k that gives at
    least ``triangles`` triangles, cut to exactly that many.

    A split face's k*k children are consecutive (split.py), so the result is
    a contiguous piece of the split surface."""
    if triangles < 1:
        raise ValueError(f"triangles must be >= 1, got {triangles}")
    k = int(np.ceil(np.sqrt(triangles / mesh.triangle_count)))
    parents = -(-triangles // (k * k))
    vertices, faces = compact(mesh.vertices, mesh.faces[:parents])
    vertices, faces = split_edges(vertices, faces, k)
    vertices, faces = compact(vertices, faces[:triangles])
    return Mesh(vertices, faces, name=f"{mesh.name}[:{parents}] split {k}")


@dataclass
class Case:
    name: str
    kind: str                 # "scaling", "mesh" or "scene"
    triangles: int
    meshes: list | None       # None: loaded from the scene file by make_scene
    path: Path | None = None

    def make_scene(self, device_id: str, builder: str) -> tuple[Scene, float]:
        """The scene, built once, and the seconds spent reading files."""
        if self.meshes is None:
            scene, _, load_seconds = load_scene(self.path, device=device_id, builder=builder)
            return scene, load_seconds
        return Scene(self.meshes, device=device_id, builder=builder), 0.0


def make_cases(config: Config) -> list[Case]:
    source = Mesh.load(MESHES / config.scaling_mesh)
    cases = []
    for size in config.sizes:
        part = mesh_part(source, size)
        cases.append(Case(f"{Path(config.scaling_mesh).stem} part {size:,}", "scaling",
                          part.triangle_count, [part]))
    for filename in config.meshes:
        mesh = Mesh.load(MESHES / filename)
        cases.append(Case(filename, "mesh", mesh.triangle_count, [mesh]))
    # The scene file's meshes are read by load_scene for every device and builder.
    cases.append(Case(config.scene, "scene", 0, None, SCENES / config.scene))
    return cases


# ---------------------------------------------------------------- measuring

def _times_summary(builds: list[dict]) -> dict:
    return {key: summary([b["times_ms"][key] for b in builds]) for key in TIME_KEYS}


def _moved(vertices: np.ndarray) -> np.ndarray:
    """The mesh scaled by 1% about its centroid: every box changes, the topology stays."""
    centre = vertices.mean(axis=0, dtype=np.float64)
    return ((vertices - centre) * 1.01 + centre).astype(np.float32)


def measure(case: Case, device_id: str, builder: str, repeats: int) -> dict:
    """Build, rebuild ``repeats`` times and refit ``repeats`` times one scene."""
    elapsed = stopwatch()
    scene, load_seconds = case.make_scene(device_id, builder)
    construct_s = elapsed() - load_seconds
    first = copy.deepcopy(scene.stats)

    scene.rebuild()  # warm-up: scratch buffers, caches
    builds = []
    cpu_before, rebuilding = cpu_seconds(), stopwatch()
    for _ in range(repeats):
        scene.rebuild()
        builds.append(copy.deepcopy(scene.stats))
    cores_used = (cpu_seconds() - cpu_before) / rebuilding()
    last = builds[-1]
    stable = all(b["sah_cost"] == last["sah_cost"] and b["nodes"] == last["nodes"]
                 for b in builds + [first])

    # Refit the largest mesh, alternately moved and back, after one warm-up.
    geom_id = int(np.argmax([m.triangle_count for m in scene.meshes]))
    original = scene.meshes[geom_id].vertices
    poses = [_moved(original), original]
    refits, calls = [], []
    for i in range(repeats + 1):
        call = stopwatch()
        scene.update_vertices(geom_id, poses[i % 2])
        if i:
            calls.append(call() * 1e3)
            refits.append(dict(scene.stats["update_ms"]))
    sah_after_refit = scene.stats["sah_cost"]  # last pose: back to the original
    times = _times_summary(builds)
    refit = {key: summary([r[key] for r in refits]) for key in ("upload", "refit", "wall")}
    refit["call_wall"] = summary(calls)
    result = {
        "case": case.name, "kind": case.kind, "builder": builder,
        "triangles": last["triangles"], "meshes": len(scene.meshes),
        "nodes": last["nodes"], "leaves": last["leaves"], "depth": last["depth"],
        "clusters": last["clusters"], "sah_cost": last["sah_cost"],
        "deterministic": stable,
        "load_s": load_seconds, "construct_s": construct_s,
        "loadavg_1min": os.getloadavg()[0],  # others' work on the shared machine skews times
        "cores_used": cores_used,  # CPU seconds / wall seconds over the timed rebuilds
        "first_build_ms": {"total": first["times_ms"]["total"], "wall": first["times_ms"]["wall"]},
        "times_ms": times,
        "triangles_per_s": last["triangles"] / (times["wall"]["median"] * 1e-3),
        "refit": {
            "geom_id": geom_id, "ms": refit,
            "sah_cost_after": sah_after_refit,
            "wall_vs_rebuild": ratio(refit["wall"]["median"], times["wall"]["median"]),
            "device_vs_rebuild": ratio(refit["refit"]["median"], times["total"]["median"]),
        },
    }
    del scene
    return result


def bench_device(device_id: str, cases: list[Case], config: Config, bar) -> dict:
    from sort import bench_sort

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
    bar.set_postfix_str(f"{device_id} sort peers")
    try:
        sort = bench_sort(device_id, config.sort_n, config.sort_repeats)
    except Exception as error:
        sort = {"error": f"{type(error).__name__}: {error}"}
    bar.update()
    cold = None
    if config.cold_compile:
        bar.set_postfix_str(f"{device_id} cold compile")
        try:
            cold = cold_compile(device_id)
        except Exception as error:
            cold = {"error": f"{type(error).__name__}: {error}"}
        bar.update()
    return {"cases": results, "errors": errors, "sah_ratios": sah_ratios(results),
            "compile_ms": compile_estimates(results), "cold_compile_ms": cold, "sort": sort}


COMPILE_PROBE_MESH = MESHES / "knight.ply"  # 1,000 triangles: the build itself is negligible


def cold_compile(device_id: str) -> dict:
    """First build in a fresh process with pyopencl's and PoCL's on-disk
    kernel caches off: what a user's very first build costs."""
    env = dict(os.environ, PYOPENCL_NO_CACHE="1", POCL_KERNEL_CACHE="0")
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--compile-probe",
                           device_id], env=env, capture_output=True, text=True, timeout=900)
    if done.returncode != 0:
        raise RuntimeError(f"compile probe failed: {done.stderr.strip()[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def compile_probe(device_id: str) -> dict:
    """Run in the child process of cold_compile: builders in order, each
    built once (compiling what the previous one did not) and rebuilt once."""
    mesh = Mesh.load(COMPILE_PROBE_MESH)
    probe = {}
    for builder in BUILDERS:
        elapsed = stopwatch()
        scene = Scene([mesh], device=device_id, builder=builder)
        construct_ms = elapsed() * 1e3
        first = scene.stats["times_ms"]["wall"]
        scene.rebuild()
        probe[builder] = {"scene_ms": construct_ms, "first_build_wall": first,
                          "rebuild_wall": scene.stats["times_ms"]["wall"]}
    return probe


def sah_ratios(results: list[dict]) -> dict:
    """HLBVH SAH cost / LBVH SAH cost per case (< 1: HLBVH's tree is better)."""
    by_case: dict[str, dict] = {}
    for r in results:
        by_case.setdefault(r["case"], {})[r["builder"]] = r["sah_cost"]
    return {name: ratio(costs["hlbvh"], costs["lbvh"])
            for name, costs in by_case.items() if {"hlbvh", "lbvh"} <= costs.keys()}


def compile_estimates(results: list[dict]) -> dict:
    """Per builder: the first build of the device's first scene minus a warm
    rebuild of it, i.e. roughly the kernels' compile (or cache load) time."""
    estimates = {}
    for builder in BUILDERS:
        runs = [r for r in results if r["builder"] == builder]
        if runs:
            first = runs[0]
            estimates[builder] = {"case": first["case"],
                                  "first_build_wall": first["first_build_ms"]["wall"],
                                  "rebuild_wall": first["times_ms"]["wall"]["median"],
                                  "compile_estimate": first["first_build_ms"]["wall"]
                                  - first["times_ms"]["wall"]["median"]}
    return estimates


# ---------------------------------------------------------------- reporting

def _spread(times: dict) -> str:
    return f"{times['median']:.1f} ({times['min']:.1f}-{times['max']:.1f})"


def format_device(device_id: str, result: dict) -> str:
    cases = result["cases"]
    out = [f"=== {device_id} ==="]
    rows = [[r["case"], r["builder"], r["triangles"], r["first_build_ms"]["wall"],
             _spread(r["times_ms"]["wall"]), r["times_ms"]["total"]["median"],
             *[r["times_ms"][s]["median"] for s in STAGES], r["triangles_per_s"] / 1e6,
             f"{r['cores_used']:.2f}", f"{r['loadavg_1min']:.1f}"]
            for r in cases]
    out.append(table(["case", "builder", "triangles", "first", "wall", "device", *STAGES, "Mtri/s",
                      "cores", "load"],
                     rows, title="build ms: first build (with compilation), then median (min-max) "
                                 "of the rebuilds; stages = device time; cores = CPU time / wall "
                                 "time of the rebuilds; load = 1-min load average (2 cores)"))
    by_case: dict[str, dict] = {}
    for r in cases:
        by_case.setdefault(r["case"], {})[r["builder"]] = r
    rows = []
    for name, pair in by_case.items():
        h, lb = pair.get("hlbvh"), pair.get("lbvh")
        row = [name, (h or lb)["triangles"]]
        for key in ("sah_cost", "nodes", "leaves", "depth"):
            row += [h[key] if h else None, lb[key] if lb else None]
        row.append(f"{result['sah_ratios'].get(name):.3f}" if result["sah_ratios"].get(name)
                   else None)
        rows.append(row)
    out.append(table(["case", "triangles", "SAH hlbvh", "SAH lbvh", "nodes hlbvh", "nodes lbvh",
                      "leaves hlbvh", "leaves lbvh", "depth h", "depth l", "SAH h/l"], rows,
                     title="tree quality (SAH cost with C_t = C_i = 1, relative to the root's area)"))
    rows = [[r["case"], r["builder"], r["triangles"], r["refit"]["ms"]["refit"]["median"],
             _spread(r["refit"]["ms"]["wall"]), r["times_ms"]["wall"]["median"],
             f"{r['refit']['wall_vs_rebuild']:.3f}", f"{r['refit']['device_vs_rebuild']:.3f}",
             f"{r['sah_cost']:.3f} -> {r['refit']['sah_cost_after']:.3f}"]
            for r in cases]
    out.append(table(["case", "builder", "triangles", "refit device", "refit wall", "rebuild wall",
                      "wall ratio", "device ratio", "SAH built -> refit"], rows,
                     title="refit (update_vertices of the largest mesh, moved 1% then back) vs "
                           "rebuild, ms; ratios = refit / rebuild"))
    compile_rows = [[b, e["case"], e["first_build_wall"], e["rebuild_wall"], e["compile_estimate"]]
                    for b, e in result["compile_ms"].items()]
    out.append(table(["builder", "first scene", "first build", "rebuild", "difference"],
                     compile_rows, title="compilation, kernel caches as found: first build of the "
                                         "first scene vs its rebuild, wall ms"))
    cold = result.get("cold_compile_ms")
    if cold and "error" in cold:
        out.append(f"cold compilation: failed: {cold['error']}")
    elif cold:
        rows = [[b, c["scene_ms"], c["first_build_wall"], c["rebuild_wall"]] for b, c in cold.items()]
        out.append(table(["builder", "Scene()", "first build", "rebuild"], rows,
                         title=f"compilation, kernel caches off, fresh process, "
                               f"{COMPILE_PROBE_MESH.name} (builders in this order), wall ms"))
    sort = result["sort"]
    if "error" in sort:
        out.append(f"sort peers: failed: {sort['error']}")
    else:
        rows = []
        for name, c in sort["cases"].items():
            ms = {k: (_spread({q: v * 1e3 for q, v in c[k].items()}) if c[k] else "skipped")
                  for k in ("ours", "pyopencl", "numpy")}
            rows.append([name, ms["ours"], ms["pyopencl"], ms["numpy"],
                         f"{c['speedup_vs_pyopencl']:.2f}" if c["speedup_vs_pyopencl"] else None,
                         f"{c['speedup_vs_numpy']:.2f}", str(c["correct"])])
        out.append(table(["keys", "ours", "pyopencl RadixSort", "numpy stable", "x pyopencl",
                          "x numpy", "correct"], rows,
                         title=f"sort of {sort['n']:,} random keys, wall ms, median (min-max) of "
                               f"{sort['repeats']}; x = peer time / our time"))
    for e in result["errors"]:
        out.append(f"FAILED {e['case']} {e['builder']}: {e['error']}")
    return "\n\n".join(out)


def plot(results: dict, path: Path) -> Path:
    plt = pyplot()
    figure, (scaling, stages) = plt.subplots(1, 2, figsize=(13, 5))
    markers = {"hlbvh": "o", "lbvh": "s"}
    for device_id, result in results["devices"].items():
        for builder in BUILDERS:
            series = [r for r in result["cases"] if r["kind"] == "scaling" and r["builder"] == builder]
            if not series:
                continue
            x = [r["triangles"] for r in series]
            y = [r["times_ms"]["wall"]["median"] for r in series]
            low = [r["times_ms"]["wall"]["median"] - r["times_ms"]["wall"]["min"] for r in series]
            high = [r["times_ms"]["wall"]["max"] - r["times_ms"]["wall"]["median"] for r in series]
            line = scaling.errorbar(x, y, yerr=[low, high], marker=markers[builder], capsize=2,
                                    label=f"{device_id} {builder}")
            others = [r for r in result["cases"] if r["kind"] != "scaling" and r["builder"] == builder]
            scaling.scatter([r["triangles"] for r in others],
                            [r["times_ms"]["wall"]["median"] for r in others], marker="x",
                            color=line[0].get_color())
    scaling.set(xscale="log", yscale="log", xlabel="triangles", ylabel="build wall time (ms)",
                title="build time (median of rebuilds; x: the meshes and the scene)")
    scaling.grid(True, which="both", alpha=0.3)
    scaling.legend(fontsize=8)

    bars = [(f"{device_id}\n{r['builder']}", r) for device_id, result in results["devices"].items()
            for r in result["cases"] if r["kind"] == "scene"]
    bottom = np.zeros(len(bars))
    for stage in STAGES:
        heights = np.array([r["times_ms"][stage]["median"] for _, r in bars])
        stages.bar([label for label, _ in bars], heights, bottom=bottom, label=stage)
        bottom += heights
    scene_name = bars[0][1]["case"] if bars else "scene"
    triangles = bars[0][1]["triangles"] if bars else 0
    stages.set(ylabel="device time (ms, median)",
               title=f"stages of the {scene_name} build ({triangles:,} triangles)")
    stages.legend(fontsize=8)
    return save_figure(figure, path)


# ---------------------------------------------------------------- main

def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="a tiny configuration (small scenes, 1 repeat), for tests")
    parser.add_argument("--devices", default=None,
                        help="comma-separated device ids or names (default: every working device)")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    parser.add_argument("--compile-probe", metavar="DEVICE", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.compile_probe:
        quiet_compiler_warnings()
        print(json.dumps(compile_probe(args.compile_probe)))
        return {}
    config = QUICK if args.quick else FULL
    elapsed = stopwatch()
    quiet_compiler_warnings()

    chosen, skipped = pick_devices(args.devices)
    for s in skipped:
        print(f"skipping {s['device']}: {s['problem']}")
    if not chosen:
        raise SystemExit("no working OpenCL device to benchmark")
    print(f"devices: {', '.join(str(d) for d in chosen)}", flush=True)

    cases = make_cases(config)
    results = {"config": asdict(config), "quick": args.quick, "machine": machine_info(),
               "skipped_devices": skipped, "devices": {}}
    steps_per_device = len(BUILDERS) * len(cases) + 1 + config.cold_compile
    with progress(len(chosen) * steps_per_device, "build bench",
                  enabled=not args.no_progress) as bar:
        for device in chosen:
            results["devices"][device.id] = bench_device(device.id, cases, config, bar)
            bar.write(format_device(device.id, results["devices"][device.id]), file=sys.stdout)
    results["peak_rss_bytes"] = peak_rss_bytes()
    results["elapsed_s"] = elapsed()
    json_path = write_json(args.out / "build.json", results)
    png_path = plot(results, args.out / "build.png")
    print(f"\nwrote {json_path} and {png_path} in {results['elapsed_s']:.0f} s")
    return results


if __name__ == "__main__":
    main()
