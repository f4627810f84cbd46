"""Point queries (hlbvh_cl/query/points.py, kernels/query/points.cl): closest points,
winding numbers, signed distance and inside, against the float64 brute
force of tests/support/point_oracle.py, parity ray casting (embreex) on watertight
meshes, and Open3D / libigl on the bunny."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

import hlbvh_cl
import built
from point_cases import assert_signs_off_the_surface, parity_inside, surface_samples
from point_oracle import brute_force_closest, brute_force_winding

#: Distances agree with the float64 oracle to this much of the scene's size
#: (float32 coordinates, a few roundings per test).
DISTANCE_TOLERANCE = 2e-6


def icosphere(subdivisions=2, radius=1.0):
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(sphere.vertices, np.float32), np.asarray(sphere.faces, np.int32)


@pytest.fixture(scope="module")
def sphere_scene(suite_device):
    vertices, faces = icosphere()
    return hlbvh_cl.Scene([hlbvh_cl.Mesh(vertices, faces)], device=suite_device)


def oracle_of(scene):
    """(vertices, faces) of the whole scene as the device holds them
    (float32), and each face's (geom_id, prim_id)."""
    vertices = np.concatenate([m.vertices for m in scene.meshes]).astype(np.float64)
    offsets = np.cumsum([0] + [m.vertex_count for m in scene.meshes])
    faces = np.concatenate([m.faces + o for m, o in zip(scene.meshes, offsets)])
    ids = np.concatenate([np.stack([np.full(m.triangle_count, g), np.arange(m.triangle_count)], 1)
                          for g, m in enumerate(scene.meshes)])
    return vertices, faces, ids


def assert_closest_matches(scene, got, points, max_distance=np.inf, size=1.0):
    vertices, faces, ids = oracle_of(scene)
    expected = brute_force_closest(vertices, faces, points, max_distance)
    tolerance = np.broadcast_to(DISTANCE_TOLERANCE * np.asarray(size, np.float64), len(points))
    found = expected["index"] >= 0
    # at the max_distance boundary either answer is right
    edge = np.abs(expected["distance"] - max_distance) <= tolerance if np.isfinite(max_distance) \
        else np.zeros(len(points), bool)
    assert np.array_equal(got.found[~edge], found[~edge])
    both = got.found & found
    assert_near(got.distance[both], expected["distance"][both], tolerance[both])
    assert np.all(np.isinf(got.distance[~got.found]))
    assert np.all(got.prim_id[~got.found] == -1) and np.all(got.geom_id[~got.found] == -1)
    assert np.all(np.isnan(got.points[~got.found]))
    assert np.all(got.normal[~got.found] == 0)
    # the point is on the triangle named, at the distance given
    g = got.found
    tri = np.stack([vertices[faces[np.flatnonzero((ids[:, 0] == gid) & (ids[:, 1] == pid))[0]]]
                    for gid, pid in zip(got.geom_id[g], got.prim_id[g])]) if g.any() \
        else np.zeros((0, 3, 3))
    u, v = got.u[g].astype(np.float64), got.v[g].astype(np.float64)
    assert np.all((u >= -1e-6) & (v >= -1e-6) & (u + v <= 1 + 1e-6))
    on = tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
    assert_near(got.points[g], on, tolerance[g, None])
    gap = got.points[g].astype(np.float64) - np.asarray(points, np.float64)[g]
    assert_near(np.linalg.norm(gap, axis=1), got.distance[g], tolerance[g])
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    np.testing.assert_allclose(got.normal[g], normal, atol=1e-5)
    # where the nearest triangle is clearly unique, the same one
    all_d = np.sqrt(_all_distances(vertices, faces, points))
    ordered = np.sort(all_d, axis=1)
    unique = both & (ordered[:, 1] - ordered[:, 0] > 10 * tolerance)
    want = ids[expected["index"][unique]]
    assert np.array_equal(got.geom_id[unique], want[:, 0])
    assert np.array_equal(got.prim_id[unique], want[:, 1])
    return unique.sum()


def assert_near(got, expected, tolerance):
    error = np.abs(np.asarray(got, np.float64) - expected)
    bad = ~(error <= tolerance)
    assert not bad.any(), f"{bad.sum()} values off by up to {error[bad].max()}"


def _all_distances(vertices, faces, points):
    from point_oracle import triangle_corners, closest_on_triangles
    a, b, c = triangle_corners(vertices, faces)
    return closest_on_triangles(np.asarray(points, np.float64), a, b, c)[0]


def test_random_points_match_brute_force(sphere_scene):
    rng = np.random.default_rng(3)
    points = rng.uniform(-2, 2, (3000, 3)).astype(np.float32)
    got = sphere_scene.closest_points(points)
    assert len(got) == 3000 and got.found.all()
    assert assert_closest_matches(sphere_scene, got, points) > 500  # ids compared


def test_points_on_vertices_edges_and_faces(sphere_scene):
    vertices, faces = icosphere()
    rng = np.random.default_rng(4)
    f = faces[rng.integers(0, len(faces), 200)]
    a, b, c = (vertices[f[:, k]].astype(np.float64) for k in range(3))
    s = rng.uniform(0.05, 0.95, (200, 1))
    w = rng.dirichlet((1, 1, 1), 200)
    points = np.concatenate([vertices, a + s * (b - a),
                             w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c]).astype(np.float32)
    got = sphere_scene.closest_points(points)
    assert_closest_matches(sphere_scene, got, points)
    assert np.all(got.distance[:len(vertices)] == 0)  # a vertex is exactly on the surface
    assert got.distance.max() < 1e-6


def test_far_points_and_max_distance(sphere_scene):
    rng = np.random.default_rng(5)
    directions = rng.normal(size=(500, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points = (directions * rng.uniform(0.0, 50.0, (500, 1))).astype(np.float32)
    points[:3] = [[1e6, 0, 0], [0, -3e7, 0], [1e15, 1e15, -1e15]]
    got = sphere_scene.closest_points(points)
    # a float32 point far away is known to a few of its ulps: so is its distance
    size = np.linalg.norm(points, axis=1).clip(1.0, None)
    assert_closest_matches(sphere_scene, got, points, size=size)
    for max_distance in (0.0, 0.5, 3.0, 40.0):
        cut = sphere_scene.closest_points(points, max_distance=max_distance)
        assert_closest_matches(sphere_scene, cut, points, max_distance, size=size)
        assert 0 < cut.found.sum() < len(points) or max_distance == 0.0
    assert not sphere_scene.closest_points(points[:3], max_distance=10.0).found.any()
    # a point exactly max_distance away, as the query itself reports its
    # distance, is kept: the limit is not float32(max_distance**2)
    for k in np.linspace(3, len(points) - 1, 40).astype(int):
        limit = float(np.sort(got.distance)[k])
        below = float(np.nextafter(np.float32(limit), np.float32(0)))
        for cut in (limit, (limit + below) / 2):  # a float32, and a limit between two
            within = sphere_scene.closest_points(points, max_distance=cut).found
            # in float64: numpy would round a Python float to float32 to compare
            np.testing.assert_array_equal(within, got.distance.astype(np.float64) <= cut,
                                          err_msg=f"{cut!r}")
    # a limit whose square overflows float64 is no limit
    huge = sphere_scene.closest_points(points, max_distance=1e200)
    np.testing.assert_array_equal(huge.distance, got.distance)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(*[st.floats(-3, 3, width=32)] * 3), min_size=1, max_size=40),
       st.floats(0.0, 4.0, width=32) | st.just(float("inf")))
def test_distances_never_exceed_brute_force(sphere_scene, rows, max_distance):
    points = np.array(rows, np.float32)
    got = sphere_scene.closest_points(points, max_distance=max_distance)
    vertices, faces, _ = oracle_of(sphere_scene)
    expected = brute_force_closest(vertices, faces, points)["distance"]
    assert np.all(got.distance[got.found] <= expected[got.found] + DISTANCE_TOLERANCE)
    np.testing.assert_allclose(got.distance[got.found], expected[got.found],
                               atol=DISTANCE_TOLERANCE)
    clearly_within = expected <= max_distance - DISTANCE_TOLERANCE
    assert got.found[clearly_within].all()
    assert not got.found[expected > max_distance + DISTANCE_TOLERANCE].any()


def _edges_or_face_distance(points, a, b, c):
    """(P, F) float64 distances from points to triangles, independent of
    Ericson's regions: the nearest of the three edges, or the plane where
    the point's projection falls inside (barycentrics by least squares)."""
    from point_oracle import closest_on_segment
    p = np.asarray(points, np.float64)[:, None, :]
    a, b, c = (np.asarray(x, np.float64)[None] for x in (a, b, c))
    best = np.minimum(np.minimum(closest_on_segment(a, b - a, p)[0],
                                 closest_on_segment(a, c - a, p)[0]),
                      closest_on_segment(b, c - b, p)[0])
    ab, ac, ap = b - a, c - a, p - a
    gram = np.stack([np.stack([(ab * ab).sum(-1), (ab * ac).sum(-1)], -1),
                     np.stack([(ac * ab).sum(-1), (ac * ac).sum(-1)], -1)], -2)
    rhs = np.stack([(ab * ap).sum(-1), (ac * ap).sum(-1)], -1)
    gram = np.broadcast_to(gram, rhs.shape[:-1] + (2, 2))
    solvable = np.abs(np.linalg.det(gram)) > 1e-300
    uv = np.zeros(rhs.shape)
    uv[solvable] = np.linalg.solve(gram[solvable], rhs[solvable][..., None])[..., 0]
    inside = solvable & (uv[..., 0] >= 0) & (uv[..., 1] >= 0) & (uv.sum(-1) <= 1)
    face = ap - uv[..., :1] * ab - uv[..., 1:] * ac
    best = np.where(inside, np.minimum(best, (face * face).sum(-1)), best)
    return np.sqrt(best)


@pytest.mark.parametrize("case", ["repeated vertex", "collinear", "sliver", "far point"])
def test_degenerate_and_thin_triangles_and_far_points(case, suite_device):
    """Triangles that Ericson's formulas divide by zero or cancel on: a
    repeated vertex (an edge of length 0), three collinear vertices, a
    sliver, and a point 1e5 times the triangle's size away (its products
    overflow float32): single points and packets give the nearest point
    of the triangle, against a float64 oracle of edges and face, and a
    zero-area triangle's normal is 0 (no direction), not NaN."""
    from hlbvh_cl.query.points import PointQuery
    triangles = {"repeated vertex": [[0, 0, 0], [0, 0, 0], [1, 0, 0]],
                 "collinear": [[0, 0, 0], [1, 0, 0], [2, 0, 0]],
                 "sliver": [[0, 0, 0], [0.1, 0.2, 0.3], [1.1, 2.2, 3.3]],
                 "far point": [[0, 0, 0], [1e7, 0, 0], [0, 1e7, 0]]}
    vertices = np.float32(triangles[case])
    rng = np.random.default_rng(5)
    if case == "far point":
        points = np.float32([[5e12 + 3e6, 5e12 - 3e6, 0.0], [-4e12, 3e12, 1e12]])
    else:
        points = rng.normal(0.5, 2.0, (64, 3)).astype(np.float32)
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(vertices, [[0, 1, 2]])], device=suite_device)
    expected = _edges_or_face_distance(points, *vertices[None, :, :].transpose(1, 0, 2))[:, 0]
    for packet_size in (1, 8):
        got = PointQuery(built.runtime(scene), packet_size=packet_size).closest_points(
            built.tree(scene), points)
        assert np.all(got.prim_id == 0), (case, packet_size)
        np.testing.assert_allclose(got.distance, expected, rtol=1e-5, atol=1e-6,
                                   err_msg=f"{case}, packets of {packet_size}")
        assert np.isfinite(got.normal).all()
        if case in ("repeated vertex", "collinear"):
            assert np.all(got.normal == 0)


@pytest.mark.parametrize("placed", ["flat", "instanced"])
def test_points_just_off_slivers_are_exact(suite_device, placed):
    """Triangles 30 long and 0.03 to 10 high, turned and moved, and points
    1e-4 above and below their insides: Ericson's face formula in float
    cancels on the thinner ones (its point came out up to 0.013 away, a
    hundred times the distance), so slivers are found in double where the
    device has it.  Distances within a few float ulps of the coordinates."""
    from hlbvh_cl.query.points import PointQuery
    rng = np.random.default_rng(12)
    for height in (0.03, 0.3, 1.0, 3.0, 10.0):
        turn, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        place = np.hstack([turn, [[20.0], [-10.0], [5.0]]])
        local = np.float32([[0, 0, 0], [30, 0, 0], [12, height, 0]])
        corners = local.astype(np.float64) @ turn.T + place[:, 3]
        if placed == "flat":
            scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(corners.astype(np.float32), [[0, 1, 2]])],
                                   device=suite_device)
            corners = corners.astype(np.float32).astype(np.float64)  # as the scene holds them
        else:
            scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(local, [[0, 1, 2]])], device=suite_device,
                                   instances=[(0, place)])
        normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        normal /= np.linalg.norm(normal)
        points = (rng.dirichlet(np.ones(3), 2000) @ corners
                  + 1e-4 * rng.choice([-1.0, 1.0], (2000, 1)) * normal).astype(np.float32)
        expected = _edges_or_face_distance(points, *corners[:, None, :])[:, 0]
        for packet_size in (1, 8):
            got = PointQuery(built.runtime(scene), packet_size=packet_size).closest_points(
                built.tree(scene), points)
            np.testing.assert_allclose(got.distance, expected, rtol=0, atol=1e-5,
                                       err_msg=f"height {height}, packets of {packet_size}")


def test_slivers_match_the_oracle(suite_device):
    """Many near-collinear triangles (their third vertex within 1e-4 of
    the line through the other two), each in a cell of its own, and points
    above and below their insides: the nearest distances match a float64 oracle that does not
    use Ericson's face formula, single points and packets alike, within the
    suite's tolerance of the scene's size."""
    from hlbvh_cl.query.points import PointQuery
    rng = np.random.default_rng(11)
    count = 300
    cells = np.stack(np.unravel_index(np.arange(count), (7, 7, 7)), 1)
    base = rng.uniform(-1, 1, (count, 3)) + 10.0 * cells
    along = rng.normal(0, 1, (count, 3))
    a, b = base, base + along
    c = base + rng.uniform(-0.5, 1.5, (count, 1)) * along + rng.normal(0, 1e-4, (count, 3))
    vertices = np.stack([a, b, c], 1).reshape(-1, 3).astype(np.float32)
    faces = np.arange(3 * count).reshape(-1, 3)
    corners = vertices.reshape(-1, 3, 3).astype(np.float64)
    # above and below each sliver's inside, where Ericson's face region lies
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    inside = np.einsum("rnk,nkd->rnd", rng.dirichlet(np.ones(3), (4, count)), corners)
    points = (inside + rng.normal(0, 1.0, (4, count, 1)) * normal).reshape(-1, 3)
    points = points.astype(np.float32)
    expected = _edges_or_face_distance(points, corners[:, 0], corners[:, 1],
                                       corners[:, 2]).min(axis=1)
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(vertices, faces)], device=suite_device)
    size = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    for packet_size in (1, 8):
        got = PointQuery(built.runtime(scene), packet_size=packet_size).closest_points(
            built.tree(scene), points)
        np.testing.assert_allclose(got.distance, expected, rtol=0, atol=DISTANCE_TOLERANCE * size,
                                   err_msg=f"packets of {packet_size}")


def test_multi_mesh_scene_geom_ids(suite_device):
    v1, f1 = icosphere(1)
    v2, f2 = icosphere(1, radius=0.5)
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(v1, f1), hlbvh_cl.Mesh(v2 + np.float32(3.0), f2)],
                           device=suite_device)
    rng = np.random.default_rng(6)
    points = rng.uniform(-1.5, 4.5, (1500, 3)).astype(np.float32)
    got = scene.closest_points(points)
    assert_closest_matches(scene, got, points)
    assert set(np.unique(got.geom_id)) == {0, 1}
    # a point in each ball is inside; the gap between them is not
    inside = scene.contains([[0, 0, 0], [3, 3, 3], [1.5, 1.5, 1.5]])
    assert inside.tolist() == [True, True, False]


def test_winding_numbers_match_brute_force(sphere_scene):
    rng = np.random.default_rng(7)
    points = rng.uniform(-2, 2, (2000, 3)).astype(np.float32)
    vertices, faces, _ = oracle_of(sphere_scene)
    expected = brute_force_winding(vertices, faces, points)
    got = sphere_scene.winding_number(points)
    # Barill's order-1 far field with beta = 2: a few percent at most
    np.testing.assert_allclose(got, expected, atol=0.05)
    assert np.array_equal(got >= 0.5, expected >= 0.5)


@pytest.mark.parametrize("points", [2000, 3])
def test_zero_area_triangles_add_no_winding(points, suite_device):
    """Zero-area triangles (a repeated corner, three corners on a line) on an
    edge of a closed tetrahedron subtend no solid angle; their formula's
    triple product is 0 up to rounding and its denominator negative seen
    from near the edge, and atan2 gave +-pi: w off by 0.5, points 1e-5
    inside called outside."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0, 0]], np.float64)
    closed = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    degenerate = np.concatenate([closed, [[0, 0, 1], [0, 4, 1], [4, 1, 1]]])
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(vertices, degenerate)], device=suite_device)
    rng = np.random.default_rng(0)
    near = 10.0 ** rng.uniform(-6, -3, points)  # just inside, near the edge 0-1
    query = np.stack([rng.uniform(0.1, 0.9, points), near * rng.uniform(0.2, 1, points),
                      near * rng.uniform(0.2, 1, points)], 1).astype(np.float32)
    expected = brute_force_winding(vertices, closed, query)
    np.testing.assert_allclose(scene.winding_number(query), expected, atol=0.05)
    assert scene.contains(query).all() and (scene.signed_distance(query) <= 0).all()


@pytest.mark.parametrize("height", [1e-4, 1e-6])
@pytest.mark.parametrize("points", [3000, 3])
def test_a_sliver_s_winding_is_right_next_to_it(height, points, suite_device):
    """A closed tetrahedron whose face (1, 2, 3) is a fan about a point
    `height` from edge 1-2, so that (1, 2, Q) is a sliver; points just
    inside next to it.  The sliver's solid angle in float32 cancelled to
    garbage there: w up to 1.49 (or 0.93) where it is 1."""
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64)
    middle = 0.5 * (corners[1] + corners[2])
    up = (corners[3] - middle) / np.linalg.norm(corners[3] - middle)
    vertices = np.vstack([corners, middle + height * up])
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 4], [2, 3, 4], [3, 1, 4]])
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(vertices, faces)], device=suite_device)
    rng = np.random.default_rng(1)
    along = corners[1] + rng.uniform(0.05, 0.95, (points, 1)) * (corners[2] - corners[1])
    on_sliver = along + rng.uniform(0, height, (points, 1)) * up
    inward = corners.mean(axis=0) - on_sliver  # towards the centroid: inside at once
    inward /= np.linalg.norm(inward, axis=1, keepdims=True)
    query = (on_sliver + 10.0 ** rng.uniform(-7, -4, (points, 1)) * inward).astype(np.float32)
    expected = brute_force_winding(vertices, faces, query)
    assert (expected > 0.99).all()  # every point is inside, next to the sliver
    np.testing.assert_allclose(scene.winding_number(query), expected, atol=0.05)


def watertight(name, meshes, device):
    """A watertight mesh (an icosphere or one of the project's), and its scene."""
    if name == "icosphere":
        vertices, faces = icosphere(3)
    else:
        vertices, faces = meshes[name].vertices, meshes[name].faces
    return vertices, faces, hlbvh_cl.Scene([hlbvh_cl.Mesh(vertices, faces)], device=device)


@pytest.mark.parametrize("name", ["icosphere", "bunny_small", "knight"])
def test_sign_agrees_with_parity_on_watertight_meshes(name, meshes, suite_device):
    vertices, faces, scene = watertight(name, meshes, suite_device)
    lo, hi = vertices.min(0), vertices.max(0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 * 1.2
    points = (centre + np.random.default_rng(8).uniform(-1, 1, (4000, 3)) * half).astype(np.float32)
    sdf = scene.signed_distance(points)
    nearest = scene.closest_points(points).distance
    np.testing.assert_array_equal(np.abs(sdf), nearest)
    expected = parity_inside(vertices.astype(np.float64), faces, points.astype(np.float64))
    # parity casting itself is unreliable on the surface: compare off it
    clear = nearest > 1e-4 * np.linalg.norm(hi - lo)
    assert expected[clear].sum() > 100
    assert np.array_equal((sdf < 0)[clear], expected[clear])
    assert np.array_equal(scene.contains(points)[clear], expected[clear])


@pytest.mark.parametrize("name", ["icosphere", "bunny_small"])
def test_sign_is_right_1e_6_off_the_surface(name, meshes, suite_device):
    vertices, faces, scene = watertight(name, meshes, suite_device)
    on, normal, _ = surface_samples(np.random.default_rng(9), vertices, faces, 500)
    assert_signs_off_the_surface(scene, on, normal, 400)


def test_bunny_agrees_with_open3d_and_libigl(meshes, suite_device):
    o3d = pytest.importorskip("open3d")
    igl = pytest.importorskip("igl")
    # the bunny's faces wind inward (negative volume), so its winding numbers
    # are near -1 inside: inside is |w| >= 0.5 (hlbvh_cl/query/points.py)
    mesh = meshes["bunny"]
    scene = hlbvh_cl.Scene([mesh], device=suite_device)
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 * 1.4
    points = (centre + np.random.default_rng(10).uniform(-1, 1, (3000, 3)) * half).astype(np.float32)
    got = scene.closest_points(points)
    size = float(np.linalg.norm(hi - lo))
    raycasting = o3d.t.geometry.RaycastingScene()
    raycasting.add_triangles(o3d.core.Tensor(mesh.vertices), o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    answer = raycasting.compute_closest_points(o3d.core.Tensor(points))["points"].numpy()
    # the same point, or (ties: two parts of the surface as near) as near a one
    same = np.linalg.norm(got.points - answer, axis=1) <= 1e-5 * size
    assert same.mean() > 0.99
    tie = np.linalg.norm(answer - points, axis=1) - got.distance
    assert np.all(np.abs(tie[~same]) <= 1e-6 * size)
    o3d_distance = raycasting.compute_distance(o3d.core.Tensor(points)).numpy()
    np.testing.assert_allclose(got.distance, o3d_distance, atol=1e-6 * size)
    v64, f64 = mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64)
    squared, _, _ = igl.point_mesh_squared_distance(points.astype(np.float64), v64, f64)
    np.testing.assert_allclose(got.distance, np.sqrt(squared), atol=1e-6 * size)
    # the bunny has holes: winding numbers against libigl's exact ones
    expected = igl.winding_number(v64, f64, points.astype(np.float64))
    winding = scene.winding_number(points)
    error = np.abs(winding - expected)
    assert error.max() < 0.1 and np.median(error) < 0.005  # Barill's order-1 far field
    decided = np.abs(np.abs(expected) - 0.5) > 0.1
    inside = np.abs(expected) >= 0.5
    assert np.array_equal((scene.signed_distance(points) < 0)[decided], inside[decided])
    assert np.array_equal(scene.contains(points)[decided], inside[decided])
    assert 200 < inside.sum() < 2800 and (expected < -0.5).sum() == inside.sum()


def test_inside_does_not_depend_on_the_winding_order(suite_device):
    """A closed mesh oriented inward has w = -1 inside: the same inside, the
    same signed distances, and opposite winding numbers."""
    vertices, faces = icosphere(2)
    outward = hlbvh_cl.Scene([hlbvh_cl.Mesh(vertices, faces)], device=suite_device)
    inward = hlbvh_cl.Scene([hlbvh_cl.Mesh(vertices, faces[:, ::-1])], device=suite_device)
    points = np.random.default_rng(12).uniform(-1.3, 1.3, (2000, 3)).astype(np.float32)
    np.testing.assert_allclose(inward.winding_number(points), -outward.winding_number(points),
                               atol=1e-5)
    inward_sdf, outward_sdf = inward.signed_distance(points), outward.signed_distance(points)
    # the same distances up to the rounding of the vertices' other order
    np.testing.assert_allclose(inward_sdf, outward_sdf, atol=1e-6)
    np.testing.assert_array_equal(np.sign(inward_sdf), np.sign(outward_sdf))
    radius = np.linalg.norm(points, axis=1)
    assert np.all(inward.contains(points)[radius < 0.95]) and not inward.contains(points)[radius > 1.05].any()


@pytest.mark.parametrize("scale", [1e-30, 1e30])
def test_scaled_frames(scale, suite_device):
    vertices, faces = icosphere(2)
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(vertices.astype(np.float64) * scale, faces)],
                           device=suite_device)
    assert built.tree(scene).scale != 1.0
    rng = np.random.default_rng(11)
    points = (rng.uniform(-2, 2, (1000, 3)) * scale).astype(np.float32)
    got = scene.closest_points(points)
    assert_closest_matches(scene, got, points, size=scale)
    limited = scene.closest_points(points, max_distance=0.3 * scale)
    assert_closest_matches(scene, limited, points, 0.3 * scale, size=scale)
    inside = np.linalg.norm(points.astype(np.float64) / scale, axis=1) < 0.98
    outside = np.linalg.norm(points.astype(np.float64) / scale, axis=1) > 1.02
    sdf = scene.signed_distance(points)
    assert np.all(sdf[inside] < 0) and np.all(sdf[outside] > 0)
    np.testing.assert_array_equal(np.abs(sdf), got.distance)


@pytest.mark.parametrize("placed", ["flat", "instanced"])
@pytest.mark.parametrize("radius", [1e-10, 1e-15, 1e-18])
def test_a_small_mesh_in_a_big_frame(radius, placed, suite_device):
    """A closed sphere of the given radius at the origin and a triangle 1
    away, which sets the scene's frame: the sphere's features are far below
    the frame's size, where Ericson's products (its edges to the fourth)
    and the solid angle's and dipoles' (lengths cubed) underflow float
    unless scaled.  Points inside, just off the faces and outside the
    sphere, in single points and packets: the nearest distances match the
    float64 oracle to float's precision of the sphere's size, the winding
    number tells inside from outside (never NaN), and so the sign of the
    signed distance is right."""
    from hlbvh_cl.query.points import PointQuery
    vertices, faces = icosphere(1)
    small = hlbvh_cl.Mesh(vertices.astype(np.float64) * radius, faces)
    far = hlbvh_cl.Mesh([[1, 0, 0], [1, 1e-3, 0], [1, 0, 1e-3]], [[0, 1, 2]])
    if placed == "flat":
        joined = np.vstack([small.vertices, far.vertices])
        scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(joined, np.vstack([faces, [[42, 43, 44]]]))],
                               device=suite_device)
    else:
        scene = hlbvh_cl.Scene([small, far], device=suite_device,
                               instances=[(0, np.eye(3, 4)), (1, np.eye(3, 4))])
    rng = np.random.default_rng(21)
    corners = small.vertices.astype(np.float64)[faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    on_faces = np.einsum("nk,nkd->nd", rng.dirichlet(np.ones(3), len(faces)), corners)
    off = rng.choice([-0.05, 0.05], (len(faces), 1)) * radius * normal
    scattered = rng.normal(0, 1, (200, 3))
    scattered *= rng.uniform(0, 3, (200, 1)) / np.linalg.norm(scattered, axis=1, keepdims=True)
    points = np.vstack([on_faces + off, scattered * radius]).astype(np.float32)
    # icosphere(1)'s faces lie at least 0.93 of the radius from its centre
    norm = np.linalg.norm(points.astype(np.float64), axis=1) / radius
    inside, outside = norm < 0.9, norm > 1.05
    for packet_size in (1, 8):
        query = PointQuery(built.runtime(scene), packet_size=packet_size)
        got = query.closest_points(built.tree(scene), points)
        assert_closest_matches(scene, got, points, size=radius)
        w = query.winding_numbers(built.tree(scene), points)
        assert np.isfinite(w).all(), f"packets of {packet_size}"
        assert np.all(np.abs(w[inside]) > 0.9) and np.all(np.abs(w[outside]) < 0.1), \
            f"packets of {packet_size}"
    sdf = scene.signed_distance(points)
    assert np.all(sdf[inside] < 0) and np.all(sdf[outside] > 0)


def test_update_vertices_moves_the_answers(suite_device):
    vertices, faces = icosphere(2)
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(vertices, faces)], device=suite_device)
    points = np.array([[0, 0, 0], [2.5, 0, 0], [1.2, 0, 0]], np.float32)
    assert scene.contains(points).tolist() == [True, False, False]  # dipoles made here
    scene.update_vertices(0, vertices + np.float32(2.0))  # the ball moves to (2, 2, 2)
    moved = np.array([[2, 2, 2], [0, 0, 0], [2.9, 2, 2]], np.float32)
    assert scene.contains(moved).tolist() == [True, False, True]
    sdf = scene.signed_distance(moved)
    assert sdf[0] < 0 and sdf[1] > 0 and sdf[2] < 0
    assert_closest_matches(scene, scene.closest_points(moved), moved)


def test_bad_input_is_named(sphere_scene):
    with pytest.raises(ValueError, match=r"points\[1\]"):
        sphere_scene.closest_points([[0, 0, 0], [np.nan, 0, 0]])
    with pytest.raises(ValueError, match=r"points\[0\].*not finite"):
        sphere_scene.signed_distance(np.array([[np.inf, 0, 0]]))
    with pytest.raises(ValueError, match=r"points\[0\].*overflows"):
        sphere_scene.contains(np.array([[1e39, 0, 0]]))
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 3\)"):
        sphere_scene.closest_points(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="max_distance"):
        sphere_scene.closest_points(np.zeros((1, 3)), max_distance=-1.0)
    with pytest.raises(ValueError, match="max_distance"):
        sphere_scene.closest_points(np.zeros((1, 3)), max_distance=np.nan)
    # the row as the caller wrote it, not float32's 0.10000000149011612
    with pytest.raises(ValueError, match=r"points\[2\] = \[0\.1, 0\.0, 1e\+30\] is too far"):
        sphere_scene.winding_number([[0, 0, 0], [1, 1, 1], [0.1, 0, 1e30]])
    with pytest.raises(TypeError, match="points"):
        sphere_scene.closest_points([["a", "b", "c"]])


def test_array_likes(sphere_scene):
    points = np.random.default_rng(12).uniform(-2, 2, (50, 6))[:, ::2]  # float64, strided
    points.setflags(write=False)
    expected = sphere_scene.closest_points(points.astype(np.float32))
    for given in (points, points.tolist()):
        got = sphere_scene.closest_points(given)
        np.testing.assert_array_equal(got.distance, expected.distance)
        np.testing.assert_array_equal(got.points, expected.points)
    empty = sphere_scene.closest_points(np.zeros((0, 3)))
    assert len(empty) == 0 and sphere_scene.signed_distance(np.zeros((0, 3))).shape == (0,)


def test_chunks_give_the_same_answers(sphere_scene):
    from hlbvh_cl.query.points import PointQuery
    points = np.random.default_rng(13).uniform(-2, 2, (1000, 3)).astype(np.float32)
    tree = built.tree(sphere_scene)
    whole = PointQuery(built.runtime(sphere_scene))
    small = PointQuery(built.runtime(sphere_scene), max_points_per_launch=97)
    a, b = whole.closest_points(tree, points), small.closest_points(tree, points)
    for field in ("distance", "prim_id", "points", "normal"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    np.testing.assert_array_equal(whole.signed_distance(tree, points),
                                  small.signed_distance(tree, points))


def test_the_staging_path_answers_as_the_others(sphere_scene, monkeypatch):
    """Points and results through pinned staging buffers (on request;
    forced here), in chunks and in Morton order (a batch this big), give every
    point query's answers bit for bit as the scene's own path."""
    from hlbvh_cl.query.order import COHERENT_MIN
    from hlbvh_cl.query.points import PointQuery
    points = np.random.default_rng(17).uniform(-2, 2, (COHERENT_MIN + 999, 3)).astype(np.float32)
    want = _answers(sphere_scene, points)
    query = PointQuery(built.runtime(sphere_scene), max_points_per_launch=1000)
    query.engine.zero_copy, query.engine.outputs_in_place, query.staging = False, False, True
    batches = _recording(monkeypatch, query)
    got = _answers(_Through(sphere_scene, query), points)
    assert query.engine.stage is not None
    assert all(batch.order is not None and not batch.whole for batch in batches)
    for name, array in want.items():
        np.testing.assert_array_equal(got[name], array, err_msg=name)


def test_points_keep_their_leading_shape(sphere_scene):
    """(H, W, 3) points give (H, W) answers, equal to the flat query's."""
    points = np.random.default_rng(13).uniform(-2, 2, (4, 5, 3)).astype(np.float32)
    flat = sphere_scene.closest_points(points.reshape(-1, 3))
    grid = sphere_scene.closest_points(points)
    for name in ("points", "distance", "prim_id", "geom_id", "u", "v", "normal"):
        want = getattr(flat, name)
        got = getattr(grid, name)
        assert got.shape == (4, 5) + want.shape[1:], name
        np.testing.assert_array_equal(got.reshape(want.shape), want, err_msg=name)
    for query in (sphere_scene.signed_distance, sphere_scene.winding_number,
                  sphere_scene.contains):
        np.testing.assert_array_equal(query(points).reshape(-1), query(points.reshape(-1, 3)))
    with pytest.raises(ValueError, match=r"points\[1, 2\] = .*not finite"):
        sphere_scene.contains(np.where(np.arange(20).reshape(4, 5, 1) == 7, np.nan, points))


def test_big_batches_answer_in_place(sphere_scene):
    """Batches of COHERENT_MIN and more run in Morton order (order.
    device_order) and in chunks: each point's answer is the one it gets
    alone in a small batch, in its own row, also with a flat axis (all z
    equal), repeated points and extents down to a denormal."""
    from hlbvh_cl.query.order import COHERENT_MIN, coherent_order
    from hlbvh_cl.query.points import PointQuery
    rng = np.random.default_rng(21)
    count = 3 * COHERENT_MIN
    points = rng.uniform(-2, 2, (count, 3)).astype(np.float32)
    points[:, 2] = 0.25
    points[::7] = points[3]
    query = PointQuery(built.runtime(sphere_scene))  # as the scene's own, in launches of 1000
    query.max_points_per_launch = 1000
    whole = query.closest_points(built.tree(sphere_scene), points)
    sdf = query.signed_distance(built.tree(sphere_scene), points)
    pieces = [sphere_scene.closest_points(points[i:i + 500]) for i in range(0, count, 500)]
    for name in ("distance", "prim_id", "geom_id", "u", "v", "normal", "points"):
        assert np.array_equal(getattr(whole, name),
                              np.concatenate([getattr(p, name) for p in pieces]))
    assert np.array_equal(sdf, np.concatenate([sphere_scene.signed_distance(points[i:i + 500])
                                               for i in range(0, count, 500)]))
    for block in (points, np.full((5, 3), 1.0, np.float32),
                  np.array([[0, 0, 0], [1e-44, 0, 0], [0, 1e-44, 3e38]], np.float32)):
        order = coherent_order(block)
        assert np.array_equal(np.sort(order), np.arange(len(block)))


POINT_QUERIES = ("closest_points", "winding_number", "signed_distance", "contains")


class _Through:
    """A scene's point queries (Scene's methods) through a PointQuery of its
    runtime on its tree, as the scene runs them through its own."""

    def __init__(self, scene, query):
        self.query, self.tree = query, built.tree(scene)

    def closest_points(self, points):
        return self.query.closest_points(self.tree, points)

    def winding_number(self, points):
        return self.query.winding_numbers(self.tree, points)

    def signed_distance(self, points):
        return self.query.signed_distance(self.tree, points)

    def contains(self, points):
        return np.abs(self.winding_number(points)) >= 0.5


def _answers(scene, points) -> dict:
    """Every point query's answer (closest_points's fields) on ``points``,
    from a Scene, or a _Through one."""
    answers = {}
    for query in POINT_QUERIES:
        got = getattr(scene, query)(points)
        if query == "closest_points":
            answers.update({f"closest {name}": getattr(got, name) for name in
                            ("distance", "prim_id", "geom_id", "u", "v", "normal", "points")})
        else:
            answers[query] = got
    return answers


def _recording(monkeypatch, query) -> list:
    """The Batch of each of ``query``'s engine runs (which still run):
    batch.whole says whether the kernels used the whole arrays in place."""
    batches, run = [], query.engine.run
    monkeypatch.setattr(query.engine, "run",
                        lambda batch, launch: batches.append(batch) or run(batch, launch))
    return batches


def test_points_the_kernels_use_in_place_start_on_a_page(sphere_scene, monkeypatch):
    """Off zero copy, on a CPU runtime that uses host memory in place only
    where it starts on a page (Intel's: Engine.outputs_in_place), big batches
    run in place: the points are copied onto a page once, the results are
    lent on pages, and every answer is the copied path's."""
    from hlbvh_cl.query import results
    from hlbvh_cl.query.order import COHERENT_MIN
    from hlbvh_cl.query.points import PointQuery
    query = PointQuery(built.runtime(sphere_scene))  # as the scene's own
    scene = _Through(sphere_scene, query)
    if query.rt.profile.gpu:
        pytest.skip("GPUs take device copies of the points")
    monkeypatch.setattr(results, "MIN_POOLED_BYTES", 4096)  # this batch's arrays pooled
    count = 2 * COHERENT_MIN
    points = np.random.default_rng(31).uniform(-2, 2, (count + 1, 3)).astype(np.float32)[1:]
    assert points.ctypes.data % results.ALIGNMENT  # off the page its array starts on
    monkeypatch.setattr(query.engine, "zero_copy", False)
    monkeypatch.setattr(query.engine, "outputs_in_place", False)
    want = _answers(scene, points)
    monkeypatch.setattr(query.engine, "outputs_in_place", True)
    batches = _recording(monkeypatch, query)
    got = _answers(scene, points)
    assert len(batches) == len(POINT_QUERIES) and all(batch.whole for batch in batches)
    for batch in batches:
        placed = batch.inputs["input"]
        assert placed is not points and np.array_equal(placed, points)
        assert results.starts_on_page(placed, *batch.outputs.values())
    for name, array in want.items():
        np.testing.assert_array_equal(got[name], array, err_msg=name)


def test_points_stay_put_when_their_results_are_off_a_page(sphere_scene, monkeypatch):
    """On a runtime that uses host memory in place only on a page, a batch
    whose results are too small for the pool (so off a page: the copied
    path) does not first copy its points onto one."""
    from hlbvh_cl.query import points as points_module
    from hlbvh_cl.query import results
    from hlbvh_cl.query.order import COHERENT_MIN
    query = points_module.PointQuery(built.runtime(sphere_scene))  # as the scene's own
    scene = _Through(sphere_scene, query)
    monkeypatch.setattr(query.engine, "zero_copy", False)
    monkeypatch.setattr(query.engine, "outputs_in_place", True)
    count = 2 * COHERENT_MIN
    monkeypatch.setattr(results, "MIN_POOLED_BYTES", 8 * count)  # points pooled, w not

    def off_page(shape, dtype):  # np.empty's, but surely off a page (4 bytes past a 16)
        dtype = np.dtype(dtype)
        raw = np.empty(int(np.prod(shape)) * dtype.itemsize + 16, np.uint8)
        start = -raw.ctypes.data % 16 + 4
        return raw[start:start + int(np.prod(shape)) * dtype.itemsize].view(dtype).reshape(shape)
    monkeypatch.setattr(query.results, "empty", off_page)
    points = np.random.default_rng(33).uniform(-2, 2, (count + 1, 3)).astype(np.float32)[1:]
    placed = []
    monkeypatch.setattr(points_module, "on_page", lambda pool, array: placed.append(array) or array)
    batches = _recording(monkeypatch, query)
    want = scene.winding_number(points[:500])
    got = scene.winding_number(points)
    assert not placed and [batch.whole for batch in batches] == [False, False]
    np.testing.assert_array_equal(got[:500], want)


def test_points_past_a_device_buffer_go_in_chunks(sphere_scene, monkeypatch):
    """Where a whole array would not fit one buffer of the device
    (CL_DEVICE_MAX_MEM_ALLOC_SIZE), in-place runtimes too copy the points
    and results chunk by chunk, through buffers that fit, with the same
    answers."""
    import dataclasses
    from hlbvh_cl.query.order import COHERENT_MIN
    from hlbvh_cl.query.points import PointQuery
    query = PointQuery(built.runtime(sphere_scene))  # as the scene's own
    scene = _Through(sphere_scene, query)
    count = 2 * COHERENT_MIN
    points = np.random.default_rng(32).uniform(-2, 2, (count, 3)).astype(np.float32)
    want = _answers(scene, points)
    monkeypatch.setattr(query.engine, "outputs_in_place", True)
    monkeypatch.setattr(query, "max_points_per_launch", 100)
    monkeypatch.setattr(query.engine, "reused", {})  # made again within the limit
    limit = points.nbytes // 2
    monkeypatch.setattr(query.rt, "device", dataclasses.replace(query.rt.device,
                                                                max_mem_alloc_size=limit))
    batches = _recording(monkeypatch, query)
    got = _answers(scene, points)
    assert len(batches) == len(POINT_QUERIES) and not any(batch.whole for batch in batches)
    for name, array in want.items():
        np.testing.assert_array_equal(got[name], array, err_msg=name)


BEYOND_ONE_BUFFER = """
import numpy as np, hlbvh_cl
from hlbvh_cl.device.discovery import select_device
n = select_device("pocl").max_mem_alloc_size // 12 + 4096   # rows past one buffer
tetra = hlbvh_cl.Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
                      [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
scene = hlbvh_cl.Scene(tetra, device="pocl")
points = np.full((n, 3), 3.0, np.float32)
points[::7] = 0.1                                 # inside, the rest far outside
inside = np.zeros(n, bool)
inside[::7] = True
assert np.array_equal(scene.contains(points), inside)
assert np.array_equal(scene.count_intersections(points, np.float32([1, 0, 0])), inside)
print("ok")
"""


@pytest.mark.skipif(not any(d.id.startswith("pocl") and d.problem is None
                            for d in hlbvh_cl.devices()), reason="needs PoCL")
def test_batches_past_the_runtimes_buffer_limit_are_answered():
    """A batch whose points (or rays) are more than the runtime allows in
    one buffer, with the limit the runtime really enforces (PoCL's, made
    256 MiB by POCL_MEMORY_LIMIT=1, in a child): the order is found on the
    host and the queries go in chunks, where before the order's one buffer
    over every point failed with pyopencl's INVALID_BUFFER_SIZE."""
    env = {**os.environ, "POCL_MEMORY_LIMIT": "1"}
    done = subprocess.run([sys.executable, "-c", BEYOND_ONE_BUFFER], env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-2000:]


def test_every_packet_size_gives_the_same_closest_points(meshes, suite_device):
    """Closest points walked one per work-item and in packets of 8 and 16
    (kernels/query/points/point_packet.h), on a batch big enough to run in Morton order
    (whole arrays read and written in place where zero copy), uniform in the
    box and near the surface: each matches the brute force, and the sizes
    agree exactly, ties included (they resolve in tree order).  Winding
    numbers take the same terms whatever the packet (summed in another order
    than one point's walk), so a point's does not depend on its batch."""
    from hlbvh_cl.query.order import COHERENT_MIN
    from hlbvh_cl.query.points import PointQuery
    mesh = meshes["bunny_small"]
    scene = hlbvh_cl.Scene([mesh], device=suite_device)
    vertices, faces, _ = oracle_of(scene)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    rng = np.random.default_rng(31)
    count = 2 * COHERENT_MIN + 3
    uniform = rng.uniform(lo - 0.2 * (hi - lo), hi + 0.2 * (hi - lo), (count, 3))
    corners = vertices[faces[rng.integers(0, len(faces), count)]]
    weights = rng.dirichlet(np.ones(3), count)
    near = np.einsum("nk,nkd->nd", weights, corners) + rng.normal(0, 0.01, (count, 3)) * (hi - lo)
    points = np.concatenate([uniform, near]).astype(np.float32)
    size = float(np.linalg.norm(hi - lo))
    winding = brute_force_winding(vertices, faces, points)
    answers = {}
    for packet_size in (1, 8, 16):
        query = PointQuery(built.runtime(scene), packet_size=packet_size)
        tree = built.tree(scene)
        got = query.closest_points(tree, points)
        assert assert_closest_matches(scene, got, points, size=size) > count
        w = query.winding_numbers(tree, points)
        np.testing.assert_allclose(w, winding, atol=0.05)
        sdf = query.signed_distance(tree, points)
        np.testing.assert_array_equal(np.abs(sdf), got.distance)
        clear = np.abs(np.abs(winding) - 0.5) > 0.1
        assert np.array_equal((sdf < 0)[clear], (np.abs(winding) >= 0.5)[clear])
        answers[query.variant.packet_size] = got, w
    first = answers[1]
    for packet_size, (got, w) in answers.items():
        for name in ("distance", "prim_id", "u", "v", "points", "normal"):
            np.testing.assert_array_equal(getattr(got, name), getattr(first[0], name),
                                          err_msg=f"packets of {packet_size}: {name}")
        # the same terms as one point's walk, summed in another order
        np.testing.assert_allclose(w, first[1], rtol=0, atol=1e-5)
    # a lane's sum does not depend on the other points of its packet
    query = PointQuery(built.runtime(scene))
    w = query.winding_numbers(built.tree(scene), points)
    for part in (slice(None, None, 3), slice(1, None, 2)):
        np.testing.assert_array_equal(query.winding_numbers(built.tree(scene), points[part]),
                                      w[part])


@pytest.mark.parametrize("bits", [5, 10])
def test_morton_order_uses_every_bit(bits):
    """coherent_order's cells: points along one axis, one per cell of the
    2^bits grid, come out in their order along it (each bit of the cell
    index counts), and along the diagonal too."""
    from hlbvh_cl.query.order import coherent_order
    cells = 1 << bits
    line = np.zeros((cells, 3), np.float32)
    line[:, 1] = (np.arange(cells) + 0.5) / cells
    shuffled = np.random.default_rng(2).permutation(cells)
    for points in (line, np.repeat(line[:, 1:2], 3, axis=1)):
        order = coherent_order(points[shuffled], bits)
        assert np.array_equal(shuffled[order], np.arange(cells))


@pytest.mark.parametrize("bits", [5, 10])
def test_device_order_is_the_numpy_order(bits, suite_device):
    """device_order (Morton keys in kernels/query/order.cl, the library's radix
    sort) gives exactly numpy's stable coherent_order: random points, a flat
    axis, repeats, a denormal extent, coordinates up to 3e38, one point."""
    from hlbvh_cl.device.runtime import runtime
    from hlbvh_cl.query.order import coherent_order, device_order
    rt = runtime(suite_device)
    rng = np.random.default_rng(bits)
    flat = rng.normal(size=(3001, 3)).astype(np.float32)
    flat[:, 1] = 7.0
    flat[::5] = flat[2]
    blocks = [rng.random((20000, 3)).astype(np.float32), flat,
              np.array([[0, 0, 0], [1e-44, 0, 0], [0, 1e-44, 3e38], [1e-44, 1, 3e38]] * 9,
                       np.float32),
              np.ones((1, 3), np.float32)]
    for block in blocks:
        for zero_copy in (False, True):
            order = device_order(rt, block, bits, zero_copy)
            assert order.dtype == np.uint32
            assert np.array_equal(order, coherent_order(block, bits))


def test_ray_classes_follow_the_packet_rules():
    """A ray's class (kernels/query/rays/ray_class.h): kz * 8, the axis of the largest
    direction component with ties to the lower axis, plus 1, 2, 4 for a
    negative x, y, z, -0 included."""
    from hlbvh_cl.query.order import ray_classes
    directions = np.array([[1, 1, 1], [-2, 2, 0], [0, -3, 3], [-0.0, 0, 1], [0, 0, -0.0],
                           [1, -5, 4], [-1, -2, -3], [7, 0, -7]], np.float32)
    np.testing.assert_array_equal(ray_classes(directions), [0, 1, 10, 17, 4, 10, 23, 4])


def test_device_ray_order_by_direction_is_the_numpy_order(suite_device):
    """device_order by direction (ray_keys' direction_key: the 2-D Morton
    code of the direction's cell on its cube face, under its class, a 23-bit
    key) gives exactly numpy's coherent_order, on directions whose face
    coordinates sit in the middle of their cells (so that no division
    rounding crosses a cell's edge) with majors of any power of two; the
    classes come out in order, and within a class the cells."""
    from hlbvh_cl.device.runtime import runtime
    from hlbvh_cl.query.order import (DIRECTION_BITS, coherent_order, device_order, direction_keys,
                                ray_classes)
    rt = runtime(suite_device)
    rng = np.random.default_rng(21)
    count = 5003  # not whole vectors of order.cl's KEY_ROWS
    half = ((1 << DIRECTION_BITS) - 1) / 2
    cells = rng.integers(0, 1 << DIRECTION_BITS, (count, 2))
    face = (cells + 0.5) / half - 1  # in (-1, 1), mid-cell
    kz = rng.integers(0, 3, count)
    major = np.where(rng.random(count) < 0.5, -1.0, 1.0) * 2.0 ** rng.integers(-3, 4, count)
    directions = np.empty((count, 3))
    rows = np.arange(count)
    directions[rows, kz] = major
    directions[rows, (kz + 1) % 3] = face[:, 0] * np.abs(major)
    directions[rows, (kz + 2) % 3] = face[:, 1] * np.abs(major)
    directions = directions.astype(np.float32)
    origins = rng.random((count, 3)).astype(np.float32)
    expected = coherent_order(origins, directions=directions, by_direction=True)
    classes = ray_classes(directions)[expected]
    assert (np.diff(classes.astype(np.int64)) >= 0).all()
    keys = direction_keys(directions)[expected]
    same = classes[1:] == classes[:-1]
    assert (np.diff(keys.astype(np.int64))[same] >= 0).all()
    assert len(np.unique(keys)) > count // 2  # the cells tell the rays apart
    for zero_copy in (False, True):
        order = device_order(rt, origins, zero_copy=zero_copy, directions=directions,
                             by_direction=True)
        assert np.array_equal(order, expected)


def test_concurrent_rays_are_rays_aimed_at_one_point():
    """order.concurrent_rays: rays from scattered origins (a box, or a
    plane) aimed at one point are; random rays, parallel rays, and rays from
    one origin (a sensor's, whose own order is kept) are not, nor rays aimed
    at points spread wider than their origins are apart."""
    from hlbvh_cl.query.order import concurrent_rays
    rng = np.random.default_rng(22)
    count = 20000
    box = rng.random((count, 3)).astype(np.float32) * 10 - 5
    plane = box.copy()
    plane[:, 2] = 3
    target = np.float32([0.3, -0.2, 0.1])
    assert concurrent_rays(box, target - box)
    assert concurrent_rays(plane, target - plane)
    assert concurrent_rays(box + 1e4, target - box)  # far from the world's origin
    assert not concurrent_rays(box, rng.normal(size=(count, 3)).astype(np.float32))
    assert not concurrent_rays(plane, np.tile(np.float32([0.1, 0.2, -1]), (count, 1)))
    assert not concurrent_rays(np.tile(target, (count, 1)), box)
    spread = target + rng.normal(scale=0.5, size=(count, 3)).astype(np.float32)
    assert not concurrent_rays(box, spread - box)


def test_device_ray_order_is_the_numpy_order(suite_device):
    """device_order with directions (ray_keys in kernels/query/order.cl: the
    class above the origin's code, a 32-bit key) gives exactly numpy's
    coherent_order; the classes come out in order, and rays of one origin
    keep their order within a class (a LiDAR's scan)."""
    from hlbvh_cl.device.runtime import runtime
    from hlbvh_cl.query.order import RAY_ORDER_BITS, coherent_order, device_order, ray_classes
    rt = runtime(suite_device)
    rng = np.random.default_rng(9)
    origins = rng.random((20005, 3)).astype(np.float32)
    directions = rng.normal(size=(20005, 3)).astype(np.float32)
    directions[::7, 0] = -0.0
    directions[::11] = [1, 1, 1]  # ties between axes
    directions[::13] = [-2, 2, 0]
    one_origin = np.zeros_like(origins)
    for points in (origins, one_origin):
        expected = coherent_order(points, RAY_ORDER_BITS, directions)
        classes = ray_classes(directions)[expected]
        assert (np.diff(classes.astype(np.int64)) >= 0).all()
        for zero_copy in (False, True):
            order = device_order(rt, points, RAY_ORDER_BITS, zero_copy, directions=directions)
            assert np.array_equal(order, expected)
    for c in np.unique(classes):
        assert (np.diff(expected[classes == c].astype(np.int64)) > 0).all()
