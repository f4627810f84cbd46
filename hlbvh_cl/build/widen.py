"""Build stage 7 host side (kernels/build/widen.cl): the binary tree collapsed into
the 8-wide nodes that traversal reads, level by level from the root
(Dammertz et al. 2008, "Shallow Bounding Volume Hierarchies"; Wald, Benthin
& Boulos 2008, "Getting Rid of Packets").  The levels come out breadth-first,
which is what the refit (hlbvh_cl.build.refit) walks back up.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from ..core import layout
from ..device.runtime import Runtime
from ..parallel.scan import exclusive_scan

KERNEL_FILE = "build/widen.cl"


def widen(rt: Runtime, bvh2_nodes: cl.Buffer, bvh2_count: int, wait_for=None):
    """Collapse a flat BVH2 of ``bvh2_count`` >= 1 nodes (layout.FLAT_NODE)
    into wide nodes.  Returns (nodes, levels, events): the wide nodes' buffer
    (kept by the build), each level's (first, count), root first, and the
    events of the stage.  Its other buffers are the build's scratch.  One
    level per round; each round reads back the size of the next (4 bytes)."""
    if bvh2_count < 1:
        raise ValueError(f"the BVH2 has {bvh2_count} nodes; widening needs a root node")
    q = rt.queue
    arity = layout.WIDE_ARITY
    capacity = bvh2_count  # each wide node stands for a distinct BVH2 node
    rt.check_allocation("widening the tree", {
        "sources": capacity * 4, "slots": capacity * arity * 4, "first children": capacity * 4,
        "interior counts": (capacity + 1) * 4})
    take = rt.pool.take
    source, slots = take(capacity * 4), take(capacity * arity * 4)
    first_child, interior = take(capacity * 4), take((capacity + 1) * 4)
    choose = rt.kernel(KERNEL_FILE, "choose_wide_slots", **rt.prefetch_defines)
    link = rt.kernel(KERNEL_FILE, "link_wide_children")

    events = [cl.enqueue_fill_buffer(q, source, np.int32(0), 0, 4, wait_for=wait_for)]
    levels = []
    level_first, level_count = 0, 1
    total = np.empty(1, np.uint32)
    while level_count > 0:
        levels.append((level_first, level_count))
        events.append(rt.run(choose, level_count, level_first, level_count, source, bvh2_nodes,
                             slots, interior, wait_for=events[-1:]))
        events += exclusive_scan(rt, interior, level_count, wait_for=events[-1:])
        cl.enqueue_copy(q, total, interior, src_offset=level_count * 4, wait_for=events[-1:])
        next_first, next_count = level_first + level_count, int(total[0])
        if next_first + next_count > capacity:
            raise RuntimeError(f"widening needs more than {capacity} wide nodes: the BVH2 is "
                               "not a tree (a node is reached twice)")
        events.append(rt.run(link, level_count, level_first, level_count, next_first, interior,
                             bvh2_nodes, slots, source, first_child, wait_for=events[-1:]))
        level_first, level_count = next_first, next_count
    node_count = level_first
    rt.check_allocation("wide tree", {"nodes": node_count * layout.WIDE_NODE.itemsize})
    nodes = take(node_count * layout.WIDE_NODE.itemsize)
    rt.pool.keep(nodes)
    events.append(rt.run(rt.kernel(KERNEL_FILE, "write_wide_nodes"), node_count, node_count,
                         slots, first_child, bvh2_nodes, nodes, wait_for=events[-1:]))
    return nodes, tuple(levels), events
