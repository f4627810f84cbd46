"""The benchmark suite in one command, from the repository root:

    python -m bench [--quick] [--devices pocl,intel] [--peers embreex,open3d,mitsuba,trimesh]

Writes bench/results/suite.json, bench/results/suite_*.png and bench/RESULTS.md.
Sections (report.py writes one part of RESULTS.md for each):

  1. devices: every working OpenCL device (or the ones given): its name,
     driver and compute units; build time per stage (bench/build.py
     measure); ray throughput (section 3); the reference scene's build +
     render time (bench/render.py), with file loading and compilation apart;
  2. the original report's table: build + render of six scene files at
     1280x720 beside the report's times, the speed-up of each row and the
     fitted exponent alpha of time ~ triangles^alpha; the reference scene
     beside the report's "about 40 s";
  3. peers: embreex, Open3D, Mitsuba 3 and trimesh build and trace the same
     rays as our devices in the same run (bench/trace.py bench_case);
  4. tree quality: LBVH and HLBVH trees of the same scenes, their SAH cost,
     node count and ray throughput;
  5. noise: every figure is the median (with min and max) of ``repeats``
     runs after a warm-up; the machine and its load average are recorded.

--quick runs a smaller configuration (under 2 minutes on 2 cores); the full
suite about 6 minutes.
"""
from __future__ import annotations

import argparse
import gc
import os
import sys
import time
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path

from . import build as build_bench
from . import render as render_bench
from . import report
from . import trace as trace_bench
from .common import (MESHES, SCENES, machine_info, peak_rss_bytes, pick_devices, progress,
                     quiet_compiler_warnings, stopwatch, summary)

from hlbvh_cl import Mesh, Scene  # noqa: E402  (common.py put the checkout on sys.path)
from hlbvh_cl.build import BUILDERS  # noqa: E402

BENCH = Path(__file__).resolve().parent


@dataclass(frozen=True)
class Config:
    mode: str                               # "full", "quick" or "tiny" (the test's)
    repeats: int                            # timed runs after one warm-up, for every figure
    build_cases: tuple[str, ...]            # .ply in scenes/meshes or .toml in scenes/
    table_scenes: tuple[str, ...]           # scene files of the report's table
    table_resolution: tuple[int, int]
    extra_table_scenes: tuple[str, ...]     # rendered like the table rows, but not in the report
    reference_scene: str                    # the 2048x1536 scene of the report's "about 40 s"
    reference_resolution: tuple[int, int]
    reference_repeats: int
    trace_scenes: tuple[str, ...]           # .ply (camera framed on it) or .toml (its camera)
    trace_resolution: tuple[int, int]       # primary rays
    incoherent_rays: int
    peers: tuple[str, ...]
    devices: str | None                     # default device list (None: every working device)


REPORT_SCENES = tuple(f"{name}.toml" for name in render_bench.REPORT_TIMES_S)

FULL = Config(mode="full", repeats=5, build_cases=("lucy.ply", "reference.toml"),
              table_scenes=REPORT_SCENES, table_resolution=(1280, 720),
              extra_table_scenes=("reference.toml",),
              reference_scene="reference.toml", reference_resolution=(2048, 1536),
              reference_repeats=5, trace_scenes=("lucy.ply", "reference.toml"),
              trace_resolution=(2048, 1536), incoherent_rays=1_000_000,
              peers=tuple(trace_bench.PEERS), devices=None)
QUICK = Config(mode="quick", repeats=3, build_cases=("bunny.toml",),
               table_scenes=REPORT_SCENES, table_resolution=(1280, 720), extra_table_scenes=(),
               reference_scene="reference.toml", reference_resolution=(2048, 1536),
               reference_repeats=3, trace_scenes=("bunny.toml",), trace_resolution=(640, 480),
               incoherent_rays=100_000, peers=tuple(trace_bench.PEERS), devices=None)
TINY = Config(mode="tiny", repeats=1, build_cases=("bunny_small.toml",),
              table_scenes=("bunny_small.toml",), table_resolution=(160, 90),
              extra_table_scenes=(), reference_scene="bunny_small.toml",
              reference_resolution=(128, 96), reference_repeats=1,
              trace_scenes=("bunny_small.toml",), trace_resolution=(64, 48),
              incoherent_rays=4096, peers=tuple(trace_bench.PEERS), devices="pocl")
CONFIGS = {c.mode: c for c in (FULL, QUICK, TINY)}


def _say(text: str) -> None:
    """A line on stdout that does not break the progress bars on stderr."""
    from tqdm import tqdm
    tqdm.write(text, file=sys.stdout)
    sys.stdout.flush()


def _failure(where: str, error: Exception) -> dict:
    _say(f"FAILED {where}: {type(error).__name__}: {error}")
    return {"where": where, "error": f"{type(error).__name__}: {error}",
            "traceback": "".join(traceback.format_exception(error))}


# ---------------------------------------------------------------- 1. builds

def _build_case(name: str) -> build_bench.Case:
    if name.endswith(".toml"):
        return build_bench.Case(name, "scene", 0, None, SCENES / name)
    mesh = Mesh.load(MESHES / name)
    return build_bench.Case(name, "mesh", mesh.triangle_count, [mesh])


def bench_builds(device_id: str, config: Config, errors: list, show: bool) -> list[dict]:
    """bench/build.py's measure() of every build case with both builders."""
    cases = [_build_case(name) for name in config.build_cases]
    results = []
    with progress(len(cases) * len(BUILDERS), f"builds {device_id}", show) as bar:
        for case in cases:
            for builder in BUILDERS:
                bar.set_postfix_str(f"{case.name} {builder}")
                try:
                    results.append(build_bench.measure(case, device_id, builder, config.repeats))
                except Exception as error:  # one failure must not hide the other figures
                    errors.append(_failure(f"build {device_id} {case.name} {builder}", error))
                gc.collect()
                bar.update()
    return results


# ---------------------------------------------------------------- 2. renders

def bench_renders(device_id: str, scenes, resolution, repeats: int, images: dict, errors: list,
                  show: bool, label: str) -> list[dict]:
    """render.time_renders() of the scene files, in interleaved rounds; each
    image is compared with the first device's image of the same scene
    (``images`` keeps those)."""
    width, height = resolution
    rows = []
    with progress(len(scenes) * (repeats + 1), f"{label} {device_id}", show) as bar:
        timed = render_bench.time_renders([SCENES / name for name in scenes], device_id,
                                          width, height, repeats, bar=_Ticker(bar))
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
            seconds = result["times_s"]["total_s"]["median"]
            report_s = render_bench.REPORT_TIMES_S.get(name.removesuffix(".toml"))
            _say(f"  {device_id} {name} {width}x{height}: build + render {seconds:.3f} s"
                 + (f" (report {report_s} s: {report_s / seconds:.1f}x)"
                    if report_s and (width, height) == render_bench.REPORT_RESOLUTION else ""))
        gc.collect()
    return rows


class _Ticker:
    """A progress bar that advances one step as each (scene, run) starts."""

    def __init__(self, bar):
        self.bar = bar

    def set_postfix_str(self, text: str) -> None:
        self.bar.set_postfix_str(text)
        self.bar.update()


def table_section(rows_by_device: dict, config: Config) -> dict:
    """The report's table on each device: speed-ups and the fitted exponent."""
    out = {"resolution": list(config.table_resolution),
           "report_resolution": list(render_bench.REPORT_RESOLUTION),
           "report_times_s": render_bench.REPORT_TIMES_S,
           "report_triangles": render_bench.REPORT_TRIANGLES,
           "report_alpha_first_last": render_bench.report_alpha(),
           "target_speedup": render_bench.TARGET_SPEEDUP, "target_alpha": render_bench.TARGET_ALPHA,
           "devices": {}}
    comparable = tuple(config.table_resolution) == render_bench.REPORT_RESOLUTION
    for device_id, rows in rows_by_device.items():
        for row in rows:
            name = row["scene"].removesuffix(".toml")
            row["in_report"] = name in render_bench.REPORT_TIMES_S
            row["report_s"] = render_bench.REPORT_TIMES_S.get(name)
            row["speedup"] = (row["report_s"] / row["times_s"]["total_s"]["median"]
                              if row["report_s"] and comparable else None)
        in_report = [r for r in rows if r["in_report"]]
        fit = lambda chosen: trace_bench.fit_exponent(  # noqa: E731
            [r["triangles"] for r in chosen], [r["times_s"]["total_s"]["median"] for r in chosen])
        out["devices"][device_id] = {"rows": rows, "alpha": fit(in_report),
                                     "alpha_with_extra": fit(rows) if len(rows) > len(in_report)
                                     else None}
    return out


# ---------------------------------------------------------------- 3./4. tracing

class OurBuilder(trace_bench.OurDevice):
    """One device and one builder as a trace participant ("pocl:0" for
    HLBVH, "pocl:0 lbvh" for LBVH); keeps each traced tree's stats."""

    def __init__(self, device, builder: str):
        super().__init__(device)
        self.device_id, self.builder = device.id, builder
        if builder != "hlbvh":
            self.name = f"{device.id} {builder}"
            self.label = f"{self.label}, {builder}"
        self.trees: dict[str, dict] = {}

    def describe(self) -> dict:
        return {**super().describe(), "device": self.device_id, "builder": self.builder}

    def build(self, case) -> float:
        if self.builder == "hlbvh":
            seconds = super().build(case)  # takes the scene load_scene built, if any
        else:
            elapsed = stopwatch()
            self.scene = Scene(case.meshes, device=self.device_id, builder=self.builder)
            seconds = elapsed()
        stats = self.scene.stats
        self.trees[case.name] = {key: stats[key] for key in ("triangles", "nodes", "leaves",
                                                             "depth", "sah_cost")}
        return seconds


def build_times(participants: list, case, repeats: int, errors: list, bar=None) -> dict:
    """Seconds each participant takes to build its structure over the case's
    arrays: {name: median (min, max)} of ``repeats`` builds after a warm-up,
    in rounds of one build each, as bench_case times queries."""
    seconds: dict[str, list] = {p.name: [] for p in participants}
    alive = list(participants)
    for run in range(repeats + 1):
        for participant in list(alive):
            try:
                built = participant.build(case)
                if run:
                    seconds[participant.name].append(built)
            except Exception as error:
                errors.append(_failure(f"build times {case.name} {participant.name}", error))
                alive.remove(participant)
            finally:
                participant.close()
                gc.collect()
        if bar is not None:
            bar.update()
    return {p.name: summary(seconds[p.name]) for p in alive if seconds[p.name]}


def bench_trace_scene(name: str, devices: list, peers: list, config: Config, errors: list,
                      show: bool) -> dict:
    """Every device with both builders, and every peer, on the same rays."""
    tconfig = trace_bench.Config(meshes=(), scene=name, resolutions=(config.trace_resolution,),
                                 incoherent_rays=config.incoherent_rays, repeats=config.repeats,
                                 scaling=(), scaling_resolution=config.trace_resolution)
    ours = [OurBuilder(d, b) for b in BUILDERS for d in devices]
    participants = ours + peers  # bench_case times them round-robin: LBVH and HLBVH alike
    workload_count = len(tconfig.resolutions) + 1  # and the incoherent rays
    with progress(1 + workload_count + config.repeats + 1, f"trace {name}", show) as bar:
        bar.set_postfix_str(f"loading {name}")
        case = (trace_bench.scene_file_case(name, devices[0].id) if name.endswith(".toml")
                else trace_bench.mesh_case(name))
        workloads = case.workloads(tconfig)
        bar.update()
        result = trace_bench.bench_case(case, workloads, participants, config.repeats, bar)
        case.built.clear()
        bar.set_postfix_str(f"{name}: build times")
        result["build_times_s"] = build_times(
            [p for p in participants if p.name not in result["errors"]], case, config.repeats,
            errors, bar)
    for participant, error in result["errors"].items():
        errors.append({"where": f"trace {name} {participant}", "error": error})
    result["trees"] = {p.name: p.trees[case.name] for p in ours if case.name in p.trees}
    result["participants"] = {p.name: p.describe() for p in participants}
    for workload in result["workloads"]:
        figures = "  ".join(f"{n} {r['intersect_mrays']['median']:.1f}"
                            for n, r in workload["results"].items())
        _say(f"  {name} {workload['name']}, closest hit Mrays/s: {figures}")
    return result


def tree_quality(suite: dict) -> dict:
    """LBVH against HLBVH per device and traced scene: the tree's stats, its
    build time (section 1, when the scene was built there) and closest-hit
    throughput per workload, from the call's wall time ("mrays") and from
    the kernels' device time alone ("kernel_mrays", {median, min, max}): the
    tree's own effect, without the host's share of a call."""
    out = {}
    for device_id in suite["devices"]:
        rows = []
        for scene in suite["trace"]["scenes"]:
            for builder in BUILDERS:
                name = device_id if builder == "hlbvh" else f"{device_id} {builder}"
                tree = scene["trees"].get(name)
                if tree is None:
                    continue
                built = next((r for r in suite["build"].get(device_id, [])
                              if r["case"] == scene["name"] and r["builder"] == builder), None)
                traced = [w for w in scene["workloads"] if name in w["results"]]
                rows.append({
                    "scene": scene["name"], "builder": builder, "participant": name, **tree,
                    "build_ms": built["times_ms"]["wall"] if built else None,
                    "mrays": {w["name"]: w["results"][name]["intersect_mrays"] for w in traced},
                    "kernel_mrays": {w["name"]: _rates(w["rays"],
                                                       w["results"][name]["intersect_kernel_s"])
                                     for w in traced if w["results"][name]["intersect_kernel_s"]}})
        for row in rows:  # HLBVH over LBVH of the same scene
            other = next((r for r in rows if r["scene"] == row["scene"] and r["builder"] == "lbvh"),
                         None)
            if row["builder"] == "hlbvh" and other:
                row["vs_lbvh"] = {"sah_cost": row["sah_cost"] / other["sah_cost"],
                                  "nodes": row["nodes"] / other["nodes"]}
                for key in ("mrays", "kernel_mrays"):
                    row["vs_lbvh"][key] = {w: row[key][w]["median"] / other[key][w]["median"]
                                           for w in row[key] if w in other[key]}
        out[device_id] = rows
    return out


def _rates(rays: int, seconds: dict) -> dict:
    """Mrays/s {median, min, max} from a {median, min, max} of seconds."""
    return {"median": rays / seconds["median"] / 1e6, "min": rays / seconds["max"] / 1e6,
            "max": rays / seconds["min"] / 1e6}


def compile_seconds(builds: list[dict], renders: list[dict]) -> dict:
    """Seconds a device spent compiling (or loading from the on-disk caches)
    the kernels at their first use in this process: per builder, its first
    build case's first build minus its median rebuild; for rendering, the
    1x1 render of the first scene rendered.  None where not measured."""
    firsts: dict[str, dict] = {}
    for r in builds:
        firsts.setdefault(r["builder"], r)
    build = {builder: max(0.0, r["first_build_ms"]["wall"] - r["times_ms"]["wall"]["median"]) / 1e3
             for builder, r in firsts.items()}
    render = renders[0]["compile_s"]["render"] if renders else None
    return {"build": build or None, "render": render}


# ---------------------------------------------------------------- the suite

def run_suite(config: Config, devices: str | None = None, peers=None, command: str = "",
              show_progress: bool = True) -> dict:
    """Runs every section; returns the suite's results (what suite.json holds)."""
    elapsed = stopwatch()
    quiet_compiler_warnings()
    load_start = list(os.getloadavg())
    chosen, skipped = pick_devices(devices if devices is not None else config.devices)
    for s in skipped:
        _say(f"skipping {s['device']}: {s['problem']}")
    if not chosen:
        raise SystemExit("no working OpenCL device to benchmark")
    available, missing = trace_bench.load_peers(config.peers if peers is None else peers)
    machine = machine_info()
    suite = {
        "command": command, "mode": config.mode, "config": asdict(config),
        "date": time.strftime("%Y-%m-%d %H:%M %Z"), "machine": machine,
        "loadavg_start": load_start,
        "devices": {d.id: {"name": d.name, "platform": d.platform, "driver": d.driver_version,
                           "compute_units": d.compute_units, "type": d.type,
                           "global_mem_size": d.global_mem_size} for d in chosen},
        "skipped_devices": skipped,
        "peers": {p.name: p.describe() for p in available + missing},
        "embree_threads": trace_bench.EMBREE_THREADS,
        "build": {}, "errors": [],
    }
    _say(f"machine: {machine['processor']}, {machine['cpus']} logical CPUs; "
         f"load average {', '.join(f'{x:.2f}' for x in load_start)}")
    for d in chosen:
        _say(f"device {d.id}: {d.name} [{d.platform}], driver {d.driver_version}, "
             f"{d.compute_units} compute units")
    _say("peers: " + (", ".join(f"{p.name} {p.version}" for p in available) or "none")
         + "".join(f"; {p.name} missing ({p.problem})" for p in missing))

    errors = suite["errors"]
    images: dict = {}
    table_rows, reference_rows = {}, {}
    stages = []
    for d in chosen:
        stages += [
            (f"builds {d.id}", lambda d=d: suite["build"].__setitem__(
                d.id, bench_builds(d.id, config, errors, show_progress))),
            (f"report's table {d.id}", lambda d=d: table_rows.__setitem__(d.id, bench_renders(
                d.id, config.table_scenes + config.extra_table_scenes, config.table_resolution,
                config.repeats, images, errors, show_progress, "table"))),
            (f"reference {d.id}", lambda d=d: reference_rows.__setitem__(d.id, bench_renders(
                d.id, (config.reference_scene,), config.reference_resolution,
                config.reference_repeats, images, errors, show_progress, "reference"))),
        ]
    traced = []
    for name in config.trace_scenes:
        stages.append((f"trace {name}", lambda name=name: traced.append(bench_trace_scene(
            name, chosen, available, config, errors, show_progress))))

    with progress(len(stages), "bench suite", show_progress) as bar:
        for label, stage in stages:
            bar.set_postfix_str(label)
            _say(f"{label} ...")
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
        seconds = result["times_s"]["total_s"]["median"]
        result["speedup"] = (render_bench.REPORT_REFERENCE_S / seconds
                             if result["scene"] == "reference.toml" else None)
    suite["trace"] = {"resolution": list(config.trace_resolution),
                      "incoherent_rays": config.incoherent_rays, "seed": trace_bench.Config.seed,
                      "reference_participant": trace_bench.REFERENCE, "scenes": traced}
    suite["tree_quality"] = tree_quality(suite)
    suite["loadavg_end"] = list(os.getloadavg())
    suite["peak_rss_bytes"] = peak_rss_bytes()
    suite["elapsed_s"] = elapsed()
    return suite


def main(argv=None) -> dict:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = argparse.ArgumentParser(
        prog="python -m bench",
        description="hlbvh_cl's benchmark suite: every device and peer, the original report's "
                    "table reproduced; writes bench/RESULTS.md, bench/results/suite.json and "
                    "plots.")
    parser.add_argument("--quick", action="store_true",
                        help="a smaller configuration: under 2 minutes on 2 cores")
    parser.add_argument("--tiny", action="store_true", help=argparse.SUPPRESS)  # the test's
    parser.add_argument("--devices", default=None,
                        help="comma-separated device ids or names (default: every working device)")
    parser.add_argument("--peers", default=None,
                        help=f"comma-separated peers (default: {','.join(trace_bench.PEERS)}; "
                             f"'' for none)")
    parser.add_argument("--out", type=Path, default=BENCH / "results",
                        help="folder of suite.json and the plots (default: bench/results)")
    parser.add_argument("--markdown", type=Path, default=None,
                        help="RESULTS.md to write (default: bench/RESULTS.md, or OUT/RESULTS.md "
                             "when --out is given)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars on stderr")
    args = parser.parse_args(argv)
    config = TINY if args.tiny else QUICK if args.quick else FULL
    markdown = args.markdown or (BENCH / "RESULTS.md" if args.out == BENCH / "results"
                                 else args.out / "RESULTS.md")
    peers = None if args.peers is None else [p.strip() for p in args.peers.split(",") if p.strip()]
    command = " ".join(["python -m bench", *argv])

    suite = run_suite(config, args.devices, peers, command, show_progress=not args.no_progress)
    written = report.write_all(suite, args.out, markdown)
    print()
    print(report.summary_text(suite))
    print(f"\nwrote {', '.join(str(p) for p in written)} in {suite['elapsed_s'] / 60:.1f} min")
    return suite


if __name__ == "__main__":
    main()
