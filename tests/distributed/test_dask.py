"""hlbvh_cl.distributed.dask on a real cluster of worker processes: ray and point queries
over dask arrays and rendered frames are bit-identical to the same work in
one process; a worker killed mid-job costs no result; bad input raises the
local error on the client; each cluster, once closed, leaves no process
behind.  Also dask's local scheduler, and examples/sdf_dataset.py."""
from __future__ import annotations

import dataclasses
import importlib.util
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from bench_support import ROOT
from children import package_environment

import hlbvh_cl
from hlbvh_cl import travel

da = pytest.importorskip("dask.array")
distributed = pytest.importorskip("distributed")
psutil = pytest.importorskip("psutil")
trimesh = pytest.importorskip("trimesh")

import dask  # noqa: E402

import hlbvh_cl.distributed.dask as hd  # noqa: E402

spec = importlib.util.spec_from_file_location("sdf_dataset", ROOT / "examples" / "sdf_dataset.py")
sdf_dataset = importlib.util.module_from_spec(spec)
spec.loader.exec_module(sdf_dataset)


# ---------------------------------------------------------------- helpers

def _children() -> set[int]:
    """This process's descendants, but multiprocessing's resource tracker
    (started with the first spawned child, it lives as long as we do)."""
    out = set()
    for p in psutil.Process().children(recursive=True):
        try:
            if "resource_tracker" not in " ".join(p.cmdline()):
                out.add(p.pid)
        except psutil.NoSuchProcess:
            pass
    return out


def _none_left(before: set[int], within_s: float = 10.0) -> None:
    deadline = time.monotonic() + within_s
    while _children() - before and time.monotonic() < deadline:
        time.sleep(0.1)
    left = _children() - before
    assert not left, f"processes left behind: {[psutil.Process(p).cmdline() for p in left]}"


def _cluster():
    return distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1,
                                    dashboard_address=":0")


def _scene(meshes, device, name="bunny_small"):
    return hlbvh_cl.Scene([meshes[name]], device=device)


def _rays(scene, count, seed=0):
    """Rays from around the scene through its box: most hit, some miss."""
    rng = np.random.default_rng(seed)
    lo, hi = scene.meshes[0].bounds
    centre, size = (lo + hi) / 2, float(np.max(hi - lo))
    origins = (centre + rng.normal(size=(count, 3)) * size).astype(np.float32)
    targets = centre + rng.uniform(-0.6, 0.6, (count, 3)) * size
    return origins, (targets - origins).astype(np.float32)


def _points(scene, count, seed=1):
    lo, hi = scene.meshes[0].bounds
    rng = np.random.default_rng(seed)
    return (lo + (rng.random((count, 3)) * 1.4 - 0.2) * (hi - lo)).astype(np.float32)


def _same(local, spread, fields) -> None:
    got = dask.compute(*[getattr(spread, f) for f in fields])
    for name, value in zip(fields, got):
        np.testing.assert_array_equal(getattr(local, name), value, err_msg=name)


# ---------------------------------------------------------------- without a cluster

def test_importing_hlbvh_cl_imports_no_dask():
    code = ("import sys, hlbvh_cl; "
            "print(sorted(m for m in sys.modules if m.startswith(('dask', 'distributed'))))")
    found = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           cwd=ROOT, check=True, env=package_environment())
    assert found.stdout.strip() == "[]"


def test_a_scene_tokenizes_by_its_content_without_pickling(meshes, suite_device, monkeypatch):
    scene = _scene(meshes, suite_device.id)
    again = _scene(meshes, suite_device.id)
    monkeypatch.setattr(hlbvh_cl.Scene, "__reduce__", lambda self: pytest.fail("pickled"))
    assert dask.base.tokenize(scene) == dask.base.tokenize(again)
    before = dask.base.tokenize(scene)
    scene.update_vertices(0, scene.meshes[0].vertices * np.float32(2))
    assert dask.base.tokenize(scene) != before


def test_a_process_tasks_share_one_view_of_a_shipped_scene(meshes, suite_device):
    """Unpickled copies are Scene objects of their own (hlbvh_cl.travel), but
    the tasks of one process share one, its buffers and its renderers."""
    with _scene(meshes, suite_device.id).borrow() as built:
        spec = built.spec
    try:
        with hd.Shipped(spec).scene() as first, hd.Shipped(spec).scene() as second:
            assert first is second
        look = dict(colors=[(1.0, 1.0, 1.0)], light=None, materials=None, emitters=None)
        assert hd.task_renderer(first, look) is hd.task_renderer(second, dict(look))
        other = dict(look, materials=[{"type": "conductor"}])
        assert hd.task_renderer(first, other) is not hd.task_renderer(first, look)
    finally:  # later tests count the scenes this process restores
        hd.forget()


def test_a_task_on_the_scene_itself_holds_off_changes_until_it_ends(meshes, suite_device):
    """In the process that made the graph, a task queries the Scene itself
    while it holds the graph's content; a change from another thread waits
    for the task, rather than come between its check and its query (which
    gave dask's local threads chunks of both contents)."""
    import threading
    scene = _scene(meshes, suite_device.id)
    origins, directions = _rays(scene, 200)
    before = scene.intersect(origins, directions).t
    with scene.borrow() as built:
        shipped = hd.Shipped(built.spec, scene)
    changed = threading.Event()

    def change():
        scene.update_vertices(0, scene.meshes[0].vertices * np.float32(1.5))
        changed.set()
    with shipped.scene() as task_scene:
        assert task_scene is scene
        thread = threading.Thread(target=change)
        thread.start()
        assert not changed.wait(1.0), "the change came in while the task held the scene"
        np.testing.assert_array_equal(task_scene.intersect(origins, directions).t, before)
    thread.join(60)
    assert changed.is_set()
    with shipped.scene() as task_scene:  # changed since: a view of the graph's content
        assert task_scene is not scene
        np.testing.assert_array_equal(task_scene.intersect(origins, directions).t, before)
    hd.forget()


def test_dask_local_scheduler_matches_one_process(meshes, suite_device):
    with pytest.raises(ValueError):  # no default client: this test runs before any cluster
        distributed.default_client()   # of this module, so dask's local scheduler runs it
    scene = _scene(meshes, suite_device.id)
    origins, directions = _rays(scene, 5000)
    hits = hd.intersect(scene, da.from_array(origins, chunks=(1200, 3)), directions)
    _same(scene.intersect(origins, directions), hits, hd.HITS.names)
    points = _points(scene, 3000)
    np.testing.assert_array_equal(hd.signed_distance(scene, da.from_array(points, 700)).compute(),
                                  scene.signed_distance(points))
    cameras = [hlbvh_cl.Camera(tuple(origins[k]), tuple(origins[k] + directions[k]))
               for k in range(2)]
    images = hd.render_frames(scene, cameras, 32, 24, progress=False)
    renderer = hlbvh_cl.Renderer(scene)
    for image, camera in zip(images, cameras):
        np.testing.assert_array_equal(image, renderer.render(camera, 32, 24))
    assert travel.cached_count() == 0  # the scene itself served the tasks: none rebuilt



def test_render_frames_takes_the_instances_own_materials(meshes, suite_device):
    """render_frames(instance_materials=...) renders as a local Renderer
    with them does, frame for frame."""
    shift = np.hstack([np.eye(3), [[12.0], [0.0], [0.0]]])
    scene = hlbvh_cl.Scene([meshes["bunny_small"]], device=suite_device,
                           instances=[(0, np.eye(3, 4)), (0, shift)])
    own = [{"type": "roughconductor", "material": "Au", "alpha": 0.3}, None]
    lo, hi = meshes["bunny_small"].bounds
    centre = (np.asarray(lo) + np.asarray(hi)) / 2 + [6.0, 0.0, 0.0]
    cameras = [hlbvh_cl.Camera(tuple(centre + [0.0, 5.0, 40.0]), tuple(centre))]
    seen = scene.intersect(*cameras[0].rays(24, 16)).instance_id
    assert (seen == 0).any() and (seen == 1).any()  # both copies in the frame
    options = dict(shading="path", spp=2, max_depth=3, hdr=True)
    images = hd.render_frames(scene, cameras, 24, 16, progress=False, instance_materials=own,
                              **options)
    renderer = hlbvh_cl.Renderer(scene, instance_materials=own)
    np.testing.assert_array_equal(images[0], renderer.render(cameras[0], 24, 16, **options))
    with pytest.raises(ValueError, match="instance_materials has 1 entries"):
        hd.render_frames(scene, cameras, 24, 16, progress=False, instance_materials=own[:1],
                         **options)

@pytest.mark.parametrize("chunks", [(700, 0, 500), (0, 1200), (1200, 0)])
def test_every_hit_over_empty_chunks_has_the_local_offsets(meshes, suite_device, chunks):
    """Rays chunked with empty chunks (a filter's leftovers): the offsets
    and counts are the local ones, int64 as there, not float64."""
    scene = _scene(meshes, suite_device.id)
    origins, directions = _rays(scene, 1200)
    local = scene.intersect_all(origins, directions)
    spread = hd.intersect_all(scene, da.from_array(origins, chunks=(chunks, 3)),
                              da.from_array(directions, chunks=(chunks, 3)))
    for name in ("offsets", "counts", "ray_index", "t"):
        got = getattr(spread, name).compute(scheduler="threads")
        assert got.dtype == getattr(local, name).dtype, name
        np.testing.assert_array_equal(got, getattr(local, name), err_msg=name)
    assert local.t.size > 100


# ---------------------------------------------------------------- on a cluster

def test_render_frames_checks_its_files_and_flags_before_any_task(tmp_path, meshes,
                                                                 suite_device):
    """Every argument render_frames writes files or runs tasks by is
    checked before any task renders (a name without {} had written every
    frame to one file, an .exr name without hdr 8-bit codes as radiance; an
    empty camera list skipped the checks); numpy integers are integers."""
    scene = _scene(meshes, suite_device.id)
    cameras = [hlbvh_cl.Camera((0, 0.1, 0.4), (0, 0.1, 0)), hlbvh_cl.Camera((0.1, 0.1, 0.4),
                                                                          (0, 0.1, 0))]
    cases = [
        (dict(name="same.png"), ValueError, "gives 2 frames one file: it needs a {} field"),
        (dict(name="e{}.exr"), ValueError, "8-bit images (hdr=False) go to .png, .jpg"),
        (dict(name="h{}.png", hdr=True), ValueError,
         "hdr=True writes float32 radiance, to .exr files, not .png"),
        (dict(name="f{}"), ValueError, "not a name without a suffix"),
        (dict(name=5), TypeError, "name must be a file name with {} for the frame's index"),
        (dict(name="{x}.png"), ValueError, "must take the frame's index as its one {} field"),
        (dict(name=str(tmp_path / "elsewhere_{}.png")), ValueError,
         "must be a file name in the output folder, without a folder of its own"),
        (dict(output=3), TypeError, "output must be a folder's path"),
        (dict(progress="no"), TypeError, "progress must be True or False, got str"),
        (dict(client="x"), TypeError, "client must be a dask.distributed.Client"),
    ]
    folder = tmp_path / "frames"
    for options, error, words in cases:
        given = {"output": folder, **options}
        with pytest.raises(error) as raised:
            hd.render_frames(scene, cameras, 8, 6, **given)
        assert words in str(raised.value), (options, raised.value)
    assert not folder.exists() or not any(folder.iterdir())  # nothing rendered
    with pytest.raises(ValueError, match="shading must be one of"):
        hd.render_frames(scene, [], 8, 6, shading="nope")
    frames = hd.render_frames(scene, cameras, 8, 6, frames_per_task=np.int64(2), progress=False)
    local = hlbvh_cl.Renderer(scene)
    for frame, camera in zip(frames, cameras):
        np.testing.assert_array_equal(frame, local.render(camera, 8, 6))


@pytest.fixture(scope="module")
def client():
    before = _children()
    with _cluster() as cluster, distributed.Client(cluster) as client:
        yield client
    _none_left(before)


def test_ray_queries_match_one_process(client, meshes, suite_device):
    scene = _scene(meshes, suite_device.id)
    origins, directions = _rays(scene, 20_000)
    rays = da.from_array(np.concatenate([origins, directions], axis=1), chunks=(3000, 6))
    _same(scene.intersect(origins, directions), hd.intersect(scene, rays), hd.HITS.names)

    o, d = da.from_array(origins, chunks=(2500, 3)), da.from_array(directions, chunks=(4000, 3))
    tmax = np.random.default_rng(2).uniform(0.5, 2.0, len(origins)).astype(np.float32)
    np.testing.assert_array_equal(hd.occluded(scene, o, d, tmax=tmax).compute(),
                                  scene.occluded(origins, directions, tmax=tmax))
    np.testing.assert_array_equal(
        hd.count_intersections(scene, o, d, tmin=0.1, mask=7).compute(),
        scene.count_intersections(origins, directions, tmin=0.1, mask=7))

    # one origin for an image of directions, chunked in tiles
    camera = hlbvh_cl.Camera(tuple(origins[0]), tuple(np.mean(scene.meshes[0].bounds, axis=0)))
    eye, image = camera.rays(96, 64)
    image = image.reshape(64, 96, 3)
    tiles = da.from_array(image, chunks=(20, 40, 3))
    hits = hd.intersect(scene, eye[0], tiles)
    assert hits.t.chunks == ((20, 20, 20, 4), (40, 40, 16))
    _same(scene.intersect(eye[0], image), hits, ("t", "prim_id", "normal", "points"))

    # every hit: the chunks' hits in the rays' order, offsets from the counts
    local = scene.intersect_all(eye[0], image, max_hits=4, mask=3)
    spread = hd.intersect_all(scene, eye[0], tiles, max_hits=4, mask=3)
    assert spread.shape == (64, 96) and np.isnan(spread.t.chunks[0]).all()
    names = ("offsets", "ray_index", "t", "u", "v", "prim_id", "geom_id", "instance_id")
    for name, value in zip(names, dask.compute(*(getattr(spread, n) for n in names))):
        np.testing.assert_array_equal(value, getattr(local, name), err_msg=name)
    assert local.t.size > 1000

    built = client.run(travel.cached_count)
    assert sorted(built.values()) == [1, 1], built  # one build per worker for all of the above
    assert travel.cached_count() == 0  # none in the client (and its scheduler)


def test_point_queries_match_one_process(client, meshes, suite_device):
    scene = _scene(meshes, suite_device.id, "armadillo_small")
    points = _points(scene, 12_000)
    chunked = da.from_array(points, chunks=(2000, 3))
    _same(scene.closest_points(points), hd.closest_points(scene, chunked), hd.CLOSEST.names)
    near = hd.closest_points(scene, chunked, max_distance=0.05)
    _same(scene.closest_points(points, max_distance=0.05), near, ("distance", "prim_id"))
    np.testing.assert_array_equal(hd.signed_distance(scene, chunked).compute(),
                                  scene.signed_distance(points))
    np.testing.assert_array_equal(hd.contains(scene, chunked).compute(), scene.contains(points))
    grid = points.reshape(40, 300, 3)
    np.testing.assert_array_equal(
        hd.winding_number(scene, da.from_array(grid, chunks=(16, 128, 3))).compute(),
        scene.winding_number(grid))


def test_render_frames_match_one_process(client, tmp_path, suite_device):
    loaded = hlbvh_cl.io.scenefile.load(ROOT / "scenes" / "bunny_small.toml", device=suite_device.id)
    cameras = [dataclasses.replace(loaded.camera, eye=tuple(np.add(loaded.camera.eye, (x, 0, 0))))
               for x in (-4, -2, 0, 2, 4)]
    options = dict(colors=list(loaded.colors), light=loaded.light, progress=False)
    images = hd.render_frames(loaded.scene, cameras, 80, 60, client, **options)
    local = loaded.renderer()
    expected = [local.render(c, 80, 60) for c in cameras]
    assert len(images) == 5 and images[0].shape == (60, 80, 3) and images[0].dtype == np.uint8
    for k, (got, want) in enumerate(zip(images, expected)):
        np.testing.assert_array_equal(got, want, err_msg=f"frame {k}")
    assert len({im.tobytes() for im in images}) == 5  # the orbit's views differ

    import imageio.v3 as iio
    paths = hd.render_frames(loaded.scene, cameras, 80, 60, client, output=tmp_path / "frames",
                             frames_per_task=2, **options)
    assert [p.name for p in paths] == [f"frame_{k:05d}.png" for k in range(5)]
    for path, want in zip(paths, expected):
        np.testing.assert_array_equal(iio.imread(path), want)


def test_path_traced_frames_match_one_process(client, tmp_path, meshes, suite_device):
    """Materials, emitters and the path options travel to the workers: each
    frame is the one a local Renderer renders with the same seed."""
    scene = _scene(meshes, suite_device.id)
    look = dict(materials=[{"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}],
                emitters=[{"type": "constant", "radiance": 0.5},
                          {"type": "point", "position": [0.3, 0.4, 0.3], "intensity": 0.2}])
    options = dict(shading="path", spp=2, max_depth=4, seed=5, rfilter="gaussian", hdr=True)
    cameras = [hlbvh_cl.Camera(eye=(x, 0.1, 0.3), target=(0, 0.1, 0)) for x in (-0.1, 0.1)]
    local = hlbvh_cl.Renderer(scene, **look)
    expected = [local.render(c, 40, 30, **options) for c in cameras]
    paths = hd.render_frames(scene, cameras, 40, 30, client, output=tmp_path, progress=False,
                             **look, **options)
    assert [p.name for p in paths] == ["frame_00000.exr", "frame_00001.exr"]
    from hlbvh_cl.io.exr import read_exr
    for path, want in zip(paths, expected):
        assert want.dtype == np.float32 and want.max() > 0
        np.testing.assert_array_equal(read_exr(path), want)
    with pytest.raises(ValueError, match=r"materials\[0\]"):
        hd.render_frames(scene, cameras, 40, 30, client, materials=[{"type": "velvet"}],
                         shading="path")


def test_bad_input_raises_the_local_error_on_the_client(client, meshes, suite_device):
    scene = _scene(meshes, suite_device.id)
    origins, directions = _rays(scene, 10_000)
    directions[7321] = [np.nan, 0, 1]  # in the fourth chunk
    with pytest.raises(ValueError) as local:
        scene.intersect(origins, directions)
    with pytest.raises(ValueError) as spread:
        hd.intersect(scene, origins, da.from_array(directions, chunks=(2000, 3))).t.compute()
    assert str(spread.value) == str(local.value) == \
        "directions[7321] = [nan, 0.0, 1.0] is not finite"

    image = np.ones((30, 40, 6), np.float32)
    image[17, 29, 3:] = 0
    with pytest.raises(ValueError) as local:
        scene.occluded(image)
    with pytest.raises(ValueError) as spread:
        hd.occluded(scene, da.from_array(image, chunks=(8, 10, 6))).compute()
    assert str(spread.value) == str(local.value)
    assert str(local.value).startswith("rays[17, 29][3:6] = [0.0, 0.0, 0.0] has zero length")

    far = _points(scene, 5000)
    far[4444] = [np.inf, 0, 0]
    with pytest.raises(ValueError, match=r"^points\[4444\] = \[inf, 0.0, 0.0\] is not finite$"):
        hd.signed_distance(scene, da.from_array(far, chunks=1000)).compute()
    # shapes and options fail at once, before any task
    with pytest.raises(ValueError, match=r"directions must have shape \(\.\.\., 3\)"):
        hd.intersect(scene, origins, da.zeros((10, 4), chunks=5))
    with pytest.raises(ValueError, match="tmin = 2.0 is greater than tmax = 1.0"):
        hd.occluded(scene, origins, directions, tmin=2.0, tmax=1.0)
    with pytest.raises(ValueError, match="width must be an integer >= 1 and <= 16384, got 0"):
        hd.render_frames(scene, [hlbvh_cl.Camera((0, 0, 1), (0, 0, 0))], 0, 10, client)


def test_sdf_dataset_example_on_two_tiny_meshes(client, tmp_path, suite_device):
    folder = tmp_path / "meshes"
    folder.mkdir()
    trimesh.creation.icosphere(subdivisions=2).export(folder / "ball.ply")
    (folder / "more").mkdir()  # searched too
    trimesh.creation.box(extents=(1.0, 2.0, 0.5)).export(folder / "more" / "box.obj")
    out = tmp_path / "out"
    done = sdf_dataset.main([str(folder), "--output", str(out), "--points", "3000",
                             "--scheduler", client.scheduler.address, "--device",
                             suite_device.id, "--no-progress"])
    assert sorted(r["mesh"] for r in done) == ["ball.ply", "box.obj"]
    for name in ("ball", "box"):
        data = np.load(out / f"{name}.npz")
        points, sdf = data["points"], data["sdf"]
        assert points.shape == (3000, 3) and sdf.shape == (3000,) and sdf.dtype == np.float32
        mesh = hlbvh_cl.Mesh.load(next(folder.rglob(f"{name}.*")))
        local = hlbvh_cl.Scene([mesh], device=suite_device.id)
        np.testing.assert_array_equal(sdf, local.signed_distance(points))
        lo, hi = mesh.bounds
        assert (points[1500:] >= lo - 0.05 * (hi - lo) - 1e-6).all()  # the uniform half
        assert 0.05 < np.mean(sdf < 0) < 0.95  # both sides sampled
    ball = np.load(out / "ball.npz")
    radius = np.linalg.norm(ball["points"], axis=1)
    np.testing.assert_allclose(ball["sdf"], radius - 1, atol=0.02)  # an icosphere of radius 1


# ---------------------------------------------------------------- a worker killed

def test_a_killed_worker_costs_no_result(meshes, suite_device):
    before = _children()
    scene = _scene(meshes, suite_device.id, "bunny")
    lo, hi = scene.meshes[0].bounds
    centre, size = (lo + hi) / 2, float(np.max(hi - lo))
    with _cluster() as cluster, distributed.Client(cluster) as client:
        rng = da.random.default_rng(5)  # rays made on the workers, the same each time
        shape, chunks = (2_400_000, 3), (100_000, 3)
        origins = (centre + rng.normal(size=shape, chunks=chunks) * size).astype(np.float32)
        directions = (centre + rng.uniform(-0.6, 0.6, shape, chunks=chunks) * size
                      - origins).astype(np.float32)
        expected = scene.count_intersections(*dask.compute(origins, directions))
        counts = hd.count_intersections(scene, origins, directions)
        pids = client.run(os.getpid)
        victim = sorted(pids)[0]
        job = client.compute(counts)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # until the victim holds results and is working
            held = [k for k in client.has_what().get(victim, ()) if "_ray_block" in str(k)]
            if held and client.processing().get(victim):
                break
            time.sleep(0.01)
        assert not job.done()
        os.kill(pids[victim], signal.SIGKILL)
        got = job.result(timeout=120)
        assert pids[victim] not in client.run(os.getpid).values()  # it did die
    np.testing.assert_array_equal(got, expected)
    _none_left(before)
