"""Mesh: validation of arrays, and loading every supported file format."""
import gzip
from pathlib import Path

import numpy as np
import pytest
import trimesh

from hlbvh_cl.mesh import Mesh

MESHES = Path(__file__).resolve().parent.parent / "scenes" / "meshes"
QUAD = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3]])


def test_arrays_are_converted_and_read_only():
    mesh = Mesh(QUAD, QUAD_FACES.astype(np.uint64), name="quad")
    assert mesh.vertices.dtype == np.float32 and mesh.faces.dtype == np.int32
    assert mesh.vertices.flags.c_contiguous and mesh.faces.flags.c_contiguous
    np.testing.assert_array_equal(mesh.vertices, QUAD)
    np.testing.assert_array_equal(mesh.faces, QUAD_FACES)
    assert (mesh.vertex_count, mesh.triangle_count, mesh.name) == (4, 2, "quad")
    with pytest.raises(ValueError):
        mesh.vertices[0, 0] = 5.0
    # The caller's arrays stay the caller's.
    source = QUAD.astype(np.float32)
    Mesh(source, QUAD_FACES)
    source[0, 0] = 7.0
    assert source.flags.writeable


def test_lists_fortran_order_and_other_dtypes_are_accepted():
    mesh = Mesh(QUAD.tolist(), QUAD_FACES.tolist())
    np.testing.assert_array_equal(mesh.vertices, QUAD)
    for dtype in (np.float16, np.float64, np.longdouble, np.int16):
        np.testing.assert_array_equal(Mesh(QUAD.astype(dtype), QUAD_FACES).vertices, QUAD)
    mesh = Mesh(np.asfortranarray(QUAD), np.asfortranarray(QUAD_FACES).astype(np.uint8))
    assert mesh.vertices.flags.c_contiguous and mesh.faces.flags.c_contiguous


def test_degenerate_triangles_are_accepted():
    mesh = Mesh([[0, 0, 0], [1, 1, 1], [2, 2, 2]], [[0, 1, 2], [0, 0, 0]])
    assert mesh.triangle_count == 2


def test_bounds_cover_the_vertices_the_faces_use():
    vertices = np.vstack([QUAD, [[100.0, -100.0, 5.0]]])  # an unused vertex
    lo, hi = Mesh(vertices, QUAD_FACES).bounds
    assert lo.dtype == np.float64
    np.testing.assert_array_equal(lo, QUAD.min(axis=0))
    np.testing.assert_array_equal(hi, QUAD.max(axis=0))


@pytest.mark.parametrize("vertices, error, words", [
    (np.zeros((4, 2)), ValueError, ["vertices", "(4, 2)", "(N, 3)"]),
    (np.zeros((4, 3, 1)), ValueError, ["vertices", "(N, 3)"]),
    (np.zeros((0, 3)), ValueError, ["vertices", "empty"]),
    ([], ValueError, ["vertices", "empty"]),
    (np.ones((4, 3), dtype=bool), TypeError, ["vertices", "bool"]),
    (np.ones((4, 3), dtype=complex), TypeError, ["vertices", "complex"]),
    (np.full((4, 3), "x"), TypeError, ["vertices", "<U1"]),
    (np.array([[0, 0, None]] * 4), TypeError, ["vertices", "object"]),
    ([[0, 0, 0], [1, 0], [1, 1, 0], [0, 1, 0]], ValueError, ["vertices"]),
])
def test_bad_vertices(vertices, error, words):
    with pytest.raises(error) as caught:
        Mesh(vertices, QUAD_FACES)
    for word in words:
        assert word in str(caught.value)


@pytest.mark.parametrize("value, words", [
    (np.nan, ["vertices[2]", "not finite"]),
    (-np.inf, ["vertices[2]", "not finite"]),
    (1e39, ["vertices[2]", "overflows float32"]),
])
def test_vertices_must_be_finite_in_float32(value, words):
    vertices = QUAD.copy()
    vertices[2, 1] = value
    vertices = np.vstack([vertices, vertices])
    vertices[5, 0] = value  # a later bad row: the first one is named
    with pytest.raises(ValueError) as caught:
        Mesh(vertices, QUAD_FACES)
    for word in words:
        assert word in str(caught.value)


@pytest.mark.parametrize("faces, error, words", [
    (np.zeros((2, 4), dtype=int), ValueError, ["faces", "(2, 4)", "(M, 3)"]),
    (np.zeros((0, 3), dtype=int), ValueError, ["faces", "empty"]),
    (np.array([[0, 1, 2], [0, 2, 3]], dtype=float), TypeError, ["faces", "float64", "integers"]),
    (np.ones((2, 3), dtype=bool), TypeError, ["faces", "bool"]),
    ([[0, 1, 2], [0, -2, 3], [-1, 0, 0]], ValueError, ["faces[1]", "-2", "negative"]),
    ([[0, 1, 2], [0, 2, 3], [4, 0, 9]], ValueError, ["faces[2]", "4", "4 vertices"]),
    (np.array([[0, 1, 2], [0, 2**31, 3]], dtype=np.uint64), ValueError, ["faces[1]", "2147483648",
                                                                          "int32"]),
])
def test_bad_faces(faces, error, words):
    with pytest.raises(error) as caught:
        Mesh(QUAD, faces)
    for word in words:
        assert word in str(caught.value)


# -- loading files ------------------------------------------------------------

@pytest.fixture(scope="module")
def knight():
    return trimesh.load_mesh(MESHES / "knight.ply", process=False)


@pytest.mark.parametrize("extension", ["ply", "obj", "off", "glb", "stl"])
@pytest.mark.parametrize("compressed", [False, True])
def test_every_format_loads_with_its_order_kept(tmp_path, knight, extension, compressed):
    path = tmp_path / f"knight.{extension}"
    knight.export(path)
    if compressed:
        path = path.with_name(path.name + ".gz")
        path.write_bytes(gzip.compress(path.with_suffix("").read_bytes()))
    mesh = Mesh.load(path)
    assert mesh.name == "knight"
    expected = np.asarray(knight.vertices, dtype=np.float32)
    if extension == "stl":  # STL stores triangles, not shared vertices
        np.testing.assert_array_equal(mesh.vertices[mesh.faces], expected[knight.faces])
    else:
        np.testing.assert_array_equal(mesh.vertices, expected)
        np.testing.assert_array_equal(mesh.faces, knight.faces)


def test_project_copies_load(knight):
    mesh = Mesh.load(str(MESHES / "knight.ply"))
    np.testing.assert_array_equal(mesh.faces, knight.faces)
    assert Mesh.load(MESHES / "bunny.ply").triangle_count == 69451


def test_a_scene_of_several_meshes_is_concatenated_with_its_transforms(tmp_path, knight):
    box = trimesh.creation.box()
    move = trimesh.transformations.translation_matrix([5.0, 0, 0])
    turn = trimesh.transformations.rotation_matrix(np.pi / 2, [0, 0, 1])
    scene = trimesh.Scene()
    scene.add_geometry(knight, node_name="knight", transform=move)
    scene.add_geometry(box, node_name="box", transform=turn)
    scene.export(tmp_path / "two.glb")
    mesh = Mesh.load(tmp_path / "two.glb")
    assert mesh.triangle_count == len(knight.faces) + len(box.faces)
    expected = np.vstack([trimesh.transform_points(knight.vertices[knight.faces].reshape(-1, 3), move),
                          trimesh.transform_points(box.vertices[box.faces].reshape(-1, 3), turn)])
    got = mesh.vertices[mesh.faces].reshape(-1, 3).astype(np.float64)
    # Compare the corners as sorted sets: the parts' order is the file's business.
    np.testing.assert_allclose(np.unique(got.round(5), axis=0), np.unique(expected.round(5), axis=0),
                               atol=1e-5)


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing.ply"):
        Mesh.load(tmp_path / "nothing.ply")


@pytest.mark.parametrize("name", ["mesh.xyz", "mesh", "mesh.gz", "mesh.xyz.gz"])
def test_unknown_extension(tmp_path, name):
    (tmp_path / name).write_bytes(b"0 0 0\n")
    with pytest.raises(ValueError, match="unknown mesh file extension") as caught:
        Mesh.load(tmp_path / name)
    assert name in str(caught.value)


@pytest.mark.parametrize("name, content", [
    ("broken.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\n"
                   b"element face 3\nproperty list uchar int vertex_indices\nend_header\n\x01\x02"),
    ("broken.glb", b"glTF\x02\x00\x00\x00garbage"),
    ("broken.ply.gz", b"this is not gzip data"),
])
def test_corrupt_file(tmp_path, name, content):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(ValueError) as caught:
        Mesh.load(tmp_path / name)
    assert name in str(caught.value)


def test_file_without_triangles(tmp_path):
    path = tmp_path / "points.ply"
    trimesh.PointCloud(QUAD).export(path)
    with pytest.raises(ValueError, match="no triangles") as caught:
        Mesh.load(path)
    assert "points.ply" in str(caught.value)


def test_bad_data_in_a_file_names_the_file(tmp_path):
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError) as caught:
        Mesh.load(path)
    assert "nan.obj" in str(caught.value) and "vertices[2]" in str(caught.value)
