"""Result memory recycling (hlbvh_cl.results.ResultPool): a block is lent again
only once the array lent from it and every view of it are gone, so results
the caller holds are never overwritten by a later query."""
from __future__ import annotations

import gc

import numpy as np

import hlbvh_cl
from hlbvh_cl.results import MIN_POOLED_BYTES, ResultPool
from shapes import grid_mesh

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
    assert len(pool._free) <= pool.keep


def test_small_results_are_plain_arrays():
    assert ResultPool().empty(16, np.float32).flags.owndata


def test_held_hits_survive_later_queries():
    scene = hlbvh_cl.Scene([grid_mesh()])
    lo, hi = scene._tree.bounds_lo, scene._tree.bounds_hi
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
