"""Helpers shared by the benchmarks (build.py, large.py, trace.py): device
choice, timing summaries, progress bars, plain-text tables, JSON and plots.

Timings on this project's machines are noisy (2 shared cores), so every
figure is summarised by its median, with min and max beside it, and ratios
are always taken between figures of the same run.
"""
from __future__ import annotations

import json
import os
import platform
import resource
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
MESHES = REPO / "scenes" / "meshes"
SCENES = REPO / "scenes"

try:
    import hlbvh_cl  # noqa: F401
except ImportError:  # run from a checkout without installing
    sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

import hlbvh_cl  # noqa: E402
from hlbvh_cl.device import Device, select_device  # noqa: E402


def pick_devices(spec: str | None = None) -> tuple[list[Device], list[dict]]:
    """The devices to benchmark and the ones skipped, as (working, skipped).

    ``spec`` is a comma-separated list of device ids, indices or name
    substrings ("pocl,intel"); None means every device present.  A skipped
    entry is {"device": id or spec, "problem": why}.
    """
    working: list[Device] = []
    skipped: list[dict] = []
    if spec is None:
        candidates = hlbvh_cl.devices()
    else:
        candidates = []
        for part in (p.strip() for p in spec.split(",")):
            if not part:
                continue
            try:
                candidates.append(select_device(part))
            except (ValueError, TypeError, RuntimeError) as error:
                skipped.append({"device": part, "problem": str(error)})
            # list the broken devices the name also matches ("pocl": PyPI's PoCL)
            text = part.lower()
            candidates += [d for d in hlbvh_cl.devices() if d.problem is not None and
                           (text in d.id or text in d.name.lower() or text in d.platform.lower())]
    for device in candidates:
        if device.problem is not None:
            if all(device.id != s["device"] for s in skipped):
                skipped.append({"device": device.id, "problem": device.problem})
        elif all(device.id != d.id for d in working):
            working.append(device)
    return working, skipped


def quiet_compiler_warnings() -> None:
    """Hide pyopencl's "non-empty compiler output" warnings (driver chatter)."""
    import warnings

    import pyopencl
    warnings.filterwarnings("ignore", category=pyopencl.CompilerWarning)


def summary(values) -> dict:
    """median, min and max of a non-empty sequence of numbers."""
    values = [float(v) for v in values]
    if not values:
        raise ValueError("summary() needs at least one value")
    return {"median": statistics.median(values), "min": min(values), "max": max(values)}


def ratio(numerator: float, denominator: float) -> float | None:
    """numerator / denominator, or None when the denominator is not positive."""
    return numerator / denominator if denominator > 0 else None


def stopwatch():
    """A function returning the seconds elapsed since stopwatch() was called."""
    started = time.perf_counter()
    return lambda: time.perf_counter() - started


def progress(total: int, description: str, enabled: bool = True):
    """A tqdm bar on stderr (stdout keeps the tables clean)."""
    from tqdm import tqdm
    return tqdm(total=total, desc=description, file=sys.stderr, disable=not enabled,
                dynamic_ncols=True, leave=False)


def cpu_seconds() -> float:
    """User + system CPU time of this process, all threads (a CPU OpenCL
    device's worker threads included).  Over a stretch of wall time, their
    ratio is how many cores the work actually got: on a 2-core machine shared
    with others, a value near 1 for a large build means it lost a core."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def peak_rss_bytes() -> int:
    """The process's peak resident memory so far (ru_maxrss: KiB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)


def current_rss_bytes() -> int | None:
    """The process's resident memory now (Linux /proc), or None elsewhere."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


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
                     "global_mem_size": d.global_mem_size,
                     "max_mem_alloc_size": d.max_mem_alloc_size, "problem": d.problem}
                    for d in hlbvh_cl.devices()],
        "date": time.strftime("%Y-%m-%d %H:%M:%S %z"),
        "loadavg": os.getloadavg() if hasattr(os, "getloadavg") else None,
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


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save_figure(figure, path, dpi: int = 110):
    """Lay out, write and close a matplotlib figure; returns the path."""
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=dpi)
    pyplot().close(figure)
    return path
