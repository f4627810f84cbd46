"""Ray semantics (hlbvh_cl.query.rays, kernels/query/rays.cl): closest hit and any
hit against the float64 brute-force oracle (tests/support/ray_cases.py), tmin/tmax,
misses, hits.points, several meshes, refit, input forms and chunks, and
trees deeper than the stack.  Packets, watertightness and precision have
their own modules (test_packets, test_watertight, test_precision); bad input
is in test_validation, buffer and result reuse in test_memory.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import hlbvh_cl
from hlbvh_cl.query.rays import RayQuery
from hlbvh_cl.core.tree import Tree
from hlbvh_cl.build.widen import widen
import built
from oracle import brute_force_intersect, brute_force_occluded
from ray_cases import (MESH_MAKERS, MESHES, T_RTOL, SceneCase, near_edge_or_limit, scene_cache,
                       assert_matches_oracle, random_rays, scene_case)


@pytest.fixture(scope="module")
def several():
    """Three overlapping meshes: geom_id matters."""
    knight = hlbvh_cl.Mesh.load(MESHES / "knight.ply")
    teapot = hlbvh_cl.Mesh.load(MESHES / "teapot.ply")
    bunny = hlbvh_cl.Mesh.load(MESHES / "bunny_small.ply")
    k_lo, k_hi = knight.bounds
    size = float(np.max(k_hi - k_lo))

    def fit(mesh, shift):
        lo, hi = mesh.bounds
        scale = 0.6 * size / float(np.max(hi - lo))
        centre = (lo + hi) / 2
        moved = (mesh.vertices - centre) * scale + (k_lo + k_hi) / 2 + np.asarray(shift) * size
        return hlbvh_cl.Mesh(moved, mesh.faces, name=mesh.name)

    return SceneCase([knight, fit(teapot, [0.25, 0.1, 0.0]), fit(bunny, [-0.2, 0.0, 0.15])])


# -- closest hit and any hit ----------------------------------------------------

def test_hit_points_match_the_oracle():
    """hits.points = origin + t * direction in the caller's coordinates,
    NaN on a miss; within float32 rounding of the float64 oracle's point."""
    case = scene_case("teapot")
    origins, directions = random_rays(case, 3000, 11)
    hits = case.scene.intersect(origins.astype(np.float64), directions)
    expected = brute_force_intersect(case.vertices, case.faces, origins, directions)
    points = hits.points
    assert points.dtype == np.float32 and points.shape == (len(origins), 3)
    assert np.array_equal(np.isnan(points).any(axis=1), ~hits.hit)
    hit = hits.hit & np.isfinite(expected["t"])
    assert hit.sum() > 500
    oracle = origins[hit].astype(np.float64) + expected["t"][hit, None] * directions[hit]
    np.testing.assert_allclose(points[hit], oracle, atol=1e-4 * case.scale)


@pytest.mark.parametrize("scale", [1.0, 1e-30, 1e30])
def test_hit_points_are_the_rays_own_and_outlive_them(scale):
    """points are origin + t * direction rounded as float32 numpy rounds them
    (also in a scene built in a rescaled frame, hlbvh_cl.core.frame), and they are
    the query's: writing into the ray arrays afterwards changes nothing."""
    case = scene_case("teapot")
    scene = case.scene if scale == 1.0 else hlbvh_cl.Scene(
        [hlbvh_cl.Mesh(m.vertices * np.float32(scale), m.faces) for m in case.scene.meshes],
        device=case.scene.device.id)
    origins, directions = random_rays(case, 2000, 12)
    origins = (origins * scale).astype(np.float32)
    directions = directions.astype(np.float32)
    hits = scene.intersect(origins, directions)
    expected = origins + hits.t[:, None] * directions  # float32 arithmetic, as the kernel's
    assert hits.hit.sum() > 300
    assert np.array_equal(hits.points[hits.hit], expected[hits.hit])
    assert np.isnan(hits.points[~hits.hit]).all()
    kept = hits.points.copy()
    origins[:] = 0.0
    directions[:] = 1.0
    assert np.array_equal(hits.points, kept, equal_nan=True)


@pytest.mark.parametrize("name", list(MESH_MAKERS))
def test_random_rays_match_oracle(name):
    case = scene_case(name)
    origins, directions = random_rays(case, 1500, seed=1)
    hits = case.scene.intersect(origins, directions)
    assert_matches_oracle(case, hits, origins, directions)
    if name != "degenerate":
        assert 0.1 < hits.hit.mean(), "the rays should mostly hit the scene"
    # occluded agrees with intersect (and so with the oracle, checked above)
    np.testing.assert_array_equal(case.scene.occluded(origins, directions), hits.hit)


@pytest.mark.parametrize("builder", ["hlbvh", "lbvh"])
def test_every_builders_tree_traverses(builder):
    case = SceneCase([MESH_MAKERS["bunny_small"](), MESH_MAKERS["knight"]()], builder=builder)
    origins, directions = random_rays(case, 1500, seed=14)
    hits = case.scene.intersect(origins, directions)
    assert_matches_oracle(case, hits, origins, directions)
    np.testing.assert_array_equal(case.scene.occluded(origins, directions), hits.hit)


def test_degenerate_triangles_are_never_hit():
    case = scene_case("degenerate")
    rng = np.random.default_rng(5)
    # aim at points of the zero-area triangles themselves
    targets = np.concatenate([case.vertices[[3, 4, 5, 6, 7]],
                              case.vertices[3] + rng.random((200, 1)) * (case.vertices[6] - case.vertices[3])])
    origins = targets + rng.normal(size=targets.shape)
    hits = case.scene.intersect(origins.astype(np.float32), (targets - origins).astype(np.float32))
    assert set(hits.prim_id[hits.hit].tolist()) <= {0, 1}


@pytest.mark.parametrize("name", ["knight", "teapot", "bunny_small", "cube"])
def test_occluded_with_tmax_matches_oracle(name):
    case = scene_case(name)
    origins, directions = random_rays(case, 1500, seed=2)
    hits = case.scene.intersect(origins, directions)
    rng = np.random.default_rng(3)
    # per-ray tmax around the first hit: about half of the hits get cut off
    tmax = np.where(hits.hit, hits.t * rng.uniform(0.5, 1.5, len(hits)), rng.uniform(0, 10, len(hits)))
    occluded = case.scene.occluded(origins, directions, tmax=tmax)
    ref = brute_force_occluded(case.vertices, case.faces, origins, directions, 0.0, tmax.astype(np.float32))
    for i in np.flatnonzero(occluded != ref):
        assert near_edge_or_limit(case, origins[i], directions[i], 0.0, float(np.float32(tmax[i])))
    cut = case.scene.intersect(origins, directions, tmax=tmax)
    np.testing.assert_array_equal(occluded, cut.hit)
    assert np.all(cut.t[cut.hit] <= tmax.astype(np.float32)[cut.hit])
    assert 0 < np.count_nonzero(hits.hit & ~cut.hit), "some hits should have been cut off"


@pytest.mark.parametrize("name", ["knight", "bunny_small", "teapot"])
def test_tmax_cuts_off_hits(name):
    case = scene_case(name)
    origins, directions = random_rays(case, 1000, seed=4)
    first = case.scene.intersect(origins, directions)
    assert first.hit.sum() > 100
    # just short of the first hit: nothing is left to hit
    short = np.where(first.hit, first.t * 0.999, np.inf).astype(np.float32)
    hits = case.scene.intersect(origins, directions, tmax=short)
    assert_matches_oracle(case, hits, origins, directions, tmax=short)
    assert not np.any(hits.hit & first.hit)
    # just beyond it: the same hits
    beyond = np.where(first.hit, first.t * 1.001, 1.0).astype(np.float32)
    hits = case.scene.intersect(origins, directions, tmax=beyond)
    assert_matches_oracle(case, hits, origins, directions, tmax=beyond)
    np.testing.assert_array_equal(hits.t[first.hit], first.t[first.hit])


@pytest.mark.parametrize("instanced", [False, True])
def test_a_hit_exactly_at_tmax_counts(instanced):
    """[tmin, tmax] is closed: with tmax (and tmin) set to the t of each
    ray's closest hit, every query still finds that hit.  The box entry
    the walk compares with the limit rounds, and could round past it (on
    the cube, about one ray in seven, before it was allowed for)."""
    case = scene_case("cube")
    scene = case.scene
    if instanced:
        scene = hlbvh_cl.Scene(case.scene.meshes,
                               instances=[(0, np.hstack([np.eye(3), np.zeros((3, 1))]))])
    origins, directions = random_rays(case, 2000, seed=8)
    first = scene.intersect(origins, directions)
    hit = first.hit
    assert hit.sum() > 500
    o, d, t = origins[hit], directions[hit], first.t[hit]
    again = scene.intersect(o, d, tmax=t)
    np.testing.assert_array_equal(again.t, t)
    np.testing.assert_array_equal(again.prim_id, first.prim_id[hit])
    assert scene.occluded(o, d, tmax=t).all()
    assert (scene.count_intersections(o, d, tmax=t) >= 1).all()
    assert (scene.count_intersections(o, d, tmin=t, tmax=t) >= 1).all()
    found = scene.intersect_all(o, d, tmax=t)
    np.testing.assert_array_equal(found.t[found.offsets[1:] - 1], t)


def test_float64_limits_keep_every_t_returned_within_them(suite_device):
    """tmin and tmax given in float64 are rounded inward to float32: a hit
    whose (float32) t lies just outside them as given is not taken, one at
    their float32 rounding is.  Squares at z = float32(0.1) and just below,
    hit at those t by rays up z."""
    above = float(np.float32(0.1))                     # 0.10000000149...
    below = float(np.nextafter(np.float32(0.1), np.float32(0.0)))  # 0.0999999940...
    assert below < 0.1 < above
    # two rays, one through each square only (x < 0 hits the first, x > 0 the second)
    squares = [hlbvh_cl.Mesh(np.array([[x0, -1.0, z], [x1, -1.0, z], [x1, 1.0, z], [x0, 1.0, z]],
                                      np.float32), [[0, 1, 2], [0, 2, 3]])
               for z, x0, x1 in ((above, -1.0, 0.0), (below, 0.0, 1.0))]
    scene = hlbvh_cl.Scene(squares, device=suite_device)
    origins = np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]], np.float32)
    directions = np.array([[0.0, 0.0, 1.0]] * 2, np.float32)
    assert scene.intersect(origins, directions).t.tolist() == [np.float32(above),
                                                               np.float32(below)]
    # tmax 0.1: t = 0.10000000149 (ray 0) lies past it, 0.0999999940 (ray 1) within
    hits = scene.intersect(origins, directions, tmax=0.1)
    assert hits.prim_id[0] == -1 and hits.t[1] == np.float32(below)
    assert scene.occluded(origins, directions, tmax=0.1).tolist() == [False, True]
    assert scene.count_intersections(origins, directions, tmax=0.1).tolist() == [0, 1]
    assert scene.intersect_all(origins, directions, tmax=0.1).counts.tolist() == [0, 1]
    # tmin between the two float32 values, nearer the lower: only ray 0's t lies above it
    tmin = below + (above - below) / 8
    assert scene.count_intersections(origins, directions, tmin=tmin).tolist() == [1, 0]
    assert scene.occluded(origins, directions, tmin=np.array([tmin, tmin])).tolist() == [True,
                                                                                       False]
    # limits already float32 keep their hits at exactly those t, one for all or per ray,
    # and per ray as columns of one array (strided, not contiguous) too
    assert scene.count_intersections(origins, directions, tmin=np.float32(below),
                                     tmax=np.float32(above)).tolist() == [1, 1]
    window = np.array([[below, above], [below, above]], np.float32)
    assert scene.count_intersections(origins, directions, tmin=window[:, 0],
                                     tmax=window[:, 1]).tolist() == [1, 1]
    # ... and a float32 tmax one step below a hit's t leaves that hit out
    window[0, 1] = np.nextafter(np.float32(above), np.float32(0.0))
    assert scene.intersect(origins, directions, tmin=window[:, 0],
                           tmax=window[:, 1]).prim_id.tolist()[0] == -1
    assert scene.occluded(origins, directions, tmin=window[:, 0],
                          tmax=window[:, 1]).tolist() == [False, True]


@pytest.mark.parametrize("name", ["knight", "bunny_small", "teapot", "cube"])
def test_rays_from_the_surface_with_tmin(name):
    case = scene_case(name)
    rng = np.random.default_rng(6)
    count = 1000
    faces = rng.integers(0, len(case.faces), count)
    weights = rng.dirichlet([1, 1, 1], count)
    points = np.einsum("rk,rkj->rj", weights, case.vertices[case.faces[faces]])
    directions = rng.normal(size=(count, 3))
    tmin = 1e-4 * case.extent / np.linalg.norm(directions, axis=1)
    origins, directions = points.astype(np.float32), directions.astype(np.float32)
    hits = case.scene.intersect(origins, directions, tmin=tmin)
    assert_matches_oracle(case, hits, origins, directions, tmin=tmin.astype(np.float32))
    assert np.all(hits.t[hits.hit] >= tmin.astype(np.float32)[hits.hit])
    # with tmin = 0 each ray may hit its own triangle at t ~ 0
    at_zero = case.scene.intersect(origins, directions)
    assert np.count_nonzero(at_zero.hit) >= np.count_nonzero(hits.hit)


@pytest.mark.parametrize("name", ["cube", "grid", "knight"])
def test_axis_parallel_rays(name):
    """Zero direction components (+0 and -0), origins on the box planes and
    on the meshes' own vertex coordinates."""
    case = scene_case(name)
    rng = np.random.default_rng(7)
    lo, hi = case.lo, case.hi
    levels = [np.unique(np.concatenate([[lo[k], hi[k], (lo[k] + hi[k]) / 2],
                                        rng.choice(case.vertices[:, k], 6),
                                        lo[k] + rng.random(6) * (hi[k] - lo[k])]))
              for k in range(3)]
    origins, directions = [], []
    for axis in range(3):
        a, b = [k for k in range(3) if k != axis]
        for sign in (1.0, -1.0):
            for zero in (0.0, -0.0):
                for x in levels[a]:
                    for y in levels[b]:
                        origin = np.empty(3)
                        origin[axis] = lo[axis] - 1 if sign > 0 else hi[axis] + 1
                        origin[a], origin[b] = x, y
                        direction = np.full(3, zero)
                        direction[axis] = sign
                        origins.append(origin)
                        directions.append(direction)
    origins = np.array(origins, np.float32)
    directions = np.array(directions, np.float32)
    assert np.any(np.signbit(directions) & (directions == 0)), "-0 components are tested"
    hits = case.scene.intersect(origins, directions)
    assert_matches_oracle(case, hits, origins, directions)
    assert hits.hit.any()
    np.testing.assert_array_equal(case.scene.occluded(origins, directions), hits.hit)


def test_axis_parallel_rays_in_a_face_plane_hit_its_edges():
    """A ray lying in the plane x = 0 of the cube's face (direction x = +0 or
    -0) must still enter the boxes and hit the faces it crosses at their edge."""
    case = scene_case("cube")
    origins = np.array([[0, 0.5, -1], [0, 0.5, -1], [1, 0.25, 2], [0.5, 0, -3], [0, 0, -1]], np.float32)
    directions = np.array([[0, 0, 1], [-0.0, 0, 1], [-0.0, -0.0, -1], [0, -0.0, 1], [0, 0, 1]],
                          np.float32)
    hits = case.scene.intersect(origins, directions)
    ref = assert_matches_oracle(case, hits, origins, directions)
    assert np.all(ref["prim"] >= 0) and hits.hit.all()
    np.testing.assert_allclose(hits.t, [1, 1, 1, 3, 1])


def test_several_meshes_geom_id(several):
    case = several
    origins, directions = random_rays(case, 3000, seed=8)
    hits = case.scene.intersect(origins, directions)
    assert_matches_oracle(case, hits, origins, directions)
    assert set(np.unique(hits.geom_id[hits.hit])) == {0, 1, 2}
    for geom_id, mesh in enumerate(case.meshes):
        mine = hits.geom_id == geom_id
        assert np.all(hits.prim_id[mine] < mesh.triangle_count)
    np.testing.assert_array_equal(case.scene.occluded(origins, directions), hits.hit)


def test_results_after_update_vertices_equal_a_fresh_scene():
    knight = hlbvh_cl.Mesh.load(MESHES / "knight.ply")
    teapot = hlbvh_cl.Mesh.load(MESHES / "teapot.ply")
    scene = hlbvh_cl.Scene([knight, teapot])
    v = knight.vertices.astype(np.float64)
    moved = v * 1.2 + 0.05 * np.sin(7 * v[:, [1, 2, 0]]) * np.ptp(v, axis=0)
    scene.update_vertices(0, moved)
    fresh = SceneCase([hlbvh_cl.Mesh(moved, knight.faces), teapot])
    origins, directions = random_rays(fresh, 2000, seed=9)
    updated = scene.intersect(origins, directions)
    rebuilt = fresh.scene.intersect(origins, directions)
    assert_matches_oracle(fresh, updated, origins, directions)
    np.testing.assert_array_equal(updated.hit, rebuilt.hit)
    same = (updated.geom_id == rebuilt.geom_id) & (updated.prim_id == rebuilt.prim_id)
    # same triangle -> bit-identical answers; a different one only at a tie
    np.testing.assert_array_equal(updated.t[same], rebuilt.t[same])
    np.testing.assert_array_equal(updated.u[same], rebuilt.u[same])
    np.testing.assert_array_equal(updated.normal[same], rebuilt.normal[same])
    np.testing.assert_allclose(updated.t[~same], rebuilt.t[~same], rtol=T_RTOL)


# -- input forms, empty batches, chunks -------------------------------------------

def test_input_forms_give_the_same_answer():
    case = scene_case("knight")
    origins, directions = random_rays(case, 200, seed=10)
    reference = case.scene.intersect(origins, directions)
    for o, d in [(origins.astype(np.float64), directions.astype(np.float64)),
                 (origins.tolist(), directions.tolist()),
                 (np.asfortranarray(origins), np.repeat(directions, 2, 0)[::2])]:
        hits = case.scene.intersect(o, d, tmin=np.zeros(len(origins)), tmax=np.full(len(origins), np.inf))
        for field in ("t", "prim_id", "geom_id", "u", "v", "normal"):
            np.testing.assert_array_equal(getattr(hits, field), getattr(reference, field))


def test_hits_fields():
    case = scene_case("cube")
    hits = case.scene.intersect([[0.5, 0.5, -1], [5, 5, 5]], [[0, 0, 1], [1, 0, 0]])
    assert len(hits) == 2
    np.testing.assert_array_equal(hits.hit, [True, False])
    assert hits.t.dtype == np.float32 and hits.u.dtype == np.float32 and hits.v.dtype == np.float32
    assert hits.prim_id.dtype == np.int32 and hits.geom_id.dtype == np.int32
    assert hits.normal.shape == (2, 3) and hits.normal.dtype == np.float32
    assert hits.t[0] == 1.0 and abs(hits.normal[0, 2]) == 1.0


def test_empty_batch():
    case = scene_case("cube")
    hits = case.scene.intersect(np.zeros((0, 3)), np.zeros((0, 3)))
    assert len(hits) == 0 and hits.normal.shape == (0, 3) and hits.hit.shape == (0,)
    assert hits.t.dtype == np.float32 and hits.prim_id.dtype == np.int32
    occluded = case.scene.occluded(np.zeros((0, 3)), np.zeros((0, 3)))
    assert occluded.shape == (0,) and occluded.dtype == bool


#: The launch engine's paths, (zero_copy, staging): the kernels on the
#: numpy arrays in place (PoCL), through device buffers (Intel's, GPUs),
#: and through pinned staging buffers (on request).
PATHS = {"in-place": (True, False), "device-copies": (False, False), "staging": (False, True)}


@pytest.mark.parametrize("path", PATHS)
def test_batches_split_into_chunks_equal_one_launch(path):
    """Also: the kernels on the numpy arrays in place (CPUs), through device
    buffers and through pinned staging buffers (on request) give the same
    results."""
    case = scene_case("bunny_small")
    origins, directions = random_rays(case, 5000, seed=11)
    rng = np.random.default_rng(12)
    tmin = rng.uniform(0, 0.2, len(origins))
    tmax = tmin + rng.uniform(0.5, 3, len(origins))
    whole = RayQuery(built.runtime(case.scene))
    chunked = RayQuery(built.runtime(case.scene), max_rays_per_launch=777)
    chunked.zero_copy, chunked.staging = PATHS[path]
    assert chunked.max_rays_per_launch == 777 and whole.max_rays_per_launch >= 5000
    a = whole.intersect(built.tree(case.scene), origins, directions, tmin, tmax)
    b = chunked.intersect(built.tree(case.scene), origins, directions, tmin, tmax)
    for field in ("t", "prim_id", "geom_id", "u", "v", "normal"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    tree = built.tree(case.scene)
    np.testing.assert_array_equal(whole.occluded(tree, origins, directions, tmin, tmax),
                                  chunked.occluded(tree, origins, directions, tmin, tmax))
    assert 0 < a.hit.mean() < 1


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("most", [1, 15])
def test_a_launch_limit_below_a_work_item_s_rays_still_launches_one(path, most):
    """max_rays_per_launch below the rays a work-item takes (16 in a CPU's
    packets): each launch takes one work-item's rays, and every path sizes
    its buffers for them (the staging path, on a query's first call, had
    reserved `most` rows and failed to reshape 16 into them)."""
    case = scene_case("bunny_small")
    origins, directions = random_rays(case, 40, seed=15)
    tree = built.tree(case.scene)
    whole = RayQuery(built.runtime(case.scene))
    small = RayQuery(built.runtime(case.scene), max_rays_per_launch=most)
    small.zero_copy, small.staging = PATHS[path]
    a, b = (q.intersect(tree, origins, directions) for q in (whole, small))
    for field in ("t", "prim_id", "geom_id", "u", "v", "normal"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    np.testing.assert_array_equal(whole.occluded(tree, origins, directions),
                                  small.occluded(tree, origins, directions))


@pytest.mark.parametrize("path", PATHS)
def test_launches_sized_by_their_cost_equal_one_launch(path, monkeypatch):
    """Launches of varying sizes (engine.LaunchSizes: a small first one, then
    what each costs allows, here a few rays) give the results of one."""
    from hlbvh_cl.query import engine
    case = scene_case("bunny_small")
    origins, directions = random_rays(case, 3000, seed=13)
    whole = RayQuery(built.runtime(case.scene))
    expected = whole.intersect(built.tree(case.scene), origins, directions)
    monkeypatch.setattr(engine, "FIRST_LAUNCH", 1000)
    monkeypatch.setattr(engine, "LAUNCH_SECONDS", 1e-6)  # a launch's worth: a few rays
    varied = RayQuery(built.runtime(case.scene))
    varied.zero_copy, varied.staging = PATHS[path]
    got = varied.intersect(built.tree(case.scene), origins, directions)
    for field in ("t", "prim_id", "geom_id", "u", "v", "normal", "points"):
        np.testing.assert_array_equal(getattr(got, field), getattr(expected, field))


def test_every_query_sized_by_its_cost_equals_one_launch(monkeypatch):
    """The same for all-hits (count and fill passes) and the point queries,
    whose batches this size go in Morton order (indexed launches)."""
    from hlbvh_cl.query import engine
    from hlbvh_cl.query import points as points_module
    case = scene_case("bunny_small")
    scene = case.scene
    origins, directions = random_rays(case, 3000, seed=14)
    lo, hi = scene.meshes[0].bounds
    near = (lo + np.random.default_rng(15).uniform(-0.2, 1.2, (3000, 3)) * (hi - lo))
    calls = {"count_intersections": lambda: [scene.count_intersections(origins, directions)],
             "intersect_all": lambda: [getattr(scene.intersect_all(origins, directions), name)
                                       for name in ("offsets", "t", "prim_id")],
             "closest_points": lambda: [scene.closest_points(near).distance],
             "signed_distance": lambda: [scene.signed_distance(near)]}
    expected = {name: call() for name, call in calls.items()}
    monkeypatch.setattr(engine, "FIRST_LAUNCH", 1000)
    monkeypatch.setattr(points_module, "FIRST_LAUNCH", 1000)
    monkeypatch.setattr(engine, "LAUNCH_SECONDS", 1e-6)
    for name, call in calls.items():
        for got, want in zip(call(), expected[name]):
            np.testing.assert_array_equal(got, want, err_msg=name)


class _Ended:
    """A profiled event that took `seconds`."""
    def __init__(self, seconds):
        self.profile = type("Profile", (), {"start": 0, "end": int(seconds * 1e9)})


def test_launch_sizes_follow_the_cost_per_item():
    from hlbvh_cl.query.engine import FIRST_LAUNCH, LAUNCH_SECONDS, LaunchSizes
    sizes = LaunchSizes(1 << 20)
    assert sizes.size == min(1 << 20, FIRST_LAUNCH)
    sizes.ended(_Ended(4 * LAUNCH_SECONDS), 1000)  # slow: a quarter of those next
    assert sizes.size == 250
    sizes.ended(_Ended(1e-6), 1000)  # fast: as many as allowed
    assert sizes.size == 1 << 20
    sizes.ended(_Ended(1e6), 10)  # ever so slow: one at a time, not none
    assert sizes.size == 1
    assert LaunchSizes(100).size == 100  # never past the most


# -- deep trees and the traversal stack -------------------------------------------

def morton_chain_mesh(duplicates: int = 16384) -> hlbvh_cl.Mesh:
    """Small triangles whose 63-bit Morton codes are 1 << j for j = 0..62 (one
    coordinate bit set each), many more at code 0 and one at the far corner:
    the Karras tree is a chain that splits off one triangle per bit, and the
    LBVH is deeper than 64."""
    centres = [np.eye(3)[axis] * 2.0 ** (a - 21) for a in range(21) for axis in range(3)]
    centres = np.array(centres + [np.zeros(3)] * duplicates + [np.ones(3)])
    sizes = 1e-3 * np.maximum(np.abs(centres).max(axis=1), 2.0 ** -21)[:, None, None]
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]]) - [1 / 3, 1 / 3, 0]
    vertices = (centres[:, None, :] + sizes * corners).reshape(-1, 3)
    return hlbvh_cl.Mesh(vertices, np.arange(len(vertices)).reshape(-1, 3), name="chain")


@pytest.mark.parametrize("packet_size", [1, 8, 16])
def test_a_tree_deeper_than_64_traces_within_its_stack(packet_size):
    """Every profile sizes its private stack from the tree's depth: a built
    tree of depth > 64 neither overflows nor loses a hit."""
    case = scene_cache.setdefault("chain", SceneCase([morton_chain_mesh()], "lbvh", 63))
    assert case.scene.stats.depth > 64
    centres = case.vertices[case.faces].mean(axis=1)
    chain = centres[:63]  # one ray down onto each triangle of the chain, then some at random
    rng = np.random.default_rng(5)
    origins = np.concatenate([chain + [0, 0, 1], rng.uniform(0, 1, (200, 3)) + [0, 0, 1]])
    directions = np.concatenate([np.tile([0.0, 0, -1], (63, 1)), rng.normal(size=(200, 3))])
    q = RayQuery(built.runtime(case.scene), packet_size=packet_size)
    hits = q.intersect(built.tree(case.scene), origins, directions)  # raises if the stack overflows
    assert hits.hit[:63].all()
    assert_matches_oracle(case, hits, origins, directions)
    np.testing.assert_array_equal(q.occluded(built.tree(case.scene), origins, directions), hits.hit)


@pytest.mark.parametrize("packet_size", [1, 8])
def test_stack_is_sized_from_the_tree_depth_and_overflow_raises(packet_size):
    """A hand-made chain tree that pushes one subtree per level: with its true
    depth the nearest hit is found; with a depth that lies, the query raises.
    (With packets of 8 the one ray fills a packet: the packet traversal's
    stack; with 1, the single-ray traversal's.)"""
    import pyopencl as cl
    from hlbvh_cl.core import layout

    rt = built.runtime(scene_case("cube").scene)
    levels = 40
    z = np.arange(1, levels + 1, dtype=np.float32)  # triangle k at z = k + 1
    tris = np.zeros(levels, layout.TRIANGLE)
    tris["v0"] = np.stack([np.full(levels, -1), np.full(levels, -1), z], 1)
    tris["v1"] = np.stack([np.full(levels, 3), np.full(levels, -1), z], 1)
    tris["v2"] = np.stack([np.full(levels, -1), np.full(levels, 3), z], 1)
    refs = np.zeros(levels, layout.TRIANGLE_REF)
    refs["prim_id"] = np.arange(levels)

    def box(k0, k1):  # triangles [k0, k1)
        return [-1, -1, z[k0]], [3, 3, z[k1 - 1]]

    # chain node j covers triangles [0, levels - j): its near child is the next
    # chain node, its far child a node holding only the farthest triangle.
    nodes = []
    chain = list(range(levels - 1))
    holder = list(range(levels - 1, 2 * levels - 2))
    for j in range(levels - 1):
        n = np.zeros((), layout.FLAT_NODE)
        remaining = levels - j
        if remaining - 1 > 1:
            n["left"], n["left_count"] = chain[j + 1], 0
        else:
            n["left"], n["left_count"] = 0, 1
        n["left_lo"], n["left_hi"] = box(0, remaining - 1)
        n["right"], n["right_count"] = holder[j], 0
        n["right_lo"], n["right_hi"] = box(remaining - 1, remaining)
        nodes.append(n)
    for j in range(levels - 1):
        n = np.zeros((), layout.FLAT_NODE)
        k = levels - 1 - j
        n["left"], n["left_count"] = k, 1
        n["left_lo"], n["left_hi"] = box(k, k + 1)
        n["right"], n["right_count"] = layout.EMPTY_CHILD, 0
        n["right_lo"], n["right_hi"] = np.inf, -np.inf
        nodes.append(n)
    nodes = np.array(nodes, layout.FLAT_NODE)
    mf = cl.mem_flags

    def upload(array):
        return cl.Buffer(rt.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=array)

    wide, wide_levels, _ = widen(rt, upload(nodes), len(nodes))
    tree = Tree(nodes=wide, triangles=upload(tris), refs=upload(refs),
                node_count=sum(count for _, count in wide_levels), levels=wide_levels,
                triangle_count=levels, bounds_lo=np.array([-1, -1, 1], np.float32),
                bounds_hi=np.array([3, 3, levels], np.float32))
    assert tree.depth > 3

    q = RayQuery(rt, packet_size=packet_size)
    origins, directions = [[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]]
    hits = q.intersect(tree, origins, directions)
    assert hits.prim_id[0] == 0 and hits.t[0] == 1.0
    assert q.occluded(tree, origins, directions)[0]
    lying = dataclasses.replace(tree, levels=wide_levels[:1])  # depth 1
    with pytest.raises(RuntimeError, match="stack"):
        q.intersect(lying, origins, directions)
