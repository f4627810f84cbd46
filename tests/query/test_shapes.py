"""The input shapes every query accepts (hlbvh_cl.core.inputs): leading
dimensions kept in the results, one origin broadcast to many directions,
Open3D's packed (..., 6) rays, and array-likes of any numeric kind.  Each
form is checked against the same rays given as plain (R, 3) float32 rows,
whose answers tests/query/test_rays.py checks against the float64 oracle."""
from __future__ import annotations

import numpy as np
import pytest

from hlbvh_cl.core import inputs
from ray_cases import scene_case

HIT_FIELDS = ("t", "prim_id", "geom_id", "u", "v", "normal", "points", "instance_id")


@pytest.fixture(scope="module")
def case():
    return scene_case("knight")


def _grid_rays(case, height=6, width=5, seed=3):
    """(H, W, 3) rays from points around the scene towards random points in it."""
    rng = np.random.default_rng(seed)
    lo, hi = case.lo, case.hi
    centre, size = (lo + hi) / 2, case.extent
    origins = centre + rng.normal(size=(height, width, 3)) * size
    targets = lo + rng.random((height, width, 3)) * (hi - lo)
    return origins, targets - origins


def _assert_same_hits(got, want, shape):
    for name in HIT_FIELDS:
        g, w = getattr(got, name), getattr(want, name)
        assert g.shape == shape + w.shape[1:], name
        np.testing.assert_array_equal(g.reshape(w.shape), w, err_msg=name)


def test_leading_dimensions_are_kept(case):
    origins, directions = _grid_rays(case)
    flat = case.scene.intersect(origins.reshape(-1, 3), directions.reshape(-1, 3))
    assert flat.hit.any() and not flat.hit.all()
    image = case.scene.intersect(origins, directions)
    _assert_same_hits(image, flat, (6, 5))
    assert image.hit.shape == (6, 5)
    blocked = case.scene.occluded(origins, directions)
    assert blocked.shape == (6, 5)
    np.testing.assert_array_equal(blocked.reshape(-1), flat.hit)


def test_one_origin_for_many_directions(case):
    """A LiDAR: one (3,) origin, directions over a sphere, in (H, W, 3)."""
    origin = (case.lo + case.hi) / 2 + np.array([0.0, 0.0, 2.0]) * case.extent
    rng = np.random.default_rng(5)
    directions = rng.normal(size=(16, 32, 3))
    got = case.scene.intersect(origin, directions)
    want = case.scene.intersect(np.tile(origin, (16 * 32, 1)), directions.reshape(-1, 3))
    _assert_same_hits(got, want, (16, 32))
    assert want.hit.any()
    # leading dimensions broadcast as numpy's: one origin per row of the image
    rows = np.repeat(origin[None, None, :], 16, axis=0)
    _assert_same_hits(case.scene.intersect(rows, directions), want, (16, 32))


def test_packed_rays_as_open3d_takes_them(case):
    origins, directions = _grid_rays(case, seed=8)
    packed = np.concatenate([origins, directions], axis=-1)
    want = case.scene.intersect(origins, directions)
    _assert_same_hits(case.scene.intersect(packed), want.__class__(
        **{n: getattr(want, n).reshape((30,) + getattr(want, n).shape[2:]) for n in HIT_FIELDS}),
        (6, 5))
    np.testing.assert_array_equal(case.scene.occluded(packed), want.hit)
    # limits broadcast to the leading shape too
    tmax = np.full((6, 1), 0.5)
    limited = case.scene.intersect(packed, tmax=tmax)
    np.testing.assert_array_equal(limited.hit, want.hit & (want.t <= 0.5))


def test_array_likes_of_any_kind(case):
    origins, directions = _grid_rays(case, seed=11)
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    want = case.scene.intersect(origins.astype(np.float32), directions.astype(np.float32))
    read_only = directions.astype(np.float32)
    read_only.flags.writeable = False
    strided = np.zeros((len(origins), 6), np.float32)
    strided[:, ::2] = origins
    forms = [(origins.tolist(), directions.tolist()),                # lists
             (origins, directions),                                  # float64
             (strided[:, ::2], read_only),                           # non-contiguous, read-only
             (np.asfortranarray(origins), directions.astype(np.float16).astype(np.float64))]
    for o, d in forms[:3]:
        _assert_same_hits(case.scene.intersect(o, d), want, (len(origins),))
    assert case.scene.intersect(*forms[3]).t.shape == (len(origins),)


def test_single_ray_gives_scalars(case):
    origins, directions = _grid_rays(case, seed=4)
    hit = case.scene.intersect(origins[0, 0], directions[0, 0])
    assert hit.t.shape == () and hit.normal.shape == (3,) and hit.points.shape == (3,)
    flat = case.scene.intersect(origins[0, :1], directions[0, :1])
    assert float(hit.t) == float(flat.t[0]) and int(hit.prim_id) == int(flat.prim_id[0])


def test_empty_leading_dimension(case):
    hits = case.scene.intersect(np.zeros((0, 4, 3)), np.ones((0, 4, 3)))
    assert hits.t.shape == (0, 4) and hits.normal.shape == (0, 4, 3)


@pytest.mark.parametrize("origins, directions, message", [
    (np.zeros((2, 3, 3)), np.ones((2, 3, 3)) * [1, 1, np.nan], r"directions\[0, 0\] = .*not finite"),
    (np.zeros(3) + [0, np.inf, 0], np.ones((4, 3)), r"origins = \[0.0, inf, 0.0\] is not finite"),
    (np.zeros((2, 3, 3)), np.ones((2, 3, 3)) * [[[1], [1], [0]], [[1], [1], [1]]], r"directions\[0, 2\] = .*zero length"),
    (np.zeros((2, 1, 3)) + [[[0, 0, 0]], [[0, 1e39, 0]]], np.ones((2, 4, 3)), r"origins\[1, 0\] = .*overflows"),
])
def test_bad_values_are_named_by_their_index_as_given(case, origins, directions, message):
    for query in (case.scene.intersect, case.scene.occluded):
        with pytest.raises(ValueError, match=message):
            query(origins, directions)


def test_bad_packed_values_name_the_part():
    rays = np.zeros((2, 2, 6))
    rays[..., 5] = 1.0
    rays[1, 0, 4] = np.nan
    with pytest.raises(ValueError, match=r"rays\[1, 0\]\[3:6\] = .*not finite"):
        inputs.rays(rays)
    rays[1, 0, 4] = 0.0
    rays[0, 1, 5] = 0.0
    with pytest.raises(ValueError, match=r"rays\[0, 1\]\[3:6\] = .*zero length"):
        inputs.rays(rays)


def test_limits_are_named_in_the_leading_shape():
    origins, directions = np.zeros((2, 3, 3)), np.ones((2, 3, 3))
    tmin = np.zeros((2, 3))
    tmin[1, 2] = -1.0
    with pytest.raises(ValueError, match=r"tmin\[1, 2\] = -1.0 must be finite and >= 0"):
        inputs.rays(origins, directions, tmin)
    with pytest.raises(ValueError, match=r"ray 1, 2: tmin\[1, 2\] = 5.0 is greater than"):
        inputs.rays(origins, directions, np.where(tmin < 0, 5.0, 0.0), 4.0)


def test_points_keep_their_shape_and_name_bad_rows():
    rows, shape = inputs.points(np.arange(24.0).reshape(2, 4, 3))
    assert shape == (2, 4) and rows.shape == (8, 3) and rows.dtype == np.float32
    np.testing.assert_array_equal(rows, np.arange(24.0).reshape(8, 3))
    bad = np.zeros((2, 4, 3))
    bad[1, 3, 0] = np.inf
    with pytest.raises(ValueError, match=r"points\[1, 3\] = \[inf, 0.0, 0.0\] is not finite"):
        inputs.points(bad)
    with pytest.raises(ValueError, match=r"points must have shape \(\.\.\., 3\)"):
        inputs.points(np.zeros((4, 2)))


def test_all_hits_and_counts_take_the_same_shapes(case):
    """intersect_all numbers (H, W) rays in C order and keeps the shape in
    counts; count_intersections answers in the leading shape; a packed
    (..., 6) array and a broadcast origin give the same hits."""
    origins, directions = _grid_rays(case, seed=21)
    flat = case.scene.intersect_all(origins.reshape(-1, 3), directions.reshape(-1, 3))
    grid = case.scene.intersect_all(origins, directions)
    assert grid.shape == (6, 5) and grid.counts.shape == (6, 5)
    for name in ("offsets", "ray_index", "t", "prim_id", "geom_id", "u", "v"):
        np.testing.assert_array_equal(getattr(grid, name), getattr(flat, name), err_msg=name)
    counts = case.scene.count_intersections(np.concatenate([origins, directions], axis=-1))
    assert counts.shape == (6, 5) and counts.dtype == np.int32
    np.testing.assert_array_equal(counts, grid.counts)
    assert counts.max() >= 2
    origin = origins[0, 0]
    one = case.scene.intersect_all(origin, directions)
    tiled = case.scene.intersect_all(np.broadcast_to(origin, directions.shape), directions)
    np.testing.assert_array_equal(one.t, tiled.t)
    np.testing.assert_array_equal(one.counts, case.scene.count_intersections(origin, directions))
