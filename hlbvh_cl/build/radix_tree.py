"""Stage 4 host side: the binary radix tree with its boxes, SAH costs and
collapse decisions, in one bottom-up pass (kernels/build/radix_tree.cl; Karras
2012's tree, built as Apetrei 2014 does)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from ..core import layout
from ..core.tree import leaf_defines


@dataclass
class RadixTree:
    """Binary radix tree over n sorted primitives: internal nodes 0..n-2,
    leaf of sorted primitive j = node n-1+j."""

    n: int
    left_child: cl.Buffer    # int32[n-1]
    right_child: cl.Buffer   # int32[n-1]
    parent: cl.Buffer        # int32[2n-1], -1 at the root
    range_first: cl.Buffer   # int32[n-1]: first sorted primitive under the node
    range_last: cl.Buffer    # int32[n-1]
    # the bottom-up walk's scratch (build_radix_tree), dead once the tree is
    # built: later stages of the build reuse it
    far_end: cl.Buffer       # int32[2 max(1, n-1)]
    visits: cl.Buffer        # int32[max(1, n-1)]

    @classmethod
    def allocate(cls, rt, n: int) -> "RadixTree":
        def ints(count):
            return rt.pool.take(count * 4)
        splits = max(1, n - 1)
        return cls(n, ints(n - 1), ints(n - 1), ints(2 * n - 1), ints(n - 1), ints(n - 1),
                   ints(2 * splits), ints(splits))

    def buffers(self) -> list[cl.Buffer]:
        """The tree's own arrays (not the walk's scratch)."""
        return [self.left_child, self.right_child, self.parent, self.range_first,
                self.range_last]

    def read(self, queue) -> dict[str, np.ndarray]:
        """Host copies, for tests."""
        out = {}
        for name, count in (("left_child", self.n - 1), ("right_child", self.n - 1),
                            ("parent", 2 * self.n - 1), ("range_first", self.n - 1),
                            ("range_last", self.n - 1)):
            out[name] = np.empty(count, np.int32)
            if count:
                cl.enqueue_copy(queue, out[name], getattr(self, name))
        return out


@dataclass
class RadixTreeMetrics:
    """Per radix-tree node (2n-1 of them): box, SAH cost, height in the final
    tree, and (internal nodes) whether the node collapsed into a leaf."""

    boxes: cl.Buffer       # Aabb[2n-1]
    sah_cost: cl.Buffer    # float32[2n-1], not normalised
    height: cl.Buffer      # int32[2n-1], 0 for a leaf
    collapsed: cl.Buffer   # int32[n-1]

    @classmethod
    def allocate(cls, rt, n: int) -> "RadixTreeMetrics":
        buf = rt.pool.take
        nodes = 2 * n - 1
        return cls(buf(nodes * layout.AABB.itemsize), buf(nodes * 4), buf(nodes * 4),
                   buf((n - 1) * 4))

    def buffers(self) -> list[cl.Buffer]:
        return [self.boxes, self.sah_cost, self.height, self.collapsed]


def build_radix_tree(rt, keys: cl.Buffer, bits: int, vertices: cl.Buffer, faces: cl.Buffer,
                     primitive_ids: cl.Buffer, mesh_first_face: cl.Buffer, mesh_count: int,
                     tree: RadixTree, metrics: RadixTreeMetrics, triangles: cl.Buffer,
                     refs: cl.Buffer, vertex_ids: cl.Buffer, collapse_leaves: bool,
                     indexed: bool = False, wait_for=None) -> list[cl.Event]:
    """The tree's nodes, boxes, SAH costs and collapse flags (one bottom-up
    walk), and before them the triangles (as ``indexed`` leaf records where
    asked: hlbvh_cl.core.tree), their refs and their vertex ids (None and
    not written for indexed leaves) in leaf (sorted) order with the leaves'
    boxes (lay_out_leaves)."""
    n = tree.n
    splits = max(1, n - 1)
    far_end, visits = tree.far_end, tree.visits
    cleared = cl.enqueue_fill_buffer(rt.queue, visits, np.int32(0), 0, splits * 4,
                                     wait_for=wait_for)
    if n == 1:  # no internal node: the lone leaf is the root
        cl.enqueue_fill_buffer(rt.queue, metrics.collapsed, np.int32(0), 0, 4)
    defines = dict(MORTON_BITS=bits, COLLAPSE_LEAVES=int(collapse_leaves), **rt.handoff_defines,
                   **leaf_defines(indexed))
    ready = [cleared]
    if not defines["ACQUIRE_RELEASE"]:
        # The OpenCL 1.2 handoff stores with atomic_xchg (kernels/build/handoff.h),
        # and Oclgrind's uninitialised-value check takes the old word for part
        # of the new one (MemCheckUninitialized::SimpleOrAtomic), so the words
        # handed on start defined: a fill these devices (GPUs, Oclgrind) make
        # at memory speed.
        handed_on = [(far_end, 8 * splits), (metrics.boxes, splits * layout.AABB.itemsize),
                     (metrics.sah_cost, 4 * splits), (metrics.height, 4 * splits)]
        ready += [cl.enqueue_fill_buffer(rt.queue, buffer, np.int32(0), 0, nbytes,
                                         wait_for=wait_for) for buffer, nbytes in handed_on]
    leaves = rt.run(rt.kernel("build/radix_tree.cl", "lay_out_leaves", **defines), n, n, vertices,
                    faces, primitive_ids, mesh_first_face, mesh_count, triangles, refs,
                    vertex_ids, metrics.boxes, metrics.sah_cost, metrics.height,
                    wait_for=ready)
    walk = rt.run(rt.kernel("build/radix_tree.cl", "build_radix_tree", **defines), n, keys, n,
                  far_end, visits, tree.left_child, tree.right_child, tree.parent,
                  tree.range_first, tree.range_last, metrics.boxes, metrics.sah_cost,
                  metrics.height, metrics.collapsed, wait_for=[leaves])
    return [*ready, leaves, walk]
