"""The order in which a batch of queries runs: large batches go in Morton
order of their points (query points, or ray origins), so that consecutive
work-items walk much the same nodes and triangles, which stay in cache
(the ray sorting of Pharr et al. 1997 and Garanzha & Loop 2010, in its
simplest form).  Rays are sorted by the class of their direction first
(kernels/ray_class.h: the axis and signs a packet's rays must share), then
by origin.  Points come in any order, often uniformly random; a LiDAR's
rays share one origin and keep the sensor's own order within a class (the
sort is stable).  The results are put back in the caller's order."""
from __future__ import annotations

import numpy as np
import pyopencl as cl

#: Batches of at least this many points or rays run in Morton order
#: (coherent_order); smaller ones as given.
COHERENT_MIN = 1024

#: Bits per axis of the Morton codes that order the points: a 15-bit key,
#: which numpy's stable argsort sorts by radix (for queries walked one per
#: work-item, 5 to 10 bits walked alike).
ORDER_BITS = 5

#: Bits per axis for queries walked in packets (point queries,
#: kernels/point_packet.h): a packet's consecutive points must lie close
#: together, not merely in one of 2^15 cells.
FINE_ORDER_BITS = 10

#: Bits per axis for rays walked in packets: their origins' code under the
#: 5 bits of their direction's class, in a 32-bit key.  Origin rather than
#: direction under the class: keys led by the direction's cell, or
#: interleaving it with the origin's (5-D Morton), or a line's two points
#: on the scene's bounding sphere, ordered rays aimed at one point better
#: but rays with scattered origins and directions, or parallel ones, worse.
RAY_ORDER_BITS = 9
CLASS_BITS = 5


def _spread_bits(cells: np.ndarray) -> np.ndarray:
    """uint32 cells < 2^10 with two zero bits after each bit (the Morton
    interleave, by the usual shifts and masks)."""
    x = cells.astype(np.uint32)
    x = (x | (x << 16)) & 0x030000FF
    x = (x | (x << 8)) & 0x0300F00F
    x = (x | (x << 4)) & 0x030C30C3
    return (x | (x << 2)) & 0x09249249


def take_rows(points: np.ndarray, order: np.ndarray) -> np.ndarray:
    """points[order] for float32 (N, 3) points, gathering each row as one
    12-byte item rather than three floats (numpy's fancy indexing of an
    (N, 3) array goes element by element)."""
    rows = np.ascontiguousarray(points).view(np.dtype((np.void, 12))).reshape(-1)
    return np.take(rows, order).view(np.float32).reshape(-1, 3)


def put_rows(out: np.ndarray, order: np.ndarray, values: np.ndarray) -> None:
    """out[order] = values, as take_rows's inverse: rows of 2-D arrays moved
    as one item each (numpy scatters an (N, 3) array element by element)."""
    if out.ndim == 2:
        item = np.dtype((np.void, out.itemsize * out.shape[1]))
        out = out.view(item).reshape(-1)
        values = np.ascontiguousarray(values).view(item).reshape(-1)
    out[order] = values


def _cell_scales(points: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Per axis, float32, the points' least coordinate and the scale that
    maps their extent onto cells 0 .. 2^bits - 1 (0 on a flat axis)."""
    top = (1 << bits) - 1
    lo, scale = np.zeros(3, np.float32), np.zeros(3, np.float32)
    for axis in range(3):
        # a column at a time: numpy reduces a contiguous column in one pass,
        # an (N, 3) array along its first axis with a stride
        column = points[:, axis]
        low, high = column.min(), column.max()
        lo[axis] = low
        # capped: a denormal extent would make it inf, and 0 * inf NaN
        if high > low:
            scale[axis] = min(top / (float(high) - float(low)), 2.0**100)
    return lo, scale


def ray_classes(directions: np.ndarray) -> np.ndarray:
    """uint32 class of each float32 (N, 3) direction (kernels/ray_class.h):
    kz * 8, plus 1, 2, 4 for a sign bit set in x, y, z."""
    a = np.abs(directions)
    kz = np.where((a[:, 0] >= a[:, 1]) & (a[:, 0] >= a[:, 2]), 0,
                  np.where(a[:, 1] >= a[:, 2], 1, 2)).astype(np.uint32)
    signs = np.signbit(directions).astype(np.uint32)
    return kz * 8 + signs[:, 0] + (signs[:, 1] << 1) + (signs[:, 2] << 2)


def coherent_order(points: np.ndarray, bits: int = ORDER_BITS,
                   directions: np.ndarray | None = None) -> np.ndarray:
    """The indices of float32 (N, 3) points in Morton order of their cells
    in a 2^bits grid (bits <= 10) over their box: consecutive work-items
    then walk much the same nodes and triangles, which stay in cache (points
    come in any order, often uniformly random).  With `directions` the
    points are rays' origins, sorted by their ray's class first (bits <= 9:
    a 32-bit key).  Stable: points in one cell keep their order.  On the
    host with numpy; device_order gives the same order from the device."""
    key = np.zeros(len(points), np.uint32)
    top = (1 << bits) - 1
    lo, scale = _cell_scales(points, bits)
    for axis in range(3):
        cells = ((points[:, axis] - lo[axis]) * scale[axis]).astype(np.uint32)
        np.minimum(cells, top, out=cells)
        key |= _spread_bits(cells) << axis
    key_bits = 3 * bits
    if directions is not None:
        assert key_bits + CLASS_BITS <= 32
        key |= ray_classes(directions) << key_bits
        key_bits += CLASS_BITS
    # 15-bit digits, least significant first (LSD radix): numpy sorts 16-bit
    # keys by radix, wider ones by timsort
    order = np.argsort((key & 0x7FFF).astype(np.uint16), kind="stable")
    for shift in range(15, key_bits, 15):
        digit = ((key >> shift) & 0x7FFF).astype(np.uint16)
        order = order[np.argsort(digit[order], kind="stable")]
    return order


def device_order(rt, points: np.ndarray, bits: int = FINE_ORDER_BITS,
                 zero_copy: bool = False, directions: np.ndarray | None = None) -> np.ndarray:
    """coherent_order(points, bits, directions) as uint32, computed on rt's
    device: the keys by kernels/order.cl, the stable sort by the library's
    radix sort (hlbvh_cl.sort) rather than numpy's argsorts on the host.
    With zero_copy the kernel reads the points (and directions) in place."""
    from .sort import _sorter  # the sort module imports the device layer
    count = len(points)
    order = np.empty(count, np.uint32)
    if count == 0:
        return order
    points = np.ascontiguousarray(points, np.float32)
    if directions is not None:
        assert 3 * bits + CLASS_BITS <= 32
        directions = np.ascontiguousarray(directions, np.float32)
    lo, scale = _cell_scales(points, bits)
    flags = cl.mem_flags
    # the sorter's scratch buffers are shared with builds (Runtime.build_lock)
    with rt.build_lock:
        try:
            host = flags.USE_HOST_PTR if zero_copy else flags.COPY_HOST_PTR
            sources = [cl.Buffer(rt.context, flags.READ_ONLY | host, hostbuf=array)
                       for array in (points, directions) if array is not None]
            keys, ids = rt.allocate(4 * count), rt.allocate(4 * count)
            name = "point_keys" if directions is None else "ray_keys"
            made = rt.run(rt.kernel("order.cl", name, ORDER_BITS=bits), count, *sources,
                          np.uint32(count), *lo, *scale, keys, ids)
            key_bits = 3 * bits + (0 if directions is None else CLASS_BITS)
            _, values, events = _sorter(rt, np.dtype(np.uint32)).sort(
                keys, ids, count, key_bits, wait_for=[made])
            rt.wait([cl.enqueue_copy(rt.queue, order, values, wait_for=events[-1:] or [made],
                                     is_blocking=False)])
        except BaseException:  # Ctrl-C: the kernels may still read the points
            rt.queue.finish()
            raise
    return order
