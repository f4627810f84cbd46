"""The order in which a batch of queries runs: large batches go in Morton
order of their points (query points, or ray origins), so that consecutive
work-items walk much the same nodes and triangles, which stay in cache
(the ray sorting of Pharr et al. 1997 and Garanzha & Loop 2010, in its
simplest form).  Points come in any order, often uniformly random; a LiDAR's
rays share one origin and keep the sensor's own order (the sort is stable).
The results are put back in the caller's order."""
from __future__ import annotations

import numpy as np

#: Batches of at least this many points or rays run in Morton order
#: (coherent_order); smaller ones as given.
COHERENT_MIN = 1024

#: Bits per axis of the Morton codes that order the points: a 16-bit key,
#: which numpy's stable argsort sorts by radix (5 to 10 bits walked alike).
ORDER_BITS = 5


def _spread_bits(cells: np.ndarray) -> np.ndarray:
    """uint16 cells < 2^5 with two zero bits after each bit (the Morton
    interleave, by the usual shifts and masks)."""
    x = (cells | (cells << 4)) & 0x30C3
    return (x | (x << 2)) & 0x9249


def take_rows(points: np.ndarray, order: np.ndarray) -> np.ndarray:
    """points[order] for float32 (N, 3) points, gathering each row as one
    12-byte item rather than three floats (numpy's fancy indexing of an
    (N, 3) array goes element by element)."""
    rows = np.ascontiguousarray(points).view(np.dtype((np.void, 12))).reshape(-1)
    return np.take(rows, order).view(np.float32).reshape(-1, 3)


def coherent_order(points: np.ndarray) -> np.ndarray:
    """The indices of float32 (N, 3) points in Morton order of their cells
    in a 2^ORDER_BITS grid over their box: consecutive work-items then walk
    much the same nodes and triangles, which stay in cache (points come in
    any order, often uniformly random).  A column at a time: numpy reduces a
    contiguous column in one pass, an (N, 3) array along its first axis with
    a stride."""
    key = np.zeros(len(points), np.uint16)
    top = (1 << ORDER_BITS) - 1
    for axis in range(3):
        column = points[:, axis]
        lo, hi = column.min(), column.max()
        # capped: a denormal extent would make it inf, and 0 * inf NaN
        scale = np.float32(min(top / (float(hi) - float(lo)), 2.0**100)) if hi > lo else \
            np.float32(0)
        cells = ((column - lo) * scale).astype(np.uint16)
        np.minimum(cells, top, out=cells)
        key |= _spread_bits(cells) << axis
    return np.argsort(key, kind="stable")
