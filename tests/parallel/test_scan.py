"""hlbvh_cl.parallel.scan.exclusive_scan and exclusive_scan_counted against numpy.cumsum."""
import numpy as np
import pyopencl as cl
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hlbvh_cl.parallel import scan
from hlbvh_cl.device.runtime import runtime

GUARD = 7  # elements after buf[n] that the scan must leave alone


@pytest.fixture(scope="module")
def rt():
    return runtime()


def scan_on_device(rt, data: np.ndarray) -> tuple[np.ndarray, list]:
    """Scans data[:-GUARD-1] in a buffer of len(data); returns the whole buffer afterwards."""
    n = data.size - GUARD - 1
    buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=data)
    events = scan.exclusive_scan(rt, buf, n)
    out = np.empty_like(data)
    cl.enqueue_copy(rt.queue, out, buf, wait_for=events).wait()
    return out, events


def check_scan(rt, values: np.ndarray) -> None:
    n = values.size
    rng = np.random.default_rng(n)
    # buf[n] holds garbage that must be ignored; the guard must survive.
    tail = rng.integers(0, 2**32, GUARD + 1, dtype=np.uint32)
    data = np.concatenate([values.astype(np.uint32), tail])
    out, events = scan_on_device(rt, data)

    expected = np.zeros(n + 1, dtype=np.uint32)
    np.cumsum(values, dtype=np.uint32, out=expected[1:])  # wraps mod 2**32 like the device
    np.testing.assert_array_equal(out[:n + 1], expected)
    np.testing.assert_array_equal(out[n + 1:], tail[1:])
    assert events and all(isinstance(e, cl.Event) for e in events)


def interesting_sizes(rt) -> list[int]:
    """Sizes around every block boundary the plan can produce on this device."""
    plan = scan.plan(rt)
    wg = plan.group_size
    single_group = wg * scan.MIN_PER_ITEM  # above this, tiles + tile-sum scan + rescan
    bounds = {wg, single_group, 2 * single_group, plan.max_tiles * single_group}
    sizes = {0, 1, 2, 3, 100}
    for b in bounds:
        sizes |= {b - 1, b, b + 1}
    return sorted(s for s in sizes if s >= 0)


def test_block_boundaries(rt):
    rng = np.random.default_rng(0)
    for n in interesting_sizes(rt):
        check_scan(rt, rng.integers(0, 1000, n, dtype=np.uint32))


def test_n_zero_writes_zero_total(rt):
    check_scan(rt, np.zeros(0, dtype=np.uint32))


def test_large(rt):
    rng = np.random.default_rng(1)
    check_scan(rt, rng.integers(0, 64, 5_000_003, dtype=np.uint32))


def test_wraps_modulo_2_pow_32(rt):
    rng = np.random.default_rng(2)
    check_scan(rt, rng.integers(2**31, 2**32, 100_000, dtype=np.uint32))


def test_scratch_is_reused(rt):
    scan.exclusive_scan(rt, cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 4 * 200_001), 200_000)
    before = scan.plan(rt).tile_sums
    check_scan(rt, np.ones(300_000, dtype=np.uint32))
    assert scan.plan(rt).tile_sums is before


@settings(max_examples=40, deadline=None)
@given(n=st.integers(0, 40_000), high=st.sampled_from([1, 2, 1000, 2**32]), seed=st.integers(0, 2**32 - 1))
def test_matches_cumsum(rt, n, high, seed):
    values = np.random.default_rng(seed).integers(0, high, n, dtype=np.uint64).astype(np.uint32)
    check_scan(rt, values)


def test_bad_inputs(rt):
    buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 4 * 10)
    with pytest.raises(ValueError, match="n=10 needs n\\+1"):
        scan.exclusive_scan(rt, buf, 10)
    with pytest.raises(ValueError, match="n=-1"):
        scan.exclusive_scan(rt, buf, -1)
    with pytest.raises(TypeError, match="n must be an integer"):
        scan.exclusive_scan(rt, buf, 2.0)
    with pytest.raises(TypeError, match="buf must be a pyopencl.Buffer"):
        scan.exclusive_scan(rt, np.zeros(10, np.uint32), 5)


def counted_scan(rt, values: np.ndarray, most: int) -> None:
    """exclusive_scan_counted of values (n of them) with the count on the
    device at counts[3], launched for ``most``: the scan and total as
    numpy's, and the elements after buf[n] left alone."""
    n = values.size
    rng = np.random.default_rng(n + most)
    data = np.concatenate([values.astype(np.uint32),
                           rng.integers(0, 2**32, most - n + 1 + GUARD, dtype=np.uint32)])
    flags = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
    buf = cl.Buffer(rt.context, flags, hostbuf=data)
    counts = cl.Buffer(rt.context, flags, hostbuf=np.array([7, 7, 7, n, 7], np.uint32))
    events = scan.exclusive_scan_counted(rt, buf, counts, 3, most)
    out = np.empty_like(data)
    cl.enqueue_copy(rt.queue, out, buf, wait_for=events).wait()
    expected = np.zeros(n + 1, dtype=np.uint32)
    np.cumsum(values, dtype=np.uint32, out=expected[1:])
    np.testing.assert_array_equal(out[:n + 1], expected)
    np.testing.assert_array_equal(out[n + 1:], data[n + 1:])


def test_counted_scan_of_a_length_only_the_device_knows(rt):
    """Single-group and tiled launches (sized for `most`), with n from 0 to
    most: the work-items share the actual n between them."""
    rng = np.random.default_rng(3)
    plan = scan.plan(rt)
    tiled = 3 * plan.group_size * scan.MIN_PER_ITEM
    for most in (1, 100, tiled):
        for n in sorted({0, 1, most // 3, most - 1, most}):
            counted_scan(rt, rng.integers(0, 1000, n, dtype=np.uint32), most)
    counted_scan(rt, rng.integers(2**31, 2**32, 100_000, dtype=np.uint32), 300_000)


def test_counted_scan_bad_inputs(rt):
    buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 4 * 10)
    counts = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 4 * 2)
    with pytest.raises(ValueError, match="n=10 needs n\\+1"):
        scan.exclusive_scan_counted(rt, buf, counts, 0, 10)
    with pytest.raises(ValueError, match="at=2 is not an element of counts"):
        scan.exclusive_scan_counted(rt, buf, counts, 2, 5)
