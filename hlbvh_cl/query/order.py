"""The order in which a batch of queries runs: large batches go in Morton
order of their points (query points, or ray origins), so that consecutive
work-items walk much the same nodes and triangles, which stay in cache
(the ray sorting of Pharr et al. 1997 and Garanzha & Loop 2010, in its
simplest form).  Rays are sorted by the class of their direction first
(kernels/query/rays/ray_class.h: the axis and signs a packet's rays must share), then
by origin, or by direction where the lines of rays from scattered origins
nearly meet at one point (rays aimed at one target: concurrent_rays), as
rays of nearly one direction then lie along nearly one line.  Points come in
any order, often uniformly random.  The sorts are stable, and the results
are put back in the caller's order."""
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
#: kernels/query/points/point_packet.h): a packet's consecutive points must lie close
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

#: Bits per coordinate of a direction's cell on its cube face (the face
#: of the direction's class), for rays ordered by direction: the 2-D
#: Morton code under the class, a 23-bit key, sorted in one pass fewer than
#: an origin's 32 bits.  Finer cells would gain little: the six faces'
#: 2^18 cells each already hold about one ray of a million.
DIRECTION_BITS = 9

#: Rows each work-item of kernels/query/order.cl's key kernels keys at once (as
#: vectors of that many lanes).
KEY_ROWS = 8

#: Rays whose lines pass this close to one point, relative to the
#: coordinates' magnitude, meet there whatever the origins' spacing
#: (float32 rays aimed at a point miss it by their rounding); an axis of
#: the origins' box this much smaller than its largest is flat.
CONCURRENT_TOLERANCE = 1e-5

#: concurrent_rays looks at an even sample of about this many rays.
CONCURRENT_SAMPLE = 1024


#: Unit directions whose mean is at least this long are nearly parallel:
#: sorted by origin, such rays make packets that share their nodes.  Less
#: parallel rays from scattered origins walk faster one by one, interleaved
#: (count_intersections on the reference scene, rays from random points in
#: a cone of directions: sorted into packets faster where the mean's length
#: was 0.99, slower from 0.94 down).
PARALLEL_MIN = 0.98

#: Consecutive rays within this angle (its cosine) and ORDERED_SPACINGS
#: origin spacings of each other are neighbours; ORDERED_SHARE of them
#: make a batch already in a coherent order.
ORDERED_COSINE = 0.996  # 5 degrees
ORDERED_SPACINGS = 8.0
ORDERED_SHARE = 0.75


def rays_in_order(origins: np.ndarray, directions: np.ndarray) -> bool:
    """Whether the rays come in a coherent order already (a sensor's
    scanlines, a camera's pixels): most consecutive rays are neighbours in
    origin and direction.  Sorting those only costs the sort.  Decided on an
    even sample of consecutive pairs."""
    count = len(origins)
    if count < 2:
        return True
    at = np.arange(0, count - 1, max(1, count // CONCURRENT_SAMPLE))
    o, p = np.asarray(origins[at], np.float64), np.asarray(origins[at + 1], np.float64)
    a, b = np.asarray(directions[at], np.float64), np.asarray(directions[at + 1], np.float64)
    cosine = (a * b).sum(axis=1) / np.maximum(
        np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-300)
    apart = np.linalg.norm(p - o, axis=1)
    return bool(np.mean((cosine >= ORDERED_COSINE)
                        & (apart <= ORDERED_SPACINGS * _spacing(o, count))) >= ORDERED_SHARE)


def nearly_parallel(directions: np.ndarray) -> bool:
    """Whether the rays' directions are nearly one (PARALLEL_MIN), on an even
    sample."""
    d = np.asarray(directions[::max(1, len(directions) // CONCURRENT_SAMPLE)], np.float64)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    return bool(np.linalg.norm(d.mean(axis=0)) >= PARALLEL_MIN)


def _spacing(points: np.ndarray, count: int) -> float:
    """The spacing of `count` points spread over the box of `points` (a
    sample of them): its extent per point, over its axes that are not flat;
    0 for one point."""
    extent = points.max(axis=0) - points.min(axis=0)
    spread = extent[extent > CONCURRENT_TOLERANCE * extent.max()]
    if not len(spread):
        return 0.0
    return (float(np.prod(spread)) / count) ** (1 / len(spread))


def _spread_bits(cells: np.ndarray) -> np.ndarray:
    """uint32 cells < 2^10 with two zero bits after each bit (the Morton
    interleave, by the usual shifts and masks)."""
    x = cells.astype(np.uint32)
    x = (x | (x << 16)) & 0x030000FF
    x = (x | (x << 8)) & 0x0300F00F
    x = (x | (x << 4)) & 0x030C30C3
    return (x | (x << 2)) & 0x09249249


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
    """uint32 class of each float32 (N, 3) direction (kernels/query/rays/ray_class.h):
    kz * 8, plus 1, 2, 4 for a sign bit set in x, y, z."""
    a = np.abs(directions)
    kz = np.where((a[:, 0] >= a[:, 1]) & (a[:, 0] >= a[:, 2]), 0,
                  np.where(a[:, 1] >= a[:, 2], 1, 2)).astype(np.uint32)
    signs = np.signbit(directions).astype(np.uint32)
    return kz * 8 + signs[:, 0] + (signs[:, 1] << 1) + (signs[:, 2] << 2)


def concurrent_rays(origins: np.ndarray, directions: np.ndarray) -> bool:
    """Whether rays from scattered origins have lines that nearly pass
    through one point (rays aimed at one target): then rays of nearly one
    direction lie along nearly one line, and ordered by direction they make
    packets that share their nodes and triangles, while neighbours in
    origin, aimed apart, share little.  Rays from one origin (a camera's, a
    LiDAR's) are not: their origin keys keep the sensor's own order, already
    coherent, and ordering them by direction scatters their reads.
    Decided on an even sample of the rays: the point nearest to their lines
    in least squares, and the ninth decile of the lines' distances from it
    against the spacing of the origins (their box's extent per ray, over its
    axes that are not flat) or the float32 rounding of the coordinates
    (CONCURRENT_TOLERANCE)."""
    count = len(origins)
    step = max(1, count // CONCURRENT_SAMPLE)
    o = np.asarray(origins[::step], np.float64)
    d = np.asarray(directions[::step], np.float64)
    extent = o.max(axis=0) - o.min(axis=0)
    if not (extent > CONCURRENT_TOLERANCE * extent.max()).any():  # one origin
        return False
    spacing = _spacing(o, count)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    # the sums over the lines of their projections across, (I - d d^T), and
    # of those applied to their origins: the normal equations of the point
    # (sums of outer products, not d.T @ d: BLAS wakes its threads for that)
    along = (d * o).sum(axis=1)
    outer = (d[:, :, None] * d[:, None, :]).sum(axis=0)
    point = np.linalg.lstsq(len(d) * np.eye(3) - outer,
                            o.sum(axis=0) - (d * along[:, None]).sum(axis=0), rcond=None)[0]
    offsets = o - point
    distances = np.linalg.norm(offsets - (offsets * d).sum(axis=1, keepdims=True) * d, axis=1)
    rounding = CONCURRENT_TOLERANCE * (np.abs(point).max()
                                       + np.linalg.norm(offsets, axis=1).max())
    return bool(np.quantile(distances, 0.9) <= max(spacing, rounding))


def direction_keys(directions: np.ndarray) -> np.ndarray:
    """uint32 2-D Morton code of each float32 direction's cell on its cube
    face (DIRECTION_BITS per coordinate): the face coordinates are its two
    other components over its largest one, kz's (ray_classes), in [-1, 1].
    As kernels/query/order.cl's ray_keys computes it, in float32."""
    a = np.abs(directions)
    kz = (ray_classes(directions) >> 3).astype(np.intp)
    rows = np.arange(len(directions))
    major = a[rows, kz]
    top = (1 << DIRECTION_BITS) - 1
    key = np.zeros(len(directions), np.uint32)
    for shift, step in enumerate((1, 2)):  # the axes after kz, cyclically
        face = directions[rows, (kz + step) % 3] / major
        cells = ((face + np.float32(1)) * np.float32(top / 2)).astype(np.uint32)
        np.minimum(cells, top, out=cells)
        key |= _morton_2d(cells) << shift
    return key


def _morton_2d(cells: np.ndarray) -> np.ndarray:
    """uint32 cells < 2^16 with one zero bit after each bit."""
    x = cells.astype(np.uint32)
    x = (x | (x << 8)) & 0x00FF00FF
    x = (x | (x << 4)) & 0x0F0F0F0F
    x = (x | (x << 2)) & 0x33333333
    return (x | (x << 1)) & 0x55555555


def coherent_order(points: np.ndarray, bits: int = ORDER_BITS,
                   directions: np.ndarray | None = None,
                   by_direction: bool = False) -> np.ndarray:
    """The indices of float32 (N, 3) points in Morton order of their cells
    in a 2^bits grid (bits <= 10) over their box: consecutive work-items
    then walk much the same nodes and triangles, which stay in cache (points
    come in any order, often uniformly random).  With `directions` the
    points are rays' origins, sorted by their ray's class first (bits <= 9:
    a 32-bit key), then by origin, or `by_direction` by their direction's
    cell (direction_keys).  Stable: points in one cell keep their order.  On
    the host with numpy; device_order gives the same order from the
    device."""
    if by_direction:
        assert directions is not None
        key = direction_keys(directions)
        key_bits = 2 * DIRECTION_BITS
    else:
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
                 zero_copy: bool = False, directions: np.ndarray | None = None,
                 by_direction: bool = False) -> np.ndarray:
    """coherent_order(points, bits, directions, by_direction) as uint32, computed on rt's
    device: the keys by kernels/query/order.cl, the stable sort by the library's
    radix sort (hlbvh_cl.parallel.radix_sort) rather than numpy's argsorts on the host
    (still the host's where the points are too many for one device buffer).
    With zero_copy the kernel reads the points (and directions) in place."""
    from ..parallel.radix_sort import sorter  # the sort module imports the device layer
    count = len(points)
    order = np.empty(count, np.uint32)
    if count == 0:
        return order
    if 12 * count > rt.device.max_mem_alloc_size:
        # the kernel reads each array as one buffer, which the device
        # refuses past CL_DEVICE_MAX_MEM_ALLOC_SIZE: the host sorts instead
        return coherent_order(points, bits, directions, by_direction).astype(np.uint32)
    points = np.ascontiguousarray(points, np.float32)
    if directions is not None:
        assert by_direction or 3 * bits + CLASS_BITS <= 32
        directions = np.ascontiguousarray(directions, np.float32)
    # the origins' box is not needed by direction (no pass over them)
    lo, scale = (np.zeros(3, np.float32),) * 2 if by_direction else _cell_scales(points, bits)
    flags = cl.mem_flags
    # the sorter's scratch buffers are shared with builds (Runtime.build_lock)
    with rt.build_lock:
        try:
            host = flags.USE_HOST_PTR if zero_copy else flags.COPY_HOST_PTR
            sources = [cl.Buffer(rt.context, flags.READ_ONLY | host, hostbuf=array)
                       for array in (points, directions) if array is not None]
            keys, ids = rt.allocate(4 * count), rt.allocate(4 * count)
            if directions is None:
                name, mode, key_bits = "point_keys", [], 3 * bits
            else:
                name, mode = "ray_keys", [np.uint32(by_direction)]
                key_bits = (2 * DIRECTION_BITS if by_direction else 3 * bits) + CLASS_BITS
            made = rt.run(rt.kernel("query/order.cl", name, ORDER_BITS=bits,
                                     DIRECTION_BITS=DIRECTION_BITS, ROWS_PER_ITEM=KEY_ROWS),
                          -(-count // KEY_ROWS), *sources,
                          np.uint32(count), *lo, *scale, *mode, keys, ids)
            _, values, events = sorter(rt, np.dtype(np.uint32)).sort(
                keys, ids, count, key_bits, wait_for=[made])
            rt.wait([cl.enqueue_copy(rt.queue, order, values, wait_for=events[-1:] or [made],
                                     is_blocking=False)])
        except BaseException:  # Ctrl-C: the kernels may still read the points
            rt.queue.finish()
            raise
    return order
