"""hlbvh_cl.parallel.radix_sort against numpy.argsort(kind="stable")."""
import numpy as np
import pyopencl as cl
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hlbvh_cl.device.runtime import runtime
from hlbvh_cl.parallel.radix_sort import RadixSorter, sort_pairs


@pytest.fixture(scope="module")
def rt():
    return runtime()


def expected_order(keys: np.ndarray, key_bits: int) -> np.ndarray:
    mask = keys.dtype.type((1 << key_bits) - 1)
    return np.argsort(keys & mask, kind="stable")


def check_sort(keys: np.ndarray, key_bits: int, values: np.ndarray | None = None) -> None:
    order = expected_order(keys, key_bits)
    sorted_keys, sorted_values = sort_pairs(keys, values, key_bits=key_bits)
    expected_values = order.astype(np.uint32) if values is None else values[order]
    np.testing.assert_array_equal(sorted_keys, keys[order])
    np.testing.assert_array_equal(sorted_values, expected_values)
    assert sorted_keys.dtype == keys.dtype and sorted_values.dtype == np.uint32


def random_keys(n: int, dtype, key_bits: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 1 << key_bits, n, dtype=dtype)


@pytest.mark.parametrize("n", [1, 2, 255, 256, 257, 1000, 4097, 1_000_003])
def test_random_uint32_30_bit(n):
    check_sort(random_keys(n, np.uint32, 30, seed=n), 30)


@pytest.mark.parametrize("n", [1, 2, 257, 1_000_003])
def test_random_uint64_63_bit(n):
    check_sort(random_keys(n, np.uint64, 63, seed=n), 63)


def test_full_width_keys():
    check_sort(random_keys(100_001, np.uint32, 32, seed=3), 32)
    check_sort(np.random.default_rng(4).integers(0, 2**64, 100_001, dtype=np.uint64), 64)


def test_one_million_keys():
    check_sort(random_keys(1_000_000, np.uint32, 30, seed=5), 30)


def test_all_equal_keys_keep_input_order():
    check_sort(np.full(300_001, 12345, dtype=np.uint32), 30)
    check_sort(np.full(70_000, 2**62 + 7, dtype=np.uint64), 63)


def test_few_distinct_keys_are_stable():
    check_sort(random_keys(500_000, np.uint32, 3, seed=6), 30)


def test_already_sorted_and_reversed():
    keys = np.sort(random_keys(200_003, np.uint32, 30, seed=7))
    check_sort(keys, 30)
    check_sort(keys[::-1].copy(), 30)
    keys64 = np.sort(random_keys(200_003, np.uint64, 63, seed=8))
    check_sort(keys64, 63)
    check_sort(keys64[::-1], 63)  # a negative-stride view


def test_bits_above_key_bits_do_not_order():
    rng = np.random.default_rng(9)
    keys = rng.integers(0, 2**32, 50_000, dtype=np.uint32)
    for key_bits in (1, 7, 8, 9, 17):
        check_sort(keys, key_bits)


def test_given_values_follow_their_keys():
    rng = np.random.default_rng(10)
    keys = random_keys(123_457, np.uint64, 40, seed=11)
    values = rng.integers(0, 2**32, keys.size, dtype=np.uint32)
    check_sort(keys, 40, values)


def test_empty_input():
    keys, values = sort_pairs(np.zeros(0, np.uint32))
    assert keys.size == 0 and values.size == 0 and values.dtype == np.uint32


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 5000), wide=st.booleans(), key_bits=st.integers(1, 64),
       spread=st.integers(0, 64), seed=st.integers(0, 2**32 - 1))
def test_matches_stable_argsort(n, wide, key_bits, spread, seed):
    dtype = np.uint64 if wide else np.uint32
    key_bits = min(key_bits, 64 if wide else 32)
    spread = min(spread, 64 if wide else 32)  # small spreads give many equal keys
    rng = np.random.default_rng(seed)
    keys = rng.integers(0, 2**spread, n, dtype=np.uint64).astype(dtype)
    check_sort(keys, key_bits)


@pytest.mark.parametrize("radix_bits", [1, 4, 11])
def test_other_radix_widths(rt, radix_bits):
    """Odd widths leave a narrower last pass; results must not depend on the width."""
    keys = random_keys(100_003, np.uint64, 45, seed=radix_bits)
    sorter = RadixSorter(rt, np.uint64, radix_bits=radix_bits)
    assert sorter.group_size * (4 << radix_bits) <= rt.device.cl_device.local_mem_size
    got_keys, got_values = sort_on_device(rt, sorter, keys, np.arange(keys.size, dtype=np.uint32), 45)
    order = expected_order(keys, 45)
    np.testing.assert_array_equal(got_values, order)
    np.testing.assert_array_equal(got_keys, keys[order])


def sort_on_device(rt, sorter, keys, values, key_bits):
    flags = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
    keys_buf = cl.Buffer(rt.context, flags, hostbuf=keys)
    values_buf = cl.Buffer(rt.context, flags, hostbuf=values)
    out_keys, out_values, events = sorter.sort(keys_buf, values_buf, keys.size, key_bits)
    passes = -(-key_bits // sorter.radix_bits)
    # Documented: the result is in the inputs after an even number of passes.
    assert (out_keys == keys_buf) == (passes % 2 == 0)
    got_keys, got_values = np.empty_like(keys), np.empty_like(values)
    cl.enqueue_copy(rt.queue, got_keys, out_keys, wait_for=events)
    cl.enqueue_copy(rt.queue, got_values, out_values, wait_for=events).wait()
    return got_keys, got_values


def test_sorter_reuses_scratch_and_handles_prefixes(rt):
    sorter = RadixSorter(rt, np.uint32)
    big = random_keys(300_000, np.uint32, 30, seed=12)
    sort_on_device(rt, sorter, big, np.arange(big.size, dtype=np.uint32), 30)
    scratch = sorter.scratch_keys
    # A shorter sort in longer buffers: only the first n pairs take part.
    small = random_keys(1000, np.uint32, 30, seed=13)
    padded = np.concatenate([small, np.zeros(500, np.uint32)])
    flags = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
    keys_buf = cl.Buffer(rt.context, flags, hostbuf=padded)
    values_buf = cl.Buffer(rt.context, flags, hostbuf=np.arange(padded.size, dtype=np.uint32))
    out_keys, out_values, events = sorter.sort(keys_buf, values_buf, small.size, 30)
    got = np.empty(small.size, np.uint32)
    cl.enqueue_copy(rt.queue, got, out_values, wait_for=events).wait()
    np.testing.assert_array_equal(got, expected_order(small, 30))
    assert sorter.scratch_keys is scratch


def test_bad_inputs_to_sort_pairs():
    keys = np.arange(10, dtype=np.uint32)
    with pytest.raises(TypeError, match="keys must be a numpy.ndarray"):
        sort_pairs([3, 1, 2])
    with pytest.raises(ValueError, match=r"keys must be 1-D, got shape \(2, 5\)"):
        sort_pairs(keys.reshape(2, 5))
    with pytest.raises(TypeError, match="keys has dtype int64; expected uint32 or uint64"):
        sort_pairs(keys.astype(np.int64))
    with pytest.raises(TypeError, match="keys has dtype float32"):
        sort_pairs(keys.astype(np.float32))
    with pytest.raises(TypeError, match="values has dtype int64; expected uint32"):
        sort_pairs(keys, keys.astype(np.int64))
    with pytest.raises(ValueError, match="values has 9 elements but keys has 10"):
        sort_pairs(keys, keys[:9])
    with pytest.raises(ValueError, match="key_bits=33 is out of range for uint32 keys; expected 1..32"):
        sort_pairs(keys, key_bits=33)
    with pytest.raises(ValueError, match="key_bits=0 is out of range"):
        sort_pairs(keys, key_bits=0)
    with pytest.raises(ValueError, match="key_bits=65 is out of range for uint64 keys"):
        sort_pairs(keys.astype(np.uint64), key_bits=65)
    with pytest.raises(TypeError, match="key_bits must be an integer"):
        sort_pairs(keys, key_bits=8.0)


def test_bad_inputs_to_sorter(rt):
    with pytest.raises(TypeError, match="key_dtype must be uint32 or uint64, got int32"):
        RadixSorter(rt, np.int32)
    with pytest.raises(ValueError, match="radix_bits=0 is out of range"):
        RadixSorter(rt, radix_bits=0)
    sorter = RadixSorter(rt, np.uint64)
    keys = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 8 * 100)
    values = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 4 * 100)
    with pytest.raises(ValueError, match="keys holds 800 bytes but n=101"):
        sorter.sort(keys, values, 101, 63)
    small_values = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 4 * 50)
    with pytest.raises(ValueError, match="values holds 200 bytes but n=100"):
        sorter.sort(keys, small_values, 100, 63)
    with pytest.raises(ValueError, match="key_bits=0 is out of range for uint64 keys"):
        sorter.sort(keys, values, 100, 0)
    with pytest.raises(ValueError, match="n=-1 is out of range"):
        sorter.sort(keys, values, -1, 63)
    with pytest.raises(TypeError, match="values must be a pyopencl.Buffer"):
        sorter.sort(keys, np.zeros(100, np.uint32), 100, 63)
    with pytest.raises(ValueError, match="keys and values are the same buffer"):
        sorter.sort(keys, keys, 100, 63)
    # One pass of 8 bits: the result lands in the scratch, which may not be fed back.
    out_keys, out_values, _ = sorter.sort(keys, values, 100, 8)
    assert out_keys != keys
    with pytest.raises(ValueError, match="keys is this sorter's own scratch buffer"):
        sorter.sort(out_keys, values, 100, 8)
