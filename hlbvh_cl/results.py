"""Host memory for ray query results, recycled once the caller drops them.

Each ``intersect`` returns fresh arrays: 32 bytes per ray, 100 MB for 3.1M
rays.  Memory new to the process costs a page fault per page on first write,
and on this project's machine (a VM whose host backs guest memory lazily) that
first write measured anywhere from 4 to 90 ms for 38 MB: a 3.1M-ray query took
125 or 210 ms at random.  So the arrays of one query are views into one block
that this pool owns, and a block is handed out again once nothing outside the
pool refers to it any more (CPython's reference count: a result array, or any
view of it, keeps its block in use).  A loop such as ``hits =
scene.intersect(...)`` then alternates between two blocks.

At most ``keep`` blocks are held; a block still in use when it leaves the pool
simply belongs to its arrays from then on.
"""
from __future__ import annotations

import sys
import threading

import numpy as np

#: Results smaller than this are plain np.empty arrays (cheap to allocate).
MIN_POOLED_BYTES = 1 << 20

#: Arrays start at multiples of this within a block (a cache line).
ALIGNMENT = 64


class ResultPool:
    def __init__(self, keep: int = 2):
        self.keep = keep
        self._blocks: list[np.ndarray] = []
        self._lock = threading.Lock()

    def arrays(self, fields: dict[str, tuple[tuple[int, ...], type]]) -> dict[str, np.ndarray]:
        """Uninitialised arrays {name: (shape, dtype)}, views into one block."""
        layout, offset = {}, 0
        for name, (shape, dtype) in fields.items():
            dtype = np.dtype(dtype)
            nbytes = int(np.prod(shape)) * dtype.itemsize
            layout[name] = (offset, nbytes, shape, dtype)
            offset += -(-nbytes // ALIGNMENT) * ALIGNMENT
        if offset < MIN_POOLED_BYTES:
            return {name: np.empty(shape, dtype) for name, (_, _, shape, dtype) in layout.items()}
        block = self._block(offset + ALIGNMENT)
        pad = -block.ctypes.data % ALIGNMENT
        return {name: block[pad + start:pad + start + nbytes].view(dtype).reshape(shape)
                for name, (start, nbytes, shape, dtype) in layout.items()}

    def clear(self) -> None:
        with self._lock:
            self._blocks.clear()

    def _block(self, nbytes: int) -> np.ndarray:
        with self._lock:
            for block in self._blocks:
                # referents: the list, this loop's name and getrefcount's argument
                if len(block) == nbytes and sys.getrefcount(block) == 3:
                    return block
            block = np.empty(nbytes, np.uint8)
            self._blocks.append(block)
            if len(self._blocks) > self.keep:
                free = [b for b in self._blocks if sys.getrefcount(b) == 3 and b is not block]
                self._blocks.remove(free[0] if free else self._blocks[0])
            return block
