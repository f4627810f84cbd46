"""Watertightness: rays that start inside a closed mesh always hit it, also
when aimed exactly at its vertices and edge midpoints, where a non-watertight
ray/triangle test (e.g. Moller-Trumbore in float32) lets rays slip between
the triangles that share the vertex or edge (Woop, Benthin & Wald 2013).

Interior points are found with the float64 oracle, not with the kernels.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import hlbvh_cl
from oracle import brute_force_intersect

MESHES = Path(__file__).resolve().parent.parent / "scenes" / "meshes"

CLOSED_MESHES = ["knight", "bunny_small", "armadillo"]
INTERIOR_POINTS = 3
RANDOM_DIRECTIONS = 3000


def _signed_volume(vertices, faces) -> float:
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6)


def _interior_points(mesh: hlbvh_cl.Mesh, count: int, seed: int) -> np.ndarray:
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


@pytest.fixture(scope="module", params=CLOSED_MESHES)
def closed(request):
    mesh = hlbvh_cl.Mesh.load(MESHES / f"{request.param}.ply")
    return mesh, hlbvh_cl.Scene([mesh])


def _unique_edges(faces: np.ndarray) -> np.ndarray:
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(edges, axis=1), axis=0)


def test_rays_from_inside_always_hit(closed):
    mesh, scene = closed
    vertices = mesh.vertices.astype(np.float64)
    edges = _unique_edges(mesh.faces)
    midpoints = (vertices[edges[:, 0]] + vertices[edges[:, 1]]) / 2
    rng = np.random.default_rng(1)
    for origin in _interior_points(mesh, INTERIOR_POINTS, seed=2):
        targets = {
            "vertices": vertices,
            "edge midpoints": midpoints,
            "random directions": origin + rng.normal(size=(RANDOM_DIRECTIONS, 3)),
        }
        for what, points in targets.items():
            directions = (points - origin).astype(np.float32)
            keep = np.any(directions != 0, axis=1)
            directions = directions[keep]
            origins = np.repeat(origin[None].astype(np.float32), len(directions), 0)
            hits = scene.intersect(origins, directions)
            missed = np.flatnonzero(~hits.hit)
            assert len(missed) == 0, (f"{mesh.name}: {len(missed)} of {len(directions)} rays from "
                                      f"inside {origin.tolist()} aimed at {what} escaped "
                                      f"(first: directions {directions[missed[:3]].tolist()})")
            assert scene.occluded(origins, directions).all()
