"""python -m bench.cluster: its camera tiles against Camera.rays, its orbit,
and its --quick run, where the cluster's answers must be the one process's.
Never asserts speed."""
import json

import numpy as np
import pytest
from bench_support import ROOT, check_json

import hlbvh_cl

pytest.importorskip("distributed")

from bench import cluster  # noqa: E402


def test_tiles_are_the_cameras_rays_row_by_row():
    camera = hlbvh_cl.Camera((0.3, 1.0, 4.0), (0.0, 0.5, 0.0), fov_deg=50)
    width, height, rows = 40, 30, 6
    origins, directions = camera.rays(width, height)
    pinhole = camera.pinhole(width, height)
    tiles = np.concatenate([cluster.tile_rays(pinhole, width, height, rows, (k, 0, 0))
                            for k in range(height // rows)])
    assert tiles.shape == (height, width, 6) and tiles.dtype == np.float32
    np.testing.assert_array_equal(tiles[..., :3].reshape(-1, 3), origins)
    np.testing.assert_array_equal(tiles[..., 3:].reshape(-1, 3), directions)


def test_the_orbit_turns_about_the_target_at_the_same_distance():
    camera = hlbvh_cl.Camera((1.0, 2.0, 3.0), (0.5, 0.0, -1.0))
    turned = cluster.orbit(camera, 4)
    assert turned[0].eye == pytest.approx(camera.eye)
    distance = [np.linalg.norm(np.subtract(c.eye, c.target)) for c in turned]
    np.testing.assert_allclose(distance, distance[0])
    assert {c.eye[1] for c in turned} == {2.0}
    np.testing.assert_allclose(np.subtract(turned[2].eye, camera.target)[[0, 2]],
                               -np.subtract(camera.eye, camera.target)[[0, 2]], atol=1e-12)


def test_quick_run_answers_as_one_process(suite_device, tmp_path):
    committed = (ROOT / "bench" / "RESULTS.md").read_text()
    cluster.main(["--quick", "--devices", suite_device.id, "--out", str(tmp_path),
                  "--no-progress"])
    written = json.loads((tmp_path / "cluster.json").read_text())
    check_json(written)
    assert [c["workers"] for c in written["clusters"]] == [1, 2]
    for c in written["clusters"]:
        assert c["frames"]["identical"] and c["rays"]["identical"], c["workers"]
        assert c["noop_task_ms"] > 0
    assert (ROOT / "bench" / "RESULTS.md").read_text() == committed  # only --docs writes it
