"""Exclusive prefix sum of a uint32 device buffer, in place (kernels/parallel/scan.cl).

Reduce-then-scan over a device-chosen number of tiles: one work-group per
tile, and the tile sums are few enough for a single work-group to scan.
exclusive_scan_counted scans a length that an earlier kernel left in a
device buffer, so that the host never reads it (issue 57).
"""
from __future__ import annotations

import math
import threading
import weakref
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from ..device.runtime import Runtime

KERNEL_FILE = "parallel/scan.cl"

# Below this many elements per work-item a tile is not worth a launch: small
# inputs (a radix-sort histogram) are scanned by a single work-group.
MIN_PER_ITEM = 1024
# CPU: a few tiles per core balance the load; GPU: enough groups to fill it.
CPU_TILES_PER_COMPUTE_UNIT = 4
GPU_TILES_PER_COMPUTE_UNIT = 8
CPU_GROUP_SIZE = 4
GPU_GROUP_SIZE = 256
# Sub-tile bounds are uint arithmetic on the device: n + items must fit.
MAX_COUNT = 2**31


@dataclass
class ScanPlan:
    """How exclusive_scan runs on one runtime (see plan)."""

    group_size: int
    max_tiles: int
    tile_sums: cl.Buffer  # max_tiles + 1 uint32, reused by every call


_plans: "weakref.WeakKeyDictionary[Runtime, ScanPlan]" = weakref.WeakKeyDictionary()
_plans_lock = threading.Lock()


def _fitting_group_size(rt: Runtime, group_size: int) -> int:
    """Halves group_size until every compiled scan kernel accepts it (GPU register limits)."""
    group_size = 1 << (max(1, group_size).bit_length() - 1)
    while group_size > 1:
        allowed = min(
            rt.kernel(KERNEL_FILE, name, SCAN_GROUP_SIZE=group_size).get_work_group_info(
                cl.kernel_work_group_info.WORK_GROUP_SIZE, rt.device.cl_device)
            for name in ("scan_reduce_tiles", "scan_tile_sums", "scan_tiles",
                         "scan_reduce_tiles_counted", "scan_tile_sums_counted",
                         "scan_tiles_counted"))
        if group_size <= allowed:
            break
        group_size //= 2
    return group_size


def plan(rt: Runtime) -> ScanPlan:
    """The scan's plan on ``rt``, made on first use and kept for the
    runtime's life: its work-group size, its most tiles, and the buffer of
    tile sums that every call on ``rt`` reuses."""
    with _plans_lock:
        found = _plans.get(rt)
        if found is None:
            d = rt.device
            if not rt.profile.gpu:
                group_size = CPU_GROUP_SIZE
                max_tiles = CPU_TILES_PER_COMPUTE_UNIT * d.compute_units
            else:
                group_size = GPU_GROUP_SIZE
                max_tiles = GPU_TILES_PER_COMPUTE_UNIT * d.compute_units
            group_size = _fitting_group_size(rt, min(group_size, d.cl_device.max_work_group_size))
            tile_sums = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 4 * (max_tiles + 1))
            found = ScanPlan(group_size, max_tiles, tile_sums)
            _plans[rt] = found
    return found


def _check_args(buf, n) -> int:
    if not isinstance(buf, cl.Buffer):
        raise TypeError(f"exclusive_scan: buf must be a pyopencl.Buffer, got {type(buf).__name__}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise TypeError(f"exclusive_scan: n must be an integer, got {type(n).__name__}")
    n = int(n)
    if not 0 <= n < MAX_COUNT:
        raise ValueError(f"exclusive_scan: n={n} is out of range; expected 0 <= n < {MAX_COUNT}")
    if buf.size < 4 * (n + 1):
        raise ValueError(f"exclusive_scan: buf holds {buf.size} bytes but n={n} needs n+1 uint32 "
                         f"= {4 * (n + 1)} bytes (buf[n] receives the total)")
    return n


def _tiles(chosen: ScanPlan, n: int) -> int:
    """Tiles for n elements: up to the plan's most, none under MIN_PER_ITEM per work-item."""
    return max(1, min(chosen.max_tiles, n // (chosen.group_size * MIN_PER_ITEM)))


def exclusive_scan(rt: Runtime, buf: cl.Buffer, n: int, wait_for=None) -> list[cl.Event]:
    """Exclusive prefix sum of the uint32 ``buf[0:n]``, in place, on ``rt.queue``.

    Afterwards ``buf[i]`` holds the sum of the first i inputs (mod 2**32) and
    ``buf[n]`` the total; the input ``buf[n]`` is ignored, so ``buf`` must hold
    at least n+1 elements.  Returns the enqueued events (for profiling).  The
    scratch buffer of tile sums is shared by every call on ``rt``, which is
    safe because ``rt.queue`` runs in order.
    """
    n = _check_args(buf, n)
    queue = rt.queue
    if n == 0:
        return [cl.enqueue_fill_buffer(queue, buf, np.uint32(0), 0, 4, wait_for=wait_for)]

    chosen = plan(rt)
    wg = chosen.group_size
    kernel = lambda name: rt.kernel(KERNEL_FILE, name, SCAN_GROUP_SIZE=wg)  # noqa: E731
    tiles = _tiles(chosen, n)
    per_item = math.ceil(n / (tiles * wg))
    tiles = math.ceil(n / (wg * per_item))  # no empty tiles

    if tiles == 1:
        return [kernel("scan_tile_sums")(queue, (wg,), (wg,), buf, np.uint32(n),
                                         np.uint32(per_item), wait_for=wait_for)]

    size = (tiles * wg,)
    reduce = kernel("scan_reduce_tiles")(queue, size, (wg,), buf, np.uint32(n),
                                         np.uint32(per_item), chosen.tile_sums, wait_for=wait_for)
    scan_sums = kernel("scan_tile_sums")(queue, (wg,), (wg,), chosen.tile_sums, np.uint32(tiles),
                                         np.uint32(math.ceil(tiles / wg)), wait_for=[reduce])
    rescan = kernel("scan_tiles")(queue, size, (wg,), buf, np.uint32(n), np.uint32(per_item),
                                  chosen.tile_sums, wait_for=[scan_sums])
    return [reduce, scan_sums, rescan]


def exclusive_scan_counted(rt: Runtime, buf: cl.Buffer, counts: cl.Buffer, at: int,
                           most: int, wait_for=None) -> list[cl.Event]:
    """exclusive_scan of ``buf[0:n]`` where n = ``counts[at]`` (uint32) is
    on the device only, at most ``most``: ``buf`` must hold most + 1
    elements.  The launch is sized for ``most``; the work-items share the
    actual n between them.  The kernel that writes ``counts[at]`` must come
    before it on ``rt.queue``."""
    most = _check_args(buf, most)
    elements = counts.size // 4
    if isinstance(at, bool) or not isinstance(at, (int, np.integer)) or not 0 <= at < elements:
        raise ValueError(f"exclusive_scan_counted: at={at} is not an element of counts "
                         f"({elements} uint32)")
    chosen = plan(rt)
    wg = chosen.group_size
    kernel = lambda name: rt.kernel(KERNEL_FILE, name, SCAN_GROUP_SIZE=wg)  # noqa: E731
    tiles, queue, at = _tiles(chosen, most), rt.queue, np.uint32(at)
    if tiles == 1:
        return [kernel("scan_tile_sums_counted")(queue, (wg,), (wg,), buf, counts, at,
                                                 wait_for=wait_for)]
    size = (tiles * wg,)
    reduce = kernel("scan_reduce_tiles_counted")(queue, size, (wg,), buf, counts, at,
                                                 chosen.tile_sums, wait_for=wait_for)
    scan_sums = kernel("scan_tile_sums")(queue, (wg,), (wg,), chosen.tile_sums, np.uint32(tiles),
                                         np.uint32(math.ceil(tiles / wg)), wait_for=[reduce])
    rescan = kernel("scan_tiles_counted")(queue, size, (wg,), buf, counts, at, chosen.tile_sums,
                                          wait_for=[scan_sums])
    return [reduce, scan_sums, rescan]
