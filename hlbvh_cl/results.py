"""Host memory for ray query results, recycled once the caller drops them.

Each ``intersect`` returns fresh arrays: 32 bytes per ray, 100 MB for 3.1M
rays.  Memory new to the process costs a page fault per page on first write,
and on this project's machine (a VM whose host backs guest memory lazily) that
first write measured anywhere from 4 to 90 ms for 38 MB: a 3.1M-ray query took
125 or 210 ms at random.  So the arrays of one query are views into one block
of memory that this pool lends out, and the block comes back once every one of
those arrays (and every view of them) is gone.  A loop such as ``hits =
scene.intersect(...)`` then alternates between two blocks.

The arrays' numpy base is a small lease object holding the block; a
weakref.finalize on it returns the block, so nothing depends on reference
counts.  At most ``keep`` returned blocks are held for reuse.
"""
from __future__ import annotations

import threading
import weakref

import numpy as np

#: Results smaller than this are plain np.empty arrays (cheap to allocate).
MIN_POOLED_BYTES = 1 << 20

#: Arrays start at multiples of this within a block (a cache line).
ALIGNMENT = 64


class _Lease:
    """The base object of one query's result arrays: ``nbytes`` bytes of
    ``block`` from ``offset``, exposed through the array interface."""

    def __init__(self, block: np.ndarray, offset: int, nbytes: int):
        self.block = block
        self.__array_interface__ = {"shape": (nbytes,), "typestr": "|u1", "version": 3,
                                    "data": (block.ctypes.data + offset, False)}


class ResultPool:
    def __init__(self, keep: int = 2):
        self.keep = keep
        self._free: list[np.ndarray] = []
        self._lock = threading.Lock()

    def arrays(self, fields: dict[str, tuple[tuple[int, ...], type]]) -> dict[str, np.ndarray]:
        """Uninitialised arrays {name: (shape, dtype)}, views into one block."""
        layout, size = {}, 0
        for name, (shape, dtype) in fields.items():
            dtype = np.dtype(dtype)
            nbytes = int(np.prod(shape)) * dtype.itemsize
            layout[name] = (size, nbytes, shape, dtype)
            size += -(-nbytes // ALIGNMENT) * ALIGNMENT
        if size < MIN_POOLED_BYTES:
            return {name: np.empty(shape, dtype) for name, (_, _, shape, dtype) in layout.items()}
        block = self._take(size + ALIGNMENT)
        lease = _Lease(block, -block.ctypes.data % ALIGNMENT, size)
        weakref.finalize(lease, self._give_back, block)
        memory = np.asarray(lease)
        return {name: memory[start:start + nbytes].view(dtype).reshape(shape)
                for name, (start, nbytes, shape, dtype) in layout.items()}

    def clear(self) -> None:
        with self._lock:
            self._free.clear()

    def _take(self, nbytes: int) -> np.ndarray:
        with self._lock:
            for i, block in enumerate(self._free):
                if len(block) == nbytes:
                    return self._free.pop(i)
        return np.empty(nbytes, np.uint8)

    def _give_back(self, block: np.ndarray) -> None:
        with self._lock:
            self._free.append(block)
            del self._free[:-self.keep]  # the most recent ones
