"""Small synthetic meshes the tests share."""
import numpy as np

import hlbvh_cl

#: Two triangles over the unit square in z = 0, as plain arrays.
QUAD = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3]])


def grid_mesh(n: int = 4) -> hlbvh_cl.Mesh:
    """An n x n grid of unit squares in the plane z = 0, two triangles each."""
    xs, ys = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    vertices = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    faces = []
    for i in range(n):
        for j in range(n):
            a, b = i * (n + 1) + j, (i + 1) * (n + 1) + j
            faces += [[a, b, b + 1], [a, b + 1, a + 1]]
    return hlbvh_cl.Mesh(vertices, faces, name="grid")


def deep_scene() -> list:
    """The small bunny on a ground plane a hundred times its size, in 7,200
    triangles: a scene of the common kind whose wide tree is a level deeper
    than a full 8-wide tree over its triangles, and deeper than the first
    round of wide levels a build launches (hlbvh_cl/build/widen.py)."""
    import places
    bunny = hlbvh_cl.Mesh.load(places.MESHES / "bunny_small.ply")
    plane = grid_mesh(60)
    plane = hlbvh_cl.Mesh(plane.vertices * [100.0, 100.0, 1.0] - [3000.0, 3000.0, 0.5],
                          plane.faces, name="ground")
    return [bunny, plane]
