"""Child processes that a tier of the suite runs side by side.

The slow tiers (test_oclgrind.py, test_targets.py) each run their cases in
child processes that are mostly single-threaded (the simulator, a compiler,
another device's pytest).  Run one after another they leave the other cores
idle, so a tier starts all of its selected children at its first test, as
many at once as this process may use cores and the free memory holds (each
tier says how much one child may take), and each test then waits for its
own child's result.
"""
from __future__ import annotations

import os
import subprocess
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path


def usable_cores() -> int:
    """The cores this process may run on (its affinity, where the OS tells)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)


def available_memory() -> int | None:
    """Bytes of memory available to new processes (Linux's MemAvailable), or
    None where the system does not say."""
    try:
        with open("/proc/meminfo") as info:
            for line in info:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def slots(memory_per_child: int) -> int:
    """How many children to run at once: one per usable core, as many as
    the available memory holds at memory_per_child bytes each (at least one)."""
    memory = available_memory()
    fit = usable_cores() if memory is None else memory // memory_per_child
    return max(1, min(usable_cores(), fit))


def package_environment(**variables: str) -> dict:
    """os.environ with `variables`, and PYTHONPATH led by the checkout whose
    hlbvh_cl this process tests, so that a child imports the same package."""
    import hlbvh_cl
    checkout = str(Path(hlbvh_cl.__file__).resolve().parent.parent)
    path = os.pathsep.join([checkout, *filter(None, [os.environ.get("PYTHONPATH")])])
    return {**os.environ, **variables, "PYTHONPATH": path}


def selected_params(request, function) -> list[dict]:
    """The parameters of each test of `function` this session runs (after
    -k, -x, or node ids on the command line), in their order."""
    return [item.callspec.params for item in request.session.items
            if getattr(item, "function", None) is function and hasattr(item, "callspec")]


class Children:
    """Runs commands as child processes, at most `slots` at a time (see
    slots()), in the order given; result(key) waits for one and gives its
    CompletedProcess (stdout and stderr as text), or raises its
    subprocess.TimeoutExpired.  close() kills the running children and
    drops the waiting ones."""

    def __init__(self, jobs: dict, slots: int):
        self._lock = threading.Lock()
        self._running: set[subprocess.Popen] = set()
        self._closed = False
        self._pool = ThreadPoolExecutor(max_workers=slots, thread_name_prefix="test-child")
        self._futures: dict[object, Future] = {
            key: self._pool.submit(self._run, **job) for key, job in jobs.items()}

    def result(self, key) -> subprocess.CompletedProcess:
        return self._futures[key].result()

    def _run(self, args, timeout: float, **popen) -> subprocess.CompletedProcess:
        with self._lock:
            if self._closed:
                raise RuntimeError("closed before this child started")
            child = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     stdin=subprocess.DEVNULL, text=True, **popen)
            self._running.add(child)
        try:
            try:
                stdout, stderr = child.communicate(timeout=timeout)
            except subprocess.TimeoutExpired:
                child.kill()
                stdout, stderr = child.communicate()
                raise subprocess.TimeoutExpired(args, timeout, stdout, stderr) from None
        finally:
            with self._lock:
                self._running.discard(child)
        return subprocess.CompletedProcess(args, child.returncode, stdout, stderr)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            for child in self._running:
                child.kill()
        self._pool.shutdown(wait=True, cancel_futures=True)
