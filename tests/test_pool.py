"""Buffer recycling between builds (hlbvh_cl.pool): the pool's own rules, and
a rebuild that reuses the old tree's buffers still answers like a fresh scene."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hlbvh_cl import Mesh, Scene
from hlbvh_cl.device import runtime
from hlbvh_cl.pool import KEEP_BUILDS, BufferPool

MESH_DIR = Path(__file__).resolve().parent.parent / "scenes" / "meshes"


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


def test_scratch_comes_back_after_an_error(pool):
    with pytest.raises(RuntimeError):
        with pool.build():
            taken = pool.take(512)
            raise RuntimeError("a stage failed")
    assert pool.take(512) is taken


def test_rebuild_reuses_the_old_tree_and_answers_as_a_fresh_scene():
    mesh = Mesh.load(MESH_DIR / "bunny_small.ply")
    scene = Scene([mesh])
    old = scene._tree
    old_buffers = {old.nodes.int_ptr, old.triangles.int_ptr, old.wide.nodes.int_ptr}
    scene.rebuild()
    new = scene._tree
    assert old.released and not new.released
    assert {new.nodes.int_ptr, new.triangles.int_ptr, new.wide.nodes.int_ptr} == old_buffers

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
    old = scene._tree
    scene.rebuild()
    query = scene._ray_query()
    with pytest.raises(ValueError, match="released when its Scene rebuilt"):
        query.intersect(old, np.zeros((1, 3)), np.ones((1, 3)))


def test_a_scene_that_goes_away_takes_its_scratch_with_it():
    import gc
    scene = Scene([Mesh.load(MESH_DIR / "knight.ply")])
    pool = scene._runtime.pool
    scene.rebuild()
    assert pool.free_bytes > 0  # the last build's scratch, kept for the next rebuild
    del scene
    gc.collect()
    assert pool.free_bytes == 0
