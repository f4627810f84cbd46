"""Scene: meshes on one device, one BVH over all of them, and the few verbs
users call (construct, update_vertices/rebuild, intersect/occluded, render)."""
from __future__ import annotations

import threading
import time
import weakref
from collections.abc import Sequence

import numpy as np
import pyopencl as cl

from . import frame, layout
from .build import BUILDERS, Geometry, build, check_fits
from .build import STAGES as BVH_STAGES
from .device import event_ms, runtime
from .mesh import Mesh, _validate_vertices
from .morton import key_dtype
from .refit import refit_flat_tree
from .render import AO_SAMPLES, Light, Renderer, RenderSettings, check_colors, check_light, \
    default_colors
from .widen import widen


#: stats["times_ms"] keys besides total and wall: the BVH2 build's stages,
#: then the 8-wide copy that traversal reads.
STAGES = BVH_STAGES + ("widen",)

def _as_meshes(meshes) -> list[Mesh]:
    if isinstance(meshes, Mesh):
        return [meshes]
    if not isinstance(meshes, Sequence) or isinstance(meshes, (str, bytes)):
        raise TypeError(f"meshes must be a Mesh or a sequence of Mesh, got {type(meshes).__name__}")
    out = list(meshes)
    if not out:
        raise ValueError("meshes is empty: a Scene needs at least one Mesh")
    for i, mesh in enumerate(out):
        if not isinstance(mesh, Mesh):
            raise TypeError(f"meshes[{i}] must be a hlbvh_cl.Mesh, got {type(mesh).__name__}")
    return out


class Scene:
    """One BVH over a list of meshes on an OpenCL device.

    ``geom_id`` of a triangle is the index of its mesh in ``meshes``;
    ``prim_id`` its face index within that mesh.

    For rendering, ``colors`` holds one RGB triple (0..1) per mesh (by
    default render.PALETTE, cycled) and ``light`` a hlbvh_cl.Light (by
    default direction (1, 2, 1), intensity 1, ambient 0.15); both may be
    reassigned at any time.

    Every method may be called from any thread: each takes the scene's lock,
    so concurrent calls run in some serial order and no call sees a tree
    that a rebuild or refit has half made.  Scenes on one device share its
    queue, in order, and its kernels (Runtime.run).
    """

    def __init__(self, meshes, device=None, builder: str = "hlbvh", morton_bits: int = 30):
        self.meshes = _as_meshes(meshes)
        if builder not in BUILDERS:
            raise ValueError(f"builder must be one of {BUILDERS}, got {builder!r}")
        key_dtype(morton_bits)
        self.builder = builder
        self.morton_bits = morton_bits
        self._lock = threading.RLock()
        self.runtime = runtime(device)
        vertex_counts = [m.vertex_count for m in self.meshes]
        face_counts = [m.triangle_count for m in self.meshes]
        # fail on size before anything is uploaded
        check_fits(self.runtime, sum(vertex_counts), sum(face_counts), morton_bits)
        self._vertex_offsets = np.concatenate([[0], np.cumsum(vertex_counts)]).astype(np.int64)
        first_face = np.concatenate([[0], np.cumsum(face_counts)[:-1]]).astype(np.int32)
        faces = np.concatenate([m.faces + np.int32(off) for m, off in
                                zip(self.meshes, self._vertex_offsets[:-1])])
        vertices = np.concatenate([m.vertices for m in self.meshes])
        self._largest = [frame.largest_magnitude(m.vertices) for m in self.meshes]
        self._scale = frame.scale_for(max(self._largest))  # the tree's frame (hlbvh_cl.frame)
        self._geometry = Geometry.upload(self.runtime, frame.to_frame(vertices, self._scale),
                                         faces, first_face)
        # the runtime's pool keeps this scene's build scratch for its rebuilds; not beyond it
        weakref.finalize(self, self.runtime.pool.clear)
        self._query = None
        self._renderer = None
        self.colors = default_colors(len(self.meshes))
        self.light = Light()
        self.rebuild()

    @property
    def device(self):
        return self.runtime.device

    @property
    def tree(self):
        with self._lock:
            return self._build.tree

    @property
    def stats(self) -> dict:
        """triangles, nodes, leaves, depth, sah_cost (of the binary tree) and
        times_ms of the last build: device time per stage (bounds, morton,
        sort, radix_tree, sah_top, flatten, and widen, the 8-wide copy that
        traversal reads), their total, and the host's wall time.  After
        update_vertices, sah_cost is recomputed from the refit boxes and
        update_ms holds the refit's times (both trees)."""
        with self._lock:
            if self._sah_stale:
                self._build.stats["sah_cost"] = self.tree.sah_cost(self.runtime.queue)
                self._sah_stale = False
            return self._build.stats

    def rebuild(self) -> None:
        """Build the tree from scratch over the current vertex positions.

        The old tree is released first, so a rebuild needs no more device
        memory than the first build (which check_fits accounted for), and
        the new one reuses its buffers and the last build's scratch
        (hlbvh_cl.pool); a DeviceTree taken from ``scene.tree`` before is
        invalid after."""
        rt = self.runtime
        with self._lock, rt.build_lock:
            old, self._build = getattr(self, "_build", None), None
            if old is not None:
                old.tree.release(rt.pool)
            started = time.perf_counter()
            with rt.pool.build():
                self._build = build(rt, self._geometry, self.builder, self.morton_bits)
                self.tree.scale = self._scale
                # the wide tree that traversal reads (stage 7), derived from the BVH2
                self.tree.wide, events = widen(rt, self.tree)
            cl.wait_for_events(events)
        times = self._build.stats["times_ms"]
        times["widen"] = event_ms(events)
        times["total"] += times["widen"]
        times["wall"] = (time.perf_counter() - started) * 1e3
        self._sah_stale = False

    def update_vertices(self, geom_id: int, vertices) -> None:
        """Replace mesh ``geom_id``'s vertex positions (same count) and refit
        the tree's boxes on the device; the topology is kept.  (Unless the
        move takes the scene's largest coordinate across 2^24 or 2^-24 from
        the frame it was built in: then it is rebuilt in a new frame,
        hlbvh_cl.frame.)"""
        if isinstance(geom_id, bool) or not isinstance(geom_id, (int, np.integer)):
            raise TypeError(f"geom_id must be an int, got {type(geom_id).__name__}")
        if not 0 <= geom_id < len(self.meshes):
            raise ValueError(f"geom_id {geom_id} is out of range: the scene has "
                             f"{len(self.meshes)} mesh(es)")
        old = self.meshes[geom_id]
        positions = _validate_vertices(vertices)
        if len(positions) != old.vertex_count:
            raise ValueError(f"vertices has {len(positions)} rows but mesh {geom_id} has "
                             f"{old.vertex_count} vertices; update_vertices keeps the topology")
        moved = Mesh(positions, old.faces, name=old.name)
        rt = self.runtime
        started = time.perf_counter()
        with self._lock, rt.build_lock:  # not while a build on this runtime uses the pool
            largest = list(self._largest)
            largest[geom_id] = frame.largest_magnitude(moved.vertices)
            if frame.scale_for(max(largest) * self._scale) != 1.0:  # out of this frame
                self.meshes[geom_id], self._largest = moved, largest
                self._scale = frame.scale_for(max(largest))
                vertices = np.concatenate([m.vertices for m in self.meshes])
                cl.enqueue_copy(rt.queue, self._geometry.vertices,
                                frame.to_frame(vertices, self._scale))
                self.rebuild()
                return
            upload = cl.enqueue_copy(rt.queue, self._geometry.vertices,
                                     frame.to_frame(moved.vertices, self._scale),
                                     dst_offset=int(self._vertex_offsets[geom_id]) * 12,
                                     is_blocking=False)
            events = refit_flat_tree(rt, self.tree, self._geometry.vertices, wait_for=[upload])
            self.meshes[geom_id], self._largest = moved, largest
            root = _read_root(rt.queue, self.tree.nodes, events)
            lo = np.minimum(root["left_lo"], root["right_lo"])
            hi = np.maximum(root["left_hi"], root["right_hi"])
            self.tree.bounds_lo, self.tree.bounds_hi = lo, hi
            self._sah_stale = True
            self._build.stats["update_ms"] = {"upload": event_ms([upload]),
                                              "refit": event_ms(events),
                                              "wall": (time.perf_counter() - started) * 1e3}

    def intersect(self, origins, directions, tmin=0.0, tmax=np.inf):
        """Closest hit of each ray: a Hits with t, prim_id, geom_id, u, v, normal."""
        with self._lock:
            return self._ray_query().intersect(self.tree, origins, directions, tmin, tmax)

    def occluded(self, origins, directions, tmin=0.0, tmax=np.inf) -> np.ndarray:
        """Whether each ray hits anything in [tmin, tmax] (any-hit, stops early)."""
        with self._lock:
            return self._ray_query().occluded(self.tree, origins, directions, tmin, tmax)

    def render(self, camera, width: int, height: int, shading: str = "diffuse",
               shadows: bool = True, spp: int = 1, ao_samples: int = AO_SAMPLES,
               ao_distance: float | None = None, progress: bool = False) -> np.ndarray:
        """Render the scene through a hlbvh_cl.Camera: a (height, width, 3)
        uint8 RGB image.  shading is "diffuse", "normals", "depth" or "ao";
        spp samples per pixel; ao_samples AO rays per sample, reaching
        ao_distance (default 5% of the scene's diagonal).  progress shows a
        tqdm bar on stderr for renders longer than a second.  The formulas
        are in hlbvh_cl/render.py; ``render_stats`` times the last render."""
        settings = RenderSettings.check(camera, width, height, shading, shadows, spp,
                                        ao_samples, ao_distance)
        colors = check_colors(self.colors, len(self.meshes))
        light = check_light(self.light)
        with self._lock:
            if self._renderer is None:
                self._renderer = Renderer(self.runtime)  # its own queries and buffers
            return self._renderer.render(self.tree, settings, colors, light, progress=progress)

    @property
    def render_stats(self) -> dict:
        """Rays and device times (ms per stage) of the last render; {} before one."""
        return self._renderer.last_stats if self._renderer is not None else {}

    def _ray_query(self):
        if self._query is None:
            from .query import RayQuery
            self._query = RayQuery(self.runtime)
        return self._query

    def __repr__(self) -> str:
        s = self.stats
        return (f"Scene({len(self.meshes)} mesh(es), {s['triangles']:,} triangles, "
                f"builder={self.builder!r}, device={self.device.id!r})")


def _read_root(queue, nodes, wait_for):
    out = np.empty(1, layout.FLAT_NODE)
    cl.enqueue_copy(queue, out, nodes, wait_for=wait_for)
    return out[0]
