"""python -m bench.ab: a checkout against itself gives identical hits and
the ratios of the rates it measured, on default and compact trees;
differing hits are told apart; a folder that is not a checkout is refused.
Never asserts speed."""
import numpy as np
import pytest
from bench_support import ROOT, check_json

from bench import ab


@pytest.mark.parametrize("compact", [False, True], ids=["default", "compact"])
def test_a_checkout_against_itself_has_identical_hits(suite_device, tmp_path, capsys, compact):
    returned = ab.main([str(ROOT), str(ROOT), "--quick", "--rounds", "1", "--scene",
                        "cornell_box.xml", "--devices", suite_device.id, "--out", str(tmp_path)]
                       + (["--compact"] if compact else []))
    check_json(returned)
    assert returned["compact"] is compact
    entry = returned["devices"][suite_device.id]
    assert set(entry) == set(ab.WORKLOADS)
    for name, found in entry.items():
        assert found["identical_hits"] is True
        (base,), (change,), (ratio,) = (found["base_rays_per_s"], found["change_rays_per_s"],
                                        found["ratios"])
        assert base > 0 and change > 0 and ratio == pytest.approx(change / base)
    assert "same hits" in capsys.readouterr().out


def test_differing_hits_are_told_apart(tmp_path):
    hits = {f"camera_{field}": np.arange(4, dtype=np.float32)
            for field in ("t", "geom_id", "prim_id", "u", "v")}
    np.savez(tmp_path / "a.npz", **hits)
    np.savez(tmp_path / "b.npz", **hits)
    assert ab.identical(tmp_path / "a.npz", tmp_path / "b.npz", "camera")
    hits["camera_u"] = np.nextafter(hits["camera_u"], np.float32(2))
    np.savez(tmp_path / "b.npz", **hits)
    assert not ab.identical(tmp_path / "a.npz", tmp_path / "b.npz", "camera")


def test_a_folder_that_is_not_a_checkout_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="is not a checkout of hlbvh_cl"):
        ab.main([str(tmp_path), str(ROOT), "--out", str(tmp_path)])
