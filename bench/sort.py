"""Benchmark of hlbvh_cl's radix sort against pyopencl.algorithm.RadixSort and numpy.

    python bench/sort.py [--n 3000000] [--repeats 5] [--device ID]

For every OpenCL device (or the one given) it sorts n random (key, index)
pairs: 30-bit uint32 keys (HLBVH's Morton codes) and 63-bit uint64 keys.
Device timings are wall time between two queue.finish() calls, after one
warm-up, with the upload excluded; numpy times argsort(kind="stable") plus
the gather of the sorted keys, which is the same output.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

try:
    import hlbvh_cl  # noqa: F401
except ImportError:  # run from a checkout without installing
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import pyopencl as cl  # noqa: E402
import pyopencl.array as cl_array  # noqa: E402

from hlbvh_cl.device import devices, event_ms, runtime  # noqa: E402
from hlbvh_cl.sort import RadixSorter  # noqa: E402

CASES = (("uint32 30-bit", np.uint32, 30), ("uint64 63-bit", np.uint64, 63))


def _summary(seconds: list[float]) -> dict:
    return {"median": statistics.median(seconds), "min": min(seconds), "max": max(seconds)}


def _time_ours(rt, keys: np.ndarray, key_bits: int, repeats: int) -> tuple[dict, float, bool]:
    """Our sort on device buffers; the pristine input is copied back before each run."""
    queue, n = rt.queue, keys.size
    flags = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
    pristine_keys = cl.Buffer(rt.context, flags, hostbuf=keys)
    pristine_values = cl.Buffer(rt.context, flags, hostbuf=np.arange(n, dtype=np.uint32))
    work_keys = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, keys.nbytes)
    work_values = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 4 * n)
    sorter = RadixSorter(rt, keys.dtype)
    seconds, kernel_ms = [], []
    for run in range(repeats + 1):  # run 0 warms up (build, scratch allocation)
        cl.enqueue_copy(queue, work_keys, pristine_keys)
        cl.enqueue_copy(queue, work_values, pristine_values)
        queue.finish()
        start = time.perf_counter()
        _, sorted_values, events = sorter.sort(work_keys, work_values, n, key_bits)
        queue.finish()
        if run:
            seconds.append(time.perf_counter() - start)
            kernel_ms.append(event_ms(events))
    order = np.empty(n, np.uint32)
    cl.enqueue_copy(queue, order, sorted_values).wait()
    correct = np.array_equal(order, np.argsort(keys, kind="stable"))
    return _summary(seconds), statistics.median(kernel_ms), correct


def _time_pyopencl(rt, keys: np.ndarray, key_bits: int, repeats: int) -> dict:
    from pyopencl.algorithm import RadixSort  # needs mako

    ctype = "uint" if keys.dtype == np.uint32 else "ulong"
    sort = RadixSort(rt.context, f"{ctype} *keys, uint *values", key_expr="keys[i]",
                     sort_arg_names=["keys", "values"], key_dtype=keys.dtype)
    queue = rt.queue
    keys_array = cl_array.to_device(queue, keys)
    values_array = cl_array.to_device(queue, np.arange(keys.size, dtype=np.uint32))
    seconds = []
    for run in range(repeats + 1):
        queue.finish()
        start = time.perf_counter()
        sort(keys_array, values_array, key_bits=key_bits, queue=queue)
        queue.finish()
        if run:
            seconds.append(time.perf_counter() - start)
    return _summary(seconds)


def _time_numpy(keys: np.ndarray, repeats: int) -> dict:
    seconds = []
    for run in range(repeats + 1):
        start = time.perf_counter()
        order = np.argsort(keys, kind="stable")
        keys[order]
        if run:
            seconds.append(time.perf_counter() - start)
    return _summary(seconds)


def bench_sort(device=None, n: int = 3_000_000, repeats: int = 5, *,
               pyopencl_uint64: bool = False) -> dict:
    """Times our sort, pyopencl's RadixSort and numpy on the same random keys.

    Returns {"device", "n", "repeats", "cases": {name: {"ours", "pyopencl",
    "numpy" (each median/min/max seconds, pyopencl None when skipped),
    "ours_kernel_ms", "correct", "speedup_vs_pyopencl", "speedup_vs_numpy"}}}
    with speedups as ratios of medians.  pyopencl's 2-bit sort is skipped for
    uint64 keys unless pyopencl_uint64 (32 passes: many seconds).
    """
    rt = runtime(device)
    rng = np.random.default_rng(2024)
    cases = {}
    for name, dtype, key_bits in CASES:
        keys = rng.integers(0, 1 << key_bits, n, dtype=dtype)
        ours, kernel_ms, correct = _time_ours(rt, keys, key_bits, repeats)
        peer = (_time_pyopencl(rt, keys, key_bits, repeats)
                if dtype == np.uint32 or pyopencl_uint64 else None)
        numpy_times = _time_numpy(keys, repeats)
        cases[name] = {
            "ours": ours, "pyopencl": peer, "numpy": numpy_times,
            "ours_kernel_ms": kernel_ms, "correct": correct,
            "speedup_vs_pyopencl": peer["median"] / ours["median"] if peer else None,
            "speedup_vs_numpy": numpy_times["median"] / ours["median"],
        }
    return {"device": rt.device.id, "n": n, "repeats": repeats, "cases": cases}


def _format(result: dict) -> str:
    def cell(times):
        if times is None:
            return f"{'skipped':>22}"
        return f"{times['median'] * 1e3:8.1f} ({times['min'] * 1e3:.0f}-{times['max'] * 1e3:.0f})"

    lines = [f"{result['device']}: n={result['n']:,}, median (min-max) ms of {result['repeats']} runs; "
             f"kernels = our summed kernel time (profiling events)",
             f"  {'keys':14} {'ours':>22} {'pyopencl RadixSort':>22} {'numpy stable':>22}"
             f" {'x pyopencl':>10} {'x numpy':>8} {'kernels':>8} {'correct':>7}"]
    for name, case in result["cases"].items():
        vs_peer = case["speedup_vs_pyopencl"]
        lines.append(f"  {name:14} {cell(case['ours']):>22} {cell(case['pyopencl']):>22} "
                     f"{cell(case['numpy']):>22} {(f'{vs_peer:.1f}' if vs_peer else '-'):>10} "
                     f"{case['speedup_vs_numpy']:8.1f} {case['ours_kernel_ms']:8.1f} "
                     f"{str(case['correct']):>7}")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=3_000_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--device", help="one device id (default: every device)")
    parser.add_argument("--pyopencl-uint64", action="store_true",
                        help="also time pyopencl's RadixSort on the 63-bit keys (slow)")
    args = parser.parse_args(argv)
    targets = [args.device] if args.device else [d.id for d in devices()]
    for device_id in targets:
        try:
            result = bench_sort(device_id, args.n, args.repeats, pyopencl_uint64=args.pyopencl_uint64)
        except Exception as error:  # one broken device must not hide the others
            first_line = str(error).strip().splitlines()
            print(f"{device_id}: failed: {type(error).__name__}: {' | '.join(first_line[:3])}")
            continue
        print(_format(result), flush=True)


if __name__ == "__main__":
    main()
