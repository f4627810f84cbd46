"""Host memory for query results, recycled once the caller drops them.

Each ``intersect`` returns fresh arrays: 32 bytes per ray, 100 MB for 3.1M
rays; the point queries and the hit counts likewise.  Memory new to the
process costs a page fault per page on first write, and on a VM whose host
backs guest memory lazily that first write can cost as much as the query
itself, at random.  So each result array is lent from a block of memory
that this pool keeps, and the block comes back once that array and every view
of it are gone.  A loop such as ``hits = scene.intersect(...)`` then
alternates between two sets of blocks.

An array's numpy base is a small lease object holding its block; a
weakref.finalize on the lease hands the block back.  The finalizer may run in
any thread, inside the garbage collector, so it only puts the block on a
queue (SimpleQueue.put is safe there); the pool takes returned blocks off the
queue on its next request.  Of the returned blocks, the ``keep`` most recent
are kept, and only those of a size among the last ``keep`` requests: a block
is only lent again at its own size, so one of a size no longer asked for
(results of varying length, intersect_all's) would be held for nothing.  The
pool lives as long as its RayQuery or PointQuery (so its Scene).
"""
from __future__ import annotations

import collections
import math
import queue
import threading
import weakref

import numpy as np

#: Arrays smaller than this are plain np.empty arrays (cheap to allocate).
MIN_POOLED_BYTES = 1 << 20

#: A lent array starts at a multiple of this: a page, so that a device may
#: use it in place (hlbvh_cl.query.rays: Intel's CPU runtime requires a page).
ALIGNMENT = 4096


class _Lease:
    """The base object of one lent array: ``nbytes`` bytes of ``block`` from
    ``offset``, exposed through the array interface."""

    def __init__(self, block: np.ndarray, offset: int, nbytes: int):
        self.block = block
        self.__array_interface__ = {"shape": (nbytes,), "typestr": "|u1", "version": 3,
                                    "data": (block.ctypes.data + offset, False)}


class ResultPool:
    def __init__(self, keep: int = 16):
        self.keep = keep  # an intersect's Hits take 6 blocks
        self._free: list[np.ndarray] = []
        self._asked: collections.deque = collections.deque(maxlen=keep)  # recent block sizes
        self._returned: queue.SimpleQueue = queue.SimpleQueue()
        self._lock = threading.Lock()

    def empty(self, shape, dtype) -> np.ndarray:
        """An uninitialised array, lent from a block when it is large."""
        dtype = np.dtype(dtype)
        shape = (int(shape),) if np.ndim(shape) == 0 else tuple(shape)
        nbytes = math.prod(shape) * dtype.itemsize
        if nbytes < MIN_POOLED_BYTES:
            return np.empty(shape, dtype)
        block = self._take(nbytes + ALIGNMENT)
        lease = _Lease(block, -block.ctypes.data % ALIGNMENT, nbytes)
        weakref.finalize(lease, self._returned.put, block)
        return np.asarray(lease).view(dtype).reshape(shape)

    @property
    def held(self) -> list[np.ndarray]:
        """The blocks kept for reuse now (a copy of the list)."""
        with self._lock:
            self._collect()
            return list(self._free)

    def clear(self) -> None:
        """Drops the blocks held for reuse (lent ones stay with their arrays)."""
        with self._lock:
            self._collect()
            self._free.clear()

    def _take(self, nbytes: int) -> np.ndarray:
        with self._lock:
            self._asked.append(nbytes)
            self._collect()
            for i, block in enumerate(self._free):
                if len(block) == nbytes:
                    return self._free.pop(i)
        return np.empty(nbytes, np.uint8)

    def _collect(self) -> None:
        """Moves the returned blocks to the free list (lock held)."""
        while True:
            try:
                self._free.append(self._returned.get_nowait())
            except queue.Empty:
                break
        asked = set(self._asked)
        self._free = [block for block in self._free if len(block) in asked][-self.keep:]


def starts_on_page(*arrays: np.ndarray) -> bool:
    """Whether every array's memory starts on a page (ALIGNMENT), as a CPU
    runtime needs to use a host pointer in place (Intel's)."""
    return all(array.ctypes.data % ALIGNMENT == 0 for array in arrays)


def on_page(pool: ResultPool, array: np.ndarray) -> np.ndarray:
    """``array`` itself where it is small or starts on a page, else a copy
    lent from ``pool``, which does: a CPU runtime may use a host pointer in
    place only there (Intel's), and would copy the whole array for every
    buffer made over it, where one copy here serves them all."""
    if array.nbytes < MIN_POOLED_BYTES or starts_on_page(array):
        return array
    copy = pool.empty(array.shape, array.dtype)
    copy[...] = array
    return copy
