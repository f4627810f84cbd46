"""Scenes and worker processes (docs/dask.md, "Worker processes").

OpenCL runtimes do not survive fork(): a child forked after the parent
started OpenCL would block for ever at its first kernel.  So such a child
gets a ForkedProcessError at its first call, never a hang, whether it is a
multiprocessing fork pool's or a DataLoader-style worker's; workers started
with spawn, or forked before the parent touched OpenCL, work.  Every wait
here has a timeout: a hang fails the test instead of stalling the suite."""
import multiprocessing
import os
import select
import signal
import subprocess
import sys

import numpy as np
import pytest

import hlbvh_cl
from hlbvh_cl.device.discovery import ForkedProcessError

import places
import workers
from children import package_environment
from shapes import grid_mesh

#: Seconds any worker may take to answer (a spawned one imports and builds).
ANSWER_S = 120

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork() here")


@pytest.fixture(scope="module")
def scene(suite_device):
    built = hlbvh_cl.Scene([grid_mesh(4)], device=suite_device)
    built.intersect(workers.ORIGINS, workers.DOWN)  # OpenCL is started: the kernels ran
    return built


def test_a_fork_pools_worker_gets_an_error_at_its_first_call(scene):
    workers.inherit(scene)
    with multiprocessing.get_context("fork").Pool(1) as pool:
        pending = pool.map_async(workers.trace_inherited, [0])
        with pytest.raises(ForkedProcessError) as raised:
            pending.get(timeout=ANSWER_S)
    message = str(raised.value)
    assert f"forked from process {os.getpid()}" in message
    assert "get_context('spawn')" in message and "multiprocessing_context='spawn'" in message


def test_every_entry_in_a_forked_child_fails_fast(scene):
    """Queries, renders, new scenes and runtimes: each raises before it
    takes a lock or calls OpenCL (a lock a parent thread held at the fork
    would stay held in the child)."""
    script = {
        "intersect": lambda: scene.intersect(workers.ORIGINS, workers.DOWN),
        "closest_points": lambda: scene.closest_points(workers.ORIGINS),
        "render": lambda: hlbvh_cl.Renderer(scene).render(
            hlbvh_cl.Camera((2, 2, 5), (2, 2, 0)), 8, 8),
        "new scene": lambda: hlbvh_cl.Scene([grid_mesh(2)], device=scene.device),
        "update": lambda: scene.update_vertices(0, grid_mesh(4).vertices),
    }
    read, write = os.pipe()
    child = os.fork()
    if child == 0:  # pragma: no cover (runs in the child)
        outcome = []
        for name, call in script.items():
            try:
                call()
                outcome.append(f"{name}: no error")
            except ForkedProcessError:
                outcome.append(f"{name}: ForkedProcessError")
            except BaseException as error:
                outcome.append(f"{name}: {type(error).__name__}")
        try:
            os.write(write, "\n".join(outcome).encode())
        finally:  # gone at once, as after fork it must be: no exit handlers, no pytest of its own
            os.kill(os.getpid(), signal.SIGKILL)
    os.close(write)
    ready, _, _ = select.select([read], [], [], ANSWER_S)
    if not ready:
        os.kill(child, signal.SIGKILL)
    os.waitpid(child, 0)
    with os.fdopen(read) as pipe:
        answers = pipe.read().splitlines() if ready else ["the forked child hung"]
    assert answers == [f"{name}: ForkedProcessError" for name in script]


def test_a_dataloader_style_workers_error_reaches_the_parent(scene):
    context = multiprocessing.get_context("fork")
    indices, results = context.Queue(), context.Queue()
    worker = context.Process(target=workers.loader_worker,
                             args=(workers.Dataset(scene), indices, results), daemon=True)
    worker.start()
    try:
        indices.put(3)
        index, value, error = results.get(timeout=ANSWER_S)
    finally:
        indices.put(None)
        worker.join(ANSWER_S)
    assert index == 3 and value is None
    assert error[0] == "ForkedProcessError" and "spawn" in error[1]


def test_spawned_workers_rebuild_the_pickled_scene_and_agree(scene):
    expected = scene.intersect(workers.ORIGINS, workers.DOWN).t
    rows = np.array_split(np.arange(len(workers.ORIGINS)), 2)
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        pending = pool.starmap_async(workers.trace, [(scene, r) for r in rows])
        answers = pending.get(timeout=ANSWER_S)
    np.testing.assert_array_equal(np.concatenate(answers), expected)


def test_workers_forked_before_the_parent_starts_opencl_use_it(suite_device):
    """Only the workers use hlbvh_cl: each starts OpenCL for itself."""
    script = (
        "import multiprocessing, sys\n"
        "import hlbvh_cl, workers\n"
        "from shapes import grid_mesh\n"
        "def work(rows):\n"
        "    scene = hlbvh_cl.Scene([grid_mesh(4)], device=sys.argv[1])\n"
        "    return workers.trace(scene, rows).tolist()\n"
        "with multiprocessing.get_context('fork').Pool(2) as pool:\n"
        f"    print(pool.map_async(work, [[0, 1], [2, 3]]).get(timeout={ANSWER_S}))\n")
    env = package_environment()
    env["PYTHONPATH"] = os.pathsep.join([str(places.SUPPORT), env["PYTHONPATH"]])
    done = subprocess.run([sys.executable, "-c", script, suite_device.id], env=env,
                          capture_output=True, text=True, timeout=2 * ANSWER_S)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip() == "[[2.0, 2.0], [2.0, 2.0]]"


def test_pytorchs_dataloader_forks_into_an_error_and_spawns_into_answers(scene):
    torch = pytest.importorskip("torch")
    from torch.utils.data import DataLoader
    dataset = workers.Dataset(scene)
    expected = scene.intersect(workers.ORIGINS, workers.DOWN).t
    forked = DataLoader(dataset, batch_size=12, num_workers=1, multiprocessing_context="fork",
                        timeout=ANSWER_S)
    with pytest.raises(ForkedProcessError):
        next(iter(forked))
    spawned = DataLoader(dataset, batch_size=12, num_workers=2, multiprocessing_context="spawn",
                         timeout=ANSWER_S)
    got = torch.cat(list(spawned)).numpy()
    np.testing.assert_array_equal(got, expected)
