"""Result memory recycling (hlbvh_cl.results.ResultPool): a block is handed out
again only once nothing outside the pool refers to it, so results the caller
holds are never overwritten by a later query."""
from __future__ import annotations

import gc

import numpy as np

import hlbvh_cl
from hlbvh_cl.results import MIN_POOLED_BYTES, ResultPool
from shapes import grid_mesh

BIG = MIN_POOLED_BYTES // 4  # float32 elements that make a pooled request


def fields():
    return {"a": ((BIG,), np.float32), "b": ((BIG, 3), np.int32)}


def test_views_are_laid_out_apart_and_aligned():
    arrays = ResultPool().arrays(fields())
    a, b = arrays["a"], arrays["b"]
    assert a.shape == (BIG,) and a.dtype == np.float32
    assert b.shape == (BIG, 3) and b.dtype == np.int32
    assert a.ctypes.data % 64 == 0 and b.ctypes.data % 64 == 0
    a[:] = 1.5
    b[:] = -7
    assert np.all(a == 1.5) and np.all(b == -7)  # no overlap


def test_a_block_is_reused_only_once_dropped():
    pool = ResultPool()
    first = pool.arrays(fields())
    first["a"][:] = 1.0
    second = pool.arrays(fields())
    assert not np.shares_memory(first["a"], second["a"])
    second["a"][:] = 2.0
    assert np.all(first["a"] == 1.0)
    address = first["a"].ctypes.data
    del first
    gc.collect()
    third = pool.arrays(fields())
    assert third["a"].ctypes.data == address  # recycled


def test_a_kept_view_keeps_its_block():
    pool = ResultPool()
    kept = pool.arrays(fields())["b"][10:20]  # a slice of one field only
    kept[:] = 42
    others = [pool.arrays(fields()) for _ in range(4)]
    for arrays in others:
        arrays["b"][:] = 0
        assert not np.shares_memory(arrays["b"], kept)
    assert np.all(kept == 42)
    del others
    gc.collect()
    assert len(pool._free) <= pool.keep


def test_mixed_sizes_and_held_results():
    """Requests of two sizes, the older results of each held a while."""
    pool = ResultPool()
    small = {"a": ((BIG // 2,), np.uint8)}
    held = []
    for k in range(8):
        arrays = pool.arrays(fields() if k % 2 else small)
        for array in arrays.values():
            array[...] = k
        held.append(arrays)
        if len(held) > 3:
            held.pop(0)
        for j, older in enumerate(held):
            value = k - len(held) + 1 + j
            assert all(np.all(array == value) for array in older.values())


def test_small_results_are_plain_arrays():
    arrays = ResultPool().arrays({"a": ((16,), np.float32)})
    assert arrays["a"].flags.owndata


def test_held_hits_survive_later_queries():
    scene = hlbvh_cl.Scene([grid_mesh()])
    lo, hi = scene.tree.bounds_lo, scene.tree.bounds_hi
    count = MIN_POOLED_BYTES // 8
    def rays(seed):
        r = np.random.default_rng(seed)
        targets = lo + r.random((count, 3)) * (hi - lo)
        origins = targets + np.array([0.0, 0.0, 2.0]) * float(np.max(hi - lo)) + 0.01
        return origins.astype(np.float32), (targets - origins).astype(np.float32)
    o1, d1 = rays(1)
    held = scene.intersect(o1, d1)
    copy = {name: getattr(held, name).copy() for name in ("t", "prim_id", "normal")}
    for seed in range(2, 6):
        o, d = rays(seed)
        scene.intersect(o, d)
        scene.occluded(o, d)
    for name, values in copy.items():
        np.testing.assert_array_equal(getattr(held, name), values)
    assert held.hit.mean() > 0.5
