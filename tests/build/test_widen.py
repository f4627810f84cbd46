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
