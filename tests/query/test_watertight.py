"""Watertightness: rays that start inside a closed mesh always hit it, also
when aimed exactly at its vertices and edge midpoints, where a non-watertight
ray/triangle test (e.g. Moller-Trumbore in float32) lets rays slip between
the triangles that share the vertex or edge (Woop, Benthin & Wald 2013).

Interior points are found with the float64 oracle, not with the kernels.
"""
from __future__ import annotations


import numpy as np
import pytest

import hlbvh_cl
from ray_cases import interior_points, unique_edges
import places

MESHES = places.MESHES

CLOSED_MESHES = ["knight", "bunny_small", "armadillo"]
INTERIOR_POINTS = 3
RANDOM_DIRECTIONS = 3000


@pytest.fixture(scope="module", params=CLOSED_MESHES)
def closed(request):
    mesh = hlbvh_cl.Mesh.load(MESHES / f"{request.param}.ply")
    return mesh, hlbvh_cl.Scene([mesh])


def test_rays_from_inside_always_hit(closed):
    mesh, scene = closed
    vertices = mesh.vertices.astype(np.float64)
    edges = unique_edges(mesh.faces)
    midpoints = (vertices[edges[:, 0]] + vertices[edges[:, 1]]) / 2
    rng = np.random.default_rng(1)
    for origin in interior_points(mesh, INTERIOR_POINTS, seed=2):
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
