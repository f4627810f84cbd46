"""The path tracer's rays, depth by depth, traced by our kernels and by Mitsuba 3's Embree: where the render's gap to Mitsuba lies.

bench.path times whole renders.  This bench takes the rays one of our path
renders traced (bench.path's scenes and sizes, one sample per pixel, max
depth 8): at each depth its closest-hit rays (depth 0: the camera's) and
its shadow rays (the light samples), captured as the kernels read them.
Then, in each round, each device traces every set with the renderer's own
kernels on rays already on the device (RayQuery.enqueue_intersect and
enqueue_occluded: no numpy, no checks, as inside a render), and Mitsuba
(llvm_ad_rgb, in a child process as in bench.path) traces the same rays in
the same scene file: ray_intersect_preliminary, coherent for the camera's
rays as Mitsuba's path integrator traces them, and ray_test for shadow
rays; its time is the trace and the record it leaves in memory (t, the
primitive and its u, v, as bench.trace's Mitsuba peer evaluates them; a
shadow ray's flag), where ours writes a Hit record (or a flag) on the
device.  Each timed trace
follows an untimed one of the same tracer: the threads of the one before
(Mitsuba's) would otherwise still be spinning (see bench.trace's
time_round_robin).  Mitsuba's rays start at 0, so a ray of ours that
starts at tmin > 0 goes to it moved forward by tmin.  Each set's table row gives the median rays per second over the
rounds, the ratio to Mitsuba's, and the fraction of rays whose hit or miss
differs from Mitsuba's (a check that both traced the same rays in the same
scene; rays that graze an edge may differ).

    python -m bench.depth_rays [--quick] [--devices pocl,intel] [--scenes cornell,materials]
                               [--rounds 5]
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import pyopencl as cl

from hlbvh_cl.io.scenefile import load
from hlbvh_cl.query.rays import RayQuery
from hlbvh_cl.render.renderer import Pipeline, check_settings

from .common import arguments, devices_or_exit, finish, say, stopwatch, table
from .path import (CHILD_START, FULL, MAX_DEPTH, QUICK, cornell_xml, materials_xml,
                   start_mitsuba)

SCENES = {"cornell": cornell_xml, "materials": materials_xml}

#: A ray record as the kernels read it (kernels/query/records.h's Ray):
#: origin, tmin, direction, tmax.
RAY_FLOATS = 8

#: Mitsuba's side: argv = variants to try.  Requests, a JSON line each:
#: {"load": xml, "width", "height", "rays": npz} loads the scene and the
#: rays; {"trace": key} traces one set once and answers its seconds;
#: {"hits": key} answers its hit mask's path (a .npy beside the rays).
_CHILD = CHILD_START + r"""
import drjit as dr
scene, rays, folder = None, {}, None
def trace(key):
    # the record our kernels write, as bench.trace's Mitsuba peer evaluates
    # it: t, the primitive and its u, v (a shadow ray: its flag)
    ray, shadow, coherent = rays[key]
    if shadow:
        found = scene.ray_test(ray, coherent=coherent)
        dr.eval(found)
        dr.sync_thread()  # (Dr.Jit's LLVM kernels run asynchronously)
        return found
    found = scene.ray_intersect_preliminary(ray, coherent=coherent)
    valid = found.is_valid()
    t = dr.select(valid, found.t, dr.inf)
    prim = dr.select(valid, mi.Int32(found.prim_index), -1)
    dr.eval(t, prim, found.prim_uv)
    dr.sync_thread()
    return t
def hit_mask(key):
    found = np.asarray(trace(key))
    return found if rays[key][1] else np.isfinite(found)
for line in sys.stdin:
    request = json.loads(line)
    if "load" in request:
        scene = mi.load_file(request["load"], res_x=request["width"], res_y=request["height"])
        data = np.load(request["rays"])
        folder = request["rays"].rsplit("/", 1)[0]
        for key in data.files:
            a = data[key].astype(np.float64)
            tmin = a[:, 3:4]
            origin = a[:, 0:3] + a[:, 4:7] * tmin
            maxt = np.where(np.isinf(a[:, 7]), np.inf, a[:, 7] - a[:, 3])
            f = lambda x: mi.Float(np.ascontiguousarray(x, np.float32))
            ray = mi.Ray3f(mi.Point3f(*(f(origin[:, i]) for i in range(3))),
                           mi.Vector3f(*(f(a[:, 4 + i]) for i in range(3))),
                           f(maxt), mi.Float(0.0), mi.Color0f())
            rays[key] = (ray, key.startswith("shadow"), key == "closest 0")
            trace(key)  # compiles
        print(json.dumps({"sets": len(rays)}), flush=True)
    elif "trace" in request:
        started = time.perf_counter()
        trace(request["trace"])
        print(json.dumps({"seconds": time.perf_counter() - started}), flush=True)
    else:
        path = f"{folder}/mitsuba_{request['hits'].replace(' ', '_')}.npy"
        np.save(path, hit_mask(request["hits"]))
        print(json.dumps({"path": path}), flush=True)
"""


class CapturingQuery(RayQuery):
    """A RayQuery that keeps a copy of the rays of each launch, by depth
    and kind ("closest 0", "shadow 0", ...): a render's counted launches
    read their ray count on the device, which it reads back after the
    launch (the render waits for each; only the capture render does)."""

    def __init__(self, rt):
        super().__init__(rt)
        self.rays: dict[str, list[np.ndarray]] = {}

    def _keep(self, kind: str, rays, count: int, counted) -> None:
        queue, depth = self.rt.queue, 0
        if counted is not None:
            buffer, depth = counted
            counts = np.empty(depth + 1, np.uint32)
            cl.enqueue_copy(queue, counts, buffer, is_blocking=True)
            count = min(count, int(counts[depth]))
        kept = np.empty((count, RAY_FLOATS), np.float32)
        if count:
            cl.enqueue_copy(queue, kept, rays, is_blocking=True)
        self.rays.setdefault(f"{kind} {depth}", []).append(kept)

    def enqueue_intersect(self, tree, rays, hits, count, overflow, wait_for=None,
                          instances=None, counted=None):
        event = super().enqueue_intersect(tree, rays, hits, count, overflow, wait_for,
                                          instances, counted)
        self._keep("closest", rays, count, counted)
        return event

    def enqueue_occluded(self, tree, rays, occluded, count, overflow, wait_for=None,
                         counted=None):
        event = super().enqueue_occluded(tree, rays, occluded, count, overflow, wait_for,
                                         counted)
        self._keep("shadow", rays, count, counted)
        return event


def capture(loaded, width: int, height: int) -> dict[str, np.ndarray]:
    """The rays of one path render of ``loaded`` (one sample per pixel,
    MAX_DEPTH), by set, each an (N, RAY_FLOATS) float32 array; empty sets
    left out."""
    options = {**loaded.options, "spp": 1, "max_depth": MAX_DEPTH}
    options.pop("shading", None)
    renderer = loaded.renderer()
    settings = check_settings(loaded.camera, width, height, "path", **options)
    with loaded.scene.borrow() as built:
        query = CapturingQuery(built.runtime)
        Pipeline(built.runtime, query).render(built.tree, settings, renderer.look(), hdr=True)
    sets = {key: np.concatenate(parts) for key, parts in query.rays.items()}
    order = sorted(sets, key=lambda k: (int(k.split()[1]), k))
    return {key: sets[key] for key in order if len(sets[key])}


class OurTracer:
    """One device's kernels over a loaded scene, on rays put on the device once."""

    def __init__(self, loaded, sets: dict[str, np.ndarray]):
        self.scene = loaded.scene
        self.sets = sets
        with self.scene.borrow() as built:
            self.rt, self.tree = built.runtime, built.tree
        self.query = RayQuery(self.rt)
        flags = cl.mem_flags
        self.overflow = cl.Buffer(self.rt.context, flags.READ_WRITE | flags.COPY_HOST_PTR,
                                  hostbuf=np.zeros(1, np.int32))
        self.buffers = {}
        for key, rays in sets.items():
            out_bytes = len(rays) * (1 if key.startswith("shadow") else 32)
            self.buffers[key] = (
                cl.Buffer(self.rt.context, flags.READ_ONLY | flags.COPY_HOST_PTR, hostbuf=rays),
                cl.Buffer(self.rt.context, flags.READ_WRITE, max(out_bytes, 4)))
            self.trace(key)  # compiles

    def trace(self, key: str) -> float:
        """Seconds to trace set ``key`` once, launch to finish."""
        rays, out = self.buffers[key]
        count = len(self.sets[key])
        elapsed = stopwatch()
        if key.startswith("shadow"):
            self.query.enqueue_occluded(self.tree, rays, out, count, self.overflow)
        else:
            self.query.enqueue_intersect(self.tree, rays, out, count, self.overflow)
        self.rt.queue.finish()
        return elapsed()

    def hits(self, key: str) -> np.ndarray:
        """Whether each ray of set ``key`` hit (occluded, or a finite t)."""
        rays, out = self.buffers[key]
        count = len(self.sets[key])
        if key.startswith("shadow"):
            found = np.empty(count, np.uint8)
            cl.enqueue_copy(self.rt.queue, found, out)
            return found > 0
        found = np.empty((count, 8), np.float32)  # Hit: t first
        cl.enqueue_copy(self.rt.queue, found, out)
        return np.isfinite(found[:, 0])


class MitsubaTracer:
    """Mitsuba 3 in a child process (see _CHILD)."""

    def __init__(self, path: Path, width: int, height: int, rays_file: Path):
        self.process, self.variant = start_mitsuba(_CHILD, ("llvm_ad_rgb", "scalar_rgb"))
        self._ask({"load": str(path), "width": width, "height": height,
                   "rays": str(rays_file)})

    def _answer(self) -> dict:
        line = self.process.stdout.readline()
        if not line:
            raise RuntimeError("Mitsuba's child process died")
        return json.loads(line)

    def _ask(self, request: dict) -> dict:
        self.process.stdin.write(json.dumps(request) + "\n")
        self.process.stdin.flush()
        return self._answer()

    def trace(self, key: str) -> float:
        return self._ask({"trace": key})["seconds"]

    def hits(self, key: str) -> np.ndarray:
        return np.load(self._ask({"hits": key})["path"])

    def close(self) -> None:
        self.process.stdin.close()
        self.process.wait()


def bench_scene(name: str, path: Path, size: tuple, devices: list[str], rounds: int,
                folder: Path) -> dict:
    """Captures the scene's rays on the first device, then times every
    set on every device and in Mitsuba, ``rounds`` times in turn."""
    width, height = size
    tracers = {device: load(path, device, defaults={"res_x": width, "res_y": height})
               for device in devices}
    sets = capture(tracers[devices[0]], width, height)
    rays_file = folder / f"{name}_rays.npz"
    np.savez(rays_file, **sets)
    tracers = {device: OurTracer(loaded, sets) for device, loaded in tracers.items()}
    mitsuba = MitsubaTracer(path, width, height, rays_file)
    times = {(key, who): [] for key in sets for who in [*devices, "mitsuba"]}
    try:
        for _ in range(rounds):
            for key in sets:
                for who, tracer in [*tracers.items(), ("mitsuba", mitsuba)]:
                    tracer.trace(key)  # untimed: as bench.trace's time_round_robin, and why
                    times[key, who].append(tracer.trace(key))
        theirs = {key: mitsuba.hits(key) for key in sets}
    finally:
        mitsuba.close()
    result = {"size": [width, height], "mitsuba": mitsuba.variant, "sets": {}}
    for key, rays in sets.items():
        entry = {"rays": len(rays), "hit_fraction": float(theirs[key].mean())}
        for who in [*devices, "mitsuba"]:
            entry[who] = {"seconds": float(np.median(times[key, who])),
                          "mrays_per_s": len(rays) / float(np.median(times[key, who])) / 1e6}
        for device, tracer in tracers.items():
            entry[device]["differ"] = float((tracer.hits(key) != theirs[key]).mean())
            entry[device]["ratio"] = entry["mitsuba"]["seconds"] / entry[device]["seconds"]
        result["sets"][key] = entry
    return result


def format_scene(name: str, result: dict, devices: list[str]) -> str:
    headers = ["set", "rays", "hits"] + [f"{d} Mrays/s (/ Mitsuba)" for d in devices] \
        + [f"Mitsuba {result['mitsuba']}"] + [f"{d} differs" for d in devices]
    rows = []
    for key, e in result["sets"].items():
        rows.append([key, f"{e['rays']:,}", f"{e['hit_fraction']:.3f}"]
                    + [f"{e[d]['mrays_per_s']:.2f} ({e[d]['ratio']:.2f}x)" for d in devices]
                    + [f"{e['mitsuba']['mrays_per_s']:.2f}"]
                    + [f"{e[d]['differ']:.1e}" for d in devices])
    width, height = result["size"]
    return table(headers, rows, title=f"{name}, {width}x{height}, 1 spp, max depth "
                                      f"{MAX_DEPTH}: the render's rays by depth, median of the rounds")


def main(argv=None) -> dict:
    args = arguments(__doc__.splitlines()[0], argv,
                     (["--scenes"], {"default": "cornell,materials",
                                     "help": "comma-separated: cornell, materials"}),
                     (["--rounds"], {"type": int, "default": 5,
                                     "help": "times each set is traced by each tracer"}))
    names = [n for n in args.scenes.split(",") if n]
    unknown = [n for n in names if n not in SCENES]
    if unknown or not names:
        raise SystemExit(f"--scenes: expected some of {', '.join(SCENES)}, got {args.scenes!r}")
    if args.rounds < 1:
        raise SystemExit(f"--rounds must be at least 1, got {args.rounds}")
    devices = [d.id for d in devices_or_exit(args.devices)]
    elapsed = stopwatch()
    sizes = QUICK if args.quick else FULL
    results = {"devices": devices, "rounds": args.rounds, "scenes": {}}
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        for name in names:
            say(f"{name}: capturing the render's rays on {devices[0]}")
            path = SCENES[name](folder)
            result = bench_scene(name, path, sizes[name][:2], devices, args.rounds, folder)
            results["scenes"][name] = result
            print(format_scene(name, result, devices))
    return finish(results, "depth_rays", args, elapsed)


if __name__ == "__main__":
    main()
