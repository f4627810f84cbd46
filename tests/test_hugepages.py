"""Huge-page advice for the large buffers of CPU devices (hlbvh_cl.hugepages):
the buffer keeps its contents, and where Linux offers transparent huge pages
on request its memory really is backed by them."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest

from hlbvh_cl.device import runtime
from hlbvh_cl.hugepages import HUGE_PAGE, MIN_ADVISED_BYTES, advise_huge_pages

THP_MODE = Path("/sys/kernel/mm/transparent_hugepage/enabled")


def _thp_on_request() -> bool:
    """THP set to "always" or "madvise" (the active mode is in brackets)."""
    try:
        text = THP_MODE.read_text()
    except OSError:
        return False
    return "[always]" in text or "[madvise]" in text


def _huge_kib_at(address: int) -> int:
    """AnonHugePages of the mapping of this process that holds `address`."""
    inside = False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        fields = line.split()
        if "-" in fields[0] and len(fields) >= 5:
            low, high = (int(x, 16) for x in fields[0].split("-"))
            inside = low <= address < high
        elif inside and fields[0] == "AnonHugePages:":
            return int(fields[1])
    return 0


def test_small_buffers_are_left_alone():
    rt = runtime()
    buffer = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, MIN_ADVISED_BYTES - 4)
    assert advise_huge_pages(rt.queue, buffer) is False


@pytest.mark.skipif(not sys.platform.startswith("linux") or not _thp_on_request(),
                    reason="needs Linux with transparent huge pages on request")
def test_an_advised_buffer_is_backed_by_huge_pages_and_keeps_its_data():
    rt = runtime()
    if not rt.huge_pages:
        pytest.skip(f"{rt.device.id} buffers are not advised (Runtime.huge_pages)")
    n = 4 * MIN_ADVISED_BYTES
    buffer = rt.allocate(n)  # advised on creation
    values = np.arange(n // 4, dtype=np.uint32) * np.uint32(2654435761)
    cl.enqueue_copy(rt.queue, buffer, values)
    back = np.empty_like(values)
    cl.enqueue_copy(rt.queue, back, buffer)
    assert np.array_equal(back, values)
    mapped, _ = cl.enqueue_map_buffer(rt.queue, buffer, cl.map_flags.READ, 0, (n,), np.uint8,
                                      is_blocking=True)
    try:
        inside = -(-mapped.ctypes.data // HUGE_PAGE) * HUGE_PAGE
        assert _huge_kib_at(inside) >= HUGE_PAGE // 1024
    finally:
        mapped.base.release(rt.queue)
