"""Thread safety: any mix of queries (of every kind), renders, refits and
rebuilds from many threads, on one Scene or several Scenes of one device,
gives what some serial order of the same calls gives, bit for bit."""
import dataclasses
import sys
import threading
import time

import numpy as np
import pytest

import hlbvh_cl
import built
from shapes import grid_mesh
import places

MESHES = "scenes/meshes"
SECONDS = 20.0


def _rays(scene, count, seed):
    rng = np.random.default_rng(seed)
    tree = built.tree(scene)
    lo, hi = tree.bounds_lo, tree.bounds_hi
    centre, size = (lo + hi) / 2, float(np.max(hi - lo))
    origins = centre + rng.normal(size=(count, 3)) * size
    targets = centre + rng.normal(size=(count, 3)) * size * 0.2
    return origins.astype(np.float32), (targets - origins).astype(np.float32)


@pytest.fixture(scope="module")
def scenes():
    root = places.REPO / MESHES
    bunny = hlbvh_cl.Mesh.load(root / "bunny_small.ply")
    teapot = hlbvh_cl.Mesh.load(root / "teapot.ply")
    return [hlbvh_cl.Scene([bunny, grid_mesh(3)]), hlbvh_cl.Scene([teapot])]


def _calls(scene, k):
    """The calls the threads make on a scene, each with a fixed input."""
    origins, directions = _rays(scene, 20000, k)
    points = origins[:5000] * np.float32(0.3) + directions[:5000] * np.float32(0.1)
    tree = built.tree(scene)
    lo, hi = tree.bounds_lo, tree.bounds_hi
    eye = (lo + hi) / 2 + (hi - lo) * [0.2, 0.9, 1.4]
    camera = hlbvh_cl.Camera(eye, (lo + hi) / 2)
    renderer = hlbvh_cl.Renderer(scene)
    return {
        "intersect": lambda: scene.intersect(origins, directions),
        "occluded": lambda: scene.occluded(origins, directions),
        "count_intersections": lambda: scene.count_intersections(origins, directions),
        "intersect_all": lambda: scene.intersect_all(origins, directions, max_hits=4),
        "closest_points": lambda: scene.closest_points(points),
        "signed_distance": lambda: scene.signed_distance(points),
        "contains": lambda: scene.contains(points),
        "render": lambda: renderer.render(camera, 48, 32, shading="diffuse"),
    }


def _same(a, b) -> bool:
    """Bit for bit: arrays, or every array field of a result (Hits, AllHits,
    ClosestPoints)."""
    if isinstance(a, np.ndarray):
        return a.shape == b.shape and a.dtype == b.dtype and \
            np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
    arrays = [f.name for f in dataclasses.fields(a) if isinstance(getattr(a, f.name), np.ndarray)]
    return len(arrays) > 2 and all(_same(getattr(a, name), getattr(b, name)) for name in arrays)


def test_threads_get_serial_results_while_scenes_rebuild(scenes):
    calls = [(i, name, fn) for i, s in enumerate(scenes) for name, fn in _calls(s, i).items()]
    expected = {(i, name): fn() for i, name, fn in calls}  # serial order, one thread
    vertices = [s.meshes[0].vertices.copy() for s in scenes]

    stop = time.monotonic() + SECONDS
    failures: list[str] = []
    counts = {"queries": 0, "rebuilds": 0}
    ran = set()
    lock = threading.Lock()

    def worker(seed):
        rng = np.random.default_rng(seed)
        while time.monotonic() < stop and not failures:
            i, name, fn = calls[rng.integers(len(calls))]
            ran.add(name)
            try:
                got = fn()
            except Exception as error:  # noqa: BLE001 - reported below
                failures.append(f"scene {i} {name}: {type(error).__name__}: {error}")
                return
            if not _same(got, expected[(i, name)]):
                failures.append(f"scene {i} {name}: result differs from the serial one")
            with lock:
                counts["queries"] += 1

    def rebuilder():
        k = 0
        while time.monotonic() < stop and not failures:
            scene = scenes[k % 2]
            try:
                if k % 3 == 2:  # same positions: the refit boxes are the build's
                    scene.update_vertices(0, vertices[k % 2])
                else:
                    scene.rebuild()  # bit for bit the same tree (test_build)
            except Exception as error:  # noqa: BLE001
                failures.append(f"scene {k % 2} rebuild: {type(error).__name__}: {error}")
                return
            k += 1
            with lock:
                counts["rebuilds"] += 1

    previous = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        threads = [threading.Thread(target=worker, args=(seed,)) for seed in range(4)]
        threads.append(threading.Thread(target=rebuilder))
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=SECONDS + 60)
        assert not any(t.is_alive() for t in threads), "a thread is stuck"
    finally:
        sys.setswitchinterval(previous)
    assert not failures, failures[:5]
    assert counts["queries"] > 20 and counts["rebuilds"] > 5, counts
    assert ran == {name for _, name, _ in calls}, ran


def test_views_of_one_scene_make_its_dipoles_once(monkeypatch):
    """Views of one scene (what unpickling hands out, hlbvh_cl.travel) share
    its tree, and so its winding-number dipoles: two views asking at once make
    them once, rather than each its own with one buffer lost, and both get the
    serial answer."""
    scene = hlbvh_cl.Scene([grid_mesh(3)])
    points = np.random.default_rng(0).uniform(-1, 2, (2000, 3)).astype(np.float32)
    views = [scene.view() for _ in range(2)]
    rt = built.runtime(scene)
    made, kernel = [], rt.kernel

    def slow_kernel(file, name, **defines):
        if name == "dipoles_level":  # widen the window between the check and the store
            made.append(name)
            time.sleep(0.3)
        return kernel(file, name, **defines)

    monkeypatch.setattr(rt, "kernel", slow_kernel)
    got = [None, None]

    def ask(k):
        got[k] = views[k].winding_number(points)

    threads = [threading.Thread(target=ask, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert len(made) == 1
    expected = scene.winding_number(points)
    assert all(np.array_equal(g, expected) for g in got)
