"""Instancing against flat scenes and Mitsuba 3: the top level's rebuild, a
LiDAR frame of moving objects, the build and memory of many instances, and
ray speed.

    python -m bench.instances [--quick] [--devices pocl,intel] [--parts a,b,c,d] [--docs]

Each part runs on every device given (default: PoCL and Intel's CPU runtime,
where present):
  a. set_transforms: every mover of part b's world moved at once, the top
     level rebuilt on the device; the top build's device ms (the scene's
     stats) and the call's wall ms.
  b. LiDAR frame: a ground and N movers (boxes, every tenth a bunny) driving
     straight on; a frame moves all of them (set_transforms) and traces one
     sweep of beams x azimuths rays from the single sensor origin.  Against
     the same world flattened (a mesh per mover, its transform baked in),
     whose frame is an update_vertices per mover and the same rays; and, the
     best a flat scene can do, all movers as one mesh refitted once a frame.
  c. build and memory: N instances of one mesh (the bunny): the Scene's
     construction, wall, and the peak resident memory it adds (VmHWM, in a
     child process, after a warm-up build that compiled the kernels) against
     one Scene of the mesh alone plus the nbytes of the instance arrays.  On
     a CPU device, device buffers are host memory: that is the build's peak.
  d. ray speed: the scene file's camera rays, flat against its meshes as
     instances under identity transforms; and a grid of bunnies, instanced,
     against Mitsuba 3 (llvm_ad_rgb: a shapegroup holding the mesh and an
     instance shape per bunny) on the same rays, with the agreement of t:
     its ray_intersect_preliminary (Embree's hit: t, ids, uv; the target's
     peer), and its ray_intersect (the whole SurfaceInteraction) in a round
     of its own, one timed call: on a big grid each of its calls costs
     seconds whatever its rays, spent tracing a SurfaceInteraction through
     every instance shape.

Timing as bench/trace.py: each participant built outside the timing, one
warm-up call, then ``repeats`` rounds of one call per participant, each after
an untimed call of its own (part b: each call the next frame, the same frames
for everyone); wall time, numpy in and out.  Ratios are taken within the run.

Writes <out>/instances.json and <out>/instances.png; with --docs also
docs/bench_instances.png and the instances section of bench/RESULTS.md.
"""
from __future__ import annotations

import gc
import math
import multiprocessing
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

import hlbvh_cl
import hlbvh_cl.io.scenefile

from . import common, peers, plots, trace
from .common import (BENCH, MESHES, SCENES, arguments, devices_or_exit, finish, machine_info,
                     progress, rates, reset_peak, say, spread, status_bytes, stopwatch, summary,
                     table)

PARTS = ("a", "b", "c", "d")
#: the issue's targets
TARGETS = {"transforms_device_ms": 2.0,  # a, on PoCL
           "lidar_speedup": 10.0,        # b, instanced frame over flat per mesh
           "build_s": 1.0,               # c
           "memory_ratio": 1.2,          # c, over one mesh's Scene plus the instance arrays
           "identity_ratio": 0.8,        # d, instanced over flat
           "mitsuba_ratio": 1.0}         # d, ours over Mitsuba
#: bench/RESULTS.md keeps this section between these lines (report.py leaves it be)
SECTION = "instances"
MIB = 2**20

# the LiDAR world (parts a and b), in metres, y up
GROUND = 200.0              # side of the square ground
SENSOR = (0.0, 1.8, 0.0)    # above every mover: none hides the whole sweep
RANGE = 120.0               # the rays' tmax
ELEVATION_DEG = (-25.0, 15.0)
FRAME_S = 0.1               # a 10 Hz sensor
BUNNY_EVERY = 10            # one mover in this many is a bunny, the others boxes


@dataclass(frozen=True)
class Config:
    movers: int                  # parts a and b
    beams: tuple[int, int]       # elevations x azimuths of a sweep
    frames: int                  # b: timed frames per participant
    calls: int                   # a: timed set_transforms calls
    memory_mesh: str             # c: in scenes/meshes
    memory_instances: int
    scene: str                   # d: a scene file in scenes/
    resolution: tuple[int, int]  # d: camera rays, (width, height)
    grid_mesh: str               # d
    grid: int                    # d: instances per side of the grid
    repeats: int                 # c: builds; d: timed calls after one warm-up
    seed: int = 1


FULL = Config(1000, (64, 1024), 3, 20, "bunny.ply", 10_000, "reference.toml", (1280, 720),
              "bunny.ply", 32, 5)
QUICK = Config(60, (16, 256), 1, 3, "bunny_small.ply", 200, "bunny_small.toml", (64, 48),
               "bunny_small.ply", 4, 1)


# ---------------------------------------------------------------- geometry

def box_mesh(width: float, height: float, length: float) -> hlbvh_cl.Mesh:
    """A box standing on y = 0, centred on the y axis, long along z."""
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (0, 1) for z in (-0.5, 0.5)])
    faces = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
             [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return hlbvh_cl.Mesh((corners * [width, height, length]).astype(np.float32),
                         np.array(faces, np.int32), name="box")


def ground_mesh(size: float) -> hlbvh_cl.Mesh:
    h = size / 2
    return hlbvh_cl.Mesh(np.array([[-h, 0, -h], [h, 0, -h], [h, 0, h], [-h, 0, h]], np.float32),
                         np.array([[0, 2, 1], [0, 3, 2]], np.int32), name="ground")


def standing(mesh: hlbvh_cl.Mesh, height: float) -> hlbvh_cl.Mesh:
    """``mesh`` scaled to ``height`` and moved to stand on y = 0 about the y axis."""
    lo, hi = mesh.bounds
    offset = np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])
    vertices = (mesh.vertices - offset) * (height / (hi[1] - lo[1]))
    return hlbvh_cl.Mesh(vertices.astype(np.float32), mesh.faces, name=mesh.name)


def yaw_transforms(yaw, positions) -> np.ndarray:
    """(N, 3, 4) float32: a turn by ``yaw`` about y, then a move to ``positions``."""
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.zeros((len(yaw), 3, 4))
    out[:, 0, 0], out[:, 0, 2], out[:, 1, 1], out[:, 2, 0], out[:, 2, 2] = c, s, 1, -s, c
    out[:, :, 3] = positions
    return out.astype(np.float32)


def baked(mesh: hlbvh_cl.Mesh, transform) -> np.ndarray:
    """The mesh's vertices moved by one (3, 4) transform: what a flat scene holds."""
    t = np.asarray(transform, np.float64)
    return (mesh.vertices @ t[:, :3].T + t[:, 3]).astype(np.float32)


def sweep(elevations: int, azimuths: int) -> np.ndarray:
    """(elevations, azimuths, 3) unit directions of one revolution of a
    spinning LiDAR, its beams spread over ELEVATION_DEG."""
    e = np.radians(np.linspace(*ELEVATION_DEG, elevations))[:, None]
    a = np.linspace(0, 2 * np.pi, azimuths, endpoint=False)[None, :]
    out = np.stack(np.broadcast_arrays(np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)),
                   axis=-1)
    return out.astype(np.float32)


class World:
    """Part b's world: a ground and movers driving straight on at their own
    speeds, wrapping around the ground's edge.  Frame k's poses depend on k
    alone, so that every participant traces the same frames."""

    def __init__(self, movers: int, seed: int):
        rng = np.random.default_rng(seed)
        bunny = standing(hlbvh_cl.Mesh.load(MESHES / "bunny_small.ply"), 1.2)
        self.meshes = [ground_mesh(GROUND), box_mesh(1.8, 1.5, 4.5), bunny]
        self.kinds = np.where(np.arange(movers) % BUNNY_EVERY == BUNNY_EVERY - 1, 2, 1)
        self.start = (rng.random((movers, 2)) - 0.5) * 0.9 * GROUND
        self.heading = rng.random(movers) * 2 * np.pi
        self.speed = rng.uniform(3, 15, movers)

    @property
    def ids(self) -> np.ndarray:
        """The movers' instance ids (the ground is instance 0)."""
        return np.arange(1, len(self.kinds) + 1)

    def transforms(self, frame: int) -> np.ndarray:
        span = 0.9 * GROUND
        way = np.stack([np.sin(self.heading), np.cos(self.heading)], axis=1)
        xz = self.start + way * (self.speed * frame * FRAME_S)[:, None]
        xz = (xz + span / 2) % span - span / 2
        return yaw_transforms(self.heading, np.stack([xz[:, 0], 0 * xz[:, 0], xz[:, 1]], axis=1))

    def instances(self, frame: int) -> list:
        return [(0, np.eye(4)[:3])] + list(zip(self.kinds.tolist(), self.transforms(frame)))

    def mover_vertices(self, frame: int) -> list[np.ndarray]:
        return [baked(self.meshes[k], t) for k, t in zip(self.kinds, self.transforms(frame))]

    @property
    def triangles(self) -> int:
        return int(sum(self.meshes[k].triangle_count for k in self.kinds)) + 2


def grid_transforms(count: int, mesh: hlbvh_cl.Mesh, seed: int) -> np.ndarray:
    """(count, 3, 4): a square grid on y = 0 of ``mesh`` (as it stands) turned
    at random about y, spaced 1.2 of its largest side apart."""
    side = math.ceil(math.sqrt(count))
    lo, hi = mesh.bounds
    spacing = 1.2 * float(np.max(hi - lo))
    i = np.arange(count)
    positions = np.stack([(i % side - (side - 1) / 2) * spacing, 0 * i,
                          (i // side - (side - 1) / 2) * spacing], axis=1)
    return yaw_transforms(np.random.default_rng(seed).random(count) * 2 * np.pi, positions)


def grid_camera(transforms: np.ndarray, mesh: hlbvh_cl.Mesh, aspect: float) -> hlbvh_cl.Camera:
    """A camera looking down at 30 degrees on the grid, the whole grid in view."""
    lo, hi = mesh.bounds
    radius = float(np.abs(transforms[:, [0, 2], 3]).max() + np.max(hi - lo))
    centre = np.array([0.0, (hi[1] - lo[1]) / 2, 0.0])
    fov = 40.0
    distance = 1.1 * radius / math.tan(math.radians(fov / 2)) / min(1.0, aspect)
    way = np.array([0.0, math.sin(math.radians(30)), math.cos(math.radians(30))])
    return hlbvh_cl.Camera(tuple(centre + distance * way), tuple(centre), (0, 1, 0), fov)


# ---------------------------------------------------------------- figures of a run

def top_build(scene) -> dict:
    """The device and wall ms of an instanced scene's last build: its top
    tree's (set_transforms builds no other)."""
    return {"device_ms": float(scene.stats.device_ms), "wall_ms": float(scene.stats.wall_ms)}


def agreement(hits, reference, scale: float) -> dict:
    """Hit/miss differences, and where both hit the share of t more than
    1e-4 of ``scale`` apart and the largest gap (over ``scale``); hits as
    dicts or Hits of t (inf on a miss)."""
    t, ref = (np.asarray(h["t"] if isinstance(h, dict) else h.t, np.float64).ravel()
              for h in (hits, reference))
    hit, ref_hit = np.isfinite(t), np.isfinite(ref)
    both = hit & ref_hit
    gap = np.abs(t[both] - ref[both]) / scale
    return {"hit_differs": float(np.mean(hit != ref_hit)),
            "t_differs": float(np.mean(gap > 1e-4)) if both.any() else 0.0,
            "max_t_gap": float(gap.max(initial=0)), "hits": int(hit.sum())}


# ---------------------------------------------------------------- a and b: the LiDAR world

class LidarFrames:
    """One way to keep part b's world on one device: ``call`` traces the
    next frame.  way: "instanced" (set_transforms), "flat per mesh"
    (update_vertices per mover) or "flat merged" (one update_vertices)."""

    WAYS = ("instanced", "flat per mesh", "flat merged")
    kind = "device"  # built as bench/trace.py builds our devices: build(case)

    def __init__(self, world: World, directions: np.ndarray, device_id: str, way: str):
        self.world, self.directions, self.way = world, directions, way
        self.device_id, self.name = device_id, f"{device_id} {way}"
        self.frame = 0
        self.scene = None

    def build(self, _world=None) -> float:
        elapsed = stopwatch()
        w = self.world
        if self.way == "instanced":
            self.scene = hlbvh_cl.Scene(w.meshes, instances=w.instances(0), device=self.device_id)
        else:
            moved = [hlbvh_cl.Mesh(v, w.meshes[k].faces)
                     for v, k in zip(w.mover_vertices(0), w.kinds)]
            if self.way == "flat merged":
                moved = [_merged(moved)]
            self.scene = hlbvh_cl.Scene([w.meshes[0]] + moved, device=self.device_id)
        return elapsed()

    def move(self, frame: int) -> None:
        w = self.world
        if self.way == "instanced":
            self.scene.set_transforms(w.ids, w.transforms(frame))
        elif self.way == "flat per mesh":
            for geom_id, vertices in enumerate(w.mover_vertices(frame), start=1):
                self.scene.update_vertices(geom_id, vertices)
        else:
            self.scene.update_vertices(1, np.concatenate(w.mover_vertices(frame)))

    def call(self):
        self.frame += 1
        self.move(self.frame)
        return self.scene.intersect(np.float32(SENSOR), self.directions, 0.0, RANGE)

    def close(self) -> None:
        self.scene = None


def _merged(meshes: list) -> hlbvh_cl.Mesh:
    offsets = np.cumsum([0] + [m.vertex_count for m in meshes[:-1]])
    return hlbvh_cl.Mesh(np.concatenate([m.vertices for m in meshes]),
                         np.concatenate([m.faces + np.int32(o) for m, o in zip(meshes, offsets)]))


def bench_transforms(frames: list[LidarFrames], calls: int) -> dict:
    """Part a: set_transforms of every mover, ``calls`` times after a warm-up."""
    out = {}
    for f in frames:
        world, walls, device = f.world, [], []
        f.move(1)  # warm-up
        for call in range(calls):
            transforms = world.transforms(2 + call)
            elapsed = stopwatch()
            f.scene.set_transforms(world.ids, transforms)
            walls.append(elapsed() * 1e3)
            device.append(top_build(f.scene)["device_ms"])
        out[f.device_id] = {"instances": len(world.ids) + 1, "moved": len(world.ids),
                            "calls": calls, "device_ms": summary(device),
                            "wall_ms": summary(walls)}
        say(f"  a. {f.device_id}: set_transforms of {len(world.ids):,} instances: device "
            f"{spread(out[f.device_id]['device_ms'], digits=2)} ms, wall "
            f"{spread(out[f.device_id]['wall_ms'], digits=2)} ms")
    return out


def bench_lidar(world: World, frames: list[LidarFrames], count: int) -> dict:
    """Part b: every participant traces the same ``count`` frames after a warm-up one."""
    errors: dict = {}
    for f in frames:
        f.frame = 0  # part a moved the instanced ones
    timed = trace.time_round_robin(frames, lambda f: f.call(), count, errors)
    rays = int(np.prod(frames[0].directions.shape[:-1]))
    out = {"movers": len(world.kinds), "triangles_flat": world.triangles, "rays": rays,
           "frames": count, "results": {}, "errors": errors}
    reference = next((f.name for f in frames if f.name in timed), None)
    for f in frames:
        if f.name not in timed:
            continue
        hits, walls = timed[f.name]
        out["results"][f.name] = {"device": f.device_id, "way": f.way,
                                  "frame_ms": summary([w * 1e3 for w in walls]),
                                  "mrays": rates(rays, walls),
                                  "vs_reference": agreement(hits, timed[reference][0], RANGE)}
    out["reference"] = reference
    out["speedup"] = {}
    for device in dict.fromkeys(f.device_id for f in frames):
        mine = out["results"].get(f"{device} instanced")
        if mine:
            out["speedup"][device] = {
                way: out["results"][f"{device} {way}"]["frame_ms"]["median"]
                / mine["frame_ms"]["median"]
                for way in LidarFrames.WAYS[1:] if f"{device} {way}" in out["results"]}
    for name, r in out["results"].items():
        say(f"  b. {name}: frame {spread(r['frame_ms'])} ms")
    return out


# ---------------------------------------------------------------- c: build and memory

def memory_child(kind: str, mesh_name: str, count: int, device_id: str, repeats: int,
                 seed: int) -> dict:
    """In a fresh process: the resident memory a Scene of ``count`` instances
    of the mesh adds (kind "instanced"), or of the mesh alone ("flat"), and
    its construction's wall time."""
    mesh = standing(hlbvh_cl.Mesh.load(MESHES / mesh_name), 1.0)
    transforms = grid_transforms(count, mesh, seed)
    instances = [(0, t) for t in transforms]
    masks = np.full(count, 0xFFFFFFFF, np.uint32)
    instance_bytes = transforms.nbytes + count * np.dtype(np.int32).itemsize + masks.nbytes

    def make():
        if kind == "instanced":
            return hlbvh_cl.Scene([mesh], instances=instances, masks=masks, device=device_id)
        return hlbvh_cl.Scene([mesh], device=device_id)

    warm = make()  # compiles the kernels: their memory is not the scene's
    del warm
    gc.collect()
    if not reset_peak():
        raise RuntimeError("cannot reset the peak resident memory (/proc/self/clear_refs)")
    before = status_bytes("VmRSS")
    elapsed = stopwatch()
    scene = make()
    first_s = elapsed()
    peak, after = status_bytes("VmHWM"), status_bytes("VmRSS")
    out = {"kind": kind, "instances": count if kind == "instanced" else 1,
           "triangles_seen": mesh.triangle_count * (count if kind == "instanced" else 1),
           "rss_before_bytes": before, "peak_growth_bytes": peak - before,
           "kept_growth_bytes": after - before,
           "instance_bytes": instance_bytes, "first_build_s": first_s}
    if kind == "instanced":  # a ray down onto each instance's place: are they there?
        lo, hi = mesh.bounds
        origins = transforms[:, :, 3] + np.float32([0, 2 * (hi[1] - lo[1]) + 1, 0])
        hits = scene.intersect(origins, np.float32([0, -1, 0]))
        out["hit_fraction"] = float(np.mean(hits.t < np.inf))
        out["top_build"] = top_build(scene)
    del scene
    builds = []
    for _ in range(repeats):
        gc.collect()
        elapsed = stopwatch()
        built = make()
        builds.append(elapsed())
        del built  # after the clock: freeing the tree is not its build
    out["build_s"] = summary(builds or [first_s])
    return out


def bench_memory(config: Config, device_ids: list[str]) -> dict:
    """Part c on each device: instanced and flat, each in its own process."""
    out = {"mesh": config.memory_mesh, "instances": config.memory_instances, "results": {},
           "errors": {}}
    for device in device_ids:
        found = {}
        for kind in ("instanced", "flat"):
            with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
                try:
                    found[kind] = pool.submit(memory_child, kind, config.memory_mesh,
                                              config.memory_instances, device, config.repeats,
                                              config.seed).result()
                except Exception as error:
                    out["errors"][f"{device} {kind}"] = f"{type(error).__name__}: {error}"
        if len(found) == 2:
            inst, flat = found["instanced"], found["flat"]
            baseline = flat["peak_growth_bytes"] + inst["instance_bytes"]
            found["ratio"] = inst["peak_growth_bytes"] / baseline if baseline > 0 else None
            say(f"  c. {device}: {inst['instances']:,} instances ({inst['triangles_seen']:,} "
                f"triangles): build {spread(inst['build_s'], digits=3)} s, peak growth "
                f"{inst['peak_growth_bytes'] / MIB:.1f} MiB vs one mesh "
                f"{flat['peak_growth_bytes'] / MIB:.1f} + arrays "
                f"{inst['instance_bytes'] / MIB:.2f} MiB: {found['ratio']:.2f}x")
        out["results"][device] = found
    return out


# ---------------------------------------------------------------- d: ray speed

class Tracer:
    """A built hlbvh_cl Scene under a name, tracing rays (bench/trace.py's interface)."""

    kind = "device"

    def __init__(self, name: str, device_id: str, scene):
        self.name, self.device_id, self.scene = name, device_id, scene

    def intersect(self, rays):
        return self.scene.intersect(rays.origins, rays.directions)

    def close(self) -> None:
        self.scene = None


class MitsubaInstances(peers.MitsubaPeer):
    """Mitsuba 3 with one shapegroup holding the mesh and an instance shape
    per transform.  ``full``: ray_intersect, the whole SurfaceInteraction;
    else ray_intersect_preliminary, Embree's hit alone (t, ids, uv), as
    bench/peers.py's Mitsuba traces."""

    def __init__(self, full: bool = False):
        super().__init__()
        self.full = full
        self.name = "mitsuba ray_intersect" if full else "mitsuba"
        self.label = ("Mitsuba 3 llvm_ad_rgb, shapegroup + instances, "
                      + ("ray_intersect" if full else "ray_intersect_preliminary"))

    def build_instances(self, mesh: hlbvh_cl.Mesh, transforms: np.ndarray) -> float:
        import mitsuba as mi
        elapsed = stopwatch()
        scene = {"type": "scene", "group": {"type": "shapegroup",
                                            "mesh": self.mesh(mesh.vertices, mesh.faces)}}
        for i, t in enumerate(transforms):
            scene[f"instance {i}"] = {
                "type": "instance", "shapegroup": {"type": "ref", "id": "group"},
                "to_world": mi.ScalarTransform4f(np.vstack([t, [0, 0, 0, 1]]).astype(float))}
        self.scene = mi.load_dict(scene)
        return elapsed()

    def intersect(self, rays) -> dict:
        if not self.full:
            return super().intersect(rays)
        import drjit as dr
        import mitsuba as mi
        found = self.scene.ray_intersect(self._ray(rays), ray_flags=mi.RayFlags.All,
                                         coherent=rays.kind == "primary")
        t = dr.select(found.is_valid(), found.t, dr.inf)
        dr.eval(t, found.prim_index, found.p, found.n)
        dr.sync_thread()
        return {"t": t.numpy(), "prim_index": found.prim_index.numpy(), "p": found.p.numpy(),
                "n": found.n.numpy()}


def _time_rays(participants: list, rays, repeats: int) -> tuple[dict, dict]:
    errors: dict = {}
    timed = trace.time_round_robin(participants, lambda p: p.intersect(rays), repeats, errors)
    return {name: {"mrays": rates(len(rays), walls), "answer": answer}
            for name, (answer, walls) in timed.items()}, errors


def bench_identity(config: Config, device_ids: list[str]) -> dict:
    """The scene file's meshes flat and as instances under identity transforms."""
    description = hlbvh_cl.io.scenefile.read(SCENES / config.scene)
    meshes = [m for m, _ in description.geometries()]
    rays = trace.primary_rays(description.camera, *config.resolution)
    built = []
    for device in device_ids:
        built.append(Tracer(f"{device} flat", device, hlbvh_cl.Scene(meshes, device=device)))
        built.append(Tracer(f"{device} instanced", device, hlbvh_cl.Scene(
            meshes, instances=[(i, np.eye(4)) for i in range(len(meshes))], device=device)))
    scale = float(np.linalg.norm(np.subtract(*common.bounds(meshes))))
    try:
        found, errors = _time_rays(built, rays, config.repeats)
    finally:
        trace.close_all(built)
    out = {"scene": config.scene, "meshes": len(meshes), "rays": rays.name,
           "triangles": int(sum(m.triangle_count for m in meshes)), "results": {},
           "ratio": {}, "errors": errors}
    for name, r in found.items():
        device = name.rsplit(" ", 1)[0]
        flat = found.get(f"{device} flat")
        out["results"][name] = {"mrays": r["mrays"]}
        if flat and name.endswith("instanced"):
            out["results"][name]["vs_flat"] = agreement(r["answer"], flat["answer"], scale)
            out["ratio"][device] = r["mrays"]["median"] / flat["mrays"]["median"]
            say(f"  d. {config.scene} {device}: instanced {r['mrays']['median']:.2f} vs flat "
                f"{flat['mrays']['median']:.2f} Mrays/s: {out['ratio'][device]:.2f}x")
    return out


def bench_grid(config: Config, device_ids: list[str]) -> dict:
    """A grid of instances of one mesh, the camera's rays: ours on each
    device against Mitsuba 3's preliminary hits, then against its
    ray_intersect in a round of its own with one timed call (its calls cost
    seconds on a big grid, whatever their rays: it traces a
    SurfaceInteraction through every instance shape)."""
    mesh = standing(hlbvh_cl.Mesh.load(MESHES / config.grid_mesh), 1.0)
    transforms = grid_transforms(config.grid ** 2, mesh, config.seed)
    width, height = config.resolution
    camera = grid_camera(transforms, mesh, width / height)
    out = {"mesh": config.grid_mesh, "instances": len(transforms),
           "triangles_seen": mesh.triangle_count * len(transforms), "build_s": {},
           "mitsuba": {}, "workloads": [], "errors": {}}
    ours = []
    for device in device_ids:
        elapsed = stopwatch()
        scene = hlbvh_cl.Scene([mesh], instances=[(0, t) for t in transforms], device=device)
        out["build_s"][device] = elapsed()
        ours.append(Tracer(device, device, scene))
    theirs = []
    for full in (False, True):
        peer = MitsubaInstances(full)
        peer.load()
        out["mitsuba"][peer.name] = peer.describe()
        if peer.problem is None:
            try:
                out["build_s"][peer.name] = peer.build_instances(mesh, transforms)
                theirs.append(peer)
            except Exception as error:
                out["errors"][peer.name] = f"{type(error).__name__}: {error}"
    scale = float(np.linalg.norm(camera.eye))
    try:
        rays = trace.primary_rays(camera, width, height)
        for peer_names, repeats in ((["mitsuba"], config.repeats),
                                    (["mitsuba ray_intersect"], 1)):
            found, errors = _time_rays(ours + [p for p in theirs if p.name in peer_names], rays,
                                       repeats)
            out["errors"].update(errors)
            reference = next((d for d in device_ids if d in found), None)
            work = {"rays": rays.name, "count": len(rays), "repeats": repeats, "results": {},
                    "ratio": {}}
            for name, r in found.items():
                work["results"][name] = {"mrays": r["mrays"]}
                if name != reference and reference is not None:
                    work["results"][name]["vs_ours"] = agreement(
                        r["answer"], found[reference]["answer"], scale)
            for peer in (n for n in peer_names if n in found):
                for device in (d for d in device_ids if d in found):
                    work["ratio"][device] = (found[device]["mrays"]["median"]
                                             / found[peer]["mrays"]["median"])
            out["workloads"].append(work)
            say(f"  d. grid of {len(transforms):,} {config.grid_mesh}, {rays.name}, "
                f"{repeats} timed: "
                + "  ".join(f"{n} {r['mrays']['median']:.2f}"
                            for n, r in work["results"].items()) + " Mrays/s")
    finally:
        trace.close_all(ours + theirs)
    return out


# ---------------------------------------------------------------- report

def _met(value, target: float, above: bool = True) -> str:
    if value is None:
        return "-"
    return "yes" if (value >= target if above else value <= target) else "no"


def _tables(results: dict) -> list[tuple[str, list[str], list[list]]]:
    """(title, headers, rows) of every part that ran."""
    out = []
    a = results.get("transforms")
    if a:
        out.append((f"a. set_transforms, every mover moved, top level rebuilt (target <= "
                    f"{TARGETS['transforms_device_ms']:g} ms device on PoCL)",
                    ["device", "instances", "device ms", "wall ms", "target met"],
                    [[d, r["instances"], spread(r["device_ms"], digits=2),
                      spread(r["wall_ms"], digits=2),
                      _met(r["device_ms"]["median"], TARGETS["transforms_device_ms"], False)]
                     for d, r in a.items()]))
    b = results.get("lidar")
    if b:
        rows = []
        for name, r in b["results"].items():
            up = b["speedup"].get(r["device"], {}).get(r["way"])
            rows.append([name, spread(r["frame_ms"]), f"{r['mrays']['median']:.2f}",
                         f"{up:.1f}x" if up else "-",
                         f"{r['vs_reference']['hit_differs']:.1e}",
                         f"{r['vs_reference']['max_t_gap']:.1e}"])
        out.append((f"b. LiDAR frame: {b['movers']:,} movers, {b['rays']:,} rays from one "
                    f"origin ({b['triangles_flat']:,} triangles flat), {b['frames']} timed "
                    "frame(s) each after a warm-up one; "
                    f"instanced frame's speed-up >= {TARGETS['lidar_speedup']:g}x flat per mesh",
                    ["participant", "frame ms", "Mrays/s", "instanced speed-up",
                     "hit differs", "t gap / range"], rows))
    c = results.get("memory")
    if c:
        rows = []
        for device, r in c["results"].items():
            inst, flat = r.get("instanced"), r.get("flat")
            if not (inst and flat):
                continue
            rows.append([device, inst["instances"], inst["triangles_seen"],
                         spread(inst["build_s"], digits=3),
                         f"{inst['peak_growth_bytes'] / MIB:.1f}",
                         f"{inst['kept_growth_bytes'] / MIB:.1f}",
                         f"{flat['peak_growth_bytes'] / MIB:.1f}",
                         f"{inst['instance_bytes'] / MIB:.2f}",
                         f"{r['ratio']:.2f}x" if r["ratio"] is not None else "-",
                         _met(inst["build_s"]["median"], TARGETS["build_s"], False) + " / "
                         + _met(r["ratio"], TARGETS["memory_ratio"], False),
                         f"{inst['hit_fraction']:.3f}"])
        out.append((f"c. {c['instances']:,} instances of {c['mesh']}: build wall s, peak RSS "
                    f"growth (child process) against one {c['mesh']} Scene plus the instance "
                    f"arrays (targets < {TARGETS['build_s']:g} s, <= "
                    f"{TARGETS['memory_ratio']:g}x)",
                    ["device", "instances", "triangles seen", "build s", "peak growth MiB",
                     "kept MiB", "one mesh MiB", "arrays MiB", "ratio", "targets met",
                     "hit fraction"], rows))
    d = results.get("identity")
    if d:
        out.append((f"d. {d['scene']} ({d['triangles']:,} triangles, {d['meshes']} meshes), "
                    f"{d['rays']}: flat vs its meshes as instances under identity transforms "
                    f"(target >= {TARGETS['identity_ratio']:g}x)",
                    ["participant", "Mrays/s", "instanced / flat", "hit differs", "t gap"],
                    [[n, spread(r["mrays"], digits=2),
                      f"{d['ratio'][n.rsplit(' ', 1)[0]]:.2f}x" if "vs_flat" in r else "-",
                      f"{r['vs_flat']['hit_differs']:.1e}" if "vs_flat" in r else "-",
                      f"{r['vs_flat']['max_t_gap']:.1e}" if "vs_flat" in r else "-"]
                     for n, r in d["results"].items()]))
    g = results.get("grid")
    for work in (g or {}).get("workloads", []):
        peer = next((n for n in work["results"] if n.startswith("mitsuba")), "mitsuba")
        out.append((f"d. a grid of {g['instances']:,} {g['mesh']} ({g['triangles_seen']:,} "
                    f"triangles seen), {work['rays']}, {work['repeats']} timed call(s) "
                    f"each: ours against {peer} (target >= {TARGETS['mitsuba_ratio']:g}x)",
                    ["participant", "build s", "Mrays/s", f"ours / {peer}", "hit differs",
                     "t differs", "largest t gap"],
                    [[n, f"{g['build_s'].get(n, 0):.3f}", spread(r["mrays"], digits=2),
                      f"{work['ratio'][n]:.2f}x" if n in work["ratio"] else "-",
                      *([f"{r['vs_ours'][k]:.1e}" for k in ("hit_differs", "t_differs",
                                                             "max_t_gap")]
                        if "vs_ours" in r else ["-"] * 3)]
                     for n, r in work["results"].items()]))
    return out


def _failures(results: dict) -> list[str]:
    found = []
    for part in ("lidar", "memory", "identity", "grid"):
        found += [f"FAILED {part} {n}: {e}"
                  for n, e in (results.get(part) or {}).get("errors", {}).items()]
    for name, peer in (results.get("grid") or {}).get("mitsuba", {}).items():
        if not peer.get("available"):
            found.append(f"{name} is missing: {peer.get('problem')}")
    return found


def format_results(results: dict, markdown: bool = False) -> str:
    tables = _tables(results)
    if not markdown:
        return "\n\n".join([table(h, rows, title) for title, h, rows in tables]
                           + _failures(results))
    from .report import md_table
    machine = results["machine"]
    lines = [f"<!-- begin {SECTION} -->", "", "## Instancing", "",
             f"Measured on {machine['date']} with `{results['command']}` (bench/instances.py; "
             "its docstring says how), load average "
             + ", ".join(f"{x:.2f}" for x in machine["loadavg"])
             + " at the start; above 2 means other processes ran too.", "",
             "![instancing](../docs/bench_instances.png)", ""]
    for title, headers, rows in tables:
        lines += [f"{title}:", "", md_table(headers, rows), ""]
    lines += [f"- {f}" for f in _failures(results)]
    lines += ["", "*JSON: `instances.json`*", "", f"<!-- end {SECTION} -->"]
    return "\n".join(lines) + "\n"


def write_section(path: Path, text: str) -> Path:
    return common.write_section(path, text, SECTION)


def plot(results: dict, path: Path) -> Path:
    """One panel per part, the targets drawn in red."""
    plt = plots.pyplot()
    figure, axes = plt.subplots(2, 2, figsize=(13, 9))
    (top, frame), (memory, speed) = axes
    for ax in axes.ravel():
        ax.set_axis_off()

    a = results.get("transforms")
    if a:
        top.set_axis_on()
        names = list(a)
        x = np.arange(len(names))
        for shift, key in ((-0.2, "device_ms"), (0.2, "wall_ms")):
            top.bar(x + shift, [a[n][key]["median"] for n in names], 0.4,
                    label=key.replace("_ms", ""))
        top.axhline(TARGETS["transforms_device_ms"], color="crimson", lw=1)
        top.set_xticks(x, names)
        top.set(ylabel="ms (median)", title=f"a. set_transforms, "
                f"{next(iter(a.values()))['instances']:,} instances")
        top.legend(fontsize=8)

    b = results.get("lidar")
    if b and b["results"]:
        frame.set_axis_on()
        names = list(b["results"])
        frame.bar(range(len(names)), [b["results"][n]["frame_ms"]["median"] for n in names],
                  color=[f"C{LidarFrames.WAYS.index(b['results'][n]['way'])}" for n in names])
        frame.set_xticks(range(len(names)), [n.replace(" ", "\n", 1) for n in names], fontsize=7)
        frame.set(yscale="log", ylabel="ms per frame (median)",
                  title=f"b. LiDAR frame: {b['movers']:,} movers, {b['rays']:,} rays")
        plots.plain_log(frame)

    c = results.get("memory")
    rows = [(d, r) for d, r in (c or {}).get("results", {}).items() if r.get("ratio")]
    if rows:
        memory.set_axis_on()
        x = np.arange(len(rows))
        memory.bar(x - 0.2, [r["instanced"]["peak_growth_bytes"] / MIB for _, r in rows], 0.4,
                   label=f"{c['instances']:,} instances")
        memory.bar(x + 0.2, [(r["flat"]["peak_growth_bytes"] + r["instanced"]["instance_bytes"])
                             / MIB for _, r in rows], 0.4, label="one mesh + instance arrays")
        for k, (_, r) in enumerate(rows):
            memory.annotate(f"{r['ratio']:.2f}x, build {r['instanced']['build_s']['median']:.2f} s",
                            (k, r["instanced"]["peak_growth_bytes"] / MIB), ha="center",
                            va="bottom", fontsize=8)
        memory.set_xticks(x, [d for d, _ in rows])
        memory.set(ylabel="peak RSS growth, MiB", title=f"c. build memory, {c['mesh']}")
        memory.set_ylim(0, memory.get_ylim()[1] * 1.25)  # room for the notes and the legend
        memory.legend(fontsize=8, loc="upper right")

    bars = []
    d, g = results.get("identity"), results.get("grid")
    for name, r in (d or {}).get("results", {}).items():
        bars.append((f"{d['scene'].rsplit('.', 1)[0]}\n{name}", r["mrays"]["median"]))
    for k, work in enumerate((g or {}).get("workloads", [])):
        for name, r in work["results"].items():
            if k == 0 or name.startswith("mitsuba"):  # ours once, from the first round
                bars.append((f"grid {g['instances']:,}\n{name}", r["mrays"]["median"]))
    if bars:
        speed.set_axis_on()
        speed.bar(range(len(bars)), [v for _, v in bars],
                  color=["C2" if "mitsuba" in n else "C0" for n, _ in bars])
        speed.set_xticks(range(len(bars)), [n.replace(" ", "\n") for n, _ in bars], fontsize=6)
        speed.set(yscale="log", ylabel="Mrays/s (median)",
                  title="d. camera rays, numpy in and out")
        plots.plain_log(speed)
        from matplotlib.ticker import NullFormatter
        speed.yaxis.set_minor_formatter(NullFormatter())  # a decade's labels crowd
    return plots.save(figure, path)


# ---------------------------------------------------------------- the command

def main(argv=None) -> dict:
    args = arguments(__doc__.splitlines()[0], argv,
                     (["--parts"], {"default": ",".join(PARTS),
                                    "help": f"comma-separated (default: {','.join(PARTS)})"}),
                     (["--repeats"], {"type": int, "default": None,
                                      "help": "builds (c) and timed calls (d) after the warm-up"}),
                     (["--frames"], {"type": int, "default": None,
                                     "help": "timed frames of part b (default: the mode's)"}))
    config = QUICK if args.quick else FULL
    if args.repeats is not None:
        if args.repeats < 1:
            raise SystemExit(f"--repeats must be at least 1, got {args.repeats}")
        config = replace(config, repeats=args.repeats)
    if args.frames is not None:
        if args.frames < 1:
            raise SystemExit(f"--frames must be at least 1, got {args.frames}")
        config = replace(config, frames=args.frames)
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    if set(parts) - set(PARTS):
        raise SystemExit(f"unknown --parts {', '.join(sorted(set(parts) - set(PARTS)))}; "
                         f"known: {', '.join(PARTS)}")
    elapsed = stopwatch()
    devices = [d.id for d in devices_or_exit(args.devices or "pocl,intel")]
    say(f"devices: {', '.join(devices)}")
    results = {"command": " ".join(["python -m bench.instances",
                                     *(sys.argv[1:] if argv is None else argv)]),
               "config": asdict(config), "quick": args.quick, "machine": machine_info(),
               "devices": devices, "targets": TARGETS}
    with progress(len(parts), "instances bench", enabled=not args.no_progress) as bar:
        if "a" in parts or "b" in parts:
            world = World(config.movers, config.seed)
            directions = sweep(*config.beams)
            ways = LidarFrames.WAYS if "b" in parts else LidarFrames.WAYS[:1]
            frames = [LidarFrames(world, directions, d, w) for d in devices for w in ways]
            errors: dict = {}
            frames, build_s = trace.build_all(world, frames, errors)
            try:
                if "a" in parts:
                    results["transforms"] = bench_transforms(
                        [f for f in frames if f.way == "instanced"], config.calls)
                    bar.update()
                if "b" in parts:
                    results["lidar"] = bench_lidar(world, frames, config.frames)
                    results["lidar"]["build_s"] = build_s
                    results["lidar"]["errors"].update(errors)
                    bar.update()
            finally:
                trace.close_all(frames)
        if "c" in parts:
            results["memory"] = bench_memory(config, devices)
            bar.update()
        if "d" in parts:
            results["identity"] = bench_identity(config, devices)
            results["grid"] = bench_grid(config, devices)
            bar.update()
    print(format_results(results))
    finish(results, "instances", args, elapsed, plot)
    if args.docs:
        write_section(BENCH / "RESULTS.md", format_results(results, markdown=True))
    return results


if __name__ == "__main__":
    main()
