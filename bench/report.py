"""RESULTS.md and the plots of the benchmark suite, from its results (suite.json).

    write_all(suite, out_dir, markdown_path) -> the files written

Every number in RESULTS.md is read from ``suite`` and each table names the
suite.json key it comes from.  Missing figures (a failed or skipped
measurement) show as "–".
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # common.py, as build.py and trace.py do

import numpy as np  # noqa: E402
from common import pyplot, save_figure, write_json  # noqa: E402

#: RESULTS.md's section titles, in order (the test looks for them).
SECTIONS = ("Highlights", "1. Devices", "2. The original report's table, reproduced",
            "3. Peers", "4. Tree quality: LBVH vs HLBVH", "5. How this was measured")

# bench/render.py's report figures, repeated in the suite's JSON under "table"
# and "reference"; read from there so that the JSON alone explains RESULTS.md.

#: Rows whose timed runs kept fewer cores than this busy on average are marked.
LOW_CORES = 1.5
CORES_NOTE = ("cores = CPU time over wall time of the timed runs (a CPU device's threads run in "
              "this process): how many of the machine's {cpus} logical CPUs the work got; well "
              "below {cpus} means it left one idle or another process took one.")


# ---------------------------------------------------------------- formatting

def _num(value, digits: int = 3) -> str:
    if value is None:
        return "–"
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return f"{value:,}"
    return f"{value:,.{digits}f}"


def _spread(times: dict | None, scale: float = 1.0, digits: int = 3) -> str:
    """median (min–max)"""
    if not times:
        return "–"
    return (f"{times['median'] * scale:,.{digits}f} "
            f"({times['min'] * scale:,.{digits}f}–{times['max'] * scale:,.{digits}f})")


def _times(value, digits: int = 1) -> str:
    return "–" if value is None else f"{value:,.{digits}f}x"


def _md_table(headers: list[str], rows: list[list], left: int = 1) -> str:
    """A markdown table; the first ``left`` columns left-aligned, the others right."""
    align = ["---"] * left + ["---:"] * (len(headers) - left)
    lines = ["| " + " | ".join(headers) + " |", "| " + " | ".join(align) + " |"]
    lines += ["| " + " | ".join(_num(c) if not isinstance(c, str) else c for c in row) + " |"
              for row in rows]
    return "\n".join(lines)


def _json_key(text: str) -> str:
    return f"*JSON: `suite.json` → {text}*"


def _first_device(suite: dict) -> str | None:
    return next(iter(suite["devices"]), None)


def _table_row(suite: dict, device_id: str, scene: str) -> dict | None:
    rows = suite["table"]["devices"].get(device_id, {}).get("rows", [])
    return next((r for r in rows if r["scene"] == scene), None)


def _workload(scene: dict, kind: str) -> dict | None:
    return next((w for w in scene["workloads"] if w["kind"] == kind), None)


def _main_trace_scene(suite: dict) -> dict | None:
    """The traced scene the highlights quote: the reference scene if traced, else the last."""
    scenes = suite["trace"]["scenes"]
    return next((s for s in scenes if s["name"] == suite["reference"]["scene"]),
                scenes[-1] if scenes else None)


# ---------------------------------------------------------------- highlights

def highlights(suite: dict) -> list[str]:
    """The few lines a newcomer reads first (markdown emphasis included)."""
    out = []
    first = _first_device(suite)
    reference = suite["reference"]
    for device_id, r in reference["devices"].items():
        total = r["times_s"]["total_s"]["median"]
        line = (f"**Reference scene** ({r['scene']}, {r['triangles']:,} triangles, "
                f"{r['width']}x{r['height']}, diffuse + shadows) on {device_id}: build + render "
                f"**{total:.2f} s** (build {r['times_s']['build_s']['median']:.2f} s, render "
                f"{r['times_s']['render_s']['median']:.2f} s)")
        if r.get("speedup"):
            line += (f"; the report took about {reference['report_s']:g} s: **{r['speedup']:.1f}x "
                     f"faster**; target {reference['target_s']:g} s: "
                     f"{'met' if total <= reference['target_s'] else 'not met'}")
        out.append(line)
    table = suite["table"]
    target_x, target_alpha = table["target_speedup"], table["target_alpha"]
    for device_id, entry in table["devices"].items():
        rows = [r for r in entry["rows"] if r["in_report"] and r["speedup"] is not None]
        if rows:
            factors = [r["speedup"] for r in rows]
            met = sum(f >= target_x for f in factors)
            out.append(f"**The report's table** at 1280x720 on {device_id}: "
                       f"{min(factors):.1f}x to {max(factors):.1f}x faster than the report; "
                       f"{met} of {len(rows)} rows >= {target_x:g}x (the target: every row)")
        if entry["alpha"] is not None:
            alpha = entry["alpha"]
            out.append(f"**Scaling** on {device_id}: time ~ triangles^alpha with alpha = "
                       f"**{alpha:.3f}** over the table's rows (target <= {target_alpha}: "
                       f"{'met' if alpha <= target_alpha else 'not met'})"
                       + (f"; {entry['alpha_with_extra']:.3f} with the 2.9M-triangle reference "
                          f"scene at 1280x720 added" if entry["alpha_with_extra"] is not None
                          else ""))
    scene = _main_trace_scene(suite)
    if scene and first:
        for kind in ("primary", "incoherent"):
            w = _workload(scene, kind)
            # the targets name the fastest device present, which may differ per ray kind
            devices = [d for d in (w["ratios"] if w else {}) if " " not in d]  # not "... lbvh"
            best = max(devices, key=lambda d: w["results"][d]["intersect_mrays"]["median"],
                       default=None)
            ratios = w["ratios"][best] if best else {}
            parts = [f"{peer} {_times(r['intersect'], 2)}" for peer, r in ratios.items()
                     if r.get("intersect") is not None and " " not in peer]
            if parts:
                ours = w["results"][best]["intersect_mrays"]["median"]
                out.append(f"**Peers**, {scene['name']} {w['name']}, closest hit, fastest "
                           f"device {best}: {ours:.1f} Mrays/s, i.e. " + ", ".join(parts)
                           + " the peer's speed (> 1x: ours is faster)")
    for device_id, rows in suite["tree_quality"].items():
        for row in rows:
            if "vs_lbvh" in row and device_id == first:
                v = row["vs_lbvh"]
                speed = ", ".join(
                    f"{w.split(' ')[0]} {x:.2f}x (kernels {_times(v['kernel_mrays'].get(w), 2)})"
                    for w, x in v["mrays"].items())
                out.append(f"**Tree quality** ({row['scene']}, {device_id}): HLBVH's SAH cost is "
                           f"{v['sah_cost']:.2f}x LBVH's, with {v['nodes']:.2f}x its nodes; "
                           f"closest-hit speed HLBVH / LBVH: {speed}")
    if suite["errors"]:
        out.append(f"**{len(suite['errors'])} measurement(s) failed**: see section 5")
    return out


def summary_text(suite: dict) -> str:
    """The highlights as plain text, for the terminal."""
    return "\n".join("- " + line.replace("**", "") for line in highlights(suite))


# ---------------------------------------------------------------- sections

def _header(suite: dict, links: dict) -> list[str]:
    m = suite["machine"]
    start, end = suite["loadavg_start"], suite["loadavg_end"]
    config = suite["config"]
    return [
        "# hlbvh_cl benchmark results",
        "",
        f"Measured on {suite['date']} with `{suite['command']}` ({suite['mode']} mode, "
        f"{suite['elapsed_s'] / 60:.1f} min).",
        "",
        f"- **Machine**: {m['processor']}, {m['cpus']} logical CPUs; {m['platform']}; "
        f"Python {m['python']}, numpy {m['numpy']}, pyopencl {m['pyopencl']}, "
        f"hlbvh_cl {m['hlbvh_cl']}.",
        f"- **Load average** (1, 5, 15 min): {', '.join(f'{x:.2f}' for x in start)} at the start, "
        f"{', '.join(f'{x:.2f}' for x in end)} at the end. The machine is shared: a 1-minute "
        f"load above its {m['cpus']} CPUs means others were running too.",
        f"- **Noise**: every figure is the median of {config['repeats']} run(s) after a warm-up "
        f"(the reference render: {config['reference_repeats']}), with (min–max) beside it; every "
        f"ratio is between two figures of this one run.",
        f"- **Raw numbers**: [`{links['json']}`]({links['json']}); each table names its key.",
    ]


def _stages(result: dict) -> list[str]:
    return [k for k in result["times_ms"] if k not in ("total", "wall")]


def _rest_ms(result: dict) -> float:
    """A build's median device total minus the medians of its listed stages."""
    times = result["times_ms"]
    return times["total"]["median"] - sum(times[s]["median"] for s in _stages(result))


def _devices_section(suite: dict, links: dict) -> list[str]:
    out = [f"## {SECTIONS[1]}", ""]
    rows = []
    for d, i in suite["devices"].items():
        compiled = i.get("compile_s") or {}
        build = compiled.get("build") or {}
        rows.append([d, i["name"], i["platform"], i["driver"], i["compute_units"],
                     " / ".join(f"{b} {_num(x, 2)}" for b, x in build.items()) or "–",
                     _num(compiled.get("render"), 2)])
    out += [_md_table(["device", "name", "platform", "driver", "compute units",
                       "compile s: build", "compile s: render"], rows, left=4), "",
            "Compile: seconds the first use of the kernels in this process took beyond a warm "
            "run (first build minus the median rebuild, per builder; a 1x1 render), kernels "
            "compiled or loaded from pyopencl's and the driver's on-disk caches. Kept out of "
            "every other figure.", "", _json_key("`devices` (`compile_s`)")]
    for s in suite["skipped_devices"]:
        out.append(f"\nSkipped `{s['device']}`: {s['problem'].splitlines()[0]}")

    stages = None
    out += ["", "### Build time per stage", "",
            "Device time of each stage (profiling events), ms, median of the rebuilds; wall = "
            "the host's time around `scene.rebuild()`, median (min–max). First build (with "
            "kernel compilation) and refits are in the JSON.", ""]
    rows = []
    for device_id, results in suite["build"].items():
        for r in results:
            stages = stages or _stages(r)
            rows.append([device_id, r["case"], r["builder"], r["triangles"],
                         *[_num(r["times_ms"][s]["median"], 1) for s in stages],
                         _num(_rest_ms(r), 1), _num(r["times_ms"]["total"]["median"], 1),
                         _spread(r["times_ms"]["wall"], digits=1), _num(r["cores_used"], 2)])
    if rows:
        out += [_md_table(["device", "case", "builder", "triangles", *stages, "rest",
                           "device total", "wall", "cores"], rows, left=3), "",
                "rest = device total minus the stages listed: the stages bench/build.py does "
                "not list apart (`widen`, the 8-wide copy of the tree that traversal reads, "
                "which `Scene.rebuild` adds to the total).", "",
                CORES_NOTE.format(cpus=suite["machine"]["cpus"]), "",
                _json_key('`build["<device>"][i].times_ms.<stage>` (ms, median/min/max), '
                          '`.cores_used`'), "",
                f"![build stages]({links['builds']})"]

    out += ["", "### Ray throughput", "",
            "Closest-hit and any-hit queries, numpy arrays in and out, Mrays/s: median "
            "(min–max). The same rays for every participant (section 3).", ""]
    rows = []
    for scene in suite["trace"]["scenes"]:
        for w in scene["workloads"]:
            for device_id in suite["devices"]:
                r = w["results"].get(device_id)
                if r:
                    kernels = r.get("intersect_kernel_s")
                    rows.append([device_id, scene["name"], w["name"], w["rays"],
                                 _spread(r["intersect_mrays"], digits=2),
                                 _num(w["rays"] / kernels["median"] / 1e6, 2) if kernels else "–",
                                 _spread(r["occluded_mrays"], digits=2)])
    out += [_md_table(["device", "scene", "rays", "count", "closest hit",
                       "closest hit, kernels only", "any hit"], rows, left=3), "",
            _json_key('`trace.scenes[i].workloads[j].results["<device>"].intersect_mrays`, '
                      '`.intersect_kernel_s` (seconds), `.occluded_mrays`')]

    reference = suite["reference"]
    out += ["", "### The reference scene", "",
            f"`{reference['scene']}` at {reference['resolution'][0]}x{reference['resolution'][1]}, "
            "diffuse shading with shadows, 1 sample per pixel: `scene.rebuild()` then "
            "`scene.render()`, seconds. Reading the file (load) is apart; the kernels were "
            "compiled before (the devices table).", ""]
    rows = []
    for device_id, r in reference["devices"].items():
        rays = r["primary_rays"] + r["secondary_rays"]
        rows.append([device_id, r["triangles"], _spread(r["times_s"]["build_s"]),
                     _spread(r["times_s"]["render_s"]), _spread(r["times_s"]["total_s"]),
                     _num(rays / 1e6, 2), _num(r["render_mrays"], 1),
                     _num(r.get("cores_used"), 2), _num(r["load_s"], 2),
                     _times(r.get("speedup"))])
    out += [_md_table(["device", "triangles", "build", "render", "build + render", "Mrays",
                       "render Mrays/s", "cores", "load (apart)", "vs report's 40 s"], rows), "",
            _json_key('`reference.devices["<device>"].times_s.{build_s,render_s,total_s}`, '
                      '`.cores_used`, `.load_s`, `.speedup`')]
    diffs = [(d, r["image_vs"]) for d, r in reference["devices"].items() if "image_vs" in r]
    for device_id, diff in diffs:
        out.append(f"\n{device_id}'s image against {diff['device']}'s: "
                   f"{100 * diff['pixels_differing']:.3f}% of pixels differ, by at most "
                   f"{diff['max_channel_difference']} of 255.")
    return out


def _table_section(suite: dict, links: dict) -> list[str]:
    table = suite["table"]
    devices = list(table["devices"])
    width, height = table["resolution"]
    report = table["report_times_s"]
    known = table["report_triangles"]
    out = [f"## {SECTIONS[2]}", "",
           f"Each row: the scene file `scenes/<mesh>.toml` (the mesh on a 2-triangle ground) "
           f"built and rendered at {width}x{height}, diffuse + shadows: `scene.rebuild()` + "
           f"`scene.render()`, seconds, median (min–max); x = the report's time / ours. The "
           f"report gives its triangle counts only as \"1,392 ... 2,805,572\": the others are "
           f"n/a. Our bunny is the original scan (69,451 triangles), our armadillo and Lucy are "
           f"decimated copies (86,482 and 99,970; "
           f"`scenes/README.md`), far fewer than the report's 2.8M-triangle Lucy.", ""]
    if (width, height) != tuple(table["report_resolution"]):
        out += [f"*{suite['mode']} mode: {width}x{height}, not the report's "
                f"{table['report_resolution'][0]}x{table['report_resolution'][1]}: no speed-ups.*",
                ""]
    headers = ["scene", "report triangles", "our triangles", "report s"]
    for device_id in devices:
        headers += [device_id, "x"]
    names = [name + ".toml" for name in report]
    extra = sorted({r["scene"] for d in devices for r in table["devices"][d]["rows"]
                    if not r["in_report"]})
    rows = []
    for scene in names + extra:
        stem = scene.removesuffix(".toml")
        measured = [_table_row(suite, d, scene) for d in devices]
        triangles = next((r["triangles"] for r in measured if r), None)
        row = [f"`{scene}`" + ("" if stem in report else " (not in the report)"),
               _num(known[stem]) if stem in known else ("n/a" if stem in report else "–"),
               _num(triangles) if triangles else "not run",
               f"{report[stem]:.3f}" if stem in report else "–"]
        for r in measured:
            few = r is not None and r.get("cores_used", LOW_CORES) < LOW_CORES
            row += [(_spread(r["times_s"]["total_s"]) + (" ‡" if few else "")) if r else "–",
                    _times(r.get("speedup") if r else None)]
        rows.append(row)
    out += [_md_table(headers, rows), ""]
    if any("‡" in cell for row in rows for cell in row if isinstance(cell, str)):
        out += [f"‡ fewer than {LOW_CORES} cores busy on average during the timed runs (CPU "
                f"time over wall time, `cores_used`): the work kept a core idle, or another "
                f"process took one.", ""]
    out += [_json_key('`table.devices["<device>"].rows[i].times_s.total_s`, `.speedup`, '
                      '`.triangles`, `.cores_used`; the report\'s figures: '
                      '`table.report_times_s`, `table.report_triangles`'), ""]
    for device_id in devices:
        entry = table["devices"][device_id]
        if entry["alpha"] is not None:
            out.append(f"- {device_id}: alpha = **{entry['alpha']:.3f}** (least squares in "
                       f"log-log over the report's rows)"
                       + (f", {entry['alpha_with_extra']:.3f} with the extra row"
                          if entry["alpha_with_extra"] is not None else "")
                       + f"; target <= {table['target_alpha']}.")
    out.append(f"- The report: {table['report_alpha_first_last']:.3f} through its first and "
               f"last rows (the only two with known triangle counts).")
    out += ["", _json_key('`table.devices["<device>"].alpha`, `.alpha_with_extra`, '
                          '`table.report_alpha_first_last`'), "",
            f"![time against triangles]({links['table']})", ""]
    reference = suite["reference"]
    for device_id, r in reference["devices"].items():
        if r.get("speedup"):
            out.append(f"- Reference scene, {r['width']}x{r['height']}, {device_id}: "
                       f"**{r['times_s']['total_s']['median']:.2f} s** against the report's "
                       f"about {reference['report_s']:g} s ({r['speedup']:.1f}x) and the "
                       f"{reference['target_s']:g} s target (section 1).")
    return out


def _peers_section(suite: dict, links: dict) -> list[str]:
    trace = suite["trace"]
    out = [f"## {SECTIONS[3]}", "",
           f"In the same run and on the same rays (float32 numpy arrays) as our devices: "
           f"embreex (Embree 4, rays split over {suite['embree_threads']} Python threads), "
           f"Open3D's RaycastingScene, Mitsuba 3 `llvm_ad_rgb` and trimesh's RayMeshIntersector "
           f"(embreex, 1 thread). Primary rays: a pinhole camera (the scene file's, or framed on "
           f"a lone mesh); incoherent rays: from a sphere around the objects towards random "
           f"points of their box (bench/trace.py). Peers see the scene's meshes as one.", ""]
    peers = suite["peers"]
    rows = [[name, p.get("version") or "–", p["label"],
             "yes" if p["available"] else f"no: {p['problem']}"] for name, p in peers.items()]
    out += [_md_table(["peer", "version", "what", "available"], rows, left=3), ""]
    for i, scene in enumerate(trace["scenes"]):
        names = list(scene["participants"])
        workloads = scene["workloads"]
        out += [f"### `{scene['name']}` ({scene['triangles']:,} triangles)", "",
                "Mrays/s, median (min–max), for the closest hit and the any hit of each ray set; "
                "build: seconds from the arrays to a structure ready to trace, median (min–max) "
                "(ours: `Scene(meshes)`, upload included, kernels already compiled); hits: rays "
                "that hit, per ray set.", ""]
        headers = ["participant", "build s"]
        for w in workloads:
            headers += [f"{w['name']}: closest", "any"]
        headers.append("hits")
        rows = []
        for n in names:
            row = [n, _spread(scene["build_times_s"].get(n))]
            for w in workloads:
                r = w["results"].get(n)
                row += ([_spread(r["intersect_mrays"], digits=2),
                         _spread(r["occluded_mrays"], digits=2)] if r else ["failed", "–"])
            row.append(" / ".join(_num(w["results"][n]["hits"]) if n in w["results"] else "–"
                                  for w in workloads))
            rows.append(row)
        out += [_md_table(headers, rows), ""]
        for w in workloads:
            differing = [f"{n} on {r['disagreement']['intersect'] * w['rays']:.0f} ray(s) "
                         f"(closest hit) and {r['disagreement']['occluded'] * w['rays']:.0f} "
                         f"(any hit)" for n, r in w["results"].items()
                         if r.get("disagreement") and max(r["disagreement"].values()) > 0]
            out.append(f"- {w['name']}: every participant finds the same hits and misses as "
                       f"{w.get('reference')}"
                       + (", ray for ray." if not differing
                          else ", ray for ray, except " + "; ".join(differing) + "."))
        pairs = [(d, p) for d in names if " " not in d and scene["participants"][d]["kind"] ==
                 "device" for p in names if scene["participants"][p]["kind"] != "device"]
        if pairs:
            headers = ["ours / peer"]
            for w in workloads:
                headers += [f"{w['name']}: closest", "any"]
            rows = []
            for d, peer in pairs:
                row = [f"{d} / {peer}"]
                for w in workloads:
                    v = w["ratios"].get(d, {}).get(peer, {})
                    row += [_times(v.get("intersect"), 2), _times(v.get("occluded"), 2)]
                rows.append(row)
            out += ["", "Speed ratios, our Mrays/s over the peer's (> 1x: ours is faster):", "",
                    _md_table(headers, rows)]
        out += ["", _json_key(f'`trace.scenes[{i}].build_times_s`, '
                              f'`trace.scenes[{i}].workloads[j].results["<participant>"]` '
                              f'(`intersect_mrays`, `occluded_mrays`, `hits`, `disagreement`), '
                              f'`.ratios["<device>"]["<peer>"]`'), ""]
    out.append(f"![throughput and build times]({links['throughput']})")
    return out


def _tree_section(suite: dict) -> list[str]:
    out = [f"## {SECTIONS[4]}", "",
           "The same scenes built by plain LBVH (Karras 2012 radix tree, one triangle per "
           "leaf) and by HLBVH (SAH top over Morton clusters, SAH-collapsed subtrees). SAH cost "
           "with C_t = C_i = 1 relative to the root's area; build wall ms from section 1; "
           "closest-hit Mrays/s from section 3, where both trees were traced in the same rounds "
           "(one call each per round), so that load from other processes falls on both alike: "
           "\"wall\" from the whole call (numpy in and out), \"kernels\" from the traversal "
           "kernels' device time alone. The wall figure includes the host's share of each call "
           "(copies, conversions), which varies from run to run (see its min–max); the kernel "
           "figure is the tree's own effect.", ""]
    workloads = []
    for entries in suite["tree_quality"].values():
        for r in entries:
            workloads = workloads or list(r["mrays"])
    rows = []
    for device_id, entries in suite["tree_quality"].items():
        for r in entries:
            speeds = []
            for w in workloads:
                speeds += [_spread(r["mrays"].get(w), digits=2),
                           _spread(r["kernel_mrays"].get(w), digits=2)]
            rows.append([device_id, r["scene"], r["builder"], _num(r["sah_cost"], 2), r["nodes"],
                         r["leaves"], r["depth"], _spread(r["build_ms"], digits=1), *speeds])
        for r in entries:  # after both builders' rows
            if "vs_lbvh" in r:
                v = r["vs_lbvh"]
                speeds = []
                for w in workloads:
                    speeds += [_times(v["mrays"].get(w), 2), _times(v["kernel_mrays"].get(w), 2)]
                rows.append([device_id, r["scene"], "*HLBVH / LBVH*", _num(v["sah_cost"], 3),
                             _num(v["nodes"], 3), "", "", "", *speeds])
    headers = ["device", "scene", "builder", "SAH cost", "nodes", "leaves", "depth", "build ms"]
    for w in workloads:
        headers += [f"{w}: wall", "kernels"]
    out += [_md_table(headers, rows, left=3), "",
            _json_key('`tree_quality["<device>"][i]` (`sah_cost`, `nodes`, `build_ms`, `mrays`, '
                      '`kernel_mrays`, `vs_lbvh`)')]
    return out


def _method_section(suite: dict) -> list[str]:
    config = suite["config"]
    out = [f"## {SECTIONS[5]}", "",
           f"- Command: `{suite['command']}` from the repository root; {suite['mode']} mode "
           f"(`bench/__main__.py`, `Config`): {config['repeats']} timed run(s) per figure after a "
           f"warm-up, {config['reference_repeats']} for the reference render.",
           "- Builds: `bench/build.py` `measure()`: the scene is built once (compiling), "
           "rebuilt once to warm up, then rebuilt and refitted `repeats` times.",
           "- Renders: `bench/render.py` `time_renders()`: each scene file is read and built "
           "(both timed apart), a 1x1 render compiles the render kernels, one rebuild + render "
           "of each warms up, then `repeats` rounds time `scene.rebuild()` + `scene.render()` "
           "of every scene in turn (so that load from other processes falls on all rows "
           "alike, and the fitted alpha does not depend on which row it hit). All the scenes "
           "stay loaded meanwhile, and each run follows another scene's, whose data it finds "
           "in the caches; earlier results timed one scene's runs back to back.",
           "- Rays: `bench/trace.py` `bench_case()`: every participant is built, runs each "
           "query once to warm up, then `repeats` rounds of one call per participant (so that "
           "load from other processes falls on all alike); wall time of one call, numpy in and "
           "out; our kernels' device time is kept too.",
           f"- Load average at the start {', '.join(f'{x:.2f}' for x in suite['loadavg_start'])}"
           f", at the end {', '.join(f'{x:.2f}' for x in suite['loadavg_end'])}; peak memory "
           f"{suite['peak_rss_bytes'] / 2**30:.1f} GiB.",
           "- Device time vs wall time, per-stage render times, refits, compilation and image "
           "digests are in the JSON."]
    if suite["errors"]:
        out += ["", "Failed measurements:", ""]
        out += [f"- {e['where']}: `{e['error'].splitlines()[0]}`" for e in suite["errors"]]
    return out


def markdown(suite: dict, links: dict) -> str:
    parts = [_header(suite, links), ["", f"## {SECTIONS[0]}", ""]
             + [f"- {line}" for line in highlights(suite)],
             [""] + _devices_section(suite, links), [""] + _table_section(suite, links),
             [""] + _peers_section(suite, links), [""] + _tree_section(suite),
             [""] + _method_section(suite)]
    return "\n".join(line for part in parts for line in part) + "\n"


# ---------------------------------------------------------------- plots

def plot_table(suite: dict, path: Path) -> Path:
    """Time against triangles in log-log, ours and the report's (its Figure 1)."""
    plt = pyplot()
    figure, axes = plt.subplots(figsize=(7.5, 5))
    table = suite["table"]
    for device_id, entry in table["devices"].items():
        rows = [r for r in entry["rows"] if r["in_report"]]
        if not rows:
            continue
        x = np.array([r["triangles"] for r in rows], float)
        y = np.array([r["times_s"]["total_s"]["median"] for r in rows])
        low = y - [r["times_s"]["total_s"]["min"] for r in rows]
        high = np.array([r["times_s"]["total_s"]["max"] for r in rows]) - y
        label = device_id + (f" (alpha {entry['alpha']:.3f})" if entry["alpha"] is not None else "")
        line = axes.errorbar(x, y, yerr=[low, high], fmt="o", capsize=2, label=label)
        if entry["alpha"] is not None:
            coefficients = np.polyfit(np.log(x), np.log(y), 1)
            grid = np.geomspace(x.min(), x.max(), 20)
            axes.plot(grid, np.exp(np.polyval(coefficients, np.log(grid))), "--",
                      color=line[0].get_color(), alpha=0.7)
        extra = [r for r in entry["rows"] if not r["in_report"]]
        if extra:
            axes.scatter([r["triangles"] for r in extra],
                         [r["times_s"]["total_s"]["median"] for r in extra], marker="x", s=60,
                         color=line[0].get_color(), label=f"{device_id}: " + ", ".join(
                             r["scene"] for r in extra) + " (not in the report)")
    known = table["report_triangles"]
    report = table["report_times_s"]
    names = [n for n in report if n in known]
    axes.plot([known[n] for n in names], [report[n] for n in names], "s-", color="crimson",
              label=f"the report (its 2 rows with known triangles; alpha "
                    f"{table['report_alpha_first_last']:.3f})")
    axes.axhspan(min(report.values()), max(report.values()), color="crimson", alpha=0.08,
                 label="the report's six times")
    target = table["target_speedup"]
    axes.axhspan(min(report.values()) / target, max(report.values()) / target, color="green",
                 alpha=0.08, label=f"the target: {target:g}x faster than the report")
    width, height = table["resolution"]
    axes.set(xscale="log", yscale="log", xlabel="triangles",
             ylabel="build + render, s (median, min-max)",
             title=f"Time ~ Triangles^alpha, {width}x{height}, diffuse + shadows")
    axes.grid(True, which="both", alpha=0.3)
    _plain_ticks(axes.yaxis)
    axes.legend(fontsize=7)
    return _save(figure, path, plt)


def plot_builds(suite: dict, path: Path) -> Path:
    """Stacked device time per build stage, each device and builder, per build case."""
    plt = pyplot()
    cases = sorted({r["case"] for results in suite["build"].values() for r in results})
    figure, axes = plt.subplots(1, max(len(cases), 1), figsize=(5.5 * max(len(cases), 1), 4.5),
                                squeeze=False)
    for ax, case in zip(axes[0], cases):
        bars = [(f"{d}\n{r['builder']}", r) for d, results in suite["build"].items()
                for r in results if r["case"] == case]
        bottom = np.zeros(len(bars))
        for stage in _stages(bars[0][1]) + ["rest"]:
            heights = np.array([_rest_ms(r) if stage == "rest" else r["times_ms"][stage]["median"]
                                for _, r in bars])
            ax.bar([label for label, _ in bars], heights, bottom=bottom, label=stage)
            bottom += heights
        ax.set(ylabel="device time, ms (median)",
               title=f"{case} ({bars[0][1]['triangles']:,} triangles)")
        ax.legend(fontsize=7)
    return _save(figure, path, plt)


def plot_throughput(suite: dict, path: Path) -> Path:
    """Closest-hit Mrays/s of every participant per workload, and build times."""
    plt = pyplot()
    scenes = suite["trace"]["scenes"]
    figure, (speed, builds) = plt.subplots(1, 2, figsize=(14, 5.5),
                                           gridspec_kw={"width_ratios": [2, 1]})
    groups = [(f"{s['name']}\n{w['name']}", w) for s in scenes for w in s["workloads"]]
    names = list(dict.fromkeys(n for s in scenes for n in s["participants"]))
    width = 0.8 / max(len(names), 1)
    for i, name in enumerate(names):
        x = [g for g, (_, w) in enumerate(groups) if name in w["results"]]
        if not x:
            continue
        rates = [groups[g][1]["results"][name]["intersect_mrays"] for g in x]
        median = np.array([r["median"] for r in rates])
        speed.bar(np.array(x) + (i - (len(names) - 1) / 2) * width, median, width,
                  yerr=[median - [r["min"] for r in rates], [r["max"] for r in rates] - median],
                  label=name, capsize=1.5)
    speed.set_xticks(range(len(groups)), [g for g, _ in groups], fontsize=8)
    speed.set(ylabel="closest hit, Mrays/s (median, min-max)", yscale="log",
              title="ray throughput, same rays for all (numpy in, numpy out)")
    speed.grid(True, axis="y", which="both", alpha=0.3)
    _plain_ticks(speed.yaxis)
    speed.legend(fontsize=7, ncol=2)
    width = 0.8 / max(len(scenes), 1)
    for i, scene in enumerate(scenes):
        times = [scene["build_times_s"].get(n) for n in names]
        x = np.arange(len(names)) + (i - (len(scenes) - 1) / 2) * width
        median = np.array([t["median"] if t else np.nan for t in times])
        builds.bar(x, median, width, label=scene["name"])
    builds.set_xticks(range(len(names)), names, rotation=45, ha="right", fontsize=8)
    builds.set(ylabel="build, s (median)", yscale="log", title="build from the arrays")
    builds.grid(True, axis="y", which="both", alpha=0.3)
    _plain_ticks(builds.yaxis)
    builds.legend(fontsize=7)
    return _save(figure, path, plt)


def _plain_ticks(axis) -> None:
    """Log-axis labels as plain numbers (0.1, 2, 20) rather than powers of ten."""
    from matplotlib.ticker import FuncFormatter
    plain = FuncFormatter(lambda value, _: f"{value:g}")
    axis.set_major_formatter(plain)
    axis.set_minor_formatter(plain)


def _save(figure, path: Path, plt) -> Path:
    return save_figure(figure, path, dpi=100)


# ---------------------------------------------------------------- all of it

def write_all(suite: dict, out: Path, markdown_path: Path) -> list[Path]:
    """suite.json and the plots into ``out``, RESULTS.md at ``markdown_path``."""
    out, markdown_path = Path(out), Path(markdown_path)
    paths = {"json": out / "suite.json", "table": out / "suite_table.png",
             "builds": out / "suite_builds.png", "throughput": out / "suite_throughput.png"}
    written = []
    for key, plot in (("table", plot_table), ("builds", plot_builds),
                      ("throughput", plot_throughput)):
        try:
            written.append(plot(suite, paths[key]))
        except Exception as error:  # a plot must not lose the tables
            suite["errors"].append({"where": f"plot {key}", "error": f"{type(error).__name__}: "
                                                                     f"{error}"})
    written.insert(0, write_json(paths["json"], suite))
    markdown_path.parent.mkdir(parents=True, exist_ok=True)
    links = {k: Path(os.path.relpath(p, markdown_path.parent)).as_posix() for k, p in paths.items()}
    markdown_path.write_text(markdown(suite, links))
    written.append(markdown_path)
    return written
