"""The bench commands a user runs, in their --quick form: what each prints
and writes, the devices they pick, and the helpers whose figures they
derive (surface sizes, fits, rates).  Never asserts speed."""
import json
import math
import subprocess
import sys

import numpy as np
import pytest
from bench_support import ROOT, check_json

pytest.importorskip("matplotlib")

from bench import build, common, gpu, large  # noqa: E402

PNG = b"\x89PNG\r\n\x1a\n"


def test_every_bench_is_a_module_of_the_package():
    for name in ("bench", "bench.build", "bench.trace", "bench.large"):
        done = subprocess.run([sys.executable, "-m", name, "--help"], cwd=ROOT,
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 0 and "--quick" in done.stdout, (name, done.stderr)


def test_build_quick_writes_its_figures(suite_device, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(common, "DOCS", tmp_path / "docs")
    returned = build.main(["--quick", "--devices", suite_device.id, "--out", str(tmp_path),
                           "--no-progress", "--docs"])
    written = json.loads((tmp_path / "build.json").read_text())
    assert written["devices"].keys() == returned["devices"].keys() == {suite_device.id}
    check_json(written)
    device = written["devices"][suite_device.id]
    assert device["errors"] == []
    config = build.QUICK
    names = [common.surface(n).name for n in config.sizes] + list(config.meshes) + [config.scene]
    assert sorted((c["case"], c["builder"]) for c in device["cases"]) == sorted(
        (n, b) for n in names for b in build.BUILDERS)
    for case in device["cases"]:
        assert case["deterministic"] and case["sah_cost"] > 0 and case["triangles"] > 0
        assert set(case["times_ms"]) >= {"sort", "device", "wall"}
        # the last refit moves the vertices back: the boxes are the built ones again
        assert case["refit"]["sah_cost_after"] == pytest.approx(case["sah_cost"], rel=1e-3)
    costs = {(c["case"], c["builder"]): c["sah_cost"] for c in device["cases"]}
    for name, value in device["sah_ratios"].items():
        assert value == pytest.approx(costs[name, "hlbvh"] / costs[name, "lbvh"])
    for png in (tmp_path / "build.png", tmp_path / "docs" / "bench_build.png"):
        assert png.read_bytes()[:8] == PNG
    out = capsys.readouterr().out
    assert f"=== {suite_device.id} ===" in out and "tree quality" in out


def test_large_quick_reports_its_build_and_memory(suite_device, tmp_path, capsys):
    result = large.main(["--quick", "--devices", suite_device.id, "--out", str(tmp_path)])
    assert json.loads((tmp_path / "large.json").read_text())["triangles"] == result["triangles"]
    assert result["tree"]["leaves"] >= 1 and result["times_ms"]["wall"]["median"] > 0
    memory = result["rss_bytes"]
    assert 0 < memory["before"] <= memory["first_build"] <= memory["rebuilds"]
    assert "peak RSS" in capsys.readouterr().out


def test_gpu_quick_takes_every_measurement_of_issue_57(suite_device, tmp_path, capsys):
    """The script a lent GPU runs first, run here in its --quick form so
    that it works when one comes: every figure present and positive, and
    the interop probe's answer: the device's own extensions, and, with the
    extension claimed where the device has none, its ctypes query made and
    its failure recorded, not raised."""
    result = gpu.main(["--quick", "--devices", suite_device.id, "--out", str(tmp_path)])
    found = result["devices"][suite_device.id]
    assert json.loads((tmp_path / "gpu.json").read_text())["devices"].keys() == {suite_device.id}
    assert found["build"]["wall_ms"]["median"] > 0 and found["build"]["device_ms"]["median"] > 0
    assert 0 < found["camera"]["wall_share_of_kernel"]
    assert found["small"]["rays"] == 1024 and found["small"]["call_ms"]["median"] > 0
    assert found["on_device"]["rays"] == found["camera"]["rays"]
    assert 0 < found["on_device"]["wall_share_of_kernel"]
    assert found["on_device"]["small_call_ms"]["median"] > 0
    assert found["path"]["msamples_per_s"] > 0
    # staging only on request, and off zero copy the A/B of the two copy paths
    assert found["engine"]["staging"] is False
    assert ("other_path" in found) == (not found["engine"]["zero_copy"])
    if "other_path" in found:
        assert found["other_path"]["staging"] is True
        assert found["other_path"]["small_call_ms"]["median"] > 0
        assert found["other_path"]["camera_wall_mrays_per_s"] > 0
    offered = sorted(e for e in suite_device.cl_device.extensions.split()
                     if "external" in e or "semaphore" in e)
    assert found["interop"]["extensions"] == offered
    if "cl_khr_external_memory" not in offered:
        assert found["interop"]["import_handle_types"] == []
    assert "1K-ray call ms" in capsys.readouterr().out
    section = gpu.markdown(result)  # what --docs puts into bench/RESULTS.md
    assert section.startswith("<!-- begin gpu -->") and section.rstrip().endswith("end gpu -->")
    assert f"**{suite_device.id}**" in section and "Msamples/s" in section

    class Claimed:  # a device that says it has the extension, as a GPU's driver may
        extensions = "cl_khr_external_memory"
        int_ptr = suite_device.cl_device.int_ptr
    answer = gpu.interop(Claimed())
    assert answer["extensions"] == ["cl_khr_external_memory"]
    (types,) = answer["import_handle_types"]
    assert types.startswith("(query failed: clGetDeviceInfo returned -30")  # CL_INVALID_VALUE


def test_devices_are_picked_by_name_and_the_rest_listed_as_skipped(suite_device):
    chosen, skipped = common.pick_devices(f"{suite_device.id},no-such-device")
    assert [d.id for d in chosen] == [suite_device.id]
    assert skipped == [{"device": "no-such-device", "problem": "no OpenCL device matches "
                                                               "this name"}]
    with pytest.raises(SystemExit, match="no working OpenCL device"):
        common.devices_or_exit("no-such-device")


@pytest.mark.parametrize("triangles", [1_000, 50_000])
def test_surface_is_one_closed_surface_of_about_the_size_asked(triangles):
    trimesh = pytest.importorskip("trimesh")
    mesh = common.surface(triangles)
    assert abs(mesh.triangle_count - triangles) <= 0.1 * triangles + 20
    shape = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert shape.is_watertight and shape.volume > 0  # closed, wound outwards
    lo, hi = common.bounds([mesh])  # the same box at every size, to a few per cent
    np.testing.assert_allclose(hi - lo, [8.0, 2.0, 8.0], atol=0.35)


def test_fits_rates_and_ratios():
    sizes = np.array([1e3, 1e4, 1e5, 3e6])
    assert common.fit_exponent(sizes, 0.02 * sizes**0.37) == pytest.approx(0.37)
    assert common.fit_exponent(sizes, np.full(4, 5.0)) == pytest.approx(0.0, abs=1e-12)
    assert common.fit_exponent([1000], [1.0]) is None
    assert common.rates(2_000_000, [1.0, 2.0, 4.0]) == {"median": 1.0, "min": 0.5, "max": 2.0}
    assert common.summary([3, 1, 2]) == {"median": 2, "min": 1, "max": 3}
    assert common.ratio(3.0, 2.0) == 1.5 and common.ratio(1.0, 0.0) is None
    assert math.isclose(common.fit_exponent([1, 10], [1, 100]), 2.0)
