"""A spinning LiDAR on a car driving through traffic: each frame moves the
instances (Scene.set_transforms) and traces one revolution of the sensor
with a single Scene.intersect from its one origin.

    python examples/lidar.py OUTPUT [--frames 20] [--instances 200] [--device pocl]

The sensor: 64 beams from -25 to +15 degrees of elevation, 1024 azimuth steps
a revolution, 10 revolutions (frames) a second, 120 m of range; a whole
revolution is traced at one instant.  The world, in metres with y up: a
ground, and cars (boxes) and bunnies driving round in circles; the car that
carries the sensor drives straight along x.  It is in the scene too, but
outside the sensor's mask, so that the sensor does not see its own roof.

Writes OUTPUT/frame_0000.ply, ... (the hit points in world coordinates,
coloured by what they hit) and OUTPUT/fps.png, the frames per second
(set_transforms and intersect, not the writing).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if (ROOT / "hlbvh_cl" / "__init__.py").is_file():  # run from a checkout: use its hlbvh_cl
    sys.path.insert(0, str(ROOT))

import hlbvh_cl  # noqa: E402

BEAMS, STEPS, HZ, RANGE = 64, 1024, 10.0, 120.0
ELEVATION_DEG = (-25.0, 15.0)
SENSOR_HEIGHT = 1.9     # above the car's roof
EGO_SPEED = 10.0        # m/s along x
SEEN, UNSEEN = 1, 2     # mask bits: the sensor's rays carry SEEN; its own car only UNSEEN
COLORS = np.array([[150, 150, 150], [60, 120, 220], [230, 150, 60]], np.uint8)  # per mesh


def box(width: float, height: float, length: float) -> hlbvh_cl.Mesh:
    """A box standing on y = 0, long along z."""
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (0, 1) for z in (-0.5, 0.5)])
    faces = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
             [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return hlbvh_cl.Mesh(corners * [width, height, length], np.array(faces))


def meshes() -> list[hlbvh_cl.Mesh]:
    """The ground, a car and a bunny 1 m tall standing on y = 0."""
    ground = hlbvh_cl.Mesh([[-200, 0, -200], [200, 0, -200], [200, 0, 200], [-200, 0, 200]],
                           [[0, 2, 1], [0, 3, 2]])
    bunny = hlbvh_cl.Mesh.load(ROOT / "scenes" / "meshes" / "bunny_small.ply")
    lo, hi = bunny.bounds
    feet = [(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2]
    bunny = hlbvh_cl.Mesh((bunny.vertices - feet) / (hi[1] - lo[1]), bunny.faces)
    return [ground, box(1.8, 1.5, 4.5), bunny]


class Traffic:
    """Movers on circles about the origin, each at its own radius, speed and
    direction (every fourth a bunny), and the sensor's car on the x axis."""

    def __init__(self, movers: int, seed: int = 0):
        rng = np.random.default_rng(seed)
        self.mesh = np.where(np.arange(movers) % 4 == 3, 2, 1)
        self.radius = rng.uniform(8, 80, movers)
        self.rate = rng.uniform(3, 15, movers) / self.radius * rng.choice([-1, 1], movers)
        self.phase = rng.uniform(0, 2 * np.pi, movers)

    def ego(self, t: float) -> np.ndarray:
        return np.array([-40 + EGO_SPEED * t, 0.0, 0.0])

    def transforms(self, t: float) -> np.ndarray:
        """(movers + 1, 3, 4) object-to-world transforms at time t, the sensor's car last."""
        angle = self.phase + self.rate * t
        heading = angle + np.where(self.rate > 0, 0, np.pi)  # the way each one drives
        positions = np.stack([self.radius * np.cos(angle), 0 * angle,
                              self.radius * np.sin(angle)], axis=1)
        turns = np.append(-heading, np.pi / 2)  # a box is long along z; the ego car faces +x
        out = np.zeros((len(turns), 3, 4))
        out[:, 0, 0] = out[:, 2, 2] = np.cos(turns)
        out[:, 0, 2], out[:, 2, 0], out[:, 1, 1] = np.sin(turns), -np.sin(turns), 1
        out[:, :, 3] = np.vstack([positions, self.ego(t)])
        return out


def sweep() -> np.ndarray:
    """(BEAMS, STEPS, 3) unit directions of one revolution."""
    elevation = np.radians(np.linspace(*ELEVATION_DEG, BEAMS))[:, None]
    azimuth = np.linspace(0, 2 * np.pi, STEPS, endpoint=False)[None, :]
    return np.stack(np.broadcast_arrays(np.cos(elevation) * np.cos(azimuth), np.sin(elevation),
                                        np.cos(elevation) * np.sin(azimuth)), axis=-1)


def build(traffic: Traffic, device=None) -> hlbvh_cl.Scene:
    """The scene at t = 0: the ground (instance 0), the movers, the sensor's car last."""
    instances = [(0, np.eye(4))]
    instances += [(int(m), t) for m, t in zip(np.append(traffic.mesh, 1), traffic.transforms(0))]
    masks = [SEEN] * (len(instances) - 1) + [UNSEEN]
    return hlbvh_cl.Scene(meshes(), instances=instances, masks=masks, device=device)


def main(argv=None) -> list[Path]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("output", type=Path, help="folder of the PLY files and fps.png")
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--instances", type=int, default=200, help="moving cars and bunnies")
    parser.add_argument("--device", default=None, help="OpenCL device id (default: the best)")
    args = parser.parse_args(argv)
    import trimesh

    traffic = Traffic(args.instances)
    scene = build(traffic, args.device)
    moving = np.arange(1, args.instances + 2)  # every instance but the ground
    directions = sweep().astype(np.float32)
    args.output.mkdir(parents=True, exist_ok=True)
    written, seconds = [], []
    for frame in range(args.frames):
        t = frame / HZ
        started = time.perf_counter()
        scene.set_transforms(moving, traffic.transforms(t))
        origin = traffic.ego(t) + [0, SENSOR_HEIGHT, 0]
        hits = scene.intersect(origin, directions, tmax=RANGE, mask=SEEN)
        seconds.append(time.perf_counter() - started)
        points, mesh = hits.points[hits.hit], hits.geom_id[hits.hit]
        written.append(args.output / f"frame_{frame:04d}.ply")
        trimesh.PointCloud(points, colors=COLORS[mesh]).export(written[-1])
    fps = 1 / np.array(seconds)
    print(f"{args.frames} frames of {BEAMS}x{STEPS} rays, {args.instances} movers: "
          f"{np.median(fps):.1f} frames/s (median; the first one compiles the kernels)")
    plot_fps(fps, args.output / "fps.png")
    return written


def plot_fps(fps: np.ndarray, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    figure, axes = plt.subplots(figsize=(7, 3.5))
    axes.plot(fps, marker="o")
    axes.axhline(HZ, color="crimson", lw=1, label=f"the sensor's {HZ:g} Hz")
    axes.set(xlabel="frame", ylabel="frames per second", ylim=(0, None),
             title="set_transforms + intersect per frame")
    axes.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


if __name__ == "__main__":
    main()
