"""What the all-hits tests and the Oclgrind tier share: the brute-force
comparison of intersect_all and a stack of plates."""
from __future__ import annotations

import numpy as np

import hlbvh_cl
from oracle import brute_force_all_hits
from ray_cases import EDGE_TOLERANCE, T_RTOL, UV_ATOL, SceneCase


def assert_matches_brute_force(case: SceneCase, origins, directions, tmin=0.0, tmax=np.inf,
                               max_hits=None):
    """intersect_all against the oracle on the rays that float32 cannot
    decide otherwise (no triangle boundary within EDGE_TOLERANCE, no two hits
    within T_RTOL); returns how many rays were compared."""
    got = case.scene.intersect_all(origins, directions, tmin, tmax, max_hits=max_hits)
    want = brute_force_all_hits(case.vertices, case.faces, origins, directions, tmin, tmax)
    counts = case.scene.count_intersections(origins, directions, tmin, tmax)
    expected_counts = counts if max_hits is None else np.minimum(counts, max_hits)
    np.testing.assert_array_equal(got.counts, expected_counts)
    assert got.offsets[0] == 0 and got.offsets.dtype == np.int64
    np.testing.assert_array_equal(got.ray_index, np.repeat(np.arange(len(origins)), got.counts))
    # sorted by t within each ray
    same = got.ray_index[1:] == got.ray_index[:-1]
    assert (got.t[1:][same] >= got.t[:-1][same]).all()
    clear = (want["margin"] > EDGE_TOLERANCE) & (want["gap"] > 10 * T_RTOL)
    prim = case.first_face[got.geom_id] + got.prim_id
    for r in np.flatnonzero(clear):
        mine = slice(got.offsets[r], got.offsets[r + 1])
        full = slice(want["offsets"][r], want["offsets"][r + 1])
        n = full.stop - full.start if max_hits is None else min(max_hits, full.stop - full.start)
        theirs = slice(full.start, full.start + n)
        np.testing.assert_array_equal(prim[mine], want["prim"][theirs], f"ray {r}")
        np.testing.assert_allclose(got.t[mine], want["t"][theirs], rtol=T_RTOL, err_msg=f"ray {r}")
        np.testing.assert_allclose(got.u[mine], want["u"][theirs], atol=UV_ATOL)
        np.testing.assert_allclose(got.v[mine], want["v"][theirs], atol=UV_ATOL)
    return int(clear.sum()), got


def plates(count: int = 9) -> hlbvh_cl.Mesh:
    """`count` squares [-1, 1]^2 stacked at z = 0, 1, ..., two triangles each."""
    vertices = np.array([[x, y, z] for z in range(count) for x, y in
                         ((-1, -1), (1, -1), (1, 1), (-1, 1))], float)
    faces = np.array([[q, q + 1, q + 2] for q in range(0, 4 * count, 4)]
                     + [[q, q + 2, q + 3] for q in range(0, 4 * count, 4)])
    return hlbvh_cl.Mesh(vertices, faces, name="plates")
