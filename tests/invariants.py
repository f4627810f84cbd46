"""Tree invariants, checked in numpy on every build the suite makes.

Independent of the kernels: it reads the flat tree back and re-derives
everything from the scene's meshes.
"""
from __future__ import annotations

import numpy as np

from hlbvh_cl import layout
from hlbvh_cl.frame import to_frame


def _tri_boxes(tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pts = np.stack([tris["v0"], tris["v1"], tris["v2"]], axis=1)
    return pts.min(axis=1), pts.max(axis=1)


def _area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    d = np.maximum(hi.astype(np.float64) - lo.astype(np.float64), 0.0)
    return 2.0 * (d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0])


def check_tree(scene, exact_boxes: bool = True) -> dict:
    """Assert every invariant of ``scene``'s tree; return what was derived."""
    q = scene._runtime.queue
    tree = scene._tree
    nodes = tree.read_nodes(q)
    tris, refs = tree.read_triangles(q)
    parents = np.empty(tree.node_count, np.int32)
    import pyopencl as cl
    cl.enqueue_copy(q, parents, tree.parents)
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
        # in the tree's frame: the scene's coordinates times tree.scale (hlbvh_cl.frame)
        corners = to_frame(mesh.vertices, scene._tree.scale)[mesh.faces[refs["prim_id"][sel]]]
        for k, name in enumerate(("v0", "v1", "v2")):
            assert np.array_equal(tris[name][sel], corners[:, k]), f"triangle {name} != mesh {g}"

    tri_lo, tri_hi = _tri_boxes(tris)
    leaf_slots = []
    visited = np.zeros(tree.node_count, np.int64)
    depth = 0
    leaves = 0
    sah = 0.0
    # breadth-first from the root, one level at a time (vectorised)
    level = np.array([0])
    assert parents[0] == -1
    node_lo = np.full((tree.node_count, 3), np.inf, np.float32)
    node_hi = np.full((tree.node_count, 3), -np.inf, np.float32)
    while len(level):
        depth += 1
        visited[level] += 1
        rec = nodes[level]
        node_lo[level] = np.minimum(rec["left_lo"], rec["right_lo"])
        node_hi[level] = np.maximum(rec["left_hi"], rec["right_hi"])
        sah += _area(node_lo[level], node_hi[level]).sum()
        children = []
        for side in ("left", "right"):
            idx, cnt = rec[side], rec[f"{side}_count"]
            slot_lo, slot_hi = rec[f"{side}_lo"], rec[f"{side}_hi"]
            interior = (cnt == 0) & (idx != layout.EMPTY_CHILD)
            leaf = cnt > 0
            empty = (cnt == 0) & (idx == layout.EMPTY_CHILD)
            assert not (empty & (level != 0)).any(), "an empty child below the root"
            if empty.any():
                assert n == 1 or (nodes[0]["left_count"] == n), "empty child in a multi-leaf tree"
            leaf_slots.append((idx[leaf], cnt[leaf], slot_lo[leaf], slot_hi[leaf]))
            leaves += int(leaf.sum())
            kids = idx[interior]
            assert ((kids > 0) & (kids < tree.node_count)).all(), "child index out of range"
            assert np.array_equal(parents[kids], level[interior]), "parent link disagrees"
            children.append((kids, slot_lo[interior], slot_hi[interior]))
        next_level = np.concatenate([c[0] for c in children])
        if len(next_level):
            kid_rec = nodes[next_level]
            kid_lo = np.minimum(kid_rec["left_lo"], kid_rec["right_lo"])
            kid_hi = np.maximum(kid_rec["left_hi"], kid_rec["right_hi"])
            slot_lo = np.concatenate([c[1] for c in children])
            slot_hi = np.concatenate([c[2] for c in children])
            assert (slot_lo <= kid_lo).all() and (kid_hi <= slot_hi).all(), \
                "a box does not contain its child"
            if exact_boxes:
                assert np.array_equal(slot_lo, kid_lo) and np.array_equal(slot_hi, kid_hi), \
                    "a child box in its parent is not the child's own box"
        level = next_level
    assert (visited == 1).all(), "a node is unreachable or reached twice"

    # leaves: their ranges tile [0, n) exactly, and each box bounds its triangles
    first = np.concatenate([x[0] for x in leaf_slots]).astype(np.int64)
    count = np.concatenate([x[1] for x in leaf_slots]).astype(np.int64)
    slot_lo = np.concatenate([x[2] for x in leaf_slots])
    slot_hi = np.concatenate([x[3] for x in leaf_slots])
    order = np.argsort(first, kind="stable")
    first, count, slot_lo, slot_hi = first[order], count[order], slot_lo[order], slot_hi[order]
    assert first[0] == 0 and count.sum() == n and (count >= 1).all()
    assert np.array_equal(first[1:], first[:-1] + count[:-1]), \
        "a triangle is in no leaf, or in two"
    lo = np.minimum.reduceat(tri_lo, first, axis=0)
    hi = np.maximum.reduceat(tri_hi, first, axis=0)
    assert (slot_lo <= lo).all() and (hi <= slot_hi).all(), "a leaf box misses a triangle"
    if exact_boxes:
        assert np.array_equal(slot_lo, lo) and np.array_equal(slot_hi, hi), "a leaf box is not tight"
    sah += (count * _area(slot_lo, slot_hi)).sum()
    stats = scene.stats
    assert stats.triangles == n
    assert stats.nodes == tree.node_count
    assert stats.leaves == leaves == tree.leaf_count
    assert stats.depth == depth == tree.depth
    root_area = _area(node_lo[0], node_hi[0])
    if root_area > 0 and stats.refit_ms is None:  # a refit keeps the built cost
        assert np.isclose(stats.sah_cost, sah / root_area, rtol=1e-3), \
            (stats.sah_cost, sah / root_area)
    if scene.builder == "lbvh" and n > 1:
        assert tree.node_count == n - 1, "the plain LBVH must have n-1 internal nodes"
        assert leaves == n
    if scene.builder == "hlbvh":
        assert leaves <= n
    return {"nodes": nodes, "triangles": tris, "refs": refs, "root_lo": node_lo[0],
            "root_hi": node_hi[0]}
