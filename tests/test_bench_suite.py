"""`python -m bench` (bench/__main__.py) on its hidden --tiny configuration:
one small scene, the suite's device, 1 repeat, into a temporary folder.

Never asserts speed: only that suite.json, the plots and RESULTS.md are
complete and sane: finite positive times, triangle counts from trimesh,
hits that agree across devices and peers and with a direct embreex call on
the same rays, and derived figures (speed-ups, exponents, ratios) that
follow from the measured ones.
"""
import copy
import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from bench_support import json_numbers
import trimesh

pytest.importorskip("matplotlib")
rtcs = pytest.importorskip("embreex.rtcore_scene")
from embreex.mesh_construction import TriangleMesh  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # `bench` is a package of the checkout, not of the install

import bench.__main__ as suite_main  # noqa: E402
from bench import render as render_bench  # noqa: E402
from bench import report  # noqa: E402
from bench import trace as trace_bench  # noqa: E402

from hlbvh_cl.scenefile import load_scene_file  # noqa: E402

CONFIG = suite_main.TINY
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def ours(suite_device):
    """The id the suite's device has in the bench's results."""
    return suite_device.id


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, ours):
    folder = tmp_path_factory.mktemp("suite")
    argv = ["--tiny", "--devices", ours, "--out", str(folder / "results"),
            "--markdown", str(folder / "RESULTS.md"), "--no-progress"]
    returned = suite_main.main(argv)
    written = json.loads((folder / "results" / "suite.json").read_text())
    return returned, written, folder




def _spreads(value, path="suite"):
    """Every {median, min, max} in a JSON tree, with where it is."""
    if isinstance(value, dict):
        if set(value) == {"median", "min", "max"}:
            yield path, value
            return
        for key, item in value.items():
            yield from _spreads(item, f"{path}.{key}")
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from _spreads(item, f"{path}[{i}]")


def _scene_triangles(name: str) -> int:
    """A single-mesh scene file's triangles: trimesh's face count plus the 2-triangle ground."""
    description = load_scene_file(ROOT / "scenes" / name)
    assert len(description.meshes) == 1 and description.ground is not None
    path = ROOT / "scenes" / "meshes" / Path(name).with_suffix(".ply").name
    return len(trimesh.load(path, process=False).faces) + 2


def _embree_hits(vertices, faces, origins, directions) -> int:
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, vertices, faces)
    return int((scene.run(origins, directions) >= 0).sum())


# ---------------------------------------------------------------- structure

def test_json_is_complete_finite_and_positive(tiny_run, ours):
    returned, written, _ = tiny_run
    assert written["mode"] == "tiny" and written["errors"] == []
    assert written["command"].startswith(f"python -m bench --tiny --devices {ours}")
    assert set(written) == set(returned)
    assert list(written["devices"]) == [ours]
    device = written["devices"][ours]
    assert device["name"] and device["driver"] and device["compute_units"] >= 1
    assert len(written["loadavg_start"]) == len(written["loadavg_end"]) == 3
    assert written["machine"]["processor"] and written["machine"]["cpus"] >= 1
    for where, number in json_numbers(written, "suite"):
        assert math.isfinite(number), where
    spreads = list(_spreads(written))
    assert len(spreads) > 20
    for where, s in spreads:
        assert 0 <= s["min"] <= s["median"] <= s["max"], (where, s)
        if where.endswith(("_s", "_mrays", "wall", "total", "build_ms")) or "times_s" in where:
            assert s["min"] > 0, (where, s)


def test_builds_cover_both_builders(tiny_run, ours):
    _, written, _ = tiny_run
    results = written["build"][ours]
    assert sorted((r["case"], r["builder"]) for r in results) == sorted(
        (case, builder) for case in CONFIG.build_cases for builder in ("hlbvh", "lbvh"))
    for r in results:
        assert r["triangles"] == _scene_triangles(r["case"])
        assert r["times_ms"]["wall"]["median"] > 0 and r["deterministic"] is True
    # compilation: each builder's first build beyond its median rebuild, and the 1x1 render
    compiled = written["devices"][ours]["compile_s"]
    assert set(compiled["build"]) == {"hlbvh", "lbvh"}
    for r in results:
        expected = max(0.0, r["first_build_ms"]["wall"] - r["times_ms"]["wall"]["median"]) / 1e3
        assert compiled["build"][r["builder"]] == pytest.approx(expected)
    first_render = written["table"]["devices"][ours]["rows"][0]
    assert compiled["render"] == first_render["compile_s"]["render"] >= 0


def test_render_timings_are_consistent(tiny_run, ours):
    _, written, _ = tiny_run
    rows = written["table"]["devices"][ours]["rows"]
    reference = written["reference"]["devices"][ours]
    assert [r["scene"] for r in rows] == list(CONFIG.table_scenes)
    assert reference["scene"] == CONFIG.reference_scene
    for r, (width, height) in [(row, CONFIG.table_resolution) for row in rows] + [
            (reference, CONFIG.reference_resolution)]:
        assert r["device"] == ours
        assert r["triangles"] == _scene_triangles(r["scene"])
        assert (r["width"], r["height"]) == (width, height)
        assert r["image"]["shape"] == [height, width, 3]
        assert r["primary_rays"] == r["secondary_rays"] == width * height  # one shadow ray each
        assert len(r["runs"]) == r["repeats"] == CONFIG.repeats
        for run in r["runs"]:  # the total is timed around both
            assert run["total_s"] >= run["build_s"] + run["render_s"] - 1e-9
            assert min(run.values()) > 0
        assert r["times_s"]["total_s"]["median"] == pytest.approx(
            float(np.median([run["total_s"] for run in r["runs"]])))
        assert r["load_s"] >= 0 and min(r["compile_s"].values()) >= 0
        assert r["cores_used"] > 0
    # not the report's resolution: no speed-up claimed, one row: no exponent
    assert all(r["speedup"] is None for r in rows)
    assert written["table"]["devices"][ours]["alpha"] is None
    assert written["reference"]["devices"][ours]["speedup"] is None


def test_speedups_and_exponent_follow_from_the_times(tiny_run, ours):
    _, written, _ = tiny_run
    # the tiny run's row, seen at the report's resolution, and a second row
    # made from it with 10x the triangles and twice the time
    # (min, median and max spread apart: the median is the figure)
    row = copy.deepcopy(written["table"]["devices"][ours]["rows"][0])
    median = row["times_s"]["total_s"]["median"]
    row["times_s"]["total_s"] = {"median": median, "min": 0.9 * median, "max": 1.3 * median}
    other = copy.deepcopy(row)
    other["scene"], other["triangles"] = "lucy.toml", row["triangles"] * 10
    other["times_s"]["total_s"] = {key: 2 * seconds
                                   for key, seconds in row["times_s"]["total_s"].items()}
    config = dataclasses.replace(CONFIG, table_resolution=render_bench.REPORT_RESOLUTION)
    table = suite_main.table_section({ours: [copy.deepcopy(row), other]}, config)
    first, second = table["devices"][ours]["rows"]
    assert first["speedup"] == pytest.approx(
        render_bench.REPORT_TIMES_S["bunny_small"] / row["times_s"]["total_s"]["median"])
    assert second["speedup"] == pytest.approx(
        render_bench.REPORT_TIMES_S["lucy"] / other["times_s"]["total_s"]["median"])
    assert table["devices"][ours]["alpha"] == pytest.approx(math.log(2) / math.log(10))
    assert table["report_alpha_first_last"] == pytest.approx(
        math.log(3.009 / 2.287) / math.log(2_805_572 / 1_392))


# ---------------------------------------------------------------- rays

def test_hits_agree_across_participants_and_with_embree(tiny_run, ours):
    _, written, _ = tiny_run
    (scene,) = written["trace"]["scenes"]
    assert scene["name"] == CONFIG.trace_scenes[0] and scene["errors"] == {}
    assert scene["triangles"] == _scene_triangles(scene["name"])
    participants = set(scene["participants"])
    peers = {name for name, p in written["peers"].items() if p["available"]}
    assert participants == {ours, f"{ours} lbvh"} | peers
    assert "embreex" in peers

    # the same rays, regenerated, traced by embreex in one plain call
    description = load_scene_file(ROOT / "scenes" / scene["name"])
    meshes = [mesh for mesh, _ in description.geometries()]
    offsets = np.cumsum([0] + [m.vertex_count for m in meshes[:-1]])
    vertices = np.concatenate([m.vertices for m in meshes])
    faces = np.concatenate([m.faces + np.int32(o) for m, o in zip(meshes, offsets)])
    c = description.camera
    width, height = CONFIG.trace_resolution
    primary = trace_bench.camera_rays(trace_bench.Camera(c.eye, c.target, c.up, c.fov_deg),
                                      width, height)
    boxes = [entry.mesh.bounds() for entry in description.meshes]  # the ground left out
    lo, hi = np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)
    incoherent = trace_bench.incoherent_rays(lo, hi, CONFIG.incoherent_rays,
                                              written["trace"]["seed"])

    primary_load, incoherent_load = scene["workloads"]
    assert primary_load["rays"] == width * height
    assert incoherent_load["rays"] == CONFIG.incoherent_rays
    for workload, rays in ((primary_load, primary), (incoherent_load, incoherent)):
        results = workload["results"]
        assert set(results) == participants
        expected = _embree_hits(vertices, faces, *rays)
        assert 0 < expected < workload["rays"]  # rays both hit and miss
        for name, r in results.items():
            assert r["hits"] == expected, (workload["name"], name)
            assert r["occluded"] == r["hits"], (workload["name"], name)  # tmax = inf
            assert r["disagreement"] == {"intersect": 0.0, "occluded": 0.0}
        for device, per_peer in workload["ratios"].items():
            for peer, ratio in per_peer.items():
                for q in ("intersect", "occluded"):
                    assert ratio[q] == pytest.approx(results[device][f"{q}_mrays"]["median"]
                                                     / results[peer][f"{q}_mrays"]["median"])
    assert set(scene["build_times_s"]) == participants


def test_tree_quality_matches_the_builds(tiny_run, ours):
    _, written, _ = tiny_run
    rows = written["tree_quality"][ours]
    assert [(r["scene"], r["builder"]) for r in rows] == [
        (CONFIG.trace_scenes[0], "hlbvh"), (CONFIG.trace_scenes[0], "lbvh")]
    hlbvh, lbvh = rows
    for r in rows:  # the traced tree is the one section 1 built: builds are deterministic
        built = next(b for b in written["build"][ours]
                     if b["case"] == r["scene"] and b["builder"] == r["builder"])
        assert r["sah_cost"] == pytest.approx(built["sah_cost"])
        assert r["nodes"] == built["nodes"] and r["leaves"] == built["leaves"]
        assert r["triangles"] == _scene_triangles(r["scene"])
        assert 1 <= r["leaves"] <= r["triangles"]
        assert r["build_ms"] == built["times_ms"]["wall"]
    v = hlbvh["vs_lbvh"]
    assert v["sah_cost"] == pytest.approx(hlbvh["sah_cost"] / lbvh["sah_cost"])
    assert v["nodes"] == pytest.approx(hlbvh["nodes"] / lbvh["nodes"])
    for workload, ratio in v["mrays"].items():
        assert ratio == pytest.approx(hlbvh["mrays"][workload]["median"]
                                      / lbvh["mrays"][workload]["median"])
    # kernels only: the device times section 3 recorded for each tree
    (scene,) = written["trace"]["scenes"]
    assert set(v["kernel_mrays"]) == {w["name"] for w in scene["workloads"]}
    for w in scene["workloads"]:
        kernel_s = {r["participant"]: w["results"][r["participant"]]["intersect_kernel_s"]
                    for r in rows}
        assert v["kernel_mrays"][w["name"]] == pytest.approx(
            kernel_s[f"{ours} lbvh"]["median"] / kernel_s[ours]["median"])
        assert hlbvh["kernel_mrays"][w["name"]]["median"] == pytest.approx(
            w["rays"] / kernel_s[ours]["median"] / 1e6)


# ---------------------------------------------------------------- RESULTS.md

def test_results_md_has_every_section(tiny_run):
    _, written, folder = tiny_run
    text = (folder / "RESULTS.md").read_text()
    positions = [text.find(f"## {title}") for title in report.SECTIONS]
    assert -1 not in positions and positions == sorted(positions), positions
    assert f"`{written['command']}`" in text
    assert written["machine"]["processor"] in text
    assert ", ".join(f"{x:.2f}" for x in written["loadavg_start"]) in text
    assert ", ".join(f"{x:.2f}" for x in written["loadavg_end"]) in text
    for seconds in render_bench.REPORT_TIMES_S.values():  # the report's whole table
        assert f"{seconds:.3f}" in text
    assert "1,392" in text and "2,805,572" in text and "n/a" in text
    for scene in render_bench.REPORT_TIMES_S:
        assert f"`{scene}.toml`" in text
    for peer in written["peers"]:
        assert f"| {peer} |" in text
    assert text.count("suite.json") >= 6  # tables name their keys
    for link in ("results/suite.json", "results/suite_table.png", "results/suite_builds.png",
                 "results/suite_throughput.png"):
        assert f"({link})" in text, link
        path = folder / link
        assert path.is_file(), link
        if path.suffix == ".png":
            assert path.read_bytes()[:8] == PNG_MAGIC, link


def test_no_working_device_is_a_clear_error(tmp_path):
    with pytest.raises(SystemExit, match="no working OpenCL device"):
        suite_main.main(["--tiny", "--devices", "no-such-device", "--out", str(tmp_path),
                         "--no-progress"])
    assert not any(tmp_path.iterdir())


def test_a_failing_scene_leaves_the_others_timed(tmp_path, ours):
    scenes = ROOT / "scenes"
    missing = tmp_path / "missing.toml"
    outcomes = render_bench.time_renders([scenes / "bunny_small.toml", missing], ours, 32, 24, 1)
    assert isinstance(outcomes[1], Exception) and "missing.toml" in str(outcomes[1])
    result, image = outcomes[0]
    assert result["scene"] == "bunny_small.toml" and image.shape == (24, 32, 3)
    assert result["times_s"]["total_s"]["median"] > 0
