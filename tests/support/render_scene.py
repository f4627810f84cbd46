"""The renderer's test scene (a knight and a small teapot on a ground), its
camera, light and colours, and the module-scoped `scene` and `renderer`
fixtures that test_render and test_validation import."""
from __future__ import annotations


import numpy as np
import pytest

import hlbvh_cl
import places


MESHES = places.MESHES


GROUND_Y = 0.0513135  # the knight's lowest point


def render_meshes() -> list[hlbvh_cl.Mesh]:
    knight = hlbvh_cl.Mesh.load(MESHES / "knight.ply")
    teapot = hlbvh_cl.Mesh.load(MESHES / "teapot.ply")
    pot = teapot.vertices.astype(np.float64) * 0.02
    pot += np.array([1.25, GROUND_Y, 0.45]) - [0.0, pot[:, 1].min(), 0.0]
    y = GROUND_Y
    ground = hlbvh_cl.Mesh([[-1.5, y, -1.0], [2.5, y, -1.0], [2.5, y, 2.0], [-1.5, y, 2.0]],
                           [[0, 2, 1], [0, 3, 2]], name="ground")
    return [knight, hlbvh_cl.Mesh(pot, teapot.faces, name="teapot"), ground]


CAMERA = hlbvh_cl.Camera(eye=(0.3, 1.0, 2.6), target=(0.8, 0.4, 0.5), fov_deg=40.0)
LIGHT = hlbvh_cl.Light(direction=(-0.6, 1.0, 0.7), intensity=0.85, ambient=0.15)
COLORS = [(0.85, 0.6, 0.5), (0.55, 0.7, 0.85), (0.9, 0.85, 0.7)]


@pytest.fixture(scope="module")
def scene():
    return hlbvh_cl.Scene(render_meshes())


@pytest.fixture(scope="module")
def renderer(scene):
    return hlbvh_cl.Renderer(scene, colors=COLORS, light=LIGHT)
