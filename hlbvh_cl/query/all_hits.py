"""Every hit along each ray, and hit counts (kernels/query/all_hits.cl): two
visitors of the one walk of the wide tree.

intersect_all runs two passes over the rays.  The count pass gives each ray's
number of hits and keeps its first KEEP_HITS hit triangles; a prefix sum of
min(count, max_hits) gives each ray its segment of the output (CSR); the fill
pass then stores each ray's hits sorted by t in its segment, testing the kept
triangles again where they are all of them and walking again otherwise, so
memory stays near the output's own size whatever the counts.  Both passes
trace packets of nearby rays on flat scenes (the query's kernel variant).

The count pass runs big batches by direction class (the axis and signs that
a packet's rays share), then in fine Morton order of their origins, or of
their directions where their lines nearly meet (hlbvh_cl.query.order), so that
packets hold nearby rays, unless they come in a coherent order already or,
where the kernel interleaves the walks of rays that make no packet (CPUs),
are neither nearly parallel nor aimed at one point: those walk faster one
by one (_coherent_order).  A scene's count takes packets twice its query's
on CPUs (wide_count_packets).  The fill pass runs the rays in the caller's
order, so that its results land in order (most rays only test their kept
triangles again; in Morton order their hits would scatter).  On CPU devices
the launches of both passes read and write the whole arrays in place, the
count's by the slots of runs of its order (_placed puts big arrays that a
runtime could not use so on a page, once); on GPUs, off zero copy for
batches over INDEXED_COPY_MAX, and where a whole array would not fit one
device buffer, the rays of a run are taken on the host and go up in chunks
whose hits stay under HITS_PER_LAUNCH, through device buffers reused
between chunks, and the results are put back.

Rays given as pyopencl arrays (query/on_device.py) stay on the device, and
so do the results: both passes run over them in their own order, at
global offsets, and the segments are found there too, by a scan of the
counts (parallel/scan.py) in the count pass's wait, which reads back only
the hits' total, to size them.

A ray through an edge or a vertex shared by triangles on opposite sides
counts that crossing once (triangle.h, OWN_EDGES), so the parity of a count
tells inside from outside on a closed mesh.  Conventions otherwise as
hlbvh_cl.query.rays (tmin <= t <= tmax, no culling, t in units of |direction|).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from ..core import inputs
from ..device import probe
from ..parallel import scan
from . import on_device
from .order import (COHERENT_MIN, RAY_ORDER_BITS, concurrent_rays, device_order,
                    nearly_parallel, rays_in_order)
from ..build.instances import InstancedTree
from ..device.profile import PACKET_SIZES
from .results import on_page
from .engine import Batch, check_tree, kernel_defines, refuse_spheres
from .rays import RayQuery, caller_t, into_frame, masked, scene_args
from ..core.paths import kernel_of
from ..core.tree import Tree

KERNEL = kernel_of(__name__)

#: Hits one fill launch writes at most (one ray with more still goes alone):
#: bounds the device buffers where results are copied back.
HITS_PER_LAUNCH = 1 << 18

#: Rays per launch where the rays are copied to the device (GPUs; see
#: INDEXED_COPY_MAX): bounds those copies, 32 bytes a ray, two launches in
#: flight.
COPIED_RAYS_PER_LAUNCH = 1 << 16

#: Off zero copy, a CPU device runs a batch of up to this many rays by slots
#: into its whole arrays, which a runtime that cannot use them in place
#: copies (about 100 bytes a ray with intersect_all's kept hits); a bigger
#: one takes its rows per launch, as GPUs do, so that the copies stay
#: bounded.
INDEXED_COPY_MAX = 1 << 22

#: Hit triangles the count pass keeps per ray (kernels/query/all_hits.cl): a ray
#: with no more hits skips the fill pass's walk (which runs in the caller's
#: order, where rays seldom make packets).  A uint32 each, for every ray,
#: while the fill runs.
KEEP_HITS = 8

#: Output arrays of the fill pass: dtype per hit.
HIT_FIELDS = {"t": np.float32, "u": np.float32, "v": np.float32, "prim_id": np.int32,
              "geom_id": np.int32, "instance_id": np.int32}


@dataclass
class AllHits:
    """Every hit of R rays, H in all, as flat arrays: ray r's hits are
    [offsets[r], offsets[r + 1]), sorted by t (ties in a fixed order).  Rays
    given with leading dimensions (e.g. (H, W, 3)) are numbered in C order,
    and ``shape`` keeps those dimensions (``counts`` has them).  Rays given
    as pyopencl arrays get pyopencl arrays."""

    offsets: np.ndarray    # int64 (R + 1,)
    ray_index: np.ndarray  # int64 (H,) the ray of each hit
    t: np.ndarray          # float32 (H,)
    prim_id: np.ndarray    # int32 (H,) face index within its own mesh
    geom_id: np.ndarray    # int32 (H,) mesh index in the scene
    u: np.ndarray          # float32 (H,) hit = (1-u-v)*v0 + u*v1 + v*v2
    v: np.ndarray          # float32 (H,)
    instance_id: np.ndarray  # int32 (H,) instance hit in an instanced scene; else -1
    shape: tuple           # the rays' leading shape, prod(shape) = R

    def __len__(self) -> int:
        return len(self.t)

    @property
    def counts(self) -> np.ndarray:
        """int64, in the rays' leading shape: hits returned per ray (a
        pyopencl array where the hits are)."""
        return (self.offsets[1:] - self.offsets[:-1]).reshape(self.shape)


def check_max_hits(max_hits) -> int | None:
    if max_hits is None:
        return None
    max_hits = inputs.integer("max_hits (None for every hit)", max_hits, 1)
    # no ray has more hits than a count holds (int32): a larger k keeps them all
    return min(int(max_hits), np.iinfo(np.int32).max)


def _rays(origins, directions, tmin, tmax, mask, tree):
    """The checked rays (hlbvh_cl.core.inputs) in the tree's frame: their five
    arrays (with the masks, query.masked), the per-ray t factor back
    (query.into_frame) and the checked batch (its leading shape, the names
    of its rows).  The one place that reads the caller's ray arrays."""
    batch, t_factor = into_frame(masked(inputs.rays(origins, directions, tmin, tmax), mask,
                                          tree), tree)
    return ((batch.origins, batch.directions, batch.tmin, batch.tmax, batch.mask), t_factor,
            batch)


def wide_count_packets(query: RayQuery) -> int:
    """Rays per work-item for a scene's count pass: twice the query's packet
    on CPU devices (16 for 8) where that variant passes its probe, else the
    query's.  A count's lanes never part (no limit shrinks, no walk ends
    early), so a wider packet idles no lane while it halves the node steps
    per ray and gives each step two independent vector halves."""
    rt, wider = query.rt, 2 * query.packet_size
    if rt.profile.gpu or query.packet_size == 1 or wider not in PACKET_SIZES:
        return query.packet_size
    usable = probe.usable(rt.device, rt.profile, query.variant.with_packet(wider)) is None
    return wider if usable else query.packet_size


class AllHitsQuery:
    """count_intersections and intersect_all on one device, with a RayQuery's
    device choices (work-group size, kernel variant), its result pool and
    its launch engine (hlbvh_cl.query.engine); the count pass with
    `count_packet_size` rays per work-item (None: the query's)."""

    def __init__(self, query: RayQuery, count_packet_size: int | None = None):
        self.query = query
        self.rt = query.rt
        self.count_packet_size = count_packet_size or query.packet_size
        self.engine = query.engine
        self._lock = threading.Lock()

    # -- public queries ---------------------------------------------------

    def count(self, tree: Tree, origins, directions=None, tmin=0.0,
              tmax=np.inf, mask=None) -> np.ndarray:
        """int32, in the rays' leading shape: the number of hits of each ray
        with tmin <= t <= tmax (``mask`` as RayQuery.intersect).  Rays
        given as pyopencl arrays get a pyopencl array (query/on_device.py)."""
        refuse_spheres(tree, "count_intersections")
        on_device_rays = on_device.device_rays(self.rt, origins, directions, tmin, tmax, mask,
                                               self.query.device_pool())
        if on_device_rays is not None:
            found = self._on_device(tree, on_device_rays, self._device_counts)
            if found is None:  # from the host: its frame, and the counts back up
                found = self.query.device_pool().upload(self.count(
                    tree, *on_device_rays.host(), mask=on_device_rays.host_mask()))
            return found.reshape(on_device_rays.shape)
        rays, _, batch = _rays(origins, directions, tmin, tmax, mask, tree)
        with self._lock:
            counts = self._count(tree, self._placed(rays), self.query.results.empty)
        return counts.reshape(batch.shape)

    def intersect_all(self, tree: Tree, origins, directions=None, tmin=0.0, tmax=np.inf,
                      max_hits=None, mask=None) -> AllHits:
        """Every hit of each ray with tmin <= t <= tmax, sorted by t; with
        max_hits=k only the k nearest of each ray (``mask`` as
        RayQuery.intersect)."""
        refuse_spheres(tree, "intersect_all")
        max_hits = check_max_hits(max_hits)
        on_device_rays = on_device.device_rays(self.rt, origins, directions, tmin, tmax, mask,
                                               self.query.device_pool())
        if on_device_rays is not None:
            found = self._on_device(tree, on_device_rays, lambda tree, rays: self._all_on_device(
                tree, rays, max_hits))
            if found is None:  # from the host: its frame, and the hits back up
                host = self.intersect_all(tree, *on_device_rays.host(), max_hits=max_hits,
                                          mask=on_device_rays.host_mask())
                found = AllHits(**{name: self.query.device_pool().upload(value)
                                   for name, value in vars(host).items() if name != "shape"},
                                shape=host.shape)
            return found
        rays, t_factor, batch = _rays(origins, directions, tmin, tmax, mask, tree)
        pool = self.query.results
        with self._lock:
            rays = self._placed(rays)
            # each ray's count, and on flat scenes its first hits, which spare
            # most rays the fill pass's walk: from the pool, as the kernels
            # use them in place (_placed)
            counts, known = self._count(tree, rays, pool.empty, keep=True)
            kept = counts if max_hits is None else np.minimum(counts, max_hits)
            offsets = pool.empty(len(kept) + 1, np.int64)
            offsets[0] = 0
            np.cumsum(kept, out=offsets[1:])
            del kept  # before the output is allocated: peak memory
            total = int(offsets[-1])
            fields = {name: pool.empty(total, dtype) for name, dtype in HIT_FIELDS.items()}
            ray_index = pool.empty(total, np.int64)
            if total:
                self._fill(tree, rays, offsets, (counts, known),
                           {**fields, "ray_index": ray_index}, t_factor, batch)
        return AllHits(offsets=offsets, ray_index=ray_index, **fields, shape=batch.shape)

    # -- internals ----------------------------------------------------------

    def kernel(self, tree: Tree, name: str, keep: bool = True,
                packet: int | None = None) -> tuple[cl.Kernel, int]:
        """all_hits.cl's kernel `name` for `tree`, and its rays per
        work-item: on flat trees `packet` (None: the query's variant's), one
        ray on instanced ones.  Without `keep` a count keeps no hit
        (KEEP_HITS 0)."""
        packet = 1 if isinstance(tree, InstancedTree) else packet or self.query.packet_size
        defines = kernel_defines(self.rt, tree, self.query.variant, packet,
                                 KEEP_HITS=KEEP_HITS if keep else 0)
        return self.rt.kernel(KERNEL, name, **defines), packet

    def _count(self, tree, rays, empty, keep=False):
        """int32 counts of the rays, from `empty`; with `keep`, (counts,
        known): on flat scenes also each ray's first KEEP_HITS hit
        triangles, uint32 (rays, KEEP_HITS) (the fill pass tests them again
        instead of walking), else None.  Big batches run in class and
        Morton order (_launches)."""
        count = len(rays[0])
        outputs = {"counts": empty(count, np.int32)}
        if keep and not isinstance(tree, InstancedTree):
            outputs["known"] = empty((count, KEEP_HITS), np.uint32)
        results = (outputs["counts"], outputs.get("known")) if keep else outputs["counts"]
        if not (count and check_tree(self.rt, tree)):
            outputs["counts"][:] = 0
            return results
        launch, packet = self._count_launch(tree, "known" in outputs)
        interleaved = "INTERLEAVED_WALKS" in kernel_defines(self.rt, tree, self.query.variant,
                                                           packet)
        self._launches(rays, _coherent_order(self.query, rays, interleaved), None, {}, outputs,
                       launch)
        return results

    def _count_launch(self, tree, keep: bool):
        """The count pass's launch (the engine's ``launch``), writing the
        outputs "counts" and, with ``keep``, "known"; and its rays per
        work-item."""
        kernel, packet = self.kernel(tree, "count_hits_arrays", keep, self.count_packet_size)

        def launch(n, run):
            # not keeping: the kernel writes no known triangle (a stand-in buffer)
            tail = [run.buffers["known"], np.uint32(1)] if keep else \
                [self.engine.unused, np.uint32(0)]
            return self._launch(kernel, packet, tree, n, run, [], [run.buffers["counts"], *tail])
        return launch, packet

    def _placed(self, rays: tuple) -> tuple:
        """The rays' arrays (_rays's) on pages (results.on_page) where the
        kernels would use them in place off zero copy (whole_arrays): one copy
        serves the order's buffers and each pass's."""
        if self.engine.zero_copy or not whole_arrays(self.query, len(rays[0])):
            return rays
        return tuple(on_page(self.query.results, array) for array in rays)

    def _fill(self, tree, rays, offsets, known, outputs, t_factor, batch) -> None:
        """The hits into `outputs` (HIT_FIELDS and ray_index), ray r's in
        [offsets[r], offsets[r + 1]); `known`: _count's (counts, known);
        t_factor and batch: _rays's (t back in the caller's units).
        The rays go in their own order: most only have their known triangles
        tested again, and the results then land in order."""
        counts, triangles = known
        inputs = {} if triangles is None else {"counts": counts, "known": triangles}
        launch, _ = self._fill_launch(tree, bool(inputs), outputs)
        self._launches(rays, None, offsets, inputs, outputs, launch)
        if t_factor is not None:  # back from the frame
            t, ray_index = outputs["t"], outputs["ray_index"]
            step = self.query.max_rays_per_launch
            for start in range(0, len(t_factor), step):
                stop = min(start + step, len(t_factor))
                part = slice(int(offsets[start]), int(offsets[stop]))
                caller_t(t[part], t_factor, ray_index[part], batch)

    def _fill_launch(self, tree, known: bool, outputs: dict):
        """The fill pass's launch, writing ``outputs`` (HIT_FIELDS and
        ray_index) into the segments of the engine's Launch.segments; with
        ``known``, the count pass's "counts" and "known" triangles are
        inputs; and its rays per work-item."""
        kernel, packet = self.kernel(tree, "fill_hits_arrays")

        def launch(n, run):
            b = run.buffers
            given = [b["counts"], b["known"], np.uint32(1)] if known else \
                [self.engine.unused, self.engine.unused, np.uint32(0)]
            return self._launch(kernel, packet, tree, n, run, [*run.segments, *given],
                                [b[name] for name in outputs])
        return launch, packet

    def _launch(self, kernel, packet, tree, n, run, inputs, outputs) -> cl.Event:
        """One launch of a pass: the scene (scene_args, with the rays'
        masks), the rays (RAY_PARAMS in kernels/query/all_hits.cl), then the
        pass's inputs and outputs, the counters and the ray count; over the
        rays [first, first + n) where the engine gives a range (a global
        offset of whole packets: Launch.first)."""
        b, steps = run.buffers, run.steps
        return self.rt.run(kernel, -(-n // packet), *scene_args(tree, *steps["mask"]),
                           b["origins"], b["directions"], *steps["tmin"], *steps["tmax"],
                           run.slots, run.indexed, *inputs, *outputs, self.engine.counters,
                           np.uint32(run.first + n), local_size=self.query.work_group_size,
                           offset=run.first // packet)

    # -- rays on the device (query/on_device.py) ---------------------------

    def _on_device(self, tree, rays: on_device.DeviceRays, run):
        """``run(tree, rays)``'s result for rays on the device, under the
        query's lock; no rays or no triangles make no hits; None where the
        rays go from the host instead (a tree in a scaled frame, or a ray
        whose hit may lie past float32's range), as RayQuery's do."""
        with self._lock:
            if len(rays) and check_tree(self.rt, tree):
                return None if getattr(tree, "scale", 1.0) != 1.0 else run(tree, rays)
            return run(None, rays)

    def _device_counts(self, tree, rays: on_device.DeviceRays):
        """count of rays on the device (``tree`` None: no hits); None where
        they go from the host instead (_on_device)."""
        if tree is None:
            counts = self.query.device_pool().empty(len(rays), np.int32)
            on_device.fill(counts, 0)
            return counts
        found = self._count_on_device(tree, rays, self.query.walk_limits(tree, rays))
        return None if found is None else found[0]

    def _count_on_device(self, tree, rays: on_device.DeviceRays, stepped: dict,
                         keep: bool = False, then=None):
        """The count pass over rays on the device, checked there: counts
        (int32 (R,)) and, with ``keep`` on a flat scene, known triangles
        (uint32 (R, KEEP_HITS), else None), pyopencl arrays, and the
        counters; ``stepped``: the query's walk_limits; ``then(counts)``
        (Batch.then) follows the launches.  None where the rays go from
        the host instead (_on_device)."""
        pool = self.query.device_pool()
        counts = pool.empty(len(rays), np.int32)
        known = pool.empty((len(rays), KEEP_HITS), np.uint32) \
            if keep and not isinstance(tree, InstancedTree) else None
        outputs = {"counts": counts, **({} if known is None else {"known": known})}
        launch, packet = self._count_launch(tree, known is not None)
        counters = self.engine.run(self.query.device_batch(
            tree, rays, {}, outputs, stepped, check=True, granule=packet, key="count",
            then=None if then is None else lambda: then(counts)), launch)
        return None if self.query.checked(rays, counters) else (counts, known, counters)

    def _all_on_device(self, tree, rays: on_device.DeviceRays, max_hits) -> AllHits | None:
        """intersect_all of rays on the device, all of it there: the count
        pass, then (before its one wait) each ray's kept hits scanned into
        its segment's offset and the total read, which sizes the hits; then
        the fill pass into them, with its own wait.  ``tree`` None: no hits.
        None where the rays go from the host instead (_on_device)."""
        pool, count = self.query.device_pool(), len(rays)
        if count >= scan.MAX_COUNT:
            raise ValueError(f"{count} rays in one intersect_all call of rays on the device: "
                             f"at most {scan.MAX_COUNT - 1} (the device scan's limit)")
        offsets = pool.empty(count + 1, np.int64)
        total = np.zeros(1, np.int64)
        known = None
        if tree is None:
            on_device.fill(offsets, 0)
        else:
            limit = np.uint32(np.iinfo(np.int32).max if max_hits is None else max_hits)

            def segments(counts):
                scanned = self.engine.reserve({"scanned": 4 * (count + 1)})["scanned"]
                on_device.hit_offsets(self.rt, counts, limit, scanned, offsets,
                                      self.engine.counters)
                return [cl.enqueue_copy(self.rt.queue, total, offsets.data,
                                        src_offset=8 * count, is_blocking=False)]
            stepped = self.query.walk_limits(tree, rays)
            found = self._count_on_device(tree, rays, stepped, keep=True, then=segments)
            if found is None:
                return None
            counts, known, counters = found
            if counters[1]:  # hit_offsets's: the uint32 scan wrapped
                raise ValueError("intersect_all: more than 2**32 - 1 hits in one call of rays "
                                 "on the device; split the batch, or give max_hits")
        fields = {name: pool.empty(int(total[0]), dtype) for name, dtype in HIT_FIELDS.items()}
        outputs = {**fields, "ray_index": pool.empty(int(total[0]), np.int64)}
        if total[0]:
            inputs = {} if known is None else {"counts": counts, "known": known}
            launch, packet = self._fill_launch(tree, bool(inputs), outputs)
            _check_fill(self.engine.run(self.query.device_batch(
                tree, rays, inputs, outputs, stepped, check=False, segments=offsets,
                granule=packet, key="fill"), launch))
        return AllHits(offsets=offsets, **outputs, shape=rays.shape)

    def _launches(self, rays, order, offsets, inputs, outputs, launch) -> None:
        """A pass over the rays (the engine's launches), in `order` (None: as
        given), with each ray's `inputs` rows, writing `outputs` (a row per
        ray, or with `offsets` ray r's segment [offsets[r], offsets[r + 1])).

        Where whole_arrays holds (CPU devices) and the device allows a buffer of
        each whole array, each launch reads and writes the whole arrays in
        place by its rays' slots (the runtime's own copy at most, which
        _placed spares it); elsewhere (GPUs, big batches off zero copy,
        arrays too big for one buffer) each launch's rays go up and its
        results come back, in chunks of at most COPIED_RAYS_PER_LAUNCH rays
        and HITS_PER_LAUNCH hits, so that a device holds one chunk's
        copy, not the whole arrays'."""
        origins, directions, tmin, tmax, mask = rays
        arrays = [array for array in [*rays, *inputs.values(), *outputs.values()]
                  if array.ndim]
        whole = whole_arrays(self.query, len(origins)) and self.rt.fits_one_buffer(*arrays)
        counters = self.engine.run(Batch(
            len(origins), {"origins": origins, "directions": directions, **inputs}, outputs,
            stepped={"tmin": tmin, "tmax": tmax, "mask": mask}, order=order, whole=whole,
            segments=offsets, max_rows=None if whole else HITS_PER_LAUNCH,
            most=None if whole else min(self.query.max_rays_per_launch,
                                        COPIED_RAYS_PER_LAUNCH),
            key="count" if offsets is None else "fill"), launch)
        _check_fill(counters)


def _check_fill(counters: np.ndarray) -> None:
    """After a pass: counters[1], which only the fill pass sets, means it
    found fewer hits than the count pass."""
    if counters[1]:
        raise RuntimeError("hlbvh_cl internal error: intersect_all's fill pass found fewer "
                           "hits than its count pass")


def whole_arrays(query: RayQuery, count: int) -> bool:
    """Whether launches over `count` rays read and write the whole arrays in
    place by slots (_launches): on CPU devices, off zero copy only up to
    INDEXED_COPY_MAX rays (a runtime that copies a host pointer it cannot
    use copies the whole arrays)."""
    return not query.rt.profile.gpu and (query.zero_copy or count <= INDEXED_COPY_MAX)


def _coherent_order(query: RayQuery, rays, interleaved: bool) -> np.ndarray | None:
    """Big batches' rays by class, then in fine Morton order of their
    origins, or of their directions where their lines nearly meet at one
    point (hlbvh_cl.query.order: rays a packet can trace together, close enough
    to share their nodes), as uint32 slots found on the query's device;
    None: as given.  As given too where they come in a coherent order
    already (rays_in_order), and, where the kernel walks rays that make no
    packet `interleaved` (walk.h's walks), where sorting would not make
    packets of them: rays neither nearly parallel nor aimed at one point
    (measured faster as given than sorted into packets; figures in the
    commit that brought this)."""
    origins, directions = rays[:2]
    if len(origins) < COHERENT_MIN or rays_in_order(origins, directions):
        return None
    by_direction = concurrent_rays(origins, directions)
    if interleaved and not (by_direction or nearly_parallel(directions)):
        return None
    # read in place where the launches read them so (whole_arrays)
    return device_order(query.rt, origins, RAY_ORDER_BITS, whole_arrays(query, len(origins)),
                        directions=directions, by_direction=by_direction)
