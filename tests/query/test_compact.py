"""Scene(..., compact=True): leaves of vertex indices beside one copy of the
vertices (kernels/core/leaf.h) in place of three corners a triangle, and
bigger leaves where the SAH allows (build/config.h's COLLAPSE_COST_RATIO).
The oracle is the default tree itself: the compact tree must answer every
hit query with the same bits (t, ids, u, v, normals, points, flags,
counts, every hit, closest points, distances), before and after a refit,
and hold the same triangles, in less memory.  Where both layouts build the
same tree (small meshes, whose Morton clusters hold a triangle or two),
even the winding numbers are the same bits; where the compact tree's
leaves are bigger, its winding numbers are its own dipoles', checked
against the exact sum.  Two-level scenes (instances, masks) keep their
meshes' trees compact, with the same checks."""
import pickle

import numpy as np
import pytest
import trimesh

import built
import hlbvh_cl
from hlbvh_cl.build.morton import key_dtype
from hlbvh_cl.parallel.radix_sort import sorter
from invariants import check_tree
from point_oracle import brute_force_winding
from ray_cases import MESH_MAKERS, cube_mesh, random_rays, SceneCase
from shapes import grid_mesh


def _far_cube():
    """Coordinates near float32's top: the tree's frame scales them (core/frame)."""
    return hlbvh_cl.Mesh(cube_mesh().vertices * 1e37, cube_mesh().faces, name="far")


def _moved(mesh):
    return mesh.vertices * np.float32(1.125) + np.float32(0.01)


CASES = {
    **{name: (lambda make=make: [make()]) for name, make in MESH_MAKERS.items()},
    "several": lambda: [MESH_MAKERS["teapot"](), cube_mesh(2.0, 3.0), grid_mesh(5)],
    "far": lambda: [_far_cube()],
}


def _fields(result):
    """A query's result as named arrays."""
    if isinstance(result, np.ndarray):
        return {"": result}
    return {name: np.asarray(value) for name, value in vars(result).items()
            if isinstance(value, np.ndarray)}


def _assert_same_bits(name, base, compact):
    a, b = _fields(base), _fields(compact)
    assert a.keys() == b.keys() and a, name
    for field in a:
        assert a[field].dtype == b[field].dtype, (name, field)
        assert a[field].shape == b[field].shape, (name, field)
        # bit for bit: NaN payloads and the sign of zero included
        assert a[field].tobytes() == b[field].tobytes(), (name, field)


def _answers(scene, case, seed):
    """Every query family's answer on ``scene`` for rays and points made
    from ``case`` (rays around the box, some with finite tmax; a camera's
    coherent rays, traced as packets; points around and near the box)."""
    origins, directions = random_rays(case, 3000, seed)
    tmax = np.where(np.arange(len(origins)) % 3 == 0, 0.7, np.inf).astype(np.float32)
    centre = (case.lo + case.hi) / 2
    camera = hlbvh_cl.Camera(eye=centre + np.array([0.3, 0.4, 2.0]) * case.extent,
                             target=centre)
    eye, rays = camera.rays(48, 32)
    rng = np.random.default_rng(seed)
    points = (centre + (rng.random((1500, 3)) - 0.5) * 1.4
              * np.maximum(case.hi - case.lo, 0.1 * case.extent))
    return {
        "intersect": scene.intersect(origins, directions, tmax=tmax),
        "camera": scene.intersect(eye, rays),
        "occluded": scene.occluded(origins, directions, tmax=tmax),
        "count_intersections": scene.count_intersections(origins, directions),
        "intersect_all": scene.intersect_all(origins[:600], directions[:600]),
        "closest_points": scene.closest_points(points),
        "signed_distance": scene.signed_distance(points),
        "winding_number": scene.winding_number(points),
    }


@pytest.mark.parametrize("name", sorted(CASES))
def test_every_query_answers_the_same_bits(name):
    meshes = CASES[name]()
    base = hlbvh_cl.Scene(meshes)
    compact = hlbvh_cl.Scene(meshes, compact=True)
    # the same tree (so the same dipoles too): only the leaves' layout differs
    assert compact.stats.node_bytes == base.stats.node_bytes
    case = SceneCase(meshes, scene=base)
    for seed in (0, 1):
        for query, answer in _answers(base, case, seed).items():
            _assert_same_bits(query, answer, _answers(compact, case, seed)[query])
    # a refit re-reads the moved vertices into the compact leaves
    for scene in (base, compact):
        scene.update_vertices(0, _moved(meshes[0]))
    for query, answer in _answers(base, case, 2).items():
        _assert_same_bits(f"{query} after a refit", answer, _answers(compact, case, 2)[query])


@pytest.mark.parametrize("name", ["bunny_small", "several", "degenerate"])
def test_the_compact_tree_holds_the_same_triangles_in_less_memory(name):
    meshes = CASES[name]()
    base = hlbvh_cl.Scene(meshes)
    compact = hlbvh_cl.Scene(meshes, compact=True)
    base_tree, compact_tree = built.tree(base), built.tree(compact)
    queue = built.runtime(base).queue
    base_triangles, base_refs = base_tree.read_triangles(queue)
    compact_triangles, compact_refs = compact_tree.read_triangles(built.runtime(compact).queue)
    assert base_triangles.tobytes() == compact_triangles.tobytes()
    assert base_refs.tobytes() == compact_refs.tobytes()
    check_tree(compact)
    # the records name the vertices a refit re-reads: no vertex ids beside them
    assert base_tree.vertex_ids is not None and compact_tree.vertex_ids is None
    triangles = sum(m.triangle_count for m in meshes)
    vertices = sum(m.vertex_count for m in meshes)
    assert base.stats.triangle_bytes == 36 * triangles
    assert compact.stats.triangle_bytes == 12 * (triangles + vertices)
    assert compact.stats.node_bytes <= base.stats.node_bytes
    assert compact.stats.tree_bytes < base.stats.tree_bytes


def _dense_sphere():
    """A sphere of 20,480 triangles beside a far cube, which stretches the
    scene's box: the sphere's Morton clusters hold many triangles each, where
    the compact tree's collapse takes bigger leaves than the default's."""
    sphere = trimesh.creation.icosphere(subdivisions=5)
    return [hlbvh_cl.Mesh(sphere.vertices.astype(np.float32), sphere.faces, name="sphere"),
            cube_mesh(8.0, 8.1)]


def test_a_compact_tree_takes_bigger_leaves_and_answers_the_same_hits():
    meshes = _dense_sphere()
    base = hlbvh_cl.Scene(meshes)
    compact = hlbvh_cl.Scene(meshes, compact=True)
    # bigger leaves, so fewer of them and fewer nodes
    assert compact.stats.leaves < 0.95 * base.stats.leaves
    assert compact.stats.node_bytes < 0.95 * base.stats.node_bytes
    check_tree(compact)
    case = SceneCase(meshes[:1], scene=base)  # rays and points about the sphere
    for seed in (0, 1):
        answers, compact_answers = _answers(base, case, seed), _answers(compact, case, seed)
        assert (answers["intersect"].geom_id == 0).sum() > 100  # the sphere is hit
        for query in ("intersect", "camera", "occluded", "count_intersections", "intersect_all",
                      "closest_points"):
            _assert_same_bits(query, answers[query], compact_answers[query])
        _assert_same_bits("|signed_distance|", np.abs(answers["signed_distance"]),
                          np.abs(compact_answers["signed_distance"]))
    # Winding numbers: each tree's far field is its own dipoles, within 0.05 of
    # the exact sum (docs/queries.md), near the sphere's surface too.
    rng = np.random.default_rng(7)
    directions = rng.normal(size=(1200, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii = np.concatenate([rng.uniform(0.0, 3.0, 600), 1.0 + rng.uniform(-0.05, 0.05, 600)])
    points = (directions * radii[:, None]).astype(np.float32)
    exact = sum(brute_force_winding(m.vertices, m.faces, points) for m in meshes)
    assert ((exact > 0.9).sum() > 300) and ((exact < 0.1).sum() > 300)
    for scene in (base, compact):
        np.testing.assert_allclose(scene.winding_number(points), exact, atol=0.05)
        clear = np.abs(exact - 0.5) > 0.1
        assert np.array_equal(scene.contains(points)[clear], exact[clear] > 0.5)


def test_a_compact_scene_keeps_its_tree_only():
    """A compact tree's leaves hold the vertices, so a compact scene keeps no
    copy of its build's input on the device (uploaded again for a rebuild)
    and lets its build's scratch go, the sorter's pair too, rather than keep
    it for rebuilds, as a default scene does; rebuilt, and refit after a
    move, it answers as the default tree does."""
    meshes = CASES["several"]()
    rt = built.runtime(hlbvh_cl.Scene(meshes[:1]))
    rt.pool.clear()
    compact = hlbvh_cl.Scene(meshes, compact=True)
    keys = sorter(rt, key_dtype(compact.stats.morton_bits))
    assert rt.pool.free_bytes == 0 and keys.scratch_keys is None
    base = hlbvh_cl.Scene(meshes)
    # the default build's scratch, for its rebuilds
    assert rt.pool.free_bytes > 0 and keys.scratch_keys is not None
    case = SceneCase(meshes, scene=base)
    for scene in (base, compact):
        scene.update_vertices(2, _moved(meshes[2]))
        scene.rebuild()
        scene.update_vertices(0, _moved(meshes[0]))
    for query, answer in _answers(base, case, 3).items():
        _assert_same_bits(f"{query} after a rebuild and a refit", answer,
                          _answers(compact, case, 3)[query])


def test_spheres_beside_a_compact_tree_answer_the_same_bits():
    meshes = [MESH_MAKERS["teapot"](), grid_mesh(6)]
    spheres = [[0.5, 0.5, 0.5, 0.3], [-1.0, 0.2, 0.4, 0.25]]
    base = hlbvh_cl.Scene(meshes, spheres=spheres)
    compact = hlbvh_cl.Scene(meshes, spheres=spheres, compact=True)
    case = SceneCase(meshes, scene=base)
    origins, directions = random_rays(case, 4000, 5)
    found = base.intersect(origins, directions)
    assert (found.geom_id >= len(meshes)).any() and (found.geom_id == 0).any()
    _assert_same_bits("intersect", found, compact.intersect(origins, directions))
    _assert_same_bits("occluded", base.occluded(origins, directions),
                      compact.occluded(origins, directions))


def test_compact_scenes_pickle_and_render_as_compact():
    mesh = MESH_MAKERS["bunny_small"]()
    scene = hlbvh_cl.Scene([mesh], compact=True)
    again = pickle.loads(pickle.dumps(scene))
    assert again.compact and "compact=True" in repr(again)
    assert again.stats.triangle_bytes == scene.stats.triangle_bytes
    assert pickle.loads(pickle.dumps(hlbvh_cl.Scene([mesh]))).compact is False
    camera = hlbvh_cl.Camera(eye=(0, 0.1, 0.4), target=(0, 0.1, 0))
    images = [hlbvh_cl.Renderer(s).render(camera, 64, 48)
              for s in (hlbvh_cl.Scene([mesh]), again)]
    assert images[0].tobytes() == images[1].tobytes() and images[0].any()


def _placed(meshes, instances):
    """Each instance's mesh in the world, as a flat mesh (for SceneCase's box)."""
    return [hlbvh_cl.Mesh(meshes[m].vertices @ t[:3, :3].T + t[:3, 3], meshes[m].faces)
            for m, t in instances]


def _instances(count: int, seed: int):
    """(mesh, 4x4 map) pairs over three meshes: shears, scales, a mirror."""
    rng = np.random.default_rng(seed)
    placed = []
    for k in range(count):
        t = np.eye(4)
        t[:3, :3] += rng.normal(scale=0.2, size=(3, 3))
        t[:3, 3] = rng.normal(scale=2.5, size=3)
        if k == 1:
            t[0, :3] *= -1  # a mirror: its hits' normals flip with it
        placed.append((k % 3, t))
    return placed


def test_instanced_compact_scenes_answer_the_same_bits():
    """The meshes' trees of a two-level scene with compact leaves (all the
    trees' records, then all their vertices: kernels/build/instances.cl)
    answer as the default ones, bit for bit, and after a mesh moves (its
    tree rebuilt) and the instances move (the top rebuilt)."""
    teapot = MESH_MAKERS["teapot"]()  # 32 wide: brought to the others' size
    meshes = [hlbvh_cl.Mesh(teapot.vertices / 16, teapot.faces), cube_mesh(2.0, 3.0),
              grid_mesh(5)]
    instances = _instances(9, 3)
    base = hlbvh_cl.Scene(meshes, instances=instances)
    compact = hlbvh_cl.Scene(meshes, instances=instances, compact=True)
    case = SceneCase(_placed(meshes, instances), scene=base)
    found = base.intersect(*random_rays(case, 3000, 0))
    # every mesh is hit, through several instances
    assert set(np.unique(found.geom_id)) == {-1, 0, 1, 2}
    assert len(np.unique(found.instance_id[found.hit])) > 6
    for query, answer in _answers(base, case, 0).items():
        _assert_same_bits(query, answer, _answers(compact, case, 0)[query])
    for scene in (base, compact):
        scene.update_vertices(1, _moved(meshes[1]))
        scene.set_transforms([0, 4], [instances[4][1], instances[0][1]])
    for query, answer in _answers(base, case, 1).items():
        _assert_same_bits(f"{query} after a change", answer, _answers(compact, case, 1)[query])
    # the meshes' leaves: 12 bytes a triangle and a vertex, not 36 a triangle
    stored, joined = built.tree(base).meshes, built.tree(compact).meshes
    triangles = sum(m.triangle_count for m in meshes)
    vertices = sum(m.vertex_count for m in meshes)
    assert stored.memory()["triangle_bytes"] == 36 * triangles
    assert joined.memory()["triangle_bytes"] == 12 * (triangles + vertices)
    assert joined.memory()["node_bytes"] <= stored.memory()["node_bytes"]


def test_masked_compact_scenes_answer_the_same_bits():
    """A flat scene with masks is traced as one instance per mesh: its
    compact trees answer as the default ones, masks applied."""
    meshes = [MESH_MAKERS["teapot"](), grid_mesh(6)]
    base = hlbvh_cl.Scene(meshes, masks=[1, 2])
    compact = hlbvh_cl.Scene(meshes, masks=[1, 2], compact=True)
    case = SceneCase(meshes, scene=base)
    origins, directions = random_rays(case, 3000, 4)
    for mask in (1, 2, 3):
        found = base.intersect(origins, directions, mask=mask)
        assert found.hit.any()
        _assert_same_bits(f"intersect, mask {mask}", found,
                          compact.intersect(origins, directions, mask=mask))
        _assert_same_bits(f"occluded, mask {mask}", base.occluded(origins, directions, mask=mask),
                          compact.occluded(origins, directions, mask=mask))


def test_instanced_compact_scenes_pickle_and_render_as_compact():
    meshes = [MESH_MAKERS["bunny_small"](), grid_mesh(4)]
    instances = [(0, np.eye(4)), (1, np.diag([0.3, 1.0, 0.3, 1.0]))]
    scene = hlbvh_cl.Scene(meshes, instances=instances, compact=True)
    again = pickle.loads(pickle.dumps(scene))
    assert again.compact and "compact=True" in repr(again)
    assert built.tree(again).indexed
    camera = hlbvh_cl.Camera(eye=(0, 0.1, 0.4), target=(0, 0.1, 0))
    images = [hlbvh_cl.Renderer(s).render(camera, 64, 48)
              for s in (hlbvh_cl.Scene(meshes, instances=instances), again)]
    assert images[0].tobytes() == images[1].tobytes() and images[0].any()


def test_compact_is_a_flag():
    with pytest.raises(TypeError, match="compact must be True or False, got 'yes'"):
        hlbvh_cl.Scene([cube_mesh()], compact="yes")
