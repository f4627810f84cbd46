"""Other ray tracers, traced on the same rays as hlbvh_cl (bench/trace.py).

Each peer builds its structure from one mesh, float32 vertices (N, 3) and
int32 faces (M, 3), then answers closest-hit and any-hit queries on float32
(R, 3) origins and unit directions, numpy in and numpy out, so that the
conversions each API needs are part of its time.  A peer that cannot be
imported (not installed, or missing a system library: bench/setup_peers.sh)
is reported as missing, never raised.
"""
from __future__ import annotations

import importlib
import importlib.metadata
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .common import stopwatch

#: Python threads the embreex peer splits its rays over (its run releases the GIL).
EMBREE_THREADS = 2


class Peer:
    """A ray tracer imported on first use; ``problem`` says why it cannot run.

    build(vertices, faces) returns its seconds; intersect(rays) returns what
    the API returns, hits(that) a bool per ray; occluded(rays) a bool per ray.
    ``rays`` has origins, directions and kind ("primary" or "incoherent")."""

    kind = "peer"
    name = label = distribution = ""
    modules: tuple[str, ...] = ()

    def __init__(self):
        self.problem: str | None = None
        self.version: str | None = None
        self.scene = None

    def load(self) -> bool:
        """Import the peer; False (with ``problem`` set) when it is missing or broken."""
        try:
            for module in self.modules:
                importlib.import_module(module)
            self.version = importlib.metadata.version(self.distribution)
        except Exception as error:  # ImportError, OSError (no libusb), RuntimeError (no LLVM)
            self.problem = f"{type(error).__name__}: {error}".strip()
        return self.problem is None

    def describe(self) -> dict:
        return {"kind": self.kind, "label": self.label, "available": self.problem is None,
                "version": self.version, "problem": self.problem}

    def close(self) -> None:
        self.scene = None


class EmbreexPeer(Peer):
    name = distribution = "embreex"
    label = f"embreex (Embree 4), {EMBREE_THREADS} threads"
    modules = ("embreex.rtcore_scene", "embreex.mesh_construction")
    pool = None

    def build(self, vertices, faces) -> float:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
        elapsed = stopwatch()
        self.scene = rtcore_scene.EmbreeScene()
        TriangleMesh(self.scene, vertices, faces)
        self.scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))  # commits
        seconds = elapsed()
        self.pool = ThreadPoolExecutor(EMBREE_THREADS)
        return seconds

    def _run(self, rays, **options) -> list:
        cuts = np.linspace(0, len(rays.origins), EMBREE_THREADS + 1).astype(int)
        return [f.result() for f in [
            self.pool.submit(self.scene.run, rays.origins[a:b], rays.directions[a:b], **options)
            for a, b in zip(cuts[:-1], cuts[1:])]]

    def intersect(self, rays) -> dict:
        parts = self._run(rays, output=1)
        return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}

    def hits(self, result) -> np.ndarray:
        return result["primID"] >= 0

    def occluded(self, rays) -> np.ndarray:
        # embreex's OCCLUDED query gives 0 for an occluded ray and -1 otherwise
        return np.concatenate(self._run(rays, query="OCCLUDED")) != -1

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()
        self.pool = self.scene = None


class Open3DPeer(Peer):
    name = distribution = "open3d"
    label = "Open3D RaycastingScene"
    modules = ("open3d",)

    def build(self, vertices, faces) -> float:
        import open3d
        elapsed = stopwatch()
        self.scene = open3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(open3d.core.Tensor(vertices),
                                 open3d.core.Tensor(faces.astype(np.uint32)))
        self.scene.cast_rays(open3d.core.Tensor(np.array([[0, 0, 0, 1, 1, 1]], np.float32)))
        return elapsed()

    @staticmethod
    def _tensor(rays):
        import open3d
        return open3d.core.Tensor(np.concatenate([rays.origins, rays.directions], axis=1))

    def intersect(self, rays) -> dict:
        answer = self.scene.cast_rays(self._tensor(rays))
        return {key: answer[key].numpy() for key in
                ("t_hit", "geometry_ids", "primitive_ids", "primitive_uvs", "primitive_normals")}

    def hits(self, result) -> np.ndarray:
        return np.isfinite(result["t_hit"])

    def occluded(self, rays) -> np.ndarray:
        return self.scene.test_occlusions(self._tensor(rays)).numpy()


class MitsubaPeer(Peer):
    name = distribution = "mitsuba"
    label = "Mitsuba 3 llvm_ad_rgb"
    modules = ("mitsuba",)

    def load(self) -> bool:
        if super().load():
            try:
                import mitsuba
                mitsuba.set_variant("llvm_ad_rgb")  # fails without libLLVM
            except Exception as error:
                self.problem = f"{type(error).__name__}: {error}".strip()
        return self.problem is None

    @staticmethod
    def mesh(vertices, faces):
        """A Mitsuba Mesh of float32 vertices (N, 3) and faces (M, 3)."""
        import mitsuba as mi
        mesh = mi.Mesh("bench", len(vertices), len(faces), has_vertex_normals=False,
                       has_vertex_texcoords=False)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(vertices.ravel())
        params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
        params.update()
        return mesh

    def build(self, vertices, faces) -> float:
        import mitsuba as mi
        elapsed = stopwatch()
        self.scene = mi.load_dict({"type": "scene", "mesh": self.mesh(vertices, faces)})
        return elapsed()

    def _ray(self, rays):
        import mitsuba as mi
        # Dr.Jit takes a ray's coordinates as one array each, reads numpy arrays in
        # place and compiles a kernel for each pattern of their alignments: the (R, 3)
        # arrays go in one pass each into rows on 64 bytes of a buffer kept from call
        # to call, as our queries keep theirs (results.ResultPool).  Six fresh aligned
        # columns, copied one by one, had taken half of the timed call on camera rays.
        count = len(rays.origins)
        if getattr(self, "_columns", np.empty((6, 0))).shape[1] < count:
            self._columns = _aligned_rows(6, count)
        rows = self._columns[:, :count]
        rows[:3] = rays.origins.T
        rows[3:] = rays.directions.T
        return mi.Ray3f(o=mi.Point3f(*rows[:3]), d=mi.Vector3f(*rows[3:]))

    def intersect(self, rays) -> dict:
        import drjit as dr
        import mitsuba as mi
        found = self.scene.ray_intersect_preliminary(self._ray(rays),
                                                     coherent=rays.kind == "primary")
        valid = found.is_valid()  # a miss has t = inf but prim_index 0
        t = dr.select(valid, found.t, dr.inf)
        prim = dr.select(valid, mi.Int32(found.prim_index), -1)
        dr.eval(t, prim, found.prim_uv)
        return {"t": t.numpy(), "prim_index": prim.numpy(), "uv": found.prim_uv.numpy()}

    def hits(self, result) -> np.ndarray:
        return result["prim_index"] >= 0

    def occluded(self, rays) -> np.ndarray:
        return self.scene.ray_test(self._ray(rays), coherent=rays.kind == "primary").numpy()


def _aligned_rows(rows: int, count: int, alignment: int = 64) -> np.ndarray:
    """float32 (rows, at least count), each row starting on a multiple of
    ``alignment`` bytes."""
    stride = -(-count * 4 // alignment) * alignment // 4
    raw = np.empty(rows * stride * 4 + alignment, np.uint8)
    start = -raw.ctypes.data % alignment
    return raw[start:start + rows * stride * 4].view(np.float32).reshape(rows, stride)


class TrimeshPeer(Peer):
    name = distribution = "trimesh"
    label = "trimesh RayMeshIntersector (embreex, 1 thread)"
    modules = ("trimesh", "trimesh.ray.ray_pyembree")

    def build(self, vertices, faces) -> float:
        import trimesh
        from trimesh.ray.ray_pyembree import RayMeshIntersector
        elapsed = stopwatch()
        self.scene = RayMeshIntersector(trimesh.Trimesh(vertices, faces, process=False))
        self.scene.intersects_first(np.zeros((1, 3)), np.ones((1, 3)))  # builds
        return elapsed()

    def intersect(self, rays) -> np.ndarray:
        return self.scene.intersects_first(rays.origins, rays.directions)

    def hits(self, result) -> np.ndarray:
        return result >= 0

    def occluded(self, rays) -> np.ndarray:
        return self.scene.intersects_any(rays.origins, rays.directions)


PEERS = {peer.name: peer for peer in (EmbreexPeer, Open3DPeer, MitsubaPeer, TrimeshPeer)}
#: hit/miss agreement is measured against this peer when it runs
REFERENCE = "embreex"


def load_peers(names, known: dict | None = None) -> tuple[list[Peer], list[Peer]]:
    """(available, missing) peers among ``names``, keys of ``known`` (default PEERS)."""
    known = PEERS if known is None else known
    available, missing = [], []
    for name in names:
        if name not in known:
            raise ValueError(f"unknown peer {name!r}; known: {', '.join(known)}")
        peer = known[name]()
        (available if peer.load() else missing).append(peer)
    return available, missing
