"""Scenes and meshes through pickle (hlbvh_cl.travel): every kind of scene
arrives with identical hits, is built once per process however many copies
arrive, and a changed scene leaves the cache."""
from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest
import trimesh

import hlbvh_cl
from hlbvh_cl import travel

import built


def _sphere(scale=1.0):
    m = trimesh.creation.icosphere(subdivisions=2)
    return hlbvh_cl.Mesh(m.vertices * scale, m.faces, name="sphere")


def _box():
    m = trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    return hlbvh_cl.Mesh(m.vertices, m.faces, name="box")


def _kinds(device):
    maps = [np.hstack([np.eye(3) * s, [[x], [0.2], [0]]]) for s, x in ((1.0, 0), (0.5, 2.5),
                                                                      (-1.0, -2.5))]
    yield "flat", hlbvh_cl.Scene([_sphere(), _box()], device=device)
    yield "lbvh, 63-bit keys", hlbvh_cl.Scene([_sphere()], device=device, builder="lbvh",
                                             morton_bits=63)
    yield "masked", hlbvh_cl.Scene([_sphere(), _box()], device=device, masks=[1, 2])
    yield "instanced", hlbvh_cl.Scene([_sphere(), _box()], device=device, masks=[1, 2, 3],
                                      instances=[(k % 2, a) for k, a in enumerate(maps)])
    yield "huge coordinates", hlbvh_cl.Scene([_sphere(1e30)], device=device)


def _rays(scene, count=2000, seed=0):
    rng = np.random.default_rng(seed)
    tree = built.tree(scene)
    lo, hi = tree.bounds_lo / tree.scale, tree.bounds_hi / tree.scale
    centre, size = (lo + hi) / 2, float(np.max(hi - lo))
    origins = (centre + rng.normal(size=(count, 3)) * size * 2).astype(np.float32)
    targets = centre + rng.uniform(-0.5, 0.5, (count, 3)) * size
    return origins, (targets - origins).astype(np.float32)


def test_mesh_pickles_as_its_arrays_and_name():
    mesh = _box()
    back = pickle.loads(pickle.dumps(mesh))
    assert back.name == "box"
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.faces, mesh.faces)


def test_every_kind_of_scene_round_trips_with_identical_hits(suite_device):
    travel.clear()
    for name, scene in _kinds(suite_device):
        back = pickle.loads(pickle.dumps(scene))
        assert back is not scene and back.device.id == scene.device.id, name
        origins, directions = _rays(scene)
        a, b = scene.intersect(origins, directions), back.intersect(origins, directions)
        assert a.hit.sum() > 100, name
        for field in ("t", "prim_id", "geom_id", "instance_id", "u", "v", "normal"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field),
                                          err_msg=f"{name}: {field}")
        np.testing.assert_array_equal(scene.count_intersections(origins, directions, mask=1),
                                      back.count_intersections(origins, directions, mask=1))
        assert repr(back) == repr(scene)
    travel.clear()


def test_a_moved_scene_travels_as_moved(suite_device):
    scene = hlbvh_cl.Scene([_sphere(), _box()], device=suite_device)
    scene.update_vertices(1, scene.meshes[1].vertices + np.float32([3, 0, 0]))
    back = pickle.loads(pickle.dumps(scene))
    np.testing.assert_array_equal(back.meshes[1].vertices, scene.meshes[1].vertices)
    instanced = hlbvh_cl.Scene([_box()], device=suite_device,
                               instances=[(0, np.eye(3, 4)), (0, np.eye(3, 4))])
    instanced.set_transforms([1], np.hstack([np.eye(3), [[4], [0], [0]]])[None])
    back = pickle.loads(pickle.dumps(instanced))
    np.testing.assert_array_equal(back.transforms, instanced.transforms)


def test_scenes_of_one_geometry_shaded_otherwise_travel_apart(suite_device):
    """Given normals and face_normals are content: a scene differing only
    in them pickles under a key of its own (the cache had handed back the
    first scene restored for the second), and keeps them through a pickle
    and through update_vertices (which had dropped given normals)."""
    travel.clear()
    sphere = _sphere()
    tilted = np.tile(np.float32([0.0, 0.6, 0.8]), (sphere.vertex_count, 1))
    variants = {"computed": hlbvh_cl.Mesh(sphere.vertices, sphere.faces, name="sphere"),
                "face": hlbvh_cl.Mesh(sphere.vertices, sphere.faces, name="sphere",
                                      face_normals=True),
                "given": hlbvh_cl.Mesh(sphere.vertices, sphere.faces, name="sphere",
                                       normals=tilted)}
    scenes = {k: hlbvh_cl.Scene([m], device=suite_device) for k, m in variants.items()}
    backs = {k: pickle.loads(pickle.dumps(s)) for k, s in scenes.items()}
    assert travel.cached_count() == 3
    for kind, back in backs.items():
        mesh, original = back.meshes[0], variants[kind]
        assert (mesh.face_normals, mesh.has_file_normals) == \
            (original.face_normals, original.has_file_normals), kind
        np.testing.assert_array_equal(mesh.normals, original.normals, err_msg=kind)
    given = scenes["given"]
    given.update_vertices(0, given.meshes[0].vertices)
    assert given.meshes[0].has_file_normals
    np.testing.assert_array_equal(given.meshes[0].normals, tilted)
    given.update_vertices(0, given.meshes[0].vertices * np.float32(2), normals=-tilted)
    np.testing.assert_array_equal(given.meshes[0].normals, -tilted)
    computed = scenes["computed"]
    moved = computed.meshes[0].vertices * np.float32([1.0, 2.0, 1.0])
    computed.update_vertices(0, moved)  # computed normals follow the vertices
    np.testing.assert_array_equal(computed.meshes[0].normals,
                                  hlbvh_cl.Mesh(moved, sphere.faces).normals)
    travel.clear()


def _down(scene):
    """t of a ray straight down the z axis onto the scene's first mesh."""
    return float(scene.intersect([0.0, 0.0, 5.0], [0.0, 0.0, -1.0]).t)


def test_a_process_builds_a_scene_once_and_each_copy_changes_alone(suite_device):
    travel.clear()
    scene = hlbvh_cl.Scene([_sphere()], device=suite_device,
                           instances=[(0, np.eye(3, 4))])
    data = pickle.dumps(scene)
    first, second = pickle.loads(data), pickle.loads(data)
    assert first is not second and travel.cached_count() == 1  # two objects, one build
    first.set_transforms([0], np.hstack([np.eye(3), [[0], [0], [-1]]])[None])
    np.testing.assert_array_equal(second.transforms, np.eye(3, 4)[None])
    assert _down(first) == pytest.approx(5.0, abs=1e-5)
    assert _down(second) == pytest.approx(4.0, abs=1e-5)
    third = pickle.loads(data)  # the cached scene never changed
    np.testing.assert_array_equal(third.transforms, np.eye(3, 4)[None])
    assert _down(third) == pytest.approx(4.0, abs=1e-5) and travel.cached_count() == 1
    travel.clear()


@pytest.mark.parametrize("change", ["update_vertices", "rebuild"])
def test_copies_of_a_scene_are_independent(suite_device, change):
    travel.clear()
    scene = hlbvh_cl.Scene([_sphere(), _box()], device=suite_device)
    a, b = copy.deepcopy(scene), copy.copy(scene)
    assert len({id(scene), id(a), id(b)}) == 3
    if change == "update_vertices":
        a.update_vertices(0, scene.meshes[0].vertices + np.float32([0, 0, -1]))
        assert _down(a) == pytest.approx(4.75, abs=1e-5)  # the box's top now
    else:
        a.rebuild()  # its own trees: the ones b shares are not released
        assert _down(a) == pytest.approx(4.0, abs=1e-5)
    for other in (scene, b, pickle.loads(pickle.dumps(scene))):
        assert _down(other) == pytest.approx(4.0, abs=1e-5)
        np.testing.assert_array_equal(other.meshes[0].vertices, scene.meshes[0].vertices)
    travel.clear()


@pytest.mark.parametrize("move", [(0, 0, -1), (0, 0, 1e8)])  # a refit; a rebuild
def test_a_scene_that_changes_after_giving_views_leaves_them_as_they_were(suite_device, move):
    """The one that changes first builds trees of its own, the original too:
    a refit in place, or a move into a new frame (a rebuild that releases
    the old trees), would otherwise reach its views."""
    scene = hlbvh_cl.Scene([_sphere(), _box()], device=suite_device)
    views = [scene.view(), scene.view()]
    scene.update_vertices(0, scene.meshes[0].vertices + np.float32(move))
    assert _down(scene) == pytest.approx(4.75, abs=1e-4)  # the box's top now
    for view in views:
        assert _down(view) == pytest.approx(4.0, abs=1e-5)
        view.rebuild()
        assert _down(view) == pytest.approx(4.0, abs=1e-5)


def test_meshes_cannot_be_replaced_behind_the_scene(suite_device):
    scene = hlbvh_cl.Scene([_box()], device=suite_device)
    with pytest.raises(TypeError):
        scene.meshes[0] = _sphere()
    with pytest.raises(AttributeError):
        scene.meshes.append(_sphere())


@pytest.mark.parametrize("device", [None, "pocl"])
def test_the_device_travels_as_asked(device, suite_device):
    if device is not None and not suite_device.id.startswith(device):
        pytest.skip("the suite's device is another")
    scene = hlbvh_cl.Scene([_box()], device=device)
    with scene.borrow() as lent:
        assert lent.spec.device == device


def test_a_restore_that_fails_leaves_nothing_behind(suite_device):
    """A restore whose build raises (a device gone, Ctrl-C) takes its
    per-spec lock entry away with it, so failures do not pile up."""
    with hlbvh_cl.Scene([_box()], device=suite_device).borrow() as lent:
        spec = lent.spec

    def failing(*args, **kwargs):
        raise KeyboardInterrupt

    for _ in range(3):
        with pytest.raises(KeyboardInterrupt):
            travel.restore(spec, failing)
    assert spec.key not in travel.building_keys()
