"""Stage 6 host side (kernels/build/flatten.cl): the radix tree's surviving nodes,
with the SAH top above them, compacted into a flat binary tree (two child
boxes per node, Aila & Laine 2009), which widen.py collapses into the wide
tree; the flat tree is the build's scratch."""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from ..core import layout
from .radix_tree import RadixTree, RadixTreeMetrics
from .sah_top import TopTree
from ..parallel.scan import exclusive_scan


def _read_scalar(q, buf, dtype, index=0, wait_for=None):
    out = np.empty(1, dtype)
    cl.enqueue_copy(q, out, buf, src_offset=index * np.dtype(dtype).itemsize, wait_for=wait_for)
    return out[0]


def flatten_nodes(rt, keys: cl.Buffer, bits: int, tree: RadixTree, metrics: RadixTreeMetrics,
                  top: TopTree | None, use_clusters: bool, wait_for=None):
    """Returns (nodes, node_count, leaf_count, root_box, depth,
    sah_cost_unnormalised, events)."""
    n, q = tree.n, rt.queue
    defines = dict(MORTON_BITS=bits, USE_CLUSTERS=int(use_clusters))
    root_is_leaf = n == 1 or (top is None and _read_scalar(q, metrics.collapsed, np.int32,
                                                          wait_for=wait_for) != 0)
    if root_is_leaf:
        nodes = rt.pool.take(layout.FLAT_NODE.itemsize)
        event = rt.run(rt.kernel("build/flatten.cl", "write_leaf_root", **defines), 1, n, metrics.boxes,
                       nodes, wait_for=wait_for, local_size=1)
        root_box = np.empty(1, layout.AABB)
        cl.enqueue_copy(q, root_box, metrics.boxes, wait_for=[event])
        area = _area(root_box[0])
        # the root node (C_t A) over one leaf of n triangles (C_i n A)
        return nodes, 1, 1, root_box[0], 1, area * (1.0 + n), [event]

    live = rt.pool.take(n * 4)
    events = [rt.run(rt.kernel("build/flatten.cl", "mark_live_nodes", **defines), n - 1, keys, n,
                     tree.parent, tree.range_first, tree.range_last, metrics.collapsed, live,
                     wait_for=wait_for)]
    events += exclusive_scan(rt, live, n - 1, wait_for=events[-1:])
    live_count = int(_read_scalar(q, live, np.uint32, n - 1, wait_for=events[-1:]))
    top_count = top.top_count if top else 0
    node_count = top_count + live_count
    rt.check_allocation("flat tree", {"nodes": node_count * layout.FLAT_NODE.itemsize})
    nodes = rt.pool.take(node_count * layout.FLAT_NODE.itemsize)
    events.append(rt.run(rt.kernel("build/flatten.cl", "write_flat_nodes", **defines), n - 1, n,
                         top_count, live, tree.left_child, tree.right_child, tree.range_first,
                         tree.range_last, metrics.collapsed, metrics.boxes, nodes,
                         wait_for=events[-1:]))
    if top:
        events.append(rt.run(rt.kernel("build/flatten.cl", "write_top_nodes", **defines), top_count, n,
                             top_count, top.root, live, top.top_left, top.top_right, top.top_boxes,
                             top.cluster_roots, top.cluster_boxes, tree.range_first,
                             tree.range_last, metrics.collapsed, nodes,
                             wait_for=events[-1:]))
        root_box = np.empty(1, layout.AABB)
        cl.enqueue_copy(q, root_box, top.top_boxes, src_offset=top.root * layout.AABB.itemsize,
                        wait_for=events[-1:])
        return nodes, node_count, node_count + 1, root_box[0], top.depth, top.sah_cost, events

    root_box = np.empty(1, layout.AABB)
    cl.enqueue_copy(q, root_box, metrics.boxes, wait_for=events[-1:])
    depth = int(_read_scalar(q, metrics.height, np.int32))
    cost = float(_read_scalar(q, metrics.sah_cost, np.float32))
    return nodes, node_count, node_count + 1, root_box[0], depth, cost, events


def _area(box) -> float:
    d = np.maximum(box["hi"].astype(np.float64) - box["lo"].astype(np.float64), 0.0)
    return float(2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0]))


box_area = _area
