"""The wide tree (hlbvh_cl/widen.py, kernels/widen.cl), checked in numpy
against the scene's own triangles and the flat BVH2 it was made from:
every triangle in exactly one leaf, every box the exact union of what it
holds, every node reached once, nodes as full as the BVH2 allows, and a
traversal stack that cannot overflow."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import hlbvh_cl
from hlbvh_cl import layout
from hlbvh_cl.query import _stack_size
from hlbvh_cl.widen import WideTree, refit_wide_tree, wide_tree, widen
from shapes import grid_mesh

MESHES = Path(__file__).resolve().parent.parent / "scenes" / "meshes"
ARITY = layout.WIDE_ARITY


def _triangle_boxes(tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    corners = np.stack([tris["v0"], tris["v1"], tris["v2"]], axis=1)
    return corners.min(axis=1), corners.max(axis=1)


def _slot_boxes(nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(W, ARITY, 3) lo and hi of every slot."""
    lo = np.stack([nodes["lo_x"], nodes["lo_y"], nodes["lo_z"]], axis=-1)
    hi = np.stack([nodes["hi_x"], nodes["hi_y"], nodes["hi_z"]], axis=-1)
    return lo, hi


def check_wide_tree(scene) -> dict:
    """Assert every invariant of scene._tree.wide; return what was derived."""
    q = scene._runtime.queue
    tree = scene._tree
    wide = tree.wide
    assert isinstance(wide, WideTree) and wide.node_count >= 1
    nodes = wide.read_nodes(q)
    assert len(nodes) == wide.node_count
    tris, _ = tree.read_triangles(q)
    tri_lo, tri_hi = _triangle_boxes(tris)
    n = tree.triangle_count
    lo, hi = _slot_boxes(nodes)
    child, count = nodes["child"], nodes["count"]

    used = (child != layout.EMPTY_CHILD) | (count > 0)
    leaf = count > 0
    interior = used & ~leaf
    # unused slots: empty boxes, after the used ones
    assert np.all(child[~used] == layout.EMPTY_CHILD) and np.all(count[~used] == 0)
    assert np.all(lo[~used] == np.inf) and np.all(hi[~used] == -np.inf)
    assert np.all(np.diff(used.astype(np.int8), axis=1) <= 0), "an unused slot before a used one"
    assert used[:, 0].all(), "a wide node without children"

    # every node reached exactly once from the root, level by level
    reached = np.zeros(wide.node_count, np.int64)
    reached[0] = 1
    level, depth = np.array([0]), 0
    while len(level):
        depth += 1
        kids = child[level][interior[level]]
        assert ((kids > 0) & (kids < wide.node_count)).all(), "child index out of range"
        reached[kids] += 1
        level = kids
    assert (reached == 1).all(), "a wide node is unreachable or reached twice"
    assert wide.depth == depth
    assert depth <= tree.depth, "the wide tree is deeper than the BVH2"

    # leaves tile [0, n): every triangle in exactly one leaf
    first = child[leaf].astype(np.int64)
    counts = count[leaf].astype(np.int64)
    order = np.argsort(first, kind="stable")
    first, counts = first[order], counts[order]
    assert first[0] == 0 and counts.sum() == n
    assert np.array_equal(first[1:], first[:-1] + counts[:-1]), \
        "a triangle is in no leaf, or in two"

    # boxes: a leaf slot's is the union of its triangles' boxes, an interior
    # slot's the union of its child's slot boxes (min/max are exact in float)
    leaf_lo = np.minimum.reduceat(tri_lo, first, axis=0)
    leaf_hi = np.maximum.reduceat(tri_hi, first, axis=0)
    assert np.array_equal(lo[leaf][order], leaf_lo) and np.array_equal(hi[leaf][order], leaf_hi), \
        "a leaf box is not the union of its triangles' boxes"
    kid = child[interior]
    node_lo = np.where(used[..., None], lo, np.inf).min(axis=1)
    node_hi = np.where(used[..., None], hi, -np.inf).max(axis=1)
    assert np.array_equal(lo[interior], node_lo[kid]), "an interior slot's box is not its child's"
    assert np.array_equal(hi[interior], node_hi[kid]), "an interior slot's box is not its child's"
    flat = tree.read_nodes(q)
    assert np.array_equal(node_lo[0], np.minimum(flat[0]["left_lo"], flat[0]["right_lo"]))
    assert np.array_equal(node_hi[0], np.maximum(flat[0]["left_hi"], flat[0]["right_hi"]))

    # as full as the BVH2 allows: a node with a free slot was left no
    # interior child to open
    free = ~used[:, -1]
    assert not (interior[free]).any(), "a node has a free slot and an unopened interior child"

    # the traversal stack: at most ARITY - 1 entries per node on the path
    need = np.zeros(wide.node_count, np.int64)
    level = np.array([0])
    while len(level):
        pushes = used[level].sum(axis=1) - 1
        kids_mask = interior[level]
        parent_need = np.repeat(need[level] + pushes, kids_mask.sum(axis=1))
        kids = child[level][kids_mask]
        need[kids] = parent_need
        level = kids
    deepest = int((need + used.sum(axis=1) - 1).max())
    assert _stack_size(tree) >= deepest
    return {"nodes": nodes, "used": used, "leaf": leaf}


def _mesh(name):
    return hlbvh_cl.Mesh.load(MESHES / f"{name}.ply")


def _one_triangle():
    return hlbvh_cl.Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])




SCENES = {
    "one triangle": lambda: [_one_triangle()],
    "two triangles": lambda: [hlbvh_cl.Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]],
                                            [[0, 1, 2], [1, 3, 2]])],
    "grid": lambda: [grid_mesh(6)],
    "knight": lambda: [_mesh("knight")],
    "bunny_small + teapot": lambda: [_mesh("bunny_small"), _mesh("teapot")],
}


@pytest.mark.parametrize("builder", ["hlbvh", "lbvh"])
@pytest.mark.parametrize("name", list(SCENES))
def test_wide_tree_invariants(name, builder):
    scene = hlbvh_cl.Scene(SCENES[name](), builder=builder)
    check_wide_tree(scene)
    times = scene.stats.times_ms
    assert times["widen"] >= 0
    assert scene.stats.device_ms == pytest.approx(sum(times.values()))


def test_widening_again_gives_the_same_tree():
    scene = hlbvh_cl.Scene([_mesh("knight")])
    q = scene._runtime.queue
    again, _ = widen(scene._runtime, scene._tree)
    assert again.node_count == scene._tree.wide.node_count and again.depth == scene._tree.wide.depth
    assert again.read_nodes(q).tobytes() == scene._tree.wide.read_nodes(q).tobytes()


def test_update_vertices_refits_the_wide_tree():
    """After a refit the topology stays and every box is again the exact
    union of what it holds (the moved triangles)."""
    knight = _mesh("knight")
    scene = hlbvh_cl.Scene([knight, _mesh("teapot")])
    q = scene._runtime.queue
    before = scene._tree.wide.read_nodes(q)
    v = knight.vertices.astype(np.float64)
    moved = v * 1.3 + 0.1 * np.sin(5 * v[:, [2, 0, 1]]) * np.ptp(v, axis=0)
    scene.update_vertices(0, moved)
    after = check_wide_tree(scene)["nodes"]
    assert np.array_equal(before["child"], after["child"])
    assert np.array_equal(before["count"], after["count"])
    assert not np.array_equal(before["lo_x"], after["lo_x"]), "the boxes should have moved"


def test_refit_wide_tree_without_a_wide_tree_does_nothing():
    scene = hlbvh_cl.Scene([_one_triangle()])
    tree = scene._tree
    tree.wide = None
    assert refit_wide_tree(scene._runtime, tree) == []
    assert wide_tree(scene._runtime, tree) is tree.wide is not None  # made on demand
    check_wide_tree(scene)


def test_bad_tree_raises():
    scene = hlbvh_cl.Scene([_one_triangle()])
    with pytest.raises(TypeError, match="tree must be a hlbvh_cl.tree.DeviceTree"):
        wide_tree(scene._runtime, "tree")
    tree = scene._tree
    broken = type(tree)(**{**tree.__dict__, "node_count": 0, "wide": None})
    with pytest.raises(ValueError, match="node_count=0"):
        widen(scene._runtime, broken)

