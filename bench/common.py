"""What the benchmarks share: device choice, the command line, timing
summaries, a test surface of any size, plain-text tables and JSON.

Timings on a shared machine are noisy, so every figure is summarised by its
median with min and max beside it, and ratios are taken between figures of
the same run.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import hlbvh_cl

REPO = Path(__file__).resolve().parent.parent
BENCH = REPO / "bench"
MESHES = REPO / "scenes" / "meshes"
SCENES = REPO / "scenes"
DOCS = REPO / "docs"
RESULTS = BENCH / "results"


# ---------------------------------------------------------------- the command line

def arguments(description: str, argv, *extra) -> argparse.Namespace:
    """The options every bench takes (--quick, --devices, --out, --docs,
    --no-progress) and ``extra`` ones, each (flags, keyword arguments)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--quick", action="store_true",
                        help="a small configuration that runs in seconds")
    parser.add_argument("--devices", default=None,
                        help="comma-separated device ids or names (default: every working device)")
    parser.add_argument("--out", type=Path, default=RESULTS,
                        help="folder of the JSON and the plot (default: bench/results)")
    parser.add_argument("--docs", action="store_true",
                        help="also write this bench's plot under docs/ (the committed copy)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars on stderr")
    for flags, options in extra:
        parser.add_argument(*flags, **options)
    return parser.parse_args(argv)


def pick_devices(spec: str | None = None) -> tuple[list, list[dict]]:
    """The devices to benchmark and the ones skipped, as (working, skipped).

    ``spec`` is a comma-separated list of device ids or substrings of id,
    name or platform ("pocl,intel"), each naming its first working match;
    None means every working device but simulators.  A skipped entry is
    {"device": id or spec, "problem": why}.
    """
    every = hlbvh_cl.devices()
    if spec is None:
        parts = [[d] for d in every if not d.simulator]
    else:
        parts = []
        for text in (p.strip().lower() for p in spec.split(",") if p.strip()):
            exact = [d for d in every if d.id == text]
            parts.append(exact or [d for d in every if text in d.id
                                   or text in d.name.lower() or text in d.platform.lower()])
            if not parts[-1]:
                parts[-1] = [text]
    working, skipped = [], []
    for matches in parts:
        if isinstance(matches[0], str):
            skipped.append({"device": matches[0], "problem": "no OpenCL device matches this name"})
            continue
        good = [d for d in matches if d.problem is None]
        working += [d for d in good[:1] if all(d.id != w.id for w in working)]
        skipped += [{"device": d.id, "problem": d.problem} for d in matches
                    if d.problem is not None and all(d.id != s["device"] for s in skipped)]
    return working, skipped


def devices_or_exit(spec: str | None) -> list:
    """pick_devices, saying what it skipped; exits when no device is left."""
    chosen, skipped = pick_devices(spec)
    for s in skipped:
        say(f"skipping {s['device']}: {s['problem']}")
    if not chosen:
        raise SystemExit("no working OpenCL device to benchmark")
    return chosen


def say(text: str) -> None:
    """A line on stdout that does not break the progress bars on stderr."""
    from tqdm import tqdm
    tqdm.write(text, file=sys.stdout)
    sys.stdout.flush()


def progress(total: int, description: str, enabled: bool = True):
    """A tqdm bar on stderr (stdout keeps the tables clean)."""
    from tqdm import tqdm
    return tqdm(total=total, desc=description, file=sys.stderr, disable=not enabled,
                dynamic_ncols=True, leave=False)


# ---------------------------------------------------------------- figures

def summary(values) -> dict:
    """median, min and max of a non-empty sequence of numbers."""
    values = [float(v) for v in values]
    if not values:
        raise ValueError("summary() needs at least one value")
    return {"median": statistics.median(values), "min": min(values), "max": max(values)}


def rates(count: int, seconds) -> dict:
    """Millions per second {median, min, max} from a list of seconds."""
    s = summary(seconds)
    return {"median": count / s["median"] / 1e6, "min": count / s["max"] / 1e6,
            "max": count / s["min"] / 1e6}


def stage_times(stats: list) -> dict:
    """{stage, "device", "wall": {median, min, max}} ms over builds' BuildStats."""
    out = {stage: summary([s.times_ms[stage] for s in stats]) for stage in stats[0].times_ms}
    out["device"] = summary([s.device_ms for s in stats])
    out["wall"] = summary([s.wall_ms for s in stats])
    return out


def ratio(numerator: float, denominator: float) -> float | None:
    """numerator / denominator, or None when the denominator is not positive."""
    return numerator / denominator if denominator > 0 else None


def fit_exponent(sizes, seconds) -> float | None:
    """alpha of seconds ~ c * sizes^alpha, least squares in log-log; None
    with fewer than two distinct sizes."""
    x, y = np.log(np.asarray(sizes, float)), np.log(np.asarray(seconds, float))
    if len(x) < 2 or np.ptp(x) == 0:
        return None
    return float(np.polyfit(x, y, 1)[0])


def stopwatch():
    """A function returning the seconds elapsed since stopwatch() was called."""
    started = time.perf_counter()
    return lambda: time.perf_counter() - started


def cpu_seconds() -> float:
    """User + system CPU time of this process, a CPU device's threads included:
    over a stretch of wall time, their ratio is how many cores the work got."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def peak_rss_bytes() -> int:
    """The process's peak resident memory so far (ru_maxrss: KiB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)


def status_bytes(key: str) -> int | None:
    """A size line of /proc/self/status (VmRSS, VmHWM) in bytes; None off Linux."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def reset_peak() -> bool:
    """Linux: writing 5 to clear_refs resets VmHWM to the current RSS.  Freed
    heap memory is handed back first (glibc's malloc_trim): still resident,
    the call could reuse it unseen and the growth would read low."""
    try:
        import ctypes
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


# ---------------------------------------------------------------- geometry

def surface(triangles: int, name: str | None = None) -> hlbvh_cl.Mesh:
    """A closed bumpy torus of about ``triangles`` triangles (2 per grid cell,
    the ring 3 cells for each around the tube).  Every size samples the same
    surface, so a camera on it sees the same picture at any size."""
    tube = max(3, round(math.sqrt(max(triangles, 18) / 6)))
    ring = max(3, round(triangles / (2 * tube)))
    u = np.linspace(0, 2 * np.pi, ring, endpoint=False)[:, None]
    v = np.linspace(0, 2 * np.pi, tube, endpoint=False)[None, :]
    r = 1 + 0.15 * np.sin(5 * u) * np.sin(3 * v)
    x, z, y = (3 + r * np.cos(v)) * np.cos(u), (3 + r * np.cos(v)) * np.sin(u), r * np.sin(v)
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3).astype(np.float32)
    i, j = np.meshgrid(np.arange(ring), np.arange(tube), indexing="ij")
    a, b = i * tube + j, (i + 1) % ring * tube + j
    c, d = i * tube + (j + 1) % tube, (i + 1) % ring * tube + (j + 1) % tube
    faces = np.concatenate([np.stack([a, d, b], -1), np.stack([a, c, d], -1)]).reshape(-1, 3)
    return hlbvh_cl.Mesh(vertices, faces.astype(np.int32),
                         name=name or f"torus {2 * ring * tube:,}")


def bounds(meshes) -> tuple[np.ndarray, np.ndarray]:
    """The box around the meshes' vertices: (lo, hi)."""
    return (np.min([m.vertices.min(axis=0) for m in meshes], axis=0),
            np.max([m.vertices.max(axis=0) for m in meshes], axis=0))


# ---------------------------------------------------------------- output

def table(headers: list[str], rows: list[list], title: str | None = None) -> str:
    """Rows as a plain-text table: the first column left-aligned, the others
    right-aligned; ints get thousands separators, floats one decimal, None "-"."""
    def text(value) -> str:
        if value is None:
            return "-"
        if isinstance(value, (float, np.floating)):
            return f"{value:,.1f}"
        if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
            return f"{value:,}"
        return str(value)

    cells = [[text(v) for v in row] for row in rows]
    widths = [max([len(h)] + [len(c[i]) for c in cells]) for i, h in enumerate(headers)]

    def line(values) -> str:
        return "  ".join(v.ljust(w) if i == 0 else v.rjust(w)
                         for i, (v, w) in enumerate(zip(values, widths))).rstrip()

    out = [title] if title else []
    out += [line(headers), line(["-" * w for w in widths])] + [line(c) for c in cells]
    return "\n".join(out)


def spread(times: dict | None, scale: float = 1.0, digits: int = 1) -> str:
    """A {median, min, max} as "median (min-max)"; "-" for None."""
    if not times:
        return "-"
    return (f"{times['median'] * scale:,.{digits}f} "
            f"({times['min'] * scale:,.{digits}f}-{times['max'] * scale:,.{digits}f})")


def finish(results: dict, name: str, args, elapsed, plot=None) -> dict:
    """Writes a bench's results to <out>/<name>.json and, given a ``plot``
    function, <out>/<name>.png (with --docs, docs/bench_<name>.png too)."""
    results["peak_rss_bytes"] = peak_rss_bytes()
    results["elapsed_s"] = elapsed()
    written = [write_json(args.out / f"{name}.json", results)]
    if plot is not None:
        written.append(plot(results, args.out / f"{name}.png"))
        if args.docs:
            written.append(plot(results, DOCS / f"bench_{name}.png"))
    print(f"\nwrote {', '.join(map(str, written))} in {results['elapsed_s']:.0f} s")
    return results


def write_section(path: Path, text: str, name: str) -> Path:
    """Puts ``text``, a section marked "<!-- begin NAME -->" ... "<!-- end
    NAME -->", into the markdown file in place of its earlier copy, or at the
    end (bench/report.py keeps such sections when it rewrites the file)."""
    begin, end = f"<!-- begin {name} -->", f"<!-- end {name} -->"
    old = path.read_text() if path.exists() else ""
    if begin in old and end in old:
        new = old[:old.index(begin)] + text.rstrip("\n") + old[old.index(end) + len(end):]
    else:
        new = old.rstrip("\n") + "\n\n" + text
    path.write_text(new if new.endswith("\n") else new + "\n")
    return path


def machine_info() -> dict:
    """What the figures were measured on."""
    import pyopencl
    return {
        "python": platform.python_version(), "platform": platform.platform(),
        "processor": _cpu_name(), "cpus": os.cpu_count(),
        "numpy": np.__version__, "pyopencl": pyopencl.VERSION_TEXT,
        "hlbvh_cl": hlbvh_cl.__version__,
        "devices": [{"id": d.id, "name": d.name, "platform": d.platform,
                     "driver": d.driver_version, "compute_units": d.compute_units,
                     "global_mem_size": d.global_mem_size, "problem": d.problem}
                    for d in hlbvh_cl.devices()],
        "date": time.strftime("%Y-%m-%d %H:%M %Z"),
        "loadavg": list(os.getloadavg()),
    }


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def write_json(path: Path, data) -> Path:
    """Write ``data`` (numpy scalars allowed) as indented JSON, creating folders."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2, default=_json_default) + "\n")
    return path


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} to JSON")
