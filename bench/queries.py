"""The point and multi-hit queries against their peers: closest_points,
signed_distance, count_intersections and intersect_all.

    python -m bench.queries [--quick] [--devices pocl] [--peers open3d,warp,libigl,trimesh] [--docs]

Cases: the bunny and the reference scene (scenes/reference.toml).  Peers see
the scene's meshes as one mesh, the reference scene's ground included.
Workloads, made once in numpy, the same float32 arrays for everyone:
  - "uniform": points uniform in the case's box grown 1.4x about its centre;
  - "near surface": points uniform on the surface (by area) moved by an
    offset uniform in a ball of 1% of the box's diagonal;
  - "at centre": ray origins uniform in the box, each aimed at the box's
    centre (how the issue's Open3D count_intersections figure was taken);
  - "random": ray origins uniform in the box, directions uniform on the
    sphere (visibility and LiDAR-like returns: no two rays alike).
The box and the surface leave out a scene file's flat ground (as
bench/trace.py does): it would take most of the points.

Peers: Open3D RaycastingScene (all four queries), Warp's mesh_query_point on
the CPU (one thread: Warp's CPU launches are serial), libigl (AABB
squared_distance, signed_distance) and trimesh's intersects_location /
intersects_id with multiple_hits (embreex underneath, one thread, on the
first ``few_rays`` rays only: it re-casts each ray from past its last hit
in Python).  embreex itself is left out of the ray queries: its Python API
has neither a ray's tnear nor Embree's intersection filter, so its only way
to every hit is that same re-casting, which trimesh measures.

Timing: as bench/trace.py, each participant built outside the timing, each
query warmed up (our devices on the whole workload, peers on the first
WARM_UP items), then ``repeats`` rounds of one call per participant, each
after an untimed call of its own; wall time of a call, numpy in and out.
Rates are items (points or rays) per second, so a peer run on fewer rays
compares.
Agreement: each peer's answers against our first device's on the same items.
Memory: intersect_all on the memory case's rays in a child process: the
peak resident memory during the call (Linux's VmHWM, reset before it) over
the resident memory before it, against the nbytes of what the call returns.

Writes <out>/queries.json and <out>/queries.png; with --docs also
docs/bench_queries.png and the queries section of bench/RESULTS.md.
"""
from __future__ import annotations

import gc
import multiprocessing
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

import hlbvh_cl

from . import common, peers, plots, trace
from .common import (BENCH, arguments, devices_or_exit, finish, machine_info, progress, rates,
                     reset_peak, say, spread, status_bytes, stopwatch, summary, table)

QUERIES = ("closest_points", "signed_distance", "count_intersections", "intersect_all")
POINT_QUERIES = QUERIES[:2]
RAY_QUERIES = QUERIES[2:]
#: items each peer's warm-up call gets (fills its pools).  Our devices warm up
#: on the whole workload: PoCL compiles each kernel once for small launches
#: and once more for large ones, so a small warm-up with a cold kernel cache
#: left a compile inside the first timed call.
WARM_UP = 4096
#: our speed over the peer's that the issue asks for: (factor, peer or None for the fastest)
TARGETS = {"closest_points": (3.0, None), "signed_distance": (3.0, None),
           "count_intersections": (3.0, "open3d"), "intersect_all": (2.0, "open3d")}
#: intersect_all's peak memory growth over its output's size that the issue allows
MEMORY_TARGET = 2.0
#: bench/RESULTS.md keeps this section between these lines (report.py leaves it be)
SECTION = "queries"


@dataclass(frozen=True)
class Config:
    cases: tuple[str, ...]  # .ply in scenes/meshes, or .toml in scenes/
    points: int             # per point workload
    rays: int
    few_rays: int           # the rays a slow peer (trimesh) gets: the first ones
    repeats: int            # timed calls after one warm-up
    memory_case: str
    memory_rays: int
    box_factor: float = 1.4
    near_fraction: float = 0.01
    seed: int = 1


FULL = Config(("bunny.ply", "reference.toml"), 1_000_000, 1_000_000, 10_000, 3,
              "reference.toml", 1_000_000)
QUICK = Config(("bunny_small.ply", "bunny_small.toml"), 3_000, 3_000, 300, 1,
               "bunny_small.ply", 3_000)


# ---------------------------------------------------------------- workloads

@dataclass
class Points:
    name: str
    kind: str            # "uniform" or "near surface"
    points: np.ndarray   # (N, 3) float32

    def __len__(self) -> int:
        return len(self.points)


def head(work, count: int | None):
    """The first ``count`` items of a Points or trace.Rays (all for None)."""
    if count is None or count >= len(work):
        return work
    if isinstance(work, Points):
        return replace(work, points=work.points[:count])
    return replace(work, origins=work.origins[:count], directions=work.directions[:count])


def solid_meshes(case: trace.SceneCase) -> list:
    """The case's meshes but a flat ground (bench/trace.py's box leaves it out too)."""
    return [m for m in case.meshes if np.ptp(m.vertices, axis=0).min() > 0] or case.meshes


def uniform_points(lo, hi, count: int, factor: float, seed: int) -> Points:
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    rng = np.random.default_rng(seed)
    points = (lo + hi) / 2 + (rng.random((count, 3)) - 0.5) * (hi - lo) * factor
    return Points(f"uniform {count:,}", "uniform", np.ascontiguousarray(points, np.float32))


def near_surface_points(meshes, radius: float, count: int, seed: int) -> Points:
    """Points on the triangles, by area, moved uniformly within ``radius``."""
    rng = np.random.default_rng(seed)
    corners = np.concatenate([m.vertices[m.faces].astype(np.float64) for m in meshes])
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]),
                          axis=1)
    chosen = corners[rng.choice(len(corners), count, p=area / area.sum())]
    a, b = rng.random((2, count, 1))
    flip = a + b > 1  # folds the square onto the triangle: uniform barycentrics
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    on = chosen[:, 0] + a * (chosen[:, 1] - chosen[:, 0]) + b * (chosen[:, 2] - chosen[:, 0])
    offset = rng.normal(size=(count, 3))
    offset *= radius * rng.random((count, 1)) ** (1 / 3) / np.linalg.norm(offset, axis=1,
                                                                          keepdims=True)
    return Points(f"near surface {count:,}", "near surface",
                  np.ascontiguousarray(on + offset, np.float32))


def centre_rays(lo, hi, count: int, seed: int) -> trace.Rays:
    """Origins uniform in the box [lo, hi], each aimed at its centre."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    rng = np.random.default_rng(seed)
    origins = lo + rng.random((count, 3)) * (hi - lo)
    directions = (lo + hi) / 2 - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return trace.Rays(f"at centre {count:,}", "at centre",
                      np.ascontiguousarray(origins, np.float32),
                      np.ascontiguousarray(directions, np.float32))


def random_rays(lo, hi, count: int, seed: int) -> trace.Rays:
    """Origins uniform in the box [lo, hi], directions uniform on the sphere."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    rng = np.random.default_rng(seed)
    origins = lo + rng.random((count, 3)) * (hi - lo)
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return trace.Rays(f"random {count:,}", "random",
                      np.ascontiguousarray(origins, np.float32),
                      np.ascontiguousarray(directions, np.float32))


def workloads(case: trace.SceneCase, config: Config) -> dict:
    """{query: [workloads]} of one case."""
    lo, hi = case.box
    diagonal = float(np.linalg.norm(np.subtract(hi, lo)))
    points = [uniform_points(lo, hi, config.points, config.box_factor, config.seed),
              near_surface_points(solid_meshes(case), config.near_fraction * diagonal,
                                  config.points, config.seed + 1)]
    rays = [centre_rays(lo, hi, config.rays, config.seed + 2),
            random_rays(lo, hi, config.rays, config.seed + 3)]
    return {q: points if q in POINT_QUERIES else rays for q in QUERIES}


def load_case(name: str, device_id: str) -> trace.SceneCase:
    return (trace.scene_file_case(name, device_id) if name.endswith(".toml")
            else trace.mesh_case(name))


# ---------------------------------------------------------------- answers

def grouped(ray_ids, t, rays: int) -> tuple[np.ndarray, np.ndarray]:
    """Hits as (hits per ray, t of every hit by ray, nearest first)."""
    ray_ids, t = np.asarray(ray_ids, np.int64), np.asarray(t, np.float64)
    order = np.lexsort((t, ray_ids))
    return np.bincount(ray_ids, minlength=rays), t[order]


def distance_to(closest, points) -> np.ndarray:
    return np.linalg.norm(np.asarray(closest, np.float64) - points, axis=1)


# ---------------------------------------------------------------- participants
# run(query, work) is the timed call (numpy in, numpy out); answer(query,
# raw, work) puts its result in the common form, untimed: a distance per
# point, hits per ray, or (hits per ray, t by ray) for intersect_all.

class Answers:
    """What a participant of this bench declares: the queries it answers,
    and whether it is slow enough to get only the first ``few_rays`` rays."""
    queries = QUERIES
    few = False


class OurQueries(Answers, trace.OurDevice):

    def run(self, query: str, work):
        if query in POINT_QUERIES:
            return getattr(self.scene, query)(work.points)
        return getattr(self.scene, query)(work.origins, work.directions)

    def answer(self, query: str, raw, work):
        if query == "closest_points":
            return np.asarray(raw.distance, np.float64)
        if query == "intersect_all":
            return np.diff(raw.offsets), np.asarray(raw.t, np.float64)
        return np.asarray(raw)


class Open3DQueries(Answers, peers.Open3DPeer):
    label = "Open3D RaycastingScene (all threads)"

    def run(self, query: str, work):
        import open3d
        if query == "closest_points":
            found = self.scene.compute_closest_points(open3d.core.Tensor(work.points))
            return {key: value.numpy() for key, value in found.items()}
        if query == "signed_distance":
            return self.scene.compute_signed_distance(open3d.core.Tensor(work.points)).numpy()
        if query == "count_intersections":
            return self.scene.count_intersections(self._tensor(work)).numpy()
        found = self.scene.list_intersections(self._tensor(work))
        return {key: value.numpy() for key, value in found.items()}

    def answer(self, query: str, raw, work):
        if query == "closest_points":
            return distance_to(raw["points"], work.points)
        if query == "intersect_all":
            return grouped(raw["ray_ids"], raw["t_hit"], len(work))
        return np.asarray(raw)


class WarpPeer(Answers, peers.Peer):
    name, distribution = "warp", "warp-lang"
    label = "Warp mesh_query_point, CPU (1 thread)"
    modules = ("warp", "bench.warp_kernels")
    queries = POINT_QUERIES

    def build(self, vertices, faces) -> float:
        import warp as wp
        elapsed = stopwatch()
        self.arrays = (wp.array(vertices, dtype=wp.vec3, device="cpu"),
                       wp.array(faces.ravel(), dtype=wp.int32, device="cpu"))
        self.scene = wp.Mesh(points=self.arrays[0], indices=self.arrays[1])
        return elapsed()

    def run(self, query: str, work):
        import warp as wp

        from . import warp_kernels
        n = len(work)
        out = [wp.empty(n, dtype=t, device="cpu") for t in (wp.float32, wp.vec3, wp.int32)]
        wp.launch(warp_kernels.closest_points, dim=n, device="cpu", outputs=out,
                  inputs=[self.scene.id, wp.array(work.points, dtype=wp.vec3, device="cpu"),
                          float(np.finfo(np.float32).max), int(query == "signed_distance")])
        return {key: a.numpy() for key, a in zip(("distance", "points", "face"), out)}

    def answer(self, query: str, raw, work):
        return raw["distance"].astype(np.float64)

    def close(self) -> None:
        self.scene = self.arrays = None


class LibiglPeer(Answers, peers.Peer):
    name = distribution = "libigl"
    label = "libigl AABB.squared_distance, signed_distance (pseudonormal sign)"
    modules = ("igl",)
    queries = POINT_QUERIES

    def build(self, vertices, faces) -> float:
        import igl
        elapsed = stopwatch()
        self.mesh = (vertices.astype(np.float64), faces.astype(np.int64))
        self.scene = igl.AABB()
        self.scene.init(*self.mesh)
        return elapsed()

    def run(self, query: str, work):
        import igl
        points = work.points.astype(np.float64)
        if query == "closest_points":
            return self.scene.squared_distance(*self.mesh, points)
        # the binding builds its own tree inside each call: there is no other way to it.
        # Pseudonormal signs: its fastest, and its winding-number modes return wrong
        # magnitudes on an open mesh (a scene file's ground)
        return igl.signed_distance(points, *self.mesh, igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)

    def answer(self, query: str, raw, work):
        return np.sqrt(raw[0]) if query == "closest_points" else raw[0]

    def close(self) -> None:
        self.scene = self.mesh = None


class TrimeshQueries(Answers, peers.TrimeshPeer):
    label = "trimesh intersects_location/_id, multiple_hits (embreex, 1 thread)"
    queries = RAY_QUERIES
    few = True

    def run(self, query: str, work):
        if query == "count_intersections":
            return self.scene.intersects_id(work.origins, work.directions, multiple_hits=True)
        return self.scene.intersects_location(work.origins, work.directions, multiple_hits=True)

    def answer(self, query: str, raw, work):
        if query == "count_intersections":
            return np.bincount(raw[1], minlength=len(work))
        locations, ray, _ = raw
        t = np.einsum("ij,ij->i", locations - work.origins[ray], work.directions[ray])
        return grouped(ray, t, len(work))


PEERS = {p.name: p for p in (Open3DQueries, WarpPeer, LibiglPeer, TrimeshQueries)}


# ---------------------------------------------------------------- agreement

def agreement(query: str, theirs, ours, scale: float) -> dict:
    """How far ``theirs`` is from ``ours`` on the same items; distances and
    t relative to ``scale`` (the case's box diagonal)."""
    if query in POINT_QUERIES:
        a, b = np.asarray(theirs, np.float64), np.asarray(ours, np.float64)
        gap = np.abs(np.abs(a) - np.abs(b)) / scale
        out = {"max_distance_gap": float(gap.max(initial=0)),
               "distance_differs": float(np.mean(gap > 1e-4))}
        if query == "signed_distance":  # away from the surface, where a sign is meaningful
            clear = np.minimum(np.abs(a), np.abs(b)) > 1e-3 * scale
            out["sign_differs"] = float(np.mean(np.sign(a[clear]) != np.sign(b[clear]))
                                        if clear.any() else 0.0)
        return out
    if query == "count_intersections":
        return {"count_differs": float(np.mean(np.asarray(theirs) != np.asarray(ours)))}
    (counts, t), (our_counts, our_t) = theirs, ours
    same = counts == our_counts
    gap = np.abs(t[np.repeat(same, counts)] - our_t[np.repeat(same, our_counts)]) / scale
    return {"count_differs": float(np.mean(~same)), "max_t_gap": float(gap.max(initial=0))}


def ratios(query: str, results: dict, ours: list[str]) -> dict:
    """Our rate over each peer's, and over the fastest peer's / the target's peer."""
    theirs = {n: r["mrate"]["median"] for n, r in results.items() if n not in ours}
    factor, against = TARGETS[query]
    out = {}
    for device in (d for d in ours if d in results):
        mine = results[device]["mrate"]["median"]
        entry = {"peers": {n: mine / v for n, v in theirs.items() if v > 0}}
        target_peer = against if against in theirs else (
            max(theirs, key=theirs.get) if theirs and against is None else None)
        entry["target"] = {"factor": factor, "peer": target_peer,
                           "ratio": entry["peers"].get(target_peer),
                           "met": (entry["peers"].get(target_peer, 0) >= factor
                                   if target_peer else None)}
        out[device] = entry
    return out


# ---------------------------------------------------------------- measuring

def bench_query(query: str, work, participants: list, ours: list[str], config: Config,
                scale: float) -> dict:
    errors: dict = {}
    able = [p for p in participants if query in p.queries]
    sized = {p.name: head(work, config.few_rays if p.few else None) for p in able}
    timed = trace.time_round_robin(
        able, lambda p: p.run(query, sized[p.name]), config.repeats, errors,
        warm_up=lambda p: p.run(query, sized[p.name] if p.name in ours else head(work, WARM_UP)))
    results, answers = {}, {}
    for p in (p for p in able if p.name in timed):
        raw, walls = timed[p.name]
        count = len(sized[p.name])
        answers[p.name] = p.answer(query, raw, sized[p.name])
        results[p.name] = {"items": count, "seconds": summary(walls), "mrate": rates(count, walls)}
    reference = next((d for d in ours if d in answers), None)
    for name, answer in answers.items():
        if reference is not None and name != reference:
            results[name]["vs_ours"] = agreement(query, answer,
                                                 _first(query, answers[reference], len(sized[name])),
                                                 scale)
        if query == "intersect_all":
            results[name]["hits"] = int(answer[0].sum())
        elif query == "count_intersections":
            results[name]["hits"] = int(np.sum(answer))
    return {"query": query, "workload": work.name, "kind": work.kind, "items": len(work),
            "reference": reference, "results": results, "errors": errors,
            "ratios": ratios(query, results, ours)}


def _first(query: str, answer, count: int):
    """The first ``count`` items' part of an answer in the common form."""
    if query != "intersect_all":
        return answer[:count]
    counts, t = answer
    return counts[:count], t[:counts[:count].sum()]


def bench_case(name: str, devices: list, peer_list: list, config: Config, bar=None,
               chosen: tuple[str, ...] = QUERIES) -> dict:
    case = load_case(name, devices[0].id)
    ours = [OurQueries(d) for d in devices]
    participants = ours + peer_list
    errors: dict = {}
    built, build_seconds = trace.build_all(case, participants, errors)
    scale = float(np.linalg.norm(np.subtract(*case.box)))
    corners = [m.vertices[m.faces].astype(np.float64) for m in case.meshes]
    out = {"name": name, "triangles": case.triangles, "meshes": len(case.meshes),
           "diagonal": scale, "signed_volume": float(sum(  # < 0: the faces point inward
               np.einsum("fk,fk->f", c[:, 0], np.cross(c[:, 1], c[:, 2])).sum() / 6
               for c in corners)), "build_s": build_seconds, "errors": errors, "runs": []}
    try:
        for query, works in workloads(case, config).items():
            for work in works if query in chosen else ():
                if bar is not None:
                    bar.set_postfix_str(f"{name}: {query} {work.kind}")
                run = bench_query(query, work, built, [o.name for o in ours], config, scale)
                out["runs"].append(run)
                say(f"  {name} {query} {work.name}, M/s: " + "  ".join(
                    f"{n} {r['mrate']['median']:.3f}" for n, r in run["results"].items()))
                gc.collect()
                if bar is not None:
                    bar.update()
    finally:
        trace.close_all(built)
    return out


# ---------------------------------------------------------------- memory

def _output_bytes(raw) -> int:
    if isinstance(raw, dict):
        return sum(_output_bytes(v) for v in raw.values())
    if isinstance(raw, np.ndarray):
        return raw.nbytes
    if isinstance(raw, (tuple, list)):
        return sum(_output_bytes(v) for v in raw)
    return sum(v.nbytes for v in vars(raw).values() if isinstance(v, np.ndarray))


def memory_child(case_name: str, participant: str, device_id: str, count: int,
                 seed: int) -> dict:
    """In a fresh process: intersect_all's resident memory growth on the case's rays."""
    device = next(d for d in hlbvh_cl.devices() if d.id == device_id)
    case = load_case(case_name, device_id)
    p = OurQueries(device) if participant == device_id else PEERS[participant]()
    if p.kind != "device" and not p.load():
        raise RuntimeError(p.problem)
    trace.build_participant(p, case)
    rays = centre_rays(*case.box, count, seed)
    p.run("intersect_all", head(rays, WARM_UP))
    gc.collect()
    if not reset_peak():
        raise RuntimeError("cannot reset the peak resident memory (/proc/self/clear_refs)")
    before = status_bytes("VmRSS")
    raw = p.run("intersect_all", rays)
    peak = status_bytes("VmHWM")
    output = _output_bytes(raw)
    return {"participant": participant, "rays": count, "rss_before_bytes": before,
            "peak_growth_bytes": peak - before, "output_bytes": output,
            "ratio": (peak - before) / output if output else None}


def bench_memory(config: Config, device_id: str, peer_names: list[str]) -> dict:
    out = {"case": config.memory_case, "rays": config.memory_rays, "target": MEMORY_TARGET,
           "results": {}, "errors": {}}
    for name in [device_id] + peer_names:
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
            try:
                out["results"][name] = pool.submit(
                    memory_child, config.memory_case, name, device_id, config.memory_rays,
                    config.seed + 2).result()
                r = out["results"][name]
                say(f"  memory {name}: peak growth {r['peak_growth_bytes'] / 2**20:.0f} MiB, "
                    f"output {r['output_bytes'] / 2**20:.0f} MiB: {r['ratio']:.2f}x")
            except Exception as error:
                out["errors"][name] = f"{type(error).__name__}: {error}"
    return out


# ---------------------------------------------------------------- report

def _rows(results: dict):
    return [(c, r) for c in results["cases"] for r in c["runs"]]


def _ratio_text(run: dict, device: str) -> str | None:
    target = run["ratios"].get(device, {}).get("target")
    if not target or target["ratio"] is None:
        return None
    return (f"{target['ratio']:.2f}x {target['peer']} (>= {target['factor']:g}x: "
            f"{'yes' if target['met'] else 'no'})")


def format_results(results: dict, markdown: bool = False) -> str:
    names = [n for n, p in results["participants"].items() if p["available"]]
    devices = [n for n, p in results["participants"].items() if p["kind"] == "device"]
    rows = _rows(results)
    speed = [[c["name"], r["query"], r["workload"],
              *[spread(r["results"][n]["mrate"], digits=3) if n in r["results"] else None
                for n in names], *[_ratio_text(r, d) for d in devices]] for c, r in rows]
    speed_headers = ["case", "query", "workload", *names, *[f"{d} / target peer" for d in devices]]
    others = [n for n in names if n not in devices[:1]]  # the first device is the reference
    gaps = [[c["name"], r["query"], r["workload"],
             *[", ".join(f"{k} {v:.1e}" for k, v in r["results"][n]["vs_ours"].items())
               if "vs_ours" in r["results"].get(n, {}) else None for n in others]]
            for c, r in rows]
    memory = results.get("memory")
    memory_rows = [[n, r["rays"], r["peak_growth_bytes"] / 2**20, r["output_bytes"] / 2**20,
                    f"{r['ratio']:.2f}"] for n, r in (memory or {}).get("results", {}).items()]
    memory_headers = ["participant", "rays", "peak growth MiB", "output MiB", "growth / output"]
    failed = [f"FAILED {c['name']} {r.get('query', 'build')} {n}: {e}"
              for c in results["cases"] for r in [c] + c["runs"] for n, e in r["errors"].items()]
    failed += [f"FAILED memory {n}: {e}" for n, e in (memory or {}).get("errors", {}).items()]
    missing = [f"peer {n} is missing: {p['problem']}" for n, p in results["participants"].items()
               if not p["available"]]
    if not markdown:
        return "\n\n".join(missing + [
            table(speed_headers, speed, "M items/s: median (min-max), numpy in and out"),
            table(["case", "query", "workload", *others], gaps,
                  "each answer against ours (distances and t relative to the box diagonal)"),
            table(memory_headers, memory_rows,
                  f"intersect_all memory, {memory['case'] if memory else '-'}")] + failed)
    from .report import md_table
    return "\n".join([f"<!-- begin {SECTION} -->", "", "## Point and multi-hit queries", "",
                      f"Measured on {results['machine']['date']} with `{results['command']}` "
                      f"(bench/queries.py; its docstring says how), load average "
                      + ", ".join(f"{x:.2f}" for x in results["machine"]["loadavg"])
                      + " at the start; above 2 means other processes ran too.", "",
                      "![query rates](../docs/bench_queries.png)", "",
                      *[f"- {m}" for m in missing], "",
                      "M points/s or M rays/s, median (min-max) of "
                      f"{results['config']['repeats']} calls; trimesh ran on the first "
                      f"{results['config']['few_rays']:,} rays only. Target: the issue's factor "
                      "over the fastest peer (or Open3D for the ray queries).", "",
                      md_table(speed_headers, speed, left=3), "",
                      "Agreement with ours on the same items (distances and t over the box "
                      "diagonal; signs where both are more than 1e-3 of it from the surface). "
                      "Open3D signs by counting a ray's crossings, libigl (pseudonormal) and "
                      "Warp by the faces' orientation: on a case whose faces point inward "
                      "(signed volume " + ", ".join(f"{c['name']} {c['signed_volume']:.3g}"
                                                    for c in results["cases"])
                      + ") or that is not closed, their signs differ by design.",
                      "", md_table(["case", "query", "workload", *others], gaps, left=3), "",
                      f"intersect_all memory on {memory['case'] if memory else '-'}, child "
                      f"process, peak RSS growth over the output's nbytes (target < "
                      f"{MEMORY_TARGET:g}x):", "", md_table(memory_headers, memory_rows), "",
                      *[f"- {f}" for f in failed], "", "*JSON: `queries.json`*", "",
                      f"<!-- end {SECTION} -->"]) + "\n"


def write_section(path: Path, text: str) -> Path:
    """Puts ``text`` (this bench's marked section) into the markdown file."""
    return common.write_section(path, text, SECTION)


def plot(results: dict, path: Path) -> Path:
    """Rates of every participant per case, query and workload; and our
    speed over the target's peer with the target drawn."""
    plt = plots.pyplot()
    figure, (speed, ratio) = plt.subplots(2, 1, figsize=(14, 9))
    rows = _rows(results)
    names = [n for n, p in results["participants"].items() if p["available"]]
    width = 0.8 / max(len(names), 1)
    labels = [f"{c['name'].rsplit('.', 1)[0]}\n{r['query']}\n{r['kind']}" for c, r in rows]
    for i, name in enumerate(names):
        x = [k for k, (_, r) in enumerate(rows) if name in r["results"]]
        if x:
            speed.bar(np.array(x) + (i - (len(names) - 1) / 2) * width,
                      [rows[k][1]["results"][name]["mrate"]["median"] for k in x], width,
                      label=name)
    speed.set_xticks(range(len(rows)), labels, fontsize=6)
    speed.set(yscale="log", ylabel="M items/s (median)", title="query rates, same items for all")
    plots.plain_log(speed)
    speed.legend(fontsize=7, ncol=3)
    devices = [n for n, p in results["participants"].items() if p["kind"] == "device"]
    for i, device in enumerate(devices):
        values = [r["ratios"].get(device, {}).get("target", {}).get("ratio") or 0 for _, r in rows]
        ratio.bar(np.arange(len(rows)) + (i - (len(devices) - 1) / 2) * 0.8 / len(devices), values,
                  0.8 / len(devices), label=device)
    for k, (_, r) in enumerate(rows):
        ratio.hlines(TARGETS[r["query"]][0], k - 0.45, k + 0.45, color="crimson")
    ratio.set_xticks(range(len(rows)), labels, fontsize=6)
    ratio.set(ylabel="ours / target peer", title="our speed over the fastest peer "
              "(Open3D for the ray queries); red: the issue's target")
    ratio.legend(fontsize=7)
    return plots.save(figure, path)


# ---------------------------------------------------------------- the command

def main(argv=None) -> dict:
    args = arguments(__doc__.splitlines()[0], argv,
                     (["--peers"], {"default": ",".join(PEERS),
                                    "help": f"comma-separated peers (default: {','.join(PEERS)})"}),
                     (["--queries"], {"default": ",".join(QUERIES),
                                      "help": f"comma-separated (default: {','.join(QUERIES)})"}),
                     (["--repeats"], {"type": int, "default": None,
                                      "help": "timed calls after the warm-up (default: the mode's)"}),
                     (["--no-memory"], {"action": "store_true",
                                        "help": "skip the intersect_all memory measurement"}))
    config = QUICK if args.quick else FULL
    if args.repeats is not None:
        if args.repeats < 1:
            raise SystemExit(f"--repeats must be at least 1, got {args.repeats}")
        config = replace(config, repeats=args.repeats)
    chosen_queries = tuple(q.strip() for q in args.queries.split(",") if q.strip())
    unknown = set(chosen_queries) - set(QUERIES)
    if unknown:
        raise SystemExit(f"unknown --queries {', '.join(sorted(unknown))}; known: {', '.join(QUERIES)}")
    elapsed = stopwatch()
    chosen = devices_or_exit(args.devices)
    available, missing = peers.load_peers([p.strip() for p in args.peers.split(",")
                                           if p.strip()], PEERS)
    say(f"devices: {', '.join(d.id for d in chosen)}; peers: "
        + (", ".join(f"{p.name} {p.version}" for p in available) or "none")
        + "".join(f"; {p.name} missing ({p.problem})" for p in missing))
    results = {"command": " ".join(["python -m bench.queries",
                                     *(sys.argv[1:] if argv is None else argv)]),
               "config": asdict(config), "quick": args.quick, "machine": machine_info(),
               "participants": {**{d.id: OurQueries(d).describe() for d in chosen},
                                **{p.name: p.describe() for p in available + missing}},
               "cases": []}
    steps = len(config.cases) * sum(2 if q in POINT_QUERIES else 1 for q in chosen_queries)
    with progress(steps, "queries bench", enabled=not args.no_progress) as bar:
        for name in config.cases:
            results["cases"].append(bench_case(name, chosen, available, config, bar,
                                               chosen_queries))
    if not args.no_memory and "intersect_all" in chosen_queries:
        say("intersect_all memory ...")
        results["memory"] = bench_memory(config, chosen[0].id,
                                         [p.name for p in available if "intersect_all" in p.queries
                                          and not p.few])
    print(format_results(results))
    finish(results, "queries", args, elapsed, plot)
    if args.docs:
        write_section(BENCH / "RESULTS.md", format_results(results, markdown=True))
    return results


if __name__ == "__main__":
    main()
