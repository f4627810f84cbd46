"""One runtime per device and profile: its context, profiling queue,
program cache and buffer pool, and how kernels are built and launched.
"""
from __future__ import annotations

import _thread
import logging
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pyopencl as cl

from ..core.paths import kernel_dir
from .discovery import Device, check_process, select_device
from .hugepages import advise_huge_pages
from .pool import BufferPool
from .profile import Profile, Variant

class KernelBuildError(RuntimeError):
    """An OpenCL program failed to compile; the message carries the build log."""


class DeviceMemoryError(MemoryError):
    """A scene or batch needs more memory than the device allows."""


class Runtime:
    """Context, profiling queue and program cache of one device.

    Programs are built once per (kernel root, file, defines) and kept for the
    life of the runtime; pyopencl's on-disk binary cache (and PoCL's own) keep
    them across runs.
    """

    def __init__(self, device: Device, profile: Profile | None = None,
                 variant: Variant | None = None):
        """``profile`` defaults to the device's; ``variant`` to the one its
        probe chose (KernelBuildError when none passed)."""
        self.device = device
        self.profile = profile = profile or device.profile
        if variant is None:
            from . import probe
            found = probe.verdict(device, profile)
            if found.chosen is None:
                raise KernelBuildError(f"no kernel variant runs on {device}: {found.problem}")
            for failed, reason in found.failures:
                probe.warn_fallback(device, failed, reason, found.chosen)
            variant = found.chosen
        #: how every program of this runtime is compiled (hlbvh_cl.device.profile)
        self.variant = variant
        self.context = cl.Context([device.cl_device])
        self.queue = cl.CommandQueue(self.context,
                                     properties=cl.command_queue_properties.PROFILING_ENABLE)
        #: the folder whose kernel sources this runtime builds: the package's
        #: (hlbvh_cl.core.paths.kernel_dir); ``python -m bench.ab --in-process``
        #: points it at each checkout's kernels in turn, in one process
        self.kernel_root: Path = kernel_dir()
        self._programs: dict[tuple, cl.Program] = {}
        self._kernels: dict[tuple, cl.Kernel] = {}
        self._group_limits: dict[int, tuple] = {}  # see largest_group
        self._signatures: dict[int, tuple] = {}  # see run
        self._lock = threading.Lock()
        self._launch_lock = threading.Lock()
        #: seconds wait() polls on the calling thread first (SPIN_SECONDS on
        #: a GPU, 0 on other devices: see wait())
        self.spin_seconds = SPIN_SECONDS if self.device.type == "gpu" else 0.0
        self.build_lock = threading.RLock()  # builds share the pool and the sorter
        #: device buffers the build stages take and recycle (hlbvh_cl.device.pool)
        #: whether allocate() asks for 2 MiB pages (hlbvh_cl.device.hugepages): on
        #: PoCL's CPU device, where it measured faster; Intel's CPU runtime
        #: built fresh scenes slower with them
        self.huge_pages = not profile.gpu and device.id.startswith("pocl")
        self._advice_queue: cl.CommandQueue | None = None  # see allocate
        self.pool = BufferPool(self.allocate)

    def allocate(self, nbytes: int) -> cl.Buffer:
        """A fresh READ_WRITE buffer; with huge_pages a large one is backed by
        2 MiB pages (the tree's random reads miss the TLB less)."""
        buffer = cl.Buffer(self.context, cl.mem_flags.READ_WRITE, nbytes)
        if self.huge_pages:
            # A queue of its own, so that mapping the fresh buffer does not
            # wait for the work queued so far.
            if self._advice_queue is None:
                self._advice_queue = cl.CommandQueue(self.context)
            advise_huge_pages(self._advice_queue, buffer)
        return buffer

    def program(self, filename: str, **defines) -> cl.Program:
        key = (self.kernel_root, filename, tuple(sorted(defines.items())))
        with self._lock:
            program = self._programs.get(key)
            if program is None:
                program = self._build(key[0], filename, defines)
                self._programs[key] = program
        return program

    def kernel(self, filename: str, name: str, **defines) -> cl.Kernel:
        """A kernel object, cached; callers set all its arguments before each enqueue."""
        key = (self.kernel_root, filename, name, tuple(sorted(defines.items())))
        kernel = self._kernels.get(key)
        if kernel is None:
            try:
                kernel = cl.Kernel(self.program(filename, **defines), name)
            except cl.Error as error:  # e.g. a driver that built the program but cannot run it
                raise KernelBuildError(f"{filename}: kernel {name} cannot be created on "
                                       f"{self.device}: {error}") from None
            # threads that made it at once all get the first one stored
            kernel = self._kernels.setdefault(key, kernel)
        return kernel

    def packet_variant(self, packet_size: int) -> Variant:
        """This runtime's variant with ``packet_size`` rays per work-item if
        its probe passes; else the next smaller packet that does (down to the
        safest variant), with a one-line warning."""
        from . import probe
        from .profile import PACKET_SIZES, SAFEST
        wanted = self.variant.with_packet(packet_size)
        smaller = [self.variant.with_packet(p) for p in sorted(PACKET_SIZES, reverse=True)
                   if p < packet_size]
        reason = None
        for variant in [wanted, *smaller, SAFEST]:
            failed = None if variant == self.variant else probe.usable(self.device, self.profile,
                                                                       variant)
            if failed is None:
                if variant != wanted:
                    probe.warn_fallback(self.device, wanted, reason, variant)
                return variant
            reason = reason or failed
        raise KernelBuildError(f"no kernel variant with at most {packet_size} rays per "
                               f"work-item runs on {self.device}: {reason}")

    @property
    def handoff_defines(self) -> dict:
        """ACQUIRE_RELEASE for the bottom-up kernels (kernels/build/handoff.h):
        1 where the device's compiler offers acquire-release atomics; their
        programs are then built for that OpenCL C version."""
        return {"ACQUIRE_RELEASE": int(self.device.acquire_release_std is not None)}

    @property
    def prefetch_defines(self) -> dict:
        """PREFETCH=1 for kernels that ask for cache lines ahead with
        __builtin_prefetch (the CPU profile)."""
        return {} if self.profile.gpu else {"PREFETCH": 1}

    @property
    def group_size(self) -> int:
        """Default work-group size.  256 rather than 64: PoCL pays a fixed
        cost per work-group, and 64 measured much slower on a plain copy."""
        return min(256, self.device.cl_device.max_work_group_size)

    def largest_group(self, kernel: cl.Kernel) -> int:
        """The most work-items per group ``kernel`` may run with here, as a
        power of two (CL_KERNEL_WORK_GROUP_SIZE, cached): a kernel heavy in
        private memory or registers may allow fewer than the device's
        maximum, and a launch past it fails (CL_INVALID_WORK_GROUP_SIZE)."""
        # keyed by address, with the kernel kept alive beside its limit: a
        # freed kernel's address could be reused by another kernel
        known = self._group_limits.get(kernel.int_ptr)
        if known is None:
            allowed = kernel.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE,
                                                 self.device.cl_device)
            known = self._group_limits[kernel.int_ptr] = (
                kernel, 1 << (max(1, allowed).bit_length() - 1))
        return known[1]

    def run(self, kernel: cl.Kernel, work_items: int | tuple[int, int], *args, wait_for=None,
            local_size: int | None = None, offset: int = 0) -> cl.Event:
        """Enqueue ``kernel`` over ``work_items`` items, or a 2D range
        (columns, rows) in work-groups of one row; columns are rounded up to
        whole work-groups, and every kernel checks its own bound.  Python
        ints and floats become int32 and float32 arguments.  ``local_size``
        (by default group_size) is capped at what the kernel allows
        (largest_group); the kernels take any group size.  ``offset`` is a
        1D range's global offset: its work-items' get_global_id start there."""
        check_process()
        local_size = min(local_size or self.group_size, self.largest_group(kernel))
        values = [_kernel_arg(a) for a in args]
        # The scalar arguments' types, declared to pyopencl once per kernel:
        # its typed set_args packs them all in one go, where it handles each
        # undeclared numpy scalar on its own (most of a launch's host time,
        # which a GPU's wavefront renders wait on)
        # (dtype.str, not the dtype: numpy's dtype == None holds for float64)
        signature = tuple(v.dtype.str if isinstance(v, np.generic) else None for v in values)
        columns, rows = work_items if isinstance(work_items, tuple) else (work_items, None)
        size = max(1, -(-columns // local_size)) * local_size
        global_size, group = ((size,), (local_size,)) if rows is None else \
            ((size, max(1, rows)), (local_size, 1))
        # Kernel objects are shared by every scene and thread of this runtime:
        # setting the arguments and enqueueing must not interleave.
        with self._launch_lock:
            # keyed by address, with the kernel kept alive (see largest_group)
            if self._signatures.get(kernel.int_ptr, (None, None))[1] != signature:
                kernel.set_scalar_arg_dtypes([v.dtype if isinstance(v, np.generic) else None
                                              for v in values])
                self._signatures[kernel.int_ptr] = (kernel, signature)
            kernel.set_args(*values)
            return cl.enqueue_nd_range_kernel(self.queue, kernel, global_size, group,
                                              global_work_offset=(offset,) if offset else None,
                                              wait_for=wait_for)

    def wait(self, events) -> None:
        """Waits for ``events`` so that Ctrl-C still raises at once.

        cl.wait_for_events blocks in C, where Python cannot raise
        KeyboardInterrupt, so a thread started for the wait blocks there and
        this one waits on a plain lock that the thread releases when done,
        which a signal interrupts.  Blocking (not polling) matters: a CPU
        runtime may run work on the waiting thread (Intel's does), and
        polling would leave it a core short.  A GPU's work runs elsewhere, so
        there the calling thread first polls for spin_seconds: a small call's
        results come within them, without the two thread switches of the
        hand-off.  Only C locks, taken by one call each (_thread): a
        ThreadPoolExecutor's future waits on a threading.Condition, whose
        Python code Ctrl-C can stop between its lock's release and
        re-acquire; after a few thousand interrupts the executor deadlocked,
        and every later wait on the device hung."""
        check_process()
        events = [event for event in events if event is not None]
        if not events:
            return
        if self.device.simulator:
            # Oclgrind's uninitialised-value check crashed (19.10) when
            # another thread than the caller waited on its kernels.
            cl.wait_for_events(events)
            return
        if self.spin_seconds > 0 and polled(events, self.spin_seconds):
            return
        done = _thread.allocate_lock()
        done.acquire()
        failed: list[BaseException] = []

        def block() -> None:
            try:
                cl.wait_for_events(events)
            except BaseException as error:  # an event that failed: raised by the caller
                failed.append(error)
            finally:
                done.release()
        _thread.start_new_thread(block, ())
        while not done.acquire(timeout=0.25):  # a signal raises here
            pass
        if failed:
            raise failed[0]

    def _build(self, folder: Path, filename: str, defines: dict) -> cl.Program:
        defines = {**self.variant.defines, **defines}
        source = (folder / filename).read_text()
        std = (self.device.acquire_release_std if defines.get("ACQUIRE_RELEASE") else None) or "CL1.2"
        options = ["-I", str(folder), f"-cl-std={std}"]
        exact = cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT
        if self.device.cl_device.single_fp_config & exact:
            # OpenCL C lets float division be off by 2.5 ulp and sqrt by 3
            # (OpenCL C spec., "Relative Error as ULPs"), and NVIDIA's default
            # uses that freedom: rays made on the device (camera.cl), and
            # every division, then differ from the host's numpy mirrors and
            # from the CPU runtimes
            options.append("-cl-fp32-correctly-rounded-divide-sqrt")
        options += [f"-D{name}={_define_value(value)}" for name, value in sorted(defines.items())]
        try:
            return quiet_build(cl.Program(self.context, source), options, self.device.cl_device)
        except cl.RuntimeError as error:
            raise KernelBuildError(f"{filename} failed to build for {self.device}:\n{error}") from None

    def fits_one_buffer(self, *arrays: np.ndarray) -> bool:
        """Whether the device allows one buffer over each array
        (CL_DEVICE_MAX_MEM_ALLOC_SIZE): where it does not, a query takes
        the array's rows in chunks instead."""
        return all(array.nbytes <= self.device.max_mem_alloc_size for array in arrays)

    def check_allocation(self, what: str, buffers: dict[str, int]) -> None:
        """Raise DeviceMemoryError before allocating if ``buffers`` cannot fit."""
        d = self.device
        total = sum(buffers.values())
        biggest_name, biggest = max(buffers.items(), key=lambda item: item[1])
        if biggest > d.max_mem_alloc_size:
            raise DeviceMemoryError(
                f"{what}: buffer '{biggest_name}' needs {biggest / 2**20:.0f} MiB but {d.id} allows "
                f"{d.max_mem_alloc_size / 2**20:.0f} MiB per allocation (CL_DEVICE_MAX_MEM_ALLOC_SIZE)")
        if total > d.global_mem_size:
            raise DeviceMemoryError(
                f"{what} needs {total / 2**20:.0f} MiB of device memory but {d.id} has "
                f"{d.global_mem_size / 2**20:.0f} MiB (CL_DEVICE_GLOBAL_MEM_SIZE)")


#: Serialises quiet_build between runtimes: catch_warnings saves and
#: restores the process's one filter list, which overlapping uses (two
#: devices building at once) would leave changed.
_quiet_build_lock = threading.Lock()

_log = logging.getLogger("hlbvh_cl")


#: How long Runtime.wait polls a GPU's events before it blocks (see wait).
SPIN_SECONDS = 0.002


def polled(events: list, seconds: float) -> bool:
    """Whether every event completed within ``seconds`` of polling; their
    queues are flushed first, as only a blocking wait would."""
    queues = {event.command_queue.int_ptr: event.command_queue for event in events
              if event.command_queue is not None}  # a user event has none
    for queue in queues.values():
        queue.flush()
    complete = cl.command_execution_status.COMPLETE
    deadline = time.perf_counter() + seconds
    while True:
        status = [event.command_execution_status for event in events]
        if any(code < 0 for code in status):  # failed: the blocking wait raises for it
            return False
        if all(code == complete for code in status):
            return True
        if time.perf_counter() > deadline:
            return False


def quiet_build(program: cl.Program, options: list, device: cl.Device) -> cl.Program:
    """program.build(options) without pyopencl's CompilerWarning, which any
    non-empty build log raises: Intel's runtime logs every build and PoCL its
    vector-ABI notes, noise for a library's user (a failed build raises with
    its log).  The log goes to the "hlbvh_cl" logger at DEBUG instead (but
    for a build pyopencl's binary cache serves: its log is the load's).
    Python's catch_warnings is process-wide: a filter another thread adds
    while a program builds (a scene's first query) is dropped with it."""
    with _quiet_build_lock, warnings.catch_warnings():
        warnings.simplefilter("ignore", cl.CompilerWarning)
        program = program.build(options=options)
    if _log.isEnabledFor(logging.DEBUG):
        log = program.get_build_info(device, cl.program_build_info.LOG).strip()
        if log:
            _log.debug("build log (%s):\n%s", " ".join(options), log)
    return program


def _kernel_arg(value):
    if isinstance(value, bool):
        return np.int32(value)
    if isinstance(value, int):
        return np.int32(value)
    if isinstance(value, float):
        return np.float32(value)
    return value


def _define_value(value) -> str:
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, float):
        return f"{value!r}f"
    return str(value)


_runtimes: dict[tuple[str, str], Runtime] = {}
_runtimes_lock = threading.Lock()


def runtime(device=None) -> Runtime:
    """The shared runtime of a device (selected as in :func:`select_device`)
    in its current profile."""
    chosen = select_device(device)
    check_process()
    key = (chosen.id, chosen.profile.name)
    with _runtimes_lock:
        rt = _runtimes.get(key)
        if rt is None:
            rt = Runtime(chosen)
            _runtimes[key] = rt
    return rt


def forget_runtimes() -> None:
    """Forgets this process's shared runtimes: runtime() makes a fresh one
    for each device from here on, which builds its programs anew (scenes
    made before keep the runtimes they hold)."""
    with _runtimes_lock:
        _runtimes.clear()


def install_runtime(device: Device, profile: Profile, variant: Variant) -> Runtime:
    """A runtime with a fixed variant, shared as runtime(device) (the probe's
    child runs its candidate this way)."""
    check_process()
    rt = Runtime(device, profile, variant)
    with _runtimes_lock:
        _runtimes[(device.id, profile.name)] = rt
    return rt


def event_ms(events) -> float:
    """Device time covered by profiled events, in milliseconds."""
    events = [e for e in events if e is not None]
    if not events:
        return 0.0
    return sum(e.profile.end - e.profile.start for e in events) * 1e-6


def fold_events(pending: dict, spent: dict) -> None:
    """Each list of events in ``pending``: its finished ones' device time
    added to ``spent`` under the same key (event_ms) and dropped, so that a
    long run keeps only the events still in flight."""
    complete = cl.command_execution_status.COMPLETE
    for key, found in pending.items():
        done, running = [], []
        for event in found:
            if event is not None:
                (done if event.command_execution_status == complete else running).append(event)
        spent[key] = spent.get(key, 0.0) + event_ms(done)
        found[:] = running

