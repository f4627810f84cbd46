"""What the point-query and instance tests share: parity-cast insideness,
points on a surface, and the signs just off it."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh


def parity_inside(vertices, faces, points):
    """Inside by parity ray casting (embreex through trimesh), three
    directions voting."""
    pytest.importorskip("embreex")
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight
    return mesh.contains(points)


def surface_samples(rng, vertices, faces, count):
    """Points on ``count`` distinct random triangles, away from their edges
    (float64), those triangles' unit normals cross(v1 - v0, v2 - v0), and
    which triangles they are."""
    chosen = rng.choice(len(faces), count, replace=False)
    tri = np.asarray(vertices, np.float64)[faces[chosen]]
    on = np.einsum("fk,fkd->fd", rng.dirichlet((4, 4, 4), count), tri)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return on, normal / np.linalg.norm(normal, axis=1, keepdims=True), chosen


def assert_signs_off_the_surface(scene, on, outward, least):
    """Points 1e-6 outside and inside the surface points ``on`` (along the
    unit ``outward`` directions) get their side's sign from signed_distance
    and contains: those that float32 rounding leaves truly off the surface,
    at least ``least`` of each side."""
    for sign in (1, -1):
        points = (on + sign * 1e-6 * outward).astype(np.float32)
        side = np.einsum("fd,fd->f", points.astype(np.float64) - on, outward)
        off = side * sign > 2e-7
        assert off.sum() > least
        sdf = scene.signed_distance(points[off])
        assert np.all(np.sign(sdf) == sign), f"{(np.sign(sdf) != sign).sum()} flipped signs"
        assert np.all(scene.contains(points[off]) == (sign < 0))
