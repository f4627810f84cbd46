"""Ray throughput: hlbvh_cl's closest-hit and any-hit queries against the
peers of bench/peers.py, on the same rays.

    python -m bench.trace [--quick] [--devices pocl,intel] [--peers embreex,mitsuba] [--docs]
    python -m bench.trace --scene cornell_box.xml    (that scene file alone)

Scenes: the bunny, the armadillo and Lucy as they are, and the reference
scene (scenes/reference.toml); or with --scene one file of scenes/ alone
(the Cornell box: a path tracer's small closed room), without the scaling
sweep.  Workloads per scene, made once in numpy and
given to every participant as the same float32 arrays:
  - primary rays through the pixel centres of a pinhole camera: the scene
    file's, or one framed on a lone mesh (framed_camera);
  - incoherent rays: origins uniform on a sphere around the objects, each
    aimed at a uniform random point of their box (a scene file's flat
    ground is left out of that box: it would take most of them);
  - diffuse bounces, a path tracer's second segment: the primary rays of the
    last (largest) resolution are traced (by our first device), and from each hit on
    a mesh (not on a scene file's ground) one ray leaves cosine-distributed
    about the triangle's geometric normal (bounce_rays).  They follow from
    the scene, the camera, the seed and those hits, which are exact
    (watertight, the same on every device), so any user regenerates them.

Timing: each participant builds once outside the timing; each query runs
once to warm up, then in ``repeats`` rounds of one call per participant, so
that all of them meet about the same load from other processes; each timed
call follows an untimed one of its own participant, not another's
(time_round_robin says why).  The time is the host's wall time of one
call, numpy in and numpy out: what a user sees.
Peers see the scene's meshes as one mesh.  Each of our trees' device
memory (nodes plus leaf triangles, BuildStats.tree_bytes) is printed per scene.

Scaling: one workload (primary rays framed on it) over one surface
tessellated ever finer (common.surface), on our devices and embreex: the
picture stays the same, only the triangle count changes, and time ~
triangles^alpha is fitted in log-log.

Writes <out>/trace.json and <out>/trace.png (with --docs, docs/bench_trace.png).
"""
from __future__ import annotations

import gc
import math
import sys
import traceback
from dataclasses import asdict, dataclass, field, replace

import numpy as np

import hlbvh_cl
import hlbvh_cl.io.scenefile

from . import plots
from .common import (MESHES, SCENES, arguments, bounds, devices_or_exit, finish, fit_exponent,
                     machine_info, progress, rates, ratio, say, spread, stopwatch, summary,
                     surface, table)
from .peers import PEERS, REFERENCE, load_peers

#: vertical field of view of the cameras framed on a mesh's box, degrees
FRAMED_FOV_DEG = 40.0
#: incoherent rays start on a sphere this many half-diagonals from the centre
SPHERE_RADIUS_FACTOR = 1.5
#: a bounce ray's origin is lifted off its triangle along the normal by this
#: fraction of the triangle's largest absolute vertex coordinate.  The float32
#: hit point and the next traversal's origin-relative vertices are each off by
#: a few ulps of that coordinate (2^-24 relative); 2^-13 clears that ~2000
#: times over, so no ray re-hits the triangle it leaves, while staying far
#: below a triangle's size (the same idea as Mitsuba 3's relative RayEpsilon).
BOUNCE_OFFSET = 2.0 ** -13


@dataclass(frozen=True)
class Config:
    meshes: tuple[str, ...]                   # files in scenes/meshes, traced as they are
    scene: str                                # file in scenes/ (its camera gives primary rays)
    resolutions: tuple[tuple[int, int], ...]  # primary-ray images, (width, height)
    incoherent_rays: int
    repeats: int                              # timed queries after one warm-up
    scaling: tuple[int, ...]                  # triangles of the scaling series' surfaces
    scaling_resolution: tuple[int, int]       # the scaling series' workload
    seed: int = 1


FULL = Config(meshes=("bunny.ply", "armadillo.ply", "lucy.ply"), scene="reference.toml",
              resolutions=((1280, 720), (2048, 1536)), incoherent_rays=1_000_000, repeats=5,
              scaling=tuple(int(n) for n in np.geomspace(2_000, 4_000_000, 8)),
              scaling_resolution=(1280, 720))
QUICK = Config(meshes=("bunny_small.ply",), scene="bunny_small.toml",
               resolutions=((64, 48),), incoherent_rays=4096, repeats=1,
               scaling=(1_000, 4_000, 16_000), scaling_resolution=(64, 48))


# ---------------------------------------------------------------- rays

@dataclass
class Rays:
    name: str               # "primary 1280x720", "incoherent 1,000,000"
    kind: str               # "primary" (coherent) or "incoherent"
    origins: np.ndarray     # (R, 3) float32
    directions: np.ndarray  # (R, 3) float32, unit length

    def __len__(self) -> int:
        return len(self.origins)


def primary_rays(camera: hlbvh_cl.Camera, width: int, height: int) -> Rays:
    return Rays(f"primary {width}x{height}", "primary", *camera.rays(width, height))


def framed_camera(lo, hi, aspect: float, fov_deg: float = FRAMED_FOV_DEG) -> hlbvh_cl.Camera:
    """A camera looking at the box [lo, hi] along its thinnest axis, turned
    so that the box fills as much of the picture as it can, and far enough
    that all of it is in the picture."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    extent, centre = hi - lo, (lo + hi) / 2
    thin, *sides = np.argsort(extent, kind="stable")
    half = math.tan(math.radians(fov_deg) / 2)

    def distance(up: int, across: int) -> float:
        # the face of the box nearest the camera is the one that must fit
        return max(extent[up] / 2 / half, extent[across] / 2 / (half * aspect), 1e-6) * 1.05

    # the longest side up, unless the box fills more of the picture lying down
    up, across = min((sides[::-1], sides), key=lambda pair: distance(*pair))
    eye = centre + np.eye(3)[thin] * (extent[thin] / 2 + distance(up, across))
    return hlbvh_cl.Camera(tuple(eye), tuple(centre), tuple(np.eye(3)[up]), fov_deg)


def incoherent_rays(lo, hi, count: int, seed: int) -> Rays:
    """Origins uniform on a sphere around the box [lo, hi], each aimed at a
    uniform random point inside the box."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    rng = np.random.default_rng(seed)
    centre = (lo + hi) / 2
    radius = SPHERE_RADIUS_FACTOR * max(np.linalg.norm(hi - lo) / 2, 1e-6)
    normal = rng.normal(size=(count, 3))
    origins = centre + radius * normal / np.linalg.norm(normal, axis=1, keepdims=True)
    directions = lo + rng.random((count, 3)) * (hi - lo) - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return Rays(f"incoherent {count:,}", "incoherent",
                np.ascontiguousarray(origins, np.float32),
                np.ascontiguousarray(directions, np.float32))


def solid_meshes(meshes) -> list[int]:
    """Indices of the meshes with extent along every axis: all but a scene
    file's flat ground (all of them when every mesh is flat)."""
    solid = [i for i, m in enumerate(meshes) if np.ptp(m.vertices, axis=0).min() > 0]
    return solid or list(range(len(meshes)))


def orthonormal_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors that make (t, b, n) orthonormal for unit normals n
    (R, 3): Duff et al. 2017, "Building an Orthonormal Basis, Revisited"."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    return t, np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)


def bounce_rays(meshes, rays: Rays, geom_id, prim_id, u, v, seed: int) -> Rays:
    """One diffuse bounce from every hit of ``rays`` on a solid mesh
    (solid_meshes): the hit point from its barycentrics (u, v) on face
    prim_id of mesh geom_id, in float64; the direction cosine-distributed
    about the geometric normal cross(v1 - v0, v2 - v0) turned to face the
    incoming ray (Malley's method: uniform on the unit disk, lifted to the
    hemisphere; pbrt-v4, cosine-weighted hemisphere sampling); the origin lifted along that normal
    by BOUNCE_OFFSET.  Misses have geom_id -1."""
    geom_id, prim_id = np.asarray(geom_id), np.asarray(prim_id)
    keep = np.flatnonzero(np.isin(geom_id, solid_meshes(meshes)))
    corners = np.empty((len(keep), 3, 3))
    for g in np.unique(geom_id[keep]):
        mine = geom_id[keep] == g
        corners[mine] = meshes[g].vertices[meshes[g].faces[prim_id[keep][mine]]]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(normal, axis=1)
    area = length > 0  # a watertight hit has a plane; kept as a guard
    keep, corners, normal = keep[area], corners[area], normal[area] / length[area, None]
    incoming = rays.directions[keep].astype(np.float64)
    normal *= np.where((normal * incoming).sum(axis=1) > 0, -1.0, 1.0)[:, None]
    bu, bv = (np.asarray(x, np.float64)[keep, None] for x in (u, v))
    point = (1 - bu - bv) * corners[:, 0] + bu * corners[:, 1] + bv * corners[:, 2]
    origins = point + normal * (BOUNCE_OFFSET * np.abs(corners).max(axis=(1, 2)))[:, None]
    radius2, phi = np.random.default_rng(seed).random((2, len(keep)))
    radius, phi = np.sqrt(radius2), 2 * np.pi * phi
    tangent, bitangent = orthonormal_basis(normal)
    directions = ((radius * np.cos(phi))[:, None] * tangent
                  + (radius * np.sin(phi))[:, None] * bitangent
                  + np.sqrt(1 - radius2)[:, None] * normal)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return Rays(f"bounce {len(keep):,}", "bounce", np.ascontiguousarray(origins, np.float32),
                np.ascontiguousarray(directions, np.float32))


# ---------------------------------------------------------------- scenes

@dataclass
class SceneCase:
    """Meshes to trace, where the camera is, and the box incoherent rays aim at."""
    name: str
    meshes: list                              # hlbvh_cl.Mesh
    camera: hlbvh_cl.Camera | None            # None: framed on `box`
    box: tuple[np.ndarray, np.ndarray]
    built: dict = field(default_factory=dict)  # device id -> (Scene, seconds), already built

    @property
    def triangles(self) -> int:
        return sum(m.triangle_count for m in self.meshes)

    def geometry(self) -> tuple[np.ndarray, np.ndarray]:
        """All meshes as one: (vertices float32 (N, 3), faces int32 (M, 3))."""
        offsets = np.cumsum([0] + [m.vertex_count for m in self.meshes[:-1]])
        vertices = np.concatenate([m.vertices for m in self.meshes])
        faces = np.concatenate([m.faces + np.int32(o) for m, o in zip(self.meshes, offsets)])
        return np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces, np.int32)

    def workloads(self, resolutions, incoherent: int, seed: int,
                  bounce_device: str | None = None) -> list[Rays]:
        """Primary rays per resolution, the incoherent rays, and with
        ``bounce_device`` (a device id) the diffuse bounces of the last
        resolution's hits, traced there: on the reference scene at 2048x1536,
        the 374,672 bounces of issue 56's table."""
        out = [primary_rays(self.camera or framed_camera(*self.box, w / h), w, h)
               for w, h in resolutions]
        out.append(incoherent_rays(*self.box, incoherent, seed))
        if bounce_device is not None:
            camera = out[len(resolutions) - 1]
            hits = self.trace(camera, bounce_device)
            out.append(bounce_rays(self.meshes, camera, hits.geom_id, hits.prim_id, hits.u,
                                   hits.v, seed))
        return out

    def trace(self, rays: Rays, device_id: str):
        """Closest hits of ``rays`` on ``device_id``: on the scene built
        there already (left for the bench), else on one built for this."""
        if device_id in self.built:
            return self.built[device_id][0].intersect(rays.origins, rays.directions)
        return hlbvh_cl.Scene(self.meshes, device=device_id).intersect(rays.origins,
                                                                       rays.directions)


def mesh_case(filename: str) -> SceneCase:
    mesh = hlbvh_cl.Mesh.load(MESHES / filename)
    return SceneCase(filename, [mesh], None, bounds([mesh]))


def scene_file_case(filename: str, device_id: str) -> SceneCase:
    """The scene file's meshes and camera, built on ``device_id`` on the way
    (that device then uses the built scene)."""
    elapsed = stopwatch()
    loaded = hlbvh_cl.io.scenefile.load(SCENES / filename, device=device_id)
    seconds = elapsed() - loaded.load_seconds
    scene, meshes = loaded.scene, list(loaded.scene.meshes)
    if len(scene.spheres):
        # the peers trace triangles: every tracer gets the analytic spheres
        # as their meshes (this bench times the walk over triangles)
        meshes = [entry.mesh for entry in hlbvh_cl.io.scenefile.read(SCENES / filename)
                  .surfaces()]
        elapsed = stopwatch()
        scene = hlbvh_cl.Scene(meshes, device=device_id)
        seconds = elapsed()
    solid = [meshes[i] for i in solid_meshes(meshes)]  # no ground
    return SceneCase(filename, meshes, loaded.camera, bounds(solid),
                     built={device_id: (scene, seconds)})


# ---------------------------------------------------------------- participants

class OurDevice:
    """hlbvh_cl.Scene on one OpenCL device with one builder ("pocl:0" for
    HLBVH, "pocl:0 lbvh" for LBVH), compact or not ("pocl:0 compact");
    keeps each built tree's stats."""

    kind = "device"

    def __init__(self, device, builder: str = "hlbvh", compact: bool = False):
        self.device_id, self.builder, self.compact = device.id, builder, compact
        self.name = " ".join([device.id] + ([builder] if builder != "hlbvh" else [])
                             + (["compact"] if compact else []))
        self.label = (f"{device.id} ({device.name})"
                      + ("" if builder == "hlbvh" else f", {builder}")
                      + (", compact" if compact else ""))
        self.scene = None
        self.trees: dict[str, dict] = {}

    def describe(self) -> dict:
        return {"kind": self.kind, "label": self.label, "available": True, "problem": None,
                "device": self.device_id, "builder": self.builder, "compact": self.compact}

    def build(self, case: SceneCase) -> float:
        if self.builder == "hlbvh" and self.name in case.built:
            self.scene, seconds = case.built.pop(self.name)
        else:
            elapsed = stopwatch()
            self.scene = hlbvh_cl.Scene(case.meshes, device=self.device_id, builder=self.builder,
                                        compact=self.compact)
            seconds = elapsed()
        s = self.scene.stats
        self.trees[case.name] = {"triangles": s.triangles, "nodes": s.nodes, "leaves": s.leaves,
                                 "depth": s.depth, "sah_cost": s.sah_cost,
                                 "node_bytes": s.node_bytes, "triangle_bytes": s.triangle_bytes,
                                 "tree_bytes": s.tree_bytes}
        return seconds

    def intersect(self, rays: Rays):
        return self.scene.intersect(rays.origins, rays.directions)

    def hits(self, result) -> np.ndarray:
        return result.hit

    def occluded(self, rays: Rays) -> np.ndarray:
        return self.scene.occluded(rays.origins, rays.directions)

    def close(self) -> None:
        self.scene = None


def build_participant(participant, case: SceneCase) -> float:
    """Seconds ``participant`` takes to build its structure for ``case``."""
    if participant.kind == "device":
        return participant.build(case)
    return participant.build(*case.geometry())


# ---------------------------------------------------------------- measuring

def _failed(errors: dict, participant, error: Exception) -> None:
    traceback.print_exc(file=sys.stderr)
    errors[participant.name] = f"{type(error).__name__}: {error}"


def time_round_robin(participants: list, call, repeats: int, errors: dict,
                     warm_up=None) -> dict:
    """``warm_up(participant)`` (default ``call``) once per participant, then
    ``repeats`` rounds of one timed ``call`` each, each right after an
    untimed ``call`` of the same participant.  A participant that raises
    is dropped and named in ``errors``.  Returns {name: (last result, wall
    seconds)}; with repeats 0, the warm-up's result and no seconds.

    The untimed call is there because a participant's worker threads may
    keep a core busy for a while after its call returns (Mitsuba's Dr.Jit
    pool measured so, by how much slower the call after it ran): a timed
    call straight after another participant's would pay for that one's
    threads.  After a call of its own it runs as a user's loop of calls
    runs, with its own threads awake and no one else's, and every
    participant is timed alike."""
    alive, last = [], {}
    for participant in participants:
        try:
            last[participant.name] = (warm_up or call)(participant)
            alive.append(participant)
        except Exception as error:  # a broken peer must not end the run
            _failed(errors, participant, error)
    walls = {p.name: [] for p in alive}
    for _ in range(repeats):
        for participant in list(alive):
            try:
                call(participant)  # untimed: see above
                elapsed = stopwatch()
                last[participant.name] = call(participant)
                walls[participant.name].append(elapsed())
            except Exception as error:
                _failed(errors, participant, error)
                alive.remove(participant)
    return {p.name: (last[p.name], walls[p.name]) for p in alive}


def build_all(case: SceneCase, participants: list, errors: dict) -> tuple[list, dict]:
    """Each participant's structure for ``case``: (built participants, build seconds)."""
    built, seconds = [], {}
    for participant in participants:
        try:
            seconds[participant.name] = build_participant(participant, case)
            built.append(participant)
        except Exception as error:
            _failed(errors, participant, error)
            participant.close()
    return built, seconds


def close_all(participants: list) -> None:
    for participant in participants:
        participant.close()
    gc.collect()


def bench_case(case: SceneCase, workloads: list[Rays], participants: list, repeats: int,
               bar=None) -> dict:
    """Every participant on every workload of one scene, closest hit and any
    hit, each timed round-robin over the participants."""
    errors: dict = {}
    built, build_seconds = build_all(case, participants, errors)
    out = {"name": case.name, "triangles": case.triangles, "meshes": len(case.meshes),
           "build_s": build_seconds, "errors": errors, "workloads": [],
           "trees": {p.name: p.trees[case.name] for p in built
                     if p.kind == "device" and case.name in p.trees}}
    try:
        for rays in workloads:
            if bar is not None:
                bar.set_postfix_str(f"{case.name}: {rays.name}")
            closest = time_round_robin(built, lambda p: p.intersect(rays), repeats, errors)
            anyhit = time_round_robin(built, lambda p: p.occluded(rays), repeats, errors)
            results, masks = {}, {}
            for p in built:
                if p.name in closest and p.name in anyhit:
                    (found, walls), (blocked, blocked_walls) = closest[p.name], anyhit[p.name]
                    masks[p.name] = (np.asarray(p.hits(found), bool), np.asarray(blocked, bool))
                    results[p.name] = {
                        "intersect_s": summary(walls), "intersect_mrays": rates(len(rays), walls),
                        "occluded_s": summary(blocked_walls),
                        "occluded_mrays": rates(len(rays), blocked_walls),
                        "hits": int(masks[p.name][0].sum()),
                        "occluded": int(masks[p.name][1].sum())}
            out["workloads"].append(compare({"name": rays.name, "kind": rays.kind,
                                             "rays": len(rays), "results": results}, masks,
                                            [p.name for p in participants if p.kind == "device"]))
            if bar is not None:
                bar.update()
    finally:
        close_all(built)
    return out


def compare(workload: dict, masks: dict, devices: list[str]) -> dict:
    """Adds each result's hit/miss disagreement with the reference and our
    speed over each peer's ("ratios": device -> peer -> query -> ratio)."""
    reference = REFERENCE if REFERENCE in masks else next(iter(masks), None)
    workload["reference"] = reference
    results = workload["results"]
    for name, figure in results.items():
        figure["disagreement"] = {q: float(np.mean(masks[name][i] != masks[reference][i]))
                                  for i, q in enumerate(("intersect", "occluded"))}
    workload["ratios"] = {
        device: {peer: {q: ratio(results[device][f"{q}_mrays"]["median"],
                                 theirs[f"{q}_mrays"]["median"]) for q in ("intersect", "occluded")}
                 for peer, theirs in results.items() if peer not in devices}
        for device in devices if device in results}
    return workload


def bench_scaling(config: Config, participants: list, bar=None) -> dict:
    """One workload over one surface tessellated finer (config.scaling)."""
    width, height = config.scaling_resolution
    points = []
    for triangles in config.scaling:
        mesh = surface(triangles)
        case = SceneCase(mesh.name, [mesh], None, bounds([mesh]))
        rays = primary_rays(framed_camera(*case.box, width / height), width, height)
        if bar is not None:
            bar.set_postfix_str(f"scaling: {mesh.name}")
        errors: dict = {}
        built, _ = build_all(case, participants, errors)
        try:
            timed = time_round_robin(built, lambda p: p.intersect(rays), config.repeats, errors)
            results = {p.name: {"intersect_s": summary(timed[p.name][1]),
                                "hits": int(np.asarray(p.hits(timed[p.name][0])).sum())}
                       for p in built if p.name in timed}
        finally:
            close_all(built)
        points.append({"mesh": mesh.name, "triangles": mesh.triangle_count, "rays": len(rays),
                       "results": results, "errors": errors})
        if bar is not None:
            bar.update()
    alpha = {}
    for p in participants:
        series = [(pt["triangles"], pt["results"][p.name]["intersect_s"]["median"])
                  for pt in points if p.name in pt["results"]]
        alpha[p.name] = fit_exponent(*zip(*series)) if series else None
    return {"workload": f"primary {width}x{height} (framed)", "points": points, "alpha": alpha}


# ---------------------------------------------------------------- the command

def _ratio(workload: dict, device: str, peer: str) -> str | None:
    value = workload["ratios"].get(device, {}).get(peer, {}).get("intersect")
    return None if value is None else f"{value:.2f}"


def format_results(results: dict) -> str:
    names = [n for n, p in results["participants"].items() if p["available"]]
    out = [f"peer {n} is missing: {p['problem']}" for n, p in results["participants"].items()
           if not p["available"]]
    rows = [(s, w) for s in results["scenes"] for w in s["workloads"]]
    for q, title in (("intersect", "closest hit"), ("occluded", "any hit")):
        out.append(table(
            ["scene", "workload", *names],
            [[s["name"], w["name"], *[spread(w["results"][n][f"{q}_mrays"], digits=2)
                                      if n in w["results"] else None for n in names]]
             for s, w in rows],
            title=f"{title}, Mrays/s: median (min-max), numpy in and out"))
    pairs = sorted({(d, p) for _, w in rows for d in w["ratios"] for p in w["ratios"][d]})
    out.append(table(["scene", "workload", *[f"{d}/{p}" for d, p in pairs]],
                     [[s["name"], w["name"], *[_ratio(w, d, p) for d, p in pairs]] for s, w in rows],
                     title="closest hit, our speed / the peer's (> 1: ours is faster)"))
    out.append(table(["scene", "workload", "hits", *names],
                     [[s["name"], w["name"], w["results"][w["reference"]]["hits"],
                       *[f"{w['results'][n]['disagreement']['intersect']:.1e}"
                         if n in w["results"] else None for n in names]] for s, w in rows],
                     title="fraction of rays whose hit/miss differs from the reference's"))
    out.append(table(
        ["scene", "device", "nodes MiB", "leaf triangles MiB", "tree MiB", "bytes/triangle"],
        [[s["name"], name, f"{t['node_bytes'] / 2**20:.2f}", f"{t['triangle_bytes'] / 2**20:.2f}",
          f"{t['tree_bytes'] / 2**20:.2f}", f"{t['tree_bytes'] / t['triangles']:.1f}"]
         for s in results["scenes"] for name, t in s.get("trees", {}).items()],
        title="tree memory traversal reads on the device: wide nodes + leaf triangles"))
    scaling = results["scaling"]
    out.append(table(["mesh", "triangles", *names],
                     [[p["mesh"], p["triangles"], *[spread(p["results"][n]["intersect_s"], 1e3)
                                                    if n in p["results"] else None
                                                    for n in names]] for p in scaling["points"]],
                     title=f"scaling: {scaling['workload']}, closest-hit wall ms"))
    out.append("time ~ triangles^alpha: " + ", ".join(
        f"{n} {a:.3f}" for n, a in scaling["alpha"].items() if a is not None))
    out += [f"FAILED {where['name']} {name}: {error}"
            for where in results["scenes"] + scaling["points"]
            for name, error in where["errors"].items()]
    return "\n\n".join(out)


def main(argv=None) -> dict:
    args = arguments(__doc__.splitlines()[0], argv,
                     (["--peers"], {"default": ",".join(PEERS),
                                    "help": f"comma-separated peers (default: {','.join(PEERS)})"}),
                     (["--scene"], {"default": None, "metavar": "FILE",
                                    "help": "trace only this scene file of scenes/ "
                                            "(e.g. cornell_box.xml): no lone meshes, no scaling"}),
                     (["--compact"], {"action": "store_true",
                                      "help": "also trace each device's compact tree "
                                              "(Scene(..., compact=True)), interleaved"}))
    config = QUICK if args.quick else FULL
    if args.scene is not None:
        if not (SCENES / args.scene).is_file():
            sys.exit(f"bench.trace: no scene file {args.scene!r} in {SCENES}")
        config = replace(config, meshes=(), scene=args.scene, scaling=())
    elapsed = stopwatch()
    chosen = devices_or_exit(args.devices)
    peers, missing = load_peers([p.strip() for p in args.peers.split(",") if p.strip()])
    devices = [OurDevice(d, compact=compact) for d in chosen
               for compact in ((False, True) if args.compact else (False,))]
    participants = devices + peers
    say(f"devices: {', '.join(d.id for d in chosen)}; peers: "
        + (", ".join(f"{p.name} {p.version}" for p in peers) or "none")
        + "".join(f"; {p.name} missing" for p in missing))

    results = {"config": asdict(config), "quick": args.quick, "machine": machine_info(),
               "participants": {p.name: p.describe() for p in participants + missing},
               "scenes": []}
    steps = (len(config.meshes) + 1) * (len(config.resolutions) + 2) + len(config.scaling)
    with progress(steps, "trace bench", enabled=not args.no_progress) as bar:
        for filename in (*config.meshes, config.scene):
            case = (scene_file_case(filename, chosen[0].id) if filename == config.scene
                    else mesh_case(filename))
            workloads = case.workloads(config.resolutions, config.incoherent_rays, config.seed,
                                       bounce_device=chosen[0].id)
            results["scenes"].append(bench_case(case, workloads, participants, config.repeats, bar))
        results["scaling"] = bench_scaling(
            config, devices + [p for p in peers if p.name == REFERENCE], bar)
    print(format_results(results))
    return finish(results, "trace", args, elapsed, plots.trace)


if __name__ == "__main__":
    main()
