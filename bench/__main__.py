"""The benchmark suite in one command, from the repository root:

    python -m bench [--quick] [--devices pocl,intel] [--peers embreex,open3d,mitsuba,trimesh] [--docs]

Writes suite.json, suite.png and RESULTS.md into bench/results/ (not
committed); with --docs also bench/RESULTS.md and docs/bench_suite.png, the
committed copies.  Sections (report.py writes one part of RESULTS.md each):
  1. devices: each working OpenCL device (or the ones given), its build
     time per stage (bench/build.py), ray throughput (section 3) and the
     reference scene's build + render (bench/render.py);
  2. the original report's table: build + render of six scene files at
     1280x720 beside the report's times, and the fitted exponent alpha of
     time ~ triangles^alpha;
  3. peers: bench/peers.py's ray tracers on the same rays as our devices;
  4. tree quality: LBVH and HLBVH trees of the same scenes, their SAH cost,
     node count and ray throughput;
  5. how it was measured: every figure is the median (min, max) of
     ``repeats`` runs after a warm-up; the machine and its load are recorded.
--quick runs a smaller configuration (a couple of minutes on 2 cores).
"""
from __future__ import annotations

import gc
import os
import sys
import time
import traceback
from dataclasses import asdict, dataclass

import hlbvh_cl

from . import build as build_bench
from . import render as render_bench
from . import report
from . import trace as trace_bench
from .common import (BENCH, DOCS, MESHES, SCENES, arguments, devices_or_exit, fit_exponent,
                     machine_info, peak_rss_bytes, progress, say, stopwatch, summary)
from .peers import EMBREE_THREADS, PEERS, REFERENCE, load_peers


@dataclass(frozen=True)
class Config:
    mode: str                               # "full", "quick" or "tiny" (the tests')
    repeats: int                            # timed runs after one warm-up, for every figure
    build_cases: tuple[str, ...]            # .ply in scenes/meshes or .toml in scenes/
    table_scenes: tuple[str, ...]           # scene files of the report's table
    table_resolution: tuple[int, int]
    extra_table_scenes: tuple[str, ...]     # rendered like the table rows, not in the report
    reference_scene: str                    # the 2048x1536 scene of the report's "about 40 s"
    reference_resolution: tuple[int, int]
    trace_scenes: tuple[str, ...]           # .ply (camera framed on it) or .toml (its camera)
    trace_resolution: tuple[int, int]       # primary rays
    incoherent_rays: int


REPORT_SCENES = tuple(f"{name}.toml" for name in render_bench.REPORT_TIMES_S)
FULL = Config("full", 5, ("lucy.ply", "reference.toml"), REPORT_SCENES, (1280, 720),
              ("reference.toml",), "reference.toml", (2048, 1536), ("lucy.ply", "reference.toml"),
              (2048, 1536), 1_000_000)
QUICK = Config("quick", 3, ("bunny.toml",), REPORT_SCENES, (1280, 720), (), "reference.toml",
               (2048, 1536), ("bunny.toml",), (640, 480), 100_000)
TINY = Config("tiny", 1, ("bunny_small.toml",), ("bunny_small.toml",), (160, 90), (),
              "bunny_small.toml", (128, 96), ("bunny_small.toml",), (64, 48), 4096)


def _failure(where: str, error: Exception) -> dict:
    say(f"FAILED {where}: {type(error).__name__}: {error}")
    return {"where": where, "error": f"{type(error).__name__}: {error}",
            "traceback": "".join(traceback.format_exception(error))}


def bench_builds(device_id: str, config: Config, errors: list) -> list[dict]:
    """bench/build.py's measure() of every build case with both builders."""
    results = []
    for name in config.build_cases:
        case = (build_bench.Case(name, "scene", None, SCENES / name) if name.endswith(".toml")
                else build_bench.Case(name, "mesh", [hlbvh_cl.Mesh.load(MESHES / name)]))
        for builder in build_bench.BUILDERS:
            try:
                results.append(build_bench.measure(case, device_id, builder, config.repeats))
            except Exception as error:  # one failure must not hide the other figures
                errors.append(_failure(f"build {device_id} {name} {builder}", error))
            gc.collect()
    return results


def bench_renders(device_id: str, scenes, resolution, repeats: int, images: dict,
                  errors: list) -> list[dict]:
    """render.time_renders() of the scene files; each image is compared with
    the first device's image of the same scene (``images`` keeps those)."""
    width, height = resolution
    rows = []
    timed = render_bench.time_renders([SCENES / n for n in scenes], device_id, width, height,
                                      repeats)
    for name, outcome in zip(scenes, timed):
        if isinstance(outcome, Exception):
            errors.append(_failure(f"render {device_id} {name}", outcome))
            continue
        result, image = outcome
        first = images.setdefault((name, width, height), (device_id, image))
        if first[0] != device_id:
            result["image_vs"] = {"device": first[0],
                                  **render_bench.image_difference(image, first[1])}
        rows.append(result)
        say(f"  {device_id} {name} {width}x{height}: build + render "
            f"{result['times_s']['total_s']['median']:.3f} s")
    return rows


def table_section(rows_by_device: dict, config: Config) -> dict:
    """The report's table on each device: speed-ups and the fitted exponent."""
    out = {"resolution": list(config.table_resolution),
           "report_resolution": list(render_bench.REPORT_RESOLUTION),
           "report_times_s": render_bench.REPORT_TIMES_S,
           "report_triangles": render_bench.REPORT_TRIANGLES,
           "report_alpha_first_last": render_bench.report_alpha(),
           "target_speedup": render_bench.TARGET_SPEEDUP,
           "target_alpha": render_bench.TARGET_ALPHA, "devices": {}}
    comparable = tuple(config.table_resolution) == render_bench.REPORT_RESOLUTION

    def fit(rows):
        return fit_exponent([r["triangles"] for r in rows],
                            [r["times_s"]["total_s"]["median"] for r in rows])

    for device_id, rows in rows_by_device.items():
        for row in rows:
            row["report_s"] = render_bench.REPORT_TIMES_S.get(row["scene"].removesuffix(".toml"))
            row["in_report"] = row["report_s"] is not None
            row["speedup"] = (row["report_s"] / row["times_s"]["total_s"]["median"]
                              if row["in_report"] and comparable else None)
        in_report = [r for r in rows if r["in_report"]]
        out["devices"][device_id] = {
            "rows": rows, "alpha": fit(in_report),
            "alpha_with_extra": fit(rows) if len(rows) > len(in_report) else None}
    return out


def bench_trace_scene(name: str, devices: list, peers: list, config: Config) -> dict:
    """Every device with both builders, and every peer, on the same rays;
    then each one's build time, in rounds like the queries'."""
    ours = [trace_bench.OurDevice(d, b) for b in build_bench.BUILDERS for d in devices]
    participants = ours + peers
    case = (trace_bench.scene_file_case(name, devices[0].id) if name.endswith(".toml")
            else trace_bench.mesh_case(name))
    workloads = case.workloads([config.trace_resolution], config.incoherent_rays, seed=1)
    result = trace_bench.bench_case(case, workloads, participants, config.repeats)
    case.built.clear()
    seconds: dict[str, list] = {p.name: [] for p in participants if p.name not in result["errors"]}
    for run in range(config.repeats + 1):  # run 0 warms up
        for p in (p for p in participants if p.name in seconds):
            try:
                built = trace_bench.build_participant(p, case)
                seconds[p.name] += [built] if run else []
            except Exception as error:
                result["errors"][p.name] = f"{type(error).__name__}: {error}"
                del seconds[p.name]
            finally:
                p.close()
    result["build_times_s"] = {n: summary(s) for n, s in seconds.items() if s}
    result["trees"] = {p.name: p.trees[case.name] for p in ours if case.name in p.trees}
    result["participants"] = {p.name: p.describe() for p in participants}
    for workload in result["workloads"]:
        say(f"  {name} {workload['name']}, closest hit Mrays/s: " + "  ".join(
            f"{n} {r['intersect_mrays']['median']:.1f}" for n, r in workload["results"].items()))
    return result


def tree_quality(suite: dict) -> dict:
    """LBVH against HLBVH per device and traced scene: the tree's stats, its
    build time (section 1, where that scene was built) and closest-hit Mrays/s."""
    out = {}
    for device_id in suite["devices"]:
        rows = []
        for scene in suite["trace"]["scenes"]:
            for builder in build_bench.BUILDERS:
                name = device_id if builder == "hlbvh" else f"{device_id} {builder}"
                if name not in scene["trees"]:
                    continue
                built = next((r for r in suite["build"].get(device_id, [])
                              if r["case"] == scene["name"] and r["builder"] == builder), None)
                rows.append({"scene": scene["name"], "builder": builder, "participant": name,
                             **scene["trees"][name],
                             "build_ms": built["times_ms"]["wall"] if built else None,
                             "mrays": {w["name"]: w["results"][name]["intersect_mrays"]
                                       for w in scene["workloads"] if name in w["results"]}})
        for row in rows:  # HLBVH over LBVH of the same scene
            other = next((r for r in rows if r["scene"] == row["scene"]
                          and r["builder"] == "lbvh"), None)
            if row["builder"] == "hlbvh" and other:
                row["vs_lbvh"] = {"sah_cost": row["sah_cost"] / other["sah_cost"],
                                  "nodes": row["nodes"] / other["nodes"],
                                  "mrays": {w: row["mrays"][w]["median"] / other["mrays"][w]["median"]
                                            for w in row["mrays"] if w in other["mrays"]}}
        out[device_id] = rows
    return out


def compile_seconds(builds: list[dict], renders: list[dict]) -> dict:
    """Seconds a device spent compiling (or loading from the caches) the
    kernels at their first use: per builder, its first build case's first
    build minus its median rebuild; for rendering, the 1x1 render."""
    firsts: dict[str, dict] = {}
    for r in builds:
        firsts.setdefault(r["builder"], r)
    build = {b: max(0.0, r["first_build_ms"]["wall"] - r["times_ms"]["wall"]["median"]) / 1e3
             for b, r in firsts.items()}
    return {"build": build or None, "render": renders[0]["compile_s"]["render"] if renders else None}


def run_suite(config: Config, devices: str | None = None, peers=None, command: str = "",
              show_progress: bool = True) -> dict:
    """Runs every section; returns the suite's results (what suite.json holds)."""
    elapsed = stopwatch()
    load_start = list(os.getloadavg())
    chosen = devices_or_exit(devices)
    available, missing = load_peers(PEERS if peers is None else peers)
    machine = machine_info()
    suite = {
        "command": command, "mode": config.mode, "config": asdict(config),
        "date": time.strftime("%Y-%m-%d %H:%M %Z"), "machine": machine,
        "loadavg_start": load_start,
        "devices": {d.id: {"name": d.name, "platform": d.platform, "driver": d.driver_version,
                           "compute_units": d.compute_units, "type": d.type} for d in chosen},
        "peers": {p.name: p.describe() for p in available + missing},
        "embree_threads": EMBREE_THREADS, "build": {}, "errors": [],
    }
    say(f"machine: {machine['processor']}, {machine['cpus']} logical CPUs; load average "
        + ", ".join(f"{x:.2f}" for x in load_start))
    say("peers: " + (", ".join(f"{p.name} {p.version}" for p in available) or "none")
        + "".join(f"; {p.name} missing ({p.problem})" for p in missing))
    errors, images = suite["errors"], {}
    table_rows, reference_rows, traced = {}, {}, []
    stages = []
    for d in chosen:
        stages += [
            (f"builds {d.id}", lambda d=d: suite["build"].__setitem__(
                d.id, bench_builds(d.id, config, errors))),
            (f"report's table {d.id}", lambda d=d: table_rows.__setitem__(d.id, bench_renders(
                d.id, config.table_scenes + config.extra_table_scenes, config.table_resolution,
                config.repeats, images, errors))),
            (f"reference {d.id}", lambda d=d: reference_rows.__setitem__(d.id, bench_renders(
                d.id, (config.reference_scene,), config.reference_resolution, config.repeats,
                images, errors)))]
    stages += [(f"trace {name}", lambda name=name: traced.append(
        bench_trace_scene(name, chosen, available, config))) for name in config.trace_scenes]
    with progress(len(stages), "bench suite", show_progress) as bar:
        for label, stage in stages:
            bar.set_postfix_str(label)
            say(f"{label} ...")
            try:
                stage()
            except Exception as error:
                errors.append(_failure(label, error))
            gc.collect()
            bar.update()

    for device_id, info in suite["devices"].items():
        info["compile_s"] = compile_seconds(suite["build"].get(device_id, []),
                                            table_rows.get(device_id, [])
                                            + reference_rows.get(device_id, []))
    suite["table"] = table_section(table_rows, config)
    suite["reference"] = {
        "scene": config.reference_scene, "resolution": list(config.reference_resolution),
        "report_s": render_bench.REPORT_REFERENCE_S, "target_s": render_bench.TARGET_REFERENCE_S,
        "devices": {device_id: rows[0] for device_id, rows in reference_rows.items() if rows}}
    for result in suite["reference"]["devices"].values():  # the report's scene only
        result["speedup"] = (render_bench.REPORT_REFERENCE_S / result["times_s"]["total_s"]["median"]
                             if result["scene"] == "reference.toml" else None)
    suite["trace"] = {"resolution": list(config.trace_resolution),
                      "incoherent_rays": config.incoherent_rays, "seed": 1,
                      "reference_participant": REFERENCE, "scenes": traced}
    suite["tree_quality"] = tree_quality(suite)
    suite["loadavg_end"] = list(os.getloadavg())
    suite["peak_rss_bytes"] = peak_rss_bytes()
    suite["elapsed_s"] = elapsed()
    return suite


def main(argv=None) -> dict:
    args = arguments("hlbvh_cl's benchmark suite: every device and peer, the original report's "
                     "table reproduced; writes RESULTS.md, suite.json and suite.png.", argv,
                     (["--peers"], {"default": None, "help": f"comma-separated peers (default: "
                                                            f"{','.join(PEERS)}; '' for none)"}),
                     (["--tiny"], {"action": "store_true", "help": "the tests' configuration"}))
    config = TINY if args.tiny else QUICK if args.quick else FULL
    peers = None if args.peers is None else [p.strip() for p in args.peers.split(",") if p.strip()]
    command = " ".join(["python -m bench", *(argv if argv is not None else sys.argv[1:])])
    suite = run_suite(config, args.devices, peers, command, show_progress=not args.no_progress)
    written = report.write_all(suite, args.out / "suite.json", args.out / "suite.png",
                               args.out / "RESULTS.md")
    if args.docs:
        written += report.write_all(suite, None, DOCS / "bench_suite.png", BENCH / "RESULTS.md")
    print()
    print(report.summary_text(suite))
    print(f"\nwrote {', '.join(str(p) for p in written)} in {suite['elapsed_s'] / 60:.1f} min")
    return suite


if __name__ == "__main__":
    main()
