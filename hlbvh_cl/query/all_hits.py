"""Every hit along each ray, and hit counts (kernels/all_hits.cl): two
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
packets hold nearby rays; a scene's count takes packets twice its query's
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
from .order import (COHERENT_MIN, RAY_ORDER_BITS, concurrent_rays, device_order, put_rows,
                    take_rows)
from ..build.instances import InstancedTree
from ..device.profile import PACKET_SIZES
from .results import on_page
from .rays import (LaunchSizes, RayQuery, into_frame, masked, stack_size, caller_t, collect,
                    scene_args)
from ..core.tree import Tree

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

#: Hit triangles the count pass keeps per ray (kernels/all_hits.cl): a ray
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
    and ``shape`` keeps those dimensions (``counts`` has them)."""

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
        """int64, in the rays' leading shape: hits returned per ray."""
        return np.diff(self.offsets).reshape(self.shape)


def check_max_hits(max_hits) -> int | None:
    if max_hits is None:
        return None
    if isinstance(max_hits, bool) or not isinstance(max_hits, (int, np.integer)):
        raise TypeError(f"max_hits must be an int or None, got {type(max_hits).__name__}")
    if max_hits < 1:
        raise ValueError(f"max_hits must be >= 1 (or None for every hit), got {max_hits}")
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
    device choices (zero copy, work-group size, kernel variant, rays per
    launch) and its result pool; the count pass with `count_packet_size`
    rays per work-item (None: the query's)."""

    def __init__(self, query: RayQuery, count_packet_size: int | None = None):
        self.query = query
        self.rt = query.rt
        self.count_packet_size = count_packet_size or query.packet_size
        self._lock = threading.Lock()
        self._outputs: dict[str, cl.Buffer] = {}
        self._row_bytes: dict[str, int] = {}  # of each output's rows
        self._capacity = 0
        # int32 [0]: a walk overflowed its stack; [1]: the fill pass found
        # fewer hits than the count pass
        self._counters = cl.Buffer(self.rt.context, cl.mem_flags.READ_WRITE, 8)
        # stands for a buffer argument a launch does not use (no slots, no
        # kept triangles)
        self._unused = cl.Buffer(self.rt.context, cl.mem_flags.READ_ONLY, 4)

    # -- public queries ---------------------------------------------------

    def count(self, tree: Tree, origins, directions=None, tmin=0.0,
              tmax=np.inf, mask=None) -> np.ndarray:
        """int32, in the rays' leading shape: the number of hits of each ray
        with tmin <= t <= tmax (``mask`` as RayQuery.intersect)."""
        rays, _, batch = _rays(origins, directions, tmin, tmax, mask, tree)
        with self._lock:
            counts = self._count(tree, self._placed(rays), self.query._results.empty)
        return counts.reshape(batch.shape)

    def intersect_all(self, tree: Tree, origins, directions=None, tmin=0.0, tmax=np.inf,
                      max_hits=None, mask=None) -> AllHits:
        """Every hit of each ray with tmin <= t <= tmax, sorted by t; with
        max_hits=k only the k nearest of each ray (``mask`` as
        RayQuery.intersect)."""
        max_hits = check_max_hits(max_hits)
        rays, t_factor, batch = _rays(origins, directions, tmin, tmax, mask, tree)
        pool = self.query._results
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

    def _kernel(self, tree: Tree, name: str, keep: bool = True,
                packet: int | None = None) -> tuple[cl.Kernel, int]:
        """all_hits.cl's kernel `name` for `tree`, compiled as RayQuery._kernel
        compiles traverse.cl, and its rays per work-item: on flat trees
        `packet` (None: the query's variant's), one ray on instanced ones.
        Without `keep` a count keeps no hit (KEEP_HITS 0)."""
        packet = 1 if isinstance(tree, InstancedTree) else packet or self.query.packet_size
        defines = {"STACK_SIZE": stack_size(tree), "PACKET_SIZE": packet,
                   "KEEP_HITS": KEEP_HITS if keep else 0, **self.query.variant.defines,
                   **self.rt.prefetch_defines}
        if isinstance(tree, InstancedTree):
            defines["INSTANCES"] = 1
        return self.rt.kernel("query/all_hits.cl", name, **defines), packet

    def _count(self, tree, rays, empty, keep=False):
        """int32 counts of the rays, from `empty`; with `keep`, (counts,
        known): on flat scenes also each ray's first KEEP_HITS hit
        triangles, uint32 (rays, KEEP_HITS) (the fill pass tests them again
        instead of walking), else None.  Big batches run in class and
        Morton order, read by slots (_launches)."""
        count = len(rays[0])
        outputs = {"counts": empty(count, np.int32)}
        if keep and not isinstance(tree, InstancedTree):
            outputs["known"] = empty((count, KEEP_HITS), np.uint32)
        results = (outputs["counts"], outputs.get("known")) if keep else outputs["counts"]
        keep = "known" in outputs
        if not (count and self.query._check_tree(tree)):
            outputs["counts"][:] = 0
            return results
        kernel, packet = self._kernel(tree, "count_hits_arrays", keep, self.count_packet_size)
        # not keeping: the kernel writes no known triangle (a stand-in buffer)
        tail = [np.uint32(1)] if keep else [self._unused, np.uint32(0)]
        self._launches(tree, kernel, packet, rays, _coherent_order(self.query, rays), None,
                       [], outputs, tail)
        return results

    def _placed(self, rays: tuple) -> tuple:
        """The rays' arrays (_rays's) on pages (results.on_page) where the
        kernels would use them in place off zero copy (_whole): one copy
        serves the order's buffers and each pass's."""
        if self.query.zero_copy or not _whole(self.query, len(rays[0])):
            return rays
        return tuple(on_page(self.query._results, array) for array in rays)

    def _fill(self, tree, rays, offsets, known, outputs, t_factor, batch) -> None:
        """The hits into `outputs` (HIT_FIELDS and ray_index), ray r's in
        [offsets[r], offsets[r + 1]); `known`: _count's (counts, known);
        t_factor and batch: _rays's (t back in the caller's units).
        The rays go in their own order: most only have their known triangles
        tested again, and the results then land in order."""
        kernel, packet = self._kernel(tree, "fill_hits_arrays")
        counts, triangles = known
        inputs = [counts, triangles, np.uint32(1)] if triangles is not None else \
            [self._unused, self._unused, np.uint32(0)]
        self._launches(tree, kernel, packet, rays, None, offsets, inputs, outputs, [])
        if t_factor is not None:  # back from the frame
            t, ray_index = outputs["t"], outputs["ray_index"]
            for start, stop in _chunks(offsets, self.query.max_rays_per_launch, len(t_factor)):
                part = slice(int(offsets[start]), int(offsets[stop]))
                caller_t(t[part], t_factor, ray_index[part], batch)

    def _launches(self, tree, kernel, packet, rays, order, offsets, inputs, outputs,
                  tail) -> None:
        """Runs `kernel` (`packet` rays per work-item) over the rays: its
        arguments are the scene (query.scene_args, with the masks), the rays
        and their slots (RAY_PARAMS in kernels/all_hits.cl), the offsets of
        the rays' output segments and the first ray (the fill kernel:
        `offsets`, the prefix sum of each ray's slots; None: one slot per
        ray, the count kernel), the `inputs` (arrays of a row per ray, or
        arguments as they are), the `outputs` (a row per ray, or the
        segments' slots), the `tail` arguments, the counters and the ray
        count.

        They go in chunks of rays (_chunks), runs of `order` (None: as
        given).  Where _whole holds (CPU devices) and the device allows a
        buffer of each whole array, each launch reads and writes the whole
        arrays in place by its rays' slots (USE_HOST_PTR: the runtime's own
        copy at most, which _placed spares it); elsewhere (GPUs, big batches
        off zero copy, outputs too big for one buffer) the host takes each
        chunk's rays in that order and puts its results back, and the rays
        go up and the results come back through buffers reused between
        chunks, so that a device holds one chunk's copy, not the whole
        arrays'."""
        query, rt, queue = self.query, self.rt, self.rt.queue
        context, flags = rt.context, cl.mem_flags
        origins, directions, *limits = rays
        # (each whole array one buffer: only where the device allows its size)
        whole = _whole(query, len(origins)) and rt.fits_one_buffer(
            *(array for array in [*rays, *inputs, *outputs.values()]
              if isinstance(array, np.ndarray)))
        assert whole or order is None or (offsets is None and not inputs)
        cl.enqueue_copy(queue, self._counters, np.zeros(2, np.int32))

        def wrap(array, access):  # the array's own memory (in place) or a copy of it
            host = flags.USE_HOST_PTR if whole else flags.COPY_HOST_PTR
            return cl.Buffer(context, access | host, hostbuf=array)
        scalars = {id(value): wrap(np.full(1, value, value.dtype), flags.READ_ONLY)
                   for value in limits if value.ndim == 0}

        def ray_args(rows):  # the rays' arrays, or some rows of them: RAY_PARAMS but the slots
            def part(array):
                return array[rows] if isinstance(rows, slice) else take_rows(array, rows)
            stepped = [[wrap(value[rows], flags.READ_ONLY), np.uint32(1)]
                       if value.ndim else [scalars[id(value)], np.uint32(0)]
                       for value in limits]  # tmin, tmax, mask
            return (scene_args(tree, *stepped[2]), [
                wrap(part(origins), flags.READ_ONLY), wrap(part(directions), flags.READ_ONLY),
                *stepped[0], *stepped[1]])
        # at most two launches in flight (Ctrl-C waits for few), and chunks small
        # enough, where the rays are copied per chunk, that the copies stay small
        rays_per_launch = query.max_rays_per_launch if whole else \
            min(query.max_rays_per_launch, COPIED_RAYS_PER_LAUNCH)
        if whole:
            scene, whole_rays = ray_args(slice(None))
            if order is None:
                order = np.arange(len(origins), dtype=np.uint32)
            # the segments' offsets index the whole output arrays: base and
            # first ray 0
            segments = [] if offsets is None else \
                [wrap(offsets, flags.READ_ONLY), np.int64(0), np.int64(0)]
            whole_inputs = [wrap(value, flags.READ_ONLY) if isinstance(value, np.ndarray)
                            else value for value in inputs]
            # read too: the fill kernel sorts the hits in its segments
            buffers = [wrap(array, flags.READ_WRITE) for array in outputs.values()]
        # launches in flight: their events, and what ends them (results put
        # back); they hold what the kernels read or write
        flight: list[tuple[list, object, tuple, int]] = []
        sizes = LaunchSizes(rays_per_launch)

        def retire(count):
            while len(flight) > count:
                waited, put_back, _, rays = flight.pop(0)
                rt.wait(waited)
                sizes.ended(waited[0], rays)
                put_back()
        try:
            # results copied back go through buffers of HITS_PER_LAUNCH slots
            max_slots = None if whole else HITS_PER_LAUNCH
            for start, stop in _chunks(offsets, sizes, len(origins), max_slots):
                if whole:
                    args = [*whole_rays, wrap(order[start:stop], flags.READ_ONLY), np.uint32(1),
                            *segments, *whole_inputs, *buffers]
                    put_back, parts, out = (lambda: None), {}, {}
                else:
                    rows = slice(start, stop) if order is None else order[start:stop]
                    first, last = (start, stop) if offsets is None else \
                        (int(offsets[start]), int(offsets[stop]))
                    scene, args = ray_args(rows)
                    args += [self._unused, np.uint32(0)]
                    if offsets is not None:
                        args += [wrap(offsets[start:stop + 1], flags.READ_ONLY),
                                 np.int64(first), np.int64(start)]
                    args += [wrap(value[start:stop], flags.READ_ONLY)
                             if isinstance(value, np.ndarray) else value for value in inputs]
                    # a taken chunk's results land in rows of their own first
                    parts = {name: array[first:last] if order is None
                             else np.empty((stop - start, *array.shape[1:]), array.dtype)
                             for name, array in outputs.items()}
                    out = self._reserve(outputs, last - first)
                    args += list(out.values())

                    def put_back(rows=rows, parts=parts):
                        if order is not None:
                            for name, part in parts.items():
                                put_rows(outputs[name], rows, part)
                launched = rt.run(kernel, -(-(stop - start) // packet), *scene, *args, *tail,
                                  self._counters, np.uint32(stop - start),
                                  local_size=query.work_group_size)
                done = [launched, *(collect(queue, out[name], part, False)
                                    for name, part in parts.items())]
                flight.append((done, put_back, (args, out), stop - start))
                # before the next run is cut: at most one left in flight, none
                # until the first has ended and sized the runs after it
                retire(1 if sizes.measured else 0)
            retire(0)
            if whole:
                rt.wait([collect(queue, buffer, array, True)
                         for buffer, array in zip(buffers, outputs.values())])
            counters = np.zeros(2, np.int32)
            rt.wait([cl.enqueue_copy(queue, counters, self._counters, is_blocking=False)])
        except BaseException:  # launches in flight may still write: let them end
            queue.finish()
            raise
        if counters[0]:
            raise RuntimeError("ray traversal overflowed its stack (sized from Tree.depth): "
                               "the tree is deeper than its depth field says")
        if counters[1]:
            raise RuntimeError("hlbvh_cl internal error: intersect_all's fill pass found fewer "
                               "hits than its count pass")

    def _reserve(self, outputs: dict, slots: int) -> dict[str, cl.Buffer]:
        """Grow-only device buffers for `slots` rows of each output (copied
        back after each launch)."""
        self._row_bytes.update({name: array.itemsize * int(np.prod(array.shape[1:]))
                                for name, array in outputs.items()})
        if slots > self._capacity or any(name not in self._outputs for name in outputs):
            capacity = max(slots, min(HITS_PER_LAUNCH, 2 * self._capacity), self._capacity)
            sizes = {name: capacity * self._row_bytes[name] for name in {*self._outputs, *outputs}}
            self._outputs = {}
            self.rt.check_allocation("all-hits buffers", sizes)
            self._outputs = {name: cl.Buffer(self.rt.context, cl.mem_flags.READ_WRITE, size)
                             for name, size in sizes.items()}
            self._capacity = capacity
        return {name: self._outputs[name] for name in outputs}


def _whole(query: RayQuery, count: int) -> bool:
    """Whether launches over `count` rays read and write the whole arrays in
    place by slots (_launches): on CPU devices, off zero copy only up to
    INDEXED_COPY_MAX rays (a runtime that copies a host pointer it cannot
    use copies the whole arrays)."""
    return not query.rt.profile.gpu and (query.zero_copy or count <= INDEXED_COPY_MAX)


def _coherent_order(query: RayQuery, rays) -> np.ndarray | None:
    """Big batches' rays by class, then in fine Morton order of their
    origins, or of their directions where their lines nearly meet at one
    point (hlbvh_cl.query.order: rays a packet can trace together, close enough
    to share their nodes), as uint32 slots found on the query's device;
    None: as given."""
    origins, directions = rays[:2]
    if len(origins) < COHERENT_MIN:
        return None
    # read in place where the launches read them so (_whole)
    return device_order(query.rt, origins, RAY_ORDER_BITS, _whole(query, len(origins)),
                        directions=directions,
                        by_direction=concurrent_rays(origins, directions))


def _chunks(offsets: np.ndarray | None, max_rays: int | LaunchSizes, count: int,
            max_slots: int | None = HITS_PER_LAUNCH):
    """(start, stop) runs of the `count` rays with at most max_rays rays (a
    LaunchSizes: its size as each run is made) and (unless one ray has more)
    max_slots slots (None: any number), where ray r has slots
    [offsets[r], offsets[r + 1]) (None: one each); runs without slots are
    skipped."""
    start = 0
    max_slots = max_slots or count + (int(offsets[-1]) if offsets is not None else 0) + 1
    sizes = max_rays if isinstance(max_rays, LaunchSizes) else None
    while start < count:
        if sizes is not None:
            max_rays = sizes.size
        if offsets is None:
            stop = min(start + max_rays, start + max_slots, count)
        else:
            bound = int(np.searchsorted(offsets, offsets[start] + max_slots, "right")) - 1
            stop = min(start + max_rays, count, max(bound, start + 1))
            if offsets[stop] == offsets[start]:
                start = stop
                continue
        yield start, stop
        start = stop
