"""The wide tree (hlbvh_cl/build/widen.py, kernels/build/widen.cl) and its refit
(kernels/build/refit.cl), checked in numpy by tests/support/invariants.py against the
scene's own triangles."""
from __future__ import annotations


import numpy as np
import pyopencl as cl
import pytest

import hlbvh_cl
from hlbvh_cl.core import layout
from hlbvh_cl.build.widen import widen
import built
from invariants import check_tree
from shapes import deep_scene, grid_mesh
import places

MESHES = places.MESHES


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
    # deeper than the first round of wide levels: the build launches a second
    "bunny_small on a ground plane": deep_scene,
}


@pytest.mark.parametrize("builder", ["hlbvh", "lbvh"])
@pytest.mark.parametrize("name", list(SCENES))
def test_wide_tree_invariants(name, builder):
    scene = hlbvh_cl.Scene(SCENES[name](), builder=builder)
    check_tree(scene)
    times = scene.stats.times_ms
    assert times["widen"] >= 0
    assert scene.stats.device_ms == pytest.approx(sum(times.values()))


def test_rebuilds_give_the_same_wide_tree():
    scene = hlbvh_cl.Scene([_mesh("knight")])
    q = built.runtime(scene).queue
    first = built.tree(scene).read_nodes(q).tobytes()
    scene.rebuild()
    check_tree(scene)
    assert built.tree(scene).read_nodes(q).tobytes() == first


def test_update_vertices_refits_the_wide_tree():
    """After a refit the topology stays and every box is again the exact
    union of what it holds (the moved triangles); moving them back gives the
    built tree, bit for bit."""
    knight = _mesh("knight")
    scene = hlbvh_cl.Scene([knight, _mesh("teapot")])
    q = built.runtime(scene).queue
    before = built.tree(scene).read_nodes(q)
    v = knight.vertices.astype(np.float64)
    moved = v * 1.3 + 0.1 * np.sin(5 * v[:, [2, 0, 1]]) * np.ptp(v, axis=0)
    scene.update_vertices(0, moved)
    after = check_tree(scene)["nodes"]
    assert np.array_equal(before["child"], after["child"])
    assert np.array_equal(before["count"], after["count"])
    assert not np.array_equal(before["lo_x"], after["lo_x"]), "the boxes should have moved"
    scene.update_vertices(0, knight.vertices)
    check_tree(scene)
    assert built.tree(scene).read_nodes(q).tobytes() == before.tobytes()


NODE_COST = layout.CONSTANTS["WIDE_NODE_COST"]
TRIANGLE_COST = layout.CONSTANTS["WIDE_TRIANGLE_COST"]


def _area(lo, hi) -> float:
    d = np.maximum(np.asarray(hi, np.float64) - np.asarray(lo, np.float64), 0.0)
    return float(2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0]))


def _random_bvh2(rng, leaves: int) -> np.ndarray:
    """A random binary tree over `leaves` leaf runs of 1-3 triangles, laid out
    left to right, so that every subtree's triangles are one run; each leaf's
    box is random, each node's the union of its children's."""
    counts = rng.integers(1, 4, leaves)
    firsts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    lo = rng.uniform(0, 1, (leaves, 3)).astype(np.float32)
    hi = lo + rng.uniform(0.01, 0.3, (leaves, 3)).astype(np.float32)
    nodes = np.zeros(leaves - 1, layout.FLAT_NODE)
    made = [0]

    def build(a, b):  # leaves [a, b): returns (index, count, lo, hi) of the slot
        if b - a == 1:
            return int(firsts[a]), int(counts[a]), lo[a], hi[a]
        me = made[0]
        made[0] += 1
        split = int(rng.integers(a + 1, b))
        sides = build(a, split), build(split, b)
        for name, (index, count, box_lo, box_hi) in zip(("left", "right"), sides):
            nodes[me][name], nodes[me][f"{name}_count"] = index, count
            nodes[me][f"{name}_lo"], nodes[me][f"{name}_hi"] = box_lo, box_hi
        return (me, 0, np.minimum(sides[0][2], sides[1][2]),
                np.maximum(sides[0][3], sides[1][3]))
    build(0, leaves)
    return nodes


def _least_cost(nodes: np.ndarray) -> float:
    """The least SAH cost of any 8-wide tree cut from the BVH2, by enumerating
    every cut of at most 8 slots below each wide node (float64; an oracle
    independent of the device's dynamic program over slot budgets)."""
    arity = layout.WIDE_ARITY

    def slots(node):
        out = []
        for side in ("left", "right"):
            box = _area(nodes[node][f"{side}_lo"], nodes[node][f"{side}_hi"])
            out.append((int(nodes[node][side]), int(nodes[node][f"{side}_count"]), box))
        return out

    def triangles(node):  # the run's length below a node (runs are contiguous here)
        return sum(count if count else triangles(child) for child, count, _ in slots(node))

    def cuts(child, count, area):  # every cut of a slot: lists of (cost of each slot)
        own = [TRIANGLE_COST * area * count] if count else [as_node(child)]
        if not count and triangles(child) <= layout.MAX_LEAF_SIZE:
            own.append(TRIANGLE_COST * area * triangles(child))
        found = [[min(own)]]
        if not count:
            left, right = (cuts(*slot) for slot in slots(child))
            found += [a + b for a in left for b in right if len(a) + len(b) <= arity]
        return found

    memo = {}

    def as_node(node):
        if node not in memo:
            left, right = (cuts(*slot) for slot in slots(node))
            area = _area(np.minimum(nodes[node]["left_lo"], nodes[node]["right_lo"]),
                         np.maximum(nodes[node]["left_hi"], nodes[node]["right_hi"]))
            memo[node] = NODE_COST * area + min(sum(a) + sum(b) for a in left for b in right
                                                if len(a) + len(b) <= arity)
        return memo[node]
    return as_node(0)


def _wide_cost(wide: np.ndarray) -> float:
    cost = 0.0
    for node in wide:
        lanes = [(_area([node["lo_x"][k], node["lo_y"][k], node["lo_z"][k]],
                        [node["hi_x"][k], node["hi_y"][k], node["hi_z"][k]]), node["count"][k])
                 for k in range(layout.WIDE_ARITY) if node["child"][k] != layout.EMPTY_CHILD]
        cost += NODE_COST * _area(
            [min(node[f"lo_{a}"][k] for k in range(layout.WIDE_ARITY)) for a in "xyz"],
            [max(node[f"hi_{a}"][k] for k in range(layout.WIDE_ARITY)) for a in "xyz"])
        cost += sum(TRIANGLE_COST * area * int(count) for area, count in lanes if count)
    return cost


@pytest.mark.parametrize("seed", range(6))
def test_the_wide_tree_is_the_cut_of_least_sah_cost(seed):
    """The collapse (widen.cl's wide_costs and choose_slots, Ylitie et al.
    2017) against every possible cut of a random BVH2 of 20 leaf runs: its
    wide tree costs the least any does, and its leaves still tile the
    triangles, merged runs of at most MAX_LEAF_SIZE."""
    rng = np.random.default_rng(seed)
    flat = _random_bvh2(rng, 20)
    rt = built.runtime(hlbvh_cl.Scene([_one_triangle()]))
    buffer = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                       hostbuf=flat)
    nodes, levels, events = widen(rt, buffer, len(flat))
    wide = np.empty(levels[-1][0] + levels[-1][1], layout.WIDE_NODE)
    cl.enqueue_copy(rt.queue, wide, nodes, wait_for=events[-1:], is_blocking=True)
    leaf = wide["count"] > 0
    first, count = wide["child"][leaf], wide["count"][leaf].astype(np.int64)
    order = np.argsort(first)
    total = int(flat["left_count"].sum() + flat["right_count"].sum())
    assert first[order][0] == 0 and count.sum() == total
    assert np.array_equal(first[order][1:], (first[order] + count[order])[:-1])
    assert count.max() <= layout.MAX_LEAF_SIZE
    assert _wide_cost(wide) == pytest.approx(_least_cost(flat), rel=1e-5)


def test_small_subtrees_merge_into_leaves_and_nodes_fill():
    """On a real mesh the least-cost cut merges small subtrees of the binary
    tree into wide leaves and fills the nodes: the greedy collapse it
    replaced (open the largest slot first) used 4.2 of 8 slots a node here."""
    scene = hlbvh_cl.Scene([_mesh("knight")])
    nodes = check_tree(scene)["nodes"]
    used = (nodes["child"] != layout.EMPTY_CHILD) | (nodes["count"] > 0)
    assert (nodes["count"] > 0).sum() < scene.stats.leaves
    assert used.sum(axis=1).mean() >= 6.0


def test_a_bvh2_that_is_not_a_tree_is_refused():
    """Two nodes that hold each other (and a leaf each): the levels would
    never end; the device finds more wide nodes than BVH2 nodes and the
    host says so."""
    scene = hlbvh_cl.Scene([_one_triangle()])
    rt = built.runtime(scene)
    nodes = np.zeros(2, layout.FLAT_NODE)
    nodes["left"] = [1, 0]
    nodes["right"], nodes["right_count"] = 0, 1
    nodes["left_lo"] = nodes["right_lo"] = 0.0
    nodes["left_hi"] = nodes["right_hi"] = 1.0
    buffer = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                       hostbuf=nodes)
    with pytest.raises(RuntimeError, match="not a tree"):
        widen(rt, buffer, 2)


def test_a_tree_without_nodes_is_refused():
    scene = hlbvh_cl.Scene([_one_triangle()])
    with pytest.raises(ValueError, match="0 nodes"):
        widen(built.runtime(scene), built.tree(scene).nodes, 0)
