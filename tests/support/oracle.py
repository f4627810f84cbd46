"""Brute-force ray/triangle queries in float64 numpy: the tests' oracle.

Every ray is tested against every triangle with the Moller-Trumbore test
(Moller & Trumbore 1997, "Fast, Minimum Storage Ray-Triangle Intersection"),
in float64, in chunks so that rays x triangles up to ~2e7 fit in memory.

Conventions (the kernels' tests rely on them):
- A ray is origin + t * direction; direction need not be unit length, and t
  is in units of its length.  A zero direction never hits.
- A hit counts when tmin <= t <= tmax (both ends inclusive) and the point is
  inside or on the triangle: u >= 0, v >= 0, u + v <= 1.
- Degenerate (zero-area) triangles never hit; neither do rays parallel to a
  triangle's plane (det == 0).
- The closest hit wins; among equal t the lowest triangle index.
- Results: t (inf on a miss), prim (int64, -1 on a miss), u and v (the
  barycentric weights of v1 and v2: hit = (1-u-v) v0 + u v1 + v v2) and normal
  (unit cross(v1 - v0, v2 - v0)); u, v and normal are 0 on a miss.
"""
from __future__ import annotations

import numpy as np

#: rays x triangles handled at once (a few float64 temporaries of this size x 3)
CHUNK_ELEMENTS = 1 << 19


def prepare(vertices, faces, origins, directions, tmin, tmax):
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if origins.shape != directions.shape:
        raise ValueError(f"origins {origins.shape} and directions {directions.shape} differ")
    count = len(origins)
    tmin = np.broadcast_to(np.asarray(tmin, dtype=np.float64), (count,))
    tmax = np.broadcast_to(np.asarray(tmax, dtype=np.float64), (count,))
    v0, v1, v2 = (vertices[faces[:, n]] for n in range(3))
    edge1, edge2 = v1 - v0, v2 - v0
    normal = np.cross(edge1, edge2)
    valid = np.any(normal != 0, axis=1)  # zero-area triangles never hit
    return origins, directions, tmin, tmax, v0, edge1, edge2, normal, valid


def chunks(ray_count: int, tri_count: int):
    tri_step = max(1, min(tri_count, CHUNK_ELEMENTS))
    ray_step = max(1, CHUNK_ELEMENTS // tri_step)
    for r in range(0, ray_count, ray_step):
        for f in range(0, tri_count, tri_step):
            yield slice(r, min(r + ray_step, ray_count)), slice(f, min(f + tri_step, tri_count))


def moller_trumbore(o, d, v0, edge1, edge2, valid, tmin, tmax):
    """t, u, v and hit mask for rays (R) x triangles (F), all (R, F)."""
    pvec = np.cross(d[:, None, :], edge2[None, :, :])
    det = np.einsum("fk,rfk->rf", edge1, pvec)
    hit = (det != 0) & valid[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = 1.0 / det
        tvec = o[:, None, :] - v0[None, :, :]
        u = np.einsum("rfk,rfk->rf", tvec, pvec) * inv_det
        qvec = np.cross(tvec, edge1[None, :, :])
        v = np.einsum("rk,rfk->rf", d, qvec) * inv_det
        t = np.einsum("fk,rfk->rf", edge2, qvec) * inv_det
        hit &= (u >= 0) & (v >= 0) & (u + v <= 1)
        hit &= (t >= tmin[:, None]) & (t <= tmax[:, None])
    return t, u, v, hit


def brute_force_intersect(vertices, faces, origins, directions, tmin=0.0, tmax=np.inf) -> dict:
    """Closest hit of every ray (see the module docstring for conventions).

    tmin and tmax are scalars or one value per ray.
    """
    o, d, tmin, tmax, v0, edge1, edge2, normal, valid = prepare(
        vertices, faces, origins, directions, tmin, tmax)
    count = len(o)
    best_t = np.full(count, np.inf)
    best_prim = np.full(count, -1, dtype=np.int64)
    best_u = np.zeros(count)
    best_v = np.zeros(count)
    for rays, tris in chunks(count, len(v0)):
        t, u, v, hit = moller_trumbore(o[rays], d[rays], v0[tris], edge1[tris], edge2[tris],
                                       valid[tris], tmin[rays], tmax[rays])
        t = np.where(hit, t, np.inf)
        local = np.argmin(t, axis=1)  # first minimum: the lowest index among ties
        rows = np.arange(len(local))
        closest = t[rows, local]
        better = closest < best_t[rays]  # strict: earlier chunks hold lower indices
        index = np.flatnonzero(better) + rays.start
        best_t[index] = closest[better]
        best_prim[index] = local[better] + tris.start
        best_u[index] = u[rows, local][better]
        best_v[index] = v[rows, local][better]
    hits = best_prim >= 0
    unit = np.zeros((count, 3))
    n = normal[best_prim[hits]]
    unit[hits] = n / np.linalg.norm(n, axis=1, keepdims=True)
    return {"t": best_t, "prim": best_prim, "u": best_u, "v": best_v, "normal": unit}


def brute_force_occluded(vertices, faces, origins, directions, tmin=0.0, tmax=np.inf) -> np.ndarray:
    """True for every ray that hits any triangle with tmin <= t <= tmax."""
    o, d, tmin, tmax, v0, edge1, edge2, _, valid = prepare(
        vertices, faces, origins, directions, tmin, tmax)
    occluded = np.zeros(len(o), dtype=bool)
    for rays, tris in chunks(len(o), len(v0)):
        *_, hit = moller_trumbore(o[rays], d[rays], v0[tris], edge1[tris], edge2[tris],
                                  valid[tris], tmin[rays], tmax[rays])
        occluded[rays] |= hit.any(axis=1)
    return occluded


def brute_force_all_hits(vertices, faces, origins, directions, tmin=0.0, tmax=np.inf) -> dict:
    """Every hit of every ray, sorted by t (ties by triangle index), as flat
    arrays: ray r's hits are [offsets[r], offsets[r + 1]) of t, prim, u, v.
    Also per ray ``margin``: the smallest barycentric distance to a triangle's
    boundary, min(|u|, |v|, |1-u-v|), over every triangle whose plane the ray
    meets within [tmin, tmax] (hit or not), and ``gap``: the smallest
    relative difference between consecutive hits' t.  Rays with a small
    margin may go either way in float32; with a small gap may swap order."""
    o, d, tmin, tmax, v0, edge1, edge2, _, valid = prepare(
        vertices, faces, origins, directions, tmin, tmax)
    count = len(o)
    rays, prims, ts, us, vs = [], [], [], [], []
    margin = np.full(count, np.inf)
    for rows, tris in chunks(count, len(v0)):
        t, u, v, hit = moller_trumbore(o[rows], d[rows], v0[tris], edge1[tris], edge2[tris],
                                       valid[tris], tmin[rows], tmax[rows])
        with np.errstate(invalid="ignore"):
            crossed = np.isfinite(t) & (t >= tmin[rows, None]) & (t <= tmax[rows, None])
            distance = np.minimum(np.minimum(np.abs(u), np.abs(v)), np.abs(1 - u - v))
        distance = np.where(crossed & valid[tris][None, :], distance, np.inf)
        margin[rows] = np.minimum(margin[rows], distance.min(axis=1))
        r, f = np.nonzero(hit)
        rays.append(r + rows.start)
        prims.append(f + tris.start)
        ts.append(t[r, f])
        us.append(u[r, f])
        vs.append(v[r, f])
    ray, prim, t, u, v = (np.concatenate(a) for a in (rays, prims, ts, us, vs))
    order = np.lexsort((prim, t, ray))
    ray, prim, t, u, v = ray[order], prim[order], t[order], u[order], v[order]
    offsets = np.concatenate([[0], np.cumsum(np.bincount(ray, minlength=count))])
    gap = np.full(count, np.inf)
    same = ray[1:] == ray[:-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        relative = (t[1:] - t[:-1]) / np.maximum(np.abs(t[1:]), 1e-30)
    np.minimum.at(gap, ray[1:][same], relative[same])
    return {"offsets": offsets, "ray": ray, "t": t, "prim": prim, "u": u, "v": v,
            "margin": margin, "gap": gap}
