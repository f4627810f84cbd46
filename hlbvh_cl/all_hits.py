"""Every hit along each ray, and hit counts (kernels/all_hits.cl): two
visitors of the one walk of the wide tree.

intersect_all runs two passes over the rays.  The count pass gives each ray's
number of hits; a prefix sum of min(count, max_hits) gives each ray its
segment of the output (CSR); the fill pass then walks again and stores each
ray's hits sorted by t in its segment, so memory stays near the output's own
size whatever the counts.  The count pass traces packets of nearby rays on
flat scenes (the query's kernel variant), the fill pass one ray per
work-item.

Big batches run in fine Morton order of their origins (hlbvh_cl.order).  On
zero-copy devices (PoCL, query.py) each launch takes a run of that order as
its rays' slots and reads and writes the whole arrays in place: counts land
in the caller's order, and the hits in the caller's segments.  Elsewhere the
rays go up in that order in chunks whose hits stay under HITS_PER_LAUNCH,
through device buffers reused between chunks, and the hits are moved to the
caller's order afterwards (_to_caller_order).

A ray through an edge or a vertex shared by triangles on opposite sides
counts that crossing once (triangle.h, OWN_EDGES), so the parity of a count
tells inside from outside on a closed mesh.  Conventions otherwise as
hlbvh_cl.query (tmin <= t <= tmax, no culling, t in units of |direction|).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from . import inputs
from .order import COHERENT_MIN, FINE_ORDER_BITS, device_order, take_rows
from .instances import InstancedTree
from .query import RayQuery, _into_frame, _masked, _stack_size, collect, scene_args
from .tree import Tree

#: Hits one fill launch writes at most (one ray with more still goes alone):
#: bounds the device buffers where results are copied back.
HITS_PER_LAUNCH = 1 << 18

#: Rays per launch where the rays are copied to the device (not PoCL): bounds
#: those copies, 32 bytes a ray, two launches in flight.
COPIED_RAYS_PER_LAUNCH = 1 << 16

#: Rays per block of _ray_index.
RAY_INDEX_BLOCK = 1 << 16

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


def _check_max_hits(max_hits) -> int | None:
    if max_hits is None:
        return None
    if isinstance(max_hits, bool) or not isinstance(max_hits, (int, np.integer)):
        raise TypeError(f"max_hits must be an int or None, got {type(max_hits).__name__}")
    if max_hits < 1:
        raise ValueError(f"max_hits must be >= 1 (or None for every hit), got {max_hits}")
    # no ray has more hits than a count holds (int32): a larger k keeps them all
    return min(int(max_hits), np.iinfo(np.int32).max)


def _rays(origins, directions, tmin, tmax, mask, tree):
    """The checked rays (hlbvh_cl.inputs) in the tree's frame: their five
    arrays (with the masks, query._masked), the per-ray t factor back
    (query._into_frame) and their leading shape.  The one place that reads
    the caller's ray arrays."""
    batch, t_factor = _into_frame(_masked(inputs.rays(origins, directions, tmin, tmax), mask,
                                          tree), tree)
    return ((batch.origins, batch.directions, batch.tmin, batch.tmax, batch.mask), t_factor,
            batch.shape)


class AllHitsQuery:
    """count_intersections and intersect_all on one device, with a RayQuery's
    device choices (zero copy, work-group size, kernel variant, rays per
    launch) and its result pool."""

    def __init__(self, query: RayQuery):
        self.query = query
        self.rt = query.rt
        self._lock = threading.Lock()
        self._outputs: dict[str, cl.Buffer] = {}
        self._capacity = 0
        # int32 [0]: a walk overflowed its stack; [1]: the fill pass found
        # fewer hits than the count pass
        self._counters = cl.Buffer(self.rt.context, cl.mem_flags.READ_WRITE, 8)
        self._no_slots = cl.Buffer(self.rt.context, cl.mem_flags.READ_ONLY, 4)  # not indexed

    # -- public queries ---------------------------------------------------

    def count(self, tree: Tree, origins, directions=None, tmin=0.0,
              tmax=np.inf, mask=None) -> np.ndarray:
        """int32, in the rays' leading shape: the number of hits of each ray
        with tmin <= t <= tmax (``mask`` as RayQuery.intersect)."""
        rays, _, shape = _rays(origins, directions, tmin, tmax, mask, tree)
        with self._lock:
            counts = self._count(tree, rays, self.query._results.empty)
        return counts.reshape(shape)

    def intersect_all(self, tree: Tree, origins, directions=None, tmin=0.0, tmax=np.inf,
                      max_hits=None, mask=None) -> AllHits:
        """Every hit of each ray with tmin <= t <= tmax, sorted by t; with
        max_hits=k only the k nearest of each ray (``mask`` as
        RayQuery.intersect)."""
        max_hits = _check_max_hits(max_hits)
        rays, t_factor, shape = _rays(origins, directions, tmin, tmax, mask, tree)
        order = _coherent_order(self.query, rays[0])
        if order is not None and not self.query.zero_copy:
            # the rays go up chunk by chunk in Morton order, and the hits come
            # back in that order: moved to the caller's afterwards
            rays, t_factor = _take(rays, order), None if t_factor is None else t_factor[order]
            caller_order, order = order, None
        else:
            caller_order = None
        with self._lock:
            kept = self._count(tree, rays, np.empty, order)  # a temporary: not pooled
            if max_hits is not None:
                np.minimum(kept, max_hits, out=kept)
            offsets = np.empty(len(kept) + 1, np.int64)
            offsets[0] = 0
            np.cumsum(kept, out=offsets[1:])
            del kept  # before the output is allocated: peak memory
            total = int(offsets[-1])
            fields = {name: self.query._results.empty(total, dtype)
                      for name, dtype in HIT_FIELDS.items()}
            if total:
                self._fill(tree, rays, offsets, fields, t_factor, order)
        del rays  # the traced copies (ordered rays), before the hits move: peak memory
        if caller_order is not None:
            offsets = _to_caller_order(fields, offsets, caller_order, self.query._results)
        return AllHits(offsets=offsets, ray_index=_ray_index(offsets), **fields, shape=shape)

    # -- internals ----------------------------------------------------------

    def _kernel(self, tree: Tree, name: str) -> tuple[cl.Kernel, int]:
        """all_hits.cl's kernel `name` for `tree`, compiled as RayQuery._kernel
        compiles traverse.cl, and its rays per work-item: packets of the
        query's variant on flat trees, one ray on instanced ones."""
        packet = 1 if isinstance(tree, InstancedTree) else self.query.packet_size
        defines = {"STACK_SIZE": _stack_size(tree), "PACKET_SIZE": packet,
                   **self.query.variant.defines, **self.rt.prefetch_defines}
        if isinstance(tree, InstancedTree):
            defines["INSTANCES"] = 1
        return self.rt.kernel("all_hits.cl", name, **defines), packet

    def _count(self, tree, rays, empty, order="coherent") -> np.ndarray:
        """int32 counts of the rays in their own order, from `empty`.  The
        rays run in `order` (by default their Morton order where that is big
        enough): on zero-copy devices as the kernel's slots, elsewhere as
        copies taken in that order and counts put back."""
        count = len(rays[0])
        counts = empty(count, np.int32)
        if not (count and self.query._check_tree(tree)):
            counts[:] = 0
            return counts
        if isinstance(order, str):
            order = _coherent_order(self.query, rays[0])
        if order is not None and not self.query.zero_copy:
            counts[order] = self._count(tree, _take(rays, order), np.empty, None)
            return counts
        kernel, packet = self._kernel(tree, "count_hits_arrays")
        self._launches(tree, kernel, packet, rays, order, None, {"counts": counts})
        return counts

    def _fill(self, tree, rays, offsets, fields, t_factor, order) -> None:
        kernel, packet = self._kernel(tree, "fill_hits_arrays")
        self._launches(tree, kernel, packet, rays, order, offsets, fields)
        if t_factor is not None:  # back from the frame: exact, powers of two
            for start, stop in _chunks(offsets, self.query.max_rays_per_launch, len(t_factor)):
                part = slice(int(offsets[start]), int(offsets[stop]))
                fields["t"][part] = fields["t"][part] * np.repeat(
                    t_factor[start:stop], np.diff(offsets[start:stop + 1]))

    def _launches(self, tree, kernel, packet, rays, order, offsets, outputs) -> None:
        """Runs `kernel` (`packet` rays per work-item) over the rays: its
        arguments are the scene (query.scene_args, with the masks), the rays
        and their slots (RAY_PARAMS in kernels/all_hits.cl), the offsets of
        the rays' output segments (the fill kernel: `offsets`, the prefix sum
        of each ray's slots; None: one slot per ray, the count kernel), the
        `outputs`, the counters and the ray count.

        With an `order` (zero-copy devices) the kernels read and write the
        whole arrays in place, each launch a run of that order as its slots.
        Otherwise they go in chunks of rays (_chunks): on PoCL reading and
        writing the arrays' parts themselves (zero copy), elsewhere with the
        rays going up per chunk and the results coming back through buffers
        reused between chunks."""
        query, rt, queue = self.query, self.rt, self.rt.queue
        context, flags = rt.context, cl.mem_flags
        cl.enqueue_copy(queue, self._counters, np.zeros(2, np.int32))

        def wrap(array, access):  # the array's own memory (zero copy) or a copy of it
            host = flags.USE_HOST_PTR if query.zero_copy else flags.COPY_HOST_PTR
            return cl.Buffer(context, access | host, hostbuf=array)
        origins, directions, *limits = rays
        scalars = {id(value): wrap(np.full(1, value, value.dtype), flags.READ_ONLY)
                   for value in limits if value.ndim == 0}

        def ray_args(part):  # the rays' arrays, or part of them: RAY_PARAMS but the slots
            stepped = [[wrap(value[part], flags.READ_ONLY), np.uint32(1)]
                       if value.ndim else [scalars[id(value)], np.uint32(0)]
                       for value in limits]  # tmin, tmax, mask
            return (scene_args(tree, *stepped[2]), [
                wrap(origins[part], flags.READ_ONLY), wrap(directions[part], flags.READ_ONLY),
                *stepped[0], *stepped[1]])
        # at most two launches in flight (Ctrl-C waits for few), and chunks small
        # enough off PoCL that the rays' copies stay small
        rays_per_launch = query.max_rays_per_launch if query.zero_copy else \
            min(query.max_rays_per_launch, COPIED_RAYS_PER_LAUNCH)
        events, kept = [], []  # kept: what the launches in flight read or write
        try:
            if order is not None:
                whole = ray_args(slice(None))
                segments = [] if offsets is None else [wrap(offsets, flags.READ_ONLY),
                                                       np.int64(0)]
                buffers = [wrap(array, flags.WRITE_ONLY) for array in outputs.values()]
                runs = ((start, min(start + rays_per_launch, len(order)))
                        for start in range(0, len(order), rays_per_launch))
            else:
                runs = _chunks(offsets, rays_per_launch, len(origins))
            for start, stop in runs:
                if len(events) >= 2:
                    rt.wait(events[-2:-1])
                    del kept[:-1]
                if order is not None:
                    slots = wrap(order[start:stop], flags.READ_ONLY)
                    scene, args = whole
                    args = [*args, slots, np.uint32(1), *segments, *buffers]
                    held = (slots,)
                else:
                    first, last = (start, stop) if offsets is None else \
                        (int(offsets[start]), int(offsets[stop]))
                    scene, args = ray_args(slice(start, stop))
                    args += [self._no_slots, np.uint32(0)]
                    if offsets is not None:
                        args += [wrap(offsets[start:stop + 1], flags.READ_ONLY),
                                 np.int64(first)]
                    parts = {name: array[first:last] for name, array in outputs.items()}
                    if query.zero_copy:
                        out = {name: wrap(part, flags.WRITE_ONLY) for name, part in parts.items()}
                    else:
                        out = self._reserve(outputs, last - first)
                    args += list(out.values())
                    held = (out,)
                events.append(rt.run(kernel, -(-(stop - start) // packet), *scene, *args,
                                     self._counters, np.uint32(stop - start),
                                     local_size=query.work_group_size))
                if order is None:
                    held += tuple(collect(queue, out[name], part, query.zero_copy)
                                  for name, part in parts.items())
                kept.append((args, held))
            if order is not None:
                kept.append([collect(queue, buffer, array, True)
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
        """Grow-only device buffers for `slots` results of each output
        (copied back after each launch)."""
        if slots > self._capacity or any(name not in self._outputs for name in outputs):
            capacity = max(slots, min(HITS_PER_LAUNCH, 2 * self._capacity), self._capacity)
            sizes = {name: capacity * 4 for name in {*self._outputs, *outputs}}  # 4-byte fields
            self._outputs = {}
            self.rt.check_allocation("all-hits buffers", sizes)
            self._outputs = {name: cl.Buffer(self.rt.context, cl.mem_flags.READ_WRITE, size)
                             for name, size in sizes.items()}
            self._capacity = capacity
        return {name: self._outputs[name] for name in outputs}


def _coherent_order(query: RayQuery, origins: np.ndarray) -> np.ndarray | None:
    """Big batches' rays in fine Morton order of their origins (hlbvh_cl.
    order: close origins, and for packets close enough to share their
    nodes), as uint32 slots found on the query's device; None: as given."""
    if len(origins) < COHERENT_MIN:
        return None
    return device_order(query.rt, origins, FINE_ORDER_BITS, query.zero_copy)


def _take(rays: tuple, order: np.ndarray) -> tuple:
    """The rays' five arrays in `order` (scalar limits stay scalars)."""
    origins, directions, *limits = rays
    return (take_rows(origins, order), take_rows(directions, order),
            *(limit[order] if limit.ndim else limit for limit in limits))


def _to_caller_order(fields: dict, offsets: np.ndarray, order: np.ndarray, pool) -> np.ndarray:
    """Moves the hits of rays traced in ``order`` (CSR ``offsets`` in that
    order) to the caller's ray order, one field at a time and a block of rays
    at a time, so that the move needs one field's copy more, not the whole
    output's; returns the caller's offsets."""
    counts = np.empty(len(order), np.int64)
    counts[order] = np.diff(offsets)
    caller = np.zeros(len(order) + 1, np.int64)
    np.cumsum(counts, out=caller[1:])
    shift = np.empty(len(order), np.int64)  # a ray's first hit: traced at caller + shift
    shift[order] = offsets[:-1]
    shift -= caller[:-1]
    for name, values in fields.items():
        moved = pool.empty(len(values), values.dtype)
        for start in range(0, len(order), RAY_INDEX_BLOCK):
            stop = min(start + RAY_INDEX_BLOCK, len(order))
            first, last = int(caller[start]), int(caller[stop])
            source = np.repeat(shift[start:stop], counts[start:stop])
            source += np.arange(first, last)
            np.take(values, source, out=moved[first:last])
        fields[name] = moved
    return caller


def _ray_index(offsets: np.ndarray) -> np.ndarray:
    """int64 (H,): the ray of each hit.  Each ray's first slot gets the step
    from the previous ray with hits, then a running sum; block by block, so
    that no temporary is as large as a per-ray array (np.repeat over
    np.arange(R) would make two)."""
    index = np.zeros(int(offsets[-1]), np.int64)
    previous = 0
    for start in range(0, len(offsets) - 1, RAY_INDEX_BLOCK):
        rays = np.flatnonzero(np.diff(offsets[start:start + RAY_INDEX_BLOCK + 1])) + start
        if len(rays):
            index[offsets[rays]] = np.diff(rays, prepend=previous)
            previous = rays[-1]
    return np.cumsum(index, out=index)


def _chunks(offsets: np.ndarray | None, max_rays: int, count: int):
    """(start, stop) runs of the `count` rays with at most max_rays rays and
    (unless one ray has more) HITS_PER_LAUNCH slots, where ray r has slots
    [offsets[r], offsets[r + 1]) (None: one each); runs without slots are
    skipped."""
    start = 0
    while start < count:
        if offsets is None:
            stop = min(start + max_rays, start + HITS_PER_LAUNCH, count)
        else:
            bound = int(np.searchsorted(offsets, offsets[start] + HITS_PER_LAUNCH, "right")) - 1
            stop = min(start + max_rays, count, max(bound, start + 1))
            if offsets[stop] == offsets[start]:
                start = stop
                continue
        yield start, stop
        start = stop
