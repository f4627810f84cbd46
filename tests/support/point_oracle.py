"""Brute-force point queries in float64 numpy: the point tests' oracle.

Every point against every triangle: the closest point by Ericson's regions
(Ericson 2005, "Real-Time Collision Detection", sec. 5.1.5), vectorised, and
the exact winding number as the sum of the triangles' solid angles (Van
Oosterom & Strackee 1983) over 4 pi.  Chunks keep points x triangles small.

Conventions: closest point = (1-u-v) v0 + u v1 + v v2; the nearest triangle
wins, ties to the lowest index; beyond max_distance (distance > it): distance
inf, index -1.  Degenerate triangles are measured as their nearest edge.
"""
from __future__ import annotations

import numpy as np

CHUNK_ELEMENTS = 1 << 18


def triangle_corners(vertices, faces):
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    return v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]


def closest_on_segment(a, ab, p):
    """Squared distance from p to the segment a + s ab, s in [0, 1], and s."""
    length2 = np.einsum("...k,...k->...", ab, ab)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(length2 > 0, np.einsum("...k,...k->...", p - a, ab) / length2, 0.0)
    s = np.clip(s, 0.0, 1.0)
    d = p - (a + s[..., None] * ab)
    return np.einsum("...k,...k->...", d, d), s


def closest_on_triangles(p, a, b, c):
    """(P, F) squared distances and barycentrics u, v from points p (P, 3)
    to triangles (F, 3) each."""
    p = p[:, None, :]
    ab, ac = (b - a)[None], (c - a)[None]
    a_, b_, c_ = a[None], b[None], c[None]
    dot = lambda x, y: np.einsum("...k,...k->...", x, y)  # noqa: E731
    ap, bp, cp = p - a_, p - b_, p - c_
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), \
        dot(ac, cp)
    vc, vb, va = d1 * d4 - d3 * d2, d5 * d2 - d1 * d6, d3 * d6 - d5 * d4
    shape = d1.shape
    u, v = np.zeros(shape), np.zeros(shape)
    done = np.zeros(shape, bool)

    def take(region, uu, vv):
        nonlocal done
        region = region & ~done
        u[region] = np.broadcast_to(uu, shape)[region]
        v[region] = np.broadcast_to(vv, shape)[region]
        done |= region

    with np.errstate(invalid="ignore", divide="ignore"):
        take((d1 <= 0) & (d2 <= 0), 0.0, 0.0)
        take((d3 >= 0) & (d4 <= d3), 1.0, 0.0)
        take((vc <= 0) & (d1 >= 0) & (d3 <= 0), d1 / (d1 - d3), 0.0)
        take((d6 >= 0) & (d5 <= d6), 0.0, 1.0)
        take((vb <= 0) & (d2 >= 0) & (d6 <= 0), 0.0, d2 / (d2 - d6))
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        take((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), 1.0 - w, w)
        total = va + vb + vc
        fu, fv = vb / total, vc / total
        face = ~done
        u[face], v[face] = fu[face], fv[face]
    point = a_ + u[..., None] * ab + v[..., None] * ac
    diff = p - point
    dist2 = dot(diff, diff)
    # degenerate triangles: their nearest edge
    normal = np.cross(ab, ac)
    degenerate = np.broadcast_to(~np.any(normal != 0, axis=-1), shape)
    if degenerate.any():
        e = [closest_on_segment(a_, ab, p), closest_on_segment(a_, ac, p),
             closest_on_segment(b_, (c - b)[None], p)]
        best = np.minimum(np.minimum(e[0][0], e[1][0]), e[2][0])
        dist2 = np.where(degenerate, best, dist2)
    return dist2, u, v


def brute_force_closest(vertices, faces, points, max_distance=np.inf) -> dict:
    """distance, index (-1: none within max_distance), u, v, points."""
    a, b, c = triangle_corners(vertices, faces)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    count = len(points)
    best = np.full(count, np.inf)
    index = np.full(count, -1, np.int64)
    u = np.zeros(count)
    v = np.zeros(count)
    step = max(1, CHUNK_ELEMENTS // max(1, len(a)))
    for start in range(0, count, step):
        part = slice(start, min(start + step, count))
        d2, uu, vv = closest_on_triangles(points[part], a, b, c)
        nearest = np.argmin(d2, axis=1)
        rows = np.arange(len(nearest))
        best[part] = d2[rows, nearest]
        index[part] = nearest
        u[part], v[part] = uu[rows, nearest], vv[rows, nearest]
    distance = np.sqrt(best)
    beyond = ~(distance <= max_distance)
    distance[beyond] = np.inf
    index[beyond] = -1
    u[beyond] = v[beyond] = 0.0
    found = index >= 0
    at = np.full((count, 3), np.nan)
    i = index[found]
    at[found] = a[i] + u[found, None] * (b[i] - a[i]) + v[found, None] * (c[i] - a[i])
    return {"distance": distance, "index": index, "u": u, "v": v, "points": at}


def brute_force_winding(vertices, faces, points) -> np.ndarray:
    """The exact generalized winding number of each point, float64."""
    a, b, c = triangle_corners(vertices, faces)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.zeros(len(points))
    step = max(1, CHUNK_ELEMENTS // max(1, len(a)))
    for start in range(0, len(points), step):
        q = points[start:start + step, None, :]
        x, y, z = a[None] - q, b[None] - q, c[None] - q
        lx, ly, lz = (np.linalg.norm(t, axis=-1) for t in (x, y, z))
        det = np.einsum("...k,...k->...", x, np.cross(y, z))
        dot = lambda s, t: np.einsum("...k,...k->...", s, t)  # noqa: E731
        denominator = lx * ly * lz + dot(x, y) * lz + dot(y, z) * lx + dot(z, x) * ly
        out[start:start + step] = (2.0 * np.arctan2(det, denominator)).sum(axis=1) / (4 * np.pi)
    return out
