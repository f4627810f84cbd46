"""Mesh: arrays converted and kept read-only, and loading every supported
file format (bad arrays and bad files: test_validation.py)."""
import gzip
import re

import numpy as np
import pytest
import trimesh

from hlbvh_cl.mesh import Mesh
from shapes import QUAD, QUAD_FACES
import places

MESHES = places.MESHES

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


def test_an_obj_keeps_its_vertex_rows_used_or_not(tmp_path):
    """An OBJ's vertices in the file's order, an unused one among them, and
    faces that name them out of order: each row stays where the file has it
    (as update_vertices with the file's own vertex array needs), where
    trimesh by default would drop the unused row and renumber the rest."""
    rows = [[0, 0, 0], [9, 9, 9], [1, 0, 0], [0, 1, 0], [1, 1, 0]]
    faces = [[4, 0, 2], [2, 3, 4]]
    path = tmp_path / "rows.obj"
    path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in rows)
                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
    mesh = Mesh.load(path)
    np.testing.assert_array_equal(mesh.vertices, np.float32(rows))
    np.testing.assert_array_equal(mesh.faces, faces)


def test_an_obj_with_normals_keeps_a_row_no_face_uses(tmp_path):
    """A stray vertex row in an OBJ with normals: trimesh gives it a zero
    normal, which a Mesh refuses, and the file was refused for a normal it
    never gave.  It loads, the row in place with Mitsuba's stand-in normal,
    the used rows with the file's."""
    path = tmp_path / "stray.obj"
    path.write_text("v 0 0 0\nv 9 9 9\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 3//1 4//1\n")
    mesh = Mesh.load(path)
    np.testing.assert_array_equal(mesh.vertices[1], [9, 9, 9])
    np.testing.assert_array_equal(mesh.normals, [[0, 0, 1], [1, 0, 0], [0, 0, 1], [0, 0, 1]])
    assert mesh.has_file_normals


def test_an_obj_with_materials_keeps_its_rows_and_face_order(tmp_path):
    """trimesh splits an OBJ per material, each part a copy of the vertices
    with its faces grouped by material; the file's order, which prim_id and
    update_vertices count on, is kept all the same."""
    (tmp_path / "two.mtl").write_text("newmtl red\nKd 1 0 0\nnewmtl blue\nKd 0 0 1\n")
    rows = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 0, 0]]
    path = tmp_path / "two.obj"
    path.write_text("mtllib two.mtl\n" + "".join(f"v {x} {y} {z}\n" for x, y, z in rows)
                    + "usemtl red\nf 1 2 3\nusemtl blue\nf 2 4 3\n  usemtl red\nf 2 5 4\n")
    mesh = Mesh.load(path)
    np.testing.assert_array_equal(mesh.vertices, np.float32(rows))
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [1, 3, 2], [1, 4, 3]])


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


def test_another_librarys_mesh_is_taken_whole():
    """Mesh(trimesh_mesh) and Mesh(open3d_mesh): their arrays, as given."""
    sphere = trimesh.creation.icosphere(subdivisions=1)
    mesh = Mesh(sphere)
    np.testing.assert_array_equal(mesh.vertices, sphere.vertices.astype(np.float32))
    np.testing.assert_array_equal(mesh.faces, sphere.faces)
    assert Mesh(sphere, name="ball").name == "ball"
    with pytest.raises(TypeError, match="got a trimesh.Scene, which holds several meshes"):
        Mesh(trimesh.Scene([sphere]))
    with pytest.raises(TypeError, match=r"Mesh\(vertices, faces\) is missing faces; .* got ndarray"):
        Mesh(QUAD)


def test_an_open3d_mesh_is_taken_whole():
    o3d = pytest.importorskip("open3d")
    box = o3d.geometry.TriangleMesh.create_box()
    mesh = Mesh(box)
    np.testing.assert_array_equal(mesh.vertices, np.asarray(box.vertices, np.float32))
    np.testing.assert_array_equal(mesh.faces, np.asarray(box.triangles))


def test_the_area_is_trimesh_s():
    bunny = trimesh.load(places.MESHES / "bunny.ply", process=False)
    mesh = Mesh(bunny.vertices, bunny.faces)
    assert mesh.area == pytest.approx(float(bunny.area), rel=1e-6)
    assert Mesh(QUAD, QUAD_FACES).area == pytest.approx(
        float(trimesh.Trimesh(QUAD, QUAD_FACES, process=False).area), rel=1e-12)


@pytest.mark.parametrize("normals, message", [
    ([[0, 0, 1], [0, 0, 1], [0, 1]], "normals is not a rectangular array"),
    ([[0, 0, 1], [0, 0, 1], [0, 1, "x"]], "normals has dtype <U"),
    ([["0", "0", "1"]] * 3, "normals has dtype <U1, expected real numbers"),
    ([[0, 0, 1j]] * 3, "normals has dtype complex128, expected real numbers"),
    ([[0, 0, 1], [0, 0, 1], [0, 1, None]], "normals has dtype object, expected real numbers"),
    (np.ma.masked_array([[0, 0, -5.0], [0, 0, 1], [0, 0, 1]],
                        mask=[[0, 0, 1], [0, 0, 0], [0, 0, 0]]),
     "normals is a masked array with masked entries"),
    ([[0, 0, 1], [0, 0, 1e39], [0, 0, 1]],
     "normals[1] = [0.0, 0.0, 1e+39] is not a finite, nonzero vector in float32"),
    ([[0, 0, 1], [0, 0, 1], [0, 0, 0]], "normals[2] = [0, 0, 0] is not a finite, nonzero"),
])
def test_bad_normals_are_named_as_vertices_are(normals, message):
    """Mesh(..., normals=...) reads them as it reads vertices: strings,
    None and complex numbers are refused rather than converted, a masked
    array's hidden values are not used, and a ragged list is named."""
    triangle = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    with pytest.raises((ValueError, TypeError), match=re.escape(message)):
        Mesh(triangle, [[0, 1, 2]], normals=normals)
