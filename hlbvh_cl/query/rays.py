"""Ray queries on a finished Tree: closest hit and any hit, as a stack-based
walk of its 8-wide nodes (kernels/traverse.cl; Wald, Benthin & Boulos 2008,
and the watertight ray-triangle test of Woop, Benthin & Wald 2013), one ray or one small
packet of rays per work-item.  A query never builds or changes the tree.

Conventions, shared with tests/oracle.py:
  - a ray hits at distance t when tmin <= t <= tmax, with t in units of the
    direction's length (directions are not normalised);
  - tmin must be >= 0 and finite (as Embree's tnear), tmax >= tmin (may be inf);
  - no back-face culling; degenerate (zero-area) triangles are never hit;
  - u, v are barycentrics: hit = (1-u-v)*v0 + u*v1 + v*v2, and the normal is
    cross(v1-v0, v2-v0) normalised (it follows the winding).
"""
from __future__ import annotations

import dataclasses
import math
import threading
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from ..core import frame
from ..core import inputs
from ..core import layout
from ..device.runtime import Runtime
from ..device.profile import PACKET_SIZES
from .results import ResultPool, starts_on_page
from ..core.inputs import ALL_BITS
from ..build.instances import InstancedTree
from ..core.tree import Tree


#: Rays per kernel launch at most: enough to fill any device, few enough that
#: a launch ends soon, so that Ctrl-C (which waits for the launches in
#: flight, at most two) is answered within a second.
MAX_RAYS_PER_LAUNCH = 1 << 20

#: A launch's time is its rays' cost, which a scene of many overlapping
#: instances makes far higher: a batch's first launch takes at most
#: FIRST_LAUNCH rays, and each later one as many as the last to end says
#: LAUNCH_SECONDS allow (LaunchSizes).
FIRST_LAUNCH = 1 << 16
LAUNCH_SECONDS = 0.25


class LaunchSizes:
    """Items per launch for a batch: `first` (FIRST_LAUNCH by default) for
    the first launch, then what the last one ended took per item allows in
    LAUNCH_SECONDS, always within [1, most].  ``next`` paces the launches:
    at most two in flight (Ctrl-C waits for those), and the second only once
    the first has ended and sized it."""

    def __init__(self, most: int, first: int | None = None):
        self.most = most
        self.size = min(most, FIRST_LAUNCH if first is None else first)
        self.measured = False
        self._launches: list[tuple[object, int]] = []  # (event, items) of each

    def next(self, rt) -> int:
        """Waits for the launch two back (the first, while none has been
        measured) and gives the next launch's size."""
        count = len(self._launches)
        if count >= 2 or (count == 1 and not self.measured):
            event, items = self._launches[max(0, count - 2)]
            rt.wait([event])
            self.ended(event, items)
        return self.size

    def launched(self, event, items: int) -> None:
        self._launches.append((event, items))

    def ended(self, event, items: int) -> None:
        """A launch of ``items`` items has ended (its profiled event)."""
        seconds = (event.profile.end - event.profile.start) * 1e-9
        fits = LAUNCH_SECONDS * items / seconds if seconds > 0 else self.most
        self.size = int(max(1, min(self.most, fits)))
        self.measured = True


#: Stack sizes are rounded up to a multiple of this so that few program
#: variants get compiled.
STACK_GRANULE = 16


@dataclass
class Hits:
    """Closest hits of R rays; misses have t = inf, ids -1, u = v = 0, normal 0
    and points NaN."""

    t: np.ndarray        # float32 (R,)
    prim_id: np.ndarray  # int32 (R,) face index within its own mesh
    geom_id: np.ndarray  # int32 (R,) mesh index in the scene
    u: np.ndarray        # float32 (R,)
    v: np.ndarray        # float32 (R,)
    normal: np.ndarray   # float32 (R, 3) unit geometric normal, in world space
    points: np.ndarray   # float32 (R, 3) origin + t * direction, in the caller's coordinates
    instance_id: np.ndarray  # int32 (R,) instance hit in an instanced scene; else -1

    def __len__(self) -> int:
        return len(self.t)

    @property
    def hit(self) -> np.ndarray:
        """bool (R,): which rays hit something."""
        return self.geom_id >= 0


def zero_copy(rt: Runtime) -> bool:
    """Whether queries hand the kernels the numpy arrays themselves
    (CL_MEM_USE_HOST_PTR) instead of device copies.

    Only on PoCL's CPU device, where a device copy is just two memcpys and
    zero copy measured faster.  Intel's CPU runtime measured the other way,
    and a GPU's memory is its own.
    """
    return (not rt.profile.gpu and rt.device.id.startswith("pocl")
            and bool(rt.device.cl_device.host_unified_memory))


def outputs_in_place(rt: Runtime) -> bool:
    """Whether queries that copy the rays to the device let the kernels write
    the results straight into the result arrays (CL_MEM_USE_HOST_PTR),
    which the result pool starts on a page (results.ALIGNMENT; Intel's CPU
    runtime uses a host pointer in place only there).

    On Intel's CPU runtime, where the rays' own arrays measured slower in
    place (a caller's arrays seldom start on a page, zero_copy) but the
    results written in place measured faster, with the same results.
    """
    return rt.device.id.startswith("intel") and not rt.profile.gpu


def work_group_size(rt: Runtime) -> int:
    """Work-items per group for the traversal kernels.

    PoCL's speed hardly depends on it, nor does Intel's CPU runtime's up to
    8.  At 16 and more Intel would pack 16 rays into SIMD lanes (much slower:
    divergence), which the kernels' vec_type_hint now prevents, but 8 stays
    the safe choice.  GPUs want at least a warp/wavefront.
    """
    d = rt.device
    if rt.profile.gpu:
        size = 64
    elif d.id.startswith("intel"):
        size = 8
    else:
        size = 16
    return min(size, d.cl_device.max_work_group_size)


#: Device buffers of the numpy-facing queries, bytes per ray: the inputs, then
#: one buffer per field of the results (kernels/traverse.cl's *_arrays kernels).
RAY_ARRAYS = {"origins": 12, "directions": 12, "tmin": 4, "tmax": 4, "mask": 4}
#: Hits' fields: dtype and values per ray.
HIT_FIELDS = {"t": (np.float32, 1), "geom_id": (np.int32, 1), "prim_id": (np.int32, 1),
              "u": (np.float32, 1), "v": (np.float32, 1), "normal": (np.float32, 3),
              "points": (np.float32, 3), "instance_id": (np.int32, 1)}
HIT_ARRAYS = {name: np.dtype(dtype).itemsize * n for name, (dtype, n) in HIT_FIELDS.items()}
OCCLUDED_ARRAYS = {"occluded": 1}


def check_packet_size(packet_size) -> int:
    """A packet_size argument (queries per work-item) as an int of
    PACKET_SIZES, else TypeError / ValueError."""
    if isinstance(packet_size, bool) or not isinstance(packet_size, (int, np.integer)):
        raise TypeError(f"packet_size must be an int, got {type(packet_size).__name__}")
    if packet_size not in PACKET_SIZES:
        raise ValueError(f"packet_size must be one of {PACKET_SIZES}, got {packet_size!r}")
    return int(packet_size)


class RayQuery:
    """Closest-hit and any-hit queries on one device.

    On PoCL the kernels work on the numpy arrays in place (``zero_copy``);
    elsewhere device buffers for rays and results are reused between calls and
    only grow, and on Intel's CPU runtime the kernels write the results into
    their (page-aligned) arrays directly (``outputs_in_place``).  The host
    memory of results the caller has dropped is reused too (ResultPool).
    Rays go up and results come back as the numpy arrays themselves (one
    buffer per field, no packing on the host).  ``max_rays_per_launch`` caps
    the rays per kernel launch (bigger batches are split into chunks); by
    default it follows the device's memory limits.  ``packet_size`` is the
    rays each work-item traces (PACKET_SIZES; by default the runtime's kernel
    variant's): every size gives the same hits, ties aside.
    """

    def __init__(self, rt: Runtime, max_rays_per_launch: int | None = None,
                 packet_size: int | None = None):
        self.rt = rt
        self.work_group_size = work_group_size(rt)
        if packet_size is None:
            packet_size = rt.variant.packet_size  # the one its probe chose
        #: the variant traversal is compiled as (a requested packet size that
        #: the device cannot run gives way to a smaller one, with a warning)
        self.variant = rt.packet_variant(check_packet_size(packet_size))
        self.packet_size = self.variant.packet_size
        self.max_rays_per_launch = self._chunk_size(max_rays_per_launch)
        self._capacity = 0
        self._buffers: dict[str, cl.Buffer] = {}
        # int32 [0]: a traversal overflowed its stack; [1]: packets traced as
        # packets (only counted with count_packets)
        self._counters = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 8)
        self._scalars = {name: cl.Buffer(rt.context, cl.mem_flags.READ_ONLY, 4)
                         for name in ("tmin", "tmax", "mask")}
        cl.enqueue_copy(rt.queue, self._scalars["mask"], np.full(1, ALL_BITS, np.uint32))
        #: whether the kernels read the rays and write the results in the
        #: numpy arrays themselves (zero_copy); else the rays go up and the
        #: results come back through device buffers reused between calls
        self.zero_copy = zero_copy(rt)
        #: without zero_copy: whether the kernels write the results into the
        #: numpy arrays themselves when these start on a page (outputs_in_place)
        self.outputs_in_place = not self.zero_copy and outputs_in_place(rt)
        self._lock = threading.Lock()
        self._results = ResultPool()
        #: device time of the last query's kernels, milliseconds
        self.last_kernel_ms = 0.0
        #: for tests: count the work-items whose rays were traced as one packet
        #: (kernels built with COUNT_PACKETS) into last_packets
        self.count_packets = False
        self.last_packets: int | None = None

    def _chunk_size(self, requested: int | None) -> int:
        d = self.rt.device
        per_ray = sum({**RAY_ARRAYS, **HIT_ARRAYS, **OCCLUDED_ARRAYS}.values())
        fits = min(d.max_mem_alloc_size // max(RAY_ARRAYS["origins"], HIT_ARRAYS["normal"]),
                   d.global_mem_size // 4 // per_ray)  # leave room for the tree
        size = min(MAX_RAYS_PER_LAUNCH, fits)
        if requested is not None:
            if isinstance(requested, bool) or not isinstance(requested, (int, np.integer)):
                raise TypeError(f"max_rays_per_launch must be an int, got {type(requested).__name__}")
            if requested < 1:
                raise ValueError(f"max_rays_per_launch must be >= 1, got {requested}")
            size = min(size, int(requested))
        return max(1, size)

    # -- public queries ---------------------------------------------------

    def intersect(self, tree: Tree, origins, directions=None, tmin=0.0, tmax=np.inf,
                  mask=None) -> Hits:
        """Closest hit of each ray (origins[i] + t * directions[i], tmin <= t <= tmax),
        in the rays' leading shape (hlbvh_cl.core.inputs); a ray skips geometry
        whose mask shares no bit with its own (``mask``: scalar or per ray)."""
        batch = masked(inputs.rays(origins, directions, tmin, tmax), mask, tree)
        count = len(batch)
        hits = Hits(**{name: self._results.empty((count, n) if n > 1 else count, dtype)
                       for name, (dtype, n) in HIT_FIELDS.items()})
        batch, t_factor = into_frame(batch, tree)
        if count and self._check_tree(tree):
            kernel = self._kernel(tree, "intersect_closest_arrays", self.count_packets)

            def launch(n, b, steps):
                return self.rt.run(kernel, self._work_items(n, tree),
                                   *scene_args(tree, *steps["mask"]), b["origins"],
                                   b["directions"], *steps["tmin"], *steps["tmax"], b["t"],
                                   b["geom_id"], b["prim_id"], b["u"], b["v"], b["normal"],
                                   b["points"], b["instance_id"], self._counters, np.uint32(n),
                                   local_size=self.work_group_size)
            self._run(batch, launch, {name: getattr(hits, name) for name in HIT_ARRAYS})
            if t_factor is not None:  # back from the frame
                hit = np.flatnonzero(hits.prim_id >= 0)
                found = hits.t[hit]
                caller_t(found, t_factor, hit, batch)
                hits.t[hit] = found
                hits.points[:] = frame.to_frame(hits.points, 1.0 / tree.scale)
        elif count:
            hits.t[:] = np.inf
            hits.geom_id[:] = hits.prim_id[:] = hits.instance_id[:] = -1
            hits.u[:] = hits.v[:] = hits.normal[:] = 0.0
            hits.points[:] = np.nan
        return Hits(**{name: field.reshape(batch.shape + field.shape[1:])
                       for name, field in vars(hits).items()})

    def occluded(self, tree: Tree, origins, directions=None, tmin=0.0,
                 tmax=np.inf, mask=None) -> np.ndarray:
        """bool in the rays' leading shape: whether anything is hit with
        tmin <= t <= tmax (stops at the first hit); ``mask`` as intersect."""
        batch, _ = into_frame(masked(inputs.rays(origins, directions, tmin, tmax), mask, tree),
                               tree)
        count = len(batch)
        result = self._results.empty(count, np.uint8)
        if count and self._check_tree(tree):
            kernel = self._kernel(tree, "intersect_any_arrays", self.count_packets)

            def launch(n, b, steps):
                return self.rt.run(kernel, self._work_items(n, tree),
                                   *scene_args(tree, *steps["mask"]), b["origins"],
                                   b["directions"], *steps["tmin"], *steps["tmax"],
                                   b["occluded"], self._counters, np.uint32(n),
                                   local_size=self.work_group_size)
            self._run(batch, launch, {"occluded": result})
        return result.view(bool).reshape(batch.shape)  # the kernel writes 0 or 1

    # -- device-buffer entry points (the renderer's) ------------------------

    def enqueue_intersect(self, tree: Tree, rays: cl.Buffer, hits: cl.Buffer, count: int,
                          overflow: cl.Buffer, wait_for=None) -> cl.Event:
        """Enqueue intersect_closest over `count` Ray records already on the
        device; it writes `count` Hit records to `hits`.  Nothing is checked or
        read back: the rays must follow the conventions above (a ray with
        tmin > tmax hits nothing), and the caller clears the int32 `overflow`
        flag beforehand and raises if a traversal set it."""
        self._require_triangles(tree)
        kernel = self._kernel(tree, "intersect_closest")
        return self.rt.run(kernel, self._work_items(count, tree),
                           *scene_args(tree, self._scalars["mask"], 0), rays, hits, overflow,
                           np.uint32(count), wait_for=wait_for, local_size=self.work_group_size)

    def enqueue_occluded(self, tree: Tree, rays: cl.Buffer, occluded: cl.Buffer, count: int,
                         overflow: cl.Buffer, wait_for=None) -> cl.Event:
        """As enqueue_intersect, with intersect_any: occluded[i] = 1 (uchar)
        where ray i hits anything."""
        self._require_triangles(tree)
        kernel = self._kernel(tree, "intersect_any")
        return self.rt.run(kernel, self._work_items(count, tree),
                           *scene_args(tree, self._scalars["mask"], 0), rays, occluded, overflow,
                           np.uint32(count), wait_for=wait_for, local_size=self.work_group_size)

    # -- internals ----------------------------------------------------------

    def _kernel(self, tree: Tree, name: str,
                count_packets: bool = False) -> cl.Kernel:
        """The traversal kernel `name` for `tree` (an instanced one's walks
        its top tree, kernels/instance.h)."""
        defines = {"STACK_SIZE": stack_size(tree), "PACKET_SIZE": self.packet_size,
                   **self.variant.defines, **self.rt.prefetch_defines}
        if isinstance(tree, InstancedTree):
            defines["INSTANCES"] = 1
        if count_packets:
            defines["COUNT_PACKETS"] = 1
        return self.rt.kernel("query/rays.cl", name, **defines)

    def _work_items(self, rays: int, tree=None) -> int:
        """Work-items that trace `rays` rays, packet_size rays each."""
        return -(-rays // self.packet_size)

    def _require_triangles(self, tree: Tree) -> None:
        if not self._check_tree(tree):
            raise ValueError("the tree holds no triangle: there is nothing to trace rays against")

    def _check_tree(self, tree: Tree) -> bool:
        return check_tree(self.rt, tree)

    def _reserve(self, count: int) -> None:
        """Grow-only device buffers for `count` rays per launch."""
        if count <= self._capacity:
            return
        capacity = min(self.max_rays_per_launch, max(count, 2 * self._capacity))
        sizes = {**RAY_ARRAYS, **HIT_ARRAYS, **OCCLUDED_ARRAYS}
        # release the old ones before allocating, and hold none if that fails
        self._buffers, self._capacity = {}, 0
        self.rt.check_allocation("ray query buffers",
                                 {name: capacity * size for name, size in sizes.items()})
        self._buffers = {name: cl.Buffer(self.rt.context, cl.mem_flags.READ_WRITE,
                                         capacity * size) for name, size in sizes.items()}
        self._capacity = capacity

    def _run(self, batch: inputs.Rays, launch, outputs) -> None:
        """Runs ``launch(n, buffers, limits)`` over chunks of at most
        max_rays_per_launch rays; the results land in the arrays of
        ``outputs`` (in place, or read back from the device buffers)."""
        with self._lock:  # one query at a time: the buffers are shared
            try:
                self._run_locked(batch, launch, outputs)
            except BaseException:
                # Ctrl-C, or an error: the launches in flight (at most two)
                # may still write into the caller's arrays (zero copy) and the
                # shared buffers; let them end before anyone reuses those.
                self.rt.queue.finish()
                raise

    def _run_locked(self, batch: inputs.Rays, launch, outputs) -> None:
        queue, chunk = self.rt.queue, self.max_rays_per_launch
        count = len(batch)
        if not self.zero_copy:
            self._reserve(min(count, chunk))
        cl.enqueue_copy(queue, self._counters, np.zeros(2, np.int32))
        # per-ray arrays go chunk by chunk; a scalar limit is one value, step 0
        arrays = {"origins": batch.origins, "directions": batch.directions}
        limits = {}
        for name, limit in (("tmin", batch.tmin), ("tmax", batch.tmax), ("mask", batch.mask)):
            if limit.ndim:
                arrays[name] = limit
            else:
                cl.enqueue_copy(queue, self._scalars[name], np.full(1, limit, limit.dtype))
                limits[name] = self._scalars[name]
        # The queue runs in order, so each chunk's inputs wait for the last
        # chunk's results; only the final read blocks.  (pyopencl's events of
        # non-blocking copies wait when they are dropped: keep them.)
        events, transfers = [], []
        sizes, start = LaunchSizes(chunk), 0
        while start < count:
            part = slice(start, min(start + sizes.next(self.rt), count))
            start = part.stop
            if self.zero_copy:
                buffers = {name: self._wrap(array[part], cl.mem_flags.READ_ONLY)
                           for name, array in arrays.items()}
            else:
                buffers = dict(self._buffers)
                transfers += [cl.enqueue_copy(queue, buffers[name], array[part], is_blocking=False)
                              for name, array in arrays.items()]
            in_place = self.zero_copy or (self.outputs_in_place and starts_on_page(
                *(array[part] for array in outputs.values())))
            if in_place:
                buffers.update({name: self._wrap(array[part], cl.mem_flags.WRITE_ONLY)
                                for name, array in outputs.items()})
            steps = {name: (limits[name] if name in limits else buffers[name],
                            np.uint32(name in arrays)) for name in ("tmin", "tmax", "mask")}
            events.append(launch(part.stop - part.start, buffers, steps))
            sizes.launched(events[-1], part.stop - part.start)
            transfers += [collect(queue, buffers[name], array[part], in_place)
                          for name, array in outputs.items()]
        counters = np.zeros(2, np.int32)
        self.rt.wait([cl.enqueue_copy(queue, counters, self._counters, is_blocking=False)])
        self.last_kernel_ms = sum((e.profile.end - e.profile.start) * 1e-6 for e in events)
        self.last_packets = int(counters[1]) if self.count_packets else None
        if counters[0]:
            raise RuntimeError("ray traversal overflowed its stack (sized from Tree.depth): "
                               "the tree is deeper than its depth field says")

    def _wrap(self, array: np.ndarray, access) -> cl.Buffer:
        """A buffer over the array's own memory (CL_MEM_USE_HOST_PTR)."""
        return cl.Buffer(self.rt.context, access | cl.mem_flags.USE_HOST_PTR, hostbuf=array)


def collect(queue: cl.CommandQueue, buffer: cl.Buffer, array: np.ndarray,
            in_place: bool) -> cl.Event:
    """Enqueues what brings a launch's results from ``buffer`` into ``array``:
    where the kernel wrote the array itself (a USE_HOST_PTR buffer over it),
    a map of the buffer, which makes them visible without a copy; else a
    copy back.  The caller keeps the event: pyopencl's events of non-blocking
    copies wait when they are dropped."""
    if in_place:
        mapped, event = cl.enqueue_map_buffer(queue, buffer, cl.map_flags.READ, 0, array.shape,
                                              array.dtype, is_blocking=False)
        mapped.base.release(queue)
        return event
    return cl.enqueue_copy(queue, array, buffer, is_blocking=False)


def check_tree(rt: Runtime, tree: Tree) -> bool:
    """Validates a tree for a query on ``rt``; False when it holds no
    triangle (every query misses)."""
    if not isinstance(tree, (Tree, InstancedTree)):
        raise TypeError(f"tree must be a hlbvh_cl.core.tree.Tree, got {type(tree).__name__}")
    if tree.released:
        raise ValueError("this Tree was released when its Scene rebuilt")
    if tree.triangle_count == 0:
        return False
    if tree.nodes.context != rt.context:
        raise ValueError(f"tree lives on another OpenCL context than this query "
                         f"({rt.device.id}); build it with the same runtime")
    if tree.depth < 1 or tree.node_count < 1:
        raise ValueError(f"tree is malformed: depth={tree.depth}, node_count={tree.node_count}")
    return True


def scene_args(tree, masks: cl.Buffer, mask_step) -> tuple:
    """A traversal kernel's SCENE_PARAMS (traverse.cl) for ``tree``: a flat
    tree's nodes, triangles and refs (rays' masks are applied before, by
    masked); an instanced one's levels, instances and the rays' masks."""
    if isinstance(tree, InstancedTree):
        return tree.scene_args(masks, mask_step)
    return tree.nodes, tree.triangles, tree.refs


def masked(batch: inputs.Rays, mask, tree) -> inputs.Rays:
    """The rays with their masks (hlbvh_cl.core.inputs.ray_masks).  A flat tree's
    meshes all have every mask bit (a Scene with other masks is instanced),
    so there a ray sees everything unless its mask is 0: such rays get tmax
    -inf, which no box or triangle meets, and the kernels need no mask."""
    if mask is None:
        return batch
    masks = inputs.ray_masks(mask, batch.shape)
    if isinstance(tree, InstancedTree):
        return dataclasses.replace(batch, mask=masks)
    blind = masks == 0
    if not blind.any():
        return batch
    tmax = np.array(np.broadcast_to(batch.tmax, (len(batch),)), np.float32)
    tmax[np.broadcast_to(blind, (len(batch),))] = -np.inf
    return dataclasses.replace(batch, tmax=tmax)


def stack_size(tree: Tree) -> int:
    """A stack that cannot overflow: a wide node pushes at most WIDE_ARITY - 1
    children, and only those of the nodes on the path to the current one stay
    on the stack.  Sized from the tree's depth, so that a tree whose depth is
    wrong overflows (and raises) instead of being trusted in part."""
    return _round_up((layout.WIDE_ARITY - 1) * max(1, int(tree.depth)), STACK_GRANULE)


def _round_up(value: int, multiple: int) -> int:
    return (value + multiple - 1) // multiple * multiple


def into_frame(batch: inputs.Rays, tree) -> tuple[inputs.Rays, np.ndarray | None]:
    """The (checked) rays in the frame of a tree built at a scale other than 1
    (hlbvh_cl.core.frame), and the factor per ray that turns the frame's t back
    into the caller's (None when the rays go as given).  Origins take the
    tree's scale; each direction a power of two of its own that brings its
    largest component to [0.5, 1), so that no direction under- or overflows
    and t stays near the frame's size; tmin and tmax follow.  At scale 1 only
    short directions are, and only when a hit's t could pass float32's range
    (_t_may_overflow): the kernels' box and triangle tests would overflow to
    inf and miss it.  An origin that the scale takes out of
    float32 (far from a tiny scene) raises the ValueError that names it."""
    scale = getattr(tree, "scale", 1.0)
    if scale == 1.0 and not _t_may_overflow(batch):
        return batch, None
    framed = frame.to_frame(batch.origins, scale)
    finite = np.isfinite(framed).all(axis=1)
    if not finite.all():
        raise ValueError(f"{batch.name_origin(int(np.argmin(finite)))} overflows float32 once "
                         f"multiplied by {frame.describe(scale)}, the scale of this scene's "
                         "frame (hlbvh_cl/frame.py)")
    _, exponent = np.frexp(np.abs(batch.directions).max(axis=1))
    per_ray = np.ldexp(1.0, -exponent)
    if scale == 1.0:
        # only short directions are lengthened: shortening a long one would
        # lengthen the t of a far origin's hit
        np.maximum(per_ray, 1.0, out=per_ray)
        if (per_ray == 1.0).all():
            return batch, None
    directions = (batch.directions * per_ray[:, None]).astype(np.float32)
    t_factor = per_ray / scale  # the caller's t = the frame's t * t_factor
    with np.errstate(over="ignore", under="ignore"):
        tmin, tmax = ((limit / t_factor).astype(np.float32) for limit in (batch.tmin, batch.tmax))
    return dataclasses.replace(batch, origins=framed, directions=directions, tmin=tmin,
                               tmax=tmax), t_factor


#: The t that the rays of a scene at scale 1 may reach without a rescale:
#: float32's largest with room for the slab test's products.
_SAFE_T = float(np.finfo(np.float32).max) / 4


def _t_may_overflow(batch: inputs.Rays) -> bool:
    """Whether a hit of the batch in a scene at scale 1 (coordinates within
    frame.SAFE_RANGE) could lie at a t near float32's overflow: its
    distance from the origin, at most sqrt(3) (|origin|_inf + 2^24), over
    its direction's largest component."""
    reach = math.sqrt(3.0) * (batch.farthest_origin + frame.SAFE_RANGE[1])
    return reach > _SAFE_T * batch.shortest_direction


def caller_t(t: np.ndarray, t_factor: np.ndarray, rays: np.ndarray, batch: inputs.Rays) -> None:
    """t (float32, hits only) times the t_factor of its ray (rays: the ray
    of each), in place: the frame's t back in the caller's units, exactly
    (powers of two).  A t past float32's range raises the ValueError that
    names the ray's direction: a hit there has no t to give."""
    with np.errstate(over="ignore"):
        scaled = (t * t_factor[rays]).astype(np.float32)
    over = np.flatnonzero(np.isinf(scaled))
    if len(over):
        row = int(rays[over[0]])
        distance = float(t[over[0]]) * float(t_factor[row])
        raise ValueError(f"{batch.name_direction(row)} is too short for this ray's hit: it lies "
                         f"at t = {distance:.4g} direction lengths, past float32's largest "
                         "value (3.4e38); give a longer direction")
    t[...] = scaled
