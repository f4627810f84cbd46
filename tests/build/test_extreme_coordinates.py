"""Finite coordinates of any magnitude (issue 22): a scene at 1e-30 or 1e30
gives the hits a float64 brute force gives, never t = inf, a NaN normal or u, v
outside [0, 1], and a tree as deep as the same scene at 1.  Scenes outside
[2^-24, 2^24] are built in a frame scaled by a power of two
(hlbvh_cl/core/frame.py), which is exact: at a power-of-two scale the hits are
those of the unscaled scene, bit for bit."""
from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import trimesh

import hlbvh_cl
from hlbvh_cl.core import frame
import built
from oracle import brute_force_intersect


def sphere_and_ground():
    sphere = trimesh.creation.icosphere(subdivisions=3)
    ground = trimesh.creation.box(extents=(4.0, 0.2, 4.0))
    ground.apply_translation((0.0, -1.2, 0.0))
    return [(np.asarray(m.vertices, np.float64), np.asarray(m.faces)) for m in (sphere, ground)]


def rays(count, rng):
    """Rays from a shell around the scene towards points near it; most hit."""
    origins = rng.normal(size=(count, 3))
    origins *= 3.0 / np.linalg.norm(origins, axis=1, keepdims=True)
    targets = rng.uniform(-1.3, 1.3, (count, 3))
    return origins, targets - origins


def scene_at(scale, **kwargs):
    return hlbvh_cl.Scene([hlbvh_cl.Mesh(v * scale, f) for v, f in sphere_and_ground()], **kwargs)


@pytest.mark.parametrize("scale", [1e-30, 1e-20, 1e-19, 1e-10, 1e10, 1e20, 1e30, 3e37])
def test_hits_at_any_scale_match_float64(scale):
    rng = np.random.default_rng(7)
    scene = scene_at(scale)
    origins, directions = rays(2000, rng)
    origins = (origins * scale).astype(np.float32)
    directions = (directions * scale).astype(np.float32)
    hits = scene.intersect(origins, directions)
    meshes = scene.meshes
    vertices = np.concatenate([m.vertices for m in meshes])
    faces = np.concatenate([meshes[0].faces, meshes[1].faces + meshes[0].vertex_count])
    expected = brute_force_intersect(vertices, faces, origins, directions)
    hit = hits.hit
    assert hit.sum() > 1000
    assert np.array_equal(hit, expected["t"] < np.inf)
    assert np.all(np.isfinite(hits.t[hit])) and np.all(np.isfinite(hits.normal[hit]))
    np.testing.assert_allclose(hits.t[hit], expected["t"][hit], rtol=1e-5)
    assert np.all((hits.u[hit] >= 0) & (hits.u[hit] <= 1) & (hits.v[hit] >= 0) & (hits.v[hit] <= 1))
    np.testing.assert_allclose(np.linalg.norm(hits.normal[hit], axis=1), 1.0, rtol=1e-5)
    assert np.array_equal(scene.occluded(origins, directions), hit)


@pytest.mark.parametrize("exponent", [-100, -60, 70, 100])
def test_a_power_of_two_scale_changes_nothing(exponent):
    """The same scene at 2^k: the same tree (depth, SAH cost) and the same
    hits, bit for bit, t included (origins and directions scale alike)."""
    rng = np.random.default_rng(8)
    origins, directions = (a.astype(np.float32) for a in rays(3000, rng))
    scale = 2.0 ** exponent
    plain, scaled = scene_at(1.0), scene_at(scale)
    assert built.tree(scaled).scale != 1.0 and built.tree(plain).scale == 1.0
    for key in ("depth", "nodes", "leaves", "sah_cost"):
        assert getattr(scaled.stats, key) == getattr(plain.stats, key), key
    expected = plain.intersect(origins, directions)
    got = scaled.intersect((origins.astype(np.float64) * scale).astype(np.float32),
                           (directions.astype(np.float64) * scale).astype(np.float32))
    for name in ("t", "prim_id", "geom_id", "u", "v", "normal"):
        assert np.array_equal(getattr(got, name), getattr(expected, name)), name


def test_renders_at_any_scale_are_the_same_image():
    camera = hlbvh_cl.Camera((0.0, 1.0, 4.0), (0.0, -0.3, 0.0))
    expected = hlbvh_cl.Renderer(scene_at(1.0)).render(camera, 32, 24, shading="ao", ao_samples=2)
    for scale in (2.0**-90, 2.0**90):
        far = hlbvh_cl.Camera(tuple(np.multiply(camera.eye, scale)),
                              tuple(np.multiply(camera.target, scale)))
        image = hlbvh_cl.Renderer(scene_at(scale)).render(far, 32, 24, shading="ao",
                                                         ao_samples=2, ao_distance=None)
        assert np.array_equal(image, expected)


def test_update_vertices_across_frames():
    """Moving a mesh to 1e30 and back rebuilds in the frame each needs; the
    hits follow the float64 brute force each time.  At 1e30 the unit ground
    is lost in that frame, and the rebuild says so."""
    rng = np.random.default_rng(9)
    scene = scene_at(1.0)
    (v, f), _ = sphere_and_ground()
    for scale in (1e30, 1e-3, 1.0):
        with (pytest.warns(RuntimeWarning, match="of mesh 1's 12 triangles are too small")
              if scale == 1e30 else warnings.catch_warnings()):
            if scale != 1e30:
                warnings.simplefilter("error")
            scene.update_vertices(0, v * scale + [0.0, 2.0 * scale, 0.0])
        assert built.tree(scene).scale == frame.scale_for(
            max(np.abs(m.vertices).max() for m in scene.meshes))
        origins = np.tile([[0.0, 10.0 * scale, 0.0]], (50, 1)).astype(np.float32)
        directions = np.tile([[0.0, -1.0, 0.0]], (50, 1)).astype(np.float32)
        directions[:, 0] = rng.uniform(-0.04, 0.04, 50)
        hits = scene.intersect(origins, directions)
        expected = brute_force_intersect(scene.meshes[0].vertices, scene.meshes[0].faces,
                                         origins, directions)
        assert np.all(hits.geom_id == 0)
        np.testing.assert_allclose(hits.t, expected["t"], rtol=1e-5)


@pytest.mark.parametrize("scale, length", [(1e38 / 4, 1.0), (1e-30, 1e6), (1e-30, 1e-20),
                                           (1e30, 1e-6), (1.0, 1e-30)])
def test_directions_of_any_length_in_a_scene_of_any_scale(scale, length):
    """Directions need not scale with the scene: unit directions in a scene
    near float32's largest, long or short ones in tiny or huge scenes (so
    long as t itself, about scale / length, is a normal float32)."""
    rng = np.random.default_rng(10)
    scene = scene_at(scale)
    origins, directions = rays(1000, rng)
    origins = (origins * scale).astype(np.float32)
    directions = (directions / np.linalg.norm(directions, axis=1, keepdims=True)
                  * length).astype(np.float32)
    hits = scene.intersect(origins, directions, tmax=np.float32(3e38))
    meshes = scene.meshes
    vertices = np.concatenate([m.vertices for m in meshes])
    faces = np.concatenate([meshes[0].faces, meshes[1].faces + meshes[0].vertex_count])
    expected = brute_force_intersect(vertices, faces, origins, directions)
    assert hits.hit.sum() > 400
    assert np.array_equal(hits.hit, expected["t"] < np.inf)
    np.testing.assert_allclose(hits.t[hits.hit], expected["t"][hits.hit], rtol=1e-5)
    limit = expected["t"][hits.hit].max() * 0.5  # a tmax that cuts some hits off
    assert np.array_equal(scene.occluded(origins, directions, tmax=limit),
                          expected["t"] <= limit)


@pytest.mark.parametrize("scale, distance", [(1.0, 1e20), (1.0, 30.0), (1e10, 3e10),
                                             (1e-10, 1e3)])
def test_a_hit_past_float32s_t_is_found_and_its_t_refused(scale, distance):
    """A direction so short that its hit's t passes float32's largest value:
    the hit is found (occluded, counts), and the queries that return t name
    the ray rather than give t = inf or miss it.  Rays whose t fits beside
    it (near 1e37) keep their hits, scaled or not."""
    scene = scene_at(scale)
    origins = np.array([[0.0, 0.0, distance]] * 3, np.float32)
    directions = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -distance * 1e-37],
                           [0.0, 0.0, -distance * 1e-39]], np.float32)
    expected = brute_force_intersect(scene.meshes[0].vertices, scene.meshes[0].faces,
                                     origins[:2], directions[:2])
    assert np.isfinite(expected["t"]).all()
    assert scene.occluded(origins, directions).tolist() == [True, True, True]
    assert scene.count_intersections(origins, directions).tolist() == [2, 2, 2]
    hits = scene.intersect(origins[:2], directions[:2])
    np.testing.assert_allclose(hits.t, expected["t"], rtol=1e-5)
    for query in (scene.intersect, scene.intersect_all):
        with pytest.raises(ValueError, match=r"directions\[2\] = .* too short .* past float32"):
            query(origins, directions)


@pytest.mark.parametrize("instanced", [False, True])
def test_a_far_origin_s_hit_past_float32s_t_is_found_and_its_t_refused(instanced):
    """Directions of about unit length, but from an origin so far that the
    hit's t passes float32's largest value (t = 3e38 / |dz|): seen by
    occluded and the counts, its t refused by name, as for a short
    direction.  Lengthened only when short, these directions went as given
    and the hits past 3.4e38 were silently missed (t inf, count 0)."""
    mesh = hlbvh_cl.Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    scene = hlbvh_cl.Scene([mesh], instances=[(0, np.eye(3, 4))] if instanced else None)
    origins = np.tile(np.float32([0.2, 0.2, 3e38]), (5, 1))
    directions = np.float32([[0, 0, -z] for z in (1.0, 0.9, 0.8, 0.5, 1e-3)])
    assert scene.occluded(origins, directions).all()
    assert scene.count_intersections(origins, directions).tolist() == [1] * 5
    hits = scene.intersect(origins[:2], directions[:2])
    np.testing.assert_allclose(hits.t, [3e38, 3e38 / 0.9], rtol=1e-6)
    for query in (scene.intersect, scene.intersect_all):
        with pytest.raises(ValueError, match=r"directions\[2\] = .* too short .* past float32"):
            query(origins, directions)


@pytest.mark.parametrize("scale", [1e-30, 1.0])
def test_a_point_too_far_is_refused_with_the_limit_that_holds(scale):
    """The limit the point queries' error quotes is in the caller's units:
    a point at half of it is answered, one at twice it refused.  (A scene
    at 1e30 has no such limit within float32: its frame is scaled down.)"""
    scene = scene_at(scale)
    far = np.array([[0.0, 0.0, 3e38]], np.float32)
    with pytest.raises(ValueError, match=r"points\[0\] = .* too far .* up to ([0-9.e+-]+)") as error:
        scene.closest_points(far)
    limit = float(re.search(r"up to ([0-9.e+-]+)", str(error.value)).group(1))
    near = scene.closest_points(np.array([[0.0, 0.0, limit / 2]], np.float32))
    assert np.isfinite(near.distance).all() and near.prim_id[0] >= 0
    with pytest.raises(ValueError, match="too far"):
        scene.signed_distance(np.array([[0.0, 0.0, limit * 2]], np.float32))
    assert np.isfinite(scene_at(1e30).closest_points(far).distance).all()


def test_a_ray_the_frame_cannot_hold_is_named():
    scene = scene_at(1e-30)
    origins = np.array([[0.0, 0.0, 3e-30], [3e30, 0.0, 0.0]], np.float32)
    directions = np.array([[0.0, 0.0, -1e-30], [-1.0, 0.0, 0.0]], np.float32)
    with pytest.raises(ValueError, match=r"origins\[1\] .*overflows float32 once multiplied by 2\^"):
        scene.intersect(origins, directions)


def test_the_frame_is_one_where_coordinates_are_ordinary():
    assert frame.scale_for(0.0) == 1.0
    assert frame.scale_for(1e-7) == 1.0 and frame.scale_for(1e7) == 1.0
    for largest in (1e-30, 3e-8, 2.0**24 * 1.01, 1e30, 3.4e38):
        scaled = largest * frame.scale_for(largest)
        assert 0.5 <= scaled < 1.0


@pytest.mark.parametrize("far", [1e20, 1e30, 3e38])
def test_a_vertex_no_face_uses_does_not_set_the_frame(far):
    """A mesh with an unused vertex far out (a leftover of an export): the
    frame follows the triangles, so the hits are those of the mesh without
    it, from the start and after update_vertices moves the vertex out."""
    rng = np.random.default_rng(12)
    (v, f), _ = sphere_and_ground()
    origins, directions = rays(200, rng)
    expected = hlbvh_cl.Scene([hlbvh_cl.Mesh(v, f)]).intersect(origins, directions)
    assert expected.hit.sum() > 100
    with_far = np.vstack([v, [[far, -far, far]]])
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(with_far, f)])
    np.testing.assert_array_equal(scene.intersect(origins, directions).t, expected.t)
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(np.vstack([v, [[0.0, 0.0, 0.0]]]), f)])
    scene.update_vertices(0, with_far)
    np.testing.assert_array_equal(scene.intersect(origins, directions).t, expected.t)
    instanced = hlbvh_cl.Scene([hlbvh_cl.Mesh(with_far, f)],
                               instances=[(0, np.hstack([np.eye(3), np.zeros((3, 1))]))])
    np.testing.assert_array_equal(instanced.intersect(origins, directions).t, expected.t)


@pytest.mark.parametrize("wall", [1e10, 1e19, 1e25])
def test_a_mesh_the_frame_makes_degenerate_is_named(wall):
    """A unit tetrahedron beside a wall of `wall`: the frame set by the wall
    (2^-84 at 1e25) underflows the tetrahedron's edge cross products, so no
    ray hits it there.  Scene warns, naming the mesh and how many of its
    triangles are lost (frame.vanishing, which takes them as the triangle
    test does); at 1e10 and 1e19 the tetrahedron is hit and nothing is
    said."""
    tet = hlbvh_cl.Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
                        [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    far = hlbvh_cl.Mesh([[-wall, -wall, -10], [wall, -wall, -10], [wall, wall, -10],
                         [-wall, wall, -10]], [[0, 1, 2], [0, 2, 3]])
    lost = frame.vanishing(tet.vertices, tet.faces, frame.scale_for(wall))
    if wall < 1e20:
        assert lost == 0
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            scene = hlbvh_cl.Scene([tet, far])
    else:
        assert lost == 4
        with pytest.warns(RuntimeWarning, match=r"4 of mesh 0's 4 triangles are too small for "
                                                r"the scene's frame \(its coordinates times "
                                                r"2\^-84, set by its largest, 1e\+25\)"):
            scene = hlbvh_cl.Scene([tet, far])
    hits = scene.intersect(np.array([[0.2, 0.2, 5.0]]), np.array([[0.0, 0.0, -1.0]]))
    assert hits.geom_id[0] == (1 if lost else 0)


@pytest.mark.parametrize("kind", ["flat", "refit", "compact", "instanced"])
def test_a_warning_raised_as_an_error_leaves_the_scene_as_it_was(kind):
    """Under a filter that makes warnings errors (pytest -W error), a move
    that warns of triangles the frame loses raised after the scene had
    taken the new vertices and dropped its tree: every query then raised
    "this Scene has no tree", and rebuild() the warning again.  It now
    leaves the scene as it was, as a rejected move (a ValueError) does."""
    size = 1e6 if kind == "refit" else 1.0  # refit: in a 1e25 frame from the start
    tet = hlbvh_cl.Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) * size,
                        [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    wide = 1e25 if kind == "refit" else 2.0
    square = hlbvh_cl.Mesh(np.array([[-1, -1, -5], [1, -1, -5], [1, 1, -5], [-1, 1, -5]]) * wide,
                           [[0, 1, 2], [0, 2, 3]])
    identity = np.hstack([np.eye(3), np.zeros((3, 1))])
    options = {"compact": {"compact": True},
               "instanced": {"instances": [(0, identity), (1, identity)]}}.get(kind, {})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = hlbvh_cl.Scene([tet, square], **options)
    down = (np.array([[0.2, 0.2, 5.0], [1.5, 1.5, 5.0]]) * size, np.array([[0.0, 0.0, -1.0]] * 2))
    before = scene.intersect(*down)
    assert before.geom_id.tolist() == [0, 1]
    if kind == "refit":  # the tetrahedron at 1: lost in the frame the square keeps
        geom_id, moved = 0, tet.vertices / size
    elif kind == "instanced":  # one far corner: the mesh's own frame loses the rest of it
        geom_id, moved = 0, np.vstack([tet.vertices[:3], [[0, 0, 1e30]]])
    else:  # the square 1e25 wide: the scene's frame (2^-84) loses the tetrahedron
        geom_id, moved = 1, square.vertices * 1e25
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(RuntimeWarning, match="too small for"):
            scene.update_vertices(geom_id, moved)
    np.testing.assert_array_equal(scene.meshes[geom_id].vertices,
                                  (tet if geom_id == 0 else square).vertices)
    after = scene.intersect(*down)
    np.testing.assert_array_equal(after.t, before.t)
    np.testing.assert_array_equal(after.prim_id, before.prim_id)


def test_an_instanced_mesh_its_own_frame_makes_degenerate_is_named():
    """Instanced scenes build each mesh in a frame of its own: the unit
    tetrahedron beside a 1e25 wall is hit when the two are meshes of their
    own, and named (with the user's line) when one mesh holds both, whose
    frame of 2^-84 underflows the tetrahedron as a flat scene's would."""
    wall = 1e25
    tet = hlbvh_cl.Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
                        [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    far = hlbvh_cl.Mesh([[-wall, -wall, -10], [wall, -wall, -10], [wall, wall, -10],
                         [-wall, wall, -10]], [[0, 1, 2], [0, 2, 3]])
    both = hlbvh_cl.Mesh(np.vstack([tet.vertices, far.vertices]),
                         np.vstack([tet.faces, far.faces + 4]))
    aside = hlbvh_cl.Mesh([[100, 0, 0], [101, 0, 0], [100, 1, 0]], [[0, 1, 2]])
    identity = np.hstack([np.eye(3), np.zeros((3, 1))])
    down = (np.array([[0.2, 0.2, 5.0]]), np.array([[0.0, 0.0, -1.0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        apart = hlbvh_cl.Scene([tet, far], instances=[(0, identity), (1, identity)])
    assert apart.intersect(*down).geom_id[0] == 0
    with pytest.warns(RuntimeWarning, match=r"4 of mesh 0's 6 triangles are too small for its "
                                            r"own frame \(its coordinates times 2\^-84, set "
                                            r"by its largest, 1e\+25\)") as caught:
        joined = hlbvh_cl.Scene([both, aside], instances=[(0, identity), (1, identity)])
    assert caught[0].filename == __file__
    assert joined.intersect(*down).prim_id[0] in (4, 5)  # the wall, under the tetrahedron
    with warnings.catch_warnings():  # said once: changing another mesh does not repeat it
        warnings.simplefilter("error")
        joined.update_vertices(1, aside.vertices * 2)
        joined.rebuild()
