"""The build's one product: an 8-wide BVH on the device with its triangles.

Stages meet here (pbrt-v4 style): hlbvh_cl.build.pipeline makes a Tree, hlbvh_cl.build.refit
moves its boxes in place, and ray queries only read it.  The wide nodes
follow Wald, Benthin & Boulos 2008 ("Getting Rid of Packets") and Embree's
BVH8; the binary tree they are collapsed from is the build's scratch.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from . import layout


def leaf_defines(indexed: bool) -> dict:
    """The kernel defines that pick the leaf layout (kernels/core/leaf.h)."""
    return {"INDEXED_LEAVES": 1} if indexed else {}


def leaf_bytes(vertex_count: int, triangle_count: int, indexed: bool) -> int:
    """The bytes of a tree's leaves (Tree.triangles): a Triangle a
    triangle, or an indexed tree's records and then its vertices."""
    if indexed:
        return triangle_count * layout.INDEXED_TRIANGLE.itemsize + vertex_count * 12
    return triangle_count * layout.TRIANGLE.itemsize


@dataclass
class Tree:
    """A WIDE_ARITY-wide BVH on one device.

    nodes      WideNode[node_count] (layout.WIDE_NODE), breadth-first: node 0
               is the root, and each level follows the one above it.  A
               lane with count 0 is an interior child (a wide node index),
               with count > 0 a leaf covering triangles [child, child +
               count); an unused lane has child EMPTY_CHILD and an empty box.
    levels     (first, count) of each level of wide nodes, root first: a
               refit runs one launch per level, from the deepest up.
    triangles  the leaves: Triangle[triangle_count] (layout.TRIANGLE), in leaf
               order; or, for an ``indexed`` tree (Scene(..., compact=True)),
               IndexedTriangle[triangle_count] (layout.INDEXED_TRIANGLE) in
               leaf order followed by the vertices they name, vertex_count
               float32 triples in this tree's frame (kernels/core/leaf.h).
    refs       TriangleRef[triangle_count]: geometry id and face index in its mesh.
    vertex_ids int32[3 * triangle_count]: each tree-ordered triangle's vertex
               indices into the scene's vertices, which a refit re-reads
               (None for an indexed tree, whose records name its vertices,
               and for a tree made by hand, which cannot be refit).
    bounds_lo, bounds_hi  the box around every triangle (and sphere), in this
               tree's frame.
    scale      the power of two the scene's coordinates were multiplied by to
               give this tree's (hlbvh_cl.core.frame; 1 for most scenes): ray
               origins are scaled alike on their way in.
    dipoles    WideDipoles[node_count] (layout.WIDE_DIPOLES) for winding
               numbers, made on the first query that needs them
               (hlbvh_cl.query.points) and dropped by a refit (stale) or release.
    released   set by :meth:`release`: the buffers went back to a pool (the
               Scene that owned the tree rebuilt it) and must not be read.
    spheres    float4[sphere_count] (centre, radius) in this tree's frame: a
               flat scene's analytic spheres, tested beside the tree by ray
               queries (kernels/query/rays/sphere.h), geom_id sphere_geom + i;
               None without spheres.  The Scene owns the buffer.
    """

    nodes: cl.Buffer
    triangles: cl.Buffer
    refs: cl.Buffer
    node_count: int
    levels: tuple[tuple[int, int], ...]
    triangle_count: int
    bounds_lo: np.ndarray
    bounds_hi: np.ndarray
    vertex_ids: cl.Buffer | None = None
    scale: float = 1.0
    dipoles: cl.Buffer | None = None
    released: bool = False
    spheres: cl.Buffer | None = None
    sphere_count: int = 0
    sphere_geom: int = 0
    indexed: bool = False
    vertex_count: int = 0  # the vertices after an indexed tree's records

    @property
    def depth(self) -> int:
        """Wide nodes on the longest root-to-leaf path (>= 1)."""
        return len(self.levels)

    def memory(self) -> dict[str, int]:
        """Device bytes traversal reads: {"node_bytes", "triangle_bytes"},
        from the layouts' itemsizes, so that they follow any layout change."""
        return {"node_bytes": self.node_count * layout.WIDE_NODE.itemsize,
                "triangle_bytes": leaf_bytes(self.vertex_count, self.triangle_count,
                                             self.indexed)}

    def release(self, pool) -> None:
        """Give this tree's device buffers back to ``pool`` for the next
        build to reuse; the tree is unusable after."""
        pool.give(self.nodes, self.triangles, self.refs, self.vertex_ids)
        self.nodes = self.triangles = self.refs = self.vertex_ids = self.spheres = None
        self.drop_dipoles(pool)
        self.released = True

    def drop_dipoles(self, pool) -> None:
        """Give the winding-number dipoles back to ``pool``: they describe
        the triangles as they were (a refit calls this)."""
        pool.give(self.dipoles)
        self.dipoles = None

    def read_nodes(self, queue: cl.CommandQueue, wait_for=None) -> np.ndarray:
        out = np.empty(self.node_count, layout.WIDE_NODE)
        cl.enqueue_copy(queue, out, self.nodes, wait_for=wait_for)
        return out

    def read_triangles(self, queue: cl.CommandQueue) -> tuple[np.ndarray, np.ndarray]:
        """The triangles (layout.TRIANGLE, an indexed tree's gathered from
        its records and vertices) and refs, in leaf order."""
        refs = np.empty(self.triangle_count, layout.TRIANGLE_REF)
        cl.enqueue_copy(queue, refs, self.refs)
        if not self.indexed:
            tris = np.empty(self.triangle_count, layout.TRIANGLE)
            cl.enqueue_copy(queue, tris, self.triangles)
            return tris, refs
        cells = np.empty((self.triangle_count + self.vertex_count, 3), np.int32)
        cl.enqueue_copy(queue, cells, self.triangles)
        n = self.triangle_count
        corners = cells[:n] + np.arange(n, dtype=np.int32)[:, None]  # cells from the start
        tris = np.empty(n, layout.TRIANGLE)
        for k in range(3):
            tris[f"v{k}"] = cells.view(np.float32)[corners[:, k]]
        return tris, refs


    def read_root_box(self, queue: cl.CommandQueue, wait_for=None) -> tuple[np.ndarray, np.ndarray]:
        """The union of the root's lanes, as the device holds them now."""
        root = np.empty(1, layout.WIDE_NODE)
        cl.enqueue_copy(queue, root, self.nodes, wait_for=wait_for)
        lo = np.array([root[f"lo_{a}"][0].min() for a in "xyz"], np.float32)
        hi = np.array([root[f"hi_{a}"][0].max() for a in "xyz"], np.float32)
        return lo, hi
