"""Scene: meshes on one device and one BVH over all of them, with the verbs
an accelerator needs (intersect, occluded, update_vertices, rebuild).  The
tree is built by hlbvh_cl.build.pipeline (Lauterbach et al. 2009, Pantaleoni & Luebke
2010, Karras 2012); rendering is hlbvh_cl.render.renderer's Renderer."""
from __future__ import annotations

import contextlib
import dataclasses
import time
import weakref
from collections.abc import Sequence

import numpy as np
import pyopencl as cl

from .core import frame
from . import travel
from .build.pipeline import BUILDERS, BuildStats, Geometry, build, check_fits
from .device.discovery import ProcessLock
from .device.runtime import Runtime, event_ms, runtime
from .mesh import Mesh
from .build.morton import key_dtype
from .query.all_hits import AllHitsQuery, wide_count_packets
from .core import inputs
from .core.inputs import ALL_BITS, as_array
from .build.instances import InstancedTree, TwoLevel, check_instances, check_masks, check_transforms
from .query.points import PointQuery
from .query import on_device
from .query.rays import RayQuery
from .query.engine import refuse_spheres
from .build.refit import refit
from .core.tree import Tree


@dataclasses.dataclass(frozen=True)
class Built:
    """A built scene as Scene.borrow() lends it: valid while borrowed."""

    runtime: Runtime         # its device's runtime (hlbvh_cl.device.runtime)
    tree: Tree | InstancedTree  # the tree queries walk (an instanced scene's top tree)
    spec: travel.SceneSpec   # what the scene pickles as: its content key and arguments


def _as_meshes(meshes) -> tuple[Mesh, ...]:
    if isinstance(meshes, Mesh):
        return (meshes,)
    if not isinstance(meshes, Sequence) or isinstance(meshes, (str, bytes)):
        raise TypeError(f"meshes must be a Mesh or a sequence of Mesh, got {type(meshes).__name__}")
    out = list(meshes)
    if not out:
        raise ValueError("meshes is empty: a Scene needs at least one Mesh")
    for i, mesh in enumerate(out):
        if not isinstance(mesh, Mesh):
            raise TypeError(f"meshes[{i}] must be a hlbvh_cl.Mesh, got {type(mesh).__name__}")
    return tuple(out)


class Scene:
    """One BVH over a list of meshes on an OpenCL device, or, with
    ``instances``, a two-level scene of those meshes placed by affine maps.

    ``geom_id`` of a triangle is the index of its mesh in ``meshes`` (a
    tuple: update_vertices is the way to change one); ``prim_id`` its face
    index within that mesh.

    ``instances``: (mesh_index, transform) pairs, each transform a (3, 4) or
    (4, 4) affine map from the mesh's coordinates to the world's (mirrors and
    non-uniform scales included).  Only the instances are in the scene then
    (a mesh no instance places is an error, not silently left out); each
    mesh gets its own tree, shared by all its instances, under a top
    tree over the instances (hlbvh_cl.build.instances), and hits carry
    ``instance_id``.  ``masks``: a 32-bit mask per instance (per mesh
    without instances), default all bits; a ray query's ``mask`` skips the
    geometry whose mask shares no bit with the ray's, as in Embree.  A
    scene without instances whose masks all have every bit stays one flat
    tree over all the triangles (the faster walk); with other masks it is
    traced as one instance per mesh under the identity.

    ``spheres``: (S, 4) rows of centre x, y, z and radius, analytic spheres
    beside the meshes of a flat scene (Mitsuba's sphere shapes): sphere i
    has ``geom_id`` len(meshes) + i, prim_id 0, the exact outward normal,
    and u, v its spherical coordinates (docs/queries.md).  intersect and
    occluded (and the renderer) see them; the other queries refuse a scene
    with spheres rather than leave them out.  They take no instances nor
    masks.

    ``compact=True`` stores the tree's leaves (an instanced scene's: its
    meshes' trees') as three vertex indices a triangle beside one copy of
    the vertices, instead of three corners a triangle, as Embree's
    RTC_SCENE_FLAG_COMPACT does, takes bigger leaves where the SAH allows
    (so fewer nodes), and keeps no vertex ids for refits beside them; a flat
    compact scene keeps nothing else on the device either (its build's input
    and scratch go when the build ends, and a rebuild makes them again): on
    the Stanford reference scene it holds less than half the device memory,
    and incoherent rays trace slower (a triangle's corners wait on its
    indices).  Ray queries and closest points answer the same bits either
    way; winding numbers come from the compact tree's own dipoles, within
    the same accuracy (docs/queries.md).

    Every method may be called from any thread: each takes the scene's lock,
    so concurrent calls run in some serial order and no call sees a tree
    that a rebuild or refit has half made.  Scenes on one device share its
    queue, in order, and its kernels (Runtime.run).
    """

    def __init__(self, meshes, device=None, builder: str = "hlbvh", morton_bits: int = 30, *,
                 instances=None, masks=None, spheres=None, compact: bool = False):
        self.meshes = _as_meshes(meshes)
        if not isinstance(compact, (bool, np.bool_)):
            raise TypeError(f"compact must be True or False, got {compact!r}")
        self.compact = bool(compact)
        self._spheres = inputs.spheres(spheres)
        if len(self._spheres) and (instances is not None or masks is not None):
            raise ValueError("spheres are for flat scenes: a Scene with spheres takes no "
                             "instances nor masks (place the sphere as a mesh instead)")
        if builder not in BUILDERS:
            raise ValueError(f"builder must be one of {BUILDERS}, got {builder!r}")
        key_dtype(morton_bits)
        self.builder = builder
        self.morton_bits = morton_bits
        self._lock = ProcessLock()
        self._runtime = rt = runtime(device)
        # what pickling ships (hlbvh_cl.travel): the device as asked for
        self._device_spec = device if device is None or isinstance(device, str) else rt.device.id
        self._spec = None
        self._shared = False  # its trees are a view's too, or its original's (_view)
        self._instanced = instances is not None
        if self._instanced:
            instance_meshes, transforms = check_instances(instances, len(self.meshes))
            self._masks = check_masks(masks, len(instance_meshes), "instance")
        else:
            self._masks = check_masks(masks, len(self.meshes), "mesh")
            instance_meshes = np.arange(len(self.meshes), dtype=np.int32)
            transforms = np.tile(np.eye(3, 4), (len(self.meshes), 1, 1))
        self._query = None
        self._points = None
        self._all_hits = None
        self._tree = None
        self._two_level = None
        if self._instanced or (self._masks != ALL_BITS).any():
            weakref.finalize(self, rt.pool.clear)
            self._two_level = TwoLevel(rt, self.meshes, instance_meshes, transforms,
                                       self._masks, builder, morton_bits, self.compact)
            self._build()
            return
        vertex_counts = [m.vertex_count for m in self.meshes]
        face_counts = [m.triangle_count for m in self.meshes]
        # fail on size before anything is uploaded
        check_fits(rt, sum(vertex_counts), sum(face_counts), morton_bits, self.compact)
        self._vertex_offsets = np.concatenate([[0], np.cumsum(vertex_counts)]).astype(np.int64)
        self._first_face = np.concatenate([[0], np.cumsum(face_counts)[:-1]]).astype(np.int32)
        self._largest = [frame.largest_used(m.vertices, m.faces) for m in self.meshes]
        # the spheres' farthest points set the frame as well
        self._sphere_largest = float((np.abs(self._spheres[:, :3]).max(axis=1)
                                      + self._spheres[:, 3]).max()) if len(self._spheres) else 0.0
        self._sphere_buffer = None  # their float4 records in the tree's frame (_attach_spheres)
        self._scale = frame.scale_for(self._largest_extent())  # hlbvh_cl.core.frame
        self._warn_vanishing(range(len(self.meshes)))
        # the build's input, kept on the device for rebuilds and refits; a
        # compact tree's leaves hold the vertices themselves, so a compact
        # scene uploads it for each build only (_upload_geometry)
        self._geometry = None if self.compact else self._upload_geometry()
        self._stale_vertices = False  # the device's vertices lag self.meshes (_build)
        # the runtime's pool keeps a default scene's build scratch for its rebuilds; not
        # beyond it
        weakref.finalize(self, rt.pool.clear)
        self._build()

    def _upload_geometry(self) -> Geometry:
        """The meshes' vertices (in the tree's frame) and faces on the device."""
        vertices = np.concatenate([m.vertices for m in self.meshes])
        faces = np.concatenate([m.faces + np.int32(off) for m, off in
                                zip(self.meshes, self._vertex_offsets[:-1])])
        return Geometry.upload(self._runtime, frame.to_frame(vertices, self._scale), faces,
                               self._first_face)

    def _warn_vanishing(self, geom_ids, scale=None) -> None:
        """A RuntimeWarning for each mesh of ``geom_ids`` whose triangles the
        tree's frame (of ``scale``, default the scene's) makes degenerate
        (frame.vanishing): one far larger mesh, or coordinate, sets a frame
        in which float32 cannot hold them.  Given before anything changes:
        under a filter that makes warnings errors, it raises, and the change
        is undone (update_vertices, _change)."""
        for geom_id in geom_ids:
            frame.warn_vanishing(self.meshes[geom_id], geom_id,
                                 self._scale if scale is None else scale,
                                 self._largest_extent(), "the scene's")

    def _largest_extent(self, largest=None) -> float:
        """The largest coordinate magnitude of the meshes (``largest``: per
        mesh, default the scene's) and the spheres: what sets the frame."""
        return max(max(self._largest if largest is None else largest), self._sphere_largest)

    def _attach_spheres(self) -> None:
        """The spheres, in the new tree's frame, on the device beside it
        (Tree.spheres): uploaded again where the frame changed."""
        if not len(self._spheres):
            return
        if self._sphere_buffer is None or self._sphere_buffer[1] != self._scale:
            frame.warn_vanishing_spheres(self._spheres[:, 3], len(self.meshes), self._scale,
                                         self._largest_extent(), "the scene's")
            rt = self._runtime
            buffer = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                               hostbuf=np.ascontiguousarray(self._spheres * self._scale,
                                                               np.float32))
            self._sphere_buffer = (buffer, self._scale)
        self._tree.spheres = self._sphere_buffer[0]
        self._tree.sphere_count = len(self._spheres)
        self._tree.sphere_geom = len(self.meshes)
        self._sphere_bounds(self._tree)

    def _sphere_bounds(self, tree) -> None:
        """``tree``'s box grown around the spheres (in its frame): the
        renderer's depth range, AO distance and offsets read it."""
        if len(self._spheres):
            framed = self._spheres * self._scale
            lo, hi = framed[:, :3] - framed[:, 3:], framed[:, :3] + framed[:, 3:]
            tree.bounds_lo = np.minimum(tree.bounds_lo, lo.min(0)).astype(np.float32)
            tree.bounds_hi = np.maximum(tree.bounds_hi, hi.max(0)).astype(np.float32)

    @property
    def spheres(self) -> np.ndarray:
        """float64 (S, 4): the analytic spheres' centres and radii (a copy);
        (0, 4) for none."""
        return self._spheres.copy()

    @property
    def device(self):
        """The hlbvh_cl.Device the scene lives on."""
        return self._runtime.device

    @property
    def queue(self):
        """The scene's pyopencl CommandQueue (and, as queue.context, its
        context): pyopencl arrays made with it can be given to the ray and
        point queries, which then return pyopencl arrays on it
        (docs/queries.md, "Rays and points on the device")."""
        return self._runtime.queue

    @contextlib.contextmanager
    def borrow(self):
        """The one way into a built scene for the layers above it (the
        renderer, Dask, the CLI, the probe, the tests): a Built record of its
        runtime, its tree and what it pickles as, valid inside the ``with``,
        which holds the scene's lock so that no rebuild, refit or change
        comes in between.  Raises RuntimeError where the last rebuild
        failed (no tree)."""
        with self._lock:
            yield Built(self._runtime, self._built_tree(), self._travel_spec())

    def view(self) -> Scene:
        """Another Scene object over this one's trees, which it shares until
        either changes; the one that changes first builds trees of its own
        (copy on write), so that no change reaches another holder.
        Unpickling hands out these (hlbvh_cl.travel)."""
        with self._lock:
            return self._view()

    @property
    def instance_meshes(self) -> np.ndarray | None:
        """int32 (K,): the mesh each instance places (a copy); None without
        instances."""
        return self._two_level.instance_meshes.copy() if self._instanced else None

    @property
    def stats(self) -> BuildStats:
        """The last build's BuildStats (with refit_ms after update_vertices); on an
        instanced scene, or a flat one with masks (traced as one instance per
        mesh), the top tree's over the instances."""
        with self._lock:
            return self._stats

    def rebuild(self) -> None:
        """Build the tree from scratch over the current vertex positions.

        The old tree is released first, so a rebuild needs no more device
        memory than the first build (which check_fits accounted for), and
        the new one reuses its buffers and the last build's scratch
        (hlbvh_cl.device.pool)."""
        with self._lock:
            if self._own():  # a view builds its own trees: that is the rebuild
                return
            if self._two_level is not None:
                # the top tree points into the meshes' trees: gone before they go
                self._drop_tree()
                self._two_level.rebuild_meshes(self.meshes)
            self._build()

    def _drop_tree(self) -> None:
        """Release the tree: queries then raise (_built_tree) until a build
        succeeds, rather than trace a tree that is gone or out of date."""
        with self._lock, self._runtime.build_lock:
            old, self._tree = self._tree, None
            if old is not None:
                old.release(self._runtime.pool)

    def _build(self) -> None:
        """The tree over what the scene holds now (an instanced scene's top
        tree only: its meshes' trees stand)."""
        rt = self._runtime
        with self._lock, rt.build_lock:
            if self._two_level is None and self._stale_vertices:
                # the frame the vertices now need, and its warnings, before the old
                # tree goes: a warning raised as an error leaves the tree as it was
                scale = frame.scale_for(self._largest_extent())
                self._warn_vanishing(range(len(self.meshes)), scale)
            self._drop_tree()
            if self._two_level is not None:
                self._tree, self._stats = self._two_level.build_top()
            else:
                if self._stale_vertices:  # all of them again, in the frame they now need
                    self._scale = scale
                    if self._geometry is not None:
                        vertices = np.concatenate([m.vertices for m in self.meshes])
                        cl.enqueue_copy(rt.queue, self._geometry.vertices,
                                        frame.to_frame(vertices, self._scale))
                    self._stale_vertices = False
                # a compact scene's input lives for this build only
                geometry = (self._geometry if self._geometry is not None
                            else self._upload_geometry())
                self._tree, self._stats = build(rt, geometry, self.builder,
                                                self.morton_bits, self._scale, self.compact)
                self._attach_spheres()

    def _change(self, apply, undo, meshes: bool = False) -> None:
        """`apply` a change of content, then build the tree over it (its
        meshes' trees too with `meshes`).  When the build rejects that
        content (a ValueError, such as a map that overflows float32 in the
        built frames, or a warning that a filter raises as an error), `undo` restores the content as it was, its tree is
        built again, and the error raised: a rejected change leaves the scene
        as it was.  Anything else (Ctrl-C) that stops a change once begun
        drops the tree, so that no query answers for the content it replaced."""
        build = self.rebuild if meshes else self._build
        try:
            try:
                apply()
                build()
            except (ValueError, Warning):  # a Warning: raised as an error by a filter
                undo()
                build()
                raise
        except (ValueError, Warning):
            raise
        except BaseException:
            self._drop_tree()
            raise

    def __reduce__(self):
        """Pickles as its SceneSpec (hlbvh_cl.travel): meshes, instances, masks,
        options and device spec; it is built again on arrival, once per
        process however many copies arrive."""
        return (_restored, (self._travel_spec(),))

    def __dask_tokenize__(self):
        """Dask's token for this scene: its content key (hlbvh_cl.travel), so
        that naming a graph's tasks never pickles the scene."""
        return ("hlbvh_cl.Scene", self._travel_spec().key)

    def _travel_spec(self) -> travel.SceneSpec:
        with self._lock:
            if self._spec is None:
                instances = None
                if self._instanced:
                    instances = (self._two_level.instance_meshes.copy(),
                                 self._two_level.transforms.copy())
                masks = self._masks.copy() if (self._masks != ALL_BITS).any() else None
                self._spec = travel.SceneSpec.make(
                    self.meshes, instances, masks, self.builder, self.morton_bits,
                    self._device_spec, self._spheres.copy() if len(self._spheres) else None,
                    self.compact)
            return self._spec

    def _changing(self) -> None:
        """Before the scene's content changes: what it pickled as no longer
        holds, and a view gets trees of its own."""
        self._own()
        self._spec = None

    def _view(self) -> Scene:
        """Another Scene object over this one's trees (hlbvh_cl.travel hands
        these out): both share them until one changes, which then builds its
        own first (_own), so that no change reaches another holder (a refit
        in place, a rebuild that releases the trees)."""
        view = object.__new__(type(self))
        view.__dict__.update(self.__dict__)
        view._lock = ProcessLock()
        view._query = view._points = view._all_hits = None  # buffers of its own
        view._shared = self._shared = True
        return view

    def _own(self) -> bool:
        """Before a scene that shares its trees (a view, or one that gave
        views) changes or rebuilds: its own scene built from the content
        it shares (copy on write); true when one was built.  The lock
        stays, held by the caller."""
        with self._lock:
            if not self._shared:
                return False
            args, kwargs = self._travel_spec().arguments()
            own = dict(type(self)(*args, **kwargs).__dict__)
            del own["_lock"]
            self.__dict__.update(own)
            weakref.finalize(self, self._runtime.pool.clear)
            return True

    @property
    def transforms(self) -> np.ndarray | None:
        """float64 (K, 3, 4): each instance's map (a copy); None without instances."""
        return self._two_level.transforms.copy() if self._instanced else None

    @property
    def masks(self) -> np.ndarray:
        """uint32: the mask of each instance (each mesh without instances), a copy."""
        return self._masks.copy()

    def set_transforms(self, instance_ids, transforms) -> None:
        """Move instances: ``transforms`` (K, 3, 4) or (K, 4, 4) for the K
        ``instance_ids`` (one id and one (3, 4) / (4, 4) map work too).  Only
        the top tree is rebuilt, on the device; the meshes' trees stand."""
        if not self._instanced:
            raise ValueError("set_transforms needs an instanced Scene: Scene(meshes, "
                             "instances=[(mesh_index, transform), ...])")
        ids = as_array("instance_ids", instance_ids)
        if ids.size == 0 and ids.dtype.kind == "f":  # [] is float64 to numpy
            ids = ids.astype(np.int64)
        if ids.dtype.kind not in "iu":  # not bool, nor timedelta64 (a numpy integer)
            raise TypeError(f"instance_ids must be integers, got dtype {ids.dtype}")
        array = as_array("transforms", transforms)
        if ids.ndim == 0:  # one id, with one map or a stack of one
            ids = ids[None]
            if array.ndim == 2:
                array = array[None]
        if ids.ndim != 1:
            raise ValueError(f"instance_ids has shape {ids.shape}, expected (K,)")
        count = len(self._two_level.instance_meshes)
        outside = (ids < 0) | (ids >= count)
        if outside.any():
            k = int(np.flatnonzero(outside)[0])
            raise ValueError(f"instance_ids[{k}] = {int(ids[k])} is out of range: the scene has "
                             f"{count} instance(s)")
        first = np.unique(ids, return_index=True)[1]
        if len(first) < len(ids):  # which of two maps would hold is no choice to make silently
            k = int(np.setdiff1d(np.arange(len(ids)), first)[0])
            raise ValueError(f"instance_ids[{k}] = {int(ids[k])} is given twice")
        maps = check_transforms(array, lambda k: f"transforms[{k}]")
        if len(maps) != len(ids):
            raise ValueError(f"transforms has {len(maps)} maps for {len(ids)} instance_ids")
        with self._lock:
            self._changing()
            previous = self._two_level.transforms.copy()

            def apply():
                self._two_level.transforms[ids] = maps
            self._change(apply, lambda: setattr(self._two_level, "transforms", previous))

    def update_vertices(self, geom_id: int, vertices, normals=None) -> None:
        """Replace mesh ``geom_id``'s vertex positions (same count) and refit
        the tree's boxes on the device; the topology is kept, and with it
        stats.sah_cost (of the tree as built).  (Unless the move takes the
        scene's largest coordinate across 2^24 or 2^-24 from the frame it was
        built in: then it is rebuilt in a new frame, hlbvh_cl.core.frame.)
        ``normals``: the mesh's new per-vertex shading normals (as Mesh
        takes them); None keeps those the mesh was given, and computes them
        anew from the moved vertices where it had none (Mesh.normals)."""
        geom_id = inputs.integer("geom_id", geom_id)
        if not 0 <= geom_id < len(self.meshes):
            raise ValueError(f"geom_id {geom_id} is out of range: the scene has "
                             f"{len(self.meshes)} mesh(es)")
        old = self.meshes[geom_id]
        positions = inputs.mesh_vertices(vertices)
        if len(positions) != old.vertex_count:
            raise ValueError(f"vertices has {len(positions)} rows but mesh {geom_id} has "
                             f"{old.vertex_count} vertices; update_vertices keeps the topology")
        inputs.check_mesh_scale(vertices, old.faces)  # (Mesh sees float32 positions)
        if normals is None and old.has_file_normals:
            normals = old.normals  # given normals stay the caller's (computed ones follow)
        moved = Mesh(positions, old.faces, name=old.name, normals=normals,
                     face_normals=old.face_normals)
        rt = self._runtime
        started = time.perf_counter()
        # one lock throughout: a pickle between dropping the old content's
        # spec and changing the meshes would describe the old content
        with self._lock:
            self._changing()
            meshes = self.meshes[:geom_id] + (moved,) + self.meshes[geom_id + 1:]
            if self._two_level is not None:  # the mesh's own tree is built anew, then the top
                previous = self.meshes
                self._change(lambda: setattr(self, "meshes", meshes),
                             lambda: setattr(self, "meshes", previous), meshes=True)
                return
            largest = list(self._largest)
            largest[geom_id] = frame.largest_used(moved.vertices, moved.faces)
            tree = self._tree
            previous = self.meshes, self._largest
            try:
                # the meshes are new from here on, whatever fails below; until
                # the upload is done, a build uploads them all (_build)
                self._stale_vertices = True
                self.meshes, self._largest = meshes, largest
                if tree is None or frame.scale_for(self._largest_extent(largest)
                                                   * self._scale) != 1.0:
                    # out of this frame (or no tree since a failed rebuild): build anew
                    self.rebuild()
                    return
                self._warn_vanishing([geom_id])
                # the moved vertices into the scene's; a compact scene's are the
                # ones its leaves hold, after their records
                target, first = ((self._geometry.vertices, 0) if self._geometry is not None
                                 else (tree.triangles, tree.triangle_count))
                upload = cl.enqueue_copy(rt.queue, target,
                                         frame.to_frame(moved.vertices, self._scale),
                                         dst_offset=(first + int(self._vertex_offsets[geom_id]))
                                         * 12, is_blocking=False)
                self._stale_vertices = False
                events = refit(rt, tree, None if self._geometry is None
                               else self._geometry.vertices, wait_for=[upload])
                tree.bounds_lo, tree.bounds_hi = tree.read_root_box(rt.queue,
                                                                    wait_for=events[-1:])
                self._sphere_bounds(tree)
            except Warning:  # raised as an error (a warnings filter), before the tree
                self.meshes, self._largest = previous  # or the device changed (_build)
                self._stale_vertices = False
                raise
            except BaseException:  # Ctrl-C, a failed refit or build: the meshes are new
                rt.queue.finish()  # and the boxes old or part old, so no query may use them
                self._drop_tree()
                raise
            self._stats = dataclasses.replace(self._stats, refit_ms={
                "upload": event_ms([upload]), "refit": event_ms(events),
                "wall": (time.perf_counter() - started) * 1e3})

    def intersect(self, origins, directions=None, tmin=0.0, tmax=np.inf, mask=None):
        """Closest hit of each ray: a Hits with t, prim_id, geom_id,
        instance_id, u, v, normal (world space) and points, in the rays'
        leading shape.  Rays are origins and directions (..., 3), which
        broadcast (one origin (3,) for many directions), or packed (..., 6)
        in ``origins`` alone; tmin and tmax are scalars or broadcast to the
        rays (hlbvh_cl.core.inputs); ``mask``, a 32-bit integer or one per ray,
        skips the geometry whose mask shares no bit with it."""
        with self._lock:
            hits = self._ray_query().intersect(self._built_tree(), origins, directions, tmin,
                                               tmax, mask)
            if self._two_level is not None and not self._instanced:
                # instances of the masks' making, not the caller's
                on_device.fill(hits.instance_id, -1)
            return hits

    def occluded(self, origins, directions=None, tmin=0.0, tmax=np.inf,
                 mask=None) -> np.ndarray:
        """Whether each ray hits anything in [tmin, tmax] (any-hit, stops
        early), in the rays' leading shape; rays and mask as intersect takes
        them."""
        with self._lock:
            return self._ray_query().occluded(self._built_tree(), origins, directions, tmin,
                                              tmax, mask)

    def intersect_all(self, origins, directions=None, tmin=0.0, tmax=np.inf, max_hits=None,
                      mask=None):
        """Every hit of each ray in [tmin, tmax], sorted by t, as an AllHits
        (flat arrays, ray r's hits at [offsets[r], offsets[r + 1]), rays as
        intersect takes them, numbered in C order); with max_hits=k only the
        k nearest of each ray; mask as intersect takes it.  A crossing
        through a shared edge or vertex counts once."""
        with self._lock:
            hits = self._all_hits_query().intersect_all(self._built_tree(), origins, directions,
                                                        tmin, tmax, max_hits, mask)
            if self._two_level is not None and not self._instanced:
                on_device.fill(hits.instance_id, -1)  # instances of the masks' making
            return hits

    def count_intersections(self, origins, directions=None, tmin=0.0,
                            tmax=np.inf, mask=None) -> np.ndarray:
        """int32, in the rays' leading shape: how many hits each ray has in
        [tmin, tmax] (as intersect_all counts them; mask as intersect)."""
        with self._lock:
            return self._all_hits_query().count(self._built_tree(), origins, directions, tmin,
                                                tmax, mask)

    def _all_hits_query(self):
        if self._all_hits is None:
            query = self._ray_query()
            self._all_hits = AllHitsQuery(query, wide_count_packets(query))
        return self._all_hits

    def closest_points(self, points, max_distance=np.inf):
        """The nearest surface point of each of the (..., 3) ``points`` within
        ``max_distance``: a ClosestPoints with points, distance, prim_id,
        geom_id, instance_id, u, v and normal in the points' leading shape
        (distance inf and ids -1 beyond it).  Point queries take no mask:
        they see every instance (every mesh)."""
        with self._lock:
            found = self._point_query().closest_points(self._built_tree(), points, max_distance)
            if self._two_level is not None and not self._instanced:
                on_device.fill(found.instance_id, -1)  # instances of the masks' making
            return found

    def winding_number(self, points) -> np.ndarray:
        """float32: the generalized winding number of each point (1 inside a
        closed outward-oriented surface, -1 inside an inward-oriented one, 0
        outside, fractional near the holes of an open one; hlbvh_cl.query.points).
        With instances: the sum over them of each mesh's own winding number
        at the point mapped into it, negated for a mirroring map (on closed
        meshes the flattened scene's)."""
        with self._lock:
            return self._point_query().winding_numbers(self._built_tree(), points)

    def signed_distance(self, points) -> np.ndarray:
        """float32: the distance to the surface, negative inside, i.e. where
        |winding number| >= 0.5, whichever way the faces turn (on an open mesh
        that closes each hole minimally; see hlbvh_cl.query.points)."""
        with self._lock:
            return self._point_query().signed_distance(self._built_tree(), points)

    def contains(self, points) -> np.ndarray:
        """bool: whether each point is inside (|winding number| >= 0.5)."""
        with self._lock:
            refuse_spheres(self._built_tree(), "contains")
        inside = abs(self.winding_number(points)) >= 0.5
        return inside if isinstance(inside, np.ndarray) else inside.view(bool)  # int8 0 or 1

    def _point_query(self):
        if self._points is None:
            self._points = PointQuery(self._runtime)
        return self._points

    def _built_tree(self):
        """The current tree; a clear error when the last rebuild or update failed (the
        old tree was released before it) and none has been built since."""
        if self._tree is None:
            raise RuntimeError("this Scene has no tree: its last rebuild or update failed; "
                               "call scene.rebuild() (or update_vertices) to build one")
        return self._tree

    def _ray_query(self):
        if self._query is None:
            self._query = RayQuery(self._runtime)
        return self._query

    def __repr__(self) -> str:
        if self._instanced:
            held = f"{len(self._two_level.transforms):,} instances"
        else:
            held = f"{sum(m.triangle_count for m in self.meshes):,} triangles"
            if len(self._spheres):
                held += f" and {len(self._spheres):,} sphere(s)"
        compact = ", compact=True" if self.compact else ""
        return (f"Scene({len(self.meshes)} mesh(es), {held}, builder={self.builder!r}{compact}, "
                f"device={self.device.id!r})")


def _restored(spec: travel.SceneSpec) -> Scene:
    """A pickled Scene on arrival (hlbvh_cl.travel)."""
    return travel.restore(spec, Scene)
