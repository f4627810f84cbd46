"""Stable LSD radix sort of (key, value) pairs on the device (kernels/parallel/radix_sort.cl).

Keys are uint32 or uint64 (Morton codes), values uint32 (primitive ids).
Each pass sorts one digit of at most RADIX_BITS bits: per-work-group digit
histograms, an exclusive scan of the digit-major histogram matrix
(hlbvh_cl/parallel/scan.py), then a stable scatter.  Only ceil(key_bits / RADIX_BITS)
passes run: bits above ``key_bits`` cost nothing.
"""
from __future__ import annotations

import math
import threading
import weakref

import numpy as np
import pyopencl as cl

from ..device.runtime import Runtime, runtime
from .scan import exclusive_scan

KERNEL_FILE = "parallel/radix_sort.cl"

# Bits per pass: 8 beat 4, 6, 10 and 11 on PoCL 3.1 and Intel's CPU runtime
# (3M pairs, 30- and 63-bit keys).
DEFAULT_RADIX_BITS = 8
MAX_RADIX_BITS = 12
# Work-items per group and groups per compute unit.  On a CPU a work-group
# runs on one core, so a few groups per core balance the load; each
# work-item needs 4 << RADIX_BITS bytes of local memory for its counts.
CPU_GROUP_SIZE = 4
CPU_GROUPS_PER_COMPUTE_UNIT = 4
GPU_GROUP_SIZE = 64
GPU_GROUPS_PER_COMPUTE_UNIT = 8
# Fewer pairs per work-item than this and a smaller grid is faster.
MIN_PER_ITEM = 256
# Sub-tile bounds are uint arithmetic on the device: n + work-items must fit.
MAX_COUNT = 2**31

_KEY_TYPES = {np.dtype(np.uint32): "uint", np.dtype(np.uint64): "ulong"}


def _key_dtype(dtype, what: str) -> np.dtype:
    try:
        dtype = np.dtype(dtype)
    except TypeError:
        raise TypeError(f"{what} must be numpy.uint32 or numpy.uint64, got {dtype!r}") from None
    if dtype not in _KEY_TYPES:
        raise TypeError(f"{what} must be uint32 or uint64, got {dtype}")
    return dtype


def _count(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {type(value).__name__}")
    return int(value)


class RadixSorter:
    """Sorts (key, value) pairs of device buffers; keeps its scratch buffers.

    One sorter per key dtype and runtime; its scratch buffers (a ping-pong
    pair for keys and values, and the histogram matrix) grow on demand and
    are reused by later calls.  Calls must all go through ``rt.queue``
    (in order), which is what makes that reuse safe.
    """

    def __init__(self, rt: Runtime, key_dtype=np.uint32, *, radix_bits: int = DEFAULT_RADIX_BITS):
        self.rt = rt
        self.key_dtype = _key_dtype(key_dtype, "key_dtype")
        radix_bits = _count(radix_bits, "radix_bits")
        if not 1 <= radix_bits <= MAX_RADIX_BITS:
            raise ValueError(f"radix_bits={radix_bits} is out of range; expected 1..{MAX_RADIX_BITS}")
        self.radix_bits = radix_bits
        self.radix = 1 << radix_bits
        self.max_key_bits = 8 * self.key_dtype.itemsize
        self.group_size = self._choose_group_size()
        d = rt.device
        per_cu = GPU_GROUPS_PER_COMPUTE_UNIT if rt.profile.gpu else CPU_GROUPS_PER_COMPUTE_UNIT
        self.max_groups = max(1, per_cu * d.compute_units)
        # +1: exclusive_scan writes the total after the last entry.
        self._histogram = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE,
                                    4 * (self.radix * self.max_groups + 1))
        self._scratch_keys: cl.Buffer | None = None
        self._scratch_values: cl.Buffer | None = None
        self._scratch_capacity = 0

    @property
    def scratch_keys(self) -> cl.Buffer | None:
        """The scratch buffer of keys (the ping-pong's other half, which
        holds the result after an odd number of passes): None before the
        first sort of more than one pair; it grows only for a sort of more
        pairs than it holds, and later sorts reuse it."""
        return self._scratch_keys

    def _kernel(self, name: str, group_size: int) -> cl.Kernel:
        return self.rt.kernel(KERNEL_FILE, name, KEY_TYPE=_KEY_TYPES[self.key_dtype],
                              RADIX_BITS=self.radix_bits, SORT_GROUP_SIZE=group_size)

    def _choose_group_size(self) -> int:
        """Largest power of two within the device's local memory and work-group limits."""
        d = self.rt.device
        cl_device = d.cl_device
        per_item_bytes = 4 * self.radix
        limit = min(GPU_GROUP_SIZE if self.rt.profile.gpu else CPU_GROUP_SIZE,
                    cl_device.max_work_group_size, cl_device.local_mem_size // per_item_bytes)
        if limit < 1:
            raise ValueError(f"radix_bits={self.radix_bits} needs {per_item_bytes} bytes of local "
                             f"memory per work-item but {d.id} has {cl_device.local_mem_size}")
        group_size = 1 << (limit.bit_length() - 1)
        # The compiled kernels may allow fewer work-items (registers, local memory).
        while group_size > 1:
            kernels = [self._kernel(name, group_size) for name in ("radix_histogram", "radix_scatter")]
            fits = all(
                k.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, cl_device) >= group_size
                and k.get_work_group_info(cl.kernel_work_group_info.LOCAL_MEM_SIZE, cl_device)
                <= cl_device.local_mem_size
                for k in kernels)
            if fits:
                break
            group_size //= 2
        return group_size

    def release_scratch(self) -> None:
        """Lets the scratch pair go (freed once nothing else holds it); the
        next sort of more than one pair allocates it again.  For a caller
        that keeps nothing of its build but the result (a compact Scene):
        the pair is as large as the largest sort so far.  Only between
        sorts, with the queue's work on them done (Runtime.build_lock)."""
        self._scratch_keys = self._scratch_values = None
        self._scratch_capacity = 0

    def _ensure_scratch(self, n: int) -> None:
        if n <= self._scratch_capacity:
            return
        key_bytes = n * self.key_dtype.itemsize
        self.rt.check_allocation(f"radix sort of {n} pairs",
                                 {"scratch keys": key_bytes, "scratch values": 4 * n})
        # Drop the old pair first so both are never held at once.
        self._scratch_keys = self._scratch_values = None
        self._scratch_keys = self.rt.allocate(key_bytes)
        self._scratch_values = self.rt.allocate(4 * n)
        self._scratch_capacity = n

    def _check_sort_args(self, keys, values, n, key_bits) -> tuple[int, int]:
        for name, buf in (("keys", keys), ("values", values)):
            if not isinstance(buf, cl.Buffer):
                raise TypeError(f"RadixSorter.sort: {name} must be a pyopencl.Buffer, "
                                f"got {type(buf).__name__}")
        n = _count(n, "n")
        if not 0 <= n < MAX_COUNT:
            raise ValueError(f"RadixSorter.sort: n={n} is out of range; expected 0 <= n < {MAX_COUNT}")
        key_bits = _count(key_bits, "key_bits")
        if not 1 <= key_bits <= self.max_key_bits:
            raise ValueError(f"RadixSorter.sort: key_bits={key_bits} is out of range for "
                             f"{self.key_dtype} keys; expected 1..{self.max_key_bits}")
        itemsize = self.key_dtype.itemsize
        if keys.size < n * itemsize:
            raise ValueError(f"RadixSorter.sort: keys holds {keys.size} bytes but n={n} "
                             f"{self.key_dtype} keys need {n * itemsize}")
        if values.size < 4 * n:
            raise ValueError(f"RadixSorter.sort: values holds {values.size} bytes but n={n} "
                             f"uint32 values need {4 * n}")
        if keys == values:
            raise ValueError("RadixSorter.sort: keys and values are the same buffer")
        for name, buf in (("keys", keys), ("values", values)):
            if buf in (self._scratch_keys, self._scratch_values):
                raise ValueError(f"RadixSorter.sort: {name} is this sorter's own scratch buffer "
                                 "(a previous result); copy it to another buffer first")
        return n, key_bits

    def pass_digits(self, key_bits: int) -> list[tuple[int, int]]:
        """(shift, width) of each pass: as few passes as radix_bits allows, with
        the bits spread evenly over them (30 bits -> 8, 8, 7, 7).  On the CPU
        devices measured, a 5- or 6-bit pass cost twice an 8-bit one."""
        passes = -(-key_bits // self.radix_bits)
        widths = [key_bits // passes + (p < key_bits % passes) for p in range(passes)]
        return [(sum(widths[:p]), width) for p, width in enumerate(widths)]

    def sort(self, keys: cl.Buffer, values: cl.Buffer, n: int, key_bits: int,
             wait_for=None) -> tuple[cl.Buffer, cl.Buffer, list[cl.Event]]:
        """Sorts ``keys[0:n]`` with ``values[0:n]``, stably, by the low ``key_bits`` of each key.

        Bits above ``key_bits`` do not take part in the order (they are
        carried along).  Returns ``(sorted_keys, sorted_values, events)``: the
        result lives in the inputs after an even number of passes
        (ceil(key_bits / radix_bits)) and in this sorter's scratch buffers
        after an odd number.  Either way the inputs are clobbered (they are
        the other half of the ping-pong), and a result held in scratch is
        valid only until this sorter's next call.
        """
        n, key_bits = self._check_sort_args(keys, values, n, key_bits)
        if n <= 1:
            return keys, values, []
        self._ensure_scratch(n)

        wg = self.group_size
        groups = max(1, min(self.max_groups, n // (wg * MIN_PER_ITEM)))
        per_item = math.ceil(n / (groups * wg))
        groups = math.ceil(n / (wg * per_item))  # no empty groups
        global_size, local_size = (groups * wg,), (wg,)
        histogram = self._kernel("radix_histogram", wg)
        scatter = self._kernel("radix_scatter", wg)
        queue = self.rt.queue

        source = (keys, values)
        target = (self._scratch_keys, self._scratch_values)
        events: list[cl.Event] = []
        wait = wait_for
        for shift, width in self.pass_digits(key_bits):
            digit_mask = np.uint32((1 << width) - 1)
            counted = histogram(queue, global_size, local_size, source[0], np.uint32(n),
                                np.uint32(per_item), np.uint32(shift), digit_mask,
                                self._histogram, wait_for=wait)
            scanned = exclusive_scan(self.rt, self._histogram, self.radix * groups,
                                     wait_for=[counted])
            moved = scatter(queue, global_size, local_size, source[0], source[1], np.uint32(n),
                            np.uint32(per_item), np.uint32(shift), digit_mask, self._histogram,
                            target[0], target[1], wait_for=scanned[-1:])
            events += [counted, *scanned, moved]
            wait = [moved]
            source, target = target, source
        return source[0], source[1], events


_sorters: "weakref.WeakKeyDictionary[Runtime, dict]" = weakref.WeakKeyDictionary()
_sorters_lock = threading.Lock()


def sorter(rt: Runtime, key_dtype: np.dtype) -> RadixSorter:
    """The runtime's one sorter for ``key_dtype`` keys: builds and the
    queries' orders share its scratch buffers (under Runtime.build_lock)."""
    key_dtype = np.dtype(key_dtype)
    with _sorters_lock:
        per_dtype = _sorters.setdefault(rt, {})
        found = per_dtype.get(key_dtype)
        if found is None:
            found = per_dtype[key_dtype] = RadixSorter(rt, key_dtype)
    return found


def _check_array(array, name: str, dtypes: tuple) -> np.ndarray:
    if not isinstance(array, np.ndarray):
        raise TypeError(f"sort_pairs: {name} must be a numpy.ndarray, got {type(array).__name__}")
    if array.ndim != 1:
        raise ValueError(f"sort_pairs: {name} must be 1-D, got shape {array.shape}")
    if array.dtype not in dtypes:
        expected = " or ".join(str(np.dtype(d)) for d in dtypes)
        raise TypeError(f"sort_pairs: {name} has dtype {array.dtype}; expected {expected}")
    return np.ascontiguousarray(array)


def sort_pairs(keys: np.ndarray, values: np.ndarray | None = None, *, key_bits: int | None = None,
               device=None) -> tuple[np.ndarray, np.ndarray]:
    """Stable sort of host arrays on the device; returns (sorted_keys, sorted_values).

    ``values`` defaults to ``arange(n, dtype=uint32)``, so the second result
    is then the stable argsort of the keys.  Only the low ``key_bits`` of each
    key (default: all) decide the order.
    """
    keys = _check_array(keys, "keys", (np.uint32, np.uint64))
    n = keys.shape[0]
    if values is None:
        values = np.arange(n, dtype=np.uint32)
    values = _check_array(values, "values", (np.uint32,))
    if values.shape[0] != n:
        raise ValueError(f"sort_pairs: values has {values.shape[0]} elements but keys has {n}")
    max_bits = 8 * keys.dtype.itemsize
    if key_bits is None:
        key_bits = max_bits
    key_bits = _count(key_bits, "key_bits")
    if not 1 <= key_bits <= max_bits:
        raise ValueError(f"sort_pairs: key_bits={key_bits} is out of range for {keys.dtype} keys; "
                         f"expected 1..{max_bits}")
    if n >= MAX_COUNT:
        raise ValueError(f"sort_pairs: keys has {n} elements; at most {MAX_COUNT - 1} are supported")
    if n == 0:
        return keys.copy(), values.copy()

    rt = runtime(device)
    rt.check_allocation(f"radix sort of {n} pairs", {"keys": keys.nbytes, "values": values.nbytes})
    pairs = sorter(rt, keys.dtype)
    flags = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
    keys_buf = cl.Buffer(rt.context, flags, hostbuf=keys)
    values_buf = cl.Buffer(rt.context, flags, hostbuf=values)
    sorted_keys_buf, sorted_values_buf, events = pairs.sort(keys_buf, values_buf, n, key_bits)
    sorted_keys = np.empty_like(keys)
    sorted_values = np.empty_like(values)
    cl.enqueue_copy(rt.queue, sorted_keys, sorted_keys_buf, wait_for=events[-1:])
    cl.enqueue_copy(rt.queue, sorted_values, sorted_values_buf, wait_for=events[-1:]).wait()
    return sorted_keys, sorted_values
