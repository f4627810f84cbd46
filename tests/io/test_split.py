"""split_edges: counts, same surface, same winding, no cracks."""

import numpy as np
import pytest

from hlbvh_cl.mesh import Mesh
from hlbvh_cl.io.split import split_edges
import places

MESHES = places.MESHES


@pytest.fixture(scope="module")
def knight():  # closed, 1,000 triangles
    return Mesh.load(MESHES / "knight.ply")


@pytest.fixture(scope="module")
def lucy():  # closed, 99,970 triangles, coordinates up to ~1,200
    return Mesh.load(MESHES / "lucy.ply")


def areas(vertices, faces):
    p = np.asarray(vertices, dtype=np.float64)[faces]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


def is_closed_and_oriented(faces):
    """Every edge is in exactly two faces, which use it in opposite directions."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    n = directed.max() + 1
    forward = np.sort(directed @ [n, 1])
    backward = np.sort(directed @ [1, n])
    # No directed edge twice, and each one's reverse present.
    return bool((np.diff(forward) > 0).all() and np.array_equal(forward, backward))


def edge_use_counts(faces):
    """How many faces use each undirected edge."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    return np.unique(np.sort(directed, axis=1) @ [directed.max() + 1, 1], return_counts=True)[1]


def check_on_parent_surface(vertices, faces, new_vertices, new_faces, k):
    """Every corner of every child lies in its parent triangle (float64 barycentrics)."""
    parent = np.repeat(np.arange(len(faces)), k * k)
    a, b, c = (np.asarray(vertices, np.float64)[faces[parent, n]] for n in range(3))
    e1, e2 = b - a, c - a
    normal = np.cross(e1, e2)
    size = np.linalg.norm(normal, axis=1)
    scale = np.abs(np.asarray(vertices)).max()
    ok = size > 0
    for corner in range(3):
        p = np.asarray(new_vertices, np.float64)[new_faces[:, corner]] - a
        distance = np.abs(np.einsum("ij,ij->i", p, normal))[ok] / size[ok]
        assert distance.max() <= 1e-6 * scale
        # Solve p = u e1 + v e2 in the plane through the 2x2 Gram system.
        g11, g12, g22 = (np.einsum("ij,ij->i", x, y) for x, y in ((e1, e1), (e1, e2), (e2, e2)))
        r1, r2 = np.einsum("ij,ij->i", p, e1), np.einsum("ij,ij->i", p, e2)
        det = g11 * g22 - g12 * g12
        u = (g22 * r1 - g12 * r2)[ok] / det[ok]
        v = (g11 * r2 - g12 * r1)[ok] / det[ok]
        # float32 rounding moves a point by ~eps * scale: in barycentrics that
        # is that distance over the triangle's smallest altitude.
        longest = np.max([np.linalg.norm(x, axis=1) for x in (e1, e2, c - b)], axis=0)
        tolerance = 4 * np.finfo(np.float32).eps * scale * longest[ok] / size[ok]
        assert (u >= -tolerance).all() and (v >= -tolerance).all()
        assert (u + v <= 1 + tolerance).all()
    # Same winding as the parent.
    child = np.asarray(new_vertices, np.float64)[new_faces]
    child_normal = np.cross(child[:, 1] - child[:, 0], child[:, 2] - child[:, 0])
    assert (np.einsum("ij,ij->i", child_normal, normal)[ok] > 0).all()


@pytest.mark.parametrize("k", [1, 2, 3, 4, 7])
def test_counts_surface_and_winding(knight, k):
    vertices, faces = split_edges(knight.vertices, knight.faces, k)
    assert vertices.dtype == np.float32 and faces.dtype == np.int32
    assert len(faces) == knight.triangle_count * k * k
    edges = len(np.unique(np.sort(knight.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1),
                          axis=0))
    interior = (k - 1) * (k - 2) // 2
    assert len(vertices) == knight.vertex_count + edges * (k - 1) + knight.triangle_count * interior
    # The original vertices keep their indices; every point is made once.
    np.testing.assert_array_equal(vertices[: knight.vertex_count], knight.vertices)
    assert len(np.unique(vertices, axis=0)) == len(vertices)
    total = areas(knight.vertices, knight.faces).sum()
    assert areas(vertices, faces).sum() == pytest.approx(total, rel=1e-6)
    check_on_parent_surface(knight.vertices, knight.faces, vertices, faces, k)
    # Closed stays closed: each edge in exactly two faces, once in each direction.
    assert is_closed_and_oriented(faces)


def test_k1_returns_the_input(knight):
    vertices, faces = split_edges(knight.vertices, knight.faces, 1)
    np.testing.assert_array_equal(vertices, knight.vertices)
    np.testing.assert_array_equal(faces, knight.faces)


def test_lucy_split_in_five(lucy):
    vertices, faces = split_edges(lucy.vertices, lucy.faces, 5)
    assert len(faces) == 25 * lucy.triangle_count == 2_499_250
    assert areas(vertices, faces).sum() == pytest.approx(areas(lucy.vertices, lucy.faces).sum(),
                                                         rel=1e-6)
    assert is_closed_and_oriented(faces)
    sample = np.arange(0, lucy.triangle_count, 97)  # every 97th parent and its 25 children
    children = (sample[:, None] * 25 + np.arange(25)).ravel()
    check_on_parent_surface(lucy.vertices, lucy.faces[sample], vertices, faces[children], 5)


def test_shared_edge_points_are_one_vertex():
    # Two triangles sharing the edge (1, 2), listed in opposite directions.
    vertices = np.array([[0.0, 0, 0], [1.1, 0.3, 0.7], [0.2, 1.3, -0.4], [1.5, 1.7, 0.9]])
    faces = np.array([[0, 1, 2], [3, 2, 1]])
    new_vertices, new_faces = split_edges(vertices, faces, 3)
    undirected = edge_use_counts(new_faces)
    directed = np.concatenate([new_faces[:, [0, 1]], new_faces[:, [1, 2]], new_faces[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)  # wound consistently
    # 2 x 9 children use 54 edge slots; the 4 outer edges' 12 parts are used once.
    assert (undirected == 2).sum() == (54 - 12) // 2 and (undirected == 1).sum() == 12
    on_shared = np.linalg.norm(np.cross(new_vertices.astype(np.float64) - vertices[1],
                                        vertices[2] - vertices[1]), axis=1) < 1e-6
    assert on_shared.sum() == 4  # its two ends and two points, none duplicated


def test_open_and_degenerate_input():
    rng = np.random.default_rng(3)
    vertices = rng.normal(size=(30, 3))
    faces = np.vstack([rng.integers(0, 30, (50, 3)), [[4, 4, 9], [7, 7, 7]]])
    new_vertices, new_faces = split_edges(vertices, faces, 4)
    assert len(new_faces) == 16 * len(faces)
    assert areas(new_vertices, new_faces).sum() == pytest.approx(areas(vertices, faces).sum(),
                                                                 rel=1e-6)
    check_on_parent_surface(vertices, faces, new_vertices, new_faces, 4)


@pytest.mark.parametrize("k", [0, -2, 2.5, 2.0, "3", True, None])
def test_bad_k(knight, k):
    # a wrong kind is a TypeError, a bad integer a ValueError (hlbvh_cl.core.inputs)
    wrong = TypeError if isinstance(k, (bool, float, str)) or k is None else ValueError
    with pytest.raises(wrong, match=r"k \(edges per input edge\) must be an integer >= 1"):
        split_edges(knight.vertices, knight.faces, k)


def test_numpy_integer_k(knight):
    _, faces = split_edges(knight.vertices, knight.faces, np.int64(2))
    assert len(faces) == 4 * knight.triangle_count


def test_bad_arrays_are_named():
    with pytest.raises(ValueError, match=r"faces\[0\].*out of range"):
        split_edges(np.zeros((3, 3)), [[0, 1, 3]], 2)
