"""Which kernel variant a device really runs, found out in a child process.

An OpenCL compiler can take the whole process down: PyPI's PoCL 3.0 reports
16-wide float vectors on AVX-512 CPUs but compiles for an older target, and
LLVM then aborts on the traversal's vector code ("Do not know how to
scalarize this operator's operand!").  An abort is no Python exception, and
PoCL generates machine code only when a kernel is first enqueued, so building
alone proves nothing.  So each variant (hlbvh_cl.device.profile) is first built and
*run* in a child process (``python -m hlbvh_cl.device.probe_child``) under a time
limit, on a small scene whose hits are checked against a float64 brute force;
a variant that crashes, hangs or answers wrong is never used in the caller's
process.  Verdicts are kept on disk per device, driver and kernel sources, so
a machine pays for each once.  Compiled programs land in pyopencl's and the
driver's caches, so the caller's own builds then load them.

The child (hlbvh_cl.device.probe_child) also reports what its compiler targets (kernels/device/probe.cl)
and, for a variant that passes, the speed of camera rays on a 20K-triangle
mesh, which ranks devices for the default choice.
"""
from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path

from ..core.paths import cache_root, kernel_dir
from .profile import Profile, Variant, candidates

#: Bumped when what a verdict means changes, so old verdicts are not reused.
FORMAT = 1

#: What the child prints before each JSON record (probe_child.report), so
#: that the parent finds it after whatever the driver printed on its line.
REPORT = "hlbvh_cl probe: "


def timeout_s() -> float:
    """Seconds one variant may take in the child, compilation included:
    HLBVH_CL_PROBE_TIMEOUT, default 300."""
    text = os.environ.get("HLBVH_CL_PROBE_TIMEOUT", "300")
    try:
        seconds = float(text)
    except ValueError:
        seconds = float("nan")
    if not 0 < seconds < float("inf"):
        raise ValueError(f"HLBVH_CL_PROBE_TIMEOUT={text!r}: expected the seconds a device probe "
                         "may take, a number above 0 (default 300)")
    return seconds


@dataclass(frozen=True)
class Verdict:
    """What the probe found for one device and profile."""

    target: dict
    chosen: Variant | None          # the first candidate that passed
    failures: tuple                 # ((Variant, reason), ...) of the candidates before it
    mrays_per_s: float | None       # the chosen variant's camera-ray speed in the probe

    @property
    def problem(self) -> str | None:
        if self.chosen is not None:
            return None
        return "; ".join(f"{v.name}: {reason}" for v, reason in self.failures) or "no variant"


_log = logging.getLogger("hlbvh_cl")
_lock = threading.RLock()
_memory: dict[str, dict] = {}
_warned: set = set()


@functools.cache
def sources_digest(folder: Path) -> str:
    """The hash of every source below ``folder`` (.cl, .h, .py), each named
    from it, read once per process: a verdict holds for the kernels and the
    package (whose child runs the probe) it was made with, so an edit in any
    room re-probes, and a checkout never reads another's verdicts."""
    digest = hashlib.sha256()
    for path in sorted(folder.rglob("*")):
        if path.suffix in (".cl", ".h", ".py"):
            name = path.relative_to(folder).as_posix()
            digest.update(name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def _package_dir() -> Path:
    return Path(__file__).resolve().parent.parent


def _device_key(cl_device, profile: Profile) -> str:
    platform = cl_device.platform
    parts = [str(FORMAT), profile.name, platform.name, platform.version, cl_device.name,
             cl_device.version, cl_device.driver_version, cl_device.vendor,
             sources_digest(kernel_dir()), sources_digest(_package_dir())]
    return hashlib.sha256("\0".join(parts).encode()).hexdigest()[:32]


def _cache_file(key: str) -> Path:
    return cache_root() / "probes" / f"{key}.json"


def _load(key: str) -> dict:
    record = _memory.get(key)
    if record is None:
        try:
            record = json.loads(_cache_file(key).read_text())
        except (OSError, ValueError):
            record = {}
        record.setdefault("results", {})
        _memory[key] = record
    return record


def _save(key: str, record: dict) -> None:
    """Writes the record atomically, less the verdicts the machine's state
    gave (TRANSIENT): those hold for this process only.  A cache folder
    that cannot be written only costs the next process a new probe."""
    path = _cache_file(key)
    lasting = {**record, "results": {name: result for name, result in record["results"].items()
                                     if not result.get("transient")}}
    if record.get("target", {}).get("transient"):
        del lasting["target"]
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = path.with_suffix(f".{os.getpid()}.tmp")
        temporary.write_text(json.dumps(lasting, indent=1, sort_keys=True))
        temporary.replace(path)
    except OSError:
        pass


#: Signals that end a child from outside (Ctrl-C, the OOM killer, a
#: shutdown) rather than from its own code: a probe they end, like one that
#: times out on a loaded machine, says nothing lasting about the variant.
TRANSIENT_SIGNALS = {int(signal.SIGINT), int(signal.SIGKILL), int(signal.SIGTERM),
                     int(signal.SIGHUP)}


def _run_child(device_id: str, profile: Profile, variant: Variant | None) -> dict:
    """Runs the probe of one variant (or only the target query) in a child
    process; returns {"target": ..., "ok": ..., "reason": ..., ...}, with
    "transient": True when a timeout or an outside signal ended it."""
    _log.info("probing %s (%s profile) with kernel variant %s in a child process", device_id,
              profile.name, variant.name if variant else "(the compiler's target)")
    command = [sys.executable, "-m", "hlbvh_cl.device.probe_child", device_id, profile.name]
    if variant is not None:
        command.append(variant.name)
    env = {name: value for name, value in os.environ.items()
           if not name.startswith("OCLGRIND_")}  # a simulator's checks are the caller's
    env.update(HLBVH_CL_PROFILE=profile.name, PYTHONWARNINGS="ignore")
    timeout = timeout_s()
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=timeout, env=env,
                              stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired as expired:
        out = expired.stdout.decode() if isinstance(expired.stdout, bytes) else expired.stdout
        report = _last_json(out or "")
        report.update(ok=False, reason=f"timed out after {timeout:g} s", transient=True)
        return report
    report = _last_json(done.stdout)
    if done.returncode == 0 and "ok" not in report and variant is not None:
        # it ended well and gave no verdict: nothing to remember about the
        # variant (a verdict lost in the driver's output once failed every
        # variant for good)
        report.update(ok=False, transient=True,
                      reason=f"the probe gave no verdict; its output ended "
                             f"{(done.stdout or '').strip()[-200:]!r}")
    elif done.returncode != 0:
        report.update(ok=False, reason=_why(done.returncode, done.stderr))
        if -done.returncode in TRANSIENT_SIGNALS:
            report["transient"] = True
    elif report.get("ok") is False:
        # the driver's own words (an LLVM or Oclgrind fatal error) are on stderr
        fatal = [line.strip() for line in done.stderr.splitlines()
                 if "error" in line.lower() or "undefined" in line.lower()]
        if fatal:
            report["reason"] = f"{report.get('reason')} [{fatal[-1]}]"
    return report


def _last_json(text: str) -> dict:
    """The child's records (after REPORT, anywhere on a line), merged."""
    merged: dict = {}
    for line in (text or "").splitlines():
        at = line.find(REPORT)
        if at >= 0:
            try:
                merged.update(json.loads(line[at + len(REPORT):]))
            except ValueError:
                pass
    return merged


def _why(returncode: int, stderr: str) -> str:
    """One line on why a child failed: the compiler's error, else the last line."""
    lines = [line.strip() for line in (stderr or "").splitlines() if line.strip()]
    errors = [line for line in lines if "error" in line.lower() and "Traceback" not in line]
    died = f"exit code {returncode}" if returncode >= 0 else f"killed by signal {-returncode}"
    text = errors[-1] if errors else (lines[-1] if lines else "")
    return f"{text} ({died})" if text else died


def _result(device, profile: Profile, key: str, record: dict, variant: Variant) -> dict:
    result = record["results"].get(variant.name)
    if result is None:
        report = _run_child(device.id, profile, variant)
        if report.get("target"):
            record["target"] = report["target"]
        result = {k: report.get(k) for k in ("ok", "reason", "mrays_per_s")}
        result["ok"] = bool(result["ok"])
        if report.get("transient"):
            result["transient"] = True
        record["results"][variant.name] = result
        _save(key, record)
    return result


def _target(device, profile: Profile, key: str, record: dict) -> dict:
    if "target" not in record:
        report = _run_child(device.id, profile, None)
        record["target"] = report.get("target") or {
            "reported_width": 1, "error": _why(1, report.get("reason", ""))}
        if report.get("transient"):
            record["target"]["transient"] = True
        _save(key, record)
    return record["target"]


def verdict(device, profile: Profile) -> Verdict:
    """The first candidate variant that passes on ``device`` (probing as
    needed), and why the ones before it failed."""
    with _lock:
        key = _device_key(device.cl_device, profile)
        record = _load(key)
        target = _target(device, profile, key, record)
        failures = []
        for variant in candidates(profile, target):
            result = _result(device, profile, key, record, variant)
            if result["ok"]:
                return Verdict(target, variant, tuple(failures), result.get("mrays_per_s"))
            failures.append((variant, result.get("reason") or "failed"))
        return Verdict(target, None, tuple(failures), None)


def usable(device, profile: Profile, variant: Variant) -> str | None:
    """None when ``variant`` passes its probe on ``device``, else why not."""
    with _lock:
        key = _device_key(device.cl_device, profile)
        record = _load(key)
        result = _result(device, profile, key, record, variant)
        return None if result["ok"] else (result.get("reason") or "failed")


def warn_fallback(device, wanted: Variant, reason: str, used: Variant) -> None:
    """One line, once per process, when a variant gives way to a safer one."""
    what = (device.id, wanted, used)
    if what not in _warned:
        _warned.add(what)
        warnings.warn(f"hlbvh_cl: {device.id} cannot run kernel variant {wanted.name} "
                      f"({reason}); using {used.name}", RuntimeWarning, stacklevel=3)


# -- the child ------------------------------------------------------------------
