"""Ray queries on a finished Tree: closest hit and any hit, as a stack-based
walk of its 8-wide nodes (kernels/query/rays.cl; Wald, Benthin & Boulos 2008,
and the watertight ray-triangle test of Woop, Benthin & Wald 2013), one ray or one small
packet of rays per work-item.  A query never builds or changes the tree.

Conventions, shared with tests/support/oracle.py:
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
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from ..core import frame
from ..core import inputs
from . import on_device
from ..device.runtime import Runtime
from ..device.profile import PACKET_SIZES
from .engine import (Batch, Engine, check_tree, engine_setting, interleaved_walks,
                     kernel_defines, stack_size, work_group_size)
from .results import ResultPool
from ..core.inputs import ALL_BITS
from ..build.instances import InstancedTree
from ..core.paths import kernel_of
from ..core.tree import Tree

KERNEL = kernel_of(__name__)


#: Rays per kernel launch at most: enough to fill any device, few enough that
#: a launch ends soon, so that Ctrl-C (which waits for the launches in
#: flight, at most two) is answered within a second.
MAX_RAYS_PER_LAUNCH = 1 << 20


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
        """bool, of t's shape: which rays hit something (a pyopencl array where the
        hits are)."""
        hit = self.geom_id >= 0
        return hit if isinstance(hit, np.ndarray) else hit.view(bool)  # int8 0 or 1


#: Device buffers of the numpy-facing queries, bytes per ray: the inputs, then
#: one buffer per field of the results (kernels/query/rays.cl's *_arrays kernels).
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
    packet_size = inputs.integer("packet_size", packet_size)
    if packet_size not in PACKET_SIZES:
        raise ValueError(f"packet_size must be one of {PACKET_SIZES}, got {packet_size!r}")
    return int(packet_size)


class RayQuery:
    """Closest-hit and any-hit queries on one device, through the launch
    engine (hlbvh_cl.query.engine: zero copy on PoCL, device buffers reused
    between calls elsewhere, results written in place on Intel's CPU
    runtime, pinned staging buffers on request).  The host memory of results
    the caller has dropped is reused too (ResultPool).  Rays go up and
    results come back as the numpy arrays themselves (one buffer per field,
    no packing on the host).
    ``max_rays_per_launch`` caps the rays per kernel launch (bigger batches
    are split into chunks); by default it follows the device's memory
    limits.  ``packet_size`` is the rays each work-item traces
    (PACKET_SIZES; by default the runtime's kernel variant's): every size
    gives the same hits (of hits at one t, the triangle first in the tree).
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
        #: the launches of the numpy-facing queries (hlbvh_cl.query.engine)
        self.engine = Engine(rt, self._chunk_size(max_rays_per_launch))
        #: the host memory of results, lent and recycled (results.ResultPool)
        self.results = ResultPool()
        # the renderer's device-buffer entry points: every ray sees all (mask)
        self._all_bits = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY, 4)
        #: the device memory of results of rays given on the device (made
        #: on the first such call)
        self._device_results: on_device.ResultArrays | None = None
        cl.enqueue_copy(rt.queue, self._all_bits, np.full(1, ALL_BITS, np.uint32))
        #: for tests: count the work-items whose rays were traced as one packet
        #: (kernels built with COUNT_PACKETS) into last_packets
        self.count_packets = False
        self.last_packets: int | None = None

    zero_copy = engine_setting(
        "zero_copy", "Whether the kernels use the callers' arrays in place (the engine's "
        "choice for the device; settable, for tests of each path).")
    outputs_in_place = engine_setting(
        "outputs_in_place", "Off zero copy: whether results that start on a page are written "
        "in place (the engine's choice; settable, for tests of each path).")
    staging = engine_setting(
        "staging", "Off zero copy: whether rays and results travel through pinned staging "
        "buffers, their copies overlapping the kernels (off by default on every device: "
        "hlbvh_cl.query.engine.staging says why; settable).")
    max_rays_per_launch = engine_setting("most", "Rays per kernel launch at most.")

    @property
    def last_kernel_ms(self) -> float:
        """Device time of the last query's kernels, milliseconds."""
        return self.engine.last_kernel_ms

    def _chunk_size(self, requested: int | None) -> int:
        d = self.rt.device
        per_ray = sum({**RAY_ARRAYS, **HIT_ARRAYS, **OCCLUDED_ARRAYS}.values())
        fits = min(d.max_mem_alloc_size // max(RAY_ARRAYS["origins"], HIT_ARRAYS["normal"]),
                   d.global_mem_size // 4 // per_ray)  # leave room for the tree
        size = min(MAX_RAYS_PER_LAUNCH, fits)
        if requested is not None:
            size = min(size, inputs.integer("max_rays_per_launch", requested, 1))
        return max(1, size)

    # -- public queries ---------------------------------------------------

    def intersect(self, tree: Tree, origins, directions=None, tmin=0.0, tmax=np.inf,
                  mask=None) -> Hits:
        """Closest hit of each ray (origins[i] + t * directions[i], tmin <= t <= tmax),
        in the rays' leading shape (hlbvh_cl.core.inputs); a ray skips geometry
        whose mask shares no bit with its own (``mask``: scalar or per ray).
        Rays given as pyopencl arrays get a Hits of pyopencl arrays
        (query/on_device.py)."""
        rays = on_device.device_rays(self.rt, origins, directions, tmin, tmax, mask,
                                     self.device_pool())
        if rays is not None:
            return self._on_device(tree, rays, self.intersect, {
                name: ((n,) if n > 1 else (), dtype) for name, (dtype, n) in HIT_FIELDS.items()},
                lambda found: Hits(**found))
        batch = masked(inputs.rays(origins, directions, tmin, tmax), mask, tree)
        count = len(batch)
        hits = Hits(**{name: self.results.empty((count, n) if n > 1 else count, dtype)
                       for name, (dtype, n) in HIT_FIELDS.items()})
        batch, t_factor = into_frame(batch, tree)
        if count and check_tree(self.rt, tree):
            self._run(tree, batch, self._closest(tree), {name: getattr(hits, name)
                                                   for name in HIT_ARRAYS}, "closest")
            if t_factor is not None:  # back from the frame
                hit = np.flatnonzero(hits.prim_id >= 0)
                found = hits.t[hit]
                caller_t(found, t_factor, hit, batch)
                hits.t[hit] = found
                hits.points[:] = frame.to_frame(hits.points, 1.0 / tree.scale)
        elif count:
            missed(hits)
        return Hits(**{name: field.reshape(batch.shape + field.shape[1:])
                       for name, field in vars(hits).items()})

    def occluded(self, tree: Tree, origins, directions=None, tmin=0.0,
                 tmax=np.inf, mask=None) -> np.ndarray:
        """bool in the rays' leading shape: whether anything is hit with
        tmin <= t <= tmax (stops at the first hit); ``mask`` as intersect.
        Rays given as pyopencl arrays get a pyopencl array."""
        rays = on_device.device_rays(self.rt, origins, directions, tmin, tmax, mask,
                                     self.device_pool())
        if rays is not None:
            return self._on_device(tree, rays, self.occluded, {"occluded": ((), np.uint8)},
                                   lambda found: found["occluded"], viewed=bool)
        batch, _ = into_frame(masked(inputs.rays(origins, directions, tmin, tmax), mask, tree),
                              tree)
        count = len(batch)
        result = self.results.empty(count, np.uint8)
        if count and check_tree(self.rt, tree):
            self._run(tree, batch, self._any(tree), {"occluded": result}, "any")
        return result.view(bool).reshape(batch.shape)  # the kernel writes 0 or 1

    def _closest(self, tree):
        """The launch (Batch's ``launch``) of intersect_closest_arrays: over
        the rays [first, first + n) of its arrays (a global offset of whole
        packets; Launch.first)."""
        kernel = self._kernel(tree, "intersect_closest_arrays", self.count_packets)

        def launch(n, run):
            b, steps = run.buffers, run.steps
            return self.rt.run(kernel, self._work_items(tree, n),
                               *scene_args(tree, *steps["mask"]), b["origins"],
                               b["directions"], *steps["tmin"], *steps["tmax"], b["t"],
                               b["geom_id"], b["prim_id"], b["u"], b["v"], b["normal"],
                               b["points"], b["instance_id"], self.engine.counters,
                               np.uint32(run.first + n), local_size=self.work_group_size,
                               offset=run.first // self.rays_per_item(tree))
        return launch

    def _any(self, tree):
        """The launch of intersect_any_arrays."""
        kernel = self._kernel(tree, "intersect_any_arrays", self.count_packets)

        def launch(n, run):
            b, steps = run.buffers, run.steps
            return self.rt.run(kernel, self._work_items(tree, n),
                               *scene_args(tree, *steps["mask"]), b["origins"],
                               b["directions"], *steps["tmin"], *steps["tmax"],
                               b["occluded"], self.engine.counters,
                               np.uint32(run.first + n), local_size=self.work_group_size,
                               offset=run.first // self.rays_per_item(tree))
        return launch

    def _on_device(self, tree, rays: on_device.DeviceRays, query, fields: dict, make,
                   viewed=None):
        """A query (intersect or occluded) of rays on the device: the
        results, by ``fields`` (name: (trailing shape, dtype)), as pyopencl
        arrays, viewed as ``viewed`` where given, made into the query's
        result by ``make``; traced from the host where the tree's frame or a
        ray's reach asks for it (query/on_device.py)."""
        pool, count = self.device_pool(), len(rays)
        found = {name: pool.empty((count, *trailing), dtype)
                 for name, (trailing, dtype) in fields.items()}
        fallback = False
        if count and check_tree(self.rt, tree):
            fallback = getattr(tree, "scale", 1.0) != 1.0
            if not fallback:
                launch = (self._closest if "t" in fields else self._any)(tree)
                fallback = self._run_on_device(tree, rays, launch, found)
        elif count:
            missed(found)
        if fallback:  # from the host: its frame, and the results back up
            result = query(tree, *rays.host(), mask=rays.host_mask())
            host = vars(result) if "t" in fields else {"occluded": result.view(np.uint8)}
            found = {name: pool.upload(host[name].reshape(count, *fields[name][0]))
                     for name in fields}
        # viewed before shaped: pyopencl views no 0-d array (one ray has shape ())
        return make({name: shaped(array if viewed is None else array.view(viewed),
                                  (*rays.shape, *fields[name][0]))
                     for name, array in found.items()})

    def _run_on_device(self, tree, rays: on_device.DeviceRays, launch, outputs: dict) -> bool:
        """The launches over rays on the device, checked there; raises for
        a ray that fails the checks; True where a ray's hit may lie past
        float32's range (the caller traces from the host instead)."""
        counters = self.engine.run(self.device_batch(
            tree, rays, {}, outputs, self.walk_limits(tree, rays), check=True,
            granule=self.rays_per_item(tree), key="closest" if "t" in outputs else "any"),
            launch)
        self.last_packets = int(counters[1]) if self.count_packets else None
        return self.checked(rays, counters)

    def device_pool(self) -> on_device.ResultArrays:
        """The device memory of the results of rays given on the device
        (made on the first such call)."""
        if self._device_results is None:
            self._device_results = on_device.ResultArrays(self.rt.queue)
        return self._device_results

    def walk_limits(self, tree, rays: on_device.DeviceRays) -> dict:
        """The stepped values of walks of rays on the device over ``tree``
        (on_device.walk_limits)."""
        return on_device.walk_limits(rays, not isinstance(tree, InstancedTree),
                                     self.device_pool())

    def device_batch(self, tree, rays: on_device.DeviceRays, inputs: dict, outputs: dict,
                     stepped: dict, check: bool, **fields) -> Batch:
        """The engine's batch over rays on the device: their arrays and
        ``inputs`` read, ``outputs`` written, in place, each launch a range
        of them at a global offset (Batch.slots False); with ``check`` the
        rays are checked first (on_device.check_rays)."""
        return Batch(len(rays), {"origins": rays.origins, "directions": rays.directions,
                                 **inputs}, outputs, stepped=stepped, whole=True, slots=False,
                     check=on_device.checker(self.rt, rays, self.engine.counters) if check
                     else None, **fields)

    @staticmethod
    def checked(rays: on_device.DeviceRays, counters: np.ndarray) -> bool:
        """After a checked batch: raises for a ray that failed the checks,
        named as the numpy queries name it; True where a ray's hit may lie
        past float32's range (the caller traces from the host instead)."""
        if counters[2]:
            on_device.raise_for_bad_ray(rays)
        return bool(counters[3])

    # -- device-buffer entry points (the renderer's) ------------------------

    def enqueue_intersect(self, tree: Tree, rays: cl.Buffer, hits: cl.Buffer, count: int,
                          overflow: cl.Buffer, wait_for=None,
                          instances: cl.Buffer | None = None,
                          counted: tuple[cl.Buffer, int] | None = None) -> cl.Event:
        """Enqueue intersect_closest over `count` Ray records already on the
        device; it writes `count` Hit records to `hits`, and with `instances`
        each hit's instance (int32, -1: none).  With ``counted`` = (buffer,
        k), only the first min(count, buffer[k]) rays (uint32 k of a buffer
        the device fills before the launch runs), and only their records are
        written.  Nothing is checked or read back: the rays must follow the
        conventions above (a ray with tmin > tmax hits nothing), and the
        caller clears the int32 `overflow` flag beforehand and raises if a
        traversal set it."""
        self._require_triangles(tree)
        kernel = self._kernel(tree, "intersect_closest")
        return self.rt.run(kernel, self._work_items(tree, count),
                           *scene_args(tree, self._all_bits, 0), rays, hits, instances,
                           overflow, np.uint32(count), *counted_args(counted),
                           wait_for=wait_for, local_size=self.work_group_size)

    def enqueue_occluded(self, tree: Tree, rays: cl.Buffer, occluded: cl.Buffer, count: int,
                         overflow: cl.Buffer, wait_for=None,
                         counted: tuple[cl.Buffer, int] | None = None) -> cl.Event:
        """As enqueue_intersect, with intersect_any: occluded[i] = 1 (uchar)
        where ray i hits anything."""
        self._require_triangles(tree)
        kernel = self._kernel(tree, "intersect_any")
        return self.rt.run(kernel, self._work_items(tree, count),
                           *scene_args(tree, self._all_bits, 0), rays, occluded, overflow,
                           np.uint32(count), *counted_args(counted), wait_for=wait_for,
                           local_size=self.work_group_size)

    # -- internals ----------------------------------------------------------

    def _kernel(self, tree: Tree, name: str, count_packets: bool = False) -> cl.Kernel:
        """The traversal kernel `name` for `tree` (an instanced one's walks
        its top tree, kernels/query/rays/instance.h)."""
        extra = {"COUNT_PACKETS": 1} if count_packets else {}
        groups = lane_groups(self.rt, tree, self.packet_size)
        if groups > 1:
            extra["LANE_GROUPS"] = groups
        return self.rt.kernel(KERNEL, name, **kernel_defines(self.rt, tree, self.variant,
                                                              self.packet_size, **extra))

    def rays_per_item(self, tree) -> int:
        """The rays a work-item of query/rays.cl traces over ``tree``: its
        lane_groups of packet_size."""
        return lane_groups(self.rt, tree, self.packet_size) * self.packet_size

    def _work_items(self, tree, rays: int) -> int:
        """Work-items that trace `rays` rays over ``tree``."""
        return -(-rays // self.rays_per_item(tree))

    def _require_triangles(self, tree: Tree) -> None:
        if not check_tree(self.rt, tree):
            raise ValueError("the tree holds no triangle: there is nothing to trace rays against")

    def _run(self, tree, batch: inputs.Rays, launch, outputs: dict, key: str) -> None:
        """The launches over the rays (the engine's chunks), the results
        into the arrays of ``outputs``; ``key`` paces them (Batch.key).
        Launches take whole work-items' rays (granule), so that a packet is
        the caller's consecutive rays however the pacing cuts the batch."""
        counters = self.engine.run(Batch(
            len(batch), {"origins": batch.origins, "directions": batch.directions}, outputs,
            stepped={"tmin": batch.tmin, "tmax": batch.tmax, "mask": batch.mask}, key=key,
            granule=self.rays_per_item(tree)), launch)
        self.last_packets = int(counters[1]) if self.count_packets else None


def lane_groups(rt: Runtime, tree, packet: int) -> int:
    """Groups of ``packet`` rays a work-item of query/rays.cl traces over
    ``tree`` (its LANE_GROUPS): two on a flat scene whose walks go
    interleaved (interleaved_walks) with room for both groups' stacks, their
    walks then interleaved together; else one."""
    if packet == 1 or isinstance(tree, InstancedTree):
        return 1
    return 2 if interleaved_walks(rt, tree, stack_size(tree), 2 * packet) else 1


def counted_args(counted: tuple[cl.Buffer, int] | None) -> tuple:
    """The kernels' (counts, count_at) for enqueue_intersect's ``counted``:
    a null buffer for none."""
    if counted is None:
        return None, np.uint32(0)
    buffer, at = counted
    return buffer, np.uint32(at)


def missed(hits) -> None:
    """Every field of Hits (or of a dict of its fields, numpy's or
    pyopencl's) set as a miss has it."""
    fields = hits if isinstance(hits, dict) else vars(hits)
    for name, value in {"t": np.inf, "geom_id": -1, "prim_id": -1, "instance_id": -1,
                        "u": 0.0, "v": 0.0, "normal": 0.0, "points": np.nan,
                        "occluded": 0}.items():
        if name in fields:
            on_device.fill(fields[name], value)


def scene_args(tree, masks: cl.Buffer, mask_step) -> tuple:
    """A traversal kernel's SCENE_PARAMS (query/rays.cl) for ``tree``: a flat
    tree's nodes, triangles and refs, and spheres if it has them (rays' masks are applied before, by
    masked); an instanced one's levels, instances and the rays' masks."""
    if isinstance(tree, InstancedTree):
        return tree.scene_args(masks, mask_step)
    if tree.spheres is not None:  # and its spheres (kernels/query/rays/sphere.h)
        return (tree.nodes, tree.triangles, tree.refs, tree.spheres,
                np.uint32(tree.sphere_count), np.int32(tree.sphere_geom))
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


def into_frame(batch: inputs.Rays, tree) -> tuple[inputs.Rays, np.ndarray | None]:
    """The (checked) rays in the frame of a tree built at a scale other than 1
    (hlbvh_cl.core.frame), and the factor per ray that turns the frame's t back
    into the caller's (None when the rays go as given).  Origins take the
    tree's scale; each direction a power of two of its own that brings its
    largest component to [0.5, 1), so that no direction under- or overflows
    and t stays near the frame's size; tmin and tmax follow.  At scale 1 only
    short directions are, and only when a hit's t could pass float32's range
    (_t_may_overflow): the kernels' box and triangle tests would overflow to
    inf and miss it.  A far origin's direction grows further, by a power of
    two, where its hit could lie past float32's t all the same (the caller's
    t then raises, caller_t).  An origin that the scale takes out of
    float32 (far from a tiny scene) raises the ValueError that names it."""
    scale = getattr(tree, "scale", 1.0)
    if scale == 1.0 and not _t_may_overflow(batch):
        return batch, None
    framed = frame.to_frame(batch.origins, scale)
    finite = np.isfinite(framed).all(axis=1)
    if not finite.all():
        raise ValueError(f"{batch.name_origin(int(np.argmin(finite)))} overflows float32 once "
                         f"multiplied by {frame.describe(scale)}, the scale of this scene's "
                         "frame (hlbvh_cl/core/frame.py)")
    largest = np.abs(batch.directions).max(axis=1).astype(np.float64)
    _, exponent = np.frexp(largest)
    per_ray = np.ldexp(1.0, -exponent)
    if scale == 1.0:
        # only short directions are lengthened: shortening a long one would
        # lengthen the t of a far origin's hit
        np.maximum(per_ray, 1.0, out=per_ray)
    # a far origin's hit may lie past float32's t even along a direction of
    # about unit length: such directions grow by a further power of two, up
    # to where _t_may_overflow's bound, in the frame, holds
    reach = math.sqrt(3.0) * (np.abs(framed).max(axis=1).astype(np.float64)
                              + frame.SAFE_RANGE[1])
    ratio = reach / (_SAFE_T * largest * per_ray)
    far = ratio > 1.0
    if far.any():
        _, more = np.frexp(ratio[far])  # 2^more >= ratio
        per_ray[far] *= np.ldexp(1.0, more)
    if scale == 1.0 and (per_ray == 1.0).all():
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


def shaped(array, shape: tuple):
    """``array`` with ``shape``: itself where it has it already (a
    pyopencl array's reshape makes a new one even then, at a cost a
    small call notices)."""
    return array if array.shape == shape else array.reshape(shape)
