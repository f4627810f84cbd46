"""What the instance tests and the Oclgrind tier share: random instance
transforms and the float64 scene they flatten to."""
from __future__ import annotations

import numpy as np


def rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.diag(r))


def random_transforms(rng, count: int, spread: float = 4.0) -> np.ndarray:
    """(count, 3, 4) maps: rotated, non-uniformly scaled, every third one
    mirrored, some overlapping (spread is about two mesh sizes)."""
    maps = np.empty((count, 3, 4))
    for k in range(count):
        linear = rotation(rng) @ np.diag(rng.uniform(0.5, 2.0, 3))
        if k % 3 == 0:
            linear[:, 0] *= -1
        maps[k, :, :3] = linear
        maps[k, :, 3] = rng.uniform(-spread, spread, 3)
    return maps


def flattened(meshes, instance_meshes, maps):
    """float64 vertices and faces of every instance, concatenated, with the
    (instance, face) of each flattened triangle."""
    vertices, faces, owner, prim, offset = [], [], [], [], 0
    for k, (m, a) in enumerate(zip(instance_meshes, maps)):
        mesh = meshes[m]
        vertices.append(mesh.vertices.astype(np.float64) @ a[:, :3].T + a[:, 3])
        faces.append(mesh.faces + offset)
        owner.append(np.full(mesh.triangle_count, k))
        prim.append(np.arange(mesh.triangle_count))
        offset += mesh.vertex_count
    return (np.concatenate(vertices), np.concatenate(faces), np.concatenate(owner),
            np.concatenate(prim))
