"""Stage 6 host side (kernels/build/flatten.cl): the radix tree's surviving nodes,
with the SAH top above them, compacted into a flat binary tree (two child
boxes per node, Aila & Laine 2009), which widen.py collapses into the wide
tree; the flat tree is the build's scratch.

Nothing is read back here (issue 57): the buffer holds as many nodes as the
tree can have, the kernels read the SAH top's size from the device, and a
FlatSummary (layout.FLAT_SUMMARY) on the device gathers the tree's node
count, depth, cost and root box for the build's one read at the end.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from ..core import layout
from .radix_tree import RadixTree, RadixTreeMetrics
from .sah_top import TopTree
from ..parallel.scan import exclusive_scan


def flatten_nodes(rt, keys: cl.Buffer, bits: int, tree: RadixTree, metrics: RadixTreeMetrics,
                  top: TopTree | None, use_clusters: bool, spare: list | None = None,
                  wait_for=None):
    """Returns (nodes, capacity, summary, events): the flat nodes' buffer,
    the most nodes it can hold (max(1, n - 1), which the node count stays
    within) and a layout.FLAT_SUMMARY buffer, all on the device, the node
    count first in the summary.  ``spare``: dead buffers of the build to
    reuse first (BufferPool.take_spare); its own scratch joins them once
    its kernels are enqueued."""
    n = tree.n
    defines = dict(MORTON_BITS=bits, USE_CLUSTERS=int(use_clusters))
    kernel = lambda name: rt.kernel("build/flatten.cl", name, **defines)  # noqa: E731
    capacity = max(1, n - 1)  # a binary tree over n leaves has n - 1 interior nodes
    rt.check_allocation("flat tree", {"nodes": capacity * layout.FLAT_NODE.itemsize})
    spare = [] if spare is None else spare
    nodes = rt.pool.take_spare(spare, capacity * layout.FLAT_NODE.itemsize)
    summary = rt.pool.take(layout.FLAT_SUMMARY.itemsize)
    # The top's buffers where the kernels read them (USE_CLUSTERS): others
    # stand in where there is none, unread.
    top_info = top.info if top else metrics.collapsed
    top_boxes, top_cost = (top.top_boxes, top.sah_cost) if top else (metrics.boxes,
                                                                     metrics.sah_cost)
    events = []
    live = metrics.collapsed
    if n > 1:
        live = rt.pool.take_spare(spare, n * 4)
        events.append(rt.run(kernel("mark_live_nodes"), n - 1, keys, n, tree.parent,
                             tree.range_first, tree.range_last, metrics.collapsed, live,
                             wait_for=wait_for))
        events += exclusive_scan(rt, live, n - 1, wait_for=events[-1:])
        events.append(rt.run(kernel("write_flat_nodes"), n - 1, n, top_info, live,
                             tree.left_child, tree.right_child, tree.range_first,
                             tree.range_last, metrics.collapsed, metrics.boxes, nodes,
                             wait_for=events[-1:]))
    if top:
        events.append(rt.run(kernel("write_top_nodes"), max(1, top.capacity - 1), n, top.info,
                             live, top.top_left, top.top_right, top.top_boxes,
                             top.cluster_roots, top.cluster_boxes, tree.range_first,
                             tree.range_last, metrics.collapsed, nodes, wait_for=events[-1:]))
    # and the root node alone where it is a leaf
    events.append(rt.run(kernel("summarise_flat_tree"), 1, n, top_info, live, metrics.collapsed,
                         metrics.boxes, metrics.sah_cost, metrics.height, top_boxes, top_cost,
                         nodes, summary, wait_for=events[-1:] or wait_for, local_size=1))
    if n > 1:
        spare.append(live)
    return nodes, capacity, summary, events


def _area(box) -> float:
    d = np.maximum(box["hi"].astype(np.float64) - box["lo"].astype(np.float64), 0.0)
    return float(2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0]))


box_area = _area
