"""Every hit along each ray, and hit counts (kernels/all_hits.cl): two
visitors of the one walk of the wide tree.

intersect_all runs two passes over the rays.  The count pass gives each ray's
number of hits; a prefix sum of min(count, max_hits) gives each ray its
segment of the output (CSR); the fill pass then walks again and stores each
ray's hits sorted by t in its segment.  The fill pass goes in chunks of rays
whose hits stay under HITS_PER_LAUNCH, into device buffers reused between
chunks (or, on PoCL, straight into the result arrays, as query.py's zero
copy), so memory stays near the output's own size whatever the counts.

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

from .query import RayQuery, _check_rays, _into_frame, _stack_size
from .tree import Tree

#: Hits one fill launch writes at most (one ray with more still goes alone):
#: bounds the device buffers where results are copied back.
HITS_PER_LAUNCH = 1 << 21

#: Output arrays of the fill pass: dtype per hit.
HIT_FIELDS = {"t": np.float32, "u": np.float32, "v": np.float32, "prim_id": np.int32,
              "geom_id": np.int32}


@dataclass
class AllHits:
    """Every hit of R rays, H in all, as flat arrays: ray r's hits are
    [offsets[r], offsets[r + 1]), sorted by t (ties in a fixed order)."""

    offsets: np.ndarray    # int64 (R + 1,)
    ray_index: np.ndarray  # int64 (H,) the ray of each hit
    t: np.ndarray          # float32 (H,)
    prim_id: np.ndarray    # int32 (H,) face index within its own mesh
    geom_id: np.ndarray    # int32 (H,) mesh index in the scene
    u: np.ndarray          # float32 (H,) hit = (1-u-v)*v0 + u*v1 + v*v2
    v: np.ndarray          # float32 (H,)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def counts(self) -> np.ndarray:
        """int64 (R,): hits returned per ray."""
        return np.diff(self.offsets)


def _check_max_hits(max_hits) -> int | None:
    if max_hits is None:
        return None
    if isinstance(max_hits, bool) or not isinstance(max_hits, (int, np.integer)):
        raise TypeError(f"max_hits must be an int or None, got {type(max_hits).__name__}")
    if max_hits < 1:
        raise ValueError(f"max_hits must be >= 1 (or None for every hit), got {max_hits}")
    return int(max_hits)


def _rays(origins, directions, tmin, tmax, tree):
    """The checked rays in the tree's frame and the per-ray t factor back
    (query._into_frame).  The one place that reads the caller's ray arrays."""
    origins, directions, tmin, tmax = _check_rays(origins, directions, tmin, tmax)
    return _into_frame(origins, directions, tmin, tmax, tree)


class AllHitsQuery:
    """count_intersections and intersect_all on one device, built on a
    RayQuery: its chunked launches for the count pass, its device choices
    (zero copy, work-group size, kernel variant) for both."""

    def __init__(self, query: RayQuery):
        self.query = query
        self.rt = query.rt
        self._lock = threading.Lock()
        self._outputs: dict[str, cl.Buffer] = {}
        self._capacity = 0
        # int32 [0]: a walk overflowed its stack; [1]: the fill pass found
        # fewer hits than the count pass
        self._counters = cl.Buffer(self.rt.context, cl.mem_flags.READ_WRITE, 8)

    # -- public queries ---------------------------------------------------

    def count(self, tree: Tree, origins, directions, tmin=0.0, tmax=np.inf) -> np.ndarray:
        """int32 (R,): the number of hits of each ray with tmin <= t <= tmax."""
        origins, directions, tmin, tmax, _ = _rays(origins, directions, tmin, tmax, tree)
        return self._count(tree, origins, directions, tmin, tmax)

    def intersect_all(self, tree: Tree, origins, directions, tmin=0.0, tmax=np.inf,
                      max_hits=None) -> AllHits:
        """Every hit of each ray with tmin <= t <= tmax, sorted by t; with
        max_hits=k only the k nearest of each ray."""
        max_hits = _check_max_hits(max_hits)
        origins, directions, tmin, tmax, t_factor = _rays(origins, directions, tmin, tmax, tree)
        kept = self._count(tree, origins, directions, tmin, tmax)
        if max_hits is not None:
            np.minimum(kept, max_hits, out=kept)
        offsets = np.empty(len(kept) + 1, np.int64)
        offsets[0] = 0
        np.cumsum(kept, out=offsets[1:])
        total = int(offsets[-1])
        pool = self.query._results
        fields = {name: pool.empty(total, dtype) for name, dtype in HIT_FIELDS.items()}
        if total:
            with self._lock:
                try:
                    self._fill(tree, origins, directions, tmin, tmax, offsets, fields, t_factor)
                except BaseException:  # launches in flight may still write: let them end
                    self.rt.queue.finish()
                    raise
        ray_index = np.repeat(np.arange(len(kept), dtype=np.int64), kept)
        return AllHits(offsets=offsets, ray_index=ray_index, **fields)

    # -- internals ----------------------------------------------------------

    def _kernel(self, tree: Tree, name: str) -> cl.Kernel:
        """all_hits.cl's kernel `name` for `tree`, compiled as RayQuery._kernel
        compiles traverse.cl but one ray per work-item."""
        defines = {"STACK_SIZE": _stack_size(tree), "PACKET_SIZE": 1,
                   **self.query.variant.defines, **self.rt.prefetch_defines}
        return self.rt.kernel("all_hits.cl", name, **defines)

    def _count(self, tree, origins, directions, tmin, tmax) -> np.ndarray:
        query = self.query
        count = len(origins)
        counts = query._results.empty(count, np.int32)
        if not (count and query._check_tree(tree)):
            counts[:] = 0
            return counts
        kernel = self._kernel(tree, "count_hits_arrays")

        def launch(n, b, limits):
            return self.rt.run(kernel, n, tree.nodes, tree.triangles, b["origins"],
                               b["directions"], *limits, b["prim_id"], self._counters,
                               np.uint32(n), local_size=query.work_group_size)
        # RayQuery's chunked launches; the counts travel in its per-ray int32
        # buffer (named prim_id for the closest-hit query)
        query._run(count, origins, directions, tmin, tmax, launch, {"prim_id": counts})
        return counts

    def _reserve(self, hits: int) -> None:
        """Grow-only device buffers for the fill pass's results."""
        if hits <= self._capacity:
            return
        capacity = max(hits, min(HITS_PER_LAUNCH, 2 * self._capacity))
        sizes = {name: capacity * np.dtype(dtype).itemsize for name, dtype in HIT_FIELDS.items()}
        self._outputs = {}
        self.rt.check_allocation("all-hits buffers", sizes)
        self._outputs = {name: cl.Buffer(self.rt.context, cl.mem_flags.READ_WRITE, size)
                         for name, size in sizes.items()}
        self._capacity = capacity

    def _fill(self, tree, origins, directions, tmin, tmax, offsets, fields, t_factor) -> None:
        query, rt, queue = self.query, self.rt, self.rt.queue
        kernel = self._kernel(tree, "fill_hits_arrays")
        context, flags = rt.context, cl.mem_flags
        cl.enqueue_copy(queue, self._counters, np.zeros(2, np.int32))

        def wrap(array, access):  # the array's own memory (zero copy) or a copy of it
            if query.zero_copy:
                return cl.Buffer(context, access | flags.USE_HOST_PTR, hostbuf=array)
            return cl.Buffer(context, access | flags.COPY_HOST_PTR, hostbuf=array)

        limits = [(tmin, "tmin"), (tmax, "tmax")]
        scalars = [wrap(np.full(1, value, np.float32), flags.READ_ONLY)
                   for value, _ in limits if value.ndim == 0]
        events, kept = [], []  # kept: what the launches in flight read or write
        for start, stop in _chunks(offsets, query.max_rays_per_launch):
            if len(events) >= 2:  # at most two launches in flight: Ctrl-C waits for few
                rt.wait(events[-2:-1])
            first, last = int(offsets[start]), int(offsets[stop])
            segment = (offsets[start:stop + 1] - first).astype(np.uint32)
            kept.append(segment)
            args = [wrap(origins[start:stop], flags.READ_ONLY),
                    wrap(directions[start:stop], flags.READ_ONLY)]
            scalar = iter(scalars)
            for value, _ in limits:
                args += [wrap(value[start:stop], flags.READ_ONLY), np.uint32(1)] if value.ndim \
                    else [next(scalar), np.uint32(0)]
            args.append(wrap(segment, flags.READ_ONLY))
            parts = {name: array[first:last] for name, array in fields.items()}
            if query.zero_copy:
                outputs = {name: wrap(part, flags.WRITE_ONLY) for name, part in parts.items()}
            else:
                self._reserve(last - first)
                outputs = self._outputs
            events.append(rt.run(kernel, stop - start, tree.nodes, tree.triangles, tree.refs,
                                 *args, *(outputs[name] for name in
                                          ("t", "u", "v", "prim_id", "geom_id")),
                                 self._counters, np.uint32(stop - start),
                                 local_size=query.work_group_size))
            for name, part in parts.items():
                if query.zero_copy:  # the results are there once the buffer is mapped
                    array, _ = cl.enqueue_map_buffer(queue, outputs[name], cl.map_flags.READ, 0,
                                                     part.shape, part.dtype, is_blocking=False)
                    array.base.release(queue)
                else:
                    kept.append(cl.enqueue_copy(queue, part, outputs[name], is_blocking=False))
        counters = np.zeros(2, np.int32)
        rt.wait([cl.enqueue_copy(queue, counters, self._counters, is_blocking=False)])
        if counters[0]:
            raise RuntimeError("ray traversal overflowed its stack (sized from Tree.depth): "
                               "the tree is deeper than its depth field says")
        if counters[1]:
            raise RuntimeError("hlbvh_cl internal error: intersect_all's fill pass found fewer "
                               "hits than its count pass")
        if t_factor is not None:  # back from the frame: exact, powers of two
            for start, stop in _chunks(offsets, query.max_rays_per_launch):
                part = slice(int(offsets[start]), int(offsets[stop]))
                fields["t"][part] = fields["t"][part] * np.repeat(
                    t_factor[start:stop], np.diff(offsets[start:stop + 1]))


def _chunks(offsets: np.ndarray, max_rays: int):
    """(start, stop) runs of rays with at most max_rays rays and (unless one
    ray has more) HITS_PER_LAUNCH hits; runs without hits are skipped."""
    count, start = len(offsets) - 1, 0
    while start < count:
        bound = int(np.searchsorted(offsets, offsets[start] + HITS_PER_LAUNCH, "right")) - 1
        stop = min(start + max_rays, count, max(bound, start + 1))
        if offsets[stop] > offsets[start]:
            yield start, stop
        start = stop
