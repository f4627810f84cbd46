"""Which kernel variant a device really runs, found out in a child process.

An OpenCL compiler can take the whole process down: PyPI's PoCL 3.0 reports
16-wide float vectors on AVX-512 CPUs but compiles for an older target, and
LLVM then aborts on the traversal's vector code ("Do not know how to
scalarize this operator's operand!").  An abort is no Python exception, and
PoCL generates machine code only when a kernel is first enqueued, so building
alone proves nothing.  So each variant (hlbvh_cl.profile) is first built and
*run* here, in a child process (``python -m hlbvh_cl.probe``) under a time
limit, on a small scene whose hits are checked against a float64 brute force;
a variant that crashes, hangs or answers wrong is never used in the caller's
process.  Verdicts are kept on disk per device, driver and kernel sources, so
a machine pays for each once.  Compiled programs land in pyopencl's and the
driver's caches, so the caller's own builds then load them.

The child also reports what its compiler targets (kernels/target_probe.cl)
and, for a variant that passes, the speed of camera rays on a 20K-triangle
mesh, which ranks devices for the default choice.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
import subprocess
import sys
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path

from .paths import cache_root, kernel_dir
from .profile import Profile, Variant, candidates

#: Bumped when what a verdict means changes, so old verdicts are not reused.
FORMAT = 1

def _timeout_s() -> float:
    """Seconds one variant may take in the child, compilation included."""
    return float(os.environ.get("HLBVH_CL_PROBE_TIMEOUT", "300"))


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


_lock = threading.RLock()
_memory: dict[str, dict] = {}
_warned: set = set()


@functools.cache
def _sources_digest(folder: Path) -> str:
    """The kernel sources' hash (read once per process)."""
    digest = hashlib.sha256()
    for path in sorted(folder.iterdir()):
        if path.suffix in (".cl", ".h"):
            digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def _device_key(cl_device, profile: Profile) -> str:
    platform = cl_device.platform
    parts = [str(FORMAT), profile.name, platform.name, platform.version, cl_device.name,
             cl_device.version, cl_device.driver_version, cl_device.vendor,
             _sources_digest(kernel_dir())]
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
    """Writes the record atomically; a cache folder that cannot be written
    only costs the next process a new probe."""
    path = _cache_file(key)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = path.with_suffix(f".{os.getpid()}.tmp")
        temporary.write_text(json.dumps(record, indent=1, sort_keys=True))
        temporary.replace(path)
    except OSError:
        pass


def _run_child(device_id: str, profile: Profile, variant: Variant | None) -> dict:
    """Runs the probe of one variant (or only the target query) in a child
    process; returns {"target": ..., "ok": ..., "reason": ..., ...}."""
    command = [sys.executable, "-m", "hlbvh_cl.probe", device_id, profile.name]
    if variant is not None:
        command.append(variant.name)
    env = {name: value for name, value in os.environ.items()
           if not name.startswith("OCLGRIND_")}  # a simulator's checks are the caller's
    env.update(HLBVH_CL_PROFILE=profile.name, PYTHONWARNINGS="ignore")
    timeout = _timeout_s()
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=timeout, env=env,
                              stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired as expired:
        out = expired.stdout.decode() if isinstance(expired.stdout, bytes) else expired.stdout
        report = _last_json(out or "")
        report.update(ok=False, reason=f"timed out after {timeout:g} s")
        return report
    report = _last_json(done.stdout)
    if done.returncode != 0 or "ok" not in report and variant is not None:
        report.update(ok=False, reason=_why(done.returncode, done.stderr))
    elif report.get("ok") is False:
        # the driver's own words (an LLVM or Oclgrind fatal error) are on stderr
        fatal = [line.strip() for line in done.stderr.splitlines()
                 if "error" in line.lower() or "undefined" in line.lower()]
        if fatal:
            report["reason"] = f"{report.get('reason')} [{fatal[-1]}]"
    return report


def _last_json(text: str) -> dict:
    merged: dict = {}
    for line in (text or "").splitlines():
        line = line.strip()
        if line.startswith("{"):
            try:
                merged.update(json.loads(line))
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
        record["results"][variant.name] = result
        _save(key, record)
    return result


def _target(device, profile: Profile, key: str, record: dict) -> dict:
    if "target" not in record:
        report = _run_child(device.id, profile, None)
        record["target"] = report.get("target") or {
            "reported_width": 1, "error": _why(1, report.get("reason", ""))}
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

def _compile_target(rt) -> dict:
    import numpy as np
    import pyopencl as cl
    flags_buffer = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 4)
    rt.run(rt.kernel("target_probe.cl", "compile_target"), 1, flags_buffer, local_size=1)
    flags = np.zeros(1, np.int32)
    cl.enqueue_copy(rt.queue, flags, flags_buffer)
    return {"x86": bool(flags[0] & 1), "avx": bool(flags[0] & 2), "avx512": bool(flags[0] & 4),
            "reported_width": int(rt.device.cl_device.native_vector_width_float)}


def _brute_force_t(vertices, faces, origins, directions):
    """Closest t per ray in float64 (Moller & Trumbore 1997), inf on a miss."""
    import numpy as np
    v = np.asarray(vertices, np.float64)[np.asarray(faces)]
    e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    o, d = np.asarray(origins, np.float64)[:, None], np.asarray(directions, np.float64)[:, None]
    p = np.cross(d, e2)
    det = np.einsum("rtk,tk->rt", p, e1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o - v[:, 0]
        u = np.einsum("rtk,rtk->rt", s, p) * inv
        q = np.cross(s, e1)
        w = np.einsum("rtk,rtk->rt", d, q) * inv
        t = np.einsum("tk,rtk->rt", e2, q) * inv
    hit = (det != 0) & (u >= 0) & (w >= 0) & (u + w <= 1) & (t >= 0)
    return np.where(hit, t, np.inf).min(axis=1)


def _probe_variant(rt) -> dict:
    """Builds, refits, traces and renders small scenes with ``rt``'s variant;
    returns {"ok": ..., "reason": ..., "mrays_per_s": ...}."""
    import numpy as np
    import trimesh

    from .mesh import Mesh
    from .render import Camera, Renderer
    from .scene import Scene

    sphere = trimesh.creation.icosphere(subdivisions=2)
    ground_v = np.array([[-3, -3, -1.5], [3, -3, -1.5], [3, 3, -1.5], [-3, 3, -1.5]], float)
    ground_f = np.array([[0, 1, 2], [0, 2, 3]])
    meshes = [Mesh(sphere.vertices, sphere.faces), Mesh(ground_v, ground_f)]
    vertices = np.concatenate([sphere.vertices, ground_v])
    faces = np.concatenate([sphere.faces, ground_f + len(sphere.vertices)])

    rng = np.random.default_rng(7)
    # rays aimed inside random triangles from outside (all hit), rays pointing
    # away (all miss), and a 16 x 16 view (packets of coherent rays)
    aims = vertices[faces[rng.integers(0, len(faces), 256)]]
    weights = rng.dirichlet((4, 4, 4), 256)[:, :, None]
    targets = (aims * weights).sum(axis=1)
    starts = rng.normal(size=(256, 3))
    starts = 4 * starts / np.linalg.norm(starts, axis=1, keepdims=True)
    away = -starts
    xs, ys = np.meshgrid(np.linspace(-0.6, 0.6, 16), np.linspace(-0.6, 0.6, 16))
    view = np.stack([xs.ravel(), ys.ravel(), -np.ones(256)], axis=1)
    origins = np.concatenate([starts, starts, np.tile([0.1, 0.2, 4.0], (256, 1))])
    directions = np.concatenate([targets - starts, away, view])
    expected = _brute_force_t(vertices, faces, origins, directions)

    def compare(what, scene, expect):
        hits = scene.intersect(origins, directions)
        hit, hit_expected = np.isfinite(hits.t), np.isfinite(expect)
        strict = slice(0, 512)  # the aimed and the away rays cannot graze an edge
        if (hit[strict] != hit_expected[strict]).any() or \
                (hit[512:] != hit_expected[512:]).mean() > 0.01:
            return f"{what}: hits differ from a float64 brute force on " \
                   f"{int((hit != hit_expected).sum())} of {len(hit)} rays"
        both = hit & hit_expected
        error = np.abs(hits.t[both] - expect[both]) / np.maximum(expect[both], 1e-30)
        if len(error) and error.max() > 1e-4:
            return f"{what}: t differs from a float64 brute force by up to {error.max():.2g}"
        if (scene.occluded(origins, directions) != hit).any():
            return f"{what}: occluded disagrees with intersect"
        return None

    device = rt.device.id
    for builder, bits in (("hlbvh", 30), ("lbvh", 63)):
        scene = Scene(meshes, device=device, builder=builder, morton_bits=bits)
        problem = compare(f"{builder} {bits}-bit", scene, expected)
        if problem:
            return {"ok": False, "reason": problem}
    moved = sphere.vertices * 1.25
    scene.update_vertices(0, moved)
    problem = compare("refit", scene, _brute_force_t(np.concatenate([moved, ground_v]), faces,
                                                       origins, directions))
    if problem:
        return {"ok": False, "reason": problem}
    for shading in ("diffuse", "ao"):
        image = Renderer(scene).render(Camera((0.5, 3.0, 2.0), (0, 0, 0)), 12, 8,
                                       shading=shading, ao_samples=2)
        if image.shape != (8, 12, 3) or not image.any():
            return {"ok": False, "reason": f"the {shading} render came back empty"}

    if rt.device.simulator:  # never a default: no ranking needed
        return {"ok": True, "reason": None, "mrays_per_s": None}
    # speed: camera rays on a 20K-triangle sphere (ranks devices)
    dense = trimesh.creation.icosphere(subdivisions=5)
    scene = Scene([Mesh(dense.vertices, dense.faces)], device=device)
    xs, ys = np.meshgrid(np.linspace(-1, 1, 256), np.linspace(-1, 1, 256))
    view = np.stack([xs.ravel(), ys.ravel(), -2 * np.ones(xs.size)], axis=1)
    eye = np.tile([0.0, 0.0, 3.0], (len(view), 1))
    milliseconds = []
    for _ in range(4):  # the first run pays for compilation
        scene.intersect(eye, view)
        milliseconds.append(scene._ray_query().last_kernel_ms)
    fastest = sorted(milliseconds[1:])[1]
    return {"ok": True, "reason": None, "mrays_per_s": len(view) / max(fastest, 1e-3) * 1e-3}


def _injected_fault(variant: Variant) -> None:
    """For the tests of this module: HLBVH_CL_PROBE_FAULT=NAME:abort (or
    :hang) makes the child die as a crashing compiler would (or hang) while
    it probes variant NAME (* for every variant)."""
    import time
    name, _, action = os.environ.get("HLBVH_CL_PROBE_FAULT", "").partition(":")
    if name in (variant.name, "*"):
        if action == "abort":
            sys.stderr.write("LLVM ERROR: injected by HLBVH_CL_PROBE_FAULT\n")
            sys.stderr.flush()
            os.abort()
        if action == "hang":
            time.sleep(3600)


def main(argv: list[str] | None = None) -> int:
    """``python -m hlbvh_cl.probe DEVICE_ID PROFILE [VARIANT]``: prints one
    JSON line with the compiler's target and, with VARIANT, its verdict."""
    from . import device as device_module

    device_id, profile_name, *rest = argv if argv is not None else sys.argv[1:]
    found = [d for d in device_module.devices() if d.id == device_id]
    if not found:
        print(json.dumps({"ok": False, "reason": f"no device {device_id} in the child"}))
        return 1
    profile = Profile(profile_name)
    variant = Variant.parse(rest[0]) if rest else Variant(1, builtins=False)
    rt = device_module.install_runtime(found[0], profile, variant)
    print(json.dumps({"target": _compile_target(rt)}), flush=True)
    if rest:
        _injected_fault(variant)
        try:
            report = _probe_variant(rt)
        except Exception as error:  # a build error, a bad result: the verdict says which
            lines = [line for line in str(error).splitlines() if line.strip()]
            errors = [line.strip() for line in lines[1:] if "error" in line.lower()]
            reason = f"{type(error).__name__}: {lines[0] if lines else ''}"
            report = {"ok": False, "reason": reason + (f" ({errors[0]})" if errors else "")}
        print(json.dumps(report), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
