"""python -m bench.depth_rays --quick: the rays it captures are the render's,
depth by depth, and Mitsuba traces the same rays to the same hits.  Never
asserts speed."""
import json

import numpy as np
import pytest

from bench import depth_rays, path as bench_path
from hlbvh_cl.io.scenefile import load

pytest.importorskip("mitsuba")


def test_captured_sets_are_the_rays_the_render_counted(suite_device, tmp_path):
    """Each depth's closest-hit rays are the paths the render shaded there
    (depth 0: every pixel's camera ray) and its shadow rays the ones it
    cast, as Renderer.stats counts them in a render of its own."""
    xml = bench_path.materials_xml(tmp_path)
    width, height, _ = bench_path.QUICK["materials"]
    loaded = load(xml, suite_device.id, defaults={"res_x": width, "res_y": height})
    sets = depth_rays.capture(loaded, width, height)
    renderer = loaded.renderer()
    options = {**loaded.options, "spp": 1, "max_depth": bench_path.MAX_DEPTH}
    renderer.render(loaded.camera, width, height, hdr=True, **options)
    depths = renderer.stats["depths"]
    assert len(sets["closest 0"]) == width * height
    for depth, paths in enumerate(depths["paths"]):
        assert len(sets.get(f"closest {depth}", ())) == paths
        assert len(sets.get(f"shadow {depth}", ())) == depths["shadow_rays"][depth]
    for rays in sets.values():
        assert rays.dtype == np.float32 and rays.shape[1] == depth_rays.RAY_FLOATS
        assert np.isfinite(rays[:, :3]).all() and np.isfinite(rays[:, 4:7]).all()


def test_quick_run_gives_rates_ratios_and_agrees_with_mitsuba(suite_device, tmp_path, capsys):
    returned = depth_rays.main(["--quick", "--devices", suite_device.id, "--rounds", "2",
                                "--scenes", "materials", "--out", str(tmp_path)])
    written = json.loads((tmp_path / "depth_rays.json").read_text())
    assert set(written["scenes"]) == set(returned["scenes"]) == {"materials"}
    scene = written["scenes"]["materials"]
    assert {"closest 0", "shadow 0", "closest 1"} <= set(scene["sets"])
    for key, entry in scene["sets"].items():
        ours, theirs = entry[suite_device.id], entry["mitsuba"]
        assert ours["mrays_per_s"] == pytest.approx(entry["rays"] / ours["seconds"] / 1e6)
        assert ours["ratio"] == pytest.approx(theirs["seconds"] / ours["seconds"])
        # the same rays in the same scene: hit or miss alike but for grazing rays
        assert ours["differ"] <= 2e-3, key
    # some rays of each kind hit, and not all: the check above can fail
    assert 0.0 < scene["sets"]["closest 0"]["hit_fraction"] < 1.0
    assert 0.0 < scene["sets"]["shadow 0"]["hit_fraction"] < 1.0
    assert "the render's rays by depth" in capsys.readouterr().out


def test_unknown_scene_and_rounds_are_refused(tmp_path):
    with pytest.raises(SystemExit, match="--scenes: expected some of cornell, materials"):
        depth_rays.main(["--quick", "--scenes", "kitchen", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="--rounds must be at least 1"):
        depth_rays.main(["--quick", "--rounds", "0", "--out", str(tmp_path)])
