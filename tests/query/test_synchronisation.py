"""What one call costs the host, counted rather than timed (issue 57): the
kernel launches and the host synchronisations of one query call of each
family, and of one build.  A synchronisation is anything that blocks the
calling thread on the device: a blocking copy or map, wait_for_events,
Event.wait, CommandQueue.finish, or a wait that polled its events until
they completed (a GPU's Runtime.wait first polls: runtime.polled).  On a GPU each costs a round trip that
dwarfs a small query's kernel, so a query call waits once, for its results.

pyopencl's own functions are counted (wrapped for the test), not the
library's bookkeeping, so a synchronisation added anywhere shows."""
from __future__ import annotations

import collections

import numpy as np
import pyopencl as cl
import pytest

import hlbvh_cl
from hlbvh_cl.build import widen
from hlbvh_cl.device import runtime as device_runtime
from hlbvh_cl.parallel import scan
from hlbvh_cl.query import engine
from shapes import deep_scene, grid_mesh

#: One build (issue 57): its stages size their buffers for the most they can
#: need and read the sizes the stages before them found on the device, so
#: the host waits twice: for one batch of reads (the scene's box, the flat
#: tree's figures, the wide levels' sizes), before the last kernel writes
#: the wide nodes into a buffer of their exact size, and for that kernel.
BUILD_SYNCS = 2
#: The GPU profile's, the larger (its wider top stages).  A few of these are
#: empty: the SAH top's levels and the wide levels are launched for the
#: deepest tree their sizes allow without reading them (pipeline.py).
BUILD_LAUNCHES = 34


#: intersect_all of rays on the device (query/all_hits.py), a batch of one
#: launch per pass: the rays' checks, the count pass, the segments (each
#: ray's kept hits, their scan, one launch where one work-group does it, and
#: their int64 offsets), then the fill pass, into hits sized by the one read
#: of their total.
INTERSECT_ALL_ON_DEVICE = 6


@pytest.fixture
def counted(monkeypatch):
    """Counts of "launch" and "sync" while the fixture is in use."""
    counts = collections.Counter()

    def wrap(owner, name, kind, blocking=None):
        original = getattr(owner, name)

        def counting(*args, **kwargs):
            if blocking is None or kwargs.get("is_blocking", blocking):
                counts[kind] += 1
            return original(*args, **kwargs)
        monkeypatch.setattr(owner, name, counting)

    wrap(cl, "enqueue_nd_range_kernel", "launch")
    wrap(cl, "enqueue_copy", "sync", blocking=True)  # pyopencl's default: blocking
    wrap(cl, "enqueue_map_buffer", "sync", blocking=True)
    wrap(cl, "wait_for_events", "sync")
    wrap(cl.CommandQueue, "finish", "sync")
    wrap(cl.Event, "wait", "sync")
    count_polled_waits(monkeypatch, lambda: counts.update(sync=1))
    return counts


def count_polled_waits(monkeypatch, record) -> None:
    """Calls ``record()`` for each wait that ended by polling (one that gave
    up goes on to wait_for_events, counted there)."""
    polled = device_runtime.polled

    def counting(*args, **kwargs):
        done = polled(*args, **kwargs)
        if done:
            record()
        return done
    monkeypatch.setattr(device_runtime, "polled", counting)


def queries(scene):
    rng = np.random.default_rng(5)
    origins = rng.uniform(-0.5, 1.5, (300, 3)).astype(np.float32)
    origins[:, 2] = -1.0
    directions = np.tile(np.float32([0.05, 0.02, 1.0]), (300, 1))
    points = rng.uniform(-0.5, 1.5, (300, 3)).astype(np.float32)
    return {
        "intersect": lambda: scene.intersect(origins, directions),
        "intersect with scalar limits": lambda: scene.intersect(origins, directions, tmin=0.5,
                                                                tmax=9.0),
        "occluded": lambda: scene.occluded(origins, directions),
        "count_intersections": lambda: scene.count_intersections(origins, directions),
        "closest_points": lambda: scene.closest_points(points),
        "winding_number": lambda: scene.winding_number(points),
        "signed_distance": lambda: scene.signed_distance(points),
        "contains": lambda: scene.contains(points),
        # all hits: a count pass sizes the hits' arrays, then a fill pass
        "intersect_all": lambda: scene.intersect_all(origins, directions),
    }


#: The engine's paths: (zero_copy, staging).
PATHS = {"in place": (True, False), "device buffers": (False, False), "staging": (False, True)}


def force_path(monkeypatch, path: str) -> None:
    """The engines made from here on take ``path`` (PATHS), whatever the device."""
    zero_copy, staged = PATHS[path]
    monkeypatch.setattr(engine, "zero_copy", lambda rt: zero_copy)
    monkeypatch.setattr(engine, "staging", lambda rt: staged)
    if staged:  # (Intel's results in place would take the point queries off it)
        monkeypatch.setattr(engine, "outputs_in_place", lambda rt: False)


@pytest.mark.parametrize("waits", ["blocking", "polling"])
@pytest.mark.parametrize("path", PATHS)
def test_a_query_call_launches_once_and_waits_once_for_its_results(path, waits, suite_device,
                                                                  counted, monkeypatch):
    """Every query family, with the kernels on the caller's arrays (CPU
    devices), through device buffers, and through pinned staging buffers
    (on request; forced here): one launch and one wait per pass, whether
    the wait blocks or polls (a GPU's first does: Runtime.spin_seconds)."""
    force_path(monkeypatch, path)
    if waits == "polling":  # a poll that sees every call end, and no blocking wait
        monkeypatch.setattr(device_runtime.runtime(suite_device), "spin_seconds", 30.0)
        monkeypatch.setattr(cl, "wait_for_events", lambda events: pytest.fail("it blocked"))
    else:
        monkeypatch.setattr(device_runtime.runtime(suite_device), "spin_seconds", 0.0)
    scene = hlbvh_cl.Scene([grid_mesh(6)], device=suite_device)
    for name, call in queries(scene).items():
        call()  # programs built, buffers reserved
        counted.clear()
        call()
        passes = 2 if name == "intersect_all" else 1
        assert dict(counted) == {"launch": passes, "sync": passes}, name


def test_a_staged_call_moves_each_row_once_while_the_other_run_traces(suite_device, counted,
                                                                      monkeypatch):
    """The staging path (on request; forced here) over a call of several runs:
    a launch per run; a wait per run at most (for a run's results, to put
    them into the result arrays: runs - 1, the last two in one wait); each
    row up once and each result down once, on queues of their own and
    through pinned buffers (CL_MEM_ALLOC_HOST_PTR) reused between calls;
    and the second run's rows go up before the host first waits, so that
    they overlap the first run's kernel."""
    from hlbvh_cl.query.rays import HIT_ARRAYS, RayQuery
    force_path(monkeypatch, "staging")
    scene = hlbvh_cl.Scene([grid_mesh(6)], device=suite_device)
    rng = np.random.default_rng(5)
    origins = rng.uniform(-0.5, 1.5, (300, 3)).astype(np.float32)
    origins[:, 2] = -1.0
    directions = np.tile(np.float32([0.05, 0.02, 1.0]), (300, 1))
    story = []  # ("copy", queue, host array) and "launch" / "sync", in order
    for name, kind in (("enqueue_nd_range_kernel", "launch"), ("wait_for_events", "sync")):
        original = getattr(cl, name)
        monkeypatch.setattr(cl, name, lambda *args, _original=original, _kind=kind, **kw: (
            story.append(_kind), _original(*args, **kw))[1])
    count_polled_waits(monkeypatch, lambda: story.append("sync"))
    copy = cl.enqueue_copy
    monkeypatch.setattr(cl, "enqueue_copy", lambda queue, dest, src, **kw: (
        story.append(("copy", queue, dest if isinstance(dest, np.ndarray) else src)),
        copy(queue, dest, src, **kw))[1])
    with scene.borrow() as built:
        query = RayQuery(built.runtime, max_rays_per_launch=64)
        expected = query.intersect(built.tree, origins, directions)  # buffers made, paced
        stage = query.engine.stage
        kept = [dict(pinned) for pinned in stage.pinned] + [dict(d) for d in stage.device]
        counted.clear()
        story.clear()
        hits = query.intersect(built.tree, origins, directions)
    runs = -(-len(origins) // 64)
    assert counted["launch"] == runs
    assert 1 <= counted["sync"] <= runs - 1
    for field in vars(hits):
        np.testing.assert_array_equal(getattr(hits, field), getattr(expected, field))
    # reused: the same buffers, pinned ones made to be
    assert [dict(pinned) for pinned in stage.pinned] + [dict(d) for d in stage.device] == kept
    mappings = [mapped for pinned in stage.pinned for buffer, mapped in pinned.values()
                if buffer.flags & cl.mem_flags.ALLOC_HOST_PTR]
    copies = [step for step in story if isinstance(step, tuple)]
    moved = {queue: sum(host.nbytes for _, q, host in copies if q == queue)
             for queue in (stage.up, stage.down, scene.queue)}
    assert moved[stage.up] == origins.nbytes + directions.nbytes
    assert moved[stage.down] == len(origins) * sum(HIT_ARRAYS.values())
    # the kernels' queue: the counters only (tmin, tmax and the mask went up
    # with the first call, and their buffers keep them)
    assert moved[scene.queue] == 4 * engine.COUNTERS
    assert all(any(np.shares_memory(host, mapped) for mapped in mappings)
               for _, q, host in copies if q in (stage.up, stage.down))
    second_launch = [i for i, step in enumerate(story) if step == "launch"][1]
    assert story.index("sync") > second_launch


def test_a_call_on_device_arrays_waits_once_and_moves_no_rays(suite_device, counted,
                                                              monkeypatch):
    """Rays (and points) given as pyopencl arrays: the checks' kernel and the query's,
    one wait (for the counters: the results stay on the device), and no
    copy between host and device but that wait's; intersect_all, whose
    hits' number only the count pass finds, two (INTERSECT_ALL_ON_DEVICE)."""
    import pyopencl.array as cla
    scene = hlbvh_cl.Scene([grid_mesh(6)], device=suite_device)
    rng = np.random.default_rng(5)
    origins = cla.to_device(scene.queue, rng.uniform(-0.5, 1.5, (300, 3)).astype(np.float32))
    directions = cla.to_device(scene.queue, np.tile(np.float32([0.05, 0.02, 1.0]), (300, 1)))
    # the scan's kernels launch through pyopencl's Kernel.__call__, which
    # the fixture does not see: counted by the events it returns
    scanned = scan.exclusive_scan
    monkeypatch.setattr(scan, "exclusive_scan", lambda *args, **kwargs: (
        events := scanned(*args, **kwargs), counted.update(launch=len(events)))[0])
    moved = []  # bytes of each copy between the host and the device
    original = cl.enqueue_copy
    monkeypatch.setattr(cl, "enqueue_copy", lambda queue, dest, src, **kw: (
        moved.append(sum(a.nbytes for a in (dest, src) if isinstance(a, np.ndarray))),
        original(queue, dest, src, **kw))[1])
    # back: the counters (tmin, tmax and the mask went up with the first call)
    one_wait = 4 * engine.COUNTERS
    calls = {"intersect": lambda: scene.intersect(origins, directions, tmax=9.0),
             "occluded": lambda: scene.occluded(origins, directions),
             "count_intersections": lambda: scene.count_intersections(origins, directions),
             "closest_points": lambda: scene.closest_points(origins),
             "contains": lambda: scene.contains(origins),
             "intersect_all": lambda: scene.intersect_all(origins, directions, max_hits=2)}
    for name, call in calls.items():
        call()
        counted.clear()
        moved.clear()
        call()
        if name == "intersect_all":
            # INTERSECT_ALL_ON_DEVICE's launches; a wait for the count
            # pass's counters and the hits' total (int64), then the fill's
            assert dict(counted) == {"launch": INTERSECT_ALL_ON_DEVICE, "sync": 2}, name
            assert 0 < sum(moved) <= 2 * one_wait + 8, name
        else:
            assert dict(counted) == {"launch": 2, "sync": 1}, name
            assert sum(moved) == one_wait, name


def test_a_scalar_goes_up_only_when_it_changes(suite_device, monkeypatch):
    """tmin, tmax and the mask given once for every ray live in buffers of
    the query's engine: a call sends those whose value changed since the
    last (one number each), and answers with the new value."""
    scene = hlbvh_cl.Scene([grid_mesh(6)], device=suite_device)
    origins = np.tile(np.float32([0.5, 0.5, -1.0]), (50, 1))
    directions = np.tile(np.float32([0.0, 0.0, 1.0]), (50, 1))
    sent = []  # bytes of each copy from the host
    original = cl.enqueue_copy
    monkeypatch.setattr(cl, "enqueue_copy", lambda queue, dest, src, **kw: (
        sent.append(src.nbytes if isinstance(src, np.ndarray) else 0),
        original(queue, dest, src, **kw))[1])
    far = scene.intersect(origins, directions, tmax=5.0)
    assert (far.prim_id >= 0).all()
    sent.clear()
    assert (scene.intersect(origins, directions, tmax=5.0).t == far.t).all()
    again = sum(sent)
    sent.clear()
    near = scene.intersect(origins, directions, tmax=0.5)  # the grid lies at t = 1
    assert (near.prim_id == -1).all()
    assert sum(sent) == again + 4  # tmax, once


def test_a_build_waits_for_one_batch_of_reads_and_for_its_last_kernel(suite_device, counted):
    mesh = grid_mesh(20)
    hlbvh_cl.Scene([mesh], device=suite_device)  # programs built
    counted.clear()
    hlbvh_cl.Scene([mesh], device=suite_device)
    assert 0 < counted["launch"] <= BUILD_LAUNCHES
    assert counted["sync"] == BUILD_SYNCS


@pytest.mark.parametrize("builder", ["hlbvh", "lbvh"])
def test_a_tree_deeper_than_the_first_round_of_levels_reads_once_more(suite_device, counted,
                                                                      builder):
    """A mesh on a wide ground plane makes a wide tree one level deeper
    than the first round of wide levels (widen.py): one more read, for the
    next round, and the tree is whole (tests/build/test_widen.py checks it)."""
    meshes = deep_scene()
    hlbvh_cl.Scene(meshes, device=suite_device, builder=builder)  # programs built
    counted.clear()
    scene = hlbvh_cl.Scene(meshes, device=suite_device, builder=builder)
    first_round = widen.EXTRA_LEVELS + -(-(scene.stats.triangles - 2).bit_length() // 3)
    assert scene.stats.wide_depth > first_round
    assert counted["sync"] == BUILD_SYNCS + 1


def test_a_query_call_starts_its_launches_where_the_last_call_ended(suite_device, monkeypatch):
    """The engine paces launches by what the last one took (Ctrl-C waits for
    those in flight); a call of the same kernel starts from the last call's
    pace rather than the query's FIRST_LAUNCH, so that a scene whose items
    cost much pays that first launch once."""
    from hlbvh_cl.query.rays import RayQuery
    scene = hlbvh_cl.Scene([grid_mesh(6)], device=suite_device)
    rng = np.random.default_rng(2)
    origins = rng.uniform(-0.5, 1.5, (3000, 3)).astype(np.float32)
    directions = np.tile(np.float32([0.05, 0.02, 1.0]), (3000, 1))
    firsts = []

    class Recorded(engine.LaunchSizes):
        def __init__(self, most, first=None):
            firsts.append(first)
            super().__init__(most, first)
    monkeypatch.setattr(engine, "LaunchSizes", Recorded)
    with scene.borrow() as built:
        query = RayQuery(built.runtime)
        query.intersect(built.tree, origins, directions)
        paced = query.engine.paced["closest"]
        query.intersect(built.tree, origins, directions)
        query.occluded(built.tree, origins, directions)
    assert firsts == [None, paced, None]  # occluded is paced on its own
    assert paced >= 1
