"""Memory reuse: the buffer pool that recycles scratch and trees between
builds (hlbvh_cl.device.pool), the result pool that lends result arrays
(hlbvh_cl.query.results), huge-page advice for large buffers (hlbvh_cl.device.hugepages),
and the ray query's own buffers: reused, grown, sized from device memory,
used in place or written in place.
"""
from __future__ import annotations

import gc
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest

import hlbvh_cl
from hlbvh_cl import Mesh
from hlbvh_cl import Scene
from hlbvh_cl.query import rays as query_module
from hlbvh_cl.device.runtime import runtime
from hlbvh_cl.device.hugepages import HUGE_PAGE, MIN_ADVISED_BYTES, advise_huge_pages
from hlbvh_cl.device.pool import KEEP_BUILDS, BufferPool
from hlbvh_cl.query.rays import RayQuery
from hlbvh_cl.query.results import MIN_POOLED_BYTES, ResultPool, starts_on_page
import built
from ray_cases import assert_matches_oracle, random_rays, scene_case
from shapes import grid_mesh
import places


# -- the buffer pool: scratch and trees between builds ----------------------------

MESH_DIR = places.MESHES


@pytest.fixture
def pool():
    return BufferPool(runtime().allocate)


def test_take_reuses_a_given_buffer_of_the_same_size_only(pool):
    a = pool.take(1000)
    pool.give(a)
    assert pool.take(1000) is a
    pool.give(a)
    b = pool.take(1004)
    assert b is not a and b.size == 1004
    assert pool.take(0).size == 4  # never an empty buffer


def test_a_build_returns_its_scratch_and_keeps_its_results(pool):
    stale = pool.take(48)
    pool.give(stale)
    with pool.build():
        scratch, result = pool.take(64), pool.take(128)
        with pool.build():  # nested scopes join the outer one
            inner = pool.take(256)
        assert pool.free_bytes == 48  # nothing comes back before the outer scope ends
        pool.keep(result)
    # the scratch came back, and the unused 48 stay: 48 + 64 + 256 is within
    # the budget (KEEP_BUILDS x the 448 bytes this build took)
    assert pool.free_bytes == 48 + 64 + 256
    assert pool.take(64) is scratch and pool.take(256) is inner and pool.take(48) is stale
    assert pool.take(128) is not result


def _build(pool, sizes):
    with pool.build():
        return [pool.take(size) for size in sizes]


def test_scenes_rebuilt_in_turn_each_find_their_buffers(pool):
    first_a, first_b = _build(pool, [1000, 3000]), _build(pool, [2000, 500])
    for _ in range(3):
        again_a, again_b = _build(pool, [1000, 3000]), _build(pool, [2000, 500])
        assert all(x is y for x, y in zip(again_a, first_a))
        assert all(x is y for x, y in zip(again_b, first_b))


def test_free_bytes_stay_within_budget_oldest_dropped_first(pool):
    big = _build(pool, [1000])[0]  # budget: KEEP_BUILDS x 1000 bytes
    assert KEEP_BUILDS * 1000 < 1000 + 700 + 600
    old, new = pool.take(700), pool.take(600)
    pool.give(old)
    pool.give(new)
    _build(pool, [])  # the end of a build evicts: 1000 + 700 + 600 is over the budget
    assert pool.free_bytes <= KEEP_BUILDS * 1000
    assert pool.take(600) is new  # the most recently returned stays
    assert pool.take(1000) is not big  # the one returned longest ago went first


def test_a_buffer_given_twice_is_free_once(pool):
    a = pool.take(64)
    pool.give(a)
    pool.give(a)
    assert pool.free_bytes == 64
    assert pool.take(64) is a
    assert pool.take(64) is not a


def test_a_spare_buffer_is_the_smallest_that_holds_the_bytes_and_is_handed_out_once(pool):
    with pool.build():
        small, large, other = pool.take(100), pool.take(400), pool.take(200)
        spare = [large, small, other]
        assert pool.take_spare(spare, 150) is other  # the smallest of those that fit
        assert spare == [large, small]
        assert pool.take_spare(spare, 401).size == 401  # none fits: a new one
        assert pool.take_spare(spare, 50) is small and pool.take_spare(spare, 50) is large
        assert spare == [] and pool.take_spare(spare, 50) not in (small, large, other)
    # the spare buffers came back once each, with the new ones
    assert pool.free_bytes == 100 + 400 + 200 + 401 + 50


def test_scratch_comes_back_after_an_error(pool):
    with pytest.raises(RuntimeError):
        with pool.build():
            taken = pool.take(512)
            raise RuntimeError("a stage failed")
    assert pool.take(512) is taken


def test_rebuild_reuses_the_old_tree_and_answers_as_a_fresh_scene():
    # an earlier test's Scene, collected mid-test, would clear the runtime's
    # pool (its finalizer) and with it the old tree this rebuild reuses
    gc.collect()
    mesh = Mesh.load(MESH_DIR / "bunny_small.ply")
    scene = Scene([mesh])
    old = built.tree(scene)
    old_buffers = {old.nodes.int_ptr, old.triangles.int_ptr, old.refs.int_ptr}
    scene.rebuild()
    new = built.tree(scene)
    assert old.released and not new.released
    assert {new.nodes.int_ptr, new.triangles.int_ptr, new.refs.int_ptr} == old_buffers

    rng = np.random.default_rng(5)
    center = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
    origins = center + rng.normal(size=(2000, 3)).astype(np.float32) * 0.3
    directions = rng.normal(size=(2000, 3)).astype(np.float32)
    fresh = Scene([mesh])
    a, b = scene.intersect(origins, directions), fresh.intersect(origins, directions)
    for field in ("t", "prim_id", "geom_id", "u", "v", "normal"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert 0 < a.hit.mean() < 1
    np.testing.assert_array_equal(scene.occluded(origins, directions),
                                  fresh.occluded(origins, directions))


def test_a_released_tree_cannot_be_queried():
    scene = Scene([Mesh.load(MESH_DIR / "knight.ply")])
    old = built.tree(scene)
    scene.rebuild()
    query = RayQuery(built.runtime(scene))
    with pytest.raises(ValueError, match="released when its Scene rebuilt"):
        query.intersect(old, np.zeros((1, 3)), np.ones((1, 3)))


def test_a_scene_that_goes_away_takes_its_scratch_with_it():
    import gc
    scene = Scene([Mesh.load(MESH_DIR / "knight.ply")])
    pool = built.runtime(scene).pool
    scene.rebuild()
    assert pool.free_bytes > 0  # the last build's scratch, kept for the next rebuild
    del scene
    gc.collect()
    assert pool.free_bytes == 0


#: A Scene only the cyclic garbage collector frees, collected while the pool's
#: lock is held in the same thread, as a collection set off by an allocation
#: inside the pool would: its finalizer's clear() must not wait for the lock.
COLLECTED_IN_THE_POOL = """
import gc, sys
import hlbvh_cl
scene = hlbvh_cl.Scene([hlbvh_cl.Mesh.load(sys.argv[1])])
scene.cycle = scene
with scene.borrow() as lent:
    pool = lent.runtime.pool
del lent
scene.rebuild()
held = pool.free_bytes
del scene
with pool._locked():
    gc.collect()
    print(held, pool.free_bytes)
print(pool.free_bytes)
"""


def test_a_scene_collected_inside_the_pool_empties_it_without_a_deadlock():
    done = subprocess.run([sys.executable, "-c", COLLECTED_IN_THE_POOL, str(MESH_DIR / "knight.ply")],
                          capture_output=True, text=True, stdin=subprocess.DEVNULL, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    (held, during), (after,) = (line.split() for line in done.stdout.splitlines())
    # kept while the section runs, dropped as it lets go of the lock
    assert int(held) > 0 and int(during) == int(held) and int(after) == 0, done.stdout


# -- the result pool: result arrays lent and lent again ---------------------------

BIG = MIN_POOLED_BYTES // 4  # float32 elements that make a pooled request


def test_lent_arrays_are_aligned_and_apart():
    pool = ResultPool()
    a, b = pool.empty(BIG, np.float32), pool.empty((BIG, 3), np.int32)
    assert a.shape == (BIG,) and a.dtype == np.float32
    assert b.shape == (BIG, 3) and b.dtype == np.int32
    assert a.ctypes.data % 64 == 0 and b.ctypes.data % 64 == 0
    a[:] = 1.5
    b[:] = -7
    assert np.all(a == 1.5) and np.all(b == -7)  # no overlap


def test_a_block_is_lent_again_only_once_dropped():
    pool = ResultPool()
    first = pool.empty(BIG, np.float32)
    first[:] = 1.0
    second = pool.empty(BIG, np.float32)
    assert not np.shares_memory(first, second)
    second[:] = 2.0
    assert np.all(first == 1.0)
    address = first.ctypes.data
    del first
    gc.collect()
    assert pool.empty(BIG, np.float32).ctypes.data == address  # recycled


def test_a_kept_view_keeps_its_block():
    pool = ResultPool()
    kept = pool.empty((BIG, 3), np.int32)[10:20]  # a slice only
    kept[:] = 42
    others = [pool.empty((BIG, 3), np.int32) for _ in range(4)]
    for array in others:
        array[:] = 0
        assert not np.shares_memory(array, kept)
    del others
    gc.collect()
    for _ in range(3):  # the others' blocks come back; kept's never does
        again = pool.empty((BIG, 3), np.int32)
        assert not np.shares_memory(again, kept)
        again[:] = 0
    assert np.all(kept == 42)


def test_blocks_of_several_sizes_and_held_results():
    """Requests of two pooled sizes, the older results of each held a while."""
    pool = ResultPool(keep=3)
    shapes = [((BIG,), np.float32), ((BIG, 3), np.float32)]
    held = []
    for k in range(12):
        shape, dtype = shapes[k % 2]
        array = pool.empty(shape, dtype)
        array[...] = k
        held.append((k, array))
        if len(held) > 3:
            held.pop(0)
        for value, older in held:
            assert np.all(older == value)
    assert len(pool.held) <= pool.keep


def test_a_block_of_a_size_no_longer_asked_for_is_let_go():
    """Results of varying length (intersect_all's) would otherwise keep up to
    `keep` blocks of sizes that are never lent again."""
    pool = ResultPool(keep=3)
    big = pool.empty(4 * BIG, np.float32)
    del big
    gc.collect()
    held = [pool.empty(BIG, np.float32) for _ in range(3)]  # the big size falls out
    assert len(held) == 3 and [len(block) for block in pool.held] == []


def test_small_results_are_plain_arrays():
    assert ResultPool().empty(16, np.float32).flags.owndata


def test_held_hits_survive_later_queries():
    scene = hlbvh_cl.Scene([grid_mesh()])
    tree = built.tree(scene)
    lo, hi = tree.bounds_lo, tree.bounds_hi
    count = MIN_POOLED_BYTES // 4 + 10

    def rays(seed):
        r = np.random.default_rng(seed)
        targets = lo + r.random((count, 3)) * (hi - lo)
        origins = targets + np.array([0.0, 0.0, 2.0]) * float(np.max(hi - lo)) + 0.01
        return origins.astype(np.float32), (targets - origins).astype(np.float32)

    held = scene.intersect(*rays(1))
    held_occluded = scene.occluded(*rays(1))
    copy = {name: getattr(held, name).copy() for name in ("t", "prim_id", "normal")}
    for seed in range(2, 6):
        scene.intersect(*rays(seed))
        scene.occluded(*rays(seed))
    for name, values in copy.items():
        np.testing.assert_array_equal(getattr(held, name), values)
    np.testing.assert_array_equal(held_occluded, held.hit)
    assert held.hit.mean() > 0.5


# -- huge pages ---------------------------------------------------------------------

THP_MODE = Path("/sys/kernel/mm/transparent_hugepage/enabled")


def _thp_on_request() -> bool:
    """THP set to "always" or "madvise" (the active mode is in brackets)."""
    try:
        text = THP_MODE.read_text()
    except OSError:
        return False
    return "[always]" in text or "[madvise]" in text


def _huge_kib_at(address: int) -> int:
    """AnonHugePages of the mapping of this process that holds `address`."""
    inside = False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        fields = line.split()
        if "-" in fields[0] and len(fields) >= 5:
            low, high = (int(x, 16) for x in fields[0].split("-"))
            inside = low <= address < high
        elif inside and fields[0] == "AnonHugePages:":
            return int(fields[1])
    return 0


def test_small_buffers_are_left_alone():
    rt = runtime()
    buffer = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, MIN_ADVISED_BYTES - 4)
    assert advise_huge_pages(rt.queue, buffer) is False


#: Run in a child process: in a long-lived process the allocator may serve the
#: buffer from heap memory that earlier work already touched with small pages,
#: where advice only takes effect when khugepaged gets round to it.
ADVISED_BUFFER = """
import sys
import numpy as np
import pyopencl as cl
sys.path[:0] = sys.argv[1:3]
from test_memory import _huge_kib_at
from hlbvh_cl.device.runtime import runtime
from hlbvh_cl.device.hugepages import HUGE_PAGE, MIN_ADVISED_BYTES
rt = runtime()
if not rt.huge_pages:
    print("not advised", rt.device.id)
    sys.exit(0)
n = 4 * MIN_ADVISED_BYTES
buffer = rt.allocate(n)  # advised on creation
values = np.arange(n // 4, dtype=np.uint32) * np.uint32(2654435761)
cl.enqueue_copy(rt.queue, buffer, values)
back = np.empty_like(values)
cl.enqueue_copy(rt.queue, back, buffer)
assert np.array_equal(back, values), "data changed"
mapped, _ = cl.enqueue_map_buffer(rt.queue, buffer, cl.map_flags.READ, 0, (n,), np.uint8,
                                  is_blocking=True)
inside = -(-mapped.ctypes.data // HUGE_PAGE) * HUGE_PAGE
print("huge KiB", _huge_kib_at(inside))
mapped.base.release(rt.queue)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or not _thp_on_request(),
                    reason="needs Linux with transparent huge pages on request")
def test_an_advised_buffer_is_backed_by_huge_pages_and_keeps_its_data():
    done = subprocess.run([sys.executable, "-c", ADVISED_BUFFER, str(places.TESTS),
                           str(places.SUPPORT)],
                          capture_output=True, text=True, cwd=places.REPO, stdin=subprocess.DEVNULL, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    result = done.stdout.split()
    if result[:2] == ["not", "advised"]:
        pytest.skip(f"{result[2]} buffers are not advised (Runtime.huge_pages)")
    assert result[:2] == ["huge", "KiB"] and int(result[2]) >= HUGE_PAGE // 1024, done.stdout


# -- the ray query's buffers ---------------------------------------------------------

@pytest.mark.parametrize("staging", [False, True], ids=["device-buffers", "staging"])
def test_buffers_are_reused_and_only_grow(staging):
    """Where the kernels cannot use the numpy arrays in place: device
    buffers, or (on request) pinned staging buffers and the device buffers
    of each of their sets."""
    case = scene_case("cube")
    q = RayQuery(built.runtime(case.scene))
    q.zero_copy, q.staging = False, staging

    def held() -> dict:
        if not staging:
            return dict(q.engine.reused)
        stage = q.engine.stage
        return {(kind, i, name): buffer
                for kind, sets in (("pinned", stage.pinned), ("device", stage.device))
                for i, held_set in enumerate(sets) for name, buffer in held_set.items()}
    origins, directions = random_rays(case, 300, seed=13)
    q.intersect(built.tree(case.scene), origins, directions)
    buffers = held()
    assert len(buffers) >= (2 * 2 * 10 if staging else 10)  # rays' 2, hits' 8
    q.intersect(built.tree(case.scene), origins[:100], directions[:100])
    q.occluded(built.tree(case.scene), origins[:200], directions[:200])
    now = held()
    assert all(now[name] is buffer for name, buffer in buffers.items())
    q.intersect(built.tree(case.scene), np.repeat(origins, 4, 0), np.repeat(directions, 4, 0))
    now = held()
    grown = {name[-1] if staging else name for name in buffers if now[name] is not buffers[name]}
    kept = {name[-1] if staging else name for name in buffers if now[name] is buffers[name]}
    assert {"origins", "directions", "t", "normal"} <= grown and not kept & grown


def test_chunk_size_follows_device_memory():
    case = scene_case("cube")
    q = RayQuery(built.runtime(case.scene))
    d = built.runtime(case.scene).device
    buffers = {**query_module.RAY_ARRAYS, **query_module.HIT_ARRAYS,
               **query_module.OCCLUDED_ARRAYS}
    assert q.max_rays_per_launch <= query_module.MAX_RAYS_PER_LAUNCH
    assert q.max_rays_per_launch * max(buffers.values()) <= d.max_mem_alloc_size
    assert q.max_rays_per_launch * sum(buffers.values()) <= d.global_mem_size


@pytest.mark.parametrize("chunk", [None, 1 << 16, 777], ids=["one-launch", "page-chunks", "odd-chunks"])
def test_results_written_in_place_equal_read_back_results(chunk):
    """With device copies of the rays, the kernels may write the results
    straight into the pool's page-aligned result arrays (Intel's CPU runtime
    does by default): the same results as reading them back, also when a
    batch splits into chunks, some of which do not start on a page."""
    case = scene_case("knight")
    count = MIN_POOLED_BYTES // 4 + 1000
    origins, directions = random_rays(case, count, seed=16)
    copied = RayQuery(built.runtime(case.scene))
    copied.zero_copy, copied.outputs_in_place = False, False
    written = RayQuery(built.runtime(case.scene), max_rays_per_launch=chunk)
    written.zero_copy, written.outputs_in_place = False, True
    expected = copied.intersect(built.tree(case.scene), origins, directions)
    got = written.intersect(built.tree(case.scene), origins, directions)
    for field in ("t", "prim_id", "geom_id", "u", "v", "normal"):
        assert starts_on_page(getattr(got, field))
        np.testing.assert_array_equal(getattr(got, field), getattr(expected, field))
    assert 0 < got.hit.mean() < 1
    np.testing.assert_array_equal(written.occluded(built.tree(case.scene), origins, directions),
                                  copied.occluded(built.tree(case.scene), origins, directions))


def test_in_place_queries_take_any_array_layout():
    """Read-only, unaligned and shared rays in place give what device copies
    give; results large enough to come from the ResultPool survive a later
    query."""
    case = scene_case("knight")
    count = MIN_POOLED_BYTES // 4 + 1000
    origins, directions = random_rays(case, count, seed=15)
    in_place = RayQuery(built.runtime(case.scene))
    in_place.zero_copy = True
    copied = RayQuery(built.runtime(case.scene))
    copied.zero_copy = False
    expected = copied.intersect(built.tree(case.scene), origins, directions)
    raw = np.zeros(origins.nbytes + 5, np.uint8)
    unaligned = raw[1:1 + origins.nbytes].view(np.float32).reshape(origins.shape)  # 1-byte offset
    unaligned[:] = origins
    frozen = directions.copy()
    frozen.flags.writeable = False
    got = in_place.intersect(built.tree(case.scene), unaligned, frozen)
    in_place.intersect(built.tree(case.scene), origins[::-1].copy(), directions[::-1].copy())
    for field in ("t", "prim_id", "geom_id", "u", "v", "normal"):
        np.testing.assert_array_equal(getattr(got, field), getattr(expected, field))
    # one array as both origins and directions, and two overlapping views
    points = np.ascontiguousarray(origins[:500])
    np.testing.assert_array_equal(in_place.intersect(built.tree(case.scene), points, points).t,
                                  copied.intersect(built.tree(case.scene), points, points.copy()).t)
    rows = np.ascontiguousarray(origins[:750])
    overlapping = in_place.intersect(built.tree(case.scene), rows[:500], rows[250:])
    assert_matches_oracle(case, overlapping, rows[:500].copy(), rows[250:].copy())
