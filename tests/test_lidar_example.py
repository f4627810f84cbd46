"""examples/lidar.py run tiny: every point of every frame's PLY lies on the
world as it stood at that frame (flattened here: each instance's mesh moved
by its transform, the sensor's own car left out as its mask leaves it out),
cars are seen, and the frames-per-second plot is written."""
import importlib.util

import numpy as np
import pytest
from bench_support import ROOT

import hlbvh_cl

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("matplotlib")

spec = importlib.util.spec_from_file_location("lidar", ROOT / "examples" / "lidar.py")
lidar = importlib.util.module_from_spec(spec)
spec.loader.exec_module(lidar)

FRAMES, MOVERS = 3, 8


def flattened(traffic, t: float) -> list:
    """The world at time t as plain meshes, without the sensor's car."""
    meshes = lidar.meshes()
    transforms = traffic.transforms(t)[:-1]
    out = [meshes[0]]
    for mesh_id, transform in zip(traffic.mesh, transforms):
        mesh = meshes[mesh_id]
        out.append(hlbvh_cl.Mesh(mesh.vertices @ transform[:, :3].T + transform[:, 3],
                                 mesh.faces))
    return out


def test_points_lie_on_the_moving_world(tmp_path, suite_device):
    written = lidar.main([str(tmp_path), "--frames", str(FRAMES), "--instances", str(MOVERS),
                          "--device", suite_device.id])
    assert [p.name for p in written] == [f"frame_{k:04d}.ply" for k in range(FRAMES)]
    assert (tmp_path / "fps.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    traffic = lidar.Traffic(MOVERS)
    car = lidar.COLORS[1]
    for frame, path in enumerate(written):
        t = frame / lidar.HZ
        cloud = trimesh.load(path)
        points = np.asarray(cloud.vertices)
        # the ground within range takes most beams below the horizon
        assert len(points) > 0.4 * lidar.BEAMS * lidar.STEPS
        origin = traffic.ego(t) + [0, lidar.SENSOR_HEIGHT, 0]
        assert np.linalg.norm(points - origin, axis=1).max() <= lidar.RANGE * (1 + 1e-5)
        world = hlbvh_cl.Scene(flattened(traffic, t), device=suite_device.id)
        distance = world.closest_points(points).distance
        assert distance.max() < 1e-3, (path.name, float(distance.max()))  # metres
        assert (np.asarray(cloud.colors)[:, :3] == car).all(axis=1).any(), path.name
    # the movers moved: a frame's points are not all on the first frame's world
    first = hlbvh_cl.Scene(flattened(traffic, 0.0), device=suite_device.id)
    last = np.asarray(trimesh.load(written[-1]).vertices)
    assert first.closest_points(last).distance.max() > 0.1
