"""python -m bench.path --quick: its figures follow from the times it
measured, and it says where our render's device time went.  Never asserts
speed."""
import argparse
import json

import pytest

from bench import path as bench_path
from hlbvh_cl.render.renderer import STAGES

pytest.importorskip("mitsuba")


def test_quick_run_writes_rates_ratios_and_stage_times(suite_device, tmp_path, capsys):
    returned = bench_path.main(["--quick", "--devices", suite_device.id, "--rounds", "1",
                                "--out", str(tmp_path)])
    written = json.loads((tmp_path / "path.json").read_text())
    assert set(written["scenes"]) == set(returned["scenes"]) == {"cornell", "materials"}
    for name, entry in written["scenes"].items():
        width, height, spp = bench_path.QUICK[name]
        assert entry["samples"] == width * height * spp
        ours = entry[suite_device.id]
        rate = entry["samples"] / ours["seconds"]["median"] / 1e6
        assert ours["msamples_per_s"] == pytest.approx(rate)
        assert ours["ratio_to_mitsuba"] == pytest.approx(rate / entry["mitsuba_msamples_per_s"])
        stages = ours["stages_ms"]
        assert set(stages) == {*STAGES, "total"}
        assert all(stages[stage] >= 0.0 for stage in STAGES)
        assert stages["closest"] > 0.0 and stages["shade"] > 0.0
        assert sum(stages[stage] for stage in STAGES) == pytest.approx(stages["total"])
        # device time of the stages cannot exceed the render's wall time
        assert stages["total"] <= 1e3 * ours["seconds"]["max"]
        # the shadow rays each depth cast: at most one a path, some at depth 0
        depths = ours["depths"]
        assert len(depths["shadow_rays"]) == len(depths["paths"])
        assert 0 < depths["shadow_rays"][0] <= depths["paths"][0]
        assert all(s <= p for s, p in zip(depths["shadow_rays"], depths["paths"]))
    out = capsys.readouterr().out
    assert "where our render's device time goes" in out
    for entry in written["scenes"].values():
        # Mitsuba's rate is its rounds' median time
        seconds = entry["mitsuba_seconds"]
        assert seconds["min"] <= seconds["median"] <= seconds["max"]
        assert entry["mitsuba_msamples_per_s"] == pytest.approx(
            entry["samples"] / seconds["median"] / 1e6)
        # equal time: each renderer's relMSE is the mean over its renders of
        # the seeds, which are independent (so not all the same)
        quality = entry["equal_time"]
        assert quality["seeds"] == list(bench_path.EQUAL_TIME_SEEDS)
        assert {"mitsuba", suite_device.id} <= set(quality["renders"])
        for render in quality["renders"].values():
            per_seed = render["relmse_seeds"]
            assert len(per_seed) == len(bench_path.EQUAL_TIME_SEEDS)
            assert render["relmse"] == pytest.approx(sum(per_seed) / len(per_seed))
            assert len(set(per_seed)) > 1 and min(per_seed) > 0.0


def test_depth_rows_give_each_depth_s_shares_and_ray_rates():
    """Shares of the device total, and rays over device time (Mrays/s: rays
    per ms / 1e3); a depth that cast no shadow ray has no shadow rate, and
    one that shaded no path no row."""
    depths = {"paths": [4000, 1000, 0], "shadow_rays": [2000, 0, 0],
              "closest": [2.0, 5.0, 0.0], "shade": [1.0, 1.0, 0.0],
              "occluded": [4.0, 0.5, 0.0], "resolve": [1.0, 0.5, 0.0]}
    rows = bench_path.depth_rows("s", "d", depths, total_ms=20.0)
    assert rows == [["s", "d", 0, 4000, 2000, "10.0%", "5.0%", "20.0%", "5.0%", "2.0", "0.5"],
                    ["s", "d", 1, 1000, 0, "25.0%", "5.0%", "2.5%", "2.5%", "0.2", "-"]]


def test_a_mitsuba_variant_that_does_not_start_is_named_and_scalar_rgb_timed(tmp_path, capsys):
    # --mitsuba cuda_ad_rgb on a machine without a GPU: the table must not
    # pass scalar_rgb off as the variant asked for
    child = bench_path.mitsuba_child({"cornell": bench_path.cornell_xml(tmp_path)},
                                     "no_such_variant")
    try:
        assert child.variant == "scalar_rgb"
    finally:
        child.close()
    assert "Mitsuba's no_such_variant does not start here; timing scalar_rgb" in \
        capsys.readouterr().out


def test_depth_sweep_times_each_max_depth_against_mitsuba(suite_device, tmp_path, capsys):
    returned = bench_path.main(["--quick", "--devices", suite_device.id, "--rounds", "1",
                                "--depths", "1,3", "--out", str(tmp_path)])
    written = json.loads((tmp_path / "path_depths.json").read_text())
    assert written["max_depths"] == returned["max_depths"] == [1, 3]
    assert set(written["depth_sweep"]) == {"cornell", "materials"}
    out = capsys.readouterr().out
    assert "render time by max depth" in out
    for name, scene in written["depth_sweep"].items():
        width, height, spp = bench_path.QUICK[name]
        assert scene["samples"] == width * height * spp
        assert set(scene["depths"]) == {"1", "3"}
        medians = {}
        for depth, entry in scene["depths"].items():
            theirs = entry["mitsuba_seconds"]["median"]
            ours = entry[suite_device.id]
            mine = ours["seconds"]["median"]
            assert ours["ratio_to_mitsuba"] == pytest.approx(theirs / mine)
            assert ours["msamples_per_s"] == pytest.approx(scene["samples"] / mine / 1e6)
            assert set(ours["stages_ms"]) == {*STAGES, "total"}
            medians[depth] = (mine, theirs)
        # the table's increments are the medians' differences, one scene row each
        added = (f"{1e3 * (medians['3'][0] - medians['1'][0]):+.0f}",
                 f"{1e3 * (medians['3'][1] - medians['1'][1]):+.0f}")
        rows = [line.split() for line in out.splitlines() if line.startswith(name)]
        assert [row[1] for row in rows] == ["1", "3"]
        assert rows[1][-2:] == list(added)


def test_depth_sweep_arguments_are_checked(tmp_path):
    for bad, says in [("0", "'0' is not a max depth"), ("2,x", "'x' is not a max depth"),
                      ("3,2", "must increase"), ("2,2", "must increase")]:
        with pytest.raises(argparse.ArgumentTypeError, match=says):
            bench_path.depth_list(bad)
    assert bench_path.depth_list("1, 2,8") == [1, 2, 8]
    with pytest.raises(SystemExit):
        bench_path.main(["--depths", "2,1", "--out", str(tmp_path)])
    # a scene file's max depth is rewritten where it has exactly one
    copy = bench_path.with_max_depth(bench_path.cornell_xml(tmp_path), 3)
    assert copy.read_text().count('<integer name="max_depth" value="3"/>') == 1
    (tmp_path / "none.xml").write_text("<scene/>")
    with pytest.raises(ValueError, match="expected one"):
        bench_path.with_max_depth(tmp_path / "none.xml", 3)
