"""Stage 5 host side: bottom-up refit (kernels/refit.cl).

refit_radix_tree runs inside a build (boxes, SAH cost, collapse decisions);
refit_flat_tree refits a finished DeviceTree after its vertices moved.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from . import layout
from .emit import RadixTree
from .tree import DeviceTree
from .widen import wide_tree


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


def _zeroed_ints(rt, count: int, wait_for=None) -> tuple[cl.Buffer, cl.Event]:
    buf = rt.pool.take(count * 4)
    return buf, cl.enqueue_fill_buffer(rt.queue, buf, np.int32(0), 0, max(1, count) * 4,
                                       wait_for=wait_for)


def refit_radix_tree(rt, vertices: cl.Buffer, faces: cl.Buffer, primitive_ids: cl.Buffer,
                     mesh_first_face: cl.Buffer, mesh_count: int, tree: RadixTree,
                     metrics: RadixTreeMetrics, triangles: cl.Buffer, refs: cl.Buffer,
                     vertex_ids: cl.Buffer, collapse_leaves: bool,
                     wait_for=None) -> list[cl.Event]:
    """Boxes, SAH costs and collapse flags of every radix-tree node; on the
    way, the triangles, their refs and their vertex ids in leaf order."""
    n = tree.n
    visits, cleared = _zeroed_ints(rt, n - 1, wait_for)
    if n == 1:  # no internal node; the walk ends at once
        cl.enqueue_fill_buffer(rt.queue, metrics.collapsed, np.int32(0), 0, 4)
    kernel = rt.kernel("refit.cl", "refit_radix_tree", COLLAPSE_LEAVES=int(collapse_leaves))
    walk = rt.run(kernel, n, vertices, faces, primitive_ids, n, mesh_first_face, mesh_count,
                  triangles, refs, vertex_ids, tree.left_child,
                  tree.right_child, tree.parent, tree.range_first, tree.range_last, visits,
                  metrics.boxes, metrics.sah_cost, metrics.height, metrics.collapsed,
                  wait_for=[cleared])
    return [cleared, walk]


def refit_flat_tree(rt, tree: DeviceTree, vertices: cl.Buffer, wait_for=None) -> list[cl.Event]:
    """Re-read ``tree``'s triangles from moved vertices and refit every box,
    those of its wide tree (made first if it has none) included; the
    topology is kept."""
    if tree.vertex_ids is None:
        raise ValueError("this tree has no vertex ids (it was not made by a build): "
                         "it cannot be refit")
    wide = wide_tree(rt, tree)
    visits, cleared = _zeroed_ints(rt, tree.node_count, wait_for)
    walk = rt.run(rt.kernel("refit.cl", "refit_flat_tree", COLLAPSE_LEAVES=0), tree.node_count,
                  tree.nodes, tree.parents, vertices, tree.vertex_ids, tree.triangles, visits,
                  tree.node_count, wide.nodes, wide.lane_of_slot, wait_for=[cleared])
    return [cleared, walk]
