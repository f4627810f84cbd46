"""Uniform edge splitting: more triangles, same surface.

Each triangle (v0, v1, v2) becomes the k*k triangles of the regular grid of
points v0 + (i/k)(v1 - v0) + (j/k)(v2 - v0), i, j >= 0, i + j <= k.  Grid
points on an input edge are made once per undirected edge, walking from the
edge's lower-index vertex to the higher one, and shared by both faces of that
edge: the two sides then use bit-identical points, so the split mesh has no
cracks (a watertight ray test, Woop et al. 2013, would see any).

Output: the input vertices first (same indices), then k - 1 points per unique
edge, then (k-1)(k-2)/2 interior points per face.  The k*k children of input
face f are output faces f*k*k ... (f+1)*k*k - 1, wound like their parent.
"""
from __future__ import annotations


import numpy as np

from ..core import inputs
from ..mesh import Mesh

_INT32_MAX = 2**31 - 1


def _check_k(k) -> int:
    return inputs.integer("k (edges per input edge)", k, 1)


def _grid(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (i, j) grid points of one triangle and its k*k children as point slots.

    Returns i, j (one entry per point) and children (k*k, 3) indexing them.
    """
    i, j = np.array([(a, b) for b in range(k + 1) for a in range(k + 1 - b)]).T
    slot = -np.ones((k + 1, k + 1), dtype=np.int64)
    slot[i, j] = np.arange(len(i))
    up = [(slot[a, b], slot[a + 1, b], slot[a, b + 1])
          for b in range(k) for a in range(k - b)]
    down = [(slot[a + 1, b], slot[a + 1, b + 1], slot[a, b + 1])
            for b in range(k - 1) for a in range(k - 1 - b)]
    # In (i, j) both kinds turn counter-clockwise, like (v0, v1, v2).
    return i, j, np.array(up + down, dtype=np.int64)


def split_edges(vertices, faces, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Cut every edge into k equal parts: k*k triangles per input triangle.

    vertices (N, 3) and faces (M, 3) are validated like a Mesh.  Returns new
    (vertices float32, faces int32) arrays; k = 1 returns the validated input.
    """
    k = _check_k(k)
    mesh = Mesh(vertices, faces)
    if k == 1:
        return mesh.vertices, mesh.faces
    if mesh.triangle_count * k * k > _INT32_MAX:
        raise ValueError(f"k = {k} would make {mesh.triangle_count * k * k} triangles from "
                         f"{mesh.triangle_count}; at most 2**31 - 1 fit int32 ids")
    try:
        return _split(mesh.vertices, mesh.faces, k)
    except MemoryError:
        raise ValueError(f"k = {k}: not enough memory to make {mesh.triangle_count * k * k} "
                         f"triangles") from None


def _split(positions: np.ndarray, faces: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    vertex_count, face_count = len(positions), len(faces)

    # Unique undirected edges, each stored as (lower, higher) vertex index.
    corners = faces.astype(np.int64)
    directed = np.stack([corners[:, [0, 1]], corners[:, [0, 2]], corners[:, [1, 2]]], axis=1)
    lower, higher = directed.min(axis=2), directed.max(axis=2)
    unique_keys, edge_of = np.unique(lower * vertex_count + higher, return_inverse=True)
    edge_of = edge_of.reshape(face_count, 3)
    edge_lo, edge_hi = np.divmod(unique_keys, vertex_count)
    edge_count = len(unique_keys)

    interior_per_face = (k - 1) * (k - 2) // 2
    total_vertices = vertex_count + edge_count * (k - 1) + face_count * interior_per_face
    if total_vertices > _INT32_MAX:
        raise ValueError(f"k = {k} would make {total_vertices} vertices; at most 2**31 - 1 fit "
                         f"int32 indices")

    # Edge points in float64 from the lower vertex towards the higher one.
    p64 = positions.astype(np.float64)
    steps = np.arange(1, k, dtype=np.float64) / k
    start = p64[edge_lo]
    edge_points = start[:, None, :] + steps[None, :, None] * (p64[edge_hi] - start)[:, None, :]

    i, j, children = _grid(k)
    is_interior = (i > 0) & (j > 0) & (i + j < k)
    a, b, c = (p64[corners[:, n]] for n in range(3))
    wi, wj = i[is_interior] / k, j[is_interior] / k
    interior_points = (a[:, None, :] + wi[None, :, None] * (b - a)[:, None, :]
                       + wj[None, :, None] * (c - a)[:, None, :])

    # Global vertex index of every grid point of every face: (M, points).
    slots = np.empty((face_count, len(i)), dtype=np.int64)
    edge_base = vertex_count
    interior_base = vertex_count + edge_count * (k - 1)
    interior_rank = np.cumsum(is_interior) - 1
    for point, (pi, pj) in enumerate(zip(i, j)):
        pl = k - pi - pj
        if pi == k or pj == k or pl == k:  # a corner
            corner = 1 if pi == k else 2 if pj == k else 0
            slots[:, point] = corners[:, corner]
            continue
        if is_interior[point]:
            slots[:, point] = (interior_base + np.arange(face_count) * interior_per_face
                               + interior_rank[point])
            continue
        # On an edge: which one, and how far (in steps) from its first corner.
        if pj == 0:
            side, start_corner, end_corner, s = 0, 0, 1, pi  # v0 -> v1
        elif pi == 0:
            side, start_corner, end_corner, s = 1, 0, 2, pj  # v0 -> v2
        else:
            side, start_corner, end_corner, s = 2, 1, 2, pj  # v1 -> v2
        forward = corners[:, start_corner] < corners[:, end_corner]
        step_from_lower = np.where(forward, s, k - s)
        slots[:, point] = edge_base + edge_of[:, side] * (k - 1) + step_from_lower - 1

    new_faces = slots[:, children].reshape(-1, 3).astype(np.int32)
    new_vertices = np.concatenate([
        positions,
        edge_points.reshape(-1, 3).astype(np.float32),
        interior_points.reshape(-1, 3).astype(np.float32),
    ])
    return new_vertices, new_faces
