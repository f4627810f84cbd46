"""Refit host side (kernels/refit.cl): refit_flat_tree refits a finished
DeviceTree after its vertices moved.  (A build computes its boxes as it
builds the radix tree: radix_tree.py.)"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from .tree import DeviceTree
from .widen import wide_tree


def _zeroed_ints(rt, count: int, wait_for=None) -> tuple[cl.Buffer, cl.Event]:
    buf = rt.pool.take(count * 4)
    return buf, cl.enqueue_fill_buffer(rt.queue, buf, np.int32(0), 0, max(1, count) * 4,
                                       wait_for=wait_for)


def refit_flat_tree(rt, tree: DeviceTree, vertices: cl.Buffer, wait_for=None) -> list[cl.Event]:
    """Re-read ``tree``'s triangles from moved vertices and refit every box,
    those of its wide tree (made first if it has none) included; the
    topology is kept."""
    if tree.vertex_ids is None:
        raise ValueError("this tree has no vertex ids (it was not made by a build): "
                         "it cannot be refit")
    wide = wide_tree(rt, tree)
    visits, cleared = _zeroed_ints(rt, tree.node_count, wait_for)
    walk = rt.run(rt.kernel("refit.cl", "refit_flat_tree", **rt.handoff_defines), tree.node_count,
                  tree.nodes, tree.parents, vertices, tree.vertex_ids, tree.triangles, visits,
                  tree.node_count, wide.nodes, wide.lane_of_slot, wait_for=[cleared])
    return [cleared, walk]
