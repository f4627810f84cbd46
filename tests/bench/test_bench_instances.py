"""python -m bench.instances: its world and sweep against geometry worked out
here, and its --quick run's output, where the flat scenes, the instanced
ones and Mitsuba 3 must see the same hits.  Never asserts speed."""
import json

import numpy as np
import pytest
from bench_support import ROOT, check_json

pytest.importorskip("matplotlib")

from bench import instances  # noqa: E402

PNG = b"\x89PNG\r\n\x1a\n"


def test_the_sweep_covers_the_beams_and_a_revolution():
    directions = instances.sweep(8, 16)
    assert directions.shape == (8, 16, 3) and directions.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1, atol=1e-6)
    elevation = np.degrees(np.arcsin(directions[..., 1]))
    np.testing.assert_allclose(elevation[[0, -1], 0], instances.ELEVATION_DEG, atol=1e-4)
    azimuth = np.arctan2(directions[0, :, 0], directions[0, :, 2]) % (2 * np.pi)
    np.testing.assert_allclose(np.diff(azimuth), 2 * np.pi / 16, atol=1e-5)


def test_the_world_moves_its_movers_straight_and_keeps_them_on_the_ground():
    world = instances.World(50, seed=3)
    first, later = world.transforms(0), world.transforms(1)
    assert first.shape == (50, 3, 4) and len(world.instances(0)) == 51
    np.testing.assert_allclose(first[:, :, :3], later[:, :, :3])  # headings kept
    step = np.linalg.norm(later[:, :, 3] - first[:, :, 3], axis=1)
    wrapped = step > 0.5 * instances.GROUND  # went over the edge and came back on the other
    np.testing.assert_allclose(step[~wrapped], world.speed[~wrapped] * instances.FRAME_S,
                               rtol=1e-4)
    assert (np.abs(world.transforms(500)[:, [0, 2], 3]) <= 0.45 * instances.GROUND + 1e-3).all()
    assert (world.transforms(7)[:, 1, 3] == 0).all()
    moved = world.mover_vertices(2)
    k = int(np.flatnonzero(world.kinds == 2)[0])  # a bunny: vertices moved by its transform
    t = world.transforms(2)[k].astype(np.float64)
    np.testing.assert_allclose(moved[k], world.meshes[2].vertices @ t[:, :3].T + t[:, 3],
                               atol=1e-4)


def test_the_grid_keeps_its_instances_apart():
    mesh = instances.standing(instances.box_mesh(1, 2, 3), 1.0)
    lo, hi = mesh.bounds
    assert lo[1] == 0 and hi[1] == pytest.approx(1.0)
    placed = instances.grid_transforms(10, mesh, seed=1)[:, :, 3]
    gaps = np.linalg.norm(placed[:, None] - placed[None], axis=-1) + np.eye(10) * 1e9
    assert gaps.min() >= 1.2 * np.max(hi - lo) - 1e-5  # wider than the mesh turned any way


def test_quick_run_sees_the_same_hits_every_way(suite_device, tmp_path, capsys):
    committed = (ROOT / "bench" / "RESULTS.md").read_text()
    instances.main(["--quick", "--devices", suite_device.id, "--out", str(tmp_path),
                    "--no-progress"])
    written = json.loads((tmp_path / "instances.json").read_text())
    check_json(written)
    assert (tmp_path / "instances.png").read_bytes()[:8] == PNG
    ours = suite_device.id
    transforms = written["transforms"][ours]
    assert transforms["moved"] == instances.QUICK.movers and transforms["device_ms"]["min"] > 0
    lidar = written["lidar"]
    assert lidar["errors"] == {} and lidar["reference"] == f"{ours} instanced"
    assert set(lidar["results"]) == {f"{ours} {way}" for way in instances.LidarFrames.WAYS}
    for result in lidar["results"].values():
        assert result["vs_reference"]["hit_differs"] <= 1e-3
        assert result["vs_reference"]["max_t_gap"] < 1e-5
        assert result["vs_reference"]["hits"] > 0
    assert set(lidar["speedup"][ours]) == {"flat per mesh", "flat merged"}
    memory = written["memory"]
    assert memory["errors"] == {}
    found = memory["results"][ours]
    assert found["instanced"]["triangles_seen"] == (instances.QUICK.memory_instances
                                                   * found["flat"]["triangles_seen"])
    assert found["instanced"]["hit_fraction"] > 0.5 and found["ratio"] > 0
    identity = written["identity"]
    assert identity["errors"] == {}
    assert identity["results"][f"{ours} instanced"]["vs_flat"]["hit_differs"] == 0
    grid = written["grid"]
    assert grid["instances"] == instances.QUICK.grid ** 2 and len(grid["workloads"]) == 2
    for work, peer in zip(grid["workloads"], ("mitsuba", "mitsuba ray_intersect")):
        assert ours in work["results"]
        if not grid["mitsuba"][peer]["available"]:
            continue
        gaps = work["results"][peer]["vs_ours"]
        assert gaps["hit_differs"] <= 0.01 and gaps["t_differs"] <= 0.01, peer
        assert work["ratio"][ours] == pytest.approx(
            work["results"][ours]["mrays"]["median"] / work["results"][peer]["mrays"]["median"])
    assert grid["errors"] == {}
    assert "LiDAR frame" in capsys.readouterr().out
    assert (ROOT / "bench" / "RESULTS.md").read_text() == committed  # no --docs
