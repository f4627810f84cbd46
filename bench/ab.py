"""A/B of two checkouts' closest hits, interleaved in one run: a speed claim's figure.

    python -m bench.ab BASE CHANGE [--devices pocl,intel] [--rounds 4] [--scene reference.toml]
                       [--quick] [--compact] [--in-process [--renders cornell,materials]]

BASE and CHANGE are checkouts of this repository (git worktrees, say).  The
workloads are bench.trace's on the scene file: primary rays of its camera
at 2048x1536, 1M incoherent rays and the diffuse bounces of the camera's
hits (512x384 and 100K with --quick), made once by BASE's code on the first
device and given to both checkouts as the same float32 arrays.

Each round runs each checkout, for each device, in a child process of its
own (its import picks its code), base first on even rounds and change first
on odd ones, so that a burst of load from other processes falls on both
alike; a child builds the scene, warms each workload up, then keeps the
best of CALLS calls (numpy in and out, as bench.trace times them).  The
summary per workload and device is the median over rounds of each one's
rays per second and of the rounds' change / base ratios, with their min and
max.  The first round's hits (t, geom_id, prim_id, u, v) are compared: a
change of speed alone leaves them identical, and the table says whether
they are.  With --compact both checkouts trace the scene's compact tree
(Scene(..., compact=True), built from its meshes as bench.trace's
--compact builds it).

With --in-process, for a change of kernels alone (the checkouts' hlbvh_cl/
must be the same, byte for byte), one child per device builds the scene
twice, from each checkout's kernels (Runtime.kernel_root), and alternates
the two within each round, call by call (base first on even rounds): the
same process, host code and rays, and a burst of load lasting a call rather
than a child's life, so that the ratios spread far less.  With --renders
(in one process only) the workloads are bench.path's path renders instead
(its sizes, samples per pixel and max depth, --quick's too), timed as
samples per second, and the images compared bit for bit.
"""
from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from .common import arguments, devices_or_exit, finish, say, stopwatch, table

#: Timed calls of each workload per child and round (after one warm-up call).
CALLS = 3

WORKLOADS = ("camera", "incoherent", "bounces")

#: The child: argv = checkout, device, scene file, workloads .npz, hits .npz or "",
#: "compact" or "".
CHILD = r"""
import json, sys, time
from pathlib import Path
import numpy as np
sys.path.insert(0, sys.argv[1])
import hlbvh_cl
if Path(hlbvh_cl.__file__).resolve().parent != Path(sys.argv[1]).resolve() / "hlbvh_cl":
    sys.exit(f"imported {hlbvh_cl.__file__}, not the checkout's: an install shadows it")
from bench.trace import scene_file_case
case = scene_file_case(sys.argv[3], sys.argv[2])
scene = case.built[sys.argv[2]][0]
if sys.argv[6] == "compact":
    scene = hlbvh_cl.Scene(case.meshes, device=sys.argv[2], compact=True)
if getattr(scene, "compact", False) != (sys.argv[6] == "compact"):  # (checkouts before compact trees: none)
    sys.exit(f"built {scene!r}, not the tree asked for")
workloads = np.load(sys.argv[4])
rates, hits = {}, {}
for name in %(workloads)r:
    origins, directions = workloads[name + "_origins"], workloads[name + "_directions"]
    found = scene.intersect(origins, directions)
    for field in ("t", "geom_id", "prim_id", "u", "v"):
        hits[name + "_" + field] = getattr(found, field)
    best = 0.0
    for _ in range(%(calls)d):
        started = time.perf_counter()
        scene.intersect(origins, directions)
        best = max(best, len(origins) / (time.perf_counter() - started))
    rates[name] = best
if sys.argv[5]:
    np.savez(sys.argv[5], **hits)
print(json.dumps(rates))
""" % {"workloads": WORKLOADS, "calls": CALLS}

#: What both one-process children start with: argv = base checkout, change checkout,
#: device, ...; the change's code imported, the device's runtime, each role's kernels.
ONE_PROCESS = r"""
import json, sys, tempfile, time
from pathlib import Path
import numpy as np
sys.path.insert(0, sys.argv[2])
import hlbvh_cl
if Path(hlbvh_cl.__file__).resolve().parent != Path(sys.argv[2]).resolve() / "hlbvh_cl":
    sys.exit(f"imported {hlbvh_cl.__file__}, not the checkout's: an install shadows it")
from hlbvh_cl.device.runtime import runtime
device = sys.argv[3]
rt = runtime(device)
roots = {"base": Path(sys.argv[1]).resolve() / "kernels",
         "change": Path(sys.argv[2]).resolve() / "kernels"}
"""

#: The --in-process child: argv = base checkout, change checkout, device, scene file,
#: workloads .npz, hits folder, "compact" or "", rounds.  Its code and host are the
#: change checkout's; each role's scene is built, and traced, from that role's kernels.
IN_PROCESS = ONE_PROCESS + r"""
from bench.trace import scene_file_case
compact, rounds = sys.argv[7] == "compact", int(sys.argv[8])
scenes = {}
for role, root in roots.items():
    rt.kernel_root = root
    case = scene_file_case(sys.argv[4], device)
    scenes[role] = (hlbvh_cl.Scene(case.meshes, device=device, compact=True) if compact
                    else case.built[device][0])
workloads = np.load(sys.argv[5])
rates = {role: {name: [] for name in %(workloads)r} for role in roots}
for name in %(workloads)r:
    origins, directions = workloads[name + "_origins"], workloads[name + "_directions"]
    for role, root in roots.items():
        rt.kernel_root = root
        found = scenes[role].intersect(origins, directions)  # also the warm-up
        np.savez(Path(sys.argv[6]) / f"{device}-{role}-{name}.npz",
                 **{name + "_" + field: getattr(found, field)
                    for field in ("t", "geom_id", "prim_id", "u", "v")})
for round_ in range(rounds):
    for name in %(workloads)r:
        origins, directions = workloads[name + "_origins"], workloads[name + "_directions"]
        for role in (list(roots) if round_ %% 2 == 0 else list(roots)[::-1]):
            rt.kernel_root = roots[role]
            best = 0.0
            for _ in range(%(calls)d):
                started = time.perf_counter()
                scenes[role].intersect(origins, directions)
                best = max(best, len(origins) / (time.perf_counter() - started))
            rates[role][name].append(best)
print(json.dumps(rates))
""" % {"workloads": WORKLOADS, "calls": CALLS}

#: The --renders child: argv = base checkout, change checkout, device, renders
#: (comma-separated), "quick" or "full", rounds, images folder.  As IN_PROCESS, with
#: bench.path's renders; each role's renderer is made, and renders, under its kernels.
RENDERS = ONE_PROCESS + r"""
from hlbvh_cl.io.scenefile import load
from bench.path import FULL, MAX_DEPTH, QUICK, cornell_xml, materials_xml
names, rounds = sys.argv[4].split(","), int(sys.argv[6])
sizes = QUICK if sys.argv[5] == "quick" else FULL
made, rates = {}, {role: {name: [] for name in names} for role in roots}
with tempfile.TemporaryDirectory() as folder:
    for name in names:
        path = {"cornell": cornell_xml, "materials": materials_xml}[name](Path(folder))
        width, height, spp = sizes[name]
        for role, root in roots.items():
            rt.kernel_root = root
            loaded = load(path, device, defaults={"res_x": width, "res_y": height})
            options = {**loaded.options, "spp": spp, "max_depth": MAX_DEPTH}
            made[name, role] = (loaded.renderer(), loaded.camera, options)
def render(name, role):
    renderer, camera, options = made[name, role]
    width, height, _ = sizes[name]
    rt.kernel_root = roots[role]
    return renderer.render(camera, width, height, hdr=True, **options)
for name in names:
    for role in roots:
        np.save(Path(sys.argv[7]) / f"{device}-{role}-{name}.npy", render(name, role))
for round_ in range(rounds):
    for name in names:
        width, height, spp = sizes[name]
        for role in (list(roots) if round_ % 2 == 0 else list(roots)[::-1]):
            started = time.perf_counter()
            render(name, role)
            rates[role][name].append(width * height * spp / (time.perf_counter() - started))
print(json.dumps(rates))
"""

#: The renders --renders may name (bench.path's scenes).
RENDER_NAMES = ("cornell", "materials")

MAKE_WORKLOADS = r"""
import sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from bench.trace import scene_file_case
case = scene_file_case(sys.argv[3], sys.argv[2])
size, rays = (512, 384) if sys.argv[5] == "quick" else (2048, 1536), int(sys.argv[6])
camera, incoherent, bounces = case.workloads([size], rays, 1, bounce_device=sys.argv[2])
np.savez(sys.argv[4], **{name + "_" + part: getattr(w, part) for name, w in
                         zip(%(workloads)r, (camera, incoherent, bounces))
                         for part in ("origins", "directions")})
""" % {"workloads": WORKLOADS}


def child(code: str, *args) -> str:
    """Runs ``code`` in a new interpreter with ``args``; its last stdout line."""
    done = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True,
                          text=True)
    if done.returncode:
        sys.exit(f"bench.ab: a child failed ({' '.join(map(str, args[:3]))}):\n"
                 f"{done.stderr[-3000:]}")
    return done.stdout.strip().splitlines()[-1] if done.stdout.strip() else ""


def identical(base: Path, change: Path, name: str) -> bool:
    a, b = np.load(base), np.load(change)
    return all(np.array_equal(a[f"{name}_{field}"], b[f"{name}_{field}"])
               for field in ("t", "geom_id", "prim_id", "u", "v"))


def host_difference(base: Path, change: Path) -> str | None:
    """The first host module (hlbvh_cl/**/*.py) that is not the same bytes in
    both checkouts, or None: --in-process runs one checkout's host code."""
    names = sorted({path.relative_to(root).as_posix() for root in (base, change)
                    for path in (root / "hlbvh_cl").rglob("*.py")})
    for name in names:
        a, b = base / name, change / name
        if not (a.is_file() and b.is_file() and a.read_bytes() == b.read_bytes()):
            return name
    return None


def summary(device: str, name: str, base: list, change: list, same: bool) -> tuple:
    """The rounds' change / base ratios, and the table's row: the medians (in
    millions a second), the median ratio (min-max), and whether the results
    were the same."""
    ratios = [c / b for b, c in zip(base, change)]
    return ratios, [device, name, f"{np.median(base) / 1e6:.2f}", f"{np.median(change) / 1e6:.2f}",
                    f"{np.median(ratios):.3f} ({min(ratios):.3f}-{max(ratios):.3f})",
                    "yes" if same else "NO"]


def compare_renders(args, checkouts: dict, devices: list, renders: list, results: dict,
                    elapsed) -> dict:
    """--renders: each device's child (RENDERS), then its table of samples per second."""
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for device in devices:
            say(f"{device}: both checkouts' renders in one process, {args.rounds} rounds")
            found = json.loads(child(RENDERS, checkouts["base"], checkouts["change"], device,
                                     ",".join(renders), "quick" if args.quick else "full",
                                     args.rounds, folder))
            entry = results["devices"][device] = {}
            for name in renders:
                base, change = found["base"][name], found["change"][name]
                same = np.array_equal(*(np.load(Path(folder) / f"{device}-{role}-{name}.npy")
                                        for role in checkouts))
                ratios, row = summary(device, name, base, change, same)
                entry[name] = {"base_samples_per_s": base, "change_samples_per_s": change,
                               "ratios": ratios, "identical_images": same}
                rows.append(row)
    print(table(["device", "render", "base Msamples/s", "change Msamples/s",
                 "change / base (min-max)", "same image"], rows,
                title=f"A/B of path renders, {args.rounds} rounds interleaved, in one process"))
    return finish(results, "ab", args, elapsed)


def main(argv=None) -> dict:
    args = arguments(__doc__.splitlines()[0], argv,
                     (["base"], {"help": "the checkout to compare against"}),
                     (["change"], {"help": "the checkout with the change"}),
                     (["--rounds"], {"type": int, "default": 4, "help": "rounds (default 4)"}),
                     (["--scene"], {"default": "reference.toml",
                                    "help": "scene file of scenes/ (default reference.toml)"}),
                     (["--compact"], {"action": "store_true",
                                      "help": "trace compact trees (Scene(..., compact=True))"}),
                     (["--in-process"], {"action": "store_true",
                                         "help": "a change of kernels alone: both in one "
                                                 "process, alternated call by call"}),
                     (["--renders"], {"default": "",
                                      "help": "with --in-process: bench.path's path renders "
                                              "(cornell,materials) instead of closest hits"}))
    checkouts = {"base": Path(args.base).resolve(), "change": Path(args.change).resolve()}
    for role, path in checkouts.items():
        if not (path / "hlbvh_cl" / "__init__.py").is_file():
            sys.exit(f"bench.ab: {role} {path} is not a checkout of hlbvh_cl")
    if args.rounds < 1:
        sys.exit("bench.ab: --rounds must be at least 1")
    renders = [name for name in args.renders.split(",") if name]
    if renders and not args.in_process:
        sys.exit("bench.ab: --renders runs in one process: add --in-process")
    for name in renders:
        if name not in RENDER_NAMES:
            sys.exit(f"bench.ab: --renders takes {', '.join(RENDER_NAMES)}, not {name!r}")
    if args.in_process:
        differs = host_difference(checkouts["base"], checkouts["change"])
        if differs is not None:
            sys.exit(f"bench.ab: --in-process runs one host for both checkouts, and {differs} "
                     f"differs between them; leave --in-process out")
    elapsed = stopwatch()
    devices = [device.id for device in devices_or_exit(args.devices)]
    results = {"base": str(checkouts["base"]), "change": str(checkouts["change"]),
               "scene": args.scene, "rounds": args.rounds, "compact": args.compact,
               "in_process": args.in_process, "renders": renders, "devices": {}}
    if renders:
        return compare_renders(args, checkouts, devices, renders, results, elapsed)
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        workloads = folder / "workloads.npz"
        say(f"workloads of {args.scene} by {checkouts['base']} on {devices[0]}")
        child(MAKE_WORKLOADS, checkouts["base"], devices[0], args.scene, workloads,
              "quick" if args.quick else "full", 100_000 if args.quick else 1_000_000)
        rates = {(device, role): [] for device in devices for role in checkouts}
        for device in devices if args.in_process else ():
            say(f"{device}: both checkouts in one process, {args.rounds} rounds")
            found = json.loads(child(IN_PROCESS, checkouts["base"], checkouts["change"], device,
                                     args.scene, workloads, folder,
                                     "compact" if args.compact else "", args.rounds))
            for role in checkouts:
                rates[device, role] = [{name: found[role][name][round_] for name in WORKLOADS}
                                       for round_ in range(args.rounds)]
        for round_ in range(0 if args.in_process else args.rounds):
            order = list(checkouts) if round_ % 2 == 0 else list(checkouts)[::-1]
            for device in devices:
                for role in order:
                    hits = folder / f"{device}-{role}.npz" if round_ == 0 else ""
                    line = child(CHILD, checkouts[role], device, args.scene, workloads, hits,
                                 "compact" if args.compact else "")
                    rates[device, role].append(json.loads(line))
            say(f"round {round_ + 1} of {args.rounds} done")
        rows = []
        for device in devices:
            entry = results["devices"][device] = {}
            for name in WORKLOADS:
                base = [r[name] for r in rates[device, "base"]]
                change = [r[name] for r in rates[device, "change"]]
                kept = ([folder / f"{device}-{role}-{name}.npz" for role in checkouts]
                        if args.in_process else
                        [folder / f"{device}-{role}.npz" for role in checkouts])
                same = identical(*kept, name)
                ratios, row = summary(device, name, base, change, same)
                entry[name] = {"base_rays_per_s": base, "change_rays_per_s": change,
                               "ratios": ratios, "identical_hits": same}
                rows.append(row)
    print(table(["device", "workload", "base Mrays/s", "change Mrays/s",
                 "change / base (min-max)", "same hits"], rows,
                title=f"A/B on {args.scene}{' (compact trees)' if args.compact else ''}, "
                      f"{args.rounds} rounds interleaved"
                      f"{', in one process' if args.in_process else ''}"))
    return finish(results, "ab", args, elapsed)


if __name__ == "__main__":
    main()
