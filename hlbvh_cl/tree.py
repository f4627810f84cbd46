"""The plain data a build hands to traversal: the flat tree on the device.

Stages meet here (pbrt-v4 style): the builder produces a DeviceTree, the
refit updates it in place, and ray queries only read it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pyopencl as cl

from . import layout

if TYPE_CHECKING:
    from .widen import WideTree


@dataclass
class DeviceTree:
    """A flat BVH2 on one device.

    nodes      FlatNode[node_count] (layout.FLAT_NODE); node 0 is the root. A
               child slot with count 0 is an interior node index, with count > 0
               a leaf covering triangles [index, index + count); EMPTY_CHILD
               (with count 0 and an empty box) is the absent second child of a
               one-triangle scene.
    triangles  Triangle[triangle_count] (layout.TRIANGLE), in leaf order.
    refs       TriangleRef[triangle_count]: geometry id and face index in its mesh.
    vertex_ids int32[3 * triangle_count]: each tree-ordered triangle's vertex
               indices into the scene's vertices, which a refit re-reads
               (None for a tree made by hand: it cannot be refit).
    parents    int32[node_count]: parent of each node (-1 for the root), for refit.
    depth      interior nodes on the longest root-to-leaf path (>= 1); a
               traversal stack of `depth` entries cannot overflow.
    wide       the WideTree traversal reads (hlbvh_cl.widen), derived from
               this tree: made by Scene after each build (or by the first query
               on a tree that has none) and refit with it by update_vertices.
    released   set by :meth:`release`: the buffers went back to a pool (the
               Scene that owned the tree rebuilt it) and must not be read.
    scale      the power of two the scene's coordinates were multiplied by to
               give this tree's (hlbvh_cl.frame; 1 for most scenes): ray origins
               are scaled alike on their way in; bounds_lo/hi are in this frame.
    """

    nodes: cl.Buffer
    triangles: cl.Buffer
    refs: cl.Buffer
    parents: cl.Buffer
    node_count: int
    leaf_count: int
    triangle_count: int
    depth: int
    bounds_lo: np.ndarray
    bounds_hi: np.ndarray
    wide: WideTree | None = None
    vertex_ids: cl.Buffer | None = None
    released: bool = False
    scale: float = 1.0

    def release(self, pool) -> None:
        """Give this tree's device buffers (and its wide tree's) back to
        ``pool`` for the next build to reuse; the tree is unusable after."""
        wide = self.wide
        pool.give(self.nodes, self.triangles, self.refs, self.parents, self.vertex_ids,
                  *((wide.nodes, wide.slots, wide.first_child, wide.lane_of_slot)
                    if wide is not None else ()))
        self.nodes = self.triangles = self.refs = self.parents = self.vertex_ids = None
        self.wide = None
        self.released = True

    def read_nodes(self, queue: cl.CommandQueue) -> np.ndarray:
        out = np.empty(self.node_count, layout.FLAT_NODE)
        cl.enqueue_copy(queue, out, self.nodes)
        return out

    def sah_cost(self, queue: cl.CommandQueue) -> float:
        """SAH cost (C_t = C_i = 1) normalised by the root's area, from the
        boxes as they are now (used after a refit has moved them)."""
        nodes = self.read_nodes(queue)
        lo = np.minimum(nodes["left_lo"], nodes["right_lo"])
        hi = np.maximum(nodes["left_hi"], nodes["right_hi"])
        cost = _area(lo, hi).sum()
        for side in ("left", "right"):
            count = nodes[f"{side}_count"]
            cost += (count * _area(nodes[f"{side}_lo"], nodes[f"{side}_hi"])).sum()
        root = _area(lo[0], hi[0])
        return float(cost / root) if root > 0 else float(self.leaf_count)

    def read_triangles(self, queue: cl.CommandQueue) -> tuple[np.ndarray, np.ndarray]:
        tris = np.empty(self.triangle_count, layout.TRIANGLE)
        refs = np.empty(self.triangle_count, layout.TRIANGLE_REF)
        cl.enqueue_copy(queue, tris, self.triangles)
        cl.enqueue_copy(queue, refs, self.refs)
        return tris, refs


def _area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    d = np.maximum(hi.astype(np.float64) - lo.astype(np.float64), 0.0)
    return 2.0 * (d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0])
