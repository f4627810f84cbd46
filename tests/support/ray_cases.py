"""Scenes, rays and the comparison with the float64 brute-force oracle
(tests/support/oracle.py) that the ray tests share (test_rays, test_packets,
test_watertight, test_memory, test_validation, test_oclgrind).

Agreement is exact for hit/miss, prim_id and geom_id, except where float32
rounding can decide the answer: a ray within rounding of a triangle's edge or
of tmin/tmax, and near-ties (two triangles at nearly the same t).  Those
exceptions are recomputed in float64 here, never assumed.
"""
from __future__ import annotations


import numpy as np

import hlbvh_cl
from hlbvh_cl.query.rays import Hits
from oracle import brute_force_intersect
from shapes import grid_mesh
import places


MESHES = places.MESHES


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


scene_cache: dict[str, SceneCase] = {}


def scene_case(name: str) -> SceneCase:
    if name not in scene_cache:
        scene_cache[name] = SceneCase([MESH_MAKERS[name]()])
    return scene_cache[name]


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


def near_edge_or_limit(case, origin, direction, tmin, tmax) -> bool:
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


def _uv_tolerance(case: SceneCase, origins, prims) -> np.ndarray:
    """The error allowed in a hit's float32 u and v: UV_ATOL, or for a small
    triangle seen from afar more, as float32 rounds the corners' offsets from
    the origin by about eps times the distance R, which moves a barycentric
    coordinate by about that over the triangle's least altitude h: 16 eps R / h."""
    a, b, c = (case.vertices[case.faces[prims, k]] for k in range(3))
    twice_area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    longest = np.max([np.linalg.norm(e, axis=1) for e in (b - a, c - b, a - c)], axis=0)
    altitude = twice_area / np.maximum(longest, 1e-300)
    distance = np.linalg.norm((a + b + c) / 3 - origins.astype(np.float64), axis=1)
    with np.errstate(divide="ignore"):
        return np.maximum(UV_ATOL, 16 * 2.0**-24 * distance / altitude)


def assert_matches_oracle(case: SceneCase, hits: Hits, origins, directions, tmin=0.0, tmax=np.inf):
    count = len(origins)
    tmin_all = np.broadcast_to(np.asarray(tmin, np.float64), (count,))
    tmax_all = np.broadcast_to(np.asarray(tmax, np.float64), (count,))
    ref = brute_force_intersect(case.vertices, case.faces, origins, directions, tmin, tmax)
    ref_hit = ref["prim"] >= 0
    assert len(hits) == count

    # hit / miss
    for i in np.flatnonzero(hits.hit != ref_hit):
        assert near_edge_or_limit(case, origins[i], directions[i], tmin_all[i], tmax_all[i]), (
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
    uv_allowed = _uv_tolerance(case, origins[same], prims[same])
    for name in ("u", "v"):
        error = np.abs(getattr(hits, name)[same] - ref[name][same])
        worst = np.argmax(error - uv_allowed) if len(error) else 0
        assert np.all(error <= uv_allowed), (
            f"ray {np.flatnonzero(same)[worst]}: {name} = {getattr(hits, name)[same][worst]}, "
            f"oracle {ref[name][same][worst]}")
    np.testing.assert_allclose(hits.normal[same], ref["normal"][same], atol=NORMAL_ATOL)
    np.testing.assert_allclose(np.linalg.norm(hits.normal[hits.hit], axis=1), 1.0, atol=1e-6)
    return ref


# -- closed meshes: points inside, shared edges -------------------------------

def _signed_volume(vertices, faces) -> float:
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6)


def interior_points(mesh: hlbvh_cl.Mesh, count: int, seed: int) -> np.ndarray:
    """Points that the oracle sees inside: from each, the first triangle hit in
    every one of 9 random directions is seen from its back (inner) side."""
    vertices = mesh.vertices.astype(np.float64)
    faces = mesh.faces
    outward = np.sign(_signed_volume(vertices, faces))
    assert outward != 0
    rng = np.random.default_rng(seed)
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    normals = np.cross(v1 - v0, v2 - v0) * outward
    lengths = np.linalg.norm(normals, axis=1)
    # candidates: a little inward from the centres of large triangles, whose
    # inside is thick enough there
    big = np.argsort(lengths)[-400:]
    chosen = rng.choice(big, 40, replace=False)
    size = np.sqrt(lengths[chosen])[:, None]
    centres = (v0[chosen] + v1[chosen] + v2[chosen]) / 3
    candidates = centres - normals[chosen] / lengths[chosen, None] * 0.3 * size
    directions = rng.normal(size=(9, 3))
    found = []
    for point in candidates:
        ref = brute_force_intersect(vertices, faces, np.repeat(point[None], 9, 0), directions)
        if np.all(ref["prim"] >= 0):
            facing = np.einsum("ij,ij->i", normals[ref["prim"]], directions)
            if np.all(facing > 0):
                found.append(point)
        if len(found) == count:
            break
    assert len(found) == count, f"only {len(found)} interior points found"
    return np.array(found)


def unique_edges(faces: np.ndarray) -> np.ndarray:
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(edges, axis=1), axis=0)
