"""TOML scene files: the project's scenes, transforms, the ground, and errors."""
import shutil
import tomllib

import numpy as np
import pytest
import trimesh

from hlbvh_cl import Camera
from hlbvh_cl.io.scenefile import SceneFileError, read, shape_mesh
import places

SCENES = places.SCENES
SCENE_FILES = sorted(SCENES.glob("*.toml"))
# Files whose meshes are drawn where they lie; an instanced file's camera
# looks over copies instead (tests/io/test_scenefile_instances.py).
FLAT_SCENE_FILES = [p for p in SCENE_FILES if "instance" not in tomllib.loads(p.read_text())]
KNIGHT = SCENES / "meshes" / "knight.ply"


@pytest.fixture(scope="module")
def loaded():
    """Each scene file loaded once for the module."""
    cache = {}

    def load(path):
        if path not in cache:
            cache[path] = read(path)
        return cache[path]
    return load


def test_the_scene_files_are_there():
    names = {p.name for p in SCENE_FILES}
    assert {"reference.toml", "bunny.toml", "armadillo.toml", "lucy.toml", "bunny_small.toml",
            "armadillo_small.toml", "lucy_small.toml"} <= names


@pytest.mark.parametrize("path", SCENE_FILES, ids=lambda p: p.name)
def test_scene_loads_with_the_expected_triangle_counts(loaded, path):
    scene = loaded(path)
    spec = tomllib.loads(path.read_text())
    assert len(scene.meshes) == len(spec["mesh"])
    for entry, table in zip(scene.meshes, spec["mesh"]):
        faces = (shape_mesh(table["shape"]).triangle_count if "shape" in table else
                 len(trimesh.load_mesh(path.parent / table["path"], process=False).faces))
        assert entry.mesh.triangle_count == faces * table.get("split", 1) ** 2
    expected = sum(e.mesh.triangle_count for e in scene.meshes) + (2 if "ground" in spec else 0)
    assert scene.triangle_count == expected
    assert sum(m.triangle_count for m, _ in scene.geometries()) == expected
    assert (scene.width, scene.height) == (spec["render"]["width"], spec["render"]["height"])


def test_reference_scene_size(loaded):
    # The figure stated in shared/meshes/PROVENANCE.md plus the 2-triangle ground.
    scene = loaded(SCENES / "reference.toml")
    assert [e.mesh.triangle_count for e in scene.meshes] == [69_451, 345_928, 2_499_250]
    assert scene.triangle_count == 2_914_631
    assert (scene.width, scene.height) == (2048, 1536)


def project(camera, width, height, points):
    """Pixel coordinates and depth of points, by the convention in scenefile's docstring."""
    eye = np.array(camera.eye)
    forward = np.array(camera.target) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, camera.up)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    relative = points - eye
    depth = relative @ forward
    half = np.tan(np.radians(camera.fov_deg) / 2)
    x = (relative @ right) / (depth * half * width / height)
    y = (relative @ up) / (depth * half)
    return (x + 1) / 2 * width, (1 - y) / 2 * height, depth


@pytest.mark.parametrize("path", FLAT_SCENE_FILES, ids=lambda p: p.name)
def test_camera_frames_the_meshes(loaded, path):
    scene = loaded(path)
    corners = []
    for entry in scene.meshes:
        if entry.emitter is not None:  # a light may hang out of view
            continue
        lo, hi = entry.mesh.bounds
        corners += [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    px, py, depth = project(scene.camera, scene.width, scene.height, np.array(corners))
    assert (depth > 0).all()
    # Every corner of every mesh's box is inside the picture ...
    assert px.min() >= 0 and px.max() <= scene.width
    assert py.min() >= 0 and py.max() <= scene.height
    # ... and together they span most of it in at least one direction.
    assert max(np.ptp(px) / scene.width, np.ptp(py) / scene.height) >= 0.75
    # The ground, if any, is below the meshes' lowest point or at it.
    if scene.ground is not None:
        lowest = min(e.mesh.bounds[0][1] for e in scene.meshes)
        assert scene.ground.y <= lowest + 1e-6 * max(1.0, abs(lowest))


# -- transforms and the ground, against independent numpy/trimesh maths -------

def write(folder, text, name="scene.toml"):
    path = folder / name
    path.write_text(text)
    return path


BASE = """
[render]
width = 64
height = 48

[camera]
eye = [0.0, 1.0, 5.0]
target = [0.0, 0.5, 0.0]
"""


@pytest.fixture(scope="module")
def knight():
    return trimesh.load_mesh(KNIGHT, process=False)


def test_transforms_in_order(tmp_path, knight):
    shutil.copy(KNIGHT, tmp_path / "knight.ply")
    path = write(tmp_path, BASE + """
[ground]
y = -0.25
size = 3.0
color = [0.1, 0.2, 0.3]

[[mesh]]
path = "knight.ply"
color = [1.0, 0.5, 0.0]
scale = [2.0, 1.0, 0.5]
rotate_deg = [30.0, -45.0, 60.0]
fit_height = 1.5
translate = [1.0, 2.0, 3.0]
place_on_ground = true
""")
    scene = read(path)
    entry = scene.meshes[0]
    assert entry.color == (1.0, 0.5, 0.0) and entry.path == tmp_path / "knight.ply"
    # Independent: trimesh's static-frame XYZ Euler matrix applied to the scaled points.
    rotation = trimesh.transformations.euler_matrix(*np.radians([30.0, -45.0, 60.0]), axes="sxyz")
    points = trimesh.transform_points(knight.vertices * [2.0, 1.0, 0.5], rotation)
    points *= 1.5 / np.ptp(points[:, 1])
    points += [1.0, 2.0, 3.0]
    points[:, 1] += -0.25 - points[:, 1].min()
    np.testing.assert_allclose(entry.mesh.vertices, points, atol=1e-5)
    np.testing.assert_array_equal(entry.mesh.faces, knight.faces)
    lo, hi = entry.mesh.bounds
    assert hi[1] - lo[1] == pytest.approx(1.5, rel=1e-5) and lo[1] == pytest.approx(-0.25)

    ground = scene.ground
    assert ground.mesh.triangle_count == 2 and ground.color == (0.1, 0.2, 0.3)
    v = ground.mesh.vertices[ground.mesh.faces].astype(np.float64)
    normals = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert (normals[:, 1] > 0).all() and not normals[:, [0, 2]].any()  # facing +y
    assert (ground.mesh.vertices[:, 1] == np.float32(-0.25)).all()
    g_lo, g_hi = ground.mesh.bounds
    np.testing.assert_allclose(g_hi[[0, 2]] - g_lo[[0, 2]], [3.0, 3.0], rtol=1e-6)
    np.testing.assert_allclose((g_lo + g_hi)[[0, 2]] / 2, ((lo + hi) / 2)[[0, 2]], atol=1e-5)
    assert 0.5 * np.linalg.norm(normals, axis=1).sum() == pytest.approx(9.0, rel=1e-6)


def test_split_then_auto_ground_and_defaults(tmp_path, knight):
    path = write(tmp_path, BASE + f"""
[ground]

[[mesh]]
path = "{KNIGHT}"
split = 3
translate = [0.0, -7.0, 0.0]
""")
    scene = read(path)
    mesh = scene.meshes[0].mesh
    assert mesh.triangle_count == 9 * len(knight.faces) and scene.meshes[0].split == 3
    np.testing.assert_allclose(mesh.bounds[0], knight.bounds[0] + [0, -7, 0], atol=1e-6)
    assert scene.ground.y == pytest.approx(knight.bounds[0][1] - 7.0)  # "auto" is the default
    assert scene.meshes[0].color == (0.8, 0.8, 0.8)
    assert scene.camera.up == (0.0, 1.0, 0.0) and scene.camera.fov_deg == 45.0
    assert np.linalg.norm(scene.light.direction) == pytest.approx(1.0)
    assert scene.triangle_count == 9 * len(knight.faces) + 2


def test_without_ground_place_on_ground_uses_zero(tmp_path):
    path = write(tmp_path, BASE + f"""
[light]
direction = [0.0, 3.0, 4.0]
intensity = 2.0
ambient = 0.0

[[mesh]]
path = "{KNIGHT}"
scale = 10.0
place_on_ground = true
""")
    scene = read(path)
    assert scene.ground is None
    assert scene.meshes[0].mesh.bounds[0][1] == pytest.approx(0.0, abs=1e-6)
    assert scene.light.direction == pytest.approx((0.0, 0.6, 0.8))
    assert (scene.light.intensity, scene.light.ambient) == (2.0, 0.0)


# -- errors: SceneFileError naming the file and the key -----------------------

MESH = f'\n[[mesh]]\npath = "{KNIGHT}"\n'


@pytest.mark.parametrize("text, key, words", [
    (BASE + MESH + "split = 0\n", "mesh[0].split", "expected an integer >= 1, got 0"),
    (BASE + MESH + MESH + "split = 2.5\n", "mesh[1].split", "an integer"),
    (BASE + '[[mesh]]\npath = "missing.ply"\n', "mesh[0].path", "not found"),
    (BASE + MESH + "colour = [1.0, 0.0, 0.0]\n", "mesh[0].colour", "unknown key"),
    (BASE + MESH + "[extra]\n", "extra", "unknown key"),
    (BASE.replace("target", "look_at") + MESH, "camera.look_at", "unknown key"),
    (BASE.replace("64", '"64"') + MESH, "render.width", "an integer"),
    (BASE.replace("eye = [0.0, 1.0, 5.0]", "eye = [0.0, 1.0]") + MESH, "camera.eye", "3 numbers"),
    (BASE.replace("eye = [0.0, 1.0, 5.0]", 'eye = [0.0, 1.0, "x"]') + MESH, "camera.eye[2]",
     "a number"),
    (BASE + "fov_deg = 180.0\n" + MESH, "camera.fov_deg", "< 180"),
    (BASE + "up = [0.0, -1.0, -10.0]\n" + MESH, "camera.up", "parallel"),
    (BASE.replace("[0.0, 0.5, 0.0]", "[0.0, 1.0, 5.0]") + MESH, "camera.target", "equals"),
    (BASE.replace("eye = [0.0, 1.0, 5.0]", "eye = [0.0, 1.0, 1e39]") + MESH, "camera.eye",
     "does not fit float32"),
    (BASE + MESH + "color = [1.5, 0.0, 0.0]\n", "mesh[0].color[0]", "<= 1"),
    (BASE + MESH + "scale = -1.0\n", "mesh[0].scale", "> 0"),
    (BASE + MESH + "scale = [1.0, 0.0, 1.0]\n", "mesh[0].scale[1]", "> 0"),
    (BASE + MESH + "fit_height = 0\n", "mesh[0].fit_height", "> 0"),
    (BASE + MESH + "scale = [1.0, 1e-20, 1.0]\nfit_height = 1.0\n", "mesh[0].fit_height",
     "flat in y"),
    (BASE + MESH + "rotate_deg = 90.0\n", "mesh[0].rotate_deg", "3 numbers"),
    (BASE + MESH + 'place_on_ground = "yes"\n', "mesh[0].place_on_ground", "true or false"),
    (BASE + MESH + "path2 = 1\n", "mesh[0].path2", "unknown key"),
    (BASE + '[[mesh]]\ncolor = [1.0, 1.0, 1.0]\n', "mesh[0].path", "missing"),
    (BASE + '[[mesh]]\npath = 3\n', "mesh[0].path", "file name"),
    (BASE + '[ground]\ny = "low"\n' + MESH, "ground.y", '"auto"'),
    (BASE + '[ground]\nsize = 0.0\n' + MESH, "ground.size", "> 0"),
    (BASE + '[ground]\nsize = 1e300\n' + MESH, "ground", "its size 1e+300 at y"),
    (BASE + '[ground]\ny = 1e39\n' + MESH, "ground", "at y 1e+39 gives an invalid square"),
    (BASE + MESH + "translate = [0.0, 1e39, 0.0]\n", "mesh[0]", "fit_height and translate give"),
    (BASE + '[ground]\nheight = 1.0\n' + MESH, "ground.height", "unknown key"),
    (BASE + '[light]\ndirection = [0.0, 0.0, 0.0]\n' + MESH, "light.direction", "zero"),
    (BASE + '[light]\nambient = 1.5\n' + MESH, "light.ambient", "<= 1"),
    (BASE + '[light]\nintensity = -1.0\n' + MESH, "light.intensity", ">= 0"),
    (BASE + '[light]\nintensity = 1e39\n' + MESH, "light.intensity", "<= 1e+20, got 1e+39"),
    # Light's own bound (film.BRIGHTEST), named with the file
    (BASE + '[light]\nintensity = 1e30\n' + MESH, "light.intensity", "<= 1e+20, got 1e+30"),
    (BASE + MESH + 'material = { type = ["diffuse"] }\n', "mesh[0].material",
     "type ['diffuse'] is not one of ('diffuse', "),
    (BASE + '[light]\nintensity = 1' + '0' * 400 + '\n' + MESH, "light.intensity",
     "expected a finite number, got an integer of 1329 bits, beyond float's range"),
    (BASE, "mesh", "missing"),
    ("mesh = []\n" + BASE, "mesh", "[[mesh]]"),
    ("mesh = 5\n" + BASE, "mesh", "[[mesh]]"),
    ("[camera]\neye = [0.0, 0.0, 1.0]\ntarget = [0.0, 0.0, 0.0]\n" + MESH, "render", "missing"),
    (BASE.replace("height = 48\n", "") + MESH, "render.height", "missing"),
    (BASE.replace("width = 64", "width = 0") + MESH, "render.width", ">= 1"),
    ("render = 3\n" + BASE.replace("[render]\nwidth = 64\nheight = 48\n", "") + MESH, "render",
     "a table"),
    (BASE + MESH + "split = true\n", "mesh[0].split", "a boolean"),
])
def test_errors_name_the_file_and_the_key(tmp_path, text, key, words):
    path = write(tmp_path, text, name="broken_scene.toml")
    with pytest.raises(SceneFileError) as caught:
        read(path)
    message = str(caught.value)
    assert "broken_scene.toml" in message
    assert f": {key}: " in message
    assert words in message


def test_a_render_size_past_the_limit_loads_where_the_caller_replaces_it(tmp_path):
    """render.width past the renderer's 16384 is refused, naming the key,
    unless the caller renders at its own width (the CLI's --width); the
    height it does not replace is still checked."""
    path = write(tmp_path, BASE.replace("width = 64", "width = 20000") + MESH)
    with pytest.raises(SceneFileError, match=r"render\.width: .*<= 16384, got 20000"):
        read(path)
    with pytest.raises(SceneFileError, match=r"render\.width: "):
        read(path, replaced={"height"})
    assert read(path, replaced={"width"}).width == 20000
    path = write(tmp_path, BASE.replace("width = 64", "width = 4294967296") + MESH)
    with pytest.raises(SceneFileError, match=r"render\.width: .*<= 4294967295, got 4294967296"):
        read(path, replaced={"width"})
    path = write(tmp_path, BASE.replace("height = 48", "height = 0") + MESH)
    with pytest.raises(SceneFileError, match=r"render\.height: .*>= 1"):
        read(path, replaced={"height"})


def test_huge_but_finite_directions_are_normalised(tmp_path):
    """The length of (0, 1e300, 0) overflows float64: the direction does not."""
    text = BASE + "up = [0.0, 1e300, 0.0]\n[light]\ndirection = [0.0, 0.0, -1e300]\n" + MESH
    scene = read(write(tmp_path, text))
    assert scene.light.direction == (0.0, 0.0, -1.0)
    np.testing.assert_allclose(scene.camera.basis()[2], Camera(**{
        "eye": scene.camera.eye, "target": scene.camera.target}).basis()[2])


def test_toml_syntax_error_gives_the_line(tmp_path):
    text = BASE + "[[mesh]]\npath = meshes/knight.ply\n"  # the path is not quoted
    line = text.splitlines().index("path = meshes/knight.ply") + 1
    path = write(tmp_path, text, name="syntax.toml")
    with pytest.raises(SceneFileError, match=rf"syntax\.toml: TOML syntax error: .*line {line}\b"):
        read(path)


def test_unreadable_mesh_file(tmp_path):
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    path = write(tmp_path, BASE + '[[mesh]]\npath = "bad.ply"\n', name="bad_mesh.toml")
    with pytest.raises(SceneFileError, match=r"bad_mesh\.toml: mesh\[0\]\.path: .*bad\.ply"):
        read(path)


def test_missing_scene_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        read(tmp_path / "nowhere.toml")


def test_scene_file_error_is_a_value_error():
    assert issubclass(SceneFileError, ValueError)


# -- the path integrator's materials and emitters -----------------------------

LOOK = BASE + """
[ground]
material = { type = "diffuse", reflectance = 0.4 }

[[mesh]]
path = "knight.ply"
color = [0.2, 0.4, 0.6]

[[mesh]]
shape = "sphere"
material = { type = "dielectric", int_ior = 1.33 }
translate = [1.0, 1.0, 0.0]

[[mesh]]
shape = "rectangle"
emitter = { type = "area", radiance = [4.0, 4.0, 4.0] }
rotate_deg = [90.0, 0.0, 0.0]
translate = [0.0, 3.0, 0.0]

[[emitter]]
type = "point"
position = [1.0, 2.0, 3.0]
intensity = 5.0
"""


def test_materials_emitters_and_shapes_reach_the_renderer(tmp_path):
    """A [[mesh]] table's material and area emitter, Mitsuba's shapes, the
    ground's material and [[emitter]] tables become Renderer.materials and
    emitters; meshes without a material keep a two-sided diffuse of their
    colour; a rectangle turned by 90 degrees about x faces -y."""
    shutil.copy(KNIGHT, tmp_path / "knight.ply")
    scene = read(write(tmp_path, LOOK))
    materials = scene.materials()
    assert materials[0] == {"type": "twosided", "bsdf": {"type": "diffuse",
                                                         "reflectance": [0.2, 0.4, 0.6]}}
    assert materials[1] == {"type": "dielectric", "int_ior": 1.33}
    assert materials[3] == {"type": "diffuse", "reflectance": 0.4}  # the ground, last
    assert scene.all_emitters() == [{"type": "area", "radiance": [4.0, 4.0, 4.0], "mesh": 2},
                                    {"type": "point", "position": [1.0, 2.0, 3.0],
                                     "intensity": 5.0}]
    sphere, rectangle = scene.meshes[1].mesh, scene.meshes[2].mesh
    assert np.allclose(np.linalg.norm(sphere.vertices - [1.0, 1.0, 0.0], axis=1), 1.0, atol=1e-6)
    v = rectangle.vertices.astype(np.float64)
    normal = np.cross(v[rectangle.faces[:, 1]] - v[rectangle.faces[:, 0]],
                      v[rectangle.faces[:, 2]] - v[rectangle.faces[:, 0]])
    assert np.allclose(normal / np.linalg.norm(normal, axis=1, keepdims=True), [0, -1, 0],
                       atol=1e-6)
    assert np.allclose(v[:, 1], 3.0)


@pytest.mark.parametrize("change, words", [
    (("material = { type = \"dielectric\", int_ior = 1.33 }",
      "material = { type = \"glass\" }"), "mesh[1].material: type 'glass' is not one of"),
    (("radiance = [4.0, 4.0, 4.0]", "radiance = -1.0"),
     "mesh[2].emitter['radiance'] must be a finite number >= 0"),
    (("radiance = [4.0, 4.0, 4.0]", "radiance = 1.0, mesh = 1"),
     "mesh[2].emitter.mesh: a [[mesh]]'s emitter lights that mesh: give no mesh key"),
    (("type = \"point\"", "type = \"area\""), "emitter[0]: an area emitter belongs in its"),
    (("shape = \"sphere\"", "shape = \"cylinder\""), "mesh[1].shape: expected one of"),
    (("shape = \"sphere\"", "shape = \"sphere\"\npath = \"knight.ply\""),
     "mesh[1].path: a mesh file (path) or one of Mitsuba's shapes (shape = 'rectangle' | "
     "'cube' | 'sphere'), not both"),
    (("position = [1.0, 2.0, 3.0]", "where = [1.0, 2.0, 3.0]"),
     "emitter[0]: point takes ('position', 'intensity'), not ['where']"),
])
def test_a_bad_material_or_emitter_names_its_table(tmp_path, change, words):
    shutil.copy(KNIGHT, tmp_path / "knight.ply")
    old, new = change
    assert old in LOOK
    with pytest.raises(SceneFileError) as error:
        read(write(tmp_path, LOOK.replace(old, new, 1)))
    assert str(error.value).startswith(str(tmp_path / "scene.toml"))
    assert words in str(error.value)


SKY = """
[[emitter]]
type = "envmap"
filename = "maps/sky.exr"
scale = 2.0
to_world = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]
"""


def test_an_envmap_table_finds_its_file_beside_the_scene_and_renders(tmp_path, suite_device):
    """An [[emitter]] envmap's filename is relative to the TOML file, as
    Mitsuba resolves an XML file's; the loaded scene renders lit by it: a
    map of one value c gives c where the camera sees the sky."""
    from hlbvh_cl.io.exr import write_exr
    from hlbvh_cl.io.scenefile import load
    (tmp_path / "maps").mkdir()
    write_exr(tmp_path / "maps" / "sky.exr", np.full((4, 8, 3), 0.25, np.float32))
    text = BASE + SKY + '\n[[mesh]]\nshape = "sphere"\nscale = 0.3\n'
    scene = read(write(tmp_path, text))
    assert scene.all_emitters() == [{
        "type": "envmap", "filename": str(tmp_path / "maps" / "sky.exr"), "scale": 2.0,
        "to_world": [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]}]
    loaded = load(write(tmp_path, text), suite_device.id)
    image = loaded.renderer().render(loaded.camera, 16, 12, shading="path", spp=2, hdr=True)
    assert np.allclose(image[0], 0.5) and np.allclose(image[:, 0], 0.5)


@pytest.mark.parametrize("change, words", [
    ("maps/sky.exr", "emitter[0]: cannot read the environment map"),
    ("scale = 2.0", "emitter[0]['scale'] must be a finite number >= 0"),
    ("[-1.0, 0.0, 0.0]]", "emitter[0]['to_world'] must be a rotation"),
    ('"1.0"', "emitter[0]['to_world'] must be a 3 x 3 or 4 x 4 matrix of numbers"),
    ("0 0 0 1", "emitter[0]['to_world']'s last row must be 0 0 0 1 (an affine map), got "
                "[1.0, 1.0, 1.0, 1.0]"),
    ("[[emitter]]", "emitter[1]: a second environment (envmap) besides emitter[0] (constant)"),
])
def test_a_bad_envmap_table_is_named(tmp_path, change, words):
    from hlbvh_cl.io.exr import write_exr
    write_exr(tmp_path / "sky.exr", np.ones((4, 8, 3), np.float32))
    text = SKY.replace("maps/", "")
    text = {"maps/sky.exr": SKY.replace("maps/sky.exr", "missing.exr"),
            "scale = 2.0": text.replace("scale = 2.0", "scale = -2.0"),
            "[-1.0, 0.0, 0.0]]": text.replace("[-1.0, 0.0, 0.0]]", "[-2.0, 0.0, 0.0]]"),
            '"1.0"': text.replace("[0.0, 1.0, 0.0]", '[0.0, "1.0", 0.0]'),
            "0 0 0 1": text.replace("[[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]",
                                    "[[1.0, 0.0, 0.0, 5.0], [0.0, 1.0, 0.0, 0.0], "
                                    "[0.0, 0.0, 1.0, 0.0], [1.0, 1.0, 1.0, 1.0]]"),
            "[[emitter]]": '[[emitter]]\ntype = "constant"\nradiance = 1.0\n' + text}[change]
    with pytest.raises(SceneFileError) as error:
        read(write(tmp_path, BASE + text + '\n[[mesh]]\nshape = "sphere"\n'))
    assert str(error.value).startswith(str(tmp_path / "scene.toml"))
    assert words in str(error.value)
