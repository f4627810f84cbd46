"""Buffer recycling between builds (hlbvh_cl.pool): the pool's own rules, and
a rebuild that reuses the old tree's buffers still answers like a fresh scene."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hlbvh_cl import Mesh, Scene
from hlbvh_cl.device import runtime
from hlbvh_cl.pool import BufferPool

MESH_DIR = Path(__file__).resolve().parent.parent / "scenes" / "meshes"


@pytest.fixture
def pool():
    return BufferPool(runtime().context)


def test_take_reuses_a_given_buffer_of_the_same_size_only(pool):
    a = pool.take(1000)
    pool.give(a)
    assert pool.take(1000) is a
    pool.give(a)
    b = pool.take(1004)
    assert b is not a and b.size == 1004
    assert pool.take(0).size == 4  # never an empty buffer


def test_a_build_returns_its_scratch_keeps_its_results_and_drops_the_unused(pool):
    stale = pool.take(48)
    pool.give(stale)
    with pool.build():
        scratch, result = pool.take(64), pool.take(128)
        with pool.build():  # nested scopes join the outer one
            inner = pool.take(256)
        assert pool.free_bytes == 48  # nothing comes back before the outer scope ends
        pool.keep(result)
    assert pool.free_bytes == 64 + 256  # the scratch came back; the unused 48 were dropped
    assert pool.take(64) is scratch and pool.take(256) is inner
    assert pool.take(128) is not result


def test_scratch_comes_back_after_an_error(pool):
    with pytest.raises(RuntimeError):
        with pool.build():
            taken = pool.take(512)
            raise RuntimeError("a stage failed")
    assert pool.take(512) is taken


def test_rebuild_reuses_the_old_tree_and_answers_as_a_fresh_scene():
    mesh = Mesh.load(MESH_DIR / "bunny_small.ply")
    scene = Scene([mesh])
    old = scene.tree
    old_buffers = {old.nodes.int_ptr, old.triangles.int_ptr, old.wide.nodes.int_ptr}
    scene.rebuild()
    new = scene.tree
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
    old = scene.tree
    scene.rebuild()
    query = scene._ray_query()
    with pytest.raises(ValueError, match="released when its Scene rebuilt"):
        query.intersect(old, np.zeros((1, 3)), np.ones((1, 3)))


def test_a_scene_that_goes_away_takes_its_scratch_with_it():
    import gc
    scene = Scene([Mesh.load(MESH_DIR / "knight.ply")])
    pool = scene.runtime.pool
    scene.rebuild()
    assert pool.free_bytes > 0  # the last build's scratch, kept for the next rebuild
    del scene
    gc.collect()
    assert pool.free_bytes == 0
