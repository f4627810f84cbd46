"""Ray queries (hlbvh_cl.query, kernels/traverse.cl) against the float64
brute-force oracle (tests/oracle.py).

Agreement is exact for hit/miss, prim_id and geom_id, except where float32
rounding can decide the answer: a ray within rounding of a triangle's edge or
of tmin/tmax, and near-ties (two triangles at nearly the same t).  Those
exceptions are recomputed in float64 here, never assumed.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import hlbvh_cl
from hlbvh_cl import query as query_module
from hlbvh_cl.query import Hits, RayQuery
from hlbvh_cl.results import MIN_POOLED_BYTES
from hlbvh_cl.tree import DeviceTree
from oracle import brute_force_intersect, brute_force_occluded
from shapes import grid_mesh

MESHES = Path(__file__).resolve().parent.parent / "scenes" / "meshes"

T_RTOL = 1e-5          # relative tolerance on t (the brief's 1e-5)
EDGE_TOLERANCE = 1e-4  # barycentric distance to an edge that float32 may decide
UV_ATOL = 1e-4
NORMAL_ATOL = 1e-4


# -- scenes -------------------------------------------------------------------

def cube_mesh(lo=0.0, hi=1.0) -> hlbvh_cl.Mesh:
    corners = np.array([[x, y, z] for x in (lo, hi) for y in (lo, hi) for z in (lo, hi)])
    faces = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
             [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return hlbvh_cl.Mesh(corners, faces, name="cube")


def tetrahedron_mesh() -> hlbvh_cl.Mesh:
    vertices = [[0.1, -0.3, 0.2], [1.3, 0.1, -0.4], [0.2, 1.1, 0.3], [0.4, 0.3, 1.2]]
    return hlbvh_cl.Mesh(vertices, [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]], name="tetra")


def triangle_mesh() -> hlbvh_cl.Mesh:
    return hlbvh_cl.Mesh([[-1.0, -1.0, 0.5], [2.0, -0.5, 0.0], [0.0, 1.5, -0.25]], [[0, 1, 2]],
                         name="triangle")




def degenerate_mesh() -> hlbvh_cl.Mesh:
    """Two real triangles and three zero-area ones (repeated vertex, collinear, a point)."""
    vertices = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [0.5, 0.5, 1],
                [2, 2, 1], [0.25, 0.25, 0.5]]
    faces = [[0, 1, 2], [3, 4, 2], [3, 3, 4], [3, 5, 6], [7, 7, 7]]
    return hlbvh_cl.Mesh(vertices, faces, name="degenerate")


MESH_MAKERS = {
    "knight": lambda: hlbvh_cl.Mesh.load(MESHES / "knight.ply"),
    "teapot": lambda: hlbvh_cl.Mesh.load(MESHES / "teapot.ply"),
    "bunny_small": lambda: hlbvh_cl.Mesh.load(MESHES / "bunny_small.ply"),
    "cube": cube_mesh,
    "tetrahedron": tetrahedron_mesh,
    "triangle": triangle_mesh,
    "grid": grid_mesh,
    "degenerate": degenerate_mesh,
}


class SceneCase:
    """A Scene plus the concatenated arrays the oracle needs."""

    def __init__(self, meshes, builder: str = "hlbvh", morton_bits: int = 30, scene=None):
        """``scene``: one already built over ``meshes`` (else built here)."""
        self.meshes = meshes
        self.scene = scene or hlbvh_cl.Scene(meshes, builder=builder, morton_bits=morton_bits)
        self.vertices = np.concatenate([m.vertices for m in meshes]).astype(np.float64)
        offsets = np.cumsum([0] + [m.vertex_count for m in meshes])
        self.faces = np.concatenate([m.faces + off for m, off in zip(meshes, offsets)])
        self.first_face = np.cumsum([0] + [m.triangle_count for m in meshes])
        self.lo, self.hi = self.vertices.min(axis=0), self.vertices.max(axis=0)
        self.extent = float(np.max(self.hi - self.lo))
        self.scale = max(self.extent, float(np.max(np.abs(self.vertices))))

    def global_prim(self, hits: Hits) -> np.ndarray:
        """Index into the concatenated faces; -1 on a miss."""
        out = np.full(len(hits), -1, np.int64)
        hit = hits.hit
        out[hit] = self.first_face[hits.geom_id[hit]] + hits.prim_id[hit]
        return out


_scene_cache: dict[str, SceneCase] = {}


def scene_case(name: str) -> SceneCase:
    if name not in _scene_cache:
        _scene_cache[name] = SceneCase([MESH_MAKERS[name]()])
    return _scene_cache[name]


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


# -- rays ---------------------------------------------------------------------

def random_rays(case: SceneCase, count: int, seed: int):
    """Origins around the scene aimed into its box, plus 20% random directions (float32)."""
    rng = np.random.default_rng(seed)
    size = np.maximum(case.hi - case.lo, 0.25 * case.extent)  # flat scenes too
    centre = (case.lo + case.hi) / 2
    origins = centre + (rng.random((count, 3)) - 0.5) * 3 * size
    targets = case.lo + rng.random((count, 3)) * (case.hi - case.lo)
    directions = targets - origins
    wild = rng.random(count) < 0.2
    directions[wild] = rng.normal(size=(wild.sum(), 3))
    directions *= rng.uniform(0.5, 2.0, (count, 1))  # t is in units of |direction|
    return origins.astype(np.float32), directions.astype(np.float32)


# -- float64 checks of the cases float32 may decide ---------------------------

def _pair_test(case: SceneCase, origins, directions, prims):
    """Moller-Trumbore in float64 of ray i against triangle prims[i]: t and the
    barycentric distance to the nearest edge (negative outside)."""
    o = origins.astype(np.float64)
    d = directions.astype(np.float64)
    v0, v1, v2 = (case.vertices[case.faces[prims, k]] for k in range(3))
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = o - v0
        u = np.einsum("ij,ij->i", s, p) / det
        q = np.cross(s, e1)
        v = np.einsum("ij,ij->i", d, q) / det
        t = np.einsum("ij,ij->i", e2, q) / det
    margin = np.minimum(np.minimum(u, v), 1 - u - v)
    return t, np.where(np.isfinite(margin), margin, -np.inf)


def _near_edge_or_limit(case, origin, direction, tmin, tmax) -> bool:
    """Whether some triangle is hit or missed only by float32 rounding: the ray
    passes within EDGE_TOLERANCE (barycentric) of it, or its t is within
    T_RTOL of tmin or tmax."""
    n = len(case.faces)
    prims = np.arange(n)
    t, margin = _pair_test(case, np.repeat(origin[None], n, 0), np.repeat(direction[None], n, 0),
                           prims)
    scale = np.maximum(np.abs(t), 1e-30) * T_RTOL
    in_range = (t >= tmin - scale) & (t <= tmax + scale)
    near_edge = in_range & (np.abs(margin) <= EDGE_TOLERANCE)
    near_limit = (margin >= -EDGE_TOLERANCE) & ((np.abs(t - tmin) <= scale) | (np.abs(t - tmax) <= scale))
    return bool(np.any(near_edge | near_limit))


def assert_matches_oracle(case: SceneCase, hits: Hits, origins, directions, tmin=0.0, tmax=np.inf):
    count = len(origins)
    tmin_all = np.broadcast_to(np.asarray(tmin, np.float64), (count,))
    tmax_all = np.broadcast_to(np.asarray(tmax, np.float64), (count,))
    ref = brute_force_intersect(case.vertices, case.faces, origins, directions, tmin, tmax)
    ref_hit = ref["prim"] >= 0
    assert len(hits) == count

    # hit / miss
    for i in np.flatnonzero(hits.hit != ref_hit):
        assert _near_edge_or_limit(case, origins[i], directions[i], tmin_all[i], tmax_all[i]), (
            f"ray {i}: kernel {'hits' if hits.hit[i] else 'misses'}, oracle "
            f"{'hits' if ref_hit[i] else 'misses'}, and no triangle is within rounding")

    # misses are reported as such
    miss = ~hits.hit
    assert np.all(np.isinf(hits.t[miss])) and np.all(hits.prim_id[miss] == -1)
    assert np.all(hits.geom_id[miss] == -1)
    assert np.all(hits.normal[miss] == 0) and np.all(hits.u[miss] == 0) and np.all(hits.v[miss] == 0)

    # which triangle: equal, or a near-tie that float64 confirms
    both = hits.hit & ref_hit
    prims = case.global_prim(hits)
    differ = np.flatnonzero(both & (prims != ref["prim"]))
    if len(differ):
        t_ours, margin = _pair_test(case, origins[differ], directions[differ], prims[differ])
        tie = (np.abs(t_ours - ref["t"][differ]) <= T_RTOL * np.abs(ref["t"][differ])) & \
              (margin >= -EDGE_TOLERANCE)
        assert tie.all(), (f"rays {differ[~tie][:5]}: kernel picked triangles "
                           f"{prims[differ[~tie]][:5]}, oracle {ref['prim'][differ[~tie]][:5]}")

    # t, everywhere both hit (ties have equal t too)
    # plus, for t ~ 0, an absolute term: float32 rounds (vertex - origin) by
    # ~1e-7 of the coordinates' magnitude, which moves t by that over the
    # speed of the ray along the normal (large for grazing rays)
    error = np.abs(hits.t[both] - ref["t"][both])
    speed = np.abs(np.einsum("ij,ij->i", ref["normal"][both], directions[both].astype(np.float64)))
    allowed = T_RTOL * np.abs(ref["t"][both]) + 1e-6 * case.scale / np.maximum(speed, 1e-30)
    worst = np.argmax(error - allowed) if len(error) else 0
    assert np.all(error <= allowed), (f"ray {np.flatnonzero(both)[worst]}: t = {hits.t[both][worst]}, "
                                      f"oracle {ref['t'][both][worst]}")
    same = both & (prims == ref["prim"])
    np.testing.assert_allclose(hits.u[same], ref["u"][same], atol=UV_ATOL)
    np.testing.assert_allclose(hits.v[same], ref["v"][same], atol=UV_ATOL)
    np.testing.assert_allclose(hits.normal[same], ref["normal"][same], atol=NORMAL_ATOL)
    np.testing.assert_allclose(np.linalg.norm(hits.normal[hits.hit], axis=1), 1.0, atol=1e-6)
    return ref


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
        assert _near_edge_or_limit(case, origins[i], directions[i], 0.0, float(np.float32(tmax[i])))
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


# -- API: input forms, chunking, buffers ----------------------------------------

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


@pytest.mark.parametrize("zero_copy", [True, False], ids=["in-place", "device-copies"])
def test_batches_split_into_chunks_equal_one_launch(zero_copy):
    """Also: the kernels on the numpy arrays in place (CPUs) and through device
    buffers (GPUs) give the same results."""
    case = scene_case("bunny_small")
    origins, directions = random_rays(case, 5000, seed=11)
    rng = np.random.default_rng(12)
    tmin = rng.uniform(0, 0.2, len(origins))
    tmax = tmin + rng.uniform(0.5, 3, len(origins))
    whole = RayQuery(case.scene._runtime)
    chunked = RayQuery(case.scene._runtime, max_rays_per_launch=777)
    chunked.zero_copy = zero_copy
    assert chunked.max_rays_per_launch == 777 and whole.max_rays_per_launch >= 5000
    a = whole.intersect(case.scene._tree, origins, directions, tmin, tmax)
    b = chunked.intersect(case.scene._tree, origins, directions, tmin, tmax)
    for field in ("t", "prim_id", "geom_id", "u", "v", "normal"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    np.testing.assert_array_equal(whole.occluded(case.scene._tree, origins, directions, tmin, tmax),
                                  chunked.occluded(case.scene._tree, origins, directions, tmin, tmax))
    assert 0 < a.hit.mean() < 1


@pytest.mark.parametrize("chunk", [None, 1 << 16, 777], ids=["one-launch", "page-chunks", "odd-chunks"])
def test_results_written_in_place_equal_read_back_results(chunk):
    """With device copies of the rays, the kernels may write the results
    straight into the pool's page-aligned result arrays (Intel's CPU runtime
    does by default): the same results as reading them back, also when a
    batch splits into chunks, some of which do not start on a page."""
    case = scene_case("knight")
    count = MIN_POOLED_BYTES // 4 + 1000
    origins, directions = random_rays(case, count, seed=16)
    copied = RayQuery(case.scene._runtime)
    copied.zero_copy, copied.outputs_in_place = False, False
    written = RayQuery(case.scene._runtime, max_rays_per_launch=chunk)
    written.zero_copy, written.outputs_in_place = False, True
    expected = copied.intersect(case.scene._tree, origins, directions)
    got = written.intersect(case.scene._tree, origins, directions)
    for field in ("t", "prim_id", "geom_id", "u", "v", "normal"):
        assert getattr(got, field).ctypes.data % query_module.RESULT_ALIGNMENT == 0
        np.testing.assert_array_equal(getattr(got, field), getattr(expected, field))
    assert 0 < got.hit.mean() < 1
    np.testing.assert_array_equal(written.occluded(case.scene._tree, origins, directions),
                                  copied.occluded(case.scene._tree, origins, directions))


def test_buffers_are_reused_and_only_grow():
    """Where the kernels cannot use the numpy arrays in place (GPUs)."""
    case = scene_case("cube")
    q = RayQuery(case.scene._runtime)
    q.zero_copy = False
    origins, directions = random_rays(case, 300, seed=13)
    q.intersect(case.scene._tree, origins, directions)
    buffers = dict(q._buffers)
    q.intersect(case.scene._tree, origins[:100], directions[:100])
    q.occluded(case.scene._tree, origins[:200], directions[:200])
    assert q._buffers == buffers
    q.intersect(case.scene._tree, np.repeat(origins, 4, 0), np.repeat(directions, 4, 0))
    assert q._buffers["origins"] is not buffers["origins"]


def test_in_place_queries_take_any_array_layout():
    """Read-only, unaligned and shared rays in place give what device copies
    give; results large enough to come from the ResultPool survive a later
    query."""
    case = scene_case("knight")
    count = MIN_POOLED_BYTES // 4 + 1000
    origins, directions = random_rays(case, count, seed=15)
    in_place = RayQuery(case.scene._runtime)
    in_place.zero_copy = True
    copied = RayQuery(case.scene._runtime)
    copied.zero_copy = False
    expected = copied.intersect(case.scene._tree, origins, directions)
    raw = np.zeros(origins.nbytes + 5, np.uint8)
    unaligned = raw[1:1 + origins.nbytes].view(np.float32).reshape(origins.shape)  # 1-byte offset
    unaligned[:] = origins
    frozen = directions.copy()
    frozen.flags.writeable = False
    got = in_place.intersect(case.scene._tree, unaligned, frozen)
    in_place.intersect(case.scene._tree, origins[::-1].copy(), directions[::-1].copy())
    for field in ("t", "prim_id", "geom_id", "u", "v", "normal"):
        np.testing.assert_array_equal(getattr(got, field), getattr(expected, field))
    # one array as both origins and directions, and two overlapping views
    points = np.ascontiguousarray(origins[:500])
    np.testing.assert_array_equal(in_place.intersect(case.scene._tree, points, points).t,
                                  copied.intersect(case.scene._tree, points, points.copy()).t)
    rows = np.ascontiguousarray(origins[:750])
    overlapping = in_place.intersect(case.scene._tree, rows[:500], rows[250:])
    assert_matches_oracle(case, overlapping, rows[:500].copy(), rows[250:].copy())


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
    case = _scene_cache.setdefault("chain", SceneCase([morton_chain_mesh()], "lbvh", 63))
    assert case.scene.stats.depth > 64
    centres = case.vertices[case.faces].mean(axis=1)
    chain = centres[:63]  # one ray down onto each triangle of the chain, then some at random
    rng = np.random.default_rng(5)
    origins = np.concatenate([chain + [0, 0, 1], rng.uniform(0, 1, (200, 3)) + [0, 0, 1]])
    directions = np.concatenate([np.tile([0.0, 0, -1], (63, 1)), rng.normal(size=(200, 3))])
    q = RayQuery(case.scene._runtime, packet_size=packet_size)
    hits = q.intersect(case.scene._tree, origins, directions)  # raises if the stack overflows
    assert hits.hit[:63].all()
    assert_matches_oracle(case, hits, origins, directions)
    np.testing.assert_array_equal(q.occluded(case.scene._tree, origins, directions), hits.hit)


@pytest.mark.parametrize("packet_size", [1, 8])
def test_stack_is_sized_from_the_tree_depth_and_overflow_raises(packet_size):
    """A hand-made chain tree that pushes one subtree per level: with its true
    depth the nearest hit is found; with a depth that lies, the query raises.
    (With packets of 8 the one ray fills a packet: the packet traversal's
    stack; with 1, the single-ray traversal's.)"""
    import pyopencl as cl
    from hlbvh_cl import layout

    rt = scene_case("cube").scene._runtime
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

    def tree(depth):
        return DeviceTree(nodes=upload(nodes), triangles=upload(tris), refs=upload(refs),
                          parents=upload(np.full(len(nodes), -1, np.int32)), node_count=len(nodes),
                          leaf_count=levels, triangle_count=levels, depth=depth,
                          bounds_lo=np.array([-1, -1, 1], np.float32),
                          bounds_hi=np.array([3, 3, levels], np.float32))

    q = RayQuery(rt, packet_size=packet_size)
    origins, directions = [[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]]
    hits = q.intersect(tree(levels), origins, directions)
    assert hits.prim_id[0] == 0 and hits.t[0] == 1.0
    assert q.occluded(tree(levels), origins, directions)[0]
    with pytest.raises(RuntimeError, match="stack"):
        q.intersect(tree(1), origins, directions)


# -- bad input --------------------------------------------------------------------

GOOD_O = np.zeros((3, 3))
GOOD_D = np.array([[0, 0, 1.0]] * 3)


def _with_row(array, row, value):
    array = np.array(array, dtype=np.float64)
    array[row] = value
    return array


BAD_INPUTS = [
    # (origins, directions, tmin, tmax, exception, message fragment)
    (np.zeros((3, 2)), GOOD_D, 0.0, np.inf, ValueError, r"origins must have shape \(R, 3\)"),
    (np.zeros(3), GOOD_D, 0.0, np.inf, ValueError, r"origins must have shape"),
    (GOOD_O, np.zeros((3, 3, 1)), 0.0, np.inf, ValueError, r"directions must have shape"),
    (np.zeros((4, 3)), GOOD_D, 0.0, np.inf, ValueError, r"origins has 4 rows but directions has 3"),
    (_with_row(GOOD_O, 1, [0, np.nan, 0]), GOOD_D, 0.0, np.inf, ValueError, r"origins\[1\].*not finite"),
    (_with_row(GOOD_O, 2, [np.inf, 0, 0]), GOOD_D, 0.0, np.inf, ValueError, r"origins\[2\].*not finite"),
    (_with_row(GOOD_O, 0, [1e39, 0, 0]), GOOD_D, 0.0, np.inf, ValueError, r"origins\[0\].*overflows float32"),
    (GOOD_O, _with_row(GOOD_D, 2, [0, -np.inf, 1]), 0.0, np.inf, ValueError, r"directions\[2\].*not finite"),
    (GOOD_O, _with_row(GOOD_D, 1, [0, 0, 0]), 0.0, np.inf, ValueError, r"directions\[1\].*zero length"),
    (GOOD_O, _with_row(GOOD_D, 1, [-0.0, 0, 0]), 0.0, np.inf, ValueError, r"directions\[1\].*zero length"),
    (GOOD_O, _with_row(GOOD_D, 0, [1e-40, 0, 0]), 0.0, np.inf, ValueError, r"directions\[0\].*too short"),
    (GOOD_O, _with_row(GOOD_D, 2, [1e-50, 0, 0]), 0.0, np.inf, ValueError, r"directions\[2\].*zero length"),
    (GOOD_O, GOOD_D, -1.0, np.inf, ValueError, r"tmin = -1.0 must be finite and >= 0"),
    (GOOD_O, GOOD_D, [0.0, -0.5, 0.0], np.inf, ValueError, r"tmin\[1\] = -0.5"),
    (GOOD_O, GOOD_D, np.nan, np.inf, ValueError, r"tmin is NaN"),
    (GOOD_O, GOOD_D, np.inf, np.inf, ValueError, r"tmin = inf must be finite"),
    (GOOD_O, GOOD_D, 0.0, [1.0, np.nan, 1.0], ValueError, r"tmax\[1\] is NaN"),
    (GOOD_O, GOOD_D, 2.0, 1.0, ValueError, r"tmin = 2.0 is greater than tmax = 1.0"),
    (GOOD_O, GOOD_D, [0.0, 0.0, 5.0], [1.0, 1.0, 4.0], ValueError, r"ray 2: tmin\[2\] = 5.0 is greater than tmax\[2\] = 4.0"),
    (GOOD_O, GOOD_D, 0.0, -1.0, ValueError, r"tmin = 0.0 is greater than tmax = -1.0"),
    (GOOD_O, GOOD_D, [0.0, 0.0], np.inf, ValueError, r"tmin has 2 entries but there are 3 rays"),
    (GOOD_O, GOOD_D, 0.0, np.ones((3, 1)), ValueError, r"tmax must be a scalar or have shape \(R,\)"),
    (GOOD_O.astype(complex), GOOD_D, 0.0, np.inf, TypeError, r"origins must hold real numbers"),
    (GOOD_O, GOOD_D.astype(bool), 0.0, np.inf, TypeError, r"directions must hold real numbers"),
    (GOOD_O, [["a", "b", "c"]] * 3, 0.0, np.inf, TypeError, r"directions must hold real numbers"),
    ([[0, 0, 0], [0, 0]], GOOD_D[:2], 0.0, np.inf, ValueError, r"origins is not a rectangular"),
    (GOOD_O, GOOD_D, "0", np.inf, TypeError, r"tmin must hold real numbers"),
]


@pytest.mark.parametrize("origins, directions, tmin, tmax, error, message", BAD_INPUTS,
                         ids=[f"{i}:{case[-1][:30]}" for i, case in enumerate(BAD_INPUTS)])
def test_bad_input_raises_before_any_kernel(monkeypatch, origins, directions, tmin, tmax, error, message):
    case = scene_case("cube")

    def no_launch(*args, **kwargs):
        raise AssertionError("a kernel was launched for bad input")

    monkeypatch.setattr(RayQuery, "_run", no_launch)
    with pytest.raises(error, match=message):
        case.scene.intersect(origins, directions, tmin, tmax)
    with pytest.raises(error, match=message):
        case.scene.occluded(origins, directions, tmin, tmax)


def test_short_directions_are_found_in_any_block_of_a_large_batch(monkeypatch):
    """The direction check goes block by block and only looks at rows in the
    blocks that hold a tiny component: a short row is found (and named) past
    the first block, while tiny components in a row that is long enough pass."""
    case = scene_case("cube")
    monkeypatch.setattr(RayQuery, "_run", lambda *a, **k: pytest.fail("a kernel ran"))
    count = 3 * query_module.CHECK_BLOCK + 17
    origins = np.zeros((count, 3), np.float32)
    directions = np.tile(np.float32([0.3, -0.5, 0.8]), (count, 1))
    directions[5] = [0.0, 1e-40, 1.0]          # tiny components, long enough
    directions[count - 3] = [-0.0, 1e-39, 0.0]  # the last block
    directions[count - 1] = [0.0, 0.0, 0.0]
    for query in (case.scene.intersect, case.scene.occluded):
        with pytest.raises(ValueError, match=rf"directions\[{count - 3}\].*too short"):
            query(origins, directions)
    directions[count - 3] = [1e-30, 0.0, 0.0]
    with pytest.raises(ValueError, match=rf"directions\[{count - 1}\].*zero length"):
        case.scene.intersect(origins, directions)


@pytest.mark.parametrize("which, row, value, message", [
    ("origins", "last", [0.0, np.nan, 0.0], "not finite"),
    ("origins", "middle", [1e39, 0.0, 0.0], "overflows float32"),
    ("directions", "middle", [0.0, -np.inf, 1.0], "not finite"),
    ("directions", "first", [0.0, 0.0, 0.0], "zero length"),
])
def test_bad_rows_are_named_in_every_part_of_a_large_batch(monkeypatch, which, row, value, message):
    """Large batches are checked a run of blocks per thread: a bad row is
    named by its index wherever it lies, and no kernel runs."""
    case = scene_case("cube")
    monkeypatch.setattr(RayQuery, "_run", lambda *a, **k: pytest.fail("a kernel ran"))
    count = 4 * query_module.CHECK_BLOCK + 5
    index = {"first": 3, "middle": 2 * query_module.CHECK_BLOCK + 1, "last": count - 2}[row]
    rays = {"origins": np.zeros((count, 3)), "directions": np.tile([0.3, -0.5, 0.8], (count, 1))}
    rays[which][index] = value
    for query in (case.scene.intersect, case.scene.occluded):
        with pytest.raises(ValueError, match=rf"{which}\[{index}\] = .*{message}"):
            query(rays["origins"], rays["directions"])


def test_bad_tree_and_chunk_size():
    case = scene_case("cube")
    q = RayQuery(case.scene._runtime)
    with pytest.raises(TypeError, match="tree must be a hlbvh_cl.tree.DeviceTree"):
        q.intersect("tree", GOOD_O, GOOD_D)
    with pytest.raises(ValueError, match="max_rays_per_launch must be >= 1"):
        RayQuery(case.scene._runtime, max_rays_per_launch=0)
    with pytest.raises(TypeError, match="max_rays_per_launch must be an int"):
        RayQuery(case.scene._runtime, max_rays_per_launch=2.5)


def test_chunk_size_follows_device_memory():
    case = scene_case("cube")
    q = RayQuery(case.scene._runtime)
    d = case.scene._runtime.device
    buffers = {**query_module.RAY_ARRAYS, **query_module.HIT_ARRAYS,
               **query_module.OCCLUDED_ARRAYS}
    assert q.max_rays_per_launch <= query_module.MAX_RAYS_PER_LAUNCH
    assert q.max_rays_per_launch * max(buffers.values()) <= d.max_mem_alloc_size
    assert q.max_rays_per_launch * sum(buffers.values()) <= d.global_mem_size
