"""`python -m bench` on its --tiny configuration (one small scene, the suite's
device, embreex, 1 repeat) into a temporary folder: suite.json, the plot and
RESULTS.md are complete, hits agree across participants, and the derived
figures (speed-ups, exponents, ratios) follow from the measured ones.
Never asserts speed."""
import copy
import dataclasses
import json
import math

import pytest
from bench_support import ROOT, check_json

pytest.importorskip("matplotlib")
pytest.importorskip("embreex")

import bench.__main__ as suite_main  # noqa: E402
from bench import render, report  # noqa: E402

CONFIG = suite_main.TINY


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, suite_device):
    folder = tmp_path_factory.mktemp("suite")
    committed = (ROOT / "bench" / "RESULTS.md").stat().st_mtime
    returned = suite_main.main(["--tiny", "--devices", suite_device.id, "--peers", "embreex",
                                "--out", str(folder), "--no-progress"])
    assert (ROOT / "bench" / "RESULTS.md").stat().st_mtime == committed  # no --docs
    return returned, json.loads((folder / "suite.json").read_text()), folder


def test_suite_json_is_complete(tiny_run, suite_device):
    returned, written, folder = tiny_run
    ours = suite_device.id
    assert written["mode"] == "tiny" and written["errors"] == [] and set(written) == set(returned)
    assert written["command"].startswith(f"python -m bench --tiny --devices {ours}")
    check_json(written)
    assert sorted((r["case"], r["builder"]) for r in written["build"][ours]) == sorted(
        (case, b) for case in CONFIG.build_cases for b in ("hlbvh", "lbvh"))
    (row,) = written["table"]["devices"][ours]["rows"]
    reference = written["reference"]["devices"][ours]
    for r, (width, height) in ((row, CONFIG.table_resolution),
                               (reference, CONFIG.reference_resolution)):
        assert r["image"]["shape"] == [height, width, 3]
        assert r["primary_rays"] == r["secondary_rays"] == width * height  # one shadow ray each
        for run in r["runs"]:
            assert run["total_s"] == pytest.approx(run["build_s"] + run["render_s"])
    assert (folder / "suite.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_hits_agree_and_tree_ratios_follow(tiny_run, suite_device):
    _, written, _ = tiny_run
    ours = suite_device.id
    (scene,) = written["trace"]["scenes"]
    assert set(scene["participants"]) == {ours, f"{ours} lbvh", "embreex"}
    assert set(scene["build_times_s"]) == set(scene["participants"])
    for w in scene["workloads"]:
        hits = {name: r["hits"] for name, r in w["results"].items()}
        assert len(set(hits.values())) == 1 and 0 < hits["embreex"] < w["rays"], hits
    hlbvh, lbvh = written["tree_quality"][ours]
    assert (hlbvh["builder"], lbvh["builder"]) == ("hlbvh", "lbvh")
    v = hlbvh["vs_lbvh"]
    assert v["sah_cost"] == pytest.approx(hlbvh["sah_cost"] / lbvh["sah_cost"])
    assert v["nodes"] == pytest.approx(hlbvh["nodes"] / lbvh["nodes"])
    for name, ratio in v["mrays"].items():
        assert ratio == pytest.approx(hlbvh["mrays"][name]["median"] / lbvh["mrays"][name]["median"])


def test_speedups_and_exponent_follow_from_the_times(tiny_run, suite_device):
    # the tiny run's row seen at the report's resolution, and a second row
    # made from it with 10x the triangles and twice the time
    _, written, _ = tiny_run
    row = copy.deepcopy(written["table"]["devices"][suite_device.id]["rows"][0])
    other = copy.deepcopy(row)
    other["scene"], other["triangles"] = "lucy.toml", row["triangles"] * 10
    other["times_s"]["total_s"] = {k: 2 * s for k, s in row["times_s"]["total_s"].items()}
    config = dataclasses.replace(CONFIG, table_resolution=render.REPORT_RESOLUTION)
    table = suite_main.table_section({"d": [row, other]}, config)
    first, second = table["devices"]["d"]["rows"]
    seconds = row["times_s"]["total_s"]["median"]
    assert first["speedup"] == pytest.approx(render.REPORT_TIMES_S["bunny_small"] / seconds)
    assert second["speedup"] == pytest.approx(render.REPORT_TIMES_S["lucy"] / (2 * seconds))
    assert table["devices"]["d"]["alpha"] == pytest.approx(math.log(2) / math.log(10))
    assert table["report_alpha_first_last"] == pytest.approx(
        math.log(3.009 / 2.287) / math.log(2_805_572 / 1_392))


def test_results_md_has_every_section(tiny_run):
    _, written, folder = tiny_run
    text = (folder / "RESULTS.md").read_text()
    positions = [text.find(f"## {title}") for title in report.SECTIONS]
    assert -1 not in positions and positions == sorted(positions), positions
    assert f"`{written['command']}`" in text and written["machine"]["processor"] in text
    for seconds in render.REPORT_TIMES_S.values():  # the report's whole table
        assert f"{seconds:.3f}" in text
    assert "(suite.png)" in text and "(suite.json)" in text
    assert "| embreex |" in text
