"""OpenCL devices: discovery and selection.

Device ids are short and stable: ``<vendor>:<k>``, where k counts that
vendor's devices in platform order (``pocl:0``, ``intel:0``, ``nvidia:1``);
the rules a spec follows are hlbvh_cl.device.selection's.  A process forked
after the devices were listed cannot use OpenCL (check_process).
"""
from __future__ import annotations

import ctypes
import dataclasses
import functools
import os
import re
import sys
import threading
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import pyopencl as cl

from ..core.paths import cache_root
from . import selection
from .profile import Profile, profile_name

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
        write_vendors(folder, lib, Path("/etc/OpenCL/vendors"))
        # libintelocl.so finds libimf & co. through its RUNPATH ($ORIGIN);
        # loading it here is a cheap check that the runtime is complete.
        ctypes.CDLL(str(lib.parent / "libimf.so"), mode=ctypes.RTLD_GLOBAL)
    except OSError as error:
        unregistered.append(f"{what} could not be registered: {error}")
        return
    os.environ["OCL_ICD_VENDORS"] = str(folder)


def write_vendors(folder: Path, lib: Path, system: Path) -> None:
    """The vendors folder _register_intel_cpu_runtime points the ICD loader
    at: an .icd naming Intel's ``lib`` and copies of the ``system`` folder's
    .icd files, as they are now: a copy whose runtime was uninstalled since
    is removed (the loader would try its library, gone, in every process)."""
    folder.mkdir(parents=True, exist_ok=True)
    entries = {"intel-cpu-hlbvh_cl.icd": f"{lib}\n"}
    if system.is_dir():
        for icd in system.glob("*.icd"):
            entries[icd.name] = icd.read_text()
    for stale in folder.glob("*.icd"):
        if stale.name not in entries:
            stale.unlink()
    for name, text in entries.items():
        path = folder / name
        if not path.is_file() or path.read_text() != text:
            path.write_text(text)


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
        """The profile this device runs (hlbvh_cl.device.profile; $HLBVH_CL_PROFILE)."""
        return Profile(profile_name(self.type))

    @property
    def verdict(self):
        """What the kernel probe found for this device in its current profile
        (hlbvh_cl.device.probe.Verdict): the variant it runs and why faster ones
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
        (kernels/build/handoff.h)."""
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


class _LockMethod:
    """ProcessLock's __enter__ or __exit__: its RLock's own (C) method, found
    when the with statement looks it up, after check_process where
    ``checked``.  A with statement calls the __enter__ it found and enters
    its block with no Python code between, so Ctrl-C cannot land after the
    acquire and before the block that releases it; a Python __enter__ that
    acquired, then returned, could take it there (about once in 3,000
    interrupts), and left the lock held for ever: every call of the Scene
    from another thread then hung."""

    def __init__(self, name: str, checked: bool):
        self.name, self.checked = name, checked

    def __get__(self, lock, owner=None):
        if lock is None:
            return self
        if self.checked:
            check_process()
        return getattr(lock.held, self.name)


class ProcessLock:
    """A re-entrant lock that refuses a forked process before it waits
    (check_process): a thread of the parent that held it at the fork left
    it held for ever in the child.  A Scene's lock, taken by every call
    (``with``)."""

    __enter__ = _LockMethod("__enter__", checked=True)
    __exit__ = _LockMethod("__exit__", checked=False)

    def __init__(self):
        self.held = threading.RLock()  # what a with statement takes (_LockMethod)


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
        deviceless: list[str] = []
        per_vendor: dict[str, int] = {}
        for platform in platforms:
            vendor = _vendor_id(platform.name)
            try:
                cl_devices = platform.get_devices()
            except cl.Error:
                cl_devices = []
            if not cl_devices and _is_pocl(platform.name):
                # (a PoCL without devices had read as "install a driver")
                deviceless.append(_deviceless(platform.name.strip()))
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
        unregistered.extend(_unloadable_runtimes(intel) + deviceless)
        for note in unregistered:
            warnings.warn(f"hlbvh_cl: {note}", RuntimeWarning, stacklevel=2)
        ordered = sorted(found, key=lambda d: d.simulator)  # stable: platform order otherwise
        _devices_cache = [dataclasses.replace(d, index=i) for i, d in enumerate(ordered)]
    return list(_devices_cache)


def _is_pocl(platform: str) -> bool:
    return "portable computing language" in platform.lower()


def _deviceless(platform: str) -> str:
    """What `unregistered` says of a PoCL platform that lists no device:
    PoCL lists none when it cannot create its kernel cache folder."""
    cache = os.environ.get("POCL_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "pocl")
    return (f"the OpenCL platform {platform!r} lists no device (PoCL lists none when it "
            f"cannot create its kernel cache folder, {cache}: set POCL_CACHE_DIR to a "
            "writable folder)")


def select_device(device=None) -> Device:
    """Pick a device: the argument, then $HLBVH_CL_DEVICE, then the default:
    a GPU, else a CPU (PoCL before Intel's runtime: selection.best), else
    any other device; never a simulator or a device whose kernels fail.  The
    rules a spec follows are hlbvh_cl.device.selection's: an index, an id, a
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
                       + "".join(f"not listed: {note}; " for note in unregistered)
                       + f"{_INSTALL_HINT}. On Debian/Ubuntu, the distribution's PoCL (apt-get "
                       "install pocl-opencl-icd) supports newer CPUs than PyPI's.")
