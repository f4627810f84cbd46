"""Ray-tracing benchmark: our closest-hit and any-hit queries against Embree, Open3D, Mitsuba 3
and trimesh, on the same rays.

    python bench/trace.py [--quick] [--devices pocl,intel] [--peers embreex,mitsuba] [--out bench/results]

Scenes: the bunny, the armadillo and Lucy as they are, and the reference
scene (scenes/reference.toml through hlbvh_cl.cli.load_scene, 2.91M
triangles).  Workloads per scene, generated once in numpy and given to every
participant as the same float32 arrays (unit directions):
  - primary rays of a pinhole camera at 1280x720 and 2048x1536: the scene
    file's camera for the reference scene, a camera framed on the bounds for
    a single mesh (framed_camera);
  - 1M incoherent rays: origins uniform on a sphere around the objects,
    each aimed at a uniform random point of their bounds (the reference
    scene's ground is left out of those bounds: it would hold most of them).

Participants: every working OpenCL device (scene.intersect / scene.occluded)
and the peers that are installed (the `bench` extra):
  - embreex (Embree 4), rays split over EMBREE_THREADS Python threads
    (its run releases the GIL);
  - Open3D's RaycastingScene (cast_rays / test_occlusions, all cores);
  - Mitsuba 3 `llvm_ad_rgb` (ray_intersect_preliminary / ray_test, all cores,
    `coherent` set for primary rays);
  - trimesh's embreex-backed RayMeshIntersector (one thread, as trimesh runs it).
A peer that cannot be imported is reported as missing.  Peers see one mesh:
the scene's meshes concatenated.

Timing: each participant's structure is built once, outside the timing (its
build time is reported apart; ours includes kernel compilation or the kernel
cache's load).  Each query runs once per participant to warm up, then in
``repeats`` rounds of one call per participant, so that all of them meet
about the same load from other processes on a shared machine; the time is
the host's wall time of one call, numpy arrays in and numpy arrays out, so
conversions each API needs are counted.  Reported: Mrays/s from the
median (min-max) time, ratios of each of our devices to each peer (> 1: ours
is faster), and each participant's hit/miss disagreement with Embree.  For
our devices the kernels' own time (profiling events) is kept too.

Scaling: one fixed workload (primary rays framed on the mesh) over one
surface, Lucy, tessellated ever finer: lucy_small (2,000 triangles, a
decimation of lucy.ply) and lucy.ply, each with every edge split in k
(hlbvh_cl.split.split_edges), 2K..3.6M triangles, on our devices and
embreex.  The surface, the camera and so which rays hit stay the same: only
the triangle count changes.  (Cutting pieces of growing size out of a mesh,
as bench/build.py does for builds, would also change how many rays hit.)
time ~ triangles^alpha is fitted by least squares in log-log.

Writes <out>/trace.json and <out>/trace.png, prints tables on stdout and a
progress bar on stderr.  Figures are of one run on a shared 2-core machine.
"""
from __future__ import annotations

import argparse
import gc
import importlib
import importlib.metadata
import math
import sys
import traceback
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # common.py and build.py

import numpy as np  # noqa: E402
from common import (MESHES, SCENES, machine_info, peak_rss_bytes, pick_devices,  # noqa: E402
                    progress, pyplot, quiet_compiler_warnings, ratio, save_figure, stopwatch,
                    summary, table, write_json)

from hlbvh_cl import Mesh, Scene  # noqa: E402
from hlbvh_cl.cli import load_scene  # noqa: E402
from hlbvh_cl.split import split_edges  # noqa: E402

#: Python threads the embreex peer splits its rays over (one per core here).
EMBREE_THREADS = 2
#: vertical field of view of the cameras framed on a mesh's bounds, degrees
FRAMED_FOV_DEG = 40.0
#: incoherent rays start on a sphere this many half-diagonals from the centre
SPHERE_RADIUS_FACTOR = 1.5


@dataclass(frozen=True)
class Config:
    meshes: tuple[str, ...]                   # files in scenes/meshes, traced as they are
    scene: str                                # file in scenes/ (its camera gives the primary rays)
    resolutions: tuple[tuple[int, int], ...]  # primary-ray images, (width, height)
    incoherent_rays: int
    repeats: int                              # timed queries after one warm-up
    scaling: tuple[tuple[str, int], ...]      # (file in scenes/meshes, edge split k), one surface
    scaling_resolution: tuple[int, int]       # the scaling series' fixed workload
    seed: int = 1


FULL = Config(meshes=("bunny.ply", "armadillo.ply", "lucy.ply"), scene="reference.toml",
              resolutions=((1280, 720), (2048, 1536)), incoherent_rays=1_000_000, repeats=5,
              scaling=(("lucy_small.ply", 1), ("lucy_small.ply", 2), ("lucy_small.ply", 4),
                       *(("lucy.ply", k) for k in range(1, 7))),
              scaling_resolution=(1280, 720))
QUICK = Config(meshes=("bunny_small.ply",), scene="bunny_small.toml",
               resolutions=((32, 24), (64, 48)), incoherent_rays=4096, repeats=1,
               scaling=(("lucy_small.ply", 1), ("lucy_small.ply", 2), ("lucy_small.ply", 3)),
               scaling_resolution=(64, 48))


# ---------------------------------------------------------------- rays

@dataclass(frozen=True)
class Camera:
    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float]
    fov_deg: float  # vertical


@dataclass
class Rays:
    name: str               # "primary 1280x720", "incoherent 1,000,000"
    kind: str               # "primary" (coherent) or "incoherent"
    origins: np.ndarray     # (R, 3) float32
    directions: np.ndarray  # (R, 3) float32, unit length

    def __len__(self) -> int:
        return len(self.origins)


def camera_rays(camera: Camera, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """One ray through each pixel centre, rows from the top, in the scene
    file's convention (hlbvh_cl/scenefile.py): (origins, unit directions)."""
    eye, target, up = (np.asarray(v, np.float64) for v in (camera.eye, camera.target, camera.up))
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    half = math.tan(math.radians(camera.fov_deg) / 2)
    x = (2 * (np.arange(width) + 0.5) / width - 1) * (width / height) * half
    y = (1 - 2 * (np.arange(height) + 0.5) / height) * half
    directions = (forward + x[None, :, None] * right + y[:, None, None] * true_up).reshape(-1, 3)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    origins = np.broadcast_to(eye, directions.shape)
    return np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(directions, np.float32)


def framed_camera(lo, hi, aspect: float, fov_deg: float = FRAMED_FOV_DEG) -> Camera:
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
    # (the nearer camera shows it larger)
    up, across = min((sides[::-1], sides), key=lambda pair: distance(*pair))
    eye = centre + np.eye(3)[thin] * (extent[thin] / 2 + distance(up, across))
    return Camera(tuple(eye), tuple(centre), tuple(np.eye(3)[up]), fov_deg)


def incoherent_rays(lo, hi, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Origins uniform on a sphere around the box [lo, hi], each aimed at a
    uniform random point inside the box: (origins, unit directions)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    rng = np.random.default_rng(seed)
    centre = (lo + hi) / 2
    radius = SPHERE_RADIUS_FACTOR * max(np.linalg.norm(hi - lo) / 2, 1e-6)
    normal = rng.normal(size=(count, 3))
    origins = centre + radius * normal / np.linalg.norm(normal, axis=1, keepdims=True)
    directions = lo + rng.random((count, 3)) * (hi - lo) - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(directions, np.float32)


# ---------------------------------------------------------------- scenes

@dataclass
class SceneCase:
    """Meshes to trace, where the camera is, and the box incoherent rays aim at."""
    name: str
    meshes: list                       # hlbvh_cl.Mesh
    camera: Camera | None              # None: framed on `bounds`
    bounds: tuple[np.ndarray, np.ndarray]
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

    def workloads(self, config: Config) -> list[Rays]:
        out = []
        for width, height in config.resolutions:
            camera = self.camera or framed_camera(*self.bounds, width / height)
            out.append(Rays(f"primary {width}x{height}", "primary",
                            *camera_rays(camera, width, height)))
        out.append(Rays(f"incoherent {config.incoherent_rays:,}", "incoherent",
                        *incoherent_rays(*self.bounds, config.incoherent_rays, config.seed)))
        return out


def _union_bounds(meshes) -> tuple[np.ndarray, np.ndarray]:
    boxes = [m.bounds() for m in meshes]
    return (np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0))


def mesh_case(filename: str) -> SceneCase:
    mesh = Mesh.load(MESHES / filename)
    return SceneCase(filename, [mesh], None, mesh.bounds())


def scene_file_case(filename: str, device_id: str) -> SceneCase:
    """The scene file's meshes and camera; load_scene builds it on `device_id`
    on the way, which that device then uses."""
    elapsed = stopwatch()
    scene, description, load_seconds = load_scene(SCENES / filename, device=device_id)
    build_seconds = elapsed() - load_seconds
    c = description.camera
    objects = [entry.mesh for entry in description.meshes]  # not the ground
    return SceneCase(filename, list(scene.meshes), Camera(c.eye, c.target, c.up, c.fov_deg),
                     _union_bounds(objects), built={device_id: (scene, build_seconds)})


# ---------------------------------------------------------------- participants

class OurDevice:
    """hlbvh_cl.Scene on one OpenCL device."""

    kind = "device"

    def __init__(self, device):
        self.name = device.id
        self.label = f"{device.id} ({device.name})"
        self.scene: Scene | None = None

    def describe(self) -> dict:
        return {"kind": self.kind, "label": self.label, "available": True, "problem": None}

    def build(self, case: SceneCase) -> float:
        if self.name in case.built:
            self.scene, seconds = case.built.pop(self.name)
            return seconds
        elapsed = stopwatch()
        self.scene = Scene(case.meshes, device=self.name)
        return elapsed()

    def intersect(self, rays: Rays):
        return self.scene.intersect(rays.origins, rays.directions)

    def hits(self, result) -> np.ndarray:
        return result.hit

    def occluded(self, rays: Rays) -> np.ndarray:
        return self.scene.occluded(rays.origins, rays.directions)

    def kernel_seconds(self) -> float:
        """Device time of the last query's kernels."""
        return self.scene._ray_query().last_kernel_ms * 1e-3

    def close(self) -> None:
        self.scene = None


class Peer:
    """Another ray tracer, imported on first use; ``problem`` says why it cannot run."""

    kind = "peer"
    name = ""
    label = ""
    distribution = ""           # the PyPI package, for its version
    modules: tuple[str, ...] = ()

    def __init__(self):
        self.problem: str | None = None
        self.version: str | None = None

    def load(self) -> bool:
        """Import the peer; False (with ``problem`` set) when it is missing or broken."""
        try:
            self._import()
            self.version = importlib.metadata.version(self.distribution)
        except Exception as error:  # ImportError, OSError (a missing libusb), RuntimeError (no LLVM)
            self.problem = f"{type(error).__name__}: {error}".strip()
        return self.problem is None

    def _import(self) -> None:
        for module in self.modules:
            importlib.import_module(module)

    def describe(self) -> dict:
        return {"kind": self.kind, "label": self.label, "available": self.problem is None,
                "version": self.version, "problem": self.problem}

    def kernel_seconds(self) -> None:
        return None

    def close(self) -> None:
        pass


class EmbreexPeer(Peer):
    name, distribution = "embreex", "embreex"
    label = f"embreex (Embree 4), {EMBREE_THREADS} threads"
    modules = ("embreex.rtcore_scene", "embreex.mesh_construction")

    def __init__(self, threads: int = EMBREE_THREADS):
        super().__init__()
        self.threads = threads
        self.pool: ThreadPoolExecutor | None = None
        self.scene = None

    def build(self, case: SceneCase) -> float:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
        vertices, faces = case.geometry()
        elapsed = stopwatch()
        self.scene = rtcore_scene.EmbreeScene()
        TriangleMesh(self.scene, vertices, faces)
        self.scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))  # commits the BVH
        seconds = elapsed()
        self.pool = ThreadPoolExecutor(self.threads)
        return seconds

    def _run(self, rays: Rays, **options) -> list:
        bounds = np.linspace(0, len(rays), self.threads + 1).astype(int)
        futures = [self.pool.submit(self.scene.run, rays.origins[a:b], rays.directions[a:b],
                                    **options) for a, b in zip(bounds[:-1], bounds[1:])]
        return [f.result() for f in futures]

    def intersect(self, rays: Rays) -> dict:
        parts = self._run(rays, output=1)
        return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}

    def hits(self, result) -> np.ndarray:
        return result["primID"] >= 0

    def occluded(self, rays: Rays) -> np.ndarray:
        # embreex's OCCLUDED query gives 0 for an occluded ray and -1 otherwise
        return np.concatenate(self._run(rays, query="OCCLUDED")) != -1

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()
        self.pool = self.scene = None


class Open3DPeer(Peer):
    name, distribution = "open3d", "open3d"
    label = "Open3D RaycastingScene"
    modules = ("open3d",)

    def build(self, case: SceneCase) -> float:
        import open3d
        vertices, faces = case.geometry()
        elapsed = stopwatch()
        self.scene = open3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(open3d.core.Tensor(vertices), open3d.core.Tensor(faces.astype(np.uint32)))
        self.scene.cast_rays(open3d.core.Tensor(np.array([[0, 0, 0, 1, 1, 1]], np.float32)))  # builds
        return elapsed()

    def _tensor(self, rays: Rays):
        import open3d
        return open3d.core.Tensor(np.concatenate([rays.origins, rays.directions], axis=1))

    def intersect(self, rays: Rays) -> dict:
        answer = self.scene.cast_rays(self._tensor(rays))
        return {key: answer[key].numpy() for key in
                ("t_hit", "geometry_ids", "primitive_ids", "primitive_uvs", "primitive_normals")}

    def hits(self, result) -> np.ndarray:
        return np.isfinite(result["t_hit"])

    def occluded(self, rays: Rays) -> np.ndarray:
        return self.scene.test_occlusions(self._tensor(rays)).numpy()

    def close(self) -> None:
        self.scene = None


class MitsubaPeer(Peer):
    name, distribution = "mitsuba", "mitsuba"
    label = "Mitsuba 3 llvm_ad_rgb"
    variant = "llvm_ad_rgb"

    def _import(self) -> None:
        import mitsuba
        mitsuba.set_variant(self.variant)  # fails without libLLVM

    def build(self, case: SceneCase) -> float:
        import mitsuba as mi
        vertices, faces = case.geometry()
        elapsed = stopwatch()
        mesh = mi.Mesh("bench", len(vertices), len(faces), has_vertex_normals=False,
                       has_vertex_texcoords=False)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(vertices.ravel())
        params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
        params.update()
        self.scene = mi.load_dict({"type": "scene", "mesh": mesh})
        return elapsed()

    def _ray(self, rays: Rays):
        import mitsuba as mi
        o, d = rays.origins, rays.directions
        column = [np.ascontiguousarray(a[:, i]) for a in (o, d) for i in range(3)]
        return mi.Ray3f(o=mi.Point3f(*column[:3]), d=mi.Vector3f(*column[3:]))

    def intersect(self, rays: Rays) -> dict:
        import drjit as dr
        import mitsuba as mi
        found = self.scene.ray_intersect_preliminary(self._ray(rays), coherent=rays.kind == "primary")
        valid = found.is_valid()  # a miss has t = inf but prim_index 0
        t = dr.select(valid, found.t, dr.inf)
        prim = dr.select(valid, mi.Int32(found.prim_index), -1)
        uv = found.prim_uv
        dr.eval(t, prim, uv)
        return {"t": t.numpy(), "prim_index": prim.numpy(), "uv": uv.numpy()}

    def hits(self, result) -> np.ndarray:
        return result["prim_index"] >= 0

    def occluded(self, rays: Rays) -> np.ndarray:
        hit = self.scene.ray_test(self._ray(rays), coherent=rays.kind == "primary")
        return hit.numpy().astype(bool)

    def close(self) -> None:
        self.scene = None


class TrimeshPeer(Peer):
    name, distribution = "trimesh", "trimesh"
    label = "trimesh RayMeshIntersector (embreex, 1 thread)"
    modules = ("trimesh", "trimesh.ray.ray_pyembree")

    def build(self, case: SceneCase) -> float:
        import trimesh
        from trimesh.ray.ray_pyembree import RayMeshIntersector
        vertices, faces = case.geometry()
        elapsed = stopwatch()
        self.intersector = RayMeshIntersector(trimesh.Trimesh(vertices, faces, process=False))
        self.intersector.intersects_first(np.zeros((1, 3)), np.ones((1, 3)))  # builds
        return elapsed()

    def intersect(self, rays: Rays) -> np.ndarray:
        return self.intersector.intersects_first(rays.origins, rays.directions)

    def hits(self, result) -> np.ndarray:
        return result >= 0

    def occluded(self, rays: Rays) -> np.ndarray:
        return self.intersector.intersects_any(rays.origins, rays.directions)

    def close(self) -> None:
        self.intersector = None


PEERS = {peer.name: peer for peer in (EmbreexPeer, Open3DPeer, MitsubaPeer, TrimeshPeer)}
#: hit/miss agreement is measured against this participant when it runs
REFERENCE = "embreex"


def load_peers(names) -> tuple[list[Peer], list[Peer]]:
    """(available, missing) peers among ``names`` (keys of PEERS)."""
    available, missing = [], []
    for name in names:
        if name not in PEERS:
            raise ValueError(f"unknown peer {name!r}; known: {', '.join(PEERS)}")
        peer = PEERS[name]()
        (available if peer.load() else missing).append(peer)
    return available, missing


# ---------------------------------------------------------------- measuring

def _failed(errors: dict, participant, error: Exception) -> None:
    traceback.print_exc(file=sys.stderr)
    errors[participant.name] = f"{type(error).__name__}: {error}"


def time_round_robin(participants: list, call, repeats: int, errors: dict) -> dict:
    """``call(participant)`` once per participant to warm up, then ``repeats``
    rounds of one timed call each, so that every participant meets about the
    same load from other processes.  A participant that raises is dropped
    (and named in ``errors``).  Returns {name: (last result, wall seconds,
    kernel seconds or None)}."""
    alive, last = [], {}
    for participant in participants:
        try:
            last[participant.name] = call(participant)
            alive.append(participant)
        except Exception as error:  # a broken peer must not end the run
            _failed(errors, participant, error)
    walls = {p.name: [] for p in alive}
    kernels = {p.name: [] for p in alive}
    for _ in range(repeats):
        for participant in list(alive):
            try:
                elapsed = stopwatch()
                last[participant.name] = call(participant)
                walls[participant.name].append(elapsed())
                kernels[participant.name].append(participant.kernel_seconds())
            except Exception as error:
                _failed(errors, participant, error)
                alive.remove(participant)
    return {p.name: (last[p.name], walls[p.name],
                     None if None in kernels[p.name] else kernels[p.name]) for p in alive}


def _rates(rays: int, seconds: list[float]) -> dict:
    """Mrays/s from the median, slowest and fastest time."""
    s = summary(seconds)
    return {"median": rays / s["median"] / 1e6, "min": rays / s["max"] / 1e6,
            "max": rays / s["min"] / 1e6}


def build_all(case: SceneCase, participants: list, errors: dict, bar=None) -> tuple[list, dict]:
    """Each participant's structure for ``case``: (built participants, build seconds)."""
    built, seconds = [], {}
    for participant in participants:
        if bar is not None:
            bar.set_postfix_str(f"{case.name}: building {participant.name}")
        try:
            seconds[participant.name] = participant.build(case)
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
    built, build_seconds = build_all(case, participants, errors, bar)
    out = {"name": case.name, "triangles": case.triangles, "meshes": len(case.meshes),
           "build_s": build_seconds, "errors": errors, "workloads": []}
    masks: list[dict] = []
    try:
        for rays in workloads:
            if bar is not None:
                bar.set_postfix_str(f"{case.name}: {rays.name}")
            closest = time_round_robin(built, lambda p: p.intersect(rays), repeats, errors)
            occluded = time_round_robin(built, lambda p: p.occluded(rays), repeats, errors)
            results, workload_masks = {}, {}
            for participant in built:
                name = participant.name
                if name in errors:
                    continue
                hit_result, walls, kernels = closest[name]
                blocked, blocked_walls, blocked_kernels = occluded[name]
                hit = np.asarray(participant.hits(hit_result), bool)
                blocked = np.asarray(blocked, bool)
                results[name] = {
                    "intersect_s": summary(walls), "intersect_mrays": _rates(len(rays), walls),
                    "intersect_kernel_s": summary(kernels) if kernels else None,
                    "occluded_s": summary(blocked_walls),
                    "occluded_mrays": _rates(len(rays), blocked_walls),
                    "occluded_kernel_s": summary(blocked_kernels) if blocked_kernels else None,
                    "hits": int(hit.sum()), "occluded": int(blocked.sum())}
                workload_masks[name] = (hit, blocked)
            out["workloads"].append({"name": rays.name, "kind": rays.kind, "rays": len(rays),
                                     "results": results})
            masks.append(workload_masks)
            if bar is not None:
                bar.update()
    finally:
        close_all(built)
    _compare(out, masks, [p.name for p in participants if p.kind == "device"])
    return out


def _compare(out: dict, masks: list[dict], devices: list[str]) -> None:
    """Hit/miss disagreement with the reference, and our/peer speed ratios."""
    for entry, found in zip(out["workloads"], masks):
        reference = REFERENCE if REFERENCE in found else next(iter(found), None)
        entry["reference"] = reference
        results = entry["results"]
        for name, figure in results.items():
            (hit, blocked), (ref_hit, ref_blocked) = found[name], found[reference]
            figure["disagreement"] = {"intersect": float(np.mean(hit != ref_hit)),
                                      "occluded": float(np.mean(blocked != ref_blocked))}
        entry["ratios"] = {
            device: {peer: {q: ratio(results[device][f"{q}_mrays"]["median"],
                                     theirs[f"{q}_mrays"]["median"])
                            for q in ("intersect", "occluded")}
                     for peer, theirs in results.items() if peer not in devices}
            for device in devices if device in results}


def fit_exponent(triangles, seconds) -> float | None:
    """alpha of seconds ~ c * triangles^alpha, least squares in log-log."""
    x, y = np.log(np.asarray(triangles, float)), np.log(np.asarray(seconds, float))
    if len(x) < 2 or np.ptp(x) == 0:
        return None
    return float(np.polyfit(x, y, 1)[0])


def bench_scaling(config: Config, participants: list, bar=None) -> dict:
    """One fixed workload over one surface split ever finer (config.scaling)."""
    width, height = config.scaling_resolution
    sources: dict[str, Mesh] = {}
    points = []
    for filename, k in config.scaling:
        name = f"{Path(filename).stem} split {k}"
        if bar is not None:
            bar.set_postfix_str(f"scaling: {name}")
        source = sources.setdefault(filename, Mesh.load(MESHES / filename))
        mesh = Mesh(*split_edges(source.vertices, source.faces, k), name=name)
        case = SceneCase(name, [mesh], None, mesh.bounds())
        camera = framed_camera(*case.bounds, width / height)
        rays = Rays(f"primary {width}x{height}", "primary", *camera_rays(camera, width, height))
        errors: dict = {}
        built, _ = build_all(case, participants, errors)
        try:
            timed = time_round_robin(built, lambda p: p.intersect(rays), config.repeats, errors)
            results = {}
            for participant in built:
                if participant.name not in timed:
                    continue
                result, walls, kernels = timed[participant.name]
                results[participant.name] = {
                    "intersect_s": summary(walls), "intersect_mrays": _rates(len(rays), walls),
                    "intersect_kernel_s": summary(kernels) if kernels else None,
                    "hits": int(np.asarray(participant.hits(result)).sum())}
        finally:
            close_all(built)
        points.append({"mesh": name, "triangles": mesh.triangle_count, "rays": len(rays),
                       "results": results, "errors": errors})
        if bar is not None:
            bar.update()
    # alpha from the median times; alpha_min from the fastest runs, which
    # other processes on a shared machine disturb least
    alpha, alpha_min, alpha_kernel = {}, {}, {}
    for participant in participants:
        series = [(p["triangles"], p["results"][participant.name]) for p in points
                  if participant.name in p["results"]]
        x = [n for n, _ in series]
        alpha[participant.name] = fit_exponent(x, [r["intersect_s"]["median"] for _, r in series])
        alpha_min[participant.name] = fit_exponent(x, [r["intersect_s"]["min"] for _, r in series])
        if series and series[0][1]["intersect_kernel_s"]:
            alpha_kernel[participant.name] = fit_exponent(
                x, [r["intersect_kernel_s"]["median"] for _, r in series])
    return {"meshes": sorted({f for f, _ in config.scaling}),
            "workload": f"primary {width}x{height} (framed)",
            "points": points, "alpha": alpha, "alpha_min": alpha_min,
            "alpha_kernel": alpha_kernel}


def targets(results: dict, config: Config) -> list[dict]:
    """The issue's targets, from the measured figures (never asserted)."""
    scene = next((s for s in results["scenes"] if s["name"] == config.scene), None)
    devices = [n for n, p in results["participants"].items() if p["kind"] == "device"]
    out = []

    def entry(what, value, target, comparison=">="):
        met = None if value is None else (value >= target if comparison == ">=" else value <= target)
        out.append({"what": what, "value": value, "target": target, "comparison": comparison,
                    "met": met})

    def workload(name_start):
        return next((w for w in (scene or {}).get("workloads", []) if w["name"].startswith(name_start)),
                    None)

    def best_ratio(w, peer, names):
        values = [w["ratios"].get(d, {}).get(peer, {}).get("intersect") for d in names] if w else []
        values = [v for v in values if v is not None]
        return max(values) if values else None

    width, height = config.resolutions[-1]
    primary = workload(f"primary {width}x{height}")
    entry(f"{config.scene} primary {width}x{height}: fastest device / mitsuba",
          best_ratio(primary, "mitsuba", devices), 1.0)
    entry(f"{config.scene} primary {width}x{height}: pocl / mitsuba",
          best_ratio(primary, "mitsuba", [d for d in devices if d.startswith("pocl")]), 0.5)
    incoherent = workload("incoherent")
    entry(f"{config.scene} incoherent: fastest device / embreex ({EMBREE_THREADS} threads)",
          best_ratio(incoherent, "embreex", devices), 1.0)
    for device in devices:
        points = results["scaling"]["points"]
        entry(f"scaling exponent {device} ({points[0]['triangles']:,}.."
              f"{points[-1]['triangles']:,} triangles)",
              results["scaling"]["alpha"].get(device), 0.15, "<=")
    return out


# ---------------------------------------------------------------- reporting

def _spread(rates: dict) -> str:
    return f"{rates['median']:.2f} ({rates['min']:.2f}-{rates['max']:.2f})"


def _number(value, digits=2) -> str | None:
    return None if value is None else f"{value:.{digits}f}"


def format_results(results: dict) -> str:
    names = list(results["participants"])
    devices = [n for n in names if results["participants"][n]["kind"] == "device"]
    peers = [n for n in names if n not in devices and results["participants"][n]["available"]]
    repeats = results["config"]["repeats"]
    out = []
    missing = [(n, p["problem"]) for n, p in results["participants"].items() if not p["available"]]
    for name, problem in missing:
        out.append(f"peer {name} is missing: {problem}")

    rows = [[s["name"], w["name"], w["rays"]] for s in results["scenes"] for w in s["workloads"]]
    cells = {q: [[_spread(w["results"][n][f"{q}_mrays"]) if n in w["results"] else None
                  for n in devices + peers]
                 for s in results["scenes"] for w in s["workloads"]] for q in ("intersect", "occluded")}
    for q, title in (("intersect", "closest hit"), ("occluded", "any hit (occlusion)")):
        out.append(table(["scene", "workload", "rays", *devices, *peers],
                         [r + c for r, c in zip(rows, cells[q])],
                         title=f"{title}, Mrays/s: median (min-max) of {repeats} runs after a "
                               f"warm-up; numpy in, numpy out"))
    pairs = [(d, p) for d in devices for p in peers]
    for q, title in (("intersect", "closest hit"), ("occluded", "any hit")):
        ratio_rows = [r + [_number(w["ratios"].get(d, {}).get(p, {}).get(q)) for d, p in pairs]
                      for r, (s, w) in zip(rows, [(s, w) for s in results["scenes"]
                                                  for w in s["workloads"]])]
        out.append(table(["scene", "workload", "rays", *[f"{d}/{p}" for d, p in pairs]], ratio_rows,
                         title=f"{title}: our Mrays/s / peer Mrays/s (> 1: ours is faster)"))
    agree_rows = []
    for s in results["scenes"]:
        for w in s["workloads"]:
            ref = w["results"].get(w["reference"], {})
            row = [s["name"], w["name"], w["reference"],
                   _number(100 * ref["hits"] / w["rays"], 1) if ref else None]
            for n in devices + peers:
                r = w["results"].get(n)
                row.append(None if r is None else
                           f"{r['disagreement']['intersect']:.1e}/{r['disagreement']['occluded']:.1e}")
            for d in devices:
                r = w["results"].get(d)
                row.append(_number(r["intersect_kernel_s"]["median"] / r["intersect_s"]["median"])
                           if r and r["intersect_kernel_s"] else None)
            agree_rows.append(row)
    out.append(table(["scene", "workload", "reference", "hit %", *devices, *peers,
                      *[f"{d} kernel/wall" for d in devices]], agree_rows,
                     title="agreement: fraction of rays whose hit/miss (closest/any) differs from "
                           "the reference; kernel/wall = share of our closest-hit time in kernels"))
    out.append(table(["scene", "triangles", *devices, *peers],
                     [[s["name"], s["triangles"], *[_number(s["build_s"].get(n), 3)
                                                   for n in devices + peers]]
                      for s in results["scenes"]],
                     title="build, seconds (outside the timings; ours: Scene(), with kernel "
                           "compilation or cache loading where a device first meets a kernel; "
                           "reading and splitting scene files excluded)"))
    scaling = results["scaling"]
    scaled = [n for n in devices + peers if n in scaling["alpha"]]
    rows = [[p["mesh"], p["triangles"], p["rays"],
             *[(f"{r['intersect_s']['median'] * 1e3:.1f} "
                f"({r['intersect_s']['min'] * 1e3:.1f}-{r['intersect_s']['max'] * 1e3:.1f})")
               if (r := p["results"].get(n)) else None for n in scaled],
             *[_number(100 * r["hits"] / p["rays"], 1) if (r := p["results"].get(n)) else None
               for n in scaled[:1]]]
            for p in scaling["points"]]
    out.append(table(["mesh", "triangles", "rays", *scaled, "hit %"], rows,
                     title=f"scaling: {scaling['workload']}, one surface split finer, "
                           f"closest-hit wall ms, median (min-max)"))
    out.append("fitted exponent alpha (time ~ triangles^alpha) of the median times; in brackets "
               "of the fastest runs and of the kernels' median times:\n" + "\n".join(
                   f"  {n} {_number(scaling['alpha'][n], 3)} (fastest "
                   f"{_number(scaling['alpha_min'][n], 3)}"
                   + (f", kernels {_number(scaling['alpha_kernel'][n], 3)}"
                      if n in scaling["alpha_kernel"] else "") + ")" for n in scaled))
    out.append(table(["target", "measured", "wanted", "met"],
                     [[t["what"], _number(t["value"], 3), f"{t['comparison']} {t['target']}",
                       "-" if t["met"] is None else ("yes" if t["met"] else "no")]
                      for t in results["targets"]], title="targets (reported, not asserted)"))
    for s in results["scenes"]:
        for name, error in s["errors"].items():
            out.append(f"FAILED {s['name']} {name}: {error}")
    for p in scaling["points"]:
        for name, error in p["errors"].items():
            out.append(f"FAILED scaling {p['triangles']:,} {name}: {error}")
    return "\n\n".join(out)


def plot(results: dict, path: Path) -> Path:
    plt = pyplot()
    figure, (speed, scaling) = plt.subplots(1, 2, figsize=(15, 5.5),
                                            gridspec_kw={"width_ratios": [2, 1]})
    names = [n for n, p in results["participants"].items() if p["available"]]
    groups = [(f"{s['name'].rsplit('.', 1)[0]}\n{w['name']}", w)
              for s in results["scenes"] for w in s["workloads"]]
    width = 0.8 / max(len(names), 1)
    for i, name in enumerate(names):
        x = [g for g, (_, w) in enumerate(groups) if name in w["results"]]
        rates = [groups[g][1]["results"][name]["intersect_mrays"] for g in x]
        median = np.array([r["median"] for r in rates])
        speed.bar(np.array(x) + (i - (len(names) - 1) / 2) * width, median, width,
                  yerr=[median - [r["min"] for r in rates], [r["max"] for r in rates] - median],
                  label=name, capsize=1.5)
    speed.set_xticks(range(len(groups)), [g for g, _ in groups], fontsize=7, rotation=60, ha="right")
    speed.set(ylabel="closest hit, Mrays/s (median, min-max)", yscale="log",
              title="ray throughput (numpy in, numpy out)")
    speed.grid(True, axis="y", which="both", alpha=0.3)
    speed.legend(fontsize=8)

    data = results["scaling"]
    for name in names:
        series = [(p["triangles"], p["results"][name]) for p in data["points"] if name in p["results"]]
        if not series:
            continue
        x = [n for n, _ in series]
        y = np.array([r["intersect_s"]["median"] * 1e3 for _, r in series])
        low = y - [r["intersect_s"]["min"] * 1e3 for _, r in series]
        high = np.array([r["intersect_s"]["max"] * 1e3 for _, r in series]) - y
        alpha = data["alpha"].get(name)
        scaling.errorbar(x, y, yerr=[low, high], marker="o", capsize=2,
                         label=f"{name} (alpha {alpha:.3f})" if alpha is not None else name)
    scaling.set(xscale="log", yscale="log", xlabel="triangles", ylabel="closest hit, wall ms",
                title=f"scaling: {data['workload']},\none surface split finer")
    scaling.grid(True, which="both", alpha=0.3)
    scaling.legend(fontsize=8)
    return save_figure(figure, path)


# ---------------------------------------------------------------- main

def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="a tiny configuration (small meshes, few rays, 1 repeat), for tests")
    parser.add_argument("--devices", default=None,
                        help="comma-separated device ids or names (default: every working device)")
    parser.add_argument("--peers", default=",".join(PEERS),
                        help=f"comma-separated peers (default: {','.join(PEERS)})")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    args = parser.parse_args(argv)
    config = QUICK if args.quick else FULL
    elapsed = stopwatch()
    quiet_compiler_warnings()

    chosen, skipped = pick_devices(args.devices)
    for s in skipped:
        print(f"skipping {s['device']}: {s['problem']}")
    if not chosen:
        raise SystemExit("no working OpenCL device to benchmark")
    peers, missing = load_peers([p.strip() for p in args.peers.split(",") if p.strip()])
    devices = [OurDevice(d) for d in chosen]
    participants = devices + peers
    scaling_participants = devices + [p for p in peers if p.name == REFERENCE]
    print(f"devices: {', '.join(str(d) for d in chosen)}")
    print(f"peers: {', '.join(f'{p.name} {p.version}' for p in peers) or 'none'}"
          + "".join(f"; {p.name} missing" for p in missing), flush=True)

    results = {"config": asdict(config), "quick": args.quick, "machine": machine_info(),
               "skipped_devices": skipped, "embree_threads": EMBREE_THREADS,
               "participants": {p.name: p.describe() for p in participants + missing},
               "scenes": []}
    steps = (len(config.meshes) + 1) * (1 + len(config.resolutions) + 1) + len(config.scaling)
    with progress(steps, "trace bench", enabled=not args.no_progress) as bar:
        for filename in (*config.meshes, config.scene):
            bar.set_postfix_str(f"loading {filename}")
            case = (scene_file_case(filename, chosen[0].id) if filename == config.scene
                    else mesh_case(filename))
            workloads = case.workloads(config)
            bar.update()
            results["scenes"].append(bench_case(case, workloads, participants, config.repeats, bar))
            del case, workloads
            gc.collect()
        results["scaling"] = bench_scaling(config, scaling_participants, bar)
    results["targets"] = targets(results, config)
    results["peak_rss_bytes"] = peak_rss_bytes()
    results["elapsed_s"] = elapsed()
    print(format_results(results))
    json_path = write_json(args.out / "trace.json", results)
    png_path = plot(results, args.out / "trace.png")
    print(f"\nwrote {json_path} and {png_path} in {results['elapsed_s']:.0f} s")
    return results


if __name__ == "__main__":
    main()
