"""The public surface: its names, the one Camera's rays, scene files through
the package, and an import that touches nothing."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np

import hlbvh_cl
from hlbvh_cl.io import scenefile
import built
import places

ROOT = places.REPO


def test_public_names():
    assert sorted(hlbvh_cl.__all__) == sorted([
        "Scene", "Mesh", "Hits", "AllHits", "ClosestPoints", "BuildStats", "Renderer", "Camera",
        "Light", "Device", "devices", "DeviceMemoryError", "KernelBuildError", "scenefile",
        "RenderInterrupted", "RenderResult"])
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])])
    public = {name for name in dir(scene) if not name.startswith("_")}
    assert public == {"intersect", "occluded", "intersect_all", "count_intersections",
                      "closest_points", "signed_distance", "contains", "winding_number",
                      "update_vertices", "rebuild", "stats", "device", "meshes", "builder",
                      "morton_bits", "compact", "set_transforms", "transforms", "masks", "instance_meshes",
                      "borrow", "view", "queue", "spheres"}
    assert isinstance(scene.stats, hlbvh_cl.BuildStats)
    assert isinstance(scene.device, hlbvh_cl.Device)


def test_import_has_no_side_effects(tmp_path):
    """A fresh interpreter imports the package: no file is written under
    HOME or XDG_CACHE_HOME and os.environ is unchanged."""
    home, cache = tmp_path / "home", tmp_path / "cache"
    home.mkdir(), cache.mkdir()
    env = {**os.environ, "HOME": str(home), "XDG_CACHE_HOME": str(cache)}
    env.pop("OCL_ICD_VENDORS", None)
    script = ("import json, os; before = dict(os.environ); import hlbvh_cl; "
              "print(json.dumps(dict(os.environ) == before))")
    out = subprocess.run([sys.executable, "-c", script], env=env, cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout
    assert json.loads(out.strip().splitlines()[-1]) is True
    assert not any(home.rglob("*")) and not any(cache.rglob("*"))


def test_camera_rays_are_the_renderers_primary_rays():
    """Camera.rays gives the rays a one-sample render traces: the normals
    image computed from their hits is the rendered one, pixel for pixel."""
    meshes = [hlbvh_cl.Mesh.load(ROOT / "scenes/meshes/teapot.ply")]
    scene = hlbvh_cl.Scene(meshes)
    tree = built.tree(scene)
    lo, hi = tree.bounds_lo, tree.bounds_hi
    camera = hlbvh_cl.Camera((lo + hi) / 2 + (hi - lo) * [0.4, 0.6, 1.8], (lo + hi) / 2,
                             fov_deg=35)
    width, height = 37, 23
    origins, directions = camera.rays(width, height)
    assert origins.shape == directions.shape == (width * height, 3)
    assert origins.dtype == directions.dtype == np.float32
    hits = scene.intersect(origins, directions)
    assert 0.1 < hits.hit.mean() < 0.9
    normal = hits.normal.astype(np.float64)
    facing = np.where((normal * directions).sum(axis=1, keepdims=True) > 0, -normal, normal)
    expected = np.where(hits.hit[:, None], np.rint(255 * (facing + 1) / 2), 0)
    image = hlbvh_cl.Renderer(scene).render(camera, width, height, shading="normals")
    got = image.reshape(-1, 3).astype(np.float64)
    assert np.array_equal(got != 0, expected != 0)  # the same pixels hit
    assert np.abs(got - expected).max() <= 1  # float32 rounding of (n + 1) / 2 aside


def test_scene_files_load_through_the_package():
    path = ROOT / "scenes/bunny_small.toml"
    description = scenefile.read(path)
    loaded = scenefile.load(path)
    assert isinstance(loaded.scene, hlbvh_cl.Scene)
    assert isinstance(loaded.camera, hlbvh_cl.Camera) and isinstance(loaded.light, hlbvh_cl.Light)
    assert loaded.camera == description.camera and loaded.light == description.light
    assert (loaded.width, loaded.height) == (description.width, description.height)
    assert list(loaded.colors) == [color for _, color in description.geometries()]
    assert loaded.load_seconds > 0 and loaded.build_seconds > 0
    renderer = loaded.renderer()
    assert renderer.light == loaded.light and list(renderer.colors) == list(loaded.colors)
    image = renderer.render(loaded.camera, 16, 9)
    assert image.shape == (9, 16, 3)


def test_a_failed_mesh_rebuild_of_an_instanced_scene_says_so_and_recovers(monkeypatch):
    """The meshes' trees of a two-level scene are released before they are
    built again: when that build raises, queries say to rebuild (rather than
    trace the top tree into released buffers), and rebuild() recovers."""
    import pytest

    import hlbvh_cl.build.instances as instances_module
    from shapes import grid_mesh

    grid = grid_mesh(4)
    shifted = np.hstack([np.eye(3), [[0.0], [0.0], [2.0]]])
    scene = hlbvh_cl.Scene([grid], instances=[(0, np.hstack([np.eye(3), np.zeros((3, 1))])),
                                              (0, shifted)])
    origins = np.float32([[0.3, 0.4, -3.0], [1.3, 2.4, -3.0]])
    directions = np.tile(np.float32([[0.0, 0.0, 1.0]]), (2, 1))
    before = scene.intersect(origins, directions)
    assert before.hit.all()

    def fail(*args, **kwargs):
        raise KeyboardInterrupt

    for step in ("rebuild", "update_vertices"):
        with monkeypatch.context() as patch:
            patch.setattr(instances_module, "build_mesh_trees", fail)
            with pytest.raises(KeyboardInterrupt):
                scene.rebuild() if step == "rebuild" else scene.update_vertices(0, grid.vertices)
        for call in (lambda: scene.intersect(origins, directions),
                     lambda: scene.count_intersections(origins, directions),
                     lambda: scene.closest_points(origins)):
            with pytest.raises(RuntimeError, match="last rebuild or update failed"):
                call()
        scene.rebuild()
        assert np.array_equal(scene.intersect(origins, directions).t, before.t), step


def test_a_failed_buffer_reservation_does_not_break_later_queries(monkeypatch):
    """Ray-query buffers are released before bigger ones are allocated: if
    that allocation fails (or Ctrl-C comes), the next query allocates again
    rather than find no buffers under the old capacity."""
    import pytest

    from hlbvh_cl.query.rays import RayQuery
    from shapes import grid_mesh

    scene = hlbvh_cl.Scene([grid_mesh(4)])
    query = RayQuery(built.runtime(scene))
    query.zero_copy = False  # the device-buffer path (GPUs, Intel's CPU runtime)
    tree = built.tree(scene)
    origins = np.float32([[0.3, 0.4, -3.0]] * 64)
    directions = np.tile(np.float32([[0.0, 0.0, 1.0]]), (64, 1))
    expected = query.intersect(tree, origins[:8], directions[:8]).t
    with monkeypatch.context() as patch:
        patch.setattr(type(built.runtime(scene)), "check_allocation",
                      lambda *args, **kwargs: (_ for _ in ()).throw(KeyboardInterrupt()))
        with pytest.raises(KeyboardInterrupt):
            query.intersect(tree, origins, directions)
    assert np.array_equal(query.intersect(tree, origins[:8], directions[:8]).t, expected)


def test_ctrl_c_just_after_a_change_leaves_no_answer_for_the_old_content(monkeypatch):
    """A KeyboardInterrupt once set_transforms or update_vertices has put
    the new content in the scene, before its tree is rebuilt or refit: the
    scene then holds (and pickles) the new content, so queries must say to
    rebuild rather than answer for the old one; a rebuild answers for the
    new."""
    import pytest

    import hlbvh_cl.scene as scene_module
    from shapes import grid_mesh

    grid = grid_mesh(4)
    moved = grid.vertices + np.float32([0.0, 0.0, 2.0])
    lifted = np.hstack([np.eye(3), [[0.0], [0.0], [2.0]]])
    origins = np.float32([[0.3, 0.4, -3.0], [0.6, 0.2, -3.0]])
    directions = np.tile(np.float32([[0.0, 0.0, 1.0]]), (2, 1))

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    cases = {  # a change, and what it interrupts once the content is in
        "set_transforms": (lambda s: s.set_transforms(0, lifted), "_build"),
        "instanced update_vertices": (lambda s: s.update_vertices(0, moved), "rebuild"),
        "flat update_vertices": (lambda s: s.update_vertices(0, moved), None),
    }
    for name, (change, step) in cases.items():
        instanced = name != "flat update_vertices"
        scene = (hlbvh_cl.Scene([grid], instances=[(0, np.eye(3, 4))]) if instanced
                 else hlbvh_cl.Scene([grid]))
        assert np.allclose(scene.intersect(origins, directions).t, 3.0)
        with monkeypatch.context() as patch:
            if step:
                patch.setattr(scene, step, interrupted)
            else:  # the first step after the meshes are replaced: is the new frame the same?
                patch.setattr(scene_module.frame, "scale_for", interrupted)
            with pytest.raises(KeyboardInterrupt):
                change(scene)
        with pytest.raises(RuntimeError):
            scene.intersect(origins, directions)
        scene.rebuild()
        assert np.allclose(scene.intersect(origins, directions).t, 5.0), name


def test_a_failed_rebuild_or_refit_leaves_a_scene_that_says_so_and_recovers(monkeypatch):
    """A build that raises leaves no half-made tree: queries and renders say
    to rebuild, and update_vertices builds anew.  A refit that raises leaves
    no half-refit tree either (queries say so, rather than trace boxes part
    old, part new) and the meshes as the device has them, so the next
    rebuild matches them."""
    import pytest

    import hlbvh_cl.scene as scene_module
    from shapes import grid_mesh

    grid = grid_mesh(8)
    vertices, faces = grid.vertices, grid.faces
    scene = hlbvh_cl.Scene([grid])
    origins = np.float32([[0.3 + k, 0.4 + 2 * k, -3.0] for k in range(4)])
    directions = np.tile(np.float32([[0.0, 0.0, 1.0]]), (4, 1))
    before = scene.intersect(origins, directions)
    assert before.hit.all()

    def fail(*args, **kwargs):
        raise RuntimeError("injected")

    with monkeypatch.context() as patch:
        patch.setattr(scene_module, "build", fail)
        with pytest.raises(RuntimeError, match="injected"):
            scene.rebuild()
    for call in (lambda: scene.intersect(origins, directions),
                 lambda: scene.occluded(origins, directions),
                 lambda: hlbvh_cl.Renderer(scene).render(
                     hlbvh_cl.Camera((4, 4, -3), (4, 4, 0)), 4, 4)):
        with pytest.raises(RuntimeError, match="last rebuild or update failed"):
            call()
    scene.update_vertices(0, vertices)  # builds anew
    assert np.array_equal(scene.intersect(origins, directions).t, before.t)

    moved = (vertices * np.float32(2.0)).astype(np.float32)
    with monkeypatch.context() as patch:
        patch.setattr(scene_module, "refit", fail)
        with pytest.raises(RuntimeError, match="injected"):
            scene.update_vertices(0, moved)
    assert np.array_equal(scene.meshes[0].vertices, moved)
    with pytest.raises(RuntimeError, match="last rebuild or update failed"):
        scene.intersect(origins, directions)
    scene.rebuild()
    fresh = hlbvh_cl.Scene([hlbvh_cl.Mesh(moved, faces)])
    assert np.array_equal(scene.intersect(origins, directions).t,
                          fresh.intersect(origins, directions).t)
