"""Tree invariants, checked in numpy: the build tests call check_tree on the
trees they make (after builds, refits and rebuilds).

Independent of the kernels: it reads the wide tree back and re-derives
everything from the scene's meshes.
"""
from __future__ import annotations

import numpy as np

from hlbvh_cl.core import layout
from hlbvh_cl.core.frame import to_frame
from hlbvh_cl.query.engine import stack_size

ARITY = layout.WIDE_ARITY


def _lane_boxes(nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(W, ARITY, 3) lo and hi of every lane."""
    lo = np.stack([nodes["lo_x"], nodes["lo_y"], nodes["lo_z"]], axis=-1)
    hi = np.stack([nodes["hi_x"], nodes["hi_y"], nodes["hi_z"]], axis=-1)
    return lo, hi


def check_tree(scene, tree=None, queue=None) -> dict:
    """Assert every invariant of ``scene``'s tree; return what was derived:
    every triangle in exactly one leaf, the refs a permutation matching the
    meshes, every lane's box exactly the union of what it holds (so a node's
    box contains its children's), every node reached once and level by level
    as ``levels`` says, the depth and the stats right, and a traversal stack
    that cannot overflow.  ``tree`` read on ``queue``: another tree to check
    against ``scene``'s meshes, stats and builder (by default the scene's
    own, borrowed)."""
    if tree is None:
        with scene.borrow() as built:
            tree, queue = built.tree, built.runtime.queue
    q = queue
    nodes = tree.read_nodes(q)
    tris, refs = tree.read_triangles(q)
    n = tree.triangle_count
    assert n == sum(m.triangle_count for m in scene.meshes)
    assert len(nodes) == tree.node_count >= 1

    # refs are a permutation of every (mesh, face), and the triangles match them
    flat_ids = np.array([0] + [m.triangle_count for m in scene.meshes]).cumsum()
    assert refs["geom_id"].min() >= 0 and refs["geom_id"].max() < len(scene.meshes)
    global_face = flat_ids[refs["geom_id"]] + refs["prim_id"]
    assert np.array_equal(np.sort(global_face), np.arange(n)), "triangle refs are not a permutation"
    for g, mesh in enumerate(scene.meshes):
        sel = refs["geom_id"] == g
        # in the tree's frame: the scene's coordinates times tree.scale (hlbvh_cl.core.frame)
        corners = to_frame(mesh.vertices, tree.scale)[mesh.faces[refs["prim_id"][sel]]]
        for k, name in enumerate(("v0", "v1", "v2")):
            assert np.array_equal(tris[name][sel], corners[:, k]), f"triangle {name} != mesh {g}"

    lo, hi = _lane_boxes(nodes)
    child, count = nodes["child"], nodes["count"]
    used = (child != layout.EMPTY_CHILD) | (count > 0)
    leaf = count > 0
    interior = used & ~leaf
    # unused lanes: empty boxes, after the used ones
    assert np.all(child[~used] == layout.EMPTY_CHILD) and np.all(count[~used] == 0)
    assert np.all(lo[~used] == np.inf) and np.all(hi[~used] == -np.inf)
    assert np.all(np.diff(used.astype(np.int8), axis=1) <= 0), "an unused lane before a used one"
    assert used[:, 0].all(), "a wide node without children"

    # every node reached exactly once from the root, one level after the other
    reached = np.zeros(tree.node_count, np.int64)
    reached[0] = 1
    level, levels = np.array([0]), []
    while len(level):
        levels.append((int(level[0]), len(level)))
        assert np.array_equal(level, np.arange(level[0], level[0] + len(level))), \
            "a level's nodes are not consecutive"
        kids = child[level][interior[level]]
        assert ((kids > 0) & (kids < tree.node_count)).all(), "child index out of range"
        reached[kids] += 1
        level = kids
    assert (reached == 1).all(), "a wide node is unreachable or reached twice"
    assert tuple(levels) == tuple(tree.levels) and tree.depth == len(levels)

    # leaves tile [0, n): every triangle in exactly one leaf
    first = child[leaf].astype(np.int64)
    counts = count[leaf].astype(np.int64)
    order = np.argsort(first, kind="stable")
    first, counts = first[order], counts[order]
    assert first[0] == 0 and counts.sum() == n and (counts >= 1).all()
    assert np.array_equal(first[1:], first[:-1] + counts[:-1]), \
        "a triangle is in no leaf, or in two"

    # boxes: a leaf lane's is the union of its triangles' boxes, an interior
    # lane's the union of its child's lanes (min/max are exact in float)
    corners = np.stack([tris["v0"], tris["v1"], tris["v2"]], axis=1)
    tri_lo, tri_hi = corners.min(axis=1), corners.max(axis=1)
    leaf_lo = np.minimum.reduceat(tri_lo, first, axis=0)
    leaf_hi = np.maximum.reduceat(tri_hi, first, axis=0)
    assert np.array_equal(lo[leaf][order], leaf_lo) and np.array_equal(hi[leaf][order], leaf_hi), \
        "a leaf box is not the union of its triangles' boxes"
    node_lo = np.where(used[..., None], lo, np.inf).min(axis=1)
    node_hi = np.where(used[..., None], hi, -np.inf).max(axis=1)
    kid = child[interior]
    assert np.array_equal(lo[interior], node_lo[kid]), "an interior lane's box is not its child's"
    assert np.array_equal(hi[interior], node_hi[kid]), "an interior lane's box is not its child's"
    assert np.all(node_lo[0] == tri_lo.min(axis=0)) and np.all(node_hi[0] == tri_hi.max(axis=0))

    # the traversal stack: at most ARITY - 1 entries per node on the path
    need = np.zeros(tree.node_count, np.int64)
    level = np.array([0])
    while len(level):
        pushes = used[level].sum(axis=1) - 1
        kids_mask = interior[level]
        need[child[level][kids_mask]] = np.repeat(need[level] + pushes, kids_mask.sum(axis=1))
        level = child[level][kids_mask]
    assert stack_size(tree) >= int((need + used.sum(axis=1) - 1).max())

    stats = scene.stats
    # the collapse merges small subtrees of the binary tree into one wide leaf
    assert stats.triangles == n and stats.leaves >= int(leaf.sum())
    assert count.max() <= layout.MAX_LEAF_SIZE
    assert stats.wide_nodes == tree.node_count and stats.wide_depth == tree.depth
    assert stats.depth >= tree.depth, "the wide tree is deeper than the binary one"
    # the memory traversal reads: what was read back here, byte for byte
    # (a compact tree's leaves: a record a triangle, then the vertices they name)
    leaves = 12 * (n + tree.vertex_count) if getattr(tree, "indexed", False) else tris.nbytes
    assert (stats.node_bytes, stats.triangle_bytes) == (nodes.nbytes, leaves)
    assert stats.tree_bytes == nodes.nbytes + leaves
    if scene.builder == "lbvh" and n > 1:
        assert stats.nodes == n - 1 and stats.leaves == n, "the plain LBVH has n-1 nodes, n leaves"
    return {"nodes": nodes, "triangles": tris, "refs": refs, "used": used, "leaf": leaf,
            "root_lo": node_lo[0], "root_hi": node_hi[0]}
