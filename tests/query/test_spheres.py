"""Analytic spheres beside a flat scene's meshes (Scene(spheres=...),
kernels/query/rays/sphere.h), checked against a float64 oracle of the same
rays (their float32 values): closest hits and occlusion, on every packet
size, with per-ray limits, from inside a sphere, in a rescaled frame, on
rays given on the device, and through pickling and refits.  The queries
that do not see spheres refuse a scene with them."""
from __future__ import annotations

import pickle

import numpy as np
import pyopencl.array as cla
import pytest

import hlbvh_cl
from hlbvh_cl.device.profile import PACKET_SIZES
from sphere_oracle import oracle
from test_packets import packet_query

#: A ground square (two triangles at y = 0, |x|, |z| <= 4) and spheres:
#: one resting near it, one small, one large that the ground cuts.
GROUND = ([[-4, 0, -4], [4, 0, -4], [4, 0, 4], [-4, 0, 4]], [[0, 2, 1], [0, 3, 2]])
SPHERES = np.array([[0.0, 1.0, 0.0, 0.75], [1.7, 0.4, -0.3, 0.2], [-1.5, 0.2, 1.0, 0.9]])


def ground(scale: float = 1.0) -> hlbvh_cl.Mesh:
    return hlbvh_cl.Mesh(np.array(GROUND[0], np.float64) * scale, GROUND[1], name="ground")


@pytest.fixture(scope="module")
def scene(suite_device):
    return hlbvh_cl.Scene([ground()], device=suite_device, spheres=SPHERES)


def random_rays(count: int, seed: int, scale: float = 1.0):
    """Rays from all over the scene, some inside the spheres, in every direction."""
    rng = np.random.default_rng(seed)
    origins = rng.uniform([-3, 0.01, -3], [3, 2.5, 3], (count, 3)) * scale
    directions = rng.normal(size=(count, 3)) * rng.uniform(0.5, 2.0, (count, 1))
    return origins.astype(np.float32), directions.astype(np.float32)


def assert_matches(hits, origins, directions, spheres, tmin=0.0, tmax=np.inf, scale=1.0,
                   least: int = 20):
    t, geom, gap = oracle(origins, directions, spheres, tmin, tmax, scale)
    clear = gap > 1e-4  # elsewhere float32 may take either of two near hits
    assert clear.mean() > 0.95
    np.testing.assert_array_equal(hits.geom_id[clear], geom[clear])
    hit = clear & (geom >= 0)
    assert hit.any()
    # t to float32's precision in the distance from the origin to the hit's
    # surface (a ray that leaves a sphere's surface has its t from there)
    length = np.linalg.norm(np.asarray(directions, np.float64), axis=1)
    reach = np.linalg.norm(np.asarray(origins, np.float64), axis=1) + 2 * scale
    np.testing.assert_array_less(np.abs(hits.t[hit] - t[hit]) * length[hit], 4e-6 * reach[hit])
    on_sphere = hit & (geom >= 1)
    assert on_sphere.sum() >= least
    sphere = spheres[geom[on_sphere] - 1]
    outward = (hits.points[on_sphere] - sphere[:, :3]) / sphere[:, 3:]
    np.testing.assert_allclose(hits.normal[on_sphere], outward, atol=1e-4)
    np.testing.assert_array_equal(hits.prim_id[on_sphere], 0)
    # u, v: the spherical coordinates of the normal
    n = hits.normal[on_sphere].astype(np.float64)
    u = np.arctan2(n[:, 1], n[:, 0]) / (2 * np.pi) % 1.0
    seam = np.minimum(u, 1 - u) < 1e-4
    np.testing.assert_allclose(hits.u[on_sphere][~seam], u[~seam], atol=1e-4)
    np.testing.assert_allclose(hits.v[on_sphere], np.arccos(np.clip(n[:, 2], -1, 1)) / np.pi,
                               atol=1e-3)
    return geom, clear


@pytest.mark.parametrize("packet_size", PACKET_SIZES)
def test_closest_and_any_hits_match_the_oracle(scene, packet_size):
    """Every packet size gives the oracle's hits; occluded agrees with them."""
    q = packet_query(scene, packet_size)
    origins, directions = random_rays(20000, seed=packet_size)
    with scene.borrow() as built:
        hits = q.intersect(built.tree, origins, directions)
        blocked = q.occluded(built.tree, origins, directions)
    geom, clear = assert_matches(hits, origins, directions, SPHERES)
    assert (geom >= 1).mean() > 0.1 and (geom == 0).mean() > 0.1 and (geom < 0).mean() > 0.05
    np.testing.assert_array_equal(blocked, hits.hit)


def test_every_packet_size_gives_the_same_bits(scene):
    """Work-items of 8 and 16 rays test the spheres for all their lanes at
    once (sphere.h's sphere_roots_packet), one ray a work-item lane by lane:
    the same operations, so the same t, ids, u, v and normals, bit for bit,
    and the same occlusion, with per-ray limits that cut some hits off."""
    origins, directions = random_rays(20000, seed=11)
    rng = np.random.default_rng(12)
    tmin = np.where(rng.random(len(origins)) < 0.3, rng.uniform(0, 1, len(origins)),
                    0.0).astype(np.float32)
    tmax = np.where(rng.random(len(origins)) < 0.3, rng.uniform(1, 3, len(origins)),
                    np.inf).astype(np.float32)
    found = {}
    with scene.borrow() as built:
        for packet_size in PACKET_SIZES:
            q = packet_query(scene, packet_size)
            hits = q.intersect(built.tree, origins, directions, tmin=tmin, tmax=tmax)
            blocked = q.occluded(built.tree, origins, directions, tmin=tmin, tmax=tmax)
            found[packet_size] = (hits, blocked)
    one, one_blocked = found[1]
    assert (one.geom_id >= 1).mean() > 0.05  # sphere hits, not only the ground's
    for packet_size, (hits, blocked) in found.items():
        for field in ("t", "geom_id", "prim_id", "u", "v", "normal"):
            np.testing.assert_array_equal(getattr(hits, field), getattr(one, field),
                                          err_msg=f"{field}, packets of {packet_size}")
        np.testing.assert_array_equal(blocked, one_blocked)
        np.testing.assert_array_equal(blocked, one.hit)


def test_camera_rays_see_the_spheres_in_packets(scene):
    """Coherent rays (the packet path) of a camera over the spheres."""
    camera = hlbvh_cl.Camera(eye=(0.5, 2.0, 5.0), target=(0, 0.6, 0), fov_deg=50)
    origins, directions = camera.rays(64, 48)
    hits = scene.intersect(origins, directions)
    assert_matches(hits, origins, directions, SPHERES)
    assert (hits.geom_id == 1).mean() > 0.05


def test_limits_inside_and_behind(scene):
    """tmin past a sphere's near side takes its far side (the normal along
    the ray); tmax short of a hit misses it; a ray from inside a sphere
    leaves by its far side; both ends of [tmin, tmax] count."""
    o = np.array([[0.0, 1.0, 3.0], [0.0, 1.0, 3.0], [0.0, 1.0, 0.0], [0.0, 1.0, 3.0],
                  [0.0, 1.0, 3.0]], np.float32)
    d = np.array([[0, 0, -1], [0, 0, -1], [0, 0, 1], [0, 0, -1], [0, 0, -1]], np.float32)
    tmin = np.array([0, 3.0, 0, 0, 2.25], np.float32)
    tmax = np.array([np.inf, np.inf, np.inf, 2.0, 2.25], np.float32)
    hits = scene.intersect(o, d, tmin, tmax)
    np.testing.assert_array_equal(hits.geom_id, [1, 1, 1, -1, 1])
    np.testing.assert_allclose(hits.t[[0, 1, 2, 4]], [2.25, 3.75, 0.75, 2.25], rtol=1e-6)
    np.testing.assert_allclose(hits.normal[[0, 1, 2]], [[0, 0, 1], [0, 0, -1], [0, 0, 1]],
                               atol=1e-6)
    np.testing.assert_array_equal(scene.occluded(o, d, tmin, tmax), [1, 1, 1, 0, 1])
    assert_matches(hits, o, d, SPHERES, tmin, tmax, least=4)


@pytest.mark.parametrize("length", [1e-25, 1e-20, 1e18, 1e20, 1e30])
def test_directions_of_any_length_meet_the_spheres(scene, length):
    """t is in units of the direction, whose squares would leave float32 at
    these lengths: the roots are taken along it scaled (sphere.h)."""
    o = np.array([[0.0, 1.0, 3.0], [3.0, 0.4, -0.3]], np.float32)
    d = (np.array([[0, 0, -1], [-1, 0, 0]]) * length).astype(np.float32)
    want = np.array([2.25, 3.0 - 1.7 - 0.2]) / length
    for rays in ((o, d), tuple(cla.to_device(scene.queue, a) for a in (o, d))):
        hits = scene.intersect(*rays)
        geom = hits.geom_id if isinstance(hits.geom_id, np.ndarray) else hits.geom_id.get()
        t = hits.t if isinstance(hits.t, np.ndarray) else hits.t.get()
        np.testing.assert_array_equal(geom, [1, 2])
        np.testing.assert_allclose(t, want, rtol=1e-5)
        blocked = scene.occluded(*rays)
        assert (blocked if isinstance(blocked, np.ndarray) else blocked.get()).all()


def test_a_ray_from_the_surface_meets_it_at_t_0(scene):
    """Both ends of [tmin, tmax] count: a ray that starts on a sphere (its
    top, exactly in float32) meets it at t = +0, outward or inward."""
    hits = scene.intersect([[0, 1.75, 0], [0, 1.75, 0]], [[0, 1, 0], [0, -1, 0]])
    np.testing.assert_array_equal(hits.geom_id, [1, 1])
    np.testing.assert_array_equal(hits.t[0], 0.0)
    assert not np.signbit(hits.t[0])
    assert hits.t[1] in (0.0, 1.5)


def test_a_triangle_and_a_sphere_at_one_t_give_the_triangle(suite_device):
    """A sphere whose top touches a square at t: the triangle is the hit."""
    square = hlbvh_cl.Mesh([[-1, 1, -1], [1, 1, -1], [1, 1, 1], [-1, 1, 1]], [[0, 2, 1], [0, 3, 2]])
    scene = hlbvh_cl.Scene([square], device=suite_device, spheres=[[0, 0.5, 0, 0.5]])
    hits = scene.intersect([[0, 3, 0]], [[0, -1, 0]])
    assert hits.geom_id[0] == 0 and hits.t[0] == 2.0
    below = scene.intersect([[0, 3, 0]], [[0, -1, 0]], tmin=2.5)
    assert below.geom_id[0] == 1 and below.t[0] == 3.0


def test_a_scene_in_a_rescaled_frame(suite_device):
    """Coordinates near 1e30 put the scene in a frame scaled by a power of
    two (hlbvh_cl.core.frame): the spheres go with it, and t comes back in
    the caller's units."""
    scale = 1e30
    scene = hlbvh_cl.Scene([ground(scale)], device=suite_device, spheres=SPHERES * scale)
    with scene.borrow() as built:
        assert built.tree.scale != 1.0
    origins, directions = random_rays(5000, seed=7, scale=scale)
    assert_matches(scene.intersect(origins, directions), origins, directions, SPHERES * scale,
                   scale=scale)


def test_a_small_sphere_far_from_the_origin_keeps_its_normal(suite_device):
    """A sphere's normal is its centre's offset from the hit, (o - c) + t d:
    formed as o + t d - c, rounded to the world's coordinates first, a
    sphere of radius 1e-3 at x = 1e4 had normals 29 degrees off (and v
    0.16 off).  Against float64 on the same float32 rays, at any place."""
    rng = np.random.default_rng(0)
    for x in (0.0, 1e3, 1e4):
        centre, radius = np.array([x, 0.0, 0.0]), 1e-3
        ground = hlbvh_cl.Mesh(np.array([[0, 0, -3], [1, 0, -3], [0, 1, -3.0]]) + centre,
                               [[0, 1, 2]])
        scene = hlbvh_cl.Scene([ground], spheres=[[*centre, radius]], device=suite_device)
        away = rng.normal(size=(500, 3))
        origins = (centre + away / np.linalg.norm(away, axis=1, keepdims=True)).astype(np.float32)
        targets = centre + rng.uniform(-0.5, 0.5, (500, 3)) * radius
        directions = (targets - origins).astype(np.float32)
        hits = scene.intersect(origins, directions)
        assert (hits.geom_id == 1).all()
        f, d = origins.astype(np.float64) - centre, directions.astype(np.float64)
        a, b, c = (d * d).sum(1), (f * d).sum(1), (f * f).sum(1) - radius * radius
        t = (-b - np.sqrt(b * b - a * c)) / a
        normal = f + t[:, None] * d
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        angle = np.degrees(np.arccos(np.clip((hits.normal * normal).sum(1), -1.0, 1.0)))
        assert angle.max() < 0.1, (x, angle.max())
        v = np.arccos(np.clip(normal[:, 2], -1.0, 1.0)) / np.pi
        assert np.abs(hits.v - v).max() < 1e-3, x


def test_rays_on_the_device_get_the_host_s_hits(scene):
    origins, directions = random_rays(3000, seed=11)
    queue = scene.queue
    hits = scene.intersect(cla.to_device(queue, origins), cla.to_device(queue, directions))
    want = scene.intersect(origins, directions)
    for name in ("t", "geom_id", "prim_id", "u", "v", "normal"):
        np.testing.assert_array_equal(getattr(hits, name).get(), getattr(want, name), name)
    blocked = scene.occluded(cla.to_device(queue, origins), cla.to_device(queue, directions))
    np.testing.assert_array_equal(blocked.get(), want.hit)


def test_pickles_refits_and_rebuilds_keep_the_spheres(scene, suite_device):
    origins, directions = random_rays(4000, seed=13)
    want = scene.intersect(origins, directions)
    back = pickle.loads(pickle.dumps(scene))
    np.testing.assert_array_equal(back.spheres, SPHERES)
    np.testing.assert_array_equal(back.intersect(origins, directions).t, want.t)
    # a refit moves the ground, the spheres stay; then a move far out (a new
    # frame: a rebuild) takes the spheres' records into it
    moved = hlbvh_cl.Scene([ground()], device=suite_device, spheres=SPHERES)
    lowered = np.array(GROUND[0], np.float64) - [0, 0.25, 0]
    moved.update_vertices(0, lowered)
    hits = moved.intersect(origins, directions)
    t, geom, gap = oracle(origins, directions, SPHERES)
    on_sphere = (geom >= 1) & (gap > 1e-4)
    np.testing.assert_array_equal(hits.geom_id[on_sphere], geom[on_sphere])
    moved.update_vertices(0, np.array(GROUND[0], np.float64) * 1e8)
    with moved.borrow() as built:
        assert built.tree.scale < 1.0  # 2^-29, which the spheres keep
    far = moved.intersect(origins, directions)
    np.testing.assert_array_equal(far.geom_id[on_sphere], geom[on_sphere])
    np.testing.assert_allclose(far.t[on_sphere], t[on_sphere], rtol=1e-5, atol=1e-6)
    # a frame in which float32 cannot hold the spheres' squares says so
    with pytest.warns(RuntimeWarning, match=r"3 sphere\(s\) \(geom_id 1 first\) are too "
                                            "small for the scene's frame"):
        moved.update_vertices(0, np.array(GROUND[0], np.float64) * 1e30)


@pytest.mark.parametrize("verb, args", [
    ("intersect_all", ([[0, 1, 3]], [[0, 0, -1]])), ("count_intersections", ([[0, 1, 3]],
                                                                             [[0, 0, -1]])),
    ("closest_points", ([[0, 3, 0]],)), ("winding_number", ([[0, 3, 0]],)),
    ("signed_distance", ([[0, 3, 0]],)), ("contains", ([[0, 3, 0]],))])
def test_queries_that_do_not_see_spheres_refuse_them(scene, verb, args):
    with pytest.raises(ValueError, match=rf"^{verb} takes triangle meshes only, and this "
                                         r"scene has 3 analytic sphere\(s\) \(geom_id 1 to 3\)"):
        getattr(scene, verb)(*args)


def test_the_query_layer_refuses_them_too(scene):
    """Through Scene.borrow (the layers above the scene), as the Scene does."""
    from hlbvh_cl.query.all_hits import AllHitsQuery
    from hlbvh_cl.query.points import PointQuery
    from hlbvh_cl.query.rays import RayQuery
    with scene.borrow() as built:
        rays = AllHitsQuery(RayQuery(built.runtime))
        points = PointQuery(built.runtime)
        for run, verb in ((lambda: rays.count(built.tree, [[0, 1, 3]], [[0, 0, -1]]),
                           "count_intersections"),
                          (lambda: rays.intersect_all(built.tree, [[0, 1, 3]], [[0, 0, -1]]),
                           "intersect_all"),
                          (lambda: points.closest_points(built.tree, [[0, 3, 0]]),
                           "closest_points"),
                          (lambda: points.winding_numbers(built.tree, [[0, 3, 0]]),
                           "winding_number"),
                          (lambda: points.signed_distance(built.tree, [[0, 3, 0]]),
                           "signed_distance")):
            with pytest.raises(ValueError, match=f"^{verb} takes triangle meshes only"):
                run()


@pytest.mark.parametrize("none", [None, [], np.zeros((0, 4))])
def test_no_spheres(suite_device, none):
    scene = hlbvh_cl.Scene([ground()], device=suite_device, spheres=none)
    assert scene.spheres.shape == (0, 4)
    assert scene.count_intersections([[0, 1, 0]], [[0, -1, 0]])[0] == 1


@pytest.mark.parametrize("spheres, error, words", [
    ([0, 0, 0, 1], ValueError, r"spheres has shape \(4,\), expected \(S, 4\)"),
    ([[0, 0, 0]], ValueError, r"spheres has shape \(1, 3\), expected \(S, 4\)"),
    ([[0, 0, 0, 1], [0, np.nan, 0, 1]], ValueError, r"spheres\[1\] = \[0.0, nan, 0.0, 1.0\] is "
                                                     "not finite"),
    ([[0, 0, 0, 1], [1e39, 0, 0, 1]], ValueError, r"spheres\[1\] .* is not finite in float32"),
    ([[0, 0, 0, 1], [0, 0, 0, 0]], ValueError, r"spheres\[1\] has radius 0: a sphere's radius "
                                               "must be positive"),
    ([[0, 0, 0, -2]], ValueError, r"spheres\[0\] has radius -2"),
    ([["a", "b", "c", "d"]], TypeError, r"spheres has dtype <U1, expected real numbers"),
    ([[]], ValueError, r"spheres has shape \(1, 0\), expected \(S, 4\)"),
    (np.zeros((4, 0)), ValueError, r"spheres has shape \(4, 0\), expected \(S, 4\)"),
    (np.zeros((0, 3)), ValueError, r"spheres has shape \(0, 3\), expected \(S, 4\)"),
])
def test_bad_spheres_are_refused(suite_device, spheres, error, words):
    with pytest.raises(error, match=words):
        hlbvh_cl.Scene([ground()], device=suite_device, spheres=spheres)


@pytest.mark.parametrize("layout", ["fortran", "columns", "strided"])
def test_spheres_in_any_memory_layout_give_the_same_hits(scene, suite_device, layout):
    """Column-major rows (np.vstack([x, y, z, r]).T) and strided views are
    the same spheres: the records go to the device as rows."""
    given = {"fortran": np.asfortranarray(SPHERES), "columns": np.vstack(SPHERES.T.copy()).T,
             "strided": np.repeat(SPHERES, 2, axis=0)[::2]}[layout]
    assert not given.flags.c_contiguous
    other = hlbvh_cl.Scene([ground()], device=suite_device, spheres=given)
    origins, directions = random_rays(3000, 5)
    expected, got = scene.intersect(origins, directions), other.intersect(origins, directions)
    np.testing.assert_array_equal(got.geom_id, expected.geom_id)
    np.testing.assert_array_equal(got.t, expected.t)
    assert (got.geom_id >= 1).sum() > 100


def test_spheres_take_no_instances_nor_masks(suite_device):
    for extra in ({"instances": [(0, np.eye(3, 4))]}, {"masks": [1]}):
        with pytest.raises(ValueError, match="spheres are for flat scenes"):
            hlbvh_cl.Scene([ground()], device=suite_device, spheres=SPHERES, **extra)
