"""The brute-force oracle against cases worked out by hand."""
import numpy as np
import pytest

from oracle import brute_force_intersect, brute_force_occluded

# The unit right triangle in the z = 0 plane, normal +z.
UNIT = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
ONE_FACE = np.array([[0, 1, 2]])
DOWN = [0.0, 0.0, -1.0]


def test_ray_down_the_z_axis_hits_the_unit_triangle():
    hit = brute_force_intersect(UNIT, ONE_FACE, [[0.25, 0.5, 2.0]], [DOWN])
    # The hit point (0.25, 0.5, 0) = (1-u-v) v0 + u v1 + v v2 with v1 = x, v2 = y.
    assert hit["t"][0] == pytest.approx(2.0)
    assert hit["prim"][0] == 0
    assert hit["u"][0] == pytest.approx(0.25)
    assert hit["v"][0] == pytest.approx(0.5)
    np.testing.assert_allclose(hit["normal"][0], [0, 0, 1])


def test_t_is_in_units_of_the_direction_length():
    hit = brute_force_intersect(UNIT, ONE_FACE, [[0.2, 0.2, 3.0]], [[0, 0, -2.0]])
    assert hit["t"][0] == pytest.approx(1.5)


@pytest.mark.parametrize("origin, direction", [
    ([0.8, 0.8, 1.0], DOWN),         # beside the hypotenuse
    ([-0.1, 0.5, 1.0], DOWN),        # left of the triangle
    ([0.2, 0.2, 1.0], [0, 0, 1.0]),  # pointing away: t = -1
    ([0.2, 0.2, 1.0], [1.0, 0, 0]),  # parallel to the plane
    ([0.2, 0.2, 1.0], [0, 0, 0.0]),  # no direction at all
])
def test_misses(origin, direction):
    hit = brute_force_intersect(UNIT, ONE_FACE, [origin], [direction])
    assert hit["t"][0] == np.inf and hit["prim"][0] == -1
    assert hit["u"][0] == 0 and hit["v"][0] == 0 and not hit["normal"][0].any()
    assert not brute_force_occluded(UNIT, ONE_FACE, [origin], [direction])[0]


def test_edges_and_both_ends_of_the_interval_count():
    origins = [[0.5, 0.5, 1.0], [0.0, 0.0, 1.0], [0.2, 0.2, 1.0], [0.2, 0.2, 1.0]]
    tmin = [0.0, 0.0, 1.0, 0.0]
    tmax = [np.inf, np.inf, 5.0, 1.0]
    hit = brute_force_intersect(UNIT, ONE_FACE, origins, [DOWN] * 4, tmin=tmin, tmax=tmax)
    np.testing.assert_array_equal(hit["prim"], [0, 0, 0, 0])
    # Just outside the interval misses.
    hit = brute_force_intersect(UNIT, ONE_FACE, origins[2:], [DOWN] * 2,
                                tmin=[1.0 + 1e-9, 0.0], tmax=[5.0, 1.0 - 1e-9])
    np.testing.assert_array_equal(hit["prim"], [-1, -1])


def test_degenerate_triangle_is_never_hit():
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 0, 0]])
    faces = np.array([[0, 1, 2], [0, 3, 1]])  # collinear, and a repeated vertex
    origins = [[0.5, 0.0, 1.0], [1.0, 0.0, 1.0]]
    hit = brute_force_intersect(vertices, faces, origins, [DOWN, DOWN])
    np.testing.assert_array_equal(hit["prim"], [-1, -1])
    assert not brute_force_occluded(vertices, faces, origins, [DOWN, DOWN]).any()


def test_closest_of_stacked_triangles_and_winding_of_the_normal():
    # Triangle 0 at z = 0 (normal +z); triangle 1 at z = 1, wound the other way.
    vertices = np.vstack([UNIT, UNIT + [0, 0, 1]])
    faces = np.array([[0, 1, 2], [3, 5, 4]])
    hit = brute_force_intersect(vertices, faces, [[0.1, 0.3, 5.0], [0.1, 0.1, -5.0]],
                                [DOWN, [0, 0, 1.0]])
    np.testing.assert_array_equal(hit["prim"], [1, 0])
    np.testing.assert_allclose(hit["t"], [4.0, 5.0])
    np.testing.assert_allclose(hit["normal"], [[0, 0, -1], [0, 0, 1]])
    # On triangle 1 = (v3, v5, v4): u weighs v5 = (0, 1, 1), v weighs v4 = (1, 0, 1).
    assert hit["u"][0] == pytest.approx(0.3) and hit["v"][0] == pytest.approx(0.1)
    # With tmax short of triangle 1 only an occlusion ray that reaches it counts.
    np.testing.assert_array_equal(
        brute_force_occluded(vertices, faces, [[0.1, 0.1, 5.0]] * 2, [DOWN] * 2,
                             tmax=[3.9, 4.0]), [False, True])


def test_chunking_gives_the_same_answer(monkeypatch):
    import oracle

    rng = np.random.default_rng(7)
    vertices = rng.uniform(-1, 1, (60, 3))
    faces = rng.integers(0, 60, (40, 3))
    origins = rng.uniform(-2, 2, (50, 3))
    directions = -origins + rng.normal(0, 0.3, (50, 3))
    whole = brute_force_intersect(vertices, faces, origins, directions)
    monkeypatch.setattr(oracle, "CHUNK_ELEMENTS", 7)
    pieces = brute_force_intersect(vertices, faces, origins, directions)
    assert (whole["prim"] >= 0).sum() > 10  # the case is not all misses
    for key in whole:
        np.testing.assert_array_equal(whole[key], pieces[key])
    np.testing.assert_array_equal(brute_force_occluded(vertices, faces, origins, directions),
                                  whole["prim"] >= 0)
