"""Path-traced samples per second: ours on each CPU runtime against Mitsuba 3's path integrator on the same XML file, in one run.

Scenes (both renderers read the same Mitsuba XML file), at 1280x720 with
max depth 8, as issue 55 asks:
  cornell    scenes/cornell_box.xml (24 triangles and a glass ball, an
             analytic sphere in both renderers)
  materials  scenes/materials.toml's meshes, lights and materials written as
             XML (its meshes as PLY files, in place)

Each round renders every scene once on every device and once in Mitsuba
(llvm_ad_rgb, or the --mitsuba variant, where it runs, else scalar_rgb; in a
child process, since the LLVM variant can abort a process on some hosts), in
turn: a burst of load falls on all alike.  A render's time is its wall time
after a warm-up render at the same spp that compiles everything (Mitsuba's
JIT included: its CUDA variant compiles a kernel per spp; its wall time is
mi.render plus the image's numpy copy, RENDERING.md).  Samples per second =
width x height x spp / seconds.

LuxCore's PATHCPU (bench/luxcore.py, where pyluxcore imports; else the bench
says it is skipped) renders the same scenes at the same size, spp and depth
on 2 threads, in a child process too, in the same rounds.  Its time is the
wall time from its session's Start returning (its scene compiled and BVH
built) until the last sample is done, polled every 2 ms: like ours and
Mitsuba's, a render of a built scene.  Each scene's image means (linear,
over pixels and channels) are printed side by side as a translation check,
and each of our renders' device time per stage (Renderer.stats: closest
hits, shading, shadow rays, ...) as a share of its total, and the bounce
stages' shares depth by depth (Renderer.stats["depths"]), with the paths
each depth shaded, the shadow rays they cast, and the rates at which
closest hits and shadow rays were traced there: where the next speed-up
must come from.

Equal-time quality: a reference of REFERENCE_SPP samples per pixel by
Mitsuba, then each renderer for the time Mitsuba takes for EQUAL_TIME_SPP,
as measured seed by seed after a warm-up render at that spp (ours with that
time budget, LuxCore at the spp its measured rate fits in it), each scored
by relMSE = mean((image - reference)^2 / (reference^2 +
0.01)) over pixels and channels, averaged over renders with each of
EQUAL_TIME_SEEDS.  The reference is Mitsuba's own: a bias of ours against
Mitsuba counts against us.

On a GPU, Mitsuba's CUDA variant renders the same files on the same card:

    python -m bench.path [--quick] [--devices pocl,intel] [--rounds 3]
    python -m bench.path --devices nvidia --mitsuba cuda_ad_rgb

Where the gap lies, bounce by bounce (--depths 1,2,3,8): instead of the
above, each scene is rendered at each of those max depths, ours and
Mitsuba's in turn as above, and the table gives both times, the ratio of
samples per second, and what each depth added to the one before (max depth
1: the camera rays and the light they see; 2: the first vertex's light
sample and BSDF sample, and the bounce's closest hit; ...).  Our stage times
are kept per depth in the JSON.  No LuxCore and no equal-time quality in
this mode:

    python -m bench.path --depths 1,2,3,8 [--rounds 5]
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hlbvh_cl.io.scenefile import load
from hlbvh_cl.io.to_mitsuba import write_xml
from hlbvh_cl.render.integrators.path import DEPTH_STAGES
from hlbvh_cl.render.renderer import STAGES as RENDER_STAGES

from . import luxcore
from .common import (BENCH, arguments, devices_or_exit, finish, machine_info, say, stopwatch,
                     summary, table)

SCENES_DIR = BENCH.parent / "scenes"

#: (width, height, spp) per scene, full and --quick.
FULL = {"cornell": (1280, 720, 4), "materials": (1280, 720, 4)}
QUICK = {"cornell": (96, 96, 2), "materials": (160, 90, 1)}

#: The path depth of every scene (the issue's: 8).
MAX_DEPTH = 8

#: Equal-time quality: the reference's spp and the budget, in Mitsuba's spp.
REFERENCE_SPP = {"full": 128, "quick": 16}
EQUAL_TIME_SPP = {"full": 8, "quick": 2}
#: and the seeds of the renders whose relMSE is averaged, each renderer's
EQUAL_TIME_SEEDS = (7, 8, 9)

#: The issue's target: at least Mitsuba's samples per second on each CPU runtime.
TARGET_RATIO = 1.0

#: A Mitsuba child's start: the first of the variants in argv that sets,
#: announced as a JSON line; the child's requests follow (MitsubaChild's
#: below; bench/depth_rays.py's).
CHILD_START = r"""
import json, sys, time
import numpy as np
import mitsuba as mi
for variant in sys.argv[1:]:
    try:
        mi.set_variant(variant)
        break
    except Exception:
        continue
print(json.dumps({"variant": mi.variant()}), flush=True)
"""

_CHILD = CHILD_START + r"""
scenes, warm = {}, set()
for line in sys.stdin:
    name, path, width, height, spp, seed, out = line.split()
    key = (path, width, height)
    if key not in scenes:
        scenes[key] = mi.load_file(path, res_x=int(width), res_y=int(height))
    if out == "-" and (key, spp) not in warm:
        # a timed render: compile first (cuda_ad_rgb's kernel depends on spp)
        np.asarray(mi.render(scenes[key], spp=int(spp), seed=int(seed)))
        warm.add((key, spp))
    started = time.perf_counter()
    image = np.asarray(mi.render(scenes[key], spp=int(spp), seed=int(seed)))
    seconds = time.perf_counter() - started
    if out != "-":
        np.save(out, image)
    print(json.dumps({"seconds": seconds, "mean": float(image.mean())}), flush=True)
"""


def materials_xml(folder: Path) -> Path:
    """scenes/materials.toml as Mitsuba XML (hlbvh_cl.io.to_mitsuba), max
    depth MAX_DEPTH."""
    return write_xml(SCENES_DIR / "materials.toml", folder, max_depth=MAX_DEPTH)


def cornell_xml(folder: Path) -> Path:
    """scenes/cornell_box.xml with its size as $res_x and $res_y, and max
    depth MAX_DEPTH."""
    source = SCENES_DIR / "cornell_box.xml"
    text = set_max_depth(source.read_text(), MAX_DEPTH, source)
    text = text.replace('<default name="res" value="256"/>',
                        '<default name="res_x" value="256"/>\n  '
                        '<default name="res_y" value="256"/>')
    text = text.replace('name="width" value="$res"', 'name="width" value="$res_x"')
    text = text.replace('name="height" value="$res"', 'name="height" value="$res_y"')
    path = folder / "cornell_box.xml"
    path.write_text(text)
    return path


def depth_list(text: str) -> list[int]:
    """--depths: comma-separated max depths, each a whole number >= 1, in
    increasing order (each increment is the cost of one more bounce)."""
    depths = []
    for part in text.split(","):
        part = part.strip()
        if not part.isdigit() or int(part) < 1:
            raise argparse.ArgumentTypeError(
                f"--depths: {part!r} is not a max depth (a whole number >= 1)")
        depths.append(int(part))
    if any(b <= a for a, b in zip(depths, depths[1:])):
        raise argparse.ArgumentTypeError(
            f"--depths: {text!r} must increase (e.g. 1,2,3,8)")
    return depths


_MAX_DEPTH_ELEMENT = re.compile(r'<integer name="max_depth" value="-?\d+"/>')


def set_max_depth(text: str, depth: int, path: Path) -> str:
    """The XML scene ``text`` (read from ``path``) with its path
    integrator's max_depth set to ``depth``."""
    if len(_MAX_DEPTH_ELEMENT.findall(text)) != 1:
        raise ValueError(f"{path}: expected one <integer name=\"max_depth\" .../> element")
    return _MAX_DEPTH_ELEMENT.sub(f'<integer name="max_depth" value="{depth}"/>', text)


def with_max_depth(path: Path, depth: int) -> Path:
    """A copy of the scene file at ``path`` whose path integrator has
    max_depth ``depth``, beside it (for Mitsuba: ours takes max_depth as an
    option)."""
    out = path.with_name(f"{path.stem}_depth{depth}{path.suffix}")
    out.write_text(set_max_depth(path.read_text(), depth, path))
    return out


#: Untimed rounds before --depths times any: the first compiles ours and
#: Mitsuba's kernels, and in the second Mitsuba's turn from one depth's
#: scene to the next renders far slower, once (seen with llvm_ad_rgb, on
#: every scene but the round's last; later rounds do not).
SWEEP_WARM_ROUNDS = 2


def depth_sweep(args, devices: list[str], paths: dict, sizes: dict, child) -> dict:
    """The --depths mode (the module's docstring): per scene and max depth,
    each device's and Mitsuba's render times over args.rounds rounds, taken
    in turn, with their ratio and our stage medians; per scene, a table row
    per depth and device."""
    out, rows = {}, []
    for name, path in paths.items():
        width, height, spp = sizes[name]
        samples = width * height * spp
        files = {d: with_max_depth(Path(path), d) for d in args.depths}
        ours = {}
        for device in devices:
            loaded = load(path, device, defaults={"res_x": width, "res_y": height})
            ours[device] = (loaded, loaded.renderer())
        times = {(d, who): [] for d in args.depths for who in [*devices, "mitsuba"]}
        stages = {(d, device): [] for d in args.depths for device in devices}
        for round_ in range(SWEEP_WARM_ROUNDS + args.rounds):
            timed = round_ >= SWEEP_WARM_ROUNDS
            for depth in args.depths:
                for device in devices:
                    loaded, renderer = ours[device]
                    started = time.perf_counter()
                    renderer.render(loaded.camera, width, height, hdr=True,
                                    **{**loaded.options, "spp": spp, "max_depth": depth})
                    if timed:
                        times[depth, device].append(time.perf_counter() - started)
                        stages[depth, device].append(renderer.stats["times_ms"])
                answer = child.render(name, str(files[depth]), width, height, spp)
                if timed:
                    times[depth, "mitsuba"].append(answer["seconds"])
        entry = {}
        for depth in args.depths:
            theirs = summary(times[depth, "mitsuba"])
            entry[depth] = {"mitsuba_seconds": theirs}
            for device in devices:
                seconds = summary(times[depth, device])
                entry[depth][device] = {"seconds": seconds,
                                        "msamples_per_s": samples / seconds["median"] / 1e6,
                                        "ratio_to_mitsuba": theirs["median"] / seconds["median"],
                                        "stages_ms": stage_medians(stages[depth, device])}
        for device in devices:
            before = None
            for depth in args.depths:
                mine = entry[depth][device]["seconds"]["median"]
                theirs = entry[depth]["mitsuba_seconds"]["median"]
                added = ("", "") if before is None else (
                    f"{1e3 * (mine - before[0]):+.0f}", f"{1e3 * (theirs - before[1]):+.0f}")
                rows.append([name, depth, device, f"{1e3 * mine:.0f}", f"{1e3 * theirs:.0f}",
                             f"{entry[depth][device]['ratio_to_mitsuba']:.2f}x", *added])
                before = (mine, theirs)
        out[name] = {"samples": samples, "depths": entry}
    print(table(["scene", "max depth", "device", "ours (ms)", "Mitsuba (ms)", "ratio",
                 "ours added (ms)", "Mitsuba added (ms)"], rows,
                title="render time by max depth (median of the rounds); added: over the "
                      "depth before"))
    return out


def llvm_path() -> str | None:
    """The newest libLLVM 19 or later on the system (setup_peers.sh installs
    one where LLVM 15 cannot compile Mitsuba's path integrator), or None."""
    import glob
    found = sorted(glob.glob("/usr/lib/*/libLLVM.so.[12][0-9]*")
                   + glob.glob("/usr/lib/*/libLLVM-[12][0-9].so"))
    return found[-1] if found else None


def start_mitsuba(script: str, variants: tuple[str, ...]) -> tuple[subprocess.Popen, str]:
    """A child process running ``script`` (which begins with CHILD_START)
    with the libLLVM that llvm_path finds, and the variant it set."""
    import os
    env = dict(os.environ)
    if llvm_path() and "DRJIT_LIBLLVM_PATH" not in env:
        env["DRJIT_LIBLLVM_PATH"] = llvm_path()
    process = subprocess.Popen([sys.executable, "-c", script, *variants], stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, text=True, env=env)
    line = process.stdout.readline()
    if not line:
        raise RuntimeError("Mitsuba's child process died as it started")
    return process, json.loads(line)["variant"]


class MitsubaChild:
    """Mitsuba 3 in a child process that renders on request (one JSON line
    per render); ``variant`` is the one it runs."""

    def __init__(self, variants: tuple[str, ...]):
        self.process, self.variant = start_mitsuba(_CHILD, variants)

    def render(self, name, path, width, height, spp, seed=0, out="-") -> dict:
        self.process.stdin.write(f"{name} {path} {width} {height} {spp} {seed} {out}\n")
        self.process.stdin.flush()
        line = self.process.stdout.readline()
        if not line:
            raise RuntimeError(f"Mitsuba ({self.variant}) died rendering {name}")
        return json.loads(line)

    def close(self) -> None:
        self.process.stdin.close()
        self.process.wait()


def mitsuba_child(paths: dict, variant: str = "llvm_ad_rgb") -> MitsubaChild:
    """A Mitsuba child in ``variant`` if it renders every scene (its LLVM
    can abort the process; cuda_ad_rgb needs a GPU and OptiX), else in
    scalar_rgb."""
    child = MitsubaChild((variant, "scalar_rgb"))
    if child.variant != variant:
        say(f"Mitsuba's {variant} does not start here; timing {child.variant}")
    try:
        for name, path in paths.items():
            child.render(name, path, 8, 8, 1)
        return child
    except (RuntimeError, ValueError):
        say(f"Mitsuba's {child.variant} failed here; timing scalar_rgb")
        child.close()
        return MitsubaChild(("scalar_rgb",))


def stage_medians(rounds: list[dict]) -> dict:
    """The median over rounds of each stage's device time in a render, in
    milliseconds (Renderer.stats["times_ms"]: the stages, and their
    "total"), which says where the next speed-up must come from."""
    return {stage: float(np.median([r[stage] for r in rounds]))
            for stage in (*RENDER_STAGES, "total")}


def depth_medians(rounds: list[dict]) -> dict:
    """The median over rounds of Renderer.stats["depths"] (the paths each
    depth shaded and each bounce stage's milliseconds there), depth by
    depth, over the depths the longest round reached (0 past a round's)."""
    depths = max(len(r["paths"]) for r in rounds)
    return {key: [float(np.median([(r[key] + [0] * depths)[d] for r in rounds]))
                  for d in range(depths)] for key in rounds[0]}


def depth_rows(name: str, device: str, depths: dict, total_ms: float) -> list[list]:
    """A table's rows of one render's depths: the paths each shaded and the
    shadow rays they cast, each bounce stage's time there as a share of the
    render's device total, and the rates at which the closest hits (the
    paths' rays: depth 0's are the camera's) and the shadow rays were
    traced there, in Mrays/s of device time."""
    def rate(rays: float, ms: float) -> str:
        return f"{rays / ms * 1e-3:.1f}" if rays > 0 and ms > 0 else "-"

    return [[name, device, d, int(depths["paths"][d]), int(depths["shadow_rays"][d])]
            + [f"{depths[stage][d] / total_ms:.1%}" for stage in DEPTH_STAGES]
            + [rate(depths["paths"][d], depths["closest"][d]),
               rate(depths["shadow_rays"][d], depths["occluded"][d])]
            for d in range(len(depths["paths"])) if depths["paths"][d] > 0]


def relmse(image: np.ndarray, reference: np.ndarray) -> float:
    """Mean of (image - reference)^2 / (reference^2 + 0.01) over pixels and
    channels (the 0.01 keeps black pixels from dominating)."""
    image, reference = np.asarray(image, np.float64), np.asarray(reference, np.float64)
    return float(np.mean((image - reference) ** 2 / (reference ** 2 + 1e-2)))


def rr_depth_of(ours, name, devices) -> int:
    """The scene's Russian-roulette depth as our loader read it (LuxCore is
    told the same)."""
    return ours[name, devices[0]][0].options.get("rr_depth", 5)


def equal_time(child, lux, ours, paths, sizes, devices, times, folder, kind) -> dict:
    """Per scene: each renderer's relMSE against a high-spp Mitsuba reference
    after the time Mitsuba takes for EQUAL_TIME_SPP (the module's
    definitions), the mean over renders with each of EQUAL_TIME_SEEDS (one
    render's relMSE swings with its few brightest outliers), the renderers
    taking turns seed by seed, each seed's budget the time Mitsuba's render
    of it took (not its timed rounds' per-sample rate times EQUAL_TIME_SPP:
    Mitsuba's time grows slower than its spp, and the Cornell box's 8 spp
    took 0.83x twice its 4); LuxCore (``lux``, unless None) at the spp its
    timed rounds say fit in that time (its relMSE holds its translation's
    bias too: bench/luxcore.py)."""
    out = {}
    for name, path in paths.items():
        width, height, spp = sizes[name]
        reference_spp, budget_spp = REFERENCE_SPP[kind], EQUAL_TIME_SPP[kind]
        say(f"{name}: Mitsuba reference at {reference_spp} spp")
        child.render(name, path, width, height, reference_spp, seed=1000,
                     out=str(folder / "reference.npy"))
        reference = np.load(folder / "reference.npy")[..., :3]
        child.render(name, path, width, height, budget_spp)  # warm-up: its JIT at this spp
        seeds = {who: {"spp": [], "relmse": []}
                 for who in ["mitsuba", *devices] + (["luxcore"] if lux is not None else [])}
        budgets = []
        for seed in EQUAL_TIME_SEEDS:
            budget = child.render(name, path, width, height, budget_spp, seed=seed,
                                  out=str(folder / "equal.npy"))["seconds"]
            budgets.append(budget)
            lux_spp = (max(1, int(budget * spp / summary(times[name, "luxcore"])["median"]))
                       if lux is not None else 0)
            seeds["mitsuba"]["spp"].append(budget_spp)
            seeds["mitsuba"]["relmse"].append(
                relmse(np.load(folder / "equal.npy")[..., :3], reference))
            for device in devices:
                loaded, renderer, options = ours[name, device]
                image = renderer.render(loaded.camera, width, height, hdr=True,
                                        **{**options, "spp": None, "seed": seed},
                                        time_budget=budget)
                # the budget's last round may cover the image's first rows only
                seeds[device]["spp"].append(renderer.stats["mean_spp"])
                seeds[device]["relmse"].append(relmse(image, reference))
            if lux is not None:
                lux.render(path, width, height, lux_spp, MAX_DEPTH,
                           rr_depth_of(ours, name, devices), seed=seed,
                           out=str(folder / "luxcore.npy"))
                seeds["luxcore"]["spp"].append(lux_spp)
                seeds["luxcore"]["relmse"].append(
                    relmse(np.load(folder / "luxcore.npy"), reference))
        renders = {who: {"spp": round(float(np.mean(r["spp"])), 2),
                         "relmse": float(np.mean(r["relmse"])), "relmse_seeds": r["relmse"]}
                   for who, r in seeds.items()}
        out[name] = {"seconds": float(np.median(budgets)), "seconds_seeds": budgets,
                     "reference_spp": reference_spp,
                     "seeds": list(EQUAL_TIME_SEEDS), "renders": renders}
    return out


def main(argv=None) -> dict:
    args = arguments(__doc__.splitlines()[0], argv,
                     (["--rounds"], {"type": int, "default": 3, "help": "timed rounds"}),
                     (["--mitsuba"], {"default": "llvm_ad_rgb",
                                      "help": "Mitsuba's variant (cuda_ad_rgb on a GPU)"}),
                     (["--depths"], {"type": depth_list, "default": None,
                                     "help": "instead, time each scene at these max depths "
                                             "(e.g. 1,2,3,8): where the gap to Mitsuba lies"}))
    elapsed = stopwatch()
    sizes = QUICK if args.quick else FULL
    devices = [d.id for d in devices_or_exit(args.devices or "pocl,intel")]
    say(f"devices: {', '.join(devices)}")
    results = {"command": " ".join(["python -m bench.path",
                                     *(sys.argv[1:] if argv is None else argv)]),
               "machine": machine_info(), "devices": devices, "sizes": sizes,
               "rounds": args.rounds, "scenes": {}}
    with tempfile.TemporaryDirectory() as temporary:
        folder = Path(temporary)
        paths = {"cornell": cornell_xml(folder), "materials": materials_xml(folder)}
        child = mitsuba_child(paths, args.mitsuba)
        results["mitsuba"] = child.variant
        if args.depths:
            results["max_depths"] = args.depths
            results["depth_sweep"] = depth_sweep(args, devices, paths, sizes, child)
            child.close()
            return finish(results, "path_depths", args, elapsed)
        lux, lux_problem = luxcore.start_child(paths, MAX_DEPTH)
        results["luxcore"] = f"skipped: {lux_problem}" if lux_problem else "PATHCPU"
        if lux_problem:
            say(f"LuxCore PATHCPU: skipped ({lux_problem})")
        ours = {}
        for name, path in paths.items():
            width, height, spp = sizes[name]
            for device in devices:
                loaded = load(path, device, defaults={"res_x": width, "res_y": height})
                renderer = loaded.renderer()
                options = {**loaded.options, "spp": spp, "max_depth": MAX_DEPTH}
                renderer.render(loaded.camera, 8, 8, **options)  # compiles
                ours[name, device] = (loaded, renderer, options)
        times = {key: [] for key in [(n, d) for n in paths for d in devices]
                 + [(n, "mitsuba") for n in paths]
                 + [(n, "luxcore") for n in paths if lux is not None]}
        means = {key: [] for key in times}
        stages = {key: [] for key in ours}
        depths = {key: [] for key in ours}
        for _ in range(args.rounds):
            for name, path in paths.items():
                width, height, spp = sizes[name]
                for device in devices:
                    loaded, renderer, options = ours[name, device]
                    started = time.perf_counter()
                    image = renderer.render(loaded.camera, width, height, hdr=True, **options)
                    times[name, device].append(time.perf_counter() - started)
                    means[name, device].append(float(image.mean()))
                    stages[name, device].append(renderer.stats["times_ms"])
                    depths[name, device].append(renderer.stats["depths"])
                answer = child.render(name, path, width, height, spp)
                times[name, "mitsuba"].append(answer["seconds"])
                means[name, "mitsuba"].append(answer["mean"])
                if lux is not None:
                    answer = lux.render(path, width, height, spp, MAX_DEPTH,
                                        rr_depth_of(ours, name, devices))
                    times[name, "luxcore"].append(answer["seconds"])
                    means[name, "luxcore"].append(answer["mean"])
        quality = equal_time(child, lux, ours, paths, sizes, devices, times, folder,
                             "quick" if args.quick else "full")
        child.close()
        if lux is not None:
            lux.close()
    rows, mean_rows, stage_rows, bounce_rows = [], [], [], []
    for name in paths:
        width, height, spp = sizes[name]
        samples = width * height * spp
        theirs = samples / summary(times[name, "mitsuba"])["median"]
        entry = {"samples": samples, "mitsuba_msamples_per_s": theirs / 1e6,
                 "mitsuba_mean": summary(means[name, "mitsuba"])["median"],
                 "mitsuba_seconds": summary(times[name, "mitsuba"])}
        lux_rate = None
        if lux is not None:
            lux_rate = samples / summary(times[name, "luxcore"])["median"]
            entry["luxcore"] = {"msamples_per_s": lux_rate / 1e6,
                                "mean": summary(means[name, "luxcore"])["median"],
                                "seconds": summary(times[name, "luxcore"])}
        for device in devices:
            rate = samples / summary(times[name, device])["median"]
            entry[device] = {"msamples_per_s": rate / 1e6, "ratio_to_mitsuba": rate / theirs,
                             "mean": summary(means[name, device])["median"],
                             "seconds": summary(times[name, device]),
                             "stages_ms": stage_medians(stages[name, device]),
                             "depths": depth_medians(depths[name, device])}
            bounce_rows += depth_rows(name, device, entry[device]["depths"],
                                      entry[device]["stages_ms"]["total"])
            stage_rows.append([name, device] + [
                f"{entry[device]['stages_ms'][stage] / entry[device]['stages_ms']['total']:.0%}"
                for stage in RENDER_STAGES] + [f"{entry[device]['stages_ms']['total']:.0f}",
                                               f"{1e3 * entry[device]['seconds']['median']:.0f}"])
            rows.append([name, f"{width}x{height}, {spp} spp", device, f"{rate / 1e6:.2f}",
                         f"{theirs / 1e6:.2f}", f"{rate / theirs:.2f}x"])
            if lux_rate is not None:
                entry[device]["ratio_to_luxcore"] = rate / lux_rate
                rows[-1] += [f"{lux_rate / 1e6:.2f}", f"{rate / lux_rate:.2f}x"]
        if lux is not None:
            mean_rows.append([name] + [f"{entry[d]['mean']:.4f}" for d in devices]
                             + [f"{entry['mitsuba_mean']:.4f}", f"{entry['luxcore']['mean']:.4f}"])
        entry["equal_time"] = quality[name]
        results["scenes"][name] = entry
    lux_columns = ["LuxCore PATHCPU", "ratio to LuxCore"] if lux is not None else []
    print(table(["scene", "size", "device", "ours (Msamples/s)",
                 f"Mitsuba {results['mitsuba']}", "ratio", *lux_columns], rows,
                title="path tracing, samples per second (median of the rounds)"))
    # a wall far above the device total is a render whose device waits on
    # the host (a GPU's, whose launches are short beside their host work)
    print(table(["scene", "device", *RENDER_STAGES, "device total (ms)", "wall (ms)"],
                stage_rows, title="where our render's device time goes (median of the rounds)"))
    print(table(["scene", "device", "depth", "paths", "shadow rays", *DEPTH_STAGES,
                 "closest (Mrays/s)", "shadow (Mrays/s)"], bounce_rows,
                title="and by depth (depth 0's closest hits: the camera rays'): stage times "
                      "as shares of the device total, and ray rates"))
    if lux is not None:  # the translation's check (bench/luxcore.py)
        print(table(["scene", *devices, "Mitsuba", "LuxCore"], mean_rows,
                    title="image means (linear; median of the rounds)"))
    rows = [[name, q["seconds"] and f"{q['seconds']:.2f} s", who, str(r["spp"]),
             f"{r['relmse']:.4g}", " ".join(f"{x:.4g}" for x in r["relmse_seeds"])]
            for name, q in quality.items() for who, r in q["renders"].items()]
    print(table(["scene", "time", "renderer", "spp (mean)", "relMSE (mean)", "per seed"], rows,
                title=f"equal time: relMSE against Mitsuba at "
                      f"{quality[next(iter(quality))]['reference_spp']} spp, "
                      f"seeds {', '.join(map(str, EQUAL_TIME_SEEDS))}"))
    return finish(results, "path", args, elapsed)


if __name__ == "__main__":
    main()
