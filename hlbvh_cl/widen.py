"""Stage 7 host side: the wide tree traversal reads (kernels/widen.cl).

The build's product stays the flat BVH2 (DeviceTree); the WideTree is
derived from it, kept on it (``DeviceTree.wide``) and rewritten from the
BVH2's boxes after a refit (:func:`refit_wide_tree`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from . import layout
from .device import Runtime
from .scan import exclusive_scan
from .tree import DeviceTree

KERNEL_FILE = "widen.cl"
NO_SLOT = 0xFFFFFFFF


@dataclass
class WideTree:
    """A WIDE_ARITY-wide BVH over a DeviceTree's triangles (same order).

    nodes        WideNode[node_count] (layout.WIDE_NODE); node 0 is the root.
    slots        uint32[node_count * WIDE_ARITY]: the BVH2 child slot each
                 child copies (2 * node + side, NO_SLOT when unused).
    first_child  int32[node_count]: the wide index of each node's first
                 interior child (the others follow in slot order).
    lane_of_slot int32[2 * BVH2 node_count]: for each BVH2 child slot, the
                 wide child copying it (WIDE_ARITY * node + k), or -1; the
                 BVH2 refit writes through it (refit.cl).
    depth        wide nodes on the longest root-to-leaf path (>= 1).
    """

    nodes: cl.Buffer
    slots: cl.Buffer
    first_child: cl.Buffer
    lane_of_slot: cl.Buffer
    node_count: int
    depth: int

    def read_nodes(self, queue: cl.CommandQueue) -> np.ndarray:
        out = np.empty(self.node_count, layout.WIDE_NODE)
        cl.enqueue_copy(queue, out, self.nodes)
        return out


def wide_tree(rt: Runtime, tree: DeviceTree) -> WideTree:
    """``tree.wide``, made first if the tree has none yet."""
    if not isinstance(tree, DeviceTree):
        raise TypeError(f"tree must be a hlbvh_cl.tree.DeviceTree, got {type(tree).__name__}")
    with rt.build_lock:
        if tree.wide is None:
            tree.wide, _ = widen(rt, tree)
    return tree.wide


def widen(rt: Runtime, tree: DeviceTree, wait_for=None) -> tuple[WideTree, list[cl.Event]]:
    """Collapse ``tree`` (a flat BVH2 with at least one node) into a WideTree.

    One level of wide nodes per round; each round reads back the size of the
    next level (4 bytes)."""
    with rt.pool.build():
        return _widen(rt, tree, wait_for)


def _widen(rt: Runtime, tree: DeviceTree, wait_for) -> tuple[WideTree, list[cl.Event]]:
    if tree.node_count < 1:
        raise ValueError(f"tree has node_count={tree.node_count}; widening needs a root node")
    q = rt.queue
    arity = layout.WIDE_ARITY
    capacity = tree.node_count  # each wide node stands for a distinct BVH2 node
    rt.check_allocation("widening the tree", {
        "sources": capacity * 4, "slots": capacity * arity * 4, "first children": capacity * 4,
        "interior counts": (capacity + 1) * 4})
    take = rt.pool.take
    source, slots = take(capacity * 4), take(capacity * arity * 4)
    first_child, interior = take(capacity * 4), take((capacity + 1) * 4)
    choose = rt.kernel(KERNEL_FILE, "choose_wide_slots", **rt.prefetch_defines)
    link = rt.kernel(KERNEL_FILE, "link_wide_children")

    events = [cl.enqueue_fill_buffer(q, source, np.int32(0), 0, 4, wait_for=wait_for)]
    level_first, level_count, depth = 0, 1, 0
    total = np.empty(1, np.uint32)
    while level_count > 0:
        depth += 1
        events.append(rt.run(choose, level_count, level_first, level_count, source, tree.nodes,
                             slots, interior, wait_for=events[-1:]))
        events += exclusive_scan(rt, interior, level_count, wait_for=events[-1:])
        cl.enqueue_copy(q, total, interior, src_offset=level_count * 4, wait_for=events[-1:])
        next_first, next_count = level_first + level_count, int(total[0])
        if next_first + next_count > capacity:
            raise RuntimeError(f"widening needs more than {capacity} wide nodes: the BVH2 is "
                               "not a tree (a node is reached twice)")
        events.append(rt.run(link, level_count, level_first, level_count, next_first, interior,
                             tree.nodes, slots, source, first_child, wait_for=events[-1:]))
        level_first, level_count = next_first, next_count
    node_count = level_first
    rt.check_allocation("wide tree", {"nodes": node_count * layout.WIDE_NODE.itemsize})
    # keep only the used part of the choice, for refits
    kept_slots, kept_first = take(node_count * arity * 4), take(node_count * 4)
    events.append(cl.enqueue_copy(q, kept_slots, slots, byte_count=node_count * arity * 4,
                                  wait_for=events[-1:]))
    events.append(cl.enqueue_copy(q, kept_first, first_child, byte_count=node_count * 4,
                                  wait_for=events[-1:]))
    lane_of_slot = take(2 * tree.node_count * 4)
    events.append(cl.enqueue_fill_buffer(q, lane_of_slot, np.int32(-1), 0, 2 * tree.node_count * 4,
                                         wait_for=events[-1:]))
    events.append(rt.run(rt.kernel(KERNEL_FILE, "map_wide_lanes"), node_count, node_count,
                         kept_slots, lane_of_slot, wait_for=events[-1:]))
    wide = WideTree(nodes=take(node_count * layout.WIDE_NODE.itemsize), slots=kept_slots,
                    first_child=kept_first, lane_of_slot=lane_of_slot, node_count=node_count,
                    depth=depth)
    rt.pool.keep(wide.nodes, wide.slots, wide.first_child, wide.lane_of_slot)
    events += refit_wide_tree(rt, tree, wide, wait_for=events[-1:])
    return wide, events


def refit_wide_tree(rt: Runtime, tree: DeviceTree, wide: WideTree | None = None,
                    wait_for=None) -> list[cl.Event]:
    """Rewrite every wide node from the BVH2's current boxes (after a refit;
    the topology is the one chosen by :func:`widen`).  ``wide`` defaults to
    ``tree.wide``; nothing is done when there is none."""
    wide = wide if wide is not None else tree.wide
    if wide is None:
        return []
    return [rt.run(rt.kernel(KERNEL_FILE, "write_wide_nodes"), wide.node_count, wide.node_count,
                   wide.slots, wide.first_child, tree.nodes, wide.nodes, wait_for=wait_for)]
