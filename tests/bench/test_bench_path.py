"""python -m bench.path --quick: its figures follow from the times it
measured, and it says where our render's device time went.  Never asserts
speed."""
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
