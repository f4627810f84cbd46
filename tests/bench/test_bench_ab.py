"""python -m bench.ab: a checkout against itself gives identical hits and
the ratios of the rates it measured, on default and compact trees, and in
one process, and identical path renders there; differing hits are told
apart; a folder that is not a checkout is refused, and --in-process with
another host, and --renders outside one process or by an unknown name.
Never asserts speed."""
import shutil

import numpy as np
import pytest
from bench_support import ROOT, check_json

from bench import ab


@pytest.mark.parametrize("compact, in_process", [(False, False), (True, False), (False, True)],
                         ids=["default", "compact", "in-process"])
def test_a_checkout_against_itself_has_identical_hits(suite_device, tmp_path, capsys, compact,
                                                      in_process):
    rounds = 2 if in_process else 1
    returned = ab.main([str(ROOT), str(ROOT), "--quick", "--rounds", str(rounds), "--scene",
                        "cornell_box.xml", "--devices", suite_device.id, "--out", str(tmp_path)]
                       + (["--compact"] if compact else [])
                       + (["--in-process"] if in_process else []))
    check_json(returned)
    assert returned["compact"] is compact and returned["in_process"] is in_process
    entry = returned["devices"][suite_device.id]
    assert set(entry) == set(ab.WORKLOADS)
    for name, found in entry.items():
        assert found["identical_hits"] is True
        base, change, ratios = (found["base_rays_per_s"], found["change_rays_per_s"],
                                found["ratios"])
        assert len(base) == len(change) == len(ratios) == rounds
        assert min(base) > 0 and min(change) > 0
        assert ratios == pytest.approx([c / b for b, c in zip(base, change)])
    out = capsys.readouterr().out
    assert "same hits" in out and ("in one process" in out) is in_process


def test_renders_of_a_checkout_against_itself_are_the_same_image(suite_device, tmp_path,
                                                                 capsys):
    returned = ab.main([str(ROOT), str(ROOT), "--quick", "--rounds", "2", "--in-process",
                        "--renders", "cornell", "--devices", suite_device.id,
                        "--out", str(tmp_path)])
    check_json(returned)
    assert returned["renders"] == ["cornell"]
    found = returned["devices"][suite_device.id]["cornell"]
    assert found["identical_images"] is True
    base, change = found["base_samples_per_s"], found["change_samples_per_s"]
    assert len(base) == len(change) == 2 and min(base) > 0 and min(change) > 0
    assert found["ratios"] == pytest.approx([c / b for b, c in zip(base, change)])
    assert "same image" in capsys.readouterr().out


@pytest.mark.parametrize("flags, message", [
    (["--renders", "cornell"], "--renders runs in one process: add --in-process"),
    (["--in-process", "--renders", "cornell,kitchen"], "not 'kitchen'"),
])
def test_renders_are_refused_without_one_process_or_by_an_unknown_name(tmp_path, flags,
                                                                        message):
    with pytest.raises(SystemExit, match=message):
        ab.main([str(ROOT), str(ROOT), "--out", str(tmp_path)] + flags)


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


def test_in_process_refuses_checkouts_whose_hosts_differ(tmp_path):
    other = tmp_path / "other"
    (other / "hlbvh_cl").mkdir(parents=True)
    (other / "hlbvh_cl" / "__init__.py").write_text("# another host\n")
    assert ab.host_difference(ROOT, ROOT) is None
    assert ab.host_difference(other, ROOT) == "hlbvh_cl/__init__.py"
    with pytest.raises(SystemExit, match="hlbvh_cl/__init__.py differs between them"):
        ab.main([str(other), str(ROOT), "--in-process", "--out", str(tmp_path)])


def test_in_process_builds_each_checkouts_own_kernels(suite_device, tmp_path):
    """The one process builds the change's kernels from the change's folder:
    they cannot build, and it fails on them, after the base's code has made
    the workloads with its own.  (That a runtime builds from whichever
    folder kernel_root names: tests/device/test_devices.py.)"""
    change = tmp_path / "change"
    for folder in ("hlbvh_cl", "kernels", "bench"):
        shutil.copytree(ROOT / folder, change / folder,
                        ignore=shutil.ignore_patterns("__pycache__", "results"))
    (change / "scenes").symlink_to(ROOT / "scenes")
    with open(change / "kernels" / "query" / "rays.cl", "a") as source:
        source.write("\n#error the change's own traversal\n")
    with pytest.raises(SystemExit, match=f"a child failed \\({ROOT} {change} "
                                         f"{suite_device.id}\\)(.|\\n)*the change's own traversal"):
        ab.main([str(ROOT), str(change), "--quick", "--rounds", "1", "--scene", "cornell_box.xml",
                 "--devices", suite_device.id, "--in-process", "--out", str(tmp_path)])
