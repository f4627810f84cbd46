"""RESULTS.md of the benchmark suite, from its results (suite.json).

Every number in RESULTS.md is read from the suite's results, and each table
names the suite.json key it comes from.  A missing figure (a failed or
skipped measurement) shows as "-".
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from . import plots
from .common import spread, write_json

#: RESULTS.md's section titles, in order.
SECTIONS = ("Highlights", "1. Devices", "2. The original report's table, reproduced",
            "3. Peers", "4. Tree quality: LBVH vs HLBVH", "5. How this was measured")
#: Rows whose timed runs kept fewer cores than this busy on average are marked.
LOW_CORES = 1.5


def _num(value, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return f"{value:,}"
    return f"{value:,.{digits}f}"


def _times(value, digits: int = 1) -> str:
    return "-" if value is None else f"{value:,.{digits}f}x"


def md_table(headers: list[str], rows: list[list], left: int = 1) -> str:
    """A markdown table; the first ``left`` columns left-aligned, the others right."""
    align = ["---"] * left + ["---:"] * (len(headers) - left)
    lines = ["| " + " | ".join(headers) + " |", "| " + " | ".join(align) + " |"]
    lines += ["| " + " | ".join(c if isinstance(c, str) else _num(c) for c in row) + " |"
              for row in rows]
    return "\n".join(lines)


def _json_key(text: str) -> str:
    return f"*JSON: `suite.json` → {text}*"


def _ours(names) -> list[str]:
    """Our HLBVH participants among ``names`` (LBVH ones are "<device> lbvh")."""
    return [n for n in names if " " not in n]


# ---------------------------------------------------------------- highlights

def highlights(suite: dict) -> list[str]:
    """The few lines a newcomer reads first (markdown emphasis included)."""
    out = []
    reference = suite["reference"]
    for device_id, r in reference["devices"].items():
        total = r["times_s"]["total_s"]["median"]
        line = (f"**Reference scene** ({r['scene']}, {r['triangles']:,} triangles, "
                f"{r['width']}x{r['height']}, diffuse + shadows) on {device_id}: build + render "
                f"**{total:.2f} s** (build {r['times_s']['build_s']['median']:.2f} s, render "
                f"{r['times_s']['render_s']['median']:.2f} s)")
        if r.get("speedup"):
            line += (f"; the report took about {reference['report_s']:g} s: "
                     f"**{r['speedup']:.1f}x faster**")
        out.append(line)
    table = suite["table"]
    for device_id, entry in table["devices"].items():
        factors = [r["speedup"] for r in entry["rows"] if r["speedup"] is not None]
        if factors:
            out.append(f"**The report's table** on {device_id}: {min(factors):.1f}x to "
                       f"{max(factors):.1f}x faster than the report; "
                       f"{sum(f >= table['target_speedup'] for f in factors)} of {len(factors)} "
                       f"rows >= {table['target_speedup']:g}x")
        if entry["alpha"] is not None:
            out.append(f"**Scaling** on {device_id}: time ~ triangles^alpha with alpha = "
                       f"**{entry['alpha']:.3f}** over the table's rows (target <= "
                       f"{table['target_alpha']})")
    scenes = suite["trace"]["scenes"]
    scene = next((s for s in scenes if s["name"] == reference["scene"]),
                 scenes[-1] if scenes else None)
    for w in scene["workloads"] if scene else []:
        best = max(_ours(w["ratios"]), default=None,
                   key=lambda d: w["results"][d]["intersect_mrays"]["median"])
        parts = [f"{peer} {_times(r['intersect'], 2)}" for peer, r in
                 (w["ratios"][best] if best else {}).items() if r["intersect"] is not None]
        if parts:
            out.append(f"**Peers**, {scene['name']} {w['name']}, closest hit on {best}: "
                       f"{w['results'][best]['intersect_mrays']['median']:.1f} Mrays/s; our "
                       f"speed over the peer's: " + ", ".join(parts))
    for device_id, rows in list(suite["tree_quality"].items())[:1]:
        for row in (r for r in rows if "vs_lbvh" in r):
            v = row["vs_lbvh"]
            out.append(f"**Tree quality** ({row['scene']}, {device_id}): HLBVH's SAH cost is "
                       f"{v['sah_cost']:.2f}x LBVH's, with {v['nodes']:.2f}x its nodes; "
                       f"closest-hit speed HLBVH / LBVH: " + ", ".join(
                           f"{w.split(' ')[0]} {x:.2f}x" for w, x in v["mrays"].items()))
    if suite["errors"]:
        out.append(f"**{len(suite['errors'])} measurement(s) failed**: see section 5")
    return out


def summary_text(suite: dict) -> str:
    """The highlights as plain text, for the terminal."""
    return "\n".join("- " + line.replace("**", "") for line in highlights(suite))


# ---------------------------------------------------------------- sections

def _header(suite: dict, links: dict) -> list[str]:
    m, config = suite["machine"], suite["config"]
    return [
        "# hlbvh_cl benchmark results", "",
        f"Measured on {suite['date']} with `{suite['command']}` ({suite['mode']} mode, "
        f"{suite['elapsed_s'] / 60:.1f} min).", "",
        f"- **Machine**: {m['processor']}, {m['cpus']} logical CPUs; {m['platform']}; "
        f"Python {m['python']}, numpy {m['numpy']}, pyopencl {m['pyopencl']}, "
        f"hlbvh_cl {m['hlbvh_cl']}.",
        f"- **Load average** (1, 5, 15 min): "
        f"{', '.join(f'{x:.2f}' for x in suite['loadavg_start'])} at the start, "
        f"{', '.join(f'{x:.2f}' for x in suite['loadavg_end'])} at the end; above "
        f"{m['cpus']} means other processes were running too.",
        f"- **Noise**: every figure is the median of {config['repeats']} run(s) after a "
        f"warm-up, with (min-max) beside it; every ratio is between two figures of this run.",
        f"- **Raw numbers**: {links['json']}; each table names its key.",
        "", f"![the report's table, build stages and ray throughput]({links['plot']})",
    ]


def _devices_section(suite: dict) -> list[str]:
    rows = []
    for d, i in suite["devices"].items():
        compiled = i.get("compile_s") or {}
        rows.append([d, i["name"], i["platform"], i["driver"], i["compute_units"],
                     " / ".join(f"{b} {_num(x, 2)}" for b, x in (compiled.get("build") or {})
                                .items()) or "-", _num(compiled.get("render"), 2)])
    out = [f"## {SECTIONS[1]}", "",
           md_table(["device", "name", "platform", "driver", "compute units",
                     "compile s: build", "compile s: render"], rows, left=4), "",
           "Compile: seconds the first use of the kernels took beyond a warm run (first build "
           "minus the median rebuild, per builder; a 1x1 render), compiled or loaded from the "
           "on-disk caches. Kept out of every other figure.", "",
           _json_key("`devices` (`compile_s`)"), "", "### Build time per stage", "",
           "Device time of each stage, ms, median of the rebuilds; wall = the host's time around "
           "`Scene.rebuild()`, median (min-max); cores = CPU time over wall time (a CPU device's "
           "threads run in this process).", ""]
    rows, stages = [], []
    for device_id, results in suite["build"].items():
        for r in results:
            stages = stages or [k for k in r["times_ms"] if k not in ("device", "wall")]
            rows.append([device_id, r["case"], r["builder"], r["triangles"],
                         *[_num(r["times_ms"][s]["median"], 1) for s in stages],
                         _num(r["times_ms"]["device"]["median"], 1),
                         spread(r["times_ms"]["wall"]), _num(r["cores_used"], 2)])
    out += [md_table(["device", "case", "builder", "triangles", *stages, "device", "wall",
                      "cores"], rows, left=3), "",
            _json_key('`build["<device>"][i].times_ms.<stage>`, `.refit`, `.cores_used`'),
            "", "### Ray throughput", "",
            "Closest-hit and any-hit queries, numpy arrays in and out, Mrays/s, median "
            "(min-max); the same rays for every participant (section 3).", ""]
    rows = [[d, s["name"], w["name"], w["rays"], spread(r["intersect_mrays"], digits=2),
             spread(r["occluded_mrays"], digits=2)]
            for s in suite["trace"]["scenes"] for w in s["workloads"]
            for d in suite["devices"] if (r := w["results"].get(d))]
    out += [md_table(["device", "scene", "rays", "count", "closest hit", "any hit"], rows,
                     left=3), "",
            _json_key('`trace.scenes[i].workloads[j].results["<device>"]`')]
    reference = suite["reference"]
    width, height = reference["resolution"]
    rows = [[d, r["triangles"], spread(r["times_s"]["build_s"], digits=3),
             spread(r["times_s"]["render_s"], digits=3), spread(r["times_s"]["total_s"], digits=3),
             _num(r["render_mrays"], 1), _num(r["cores_used"], 2), _num(r["load_s"], 2),
             _times(r.get("speedup"))] for d, r in reference["devices"].items()]
    out += ["", "### The reference scene", "",
            f"`{reference['scene']}` at {width}x{height}, diffuse shading with shadows: "
            "`Scene.rebuild()` then `Renderer.render()`, seconds; reading the file (load) apart.",
            "", md_table(["device", "triangles", "build", "render", "build + render",
                          "render Mrays/s", "cores", "load", "vs report's 40 s"], rows), "",
            _json_key('`reference.devices["<device>"]`')]
    for device_id, r in reference["devices"].items():
        if "image_vs" in r:
            diff = r["image_vs"]
            out.append(f"\n{device_id}'s image against {diff['device']}'s: "
                       f"{100 * diff['pixels_differing']:.3f}% of pixels differ, by at most "
                       f"{diff['max_channel_difference']} of 255.")
    return out


def _table_section(suite: dict) -> list[str]:
    table = suite["table"]
    devices, report, known = list(table["devices"]), table["report_times_s"], \
        table["report_triangles"]
    width, height = table["resolution"]
    out = [f"## {SECTIONS[2]}", "",
           f"Each row: `scenes/<mesh>.toml` (the mesh on a 2-triangle ground) built and rendered "
           f"at {width}x{height}, diffuse + shadows, seconds, median (min-max); x = the report's "
           f"time / ours. The report gives triangle counts only for its first and last rows; "
           f"our armadillo and Lucy are decimated copies (`scenes/README.md`).", ""]
    headers = ["scene", "report triangles", "our triangles", "report s"]
    for device_id in devices:
        headers += [device_id, "x"]
    rows = []
    scenes = [n + ".toml" for n in report] + sorted(
        {r["scene"] for d in devices for r in table["devices"][d]["rows"] if not r["in_report"]})
    for scene in scenes:
        stem = scene.removesuffix(".toml")
        measured = [next((r for r in table["devices"][d]["rows"] if r["scene"] == scene), None)
                    for d in devices]
        triangles = next((r["triangles"] for r in measured if r), None)
        row = [f"`{scene}`", _num(known[stem]) if stem in known else ("n/a" if stem in report
                                                                      else "-"),
               _num(triangles) if triangles else "not run",
               f"{report[stem]:.3f}" if stem in report else "-"]
        for r in measured:
            few = r is not None and r["cores_used"] < LOW_CORES
            row += [spread(r["times_s"]["total_s"], digits=3) + (" ‡" if few else "")
                    if r else "-", _times(r["speedup"] if r else None)]
        rows.append(row)
    out += [md_table(headers, rows), "",
            f"‡ fewer than {LOW_CORES} cores busy on average during the timed runs.", "",
            _json_key('`table.devices["<device>"].rows[i]`, `table.report_times_s`')]
    out += [f"- {d}: alpha = **{e['alpha']:.3f}** (least squares in log-log over the report's "
            f"rows); target <= {table['target_alpha']}." for d, e in table["devices"].items()
            if e["alpha"] is not None]
    out.append(f"- The report: alpha = {table['report_alpha_first_last']:.3f} through its first "
               f"and last rows.")
    return out


def _speeds(result: dict | None) -> list[str]:
    """A participant's cells of one workload: closest hit, any hit, hits."""
    if result is None:
        return ["failed", "-", "-"]
    return [spread(result["intersect_mrays"], digits=2),
            spread(result["occluded_mrays"], digits=2), _num(result["hits"])]


def _peers_section(suite: dict) -> list[str]:
    out = [f"## {SECTIONS[3]}", "",
           "In the same run and on the same rays as our devices (bench/peers.py); primary rays "
           "through a pinhole camera, incoherent rays from a sphere around the objects to random "
           "points of their box (bench/trace.py). Peers see the scene's meshes as one.", "",
           md_table(["peer", "version", "what", "available"],
                    [[n, p["version"] or "-", p["label"],
                      "yes" if p["available"] else f"no: {p['problem']}"]
                     for n, p in suite["peers"].items()], left=3)]
    for i, scene in enumerate(suite["trace"]["scenes"]):
        workloads = scene["workloads"]
        headers = ["participant", "build s"]
        for w in workloads:
            headers += [f"{w['name']}: closest", "any", "hits"]
        rows = [[n, spread(scene["build_times_s"].get(n), digits=3)]
                + [c for w in workloads for c in _speeds(w["results"].get(n))]
                for n in scene["participants"]]
        out += ["", f"### `{scene['name']}` ({scene['triangles']:,} triangles)", "",
                "Mrays/s, median (min-max); build: seconds from the arrays to a structure ready "
                "to trace (ours: `Scene(meshes)`, kernels compiled before).", "",
                md_table(headers, rows), ""]
        for w in workloads:
            differing = [f"{n} on {r['disagreement']['intersect'] * w['rays']:.0f} ray(s)"
                         for n, r in w["results"].items() if max(r["disagreement"].values()) > 0]
            out.append(f"- {w['name']}: the same hits and misses as {w['reference']}"
                       + (", ray for ray." if not differing
                          else ", except " + "; ".join(differing) + "."))
        pairs = [(d, p) for w in workloads[:1] for d in _ours(w["ratios"]) for p in w["ratios"][d]]
        if pairs:
            headers = ["ours / peer"] + [h for w in workloads for h in (f"{w['name']}: closest",
                                                                        "any")]
            rows = [[f"{d} / {p}"] + [_times(w["ratios"].get(d, {}).get(p, {}).get(q), 2)
                                      for w in workloads for q in ("intersect", "occluded")]
                    for d, p in pairs]
            out += ["", "Our Mrays/s over the peer's (> 1x: ours is faster):", "",
                    md_table(headers, rows)]
        out += ["", _json_key(f'`trace.scenes[{i}].workloads[j].results["<participant>"]`, '
                              f'`.ratios["<device>"]["<peer>"]`, `.build_times_s`')]
    return out


def _tree_section(suite: dict) -> list[str]:
    out = [f"## {SECTIONS[4]}", "",
           "The same scenes built by plain LBVH (Karras 2012 radix tree) and by HLBVH (SAH top "
           "over Morton clusters). SAH cost with C_t = C_i = 1 relative to the root's area; build "
           "wall ms from section 1; closest-hit Mrays/s from section 3, both trees traced in the "
           "same rounds.", ""]
    workloads = next((list(r["mrays"]) for rows in suite["tree_quality"].values() for r in rows),
                     [])
    rows = []
    for device_id, entries in suite["tree_quality"].items():
        rows += [[device_id, r["scene"], r["builder"], _num(r["sah_cost"], 2), r["nodes"],
                  r["leaves"], r["depth"], spread(r["build_ms"]),
                  *[spread(r["mrays"].get(w), digits=2) for w in workloads]] for r in entries]
        rows += [[device_id, r["scene"], "*HLBVH / LBVH*", _num(v["sah_cost"], 3),
                  _num(v["nodes"], 3), "", "", "", *[_times(v["mrays"].get(w), 2)
                                                     for w in workloads]]
                 for r in entries if (v := r.get("vs_lbvh"))]
    return out + [md_table(["device", "scene", "builder", "SAH cost", "nodes", "leaves", "depth",
                            "build ms", *workloads], rows, left=3), "",
                  _json_key('`tree_quality["<device>"][i]`')]


def _method_section(suite: dict) -> list[str]:
    out = [f"## {SECTIONS[5]}", "",
           f"- `{suite['command']}` from the repository root, {suite['mode']} mode "
           f"(`bench/__main__.py`, `Config`).",
           "- Builds (`bench/build.py`, `measure`): built once (compiling), rebuilt once to warm "
           "up, then rebuilt and refitted `repeats` times.",
           "- Renders (`bench/render.py`, `time_renders`): each file read and built (timed "
           "apart), a 1x1 render compiles, one rebuild + render warms up, then `repeats` rounds "
           "of rebuild + render of every scene in turn.",
           "- Rays (`bench/trace.py`, `bench_case`): each participant built, each query run once "
           "to warm up, then `repeats` rounds of one call per participant, each after an untimed "
           "call of its own; wall time of a call, numpy in and out.",
           f"- Peak memory {suite['peak_rss_bytes'] / 2**30:.1f} GiB."]
    if suite["errors"]:
        out += ["", "Failed measurements:", ""]
        out += [f"- {e['where']}: `{e['error'].splitlines()[0]}`" for e in suite["errors"]]
    return out


def markdown(suite: dict, links: dict) -> str:
    parts = [_header(suite, links), ["", f"## {SECTIONS[0]}", ""]
             + [f"- {line}" for line in highlights(suite)],
             [""] + _devices_section(suite), [""] + _table_section(suite),
             [""] + _peers_section(suite), [""] + _tree_section(suite),
             [""] + _method_section(suite)]
    return "\n".join(line for part in parts for line in part) + "\n"


def kept_sections(path: Path) -> str:
    """The sections other benches write into RESULTS.md (bench/queries.py),
    each between "<!-- begin NAME -->" and "<!-- end NAME -->": kept as they are."""
    import re
    old = path.read_text() if path.exists() else ""
    return "".join(f"\n{m.group(0)}\n" for m in
                   re.finditer(r"<!-- begin (\S+) -->.*?<!-- end \1 -->", old, re.S))


def write_all(suite: dict, json_path: Path | None, plot_path: Path,
              markdown_path: Path) -> list[Path]:
    """The suite's JSON (unless None), its plot and RESULTS.md; returns the paths."""
    written = [write_json(json_path, suite)] if json_path else []
    try:
        written.append(plots.suite(suite, plot_path))
    except Exception as error:  # a plot must not lose the tables
        suite["errors"].append({"where": "plot", "error": f"{type(error).__name__}: {error}"})
    markdown_path = Path(markdown_path)
    markdown_path.parent.mkdir(parents=True, exist_ok=True)

    def link(path: Path) -> str:
        return Path(os.path.relpath(path, markdown_path.parent)).as_posix()

    links = {"plot": link(plot_path),
             "json": f"[`{link(json_path)}`]({link(json_path)})" if json_path else
             "`bench/results/suite.json`, written by each run (not committed)"}
    markdown_path.write_text(markdown(suite, links) + kept_sections(markdown_path))
    return written + [markdown_path]
