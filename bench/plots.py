"""One matplotlib figure per bench, from the results it writes as JSON:
build() for bench/build.py, trace() for bench/trace.py, suite() for
python -m bench.  Each returns the path of the PNG it wrote."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save(figure, path: Path) -> Path:
    path = Path(path)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    pyplot().close(figure)
    return path


def plain_log(axes, *, x: bool = False, y: bool = True) -> None:
    """Log axes labelled with plain numbers (0.1, 2, 20) rather than powers of ten."""
    from matplotlib.ticker import FuncFormatter, NullFormatter
    plain = FuncFormatter(lambda value, _: f"{value:g}")
    if x:  # triangle counts: a label a decade
        axes.xaxis.set_major_formatter(plain)
        axes.xaxis.set_minor_formatter(NullFormatter())
    if y:  # times and speeds often span less than a decade
        axes.yaxis.set_major_formatter(plain)
        axes.yaxis.set_minor_formatter(plain)
    axes.grid(True, which="both", alpha=0.3)


def _errorbar(axes, x, spreads, scale: float = 1.0, **options):
    """A line through the medians of {median, min, max} with min-max bars."""
    y = np.array([s["median"] for s in spreads]) * scale
    low = y - np.array([s["min"] for s in spreads]) * scale
    high = np.array([s["max"] for s in spreads]) * scale - y
    return axes.errorbar(x, y, yerr=[low, high], capsize=2, **options)


def _throughput(axes, groups: list, names: list[str]) -> None:
    """Grouped bars of closest-hit Mrays/s: groups are (label, workload)."""
    width = 0.8 / max(len(names), 1)
    for i, name in enumerate(names):
        x = [g for g, (_, w) in enumerate(groups) if name in w["results"]]
        if not x:
            continue
        speeds = [groups[g][1]["results"][name]["intersect_mrays"] for g in x]
        median = np.array([s["median"] for s in speeds])
        axes.bar(np.array(x) + (i - (len(names) - 1) / 2) * width, median, width,
                 yerr=[median - [s["min"] for s in speeds], [s["max"] for s in speeds] - median],
                 label=name, capsize=1.5)
    axes.set_xticks(range(len(groups)), [g for g, _ in groups], fontsize=7, rotation=30,
                    ha="right", rotation_mode="anchor")
    axes.set(ylabel="closest hit, Mrays/s (median, min-max)", yscale="log",
             title="ray throughput, the same rays for all (numpy in, numpy out)")
    plain_log(axes)
    axes.legend(fontsize=7, ncol=2)


def _stages(axes, bars: list) -> None:
    """Stacked device time per build stage: bars are (label, build result)."""
    bottom = np.zeros(len(bars))
    stages = [k for k in bars[0][1]["times_ms"] if k not in ("device", "wall")] if bars else []
    for stage in stages:
        heights = np.array([r["times_ms"][stage]["median"] for _, r in bars])
        axes.bar([label for label, _ in bars], heights, bottom=bottom, label=stage)
        bottom += heights
    case = bars[0][1] if bars else {"case": "-", "triangles": 0}
    axes.set(ylabel="device time, ms (median)",
             title=f"build stages, {case['case']} ({case['triangles']:,} triangles)")
    axes.legend(fontsize=7)


def build(results: dict, path: Path) -> Path:
    """Build time against triangles (each device and builder), and the
    stages of the scene file's build."""
    plt = pyplot()
    figure, (scaling, stages) = plt.subplots(1, 2, figsize=(13, 5))
    for device_id, result in results["devices"].items():
        for builder, marker in (("hlbvh", "o"), ("lbvh", "s")):
            series = [r for r in result["cases"] if r["builder"] == builder]
            if series:
                _errorbar(scaling, [r["triangles"] for r in series],
                          [r["times_ms"]["wall"] for r in series], marker=marker, ls="",
                          label=f"{device_id} {builder}")
    scaling.set(xscale="log", yscale="log", xlabel="triangles", ylabel="build wall time, ms",
                title="build time (median of the rebuilds, min-max)")
    plain_log(scaling, x=True)
    scaling.legend(fontsize=8)
    _stages(stages, [(f"{d}\n{r['builder']}", r) for d, result in results["devices"].items()
                     for r in result["cases"] if r["kind"] == "scene"])
    return save(figure, path)


def trace(results: dict, path: Path) -> Path:
    """Closest-hit throughput of every participant per workload, and the
    scaling series' time against triangles."""
    plt = pyplot()
    figure, (speed, scaling) = plt.subplots(1, 2, figsize=(15, 5.5),
                                            gridspec_kw={"width_ratios": [2, 1]})
    names = [n for n, p in results["participants"].items() if p["available"]]
    _throughput(speed, [(f"{s['name'].rsplit('.', 1)[0]}\n{w['name']}", w)
                        for s in results["scenes"] for w in s["workloads"]], names)
    data = results["scaling"]
    for name in names:
        points = [p for p in data["points"] if name in p["results"]]
        if points:
            alpha = data["alpha"].get(name)
            _errorbar(scaling, [p["triangles"] for p in points],
                      [p["results"][name]["intersect_s"] for p in points], 1e3, marker="o",
                      label=name + (f" (alpha {alpha:.3f})" if alpha is not None else ""))
    if not data["points"]:  # bench.trace --scene: no scaling sweep
        scaling.set_axis_off()
        return save(figure, path)
    scaling.set(xscale="log", yscale="log", xlabel="triangles", ylabel="closest hit, wall ms",
                title=f"scaling: {data['workload']},\none surface tessellated finer")
    plain_log(scaling, x=True)
    scaling.legend(fontsize=8)
    return save(figure, path)


def suite(results: dict, path: Path) -> Path:
    """The report's table against ours (its Figure 1), the build stages of
    the last build case, and ray throughput."""
    plt = pyplot()
    figure, (table, stages, speed) = plt.subplots(1, 3, figsize=(20, 5.5),
                                                  gridspec_kw={"width_ratios": [1, 1, 1.6]})
    data = results["table"]
    for device_id, entry in data["devices"].items():
        rows = [r for r in entry["rows"] if r["in_report"]]
        if rows:
            alpha = entry["alpha"]
            _errorbar(table, [r["triangles"] for r in rows],
                      [r["times_s"]["total_s"] for r in rows], fmt="o",
                      label=device_id + (f" (alpha {alpha:.3f})" if alpha is not None else ""))
    report, known = data["report_times_s"], data["report_triangles"]
    table.plot([known[n] for n in report if n in known], [report[n] for n in report if n in known],
               "s-", color="crimson", label=f"the report (alpha {data['report_alpha_first_last']:.3f})")
    target = data["target_speedup"]
    table.axhspan(min(report.values()) / target, max(report.values()) / target, color="green",
                  alpha=0.08, label=f"{target:g}x faster than the report")
    width, height = data["resolution"]
    table.set(xscale="log", yscale="log", xlabel="triangles", ylabel="build + render, s",
              title=f"time ~ triangles^alpha, {width}x{height}, diffuse + shadows")
    plain_log(table, x=True)
    table.legend(fontsize=7)
    last = results["config"]["build_cases"][-1] if results["config"]["build_cases"] else None
    _stages(stages, [(f"{d}\n{r['builder']}", r) for d, rows in results["build"].items()
                     for r in rows if r["case"] == last])
    names = list(dict.fromkeys(n for s in results["trace"]["scenes"] for n in s["participants"]))
    _throughput(speed, [(f"{s['name']}\n{w['name']}", w) for s in results["trace"]["scenes"]
                        for w in s["workloads"]], names)
    return save(figure, path)
