"""Input validation: every bad argument is refused before any kernel runs or
any buffer is allocated, with an error that names the array, the row and
what is wrong: rays and their limits, ray-query settings, meshes (arrays and
files), scenes and update_vertices, scenes too large for the device, and
the renderer's, cameras' and lights' arguments.
"""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pyopencl as cl
import pytest
import trimesh

import hlbvh_cl
from hlbvh_cl import DeviceMemoryError
from hlbvh_cl import Scene
from hlbvh_cl.core import inputs as inputs_module
from hlbvh_cl.build.pipeline import Geometry, build
from hlbvh_cl.device.runtime import Runtime, runtime
from hlbvh_cl.mesh import Mesh
from hlbvh_cl.query.engine import Engine
from hlbvh_cl.query.rays import RayQuery
import built
from invariants import check_tree
from ray_cases import scene_case
from render_scene import CAMERA, COLORS, LIGHT, renderer, scene  # noqa: F401 (fixtures)
from shapes import QUAD, QUAD_FACES


# -- rays and their limits -------------------------------------------------------

GOOD_O = np.zeros((3, 3))
GOOD_D = np.array([[0, 0, 1.0]] * 3)


def _with_row(array, row, value):
    array = np.array(array, dtype=np.float64)
    array[row] = value
    return array


BAD_INPUTS = [
    # (origins, directions, tmin, tmax, exception, message fragment)
    (np.zeros((3, 2)), GOOD_D, 0.0, np.inf, ValueError, r"origins must have shape \(\.\.\., 3\)"),
    (np.zeros(()), GOOD_D, 0.0, np.inf, ValueError, r"origins must have shape"),
    (np.zeros((3, 7)), None, 0.0, np.inf, ValueError, r"rays must have shape \(\.\.\., 6\)"),
    (GOOD_O, np.zeros((3, 3, 1)), 0.0, np.inf, ValueError, r"directions must have shape"),
    (np.zeros((4, 3)), GOOD_D, 0.0, np.inf, ValueError, r"origins of shape \(4, 3\) and directions of shape \(3, 3\) do not broadcast"),
    (_with_row(GOOD_O, 1, [0, np.nan, 0]), GOOD_D, 0.0, np.inf, ValueError, r"origins\[1\].*not finite"),
    (_with_row(GOOD_O, 2, [np.inf, 0, 0]), GOOD_D, 0.0, np.inf, ValueError, r"origins\[2\].*not finite"),
    (_with_row(GOOD_O, 0, [1e39, 0, 0]), GOOD_D, 0.0, np.inf, ValueError, r"origins\[0\].*overflows float32"),
    (GOOD_O, _with_row(GOOD_D, 2, [0, -np.inf, 1]), 0.0, np.inf, ValueError, r"directions\[2\].*not finite"),
    (GOOD_O, _with_row(GOOD_D, 1, [0, 0, 0]), 0.0, np.inf, ValueError, r"directions\[1\].*zero length"),
    (GOOD_O, _with_row(GOOD_D, 1, [-0.0, 0, 0]), 0.0, np.inf, ValueError, r"directions\[1\].*zero length"),
    (GOOD_O, _with_row(GOOD_D, 0, [1e-40, 0, 0]), 0.0, np.inf, ValueError, r"directions\[0\].*too short"),
    (GOOD_O, _with_row(GOOD_D, 2, [1e-50, 0, 0]), 0.0, np.inf, ValueError, r"directions\[2\].*zero length"),
    (GOOD_O, GOOD_D, -1.0, np.inf, ValueError, r"tmin = -1.0 must be finite and >= 0"),
    (GOOD_O, GOOD_D, [0.0, -0.5, 0.0], np.inf, ValueError, r"tmin\[1\] = -0.5"),
    (GOOD_O, GOOD_D, np.nan, np.inf, ValueError, r"tmin is NaN"),
    (GOOD_O, GOOD_D, np.inf, np.inf, ValueError, r"tmin = inf must be finite"),
    (GOOD_O, GOOD_D, 0.0, [1.0, np.nan, 1.0], ValueError, r"tmax\[1\] is NaN"),
    (GOOD_O, GOOD_D, 2.0, 1.0, ValueError, r"tmin = 2.0 is greater than tmax = 1.0"),
    (GOOD_O, GOOD_D, [0.0, 0.0, 5.0], [1.0, 1.0, 4.0], ValueError, r"ray 2: tmin\[2\] = 5.0 is greater than tmax\[2\] = 4.0"),
    (GOOD_O, GOOD_D, 0.0, -1.0, ValueError, r"tmin = 0.0 is greater than tmax = -1.0"),
    # float32 limits, which are checked as they are (no float64 copy)
    (GOOD_O, GOOD_D, np.float32([0.0, 0.0, np.nan]), np.inf, ValueError, r"tmin\[2\] is NaN"),
    (GOOD_O, GOOD_D, np.float32([0.0, -np.inf, 0.0]), np.inf, ValueError, r"tmin\[1\] = -inf must be finite"),
    (GOOD_O, GOOD_D, np.float32([np.inf, 0.0, 0.0]), np.inf, ValueError, r"tmin\[0\] = inf must be finite"),
    (GOOD_O, GOOD_D, np.float32([0.0, 3.0, 0.0]), np.float32([1.0, 2.5, 1.0]), ValueError, r"ray 1: tmin\[1\] = 3.0 is greater than tmax\[1\] = 2.5"),
    (GOOD_O, GOOD_D, [0.0, 0.0], np.inf, ValueError, r"tmin has shape \(2,\), which does not broadcast to the rays' shape \(3,\)"),
    (GOOD_O, GOOD_D, 0.0, np.ones((3, 1)), ValueError, r"tmax has shape \(3, 1\), which does not broadcast"),
    (GOOD_O.astype(complex), GOOD_D, 0.0, np.inf, TypeError, r"origins must hold real numbers"),
    (GOOD_O, GOOD_D.astype(bool), 0.0, np.inf, TypeError, r"directions must hold real numbers"),
    (GOOD_O, [["a", "b", "c"]] * 3, 0.0, np.inf, TypeError, r"directions must hold real numbers"),
    ([[0, 0, 0], [0, 0]], GOOD_D[:2], 0.0, np.inf, ValueError, r"origins is not a rectangular"),
    (GOOD_O, GOOD_D, "0", np.inf, TypeError, r"tmin must hold real numbers"),
    (GOOD_O.astype("m8[s]"), GOOD_D, 0.0, np.inf, TypeError, r"origins must hold real numbers"),
    (np.ma.masked_array(GOOD_O, mask=np.eye(3, dtype=bool)), GOOD_D, 0.0, np.inf, ValueError,
     r"origins is a masked array with masked entries"),
    # a broadcast view: 2**32 rays that take no memory
    (GOOD_O[0], np.broadcast_to(GOOD_D[0], (2**16, 2**16, 3)), 0.0, np.inf, ValueError,
     r"4294967296 rays in one call \(leading shape \(65536, 65536\)\): at most 2\*\*32 - 1"),
]


@pytest.mark.parametrize("origins, directions, tmin, tmax, error, message", BAD_INPUTS,
                         ids=[f"{i}:{case[-1][:30]}" for i, case in enumerate(BAD_INPUTS)])
def test_bad_input_raises_before_any_kernel(monkeypatch, origins, directions, tmin, tmax, error, message):
    case = scene_case("cube")

    def no_launch(*args, **kwargs):
        raise AssertionError("a kernel was launched for bad input")

    monkeypatch.setattr(Engine, "run", no_launch)
    with pytest.raises(error, match=message):
        case.scene.intersect(origins, directions, tmin, tmax)
    with pytest.raises(error, match=message):
        case.scene.occluded(origins, directions, tmin, tmax)


@pytest.mark.parametrize("query", ["closest_points", "signed_distance", "contains"])
def test_too_many_points_are_refused_before_any_kernel(monkeypatch, query):
    case = scene_case("cube")
    monkeypatch.setattr(Engine, "run", lambda *args, **kwargs: pytest.fail("a kernel ran"))
    points = np.broadcast_to(np.zeros(3), (2**32, 3))  # a view: no memory
    with pytest.raises(ValueError, match=r"4294967296 points in one call .* split the batch"):
        getattr(case.scene, query)(points)


def test_python_integers_past_int64_are_numbers():
    """numpy keeps a Python integer past int64 (10**30) as an object: such
    limits, coordinates and distances are numbers as 1e30 is, and one past
    float64 is named; an object array of anything else stays refused."""
    case = scene_case("cube")
    origins, directions = GOOD_O, GOOD_D
    for name, big in (("tmax", {"tmax": 10**30}), ("tmin", {"tmin": [0, 10**30, 0]})):
        floated = {key: np.asarray(value, np.float64) for key, value in big.items()}
        np.testing.assert_array_equal(case.scene.intersect(origins, directions, **big).t,
                                      case.scene.intersect(origins, directions, **floated).t,
                                      err_msg=name)
    far = [[0.5, 0.5, 10**30]]
    assert case.scene.intersect(far, [[0, 0, -1]]).t[0] == case.scene.intersect(
        [[0.5, 0.5, 1e30]], [[0, 0, -1]]).t[0]
    assert case.scene.closest_points([[0.5, 0.5, 3.0]], max_distance=10**30).found.all()
    with pytest.raises(ValueError, match="tmax must be finite numbers, got an integer of 1329 "
                                         "bits, past float64's range"):
        case.scene.intersect(origins, directions, tmax=10**400)
    with pytest.raises(TypeError, match="tmax must hold real numbers, got dtype object"):
        case.scene.intersect(origins, directions, tmax=np.array(["far"] * 3, dtype=object))


def test_camera_rays_take_a_scene_or_none():
    with pytest.raises(TypeError, match="scene must be a hlbvh_cl.Scene, whose device makes "
                                        "the rays, or None .numpy rays., got str"):
        hlbvh_cl.Camera((0, 0, 3), (0, 0, 0)).rays(4, 3, scene="scene")


def test_short_directions_are_found_in_any_block_of_a_large_batch(monkeypatch):
    """The direction check goes block by block and only looks at rows in the
    blocks that hold a tiny component: a short row is found (and named) past
    the first block, while tiny components in a row that is long enough pass."""
    case = scene_case("cube")
    monkeypatch.setattr(Engine, "run", lambda *a, **k: pytest.fail("a kernel ran"))
    count = 3 * inputs_module.CHECK_BLOCK + 17
    origins = np.zeros((count, 3), np.float32)
    directions = np.tile(np.float32([0.3, -0.5, 0.8]), (count, 1))
    directions[5] = [0.0, 1e-40, 1.0]          # tiny components, long enough
    directions[count - 3] = [-0.0, 1e-39, 0.0]  # the last block
    directions[count - 1] = [0.0, 0.0, 0.0]
    for query in (case.scene.intersect, case.scene.occluded):
        with pytest.raises(ValueError, match=rf"directions\[{count - 3}\].*too short"):
            query(origins, directions)
    directions[count - 3] = [1e-30, 0.0, 0.0]
    with pytest.raises(ValueError, match=rf"directions\[{count - 1}\].*zero length"):
        case.scene.intersect(origins, directions)


@pytest.mark.parametrize("which, row, value, message", [
    ("origins", "last", [0.0, np.nan, 0.0], "not finite"),
    ("origins", "middle", [1e39, 0.0, 0.0], "overflows float32"),
    ("directions", "middle", [0.0, -np.inf, 1.0], "not finite"),
    ("directions", "first", [0.0, 0.0, 0.0], "zero length"),
])
def test_bad_rows_are_named_in_every_part_of_a_large_batch(monkeypatch, which, row, value, message):
    """Large batches are checked a run of blocks per thread: a bad row is
    named by its index wherever it lies, and no kernel runs."""
    case = scene_case("cube")
    monkeypatch.setattr(Engine, "run", lambda *a, **k: pytest.fail("a kernel ran"))
    count = 4 * inputs_module.CHECK_BLOCK + 5
    index = {"first": 3, "middle": 2 * inputs_module.CHECK_BLOCK + 1, "last": count - 2}[row]
    rays = {"origins": np.zeros((count, 3)), "directions": np.tile([0.3, -0.5, 0.8], (count, 1))}
    rays[which][index] = value
    for query in (case.scene.intersect, case.scene.occluded):
        with pytest.raises(ValueError, match=rf"{which}\[{index}\] = .*{message}"):
            query(rays["origins"], rays["directions"])


# -- ray-query settings -----------------------------------------------------------

def test_bad_tree_and_chunk_size():
    case = scene_case("cube")
    q = RayQuery(built.runtime(case.scene))
    with pytest.raises(TypeError, match="tree must be a hlbvh_cl.core.tree.Tree"):
        q.intersect("tree", GOOD_O, GOOD_D)
    with pytest.raises(ValueError, match="max_rays_per_launch must be an integer >= 1, got 0"):
        RayQuery(built.runtime(case.scene), max_rays_per_launch=0)
    with pytest.raises(TypeError, match="max_rays_per_launch must be an integer >= 1, got a "
                                        "number 2.5"):
        RayQuery(built.runtime(case.scene), max_rays_per_launch=2.5)


def test_packet_size_is_checked():
    case = scene_case("cube")
    with pytest.raises(ValueError, match="packet_size"):
        RayQuery(built.runtime(case.scene), packet_size=4)
    for wrong in (True, 8.0, "8"):
        with pytest.raises(TypeError, match="packet_size"):
            RayQuery(built.runtime(case.scene), packet_size=wrong)


# -- meshes: arrays ---------------------------------------------------------------

@pytest.mark.parametrize("vertices, error, words", [
    (np.zeros((4, 2)), ValueError, ["vertices", "(4, 2)", "(N, 3)"]),
    (np.zeros((4, 3, 1)), ValueError, ["vertices", "(N, 3)"]),
    (np.zeros((0, 3)), ValueError, ["vertices", "empty"]),
    ([], ValueError, ["vertices", "empty"]),
    (np.ones((4, 3), dtype=bool), TypeError, ["vertices", "bool"]),
    (np.ones((4, 3), dtype=complex), TypeError, ["vertices", "complex"]),
    (np.full((4, 3), "x"), TypeError, ["vertices", "<U1"]),
    (np.array([[0, 0, None]] * 4), TypeError, ["vertices", "object"]),
    (np.ma.masked_array(np.ones((4, 3)), mask=np.eye(4, 3, dtype=bool)), ValueError,
     ["vertices", "masked entries"]),
    ([[0, 0, 0], [1, 0], [1, 1, 0], [0, 1, 0]], ValueError,
     ["vertices", "not a rectangular array"]),
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


def test_a_mesh_spanning_float32_s_range_builds_without_numpy_s_warnings(suite_device):
    """Its edges overflow float32 in the frame's degenerate-triangle check,
    whose numpy RuntimeWarning ("overflow encountered in subtract") leaked
    to the user (and the CLI printed it with our source line)."""
    vertices = np.array([[-3e38, 0, 0], [3e38, 0, 0], [0, 1, 0]], np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Scene([Mesh(vertices, [[0, 1, 2]])], device=suite_device)


def test_a_mesh_below_float32_s_normal_range_is_refused(suite_device):
    """A float64 mesh whose coordinates are all under float32's smallest
    normal number would round to subnormals or 0 and lose its shape; one
    that reaches the normal range keeps its tiny details as rounding does."""
    with pytest.raises(ValueError) as caught:
        Mesh(QUAD * 1e-50, QUAD_FACES)
    for word in ("vertices the faces use are all below float32's normal range", "vertices[1]",
                 "scale it up"):
        assert word in str(caught.value)
    with pytest.raises(ValueError, match="below float32's normal range"):
        Mesh(QUAD * 1e-39, QUAD_FACES)
    # a vertex no face uses does not save it (it had: the mesh rounded to a
    # sliver that rays missed, in silence), in a Mesh or a moved one
    unused = np.vstack([QUAD * 1e-50, [1.0, 1.0, 1.0]])
    with pytest.raises(ValueError, match=r"normal range \(the largest, vertices\[1\]"):
        Mesh(unused, QUAD_FACES)
    scene = hlbvh_cl.Scene([Mesh(np.vstack([QUAD, [1.0, 1.0, 1.0]]), QUAD_FACES)],
                           device=suite_device)
    with pytest.raises(ValueError, match="below float32's normal range"):
        scene.update_vertices(0, unused)
    Mesh(QUAD * 1e-37, QUAD_FACES)  # normal: kept
    mixed = QUAD.copy()
    mixed[:3] *= 1e-50
    Mesh(mixed, QUAD_FACES)  # the mesh reaches 1: its tiny corner rounds as any would
    Mesh(np.zeros((4, 3)), QUAD_FACES)  # every triangle a point: no shape to lose


@pytest.mark.parametrize("faces, error, words", [
    (np.zeros((2, 4), dtype=int), ValueError, ["faces", "(2, 4)", "(M, 3)"]),
    (np.zeros((0, 3), dtype=int), ValueError, ["faces", "empty"]),
    ([], ValueError, ["faces", "empty"]),  # numpy reads [] as float64: empty, not a dtype fault
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


# -- meshes: files ----------------------------------------------------------------

def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing.ply"):
        Mesh.load(tmp_path / "nothing.ply")
    (tmp_path / "folder.ply").mkdir()
    with pytest.raises(ValueError, match=r"folder\.ply: is a folder, not a mesh file"):
        Mesh.load(tmp_path / "folder.ply")
    (tmp_path / "plain").mkdir()  # no suffix: still a folder, not an unknown format
    with pytest.raises(ValueError, match=r"plain: is a folder, not a mesh file"):
        Mesh.load(tmp_path / "plain")


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
    ("deflate.ply.gz", b"\x1f\x8b\x08\x00\x00\x00\x00\x00\x00\xffgarbage!!"),  # zlib.error
])
def test_corrupt_file(tmp_path, name, content):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(ValueError) as caught:
        Mesh.load(tmp_path / name)
    assert name in str(caught.value)


def test_a_file_too_large_for_memory_is_named(tmp_path, monkeypatch):
    path = tmp_path / "huge.ply"
    path.write_bytes(b"ply\n" + b"\0" * 1000)

    def out_of_memory(self):
        raise MemoryError
    monkeypatch.setattr(type(path), "read_bytes", out_of_memory)
    with pytest.raises(ValueError, match=r"huge\.ply: too large to read into this process's "
                                         r"memory \(1,004 bytes on disk\)"):
        Mesh.load(path)


def test_file_without_triangles(tmp_path):
    path = tmp_path / "points.ply"
    trimesh.PointCloud(QUAD).export(path)
    with pytest.raises(ValueError, match="no triangles") as caught:
        Mesh.load(path)
    assert "points.ply" in str(caught.value)


PLY_HEADER = ("ply\nformat ascii 1.0\nelement vertex {vertices}\nproperty float x\n"
              "property float y\nproperty float z\nelement face {faces}\n"
              "property list uchar int vertex_indices\nend_header\n")


@pytest.mark.parametrize("vertices, faces, read", [
    # trimesh reads nothing when the header claims more vertices than there are
    ("1,000,000,000,000", "1", "0 triangles and 0 vertices"),
    # and stops, silently, where an ASCII file is cut within its faces
    ("3", "5", "1 triangle and 3 vertices"),
])
def test_a_ply_whose_header_counts_are_wrong_says_so(tmp_path, vertices, faces, read):
    """A PLY holding fewer vertices or faces than its header declares is
    refused with the header's counts and what was read, not loaded as what
    little trimesh could read."""
    path = tmp_path / "cut.ply"
    path.write_text(PLY_HEADER.format(vertices=vertices.replace(",", ""), faces=faces)
                    + "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    with pytest.raises(ValueError) as caught:
        Mesh.load(path)
    plural = "s" * (faces != "1")
    assert str(caught.value) == (
        f"{path}: its PLY header declares {faces} face{plural} and {vertices} vertices, but "
        f"trimesh read {read}: the file is cut short or its header's counts are wrong")


@pytest.mark.parametrize("face", ["f 2/1 3/0 0/2", "f 0 1 2", "f\t-0 1 2", "f 1 2 00"])
def test_an_obj_face_with_vertex_index_0_is_refused(tmp_path, face):
    """OBJ counts vertices from 1; trimesh would read 0 as the first vertex.
    (A 0 first on its line, right after the f, was let through.)"""
    path = tmp_path / "zero.obj"
    path.write_text(f"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3  # 0 in a comment\n{face}\n")
    with pytest.raises(ValueError) as caught:
        Mesh.load(path)
    assert str(caught.value) == (f"{path}: line 5: {face!r} has vertex index 0; OBJ "
                                 "indices count from 1 (or back from -1 for the last vertex)")


@pytest.mark.parametrize("face", ["f 1 2 3", "f 10 2 3", "f 1/10 2/20 3/30", "f 1 2 -3"])
def test_an_obj_face_with_zeros_inside_its_indices_is_read(tmp_path, face):
    path = tmp_path / "tens.obj"
    path.write_text("v 0 0 0\n" * 9 + "v 1 0 0\nv 0 1 0\n" + "vt 0 0\n" * 30 + face + "\n")
    assert Mesh.load(path).triangle_count == 1


def test_bad_data_in_a_file_names_the_file(tmp_path):
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError) as caught:
        Mesh.load(path)
    assert "nan.obj" in str(caught.value) and "vertices[2]" in str(caught.value)


# -- scenes -----------------------------------------------------------------------

def test_scene_rejects_bad_arguments(meshes):
    with pytest.raises(ValueError, match="meshes is empty"):
        Scene([])
    with pytest.raises(TypeError, match=r"meshes\[1\]"):
        Scene([meshes["knight"], "teapot.ply"])
    with pytest.raises(TypeError, match="meshes must be"):
        Scene("knight.ply")
    with pytest.raises(ValueError, match="builder"):
        Scene([meshes["knight"]], builder="sah")
    with pytest.raises(ValueError, match="morton_bits"):
        Scene([meshes["knight"]], morton_bits=32)
    with pytest.raises(ValueError, match="matches no OpenCL device"):
        Scene([meshes["knight"]], device="no-such-device")


def test_update_vertices_rejects_bad_input(meshes):
    knight = meshes["knight"]
    scene = Scene([knight])
    with pytest.raises(ValueError, match="geom_id 1 is out of range"):
        scene.update_vertices(1, knight.vertices)
    with pytest.raises(TypeError, match="geom_id"):
        scene.update_vertices("0", knight.vertices)
    with pytest.raises(ValueError, match="rows but mesh 0 has"):
        scene.update_vertices(0, knight.vertices[:-1])
    bad = knight.vertices.copy()
    bad[17, 1] = np.nan
    with pytest.raises(ValueError, match="17"):
        scene.update_vertices(0, bad)
    with pytest.raises(ValueError, match="shape"):
        scene.update_vertices(0, knight.vertices[:, :2])
    check_tree(scene)  # nothing was touched


def test_too_large_for_the_device_fails_before_allocating(meshes, monkeypatch):
    rt = runtime()
    small = dataclasses.replace(rt.device, max_mem_alloc_size=1 << 20, global_mem_size=1 << 22)
    tiny_rt = Runtime(small)
    mesh = meshes["bunny"]
    geometry = Geometry.upload(tiny_rt, mesh.vertices, mesh.faces, np.zeros(1, np.int32))
    allocations = []
    real_buffer = cl.Buffer

    def counting_buffer(*args, **kwargs):
        allocations.append(args)
        return real_buffer(*args, **kwargs)

    monkeypatch.setattr(cl, "Buffer", counting_buffer)
    with pytest.raises(DeviceMemoryError, match="MiB"):
        build(tiny_rt, geometry)
    assert allocations == []


def test_scene_too_large_is_refused_before_upload(monkeypatch, meshes):
    from hlbvh_cl import scene as scene_module
    uploads = []
    monkeypatch.setattr(scene_module.Geometry, "upload", lambda *a: uploads.append(a))
    rt = runtime()
    monkeypatch.setattr(rt, "device", dataclasses.replace(rt.device, global_mem_size=1 << 20))
    with pytest.raises(DeviceMemoryError, match="building a BVH over 69,451 triangles"):
        Scene([meshes["bunny"]])
    assert uploads == []


def test_more_vertices_than_int32_indices_reach_are_refused(monkeypatch, meshes):
    """The meshes' faces are joined into one int32 index array: a scene
    whose vertex total passes that raises, naming the count, before any
    upload (the limit is lowered here: 2**31 vertices take 24 GiB)."""
    from hlbvh_cl.build import pipeline as build_module
    from hlbvh_cl import scene as scene_module
    uploads = []
    monkeypatch.setattr(scene_module.Geometry, "upload", lambda *a: uploads.append(a))
    monkeypatch.setattr(build_module, "MAX_VERTICES", 1000)
    quad = Mesh(QUAD, QUAD_FACES)
    big = Mesh(np.zeros((999, 3), np.float32), [[0, 1, 2]])
    with pytest.raises(ValueError, match="the scene has 1003 vertices over all its meshes"):
        Scene([quad, big])
    assert uploads == []
    # a compact tree's records count triangles and vertices together
    fits = Mesh(np.zeros((990, 3), np.float32), np.zeros((20, 3), np.int32))
    with pytest.raises(ValueError, match="the scene has 20 triangles and 990 vertices; a compact "
                                         "tree's int32 leaf records reach at most 1000"):
        Scene([fits], compact=True)
    assert uploads == []


# -- renderer, cameras, lights -------------------------------------------------------

@pytest.mark.parametrize("kwargs, error, words", [
    ({"camera": "front"}, TypeError, "camera"),
    ({"width": 0}, ValueError, "width"),
    ({"height": -3}, ValueError, "height"),
    ({"width": 100_000}, ValueError, "width"),
    ({"width": 12.5}, TypeError, "width"),
    ({"width": True}, TypeError, "width"),
    ({"shading": "phong"}, ValueError, "shading"),
    ({"shading": None}, TypeError, "shading"),
    ({"spp": 0}, ValueError, "spp"),
    ({"spp": 2.0}, TypeError, "spp"),
    ({"ao_samples": 0}, ValueError, "ao_samples"),
    ({"ao_distance": -1.0}, ValueError, "ao_distance"),
    ({"ao_distance": float("nan")}, ValueError, "ao_distance"),
    ({"shadows": "yes"}, TypeError, "shadows"),
    # past float32, which the kernels take it in (an overflow warning before)
    ({"ao_distance": 1e300}, ValueError, r"ao_distance must be a finite number > 0 and <= 3.40282e\+38"),
    ({"progress": "x"}, TypeError, "progress must be True or False, got str"),
])
def test_bad_render_arguments_are_named(scene, renderer, kwargs, error, words):
    arguments = {"camera": CAMERA, "width": 8, "height": 6, **kwargs}
    with pytest.raises(error, match=words):
        renderer.render(**arguments)


def test_bad_colors_and_light_are_named(scene, renderer):
    try:
        renderer.colors = COLORS[:2]
        with pytest.raises(ValueError, match="colors has 2 entries"):
            renderer.render(CAMERA, 8, 6)
        renderer.colors = [COLORS[0], (0.5, 1.5, 0.5), COLORS[2]]
        with pytest.raises(ValueError, match=r"colors\[1\]"):
            renderer.render(CAMERA, 8, 6)
        renderer.colors = [COLORS[0], COLORS[1], (True, False, True)]
        with pytest.raises(TypeError, match=r"colors\[2\] = \(True, False, True\): expected 3 "
                                            "numbers in 0..1 .RGB., not booleans"):
            renderer.render(CAMERA, 8, 6)
        renderer.colors = COLORS
        renderer.light = "sun"
        with pytest.raises(TypeError, match="light"):
            renderer.render(CAMERA, 8, 6)
    finally:
        renderer.colors, renderer.light = COLORS, LIGHT


def test_colors_and_light_of_none_are_the_defaults(scene, renderer):
    """As in the constructor: None, reassigned, gives the defaults again."""
    defaults = hlbvh_cl.Renderer(scene).render(CAMERA, 8, 6)
    try:
        renderer.colors, renderer.light = None, None
        assert np.array_equal(renderer.render(CAMERA, 8, 6), defaults)
    finally:
        renderer.colors, renderer.light = COLORS, LIGHT


@pytest.mark.parametrize("kwargs, words", [
    ({"eye": (0, 0, 0), "target": (0, 0, 0)}, "equals eye"),
    ({"eye": (0, 0, 0), "target": (0, 1, 0)}, "parallel"),
    ({"eye": (0, 0, 0), "target": (0, 0, 1), "up": (0, 0, 0)}, "zero or parallel"),
    ({"eye": (0, 0, np.nan), "target": (0, 0, 1)}, "eye"),
    ({"eye": (0, 0), "target": (0, 0, 1)}, "eye"),
    ({"eye": (0, 0, 0), "target": (0, 0, 1), "fov_deg": 180}, "fov_deg"),
    ({"eye": (0, 0, 0), "target": (0, 0, 1), "fov_deg": 0}, "fov_deg"),
    ({"eye": (0, 0, 0), "target": (0, 0, 1), "fov_deg": 10**400},
     "fov_deg must be a finite number, got an integer of 1329 bits, beyond float's range"),
    ({"eye": (0, 0, -1e39), "target": (0, 0, 0)}, r"eye \[0.0, 0.0, -1e\+39\] does not fit float32"),
    ({"eye": (-1e308, 0, 0), "target": (1e308, 0, 0)}, "eye .* does not fit float32"),
    ({"eye": (0, 0, 0), "target": (0, 0, 1), "near_clip": -1}, "near_clip must be .* >= 0"),
    ({"eye": (0, 0, 0), "target": (0, 0, 1), "near_clip": np.inf}, "near_clip must be a finite"),
    ({"eye": (0, 0, 0), "target": (0, 0, 1), "near_clip": 2, "far_clip": 2},
     "far_clip must be a finite number > 2"),
    ({"eye": (0, 0, 0), "target": (0, 0, 1), "far_clip": np.nan}, "far_clip"),
])
def test_bad_cameras_are_named(kwargs, words):
    with pytest.raises(ValueError, match=words):
        hlbvh_cl.Camera(**kwargs)


@pytest.mark.parametrize("kwargs, words", [
    ({"direction": (0, 0, 0)}, "zero vector"),
    ({"intensity": -1}, "intensity"),
    ({"intensity": 1e39}, r"intensity must be a finite number >= 0 and <= 1e\+20"),
    ({"intensity": 10**400}, "intensity must be a finite number, got an integer of 1329 bits"),
    ({"ambient": 2}, "ambient"),
])
def test_bad_lights_are_named(kwargs, words):
    with pytest.raises(ValueError, match=words):
        hlbvh_cl.Light(**kwargs)


def test_directions_of_any_finite_length_are_normalised():
    """|(0, 0, -1e300)| overflows and |(0, 0, 1e-320)| underflows in float64;
    their directions do not."""
    assert hlbvh_cl.Light(direction=(0, 0, -1e300)).direction == (0.0, 0.0, -1.0)
    assert hlbvh_cl.Light(direction=(0, 0, 1e-320)).direction == (0.0, 0.0, 1.0)
    plain = hlbvh_cl.Camera(eye=(0, 0, 0), target=(0, 0, 1)).basis()
    for up in ((0, 1e300, 0), (0, 1e-320, 0)):
        for got, expected in zip(hlbvh_cl.Camera(eye=(0, 0, 0), target=(0, 0, 1), up=up).basis(),
                                 plain):
            np.testing.assert_array_equal(got, expected)


def test_masked_entries_and_timedeltas_are_refused_everywhere(suite_device):
    """np.asarray drops a masked array's mask (and numpy counts timedelta64
    as an integer): every input that takes an array refuses them."""
    hidden = np.ma.masked_array(np.eye(3, 4), mask=np.eye(3, 4, dtype=bool))
    box = Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    with pytest.raises(ValueError, match="masked entries"):
        hlbvh_cl.Scene([box], device=suite_device, instances=[(0, hidden)])
    with pytest.raises(ValueError, match="masks is a masked array"):
        hlbvh_cl.Scene([box], device=suite_device,
                       masks=np.ma.masked_array([1], mask=[True]))
    scene = hlbvh_cl.Scene([box], device=suite_device, instances=[(0, np.eye(3, 4))])
    with pytest.raises(ValueError, match="transforms is a masked array"):
        scene.set_transforms([0], hidden[None])
    with pytest.raises(ValueError, match="instance_ids is a masked array"):
        scene.set_transforms(np.ma.masked_array([0], mask=[True]), np.eye(3, 4)[None])
    with pytest.raises(TypeError, match="instance_ids must be integers"):
        scene.set_transforms(np.array([0], "m8[s]"), np.eye(3, 4)[None])
    rays = np.zeros((2, 3)), np.ones((2, 3))
    with pytest.raises(ValueError, match="mask is a masked array"):
        scene.intersect(*rays, mask=np.ma.masked_array([1, 1], mask=[False, True]))
    with pytest.raises(TypeError, match="mask must hold integers"):
        scene.intersect(*rays, mask=np.array([1, 1], "m8[s]"))
    with pytest.raises(ValueError, match="eye is a masked array"):
        hlbvh_cl.Camera(eye=np.ma.masked_array([0, 0, 5], mask=[0, 0, 1]), target=(0, 0, 0))
    with pytest.raises(TypeError, match="eye must be 3 numbers"):
        hlbvh_cl.Camera(eye=np.array([0, 0, 5], "m8[s]"), target=(0, 0, 0))
    with pytest.raises(ValueError, match="light.direction is a masked array"):
        hlbvh_cl.Light(direction=np.ma.masked_array([0, 1, 0], mask=[0, 1, 0]))


def test_device_arrays_are_named_and_array_interfaces_read_in_place(suite_device, monkeypatch):
    """A pyopencl array (which numpy reads as one opaque object) is refused
    by name with what to pass instead where a call takes host arrays (a
    mesh's), and rays half on the device are named; an object exposing
    __array_interface__ is read without a copy on a CPU device: the
    kernel's buffer wraps the caller's memory."""
    import pyopencl.array as cla

    from hlbvh_cl.query import engine
    scene = hlbvh_cl.Scene([Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])],
                           device=suite_device)
    origins = np.float32([[0.2, 0.2, -1.0]] * 64)
    directions = np.float32([[0.0, 0.0, 1.0]] * 64)
    on_device = cla.to_device(scene.queue, origins)
    with pytest.raises(TypeError, match=r"vertices is a pyopencl array: .* vertices\.get\(\)"):
        Mesh(on_device[:3], [[0, 1, 2]])
    for call, name in [(lambda: scene.intersect(on_device, directions), "directions"),
                       (lambda: scene.occluded(origins, on_device), "origins"),
                       (lambda: scene.intersect_all(origins, on_device), "origins"),
                       (lambda: scene.count_intersections(on_device, directions), "directions")]:
        with pytest.raises(TypeError, match=rf"{name} is not a pyopencl array while another"):
            call()

    class Interface:  # e.g. a framework's CPU tensor, as numpy sees it
        def __init__(self, array):
            self.__array_interface__ = array.__array_interface__
    wrapped = []  # the host memory of every buffer the call makes
    make = cl.Buffer
    monkeypatch.setattr(cl, "Buffer", lambda *args, hostbuf=None, **kwargs: (
        wrapped.append(hostbuf), make(*args, hostbuf=hostbuf, **kwargs))[1])
    hits = scene.intersect(Interface(origins), Interface(directions))
    monkeypatch.undo()
    assert hits.hit.all() and np.allclose(hits.t, 1.0)
    if engine.zero_copy(built.runtime(scene)):  # CPU devices
        assert any(a is not None and np.shares_memory(a, origins) for a in wrapped)
        assert any(a is not None and np.shares_memory(a, directions) for a in wrapped)


def test_ragged_inputs_odd_scalars_and_far_cameras_are_named(suite_device):
    """Review G's cases: ragged lists name their array (not numpy's bare
    'setting an array element with a sequence'); a float morton_bits, a bool
    coordinate and a complex number are refused, not rounded or truncated; a
    camera that a scene's scaled frame puts past float32 is named as given."""
    box = Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    ragged_map = [[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0]]
    with pytest.raises(ValueError, match=r"instances\[0\]\[1\] is not a rectangular array"):
        hlbvh_cl.Scene([box], device=suite_device, instances=[(0, ragged_map)])
    with pytest.raises(ValueError, match="masks is not a rectangular array"):
        hlbvh_cl.Scene([box, box], device=suite_device, masks=[[1], [1, 2]])
    with pytest.raises(ValueError, match="morton_bits must be the int 30 or 63, got 30.0"):
        hlbvh_cl.Scene([box], device=suite_device, morton_bits=30.0)
    scene = hlbvh_cl.Scene([box], device=suite_device, instances=[(0, np.eye(3, 4))])
    with pytest.raises(ValueError, match="transforms is not a rectangular array"):
        scene.set_transforms([0], [ragged_map])
    with pytest.raises(ValueError, match="instance_ids is not a rectangular array"):
        scene.set_transforms([[0], [0, 1]], np.eye(3, 4)[None])
    moved = np.hstack([np.eye(3), [[1.0], [0.0], [0.0]]])
    scene.set_transforms(0, [moved])  # one id with a stack of one map
    np.testing.assert_array_equal(scene.transforms, moved[None])
    rays = np.zeros((2, 3)), np.ones((2, 3))
    with pytest.raises(ValueError, match="mask is not a rectangular array"):
        scene.intersect(*rays, mask=[[1, 2], [3]])
    with pytest.raises(ValueError, match="eye is not a rectangular array"):
        hlbvh_cl.Camera(eye=[0, [0, 1], 2], target=(0, 0, 0))
    with pytest.raises(TypeError, match=r"eye\[0\] must be a number, got a boolean True"):
        hlbvh_cl.Camera(eye=(True, False, True), target=(0, 0, 0))
    with pytest.raises(TypeError, match="fov_deg must be a number, got complex128"):
        hlbvh_cl.Camera(eye=(0, 0, 5), target=(0, 0, 0), fov_deg=np.complex128(45 + 30j))
    with pytest.raises(TypeError, match="intensity must be a number, got complex64"):
        hlbvh_cl.Light(intensity=np.complex64(1 + 2j))
    tiny = hlbvh_cl.Scene([Mesh(np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]]) * 1e-30,
                                [[0, 1, 2]])], device=suite_device)
    far = hlbvh_cl.Camera(eye=(0.0, 0.0, 1e10), target=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"camera eye \[0.0, 0.0, 10000000000.0\] is too far "
                                         r"from the origin for this scene: its frame is scaled "
                                         r"by 2\^"):
        hlbvh_cl.Renderer(tiny).render(far, 8, 6)


def test_a_mesh_no_instance_places_is_an_error(meshes):
    """With instances a Scene holds only what they place: a mesh none places
    would be missing without a word."""
    bunny = meshes["bunny_small"]
    quad = Mesh(QUAD, QUAD_FACES)
    with pytest.raises(ValueError, match=r"no instance places meshes 0, 2: .* add an instance "
                                         r"such as \(0, np.eye\(4\)\)"):
        Scene([bunny, quad, bunny], instances=[(1, np.eye(4))])
    scene = Scene([bunny, quad], instances=[(0, np.eye(4)), (1, np.eye(4))])
    assert len(scene.transforms) == 2


class _Tensor:
    """What as_array reads of a PyTorch tensor, for machines without torch:
    numpy() refuses a tensor that requires grad, and bfloat16 has no numpy
    type, as torch's does."""
    __module__ = "torch"

    class _Device:
        type = "cpu"

    device = _Device()

    def __init__(self, array, requires_grad=False, dtype="torch.float32"):
        self.array, self.requires_grad, self.dtype = array, requires_grad, dtype

    def detach(self):
        return _Tensor(self.array, False, self.dtype)

    def float(self):
        return _Tensor(self.array.astype(np.float32), self.requires_grad)

    def numpy(self):
        if self.requires_grad:
            raise RuntimeError("Can't call numpy() on Tensor that requires grad.")
        if self.dtype == "torch.bfloat16":
            raise TypeError("Got unsupported ScalarType BFloat16")
        return self.array

    def __array__(self, dtype=None, copy=None):
        return self.numpy()


def _tensor_kinds():
    """(name, make) pairs: make(array, requires_grad, bfloat16) gives a tensor."""
    kinds = [("stand-in", lambda a, grad, bf16: _Tensor(
        a, grad, "torch.bfloat16" if bf16 else "torch.float32"))]
    try:
        import torch
    except ImportError:
        return kinds

    def real(array, grad, bf16):
        tensor = torch.tensor(array, dtype=torch.bfloat16 if bf16 else torch.float32)
        return tensor.requires_grad_(grad)
    return kinds + [("torch", real)]


@pytest.mark.parametrize("kind, make", _tensor_kinds())
def test_tensors_that_require_grad_or_hold_bfloat16_are_read(kind, make, meshes):
    """Results carry no gradient, so a tensor that requires one is read as
    its values; bfloat16 widens to float32 exactly."""
    scene = Scene([Mesh(QUAD, QUAD_FACES)])
    origins = np.array([[0.25, 0.5, 1.0], [0.75, 0.25, 2.0]], np.float32)
    down = np.array([[0.0, 0.0, -1.0]] * 2, np.float32)
    expected = scene.intersect(origins, down).t
    np.testing.assert_array_equal(scene.intersect(make(origins, True, False), down).t, expected)
    np.testing.assert_array_equal(scene.intersect(make(origins, False, True), down).t, expected)
    vertices = make(np.asarray(QUAD, np.float32), True, False)
    np.testing.assert_array_equal(Mesh(vertices, QUAD_FACES).vertices, QUAD)


def test_the_dtype_message_lists_every_accepted_kind():
    scene = Scene([Mesh(QUAD, QUAD_FACES)])
    with pytest.raises(TypeError) as raised:
        scene.intersect(np.array([[1, 2, 3]], dtype="U1"), [[0, 0, -1]])
    assert "float32 (used as it is), or float64, float16, bfloat16 or integers" in \
        str(raised.value)
    # an object numpy cannot read is not called ragged
    with pytest.raises(ValueError, match="origins cannot be read as a numpy array"):
        scene.intersect(_Unreadable(), [[0, 0, -1]])


class _Unreadable:
    def __array__(self, dtype=None, copy=None):
        raise TypeError("no numpy view of this")
