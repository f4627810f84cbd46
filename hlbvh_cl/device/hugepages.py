"""2 MiB pages for the large buffers of a CPU device (Linux transparent huge pages).

A CPU device's buffers are host memory in 4 KiB pages.  Traversal reads the
tree's nodes and triangles at random, so a tree larger than what the TLB
covers (a few MiB of 4 KiB pages) pays a page walk on many loads.  Linux backs
memory with 2 MiB pages where the process asks for them (madvise
MADV_HUGEPAGE; /sys/kernel/mm/transparent_hugepage/enabled set to "madvise",
the common default).  On PoCL this measured faster for incoherent rays on
large trees, and a fresh buffer's first write costs one page fault per 2 MiB
instead of per 4 KiB.

The advice must come before the memory is first written, so it is given when
a buffer is made: the buffer is mapped (on CPU devices the map returns the
buffer's own memory), the 2 MiB-aligned part of it is advised, and it is
unmapped.  Where the advice is not available (another OS, THP disabled) the
buffer stays as it is: this only changes speed.

Only PoCL's buffers are advised (Runtime.huge_pages).  The cost falls on a
scene's first build, whose kernels fault the fresh pages in (rebuilds reuse
the pool's buffers); on PoCL that first build measured faster too.  Intel's
CPU runtime built fresh scenes slower with the advice, its threads waiting
on each other's faults, with no gain on its rays.
"""
from __future__ import annotations

import ctypes
import sys

import numpy as np
import pyopencl as cl

HUGE_PAGE = 1 << 21
#: Linux's MADV_HUGEPAGE (the same on x86, ARM, POWER and RISC-V)
MADV_HUGEPAGE = 14
#: Smaller buffers are not worth a map: at most three huge pages fit in them,
#: and the buffers traversal reads at random are far larger when it matters.
MIN_ADVISED_BYTES = 4 * HUGE_PAGE


def _load_madvise():
    if not sys.platform.startswith("linux"):
        return None
    try:
        madvise = ctypes.CDLL(None, use_errno=True).madvise
    except (OSError, AttributeError):
        return None
    madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    madvise.restype = ctypes.c_int
    return madvise


_madvise = _load_madvise()


def advise_huge_pages(queue: cl.CommandQueue, buffer: cl.Buffer) -> bool:
    """Asks for 2 MiB pages behind a fresh buffer of a CPU device; True if the
    kernel took the advice."""
    if _madvise is None or buffer.size < MIN_ADVISED_BYTES:
        return False
    mapped, _ = cl.enqueue_map_buffer(queue, buffer, cl.map_flags.WRITE_INVALIDATE_REGION, 0,
                                      (buffer.size,), np.uint8, is_blocking=True)
    try:
        start = mapped.ctypes.data
        first = -(-start // HUGE_PAGE) * HUGE_PAGE
        end = (start + buffer.size) // HUGE_PAGE * HUGE_PAGE
        return end > first and _madvise(first, end - first, MADV_HUGEPAGE) == 0
    finally:
        mapped.base.release(queue)
