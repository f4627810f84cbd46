"""Scene files with [[instance]] tables: copies, their transforms, the ground,
errors, and an instanced scene hit like its copies baked into separate meshes."""

import numpy as np
import pytest
import trimesh

from hlbvh_cl.io.scenefile import MAX_INSTANCES, SceneFileError, load, read
import places

SCENES = places.SCENES
KNIGHT = SCENES / "meshes" / "knight.ply"
BUNNY_SMALL = SCENES / "meshes" / "bunny_small.ply"

BASE = """
[render]
width = 64
height = 48

[camera]
eye = [0.0, 3.0, 9.0]
target = [0.0, 0.5, 0.0]
"""
KNIGHT_MESH = f'\n[[mesh]]\npath = "{KNIGHT}"\ncolor = [0.9, 0.1, 0.1]\n'
BUNNY_MESH = f'\n[[mesh]]\npath = "{BUNNY_SMALL}"\nfit_height = 1.0\nplace_on_ground = true\n'


def write(folder, text, name="scene.toml"):
    path = folder / name
    path.write_text(text)
    return path


def euler(degrees):
    """Rotation about x, then y, then z (fixed axes), from trimesh."""
    return trimesh.transformations.euler_matrix(*np.radians(degrees), axes="sxyz")[:3, :3]


def yaw(degrees):
    return trimesh.transformations.rotation_matrix(np.radians(degrees), [0, 1, 0])[:3, :3]


def world(transform, points):
    return points @ transform[:, :3].T + transform[:, 3]


def test_grid_positions_and_transforms(tmp_path):
    path = write(tmp_path, BASE + KNIGHT_MESH + """
[[instance]]
mesh = 0
scale = [2.0, 1.0, 0.5]
rotate_deg = [30.0, -45.0, 60.0]
grid = { count = [4, 3], spacing = [2.0, 5.0], origin = [1.0, 2.0, -3.0] }
""")
    scene = read(path)
    (entry,) = scene.instances
    assert entry.mesh == 0 and entry.transforms.shape == (12, 3, 4)
    linear = euler([30.0, -45.0, 60.0]) @ np.diag([2.0, 1.0, 0.5])
    np.testing.assert_allclose(entry.transforms[:, :, :3], np.broadcast_to(linear, (12, 3, 3)),
                               atol=1e-12)
    # i (along x) varies fastest
    expected = [[1.0 + 2.0 * i, 2.0, -3.0 + 5.0 * j] for j in range(3) for i in range(4)]
    np.testing.assert_allclose(entry.transforms[:, :, 3], expected, atol=1e-12)
    assert scene.ground is None
    placements = scene.placements()
    assert len(placements) == 12 and all(mesh == 0 for mesh, _ in placements)
    assert scene.drawn_triangle_count == 12 * 1000 and scene.triangle_count == 1000
    assert scene.geometries()[0][1] == (0.9, 0.1, 0.1)


def test_random_yaw_and_jitter_follow_the_documented_draws(tmp_path):
    path = write(tmp_path, BASE + KNIGHT_MESH + """
[[instance]]
mesh = 0
rotate_deg = [-90.0, 0.0, 0.0]
grid = { count = [5, 4], spacing = [3.0, 2.0], jitter = 0.25 }
random_yaw_deg = 40.0
seed = 7
""")
    (entry,) = read(path).instances
    rng = np.random.default_rng(7)
    angles = rng.uniform(-40.0, 40.0, 20)
    offsets = rng.uniform(-1.0, 1.0, (20, 2)) * [0.75, 0.5]
    assert np.abs(angles).max() <= 40.0 and np.ptp(angles) > 20.0
    for k in range(20):
        i, j = k % 5, k // 5
        np.testing.assert_allclose(entry.transforms[k, :, :3],
                                   yaw(angles[k]) @ euler([-90.0, 0.0, 0.0]), atol=1e-12)
        np.testing.assert_allclose(entry.transforms[k, :, 3],
                                   [3.0 * i + offsets[k, 0], 0.0, 2.0 * j + offsets[k, 1]],
                                   atol=1e-12)


def test_seed_defaults_to_the_table_index(tmp_path):
    table = "\n[[instance]]\nmesh = 0\ntranslate = [[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]]\n" \
            "random_yaw_deg = 180.0\n"
    scene = read(write(tmp_path, BASE + KNIGHT_MESH + table + table + table + "seed = 0\n"))
    first, second, third = (entry.transforms for entry in scene.instances)
    assert not np.allclose(first, second)
    np.testing.assert_array_equal(first, third)
    np.testing.assert_array_equal(first, read(write(tmp_path, BASE + KNIGHT_MESH + table,
                                                    name="again.toml")).instances[0].transforms)


def test_translate_one_or_many_and_the_default(tmp_path):
    scene = read(write(tmp_path, BASE + KNIGHT_MESH + """
[[instance]]
mesh = 0
translate = [[1.0, 2.0, 3.0], [-1.0, 0.0, 0.5], [0.0, 0.0, 9.0]]

[[instance]]
mesh = 0
translate = [4.0, 5.0, 6.0]
scale = 3.0

[[instance]]
mesh = 0
"""))
    many, one, default = scene.instances
    np.testing.assert_array_equal(many.transforms[:, :, 3],
                                  [[1.0, 2.0, 3.0], [-1.0, 0.0, 0.5], [0.0, 0.0, 9.0]])
    np.testing.assert_array_equal(many.transforms[:, :, :3], np.broadcast_to(np.eye(3), (3, 3, 3)))
    np.testing.assert_allclose(one.transforms, [np.hstack([3.0 * np.eye(3), [[4.0], [5.0], [6.0]]])],
                               atol=1e-12)
    np.testing.assert_array_equal(default.transforms, [np.eye(3, 4)])
    assert len(scene.placements()) == 5


def test_place_on_ground_and_the_auto_ground(tmp_path):
    knight = trimesh.load_mesh(KNIGHT, process=False)
    scene = read(write(tmp_path, BASE + KNIGHT_MESH + """
[ground]
color = [0.1, 0.2, 0.3]

[[instance]]
mesh = 0
rotate_deg = [20.0, 0.0, 10.0]
translate = [[0.0, 5.0, 0.0], [3.0, -2.0, 1.0]]
random_yaw_deg = 180.0
place_on_ground = true

[[instance]]
mesh = 0
translate = [[-4.0, 0.7, 0.0], [2.0, -0.3, -6.0]]
"""))
    placed, free = scene.instances
    # "auto": the lowest point of all copies, here the second free one's ...
    lowest = knight.vertices[:, 1].min() - 0.3
    assert scene.ground.y == pytest.approx(lowest, abs=1e-6)
    # ... and place_on_ground stands copies on 0 when the ground's y is "auto".
    for transform in placed.transforms:
        assert world(transform, knight.vertices)[:, 1].min() == pytest.approx(0.0, abs=1e-6)
    # Without turns the copies' boxes are exact: the ground is centred on them.
    corners = np.concatenate([world(t, knight.vertices) for t in free.transforms])
    assert scene.ground.mesh.triangle_count == 2 and scene.ground.color == (0.1, 0.2, 0.3)
    lo, hi = scene.ground.mesh.bounds
    assert lo[0] <= corners[:, 0].min() and hi[2] >= corners[:, 2].max()
    placements = scene.placements()
    assert len(placements) == 5 and placements[-1][0] == 1
    np.testing.assert_array_equal(placements[-1][1], np.eye(3, 4))
    assert scene.drawn_triangle_count == 4 * 1000 + 2


def test_ground_is_centred_on_the_copies_boxes(tmp_path):
    knight = trimesh.load_mesh(KNIGHT, process=False)
    scene = read(write(tmp_path, BASE + KNIGHT_MESH + """
[ground]
y = -1.0

[[instance]]
mesh = 0
scale = 2.0
translate = [[10.0, 0.0, 0.0], [14.0, 0.0, -8.0]]
"""))
    points = np.concatenate([world(t, knight.vertices) for t in scene.instances[0].transforms])
    lo, hi = scene.ground.mesh.bounds
    np.testing.assert_allclose((lo + hi)[[0, 2]] / 2,
                               (points.min(axis=0) + points.max(axis=0))[[0, 2]] / 2, atol=1e-5)
    extent = np.ptp(points[:, [0, 2]], axis=0).max()
    assert hi[0] - lo[0] == pytest.approx(4 * extent, rel=1e-6)
    assert scene.ground.y == -1.0


def test_a_file_without_instances_has_no_placements():
    scene = read(SCENES / "bunny_small.toml")
    assert scene.instances == [] and scene.placements() == []
    assert scene.drawn_triangle_count == scene.triangle_count


# -- the field scene ----------------------------------------------------------

@pytest.fixture(scope="module")
def field():
    return read(SCENES / "field.toml")


def test_field_scene_size(field):
    assert [entry.mesh.triangle_count for entry in field.meshes] == [69_451, 99_970, 86_482]
    assert [len(entry.transforms) for entry in field.instances] == [3500, 3500, 3500]
    assert len(field.placements()) == 10_501
    assert field.triangle_count == 255_905
    assert field.drawn_triangle_count == 895_660_502


def project(camera, width, height, points):
    """Pixel coordinates and depth, by the convention in scenefile's docstring."""
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


def test_field_camera_looks_over_the_field_to_the_horizon(field):
    camera, width, height = field.camera, field.width, field.height
    positions = np.concatenate([entry.transforms[:, :, 3] for entry in field.instances])
    px, py, depth = project(camera, width, height, positions)
    seen = (depth > 0) & (px >= 0) & (px <= width) & (py >= 0) & (py <= height)
    assert seen.mean() > 0.4
    # The horizon (a point far along -z at the eye's height) is in the upper
    # half, and the far rows of the field reach within a few pixels of it.
    eye = np.array(camera.eye)
    _, horizon, _ = project(camera, width, height, eye + [[0.0, 0.0, -1e7]])
    assert 0 < horizon[0] < height / 2
    assert 0 < py[seen].min() - horizon[0] < 0.03 * height
    # The ground is under the eye and reaches far beyond the field.
    lo, hi = field.ground.mesh.bounds
    assert lo[0] < eye[0] < hi[0] and lo[2] < eye[2] < hi[2] and field.ground.y < eye[1]
    assert lo[2] < positions[:, 2].min() - 500


# -- errors: SceneFileError naming the file and the key -----------------------

def instance(text):
    return BASE + KNIGHT_MESH + "\n[[instance]]\n" + text


@pytest.mark.parametrize("text, key, words", [
    (instance("mesh = 1\n"), "instance[0].mesh", "no [[mesh]] table 1: the file has 1"),
    (instance("mesh = -1\n"), "instance[0].mesh", "no [[mesh]] table -1"),
    (instance('mesh = "knight"\n'), "instance[0].mesh", "index of a [[mesh]] table"),
    (instance("mesh = true\n"), "instance[0].mesh", "a boolean"),
    (instance("translate = [1.0, 2.0, 3.0]\n"), "instance[0].mesh", "missing"),
    (instance("mesh = 0\n") + "[[instance]]\nmesh = 0\ncolour = [1.0, 0.0, 0.0]\n",
     "instance[1].colour", "unknown key"),
    (instance("mesh = 0\ngrid = { count = [2, 2] }\n"), "instance[0].grid.spacing", "missing"),
    (instance("mesh = 0\ngrid = { spacing = [1.0, 1.0] }\n"), "instance[0].grid.count", "missing"),
    (instance("mesh = 0\ngrid = { count = [2, 0], spacing = [1.0, 1.0] }\n"),
     "instance[0].grid.count[1]", "expected an integer >= 1, got 0"),
    (instance("mesh = 0\ngrid = { count = [2.5, 2], spacing = [1.0, 1.0] }\n"),
     "instance[0].grid.count[0]", "an integer"),
    (instance("mesh = 0\ngrid = { count = [2], spacing = [1.0, 1.0] }\n"),
     "instance[0].grid.count", "2 values [x, z]"),
    (instance("mesh = 0\ngrid = { count = [2, 2], spacing = [1.0, 0.0] }\n"),
     "instance[0].grid.spacing[1]", "> 0"),
    (instance("mesh = 0\ngrid = { count = [2, 2], spacing = [1.0, 1.0], jitter = 0.6 }\n"),
     "instance[0].grid.jitter", "<= 0.5"),
    (instance("mesh = 0\ngrid = { count = [2, 2], spacing = [1.0, 1.0], origin = [0, 0] }\n"),
     "instance[0].grid.origin", "3 numbers"),
    (instance("mesh = 0\ngrid = { count = [2, 2], spacing = [1.0, 1.0], size = 3 }\n"),
     "instance[0].grid.size", "unknown key"),
    (instance("mesh = 0\ngrid = [2, 2]\n"), "instance[0].grid", "a table"),
    (instance("mesh = 0\ngrid = { count = [5000, 5000], spacing = [1.0, 1.0] }\n"),
     "instance[0].grid.count", f"more than {MAX_INSTANCES:,}"),
    (instance("mesh = 0\ntranslate = [0.0, 0.0, 0.0]\n"
              "grid = { count = [2, 2], spacing = [1.0, 1.0] }\n"), "instance[0].grid",
     "either translate or grid"),
    (instance("mesh = 0\ntranslate = []\n"), "instance[0].translate", "a list of them"),
    (instance("mesh = 0\ntranslate = [[1.0, 2.0, 3.0], [1.0, 2.0]]\n"),
     "instance[0].translate[1]", "3 numbers"),
    (instance("mesh = 0\ntranslate = [[1.0, 2.0, 3.0], 4.0]\n"), "instance[0].translate[1]",
     "3 numbers"),
    (instance("mesh = 0\nrandom_yaw_deg = 200.0\n"), "instance[0].random_yaw_deg", "<= 180"),
    (instance("mesh = 0\nseed = -1\n"), "instance[0].seed", ">= 0"),
    (instance('mesh = 0\nmaterial = { type = "velvet" }\n'), "instance[0].material", "velvet"),
    (instance("mesh = 0\nscale = 0.0\n"), "instance[0].scale", "> 0"),
    (instance("mesh = 0\nscale = 5e38\n"), "instance[0]", "scale and positions put copies at"),
    (instance("mesh = 0\ntranslate = [0.0, 1e39, 0.0]\n"), "instance[0]", "beyond float32"),
    (instance("mesh = 0\nscale = 1e-300\n"), "instance[0]", "copy 0's transform is singular"),
    (instance("mesh = 0\nscale = 1e-12\ntranslate = [3.0, 0.0, 0.0]\n"), "instance[0]",
     "copy 0's transform makes its mesh too small for its place in the world"),
    (instance("mesh = 0\nrotate_deg = 90.0\n"), "instance[0].rotate_deg", "3 numbers"),
    (instance('mesh = 0\nplace_on_ground = "yes"\n'), "instance[0].place_on_ground",
     "true or false"),
    ("instance = 5\n" + BASE + KNIGHT_MESH, "instance", "[[instance]]"),
    ("instance = []\n" + BASE + KNIGHT_MESH, "instance", "[[instance]]"),
])
def test_errors_name_the_file_and_the_key(tmp_path, text, key, words):
    path = write(tmp_path, text, name="field.toml")
    with pytest.raises(SceneFileError) as caught:
        read(path)
    message = str(caught.value)
    assert "field.toml" in message
    assert f": {key}: " in message
    assert words in message


def test_a_map_only_the_build_refuses_names_its_table(tmp_path, suite_device):
    """A scale of 1e-300 on one axis passes read()'s checks (the map is not
    singular), but its inverse overflows float32 in the scene's frames, which
    only the Scene finds: its error still names the file and the table."""
    text = instance("mesh = 0\ntranslate = [[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]]\n")
    text += "[[instance]]\nmesh = 0\nscale = [1e-300, 1.0, 1.0]\n"
    path = write(tmp_path, text, name="field.toml")
    assert len(read(path).placements()) == 3
    with pytest.raises(SceneFileError, match=r"field\.toml: instance\[1\]: instance 2's transform "
                                             "does not fit float32"):
        load(path, device=suite_device)


def test_too_many_copies_over_several_tables(tmp_path, monkeypatch):
    monkeypatch.setattr("hlbvh_cl.io.scenefile.MAX_INSTANCES", 10)
    text = instance("mesh = 0\ngrid = { count = [3, 3], spacing = [1.0, 1.0] }\n")
    path = write(tmp_path, text + "[[instance]]\nmesh = 0\ntranslate = [[0, 0, 0], [1, 0, 0]]\n")
    with pytest.raises(SceneFileError, match=r": instance\[1\]\.translate: more than 10 copies"):
        read(path)
    assert len(read(write(tmp_path, text + "[[instance]]\nmesh = 0\n", name="ok.toml"))
               .placements()) == 10


# -- an instanced file against its copies baked into a flat file --------------

TWIN_VIEW = """
[render]
width = 96
height = 72

[camera]
eye = [0.3, 2.4, 4.5]
target = [0.0, 0.5, 0.0]
"""
INSTANCED = TWIN_VIEW + f"""
[ground]
size = 200.0
color = [0.5, 0.5, 0.5]

[[mesh]]
path = "{KNIGHT}"
color = [0.9, 0.2, 0.2]
fit_height = 1.2

[[mesh]]
path = "{BUNNY_SMALL}"
color = [0.2, 0.4, 0.9]
fit_height = 1.0

[[instance]]
mesh = 0
scale = [1.3, 0.9, 1.0]
rotate_deg = [10.0, 0.0, -5.0]
grid = {{ count = [3, 2], spacing = [1.6, 1.8], origin = [-2.5, 0.0, -1.5], jitter = 0.2 }}
random_yaw_deg = 90.0
place_on_ground = true

[[instance]]
mesh = 1
translate = [[2.6, 0.0, 0.4], [-0.4, 0.3, 1.6]]
random_yaw_deg = 180.0
"""


@pytest.fixture(scope="module")
def twins(tmp_path_factory):
    """The instanced file and the flat one, loaded, with each copy's (mesh
    index, world vertices, faces) in the order of the instanced Scene."""
    from hlbvh_cl.io.scenefile import load
    folder = tmp_path_factory.mktemp("twins")
    description = read(write(folder, INSTANCED, name="instanced.toml"))
    colors = [color for _, color in description.geometries()]
    copies, flat = [], TWIN_VIEW + f"""
[ground]
y = {description.ground.y!r}
size = 200.0
color = [0.5, 0.5, 0.5]
"""
    for k, (mesh_index, transform) in enumerate(description.placements()[:-1]):
        mesh = description.meshes[mesh_index].mesh
        vertices = world(transform, mesh.vertices.astype(np.float64))
        copies.append((mesh_index, vertices, mesh.faces))
        trimesh.Trimesh(vertices, mesh.faces, process=False).export(folder / f"copy{k}.ply")
        flat += f'\n[[mesh]]\npath = "copy{k}.ply"\ncolor = {list(colors[mesh_index])}\n'
    return load(folder / "instanced.toml"), load(write(folder, flat, name="flat.toml")), copies


def test_instanced_file_hits_like_its_flat_twin(twins):
    instanced, flat, copies = twins
    assert len(instanced.scene.meshes) == 3 and len(instanced.colors) == 3
    assert len(flat.scene.meshes) == len(copies) + 1 == 9
    rng = np.random.default_rng(5)
    eye = np.array([0.5, 5.0, 9.0])
    targets, normals, faces, owners = [], [], [], []
    for k, (_, vertices, mesh_faces) in enumerate(copies):
        picked = rng.choice(len(mesh_faces), 200, replace=False)
        corners = vertices[mesh_faces[picked]]
        targets.append(corners.mean(axis=1))  # centroids: far from edges
        normals.append(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]))
        faces.append(picked)
        owners.append(np.full(200, k))
    targets, normals, faces, owners = map(np.concatenate, (targets, normals, faces, owners))
    directions = targets - eye
    origins = np.broadcast_to(eye, directions.shape)
    expected = flat.scene.intersect(origins, directions)
    # Only rays whose first hit is the triangle aimed at (none grazes an edge)
    # and that meet it at more than about 3 degrees: at grazing incidence the
    # float32 rounding of the baked vertices moves t by far more than 1e-5.
    cosine = np.abs((normals * directions).sum(axis=1)) / (
        np.linalg.norm(normals, axis=1) * np.linalg.norm(directions, axis=1))
    kept = (expected.geom_id == owners) & (expected.prim_id == faces) & (cosine > 0.05)
    assert np.bincount(owners[kept], minlength=len(copies)).min() >= 20
    got = instanced.scene.intersect(origins[kept], directions[kept])
    mesh_of = np.array([mesh_index for mesh_index, _, _ in copies])
    np.testing.assert_array_equal(got.geom_id, mesh_of[owners[kept]])
    np.testing.assert_array_equal(got.instance_id, owners[kept])
    np.testing.assert_array_equal(got.prim_id, faces[kept])
    np.testing.assert_allclose(got.t, expected.t[kept], rtol=1e-5)
    np.testing.assert_allclose(got.normal, expected.normal[kept], atol=1e-4)
    # u, v as the points they name on the triangle: on small triangles the
    # float32 rounding of the hit moves them by more than a fixed tolerance.
    first_face = np.cumsum([0] + [len(mesh_faces) for _, _, mesh_faces in copies])
    corners = np.concatenate([vertices[mesh_faces] for _, vertices, mesh_faces in copies])
    corners = corners[(first_face[owners] + faces)[kept]]

    def on_triangle(u, v):
        u, v = u[:, None].astype(np.float64), v[:, None].astype(np.float64)
        return (1 - u - v) * corners[:, 0] + u * corners[:, 1] + v * corners[:, 2]
    np.testing.assert_allclose(on_triangle(got.u, got.v),
                               on_triangle(expected.u[kept], expected.v[kept]), atol=1e-5)


def test_instanced_file_ground_is_its_last_instance(twins):
    instanced, _, copies = twins
    lo, hi = instanced.scene.meshes[-1].bounds
    corner = lo + 0.05 * (hi - lo)  # outside the copies, which sit in the middle
    hits = instanced.scene.intersect(np.array([[corner[0], 10.0, corner[2]]]),
                                     np.array([[0.0, -1.0, 0.0]]))
    assert hits.geom_id[0] == 2 and hits.instance_id[0] == len(copies)
    assert hits.t[0] == pytest.approx(10.0 - lo[1], rel=1e-6)


def test_instanced_file_renders_like_its_flat_twin(twins):
    instanced, flat, _ = twins
    images = [loaded.renderer().render(loaded.camera, loaded.width, loaded.height)
              for loaded in (instanced, flat)]
    drawn = instanced.scene.intersect(*instanced.camera.rays(96, 72)).geom_id
    assert np.isin(drawn, [0, 1]).mean() > 0.08  # the copies fill a good part of the picture
    differ = np.abs(images[0].astype(int) - images[1].astype(int)).max(axis=2) > 2
    assert differ.mean() < 0.01


def test_a_mesh_no_instance_draws_is_an_error(tmp_path):
    """A file with [[instance]] tables draws only instances: a [[mesh]] none
    names would be missing from the picture without a word."""
    text = BASE + KNIGHT_MESH + BUNNY_MESH + "\n[[instance]]\nmesh = 1\n"
    with pytest.raises(SceneFileError, match=r"scene.toml: mesh\[0\]: no \[\[instance\]\] table "
                                             r"draws it.*add one with mesh = 0, or remove"):
        read(write(tmp_path, text))


def test_an_instance_table_s_material_is_every_copy_s(tmp_path, suite_device):
    """[[instance]] material: each copy of that table takes it as
    Renderer.instance_materials, in the scene's instance order; other copies
    and the ground keep their mesh's (None); a file that names none gives
    None, the Renderer's default."""
    gold = {"type": "roughconductor", "material": "Au", "alpha": 0.2}
    path = write(tmp_path, BASE + KNIGHT_MESH + """
[ground]
y = 0.0

[[instance]]
mesh = 0
translate = [[-2.0, 0.0, 0.0], [2.0, 0.0, 0.0]]

[[instance]]
mesh = 0
translate = [[0.0, 0.0, -2.0], [0.0, 0.0, 2.0], [0.0, 0.0, 4.0]]
material = { type = "roughconductor", material = "Au", alpha = 0.2 }
""")
    loaded = load(path, suite_device)
    assert loaded.instance_materials == [None, None, gold, gold, gold, None]
    assert list(loaded.scene.instance_meshes) == [0, 0, 0, 0, 0, 1]
    assert loaded.renderer().instance_materials == loaded.instance_materials
    plain = write(tmp_path, BASE + KNIGHT_MESH + "\n[[instance]]\nmesh = 0\n", name="plain.toml")
    assert load(plain, suite_device).instance_materials is None
