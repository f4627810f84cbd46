"""Build stage 7 host side (kernels/build/widen.cl): the binary tree collapsed into
the 8-wide nodes that traversal reads (Dammertz et al. 2008, "Shallow Bounding
Volume Hierarchies"; Wald, Benthin & Boulos 2008, "Getting Rid of Packets"),
along the cuts of least SAH cost (Ylitie, Karras & Laine 2017), found in one
bottom-up pass, then level by level from the root.  The levels come out
breadth-first, which is what the refit (hlbvh_cl.build.refit) walks back up.

The level sizes stay on the device (issue 57): the host launches a round of
levels without reading them, then reads the round's sizes once, with
whatever else the caller reads at that point (hlbvh_cl.build.pipeline reads
the whole build's figures then); only a tree deeper than the round asks for
another round.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from ..core import layout
from ..device.runtime import Runtime
from ..parallel.scan import exclusive_scan_counted

KERNEL_FILE = "build/widen.cl"
#: Levels a first round launches beyond ceil(log8(capacity)), the depth of a
#: full 8-wide tree over the nodes: the Stanford meshes' trees are one or two
#: levels deeper than that.  Each later round launches as many levels as all
#: the rounds before it, so a tree of depth D deeper than the first round
#: takes O(log D) rounds and fewer than 2D launched levels.
EXTRA_LEVELS = 2
#: Work-items a level launches at most, per compute unit: each work-group
#: takes its share of a larger level's nodes (group_block in widen.cl), and
#: the levels smaller than their launch (the last ones, the empty ones past
#: the tree's depth) cost no more than this.  A GPU's multiprocessor holds
#: 2048 work-items at once (NVIDIA's); a CPU core takes 32 groups of 256, so
#: that a runtime that hands out groups as cores free up can balance them
#: (8 per core measured slower on PoCL).
GPU_ITEMS_PER_UNIT = 2048
CPU_ITEMS_PER_UNIT = 8192


class Widening:
    """One widening in flight: the rounds of levels launched, their sizes
    read back (``pending`` says what to read, ``advance`` takes it), then
    the wide nodes written (``write``).

    ``capacity`` bounds the BVH2's node count on the host (the buffers are
    sized for it); the actual count is the int32 at the start of
    ``bvh2_count`` on the device, which an earlier kernel on ``rt.queue``
    may still be writing.  ``spare``: dead buffers of the build to reuse
    first (BufferPool.take_spare)."""

    def __init__(self, rt: Runtime, bvh2_nodes: cl.Buffer, capacity: int, bvh2_count: cl.Buffer,
                 spare: list | None = None, wait_for=None):
        if capacity < 1:
            raise ValueError(f"the BVH2 has {capacity} nodes; widening needs a root node")
        arity = layout.WIDE_ARITY
        # each wide node stands for a distinct BVH2 node
        rt.check_allocation("widening the tree", {
            "sources": capacity * 4, "slots": capacity * arity * 4, "first children": capacity * 4,
            "interior counts": (capacity + 1) * 4, "cut costs": capacity * arity * 4,
            "cut choices": capacity * arity, "subtree runs": capacity * 8,
            "parents and visits": capacity * 8})
        spare = [] if spare is None else spare

        def take(nbytes):
            return rt.pool.take_spare(spare, nbytes)
        self.rt, self.bvh2_nodes, self.capacity = rt, bvh2_nodes, capacity
        self.bvh2_count = bvh2_count
        self.slots, self.interior = take(capacity * arity * 4), take((capacity + 1) * 4)
        self.source, self.first_child = take(capacity * 4), take(capacity * 4)
        self.choice, self.spans = take(capacity * arity), take(capacity * 8)
        units = rt.device.compute_units
        self.most_items = units * (GPU_ITEMS_PER_UNIT if rt.profile.gpu else CPU_ITEMS_PER_UNIT)
        self.levels: list[tuple[int, int]] = []  # read back so far, root first
        self.launched = 0  # levels launched so far
        self.defines = rt.handoff_defines
        self.events = [cl.enqueue_fill_buffer(rt.queue, self.source, np.int32(0), 0, 4,
                                              wait_for=wait_for)]
        self._cut_costs(take(capacity * arity * 4), take(capacity * 4), take(capacity * 4), spare)
        self._round(0, 1, EXTRA_LEVELS + -(-(capacity - 1).bit_length() // 3))

    def _cut_costs(self, costs: cl.Buffer, parent: cl.Buffer, visits: cl.Buffer,
                   spare: list) -> None:
        """The optimal cuts' choices and runs (widen.cl's wide_costs), over
        the whole BVH2, before the first level; their other buffers go back
        to ``spare`` once enqueued."""
        rt, q, capacity, arity = self.rt, self.rt.queue, self.capacity, layout.WIDE_ARITY
        fills = [cl.enqueue_fill_buffer(q, visits, np.int32(0), 0, capacity * 4),
                 # a BVH2 that is not a tree leaves choices unwritten: zero cuts stay in bounds
                 cl.enqueue_fill_buffer(q, self.choice, np.uint8(0), 0, capacity * arity)]
        if not self.defines["ACQUIRE_RELEASE"]:
            # words handed on by atomics start defined (as in radix_tree.py, for Oclgrind)
            fills += [cl.enqueue_fill_buffer(q, costs, np.int32(0), 0, capacity * 4 * arity),
                      cl.enqueue_fill_buffer(q, self.spans, np.int32(0), 0, capacity * 8)]
        parents = rt.run(rt.kernel(KERNEL_FILE, "link_wide_parents", **self.defines), capacity,
                         self.bvh2_count, self.bvh2_nodes, parent,
                         wait_for=self.events[-1:] + fills)
        self.events += [*fills, parents, rt.run(
            rt.kernel(KERNEL_FILE, "wide_costs", **self.defines), capacity, self.bvh2_count,
            self.bvh2_nodes, parent, visits, costs, self.spans, self.choice, wait_for=[parents])]
        spare += [costs, parent, visits]

    def _round(self, first: int, count: int, launched: int) -> None:
        """Launch ``launched`` levels from the level (first, count), the
        one after those read back so far."""
        rt, q = self.rt, self.rt.queue
        choose = rt.kernel(KERNEL_FILE, "choose_wide_slots", **self.defines)
        link = rt.kernel(KERNEL_FILE, "link_wide_children", **self.defines)
        # (first, count) of each level of the round and the next, then the overflow flag
        start = np.zeros(2 * (launched + 1) + 1, np.int32)
        start[:2] = first, count
        self._sizes, self._read = rt.pool.take(start.nbytes), np.empty_like(start)
        overflow_at = len(start) - 1
        self.launched += launched
        self.events.append(cl.enqueue_copy(q, self._sizes, start, is_blocking=False))
        for at in range(launched):
            # a wide node has at most 8 interior children (and 8^11 > 2^30 nodes)
            most = min(self.capacity, count * 8 ** min(at, 11))
            items = min(most, self.most_items)
            self.events.append(rt.run(choose, items, at, self._sizes, self.source,
                                      self.bvh2_nodes, self.choice, self.slots, self.interior,
                                      wait_for=self.events[-1:]))
            self.events += exclusive_scan_counted(rt, self.interior, self._sizes, 2 * at + 1,
                                                  most, wait_for=self.events[-1:])
            self.events.append(rt.run(link, items, at, self._sizes, overflow_at, self.bvh2_count,
                                      self.interior, self.bvh2_nodes, self.slots, self.source,
                                      self.first_child, wait_for=self.events[-1:]))

    def pending(self) -> list[tuple[np.ndarray, cl.Buffer]]:
        """(host array, device buffer) pairs to copy before ``advance``."""
        return [(self._read, self._sizes)]

    def advance(self) -> bool:
        """Take the round's sizes (copied into pending()'s arrays); True when
        the tree has no more levels, else the next round is launched."""
        sizes, round_levels = self._read, (len(self._read) - 3) // 2
        if sizes[-1]:
            raise RuntimeError("widening needs more wide nodes than the BVH2 has nodes: the BVH2 "
                               "is not a tree (a node is reached twice)")
        for at in range(round_levels):
            first, count = int(sizes[2 * at]), int(sizes[2 * at + 1])
            if count == 0:
                return True
            self.levels.append((first, count))
        first, count = int(sizes[-3]), int(sizes[-2])
        if count == 0:
            return True
        self._round(first, count, self.launched)  # the tree goes on
        return False

    def write(self) -> tuple[cl.Buffer, tuple[tuple[int, int], ...], list[cl.Event]]:
        """The wide nodes (a buffer the build keeps), the levels and the
        stage's events, once ``advance`` returned True."""
        rt = self.rt
        first, count = self.levels[-1]
        node_count = first + count
        rt.check_allocation("wide tree", {"nodes": node_count * layout.WIDE_NODE.itemsize})
        nodes = rt.pool.take(node_count * layout.WIDE_NODE.itemsize)
        rt.pool.keep(nodes)
        self.events.append(rt.run(rt.kernel(KERNEL_FILE, "write_wide_nodes", **self.defines),
                                  node_count, node_count, self.slots, self.first_child,
                                  self.bvh2_nodes, self.spans, nodes,
                                  wait_for=self.events[-1:]))
        return nodes, tuple(self.levels), self.events


def read_back(rt: Runtime, pairs: list[tuple[np.ndarray, cl.Buffer]]) -> None:
    """Copy each device buffer into its host array: one batch of copies and
    one wait (issue 57: a build's one read)."""
    copies = [cl.enqueue_copy(rt.queue, host, device, is_blocking=False) for host, device in pairs]
    rt.wait(copies)


def widen(rt: Runtime, bvh2_nodes: cl.Buffer, bvh2_count: int, wait_for=None):
    """Collapse a flat BVH2 of ``bvh2_count`` >= 1 nodes (layout.FLAT_NODE),
    counted on the host, into wide nodes.  Returns (nodes, levels, events):
    the wide nodes' buffer (kept by the build), each level's (first, count),
    root first, and the events of the stage.  Its other buffers are the
    build's scratch."""
    count = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                      hostbuf=np.array([bvh2_count], np.int32))
    widening = Widening(rt, bvh2_nodes, bvh2_count, count, wait_for=wait_for)
    read_back(rt, widening.pending())
    while not widening.advance():
        read_back(rt, widening.pending())
    return widening.write()
