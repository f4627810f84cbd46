"""A slice of a mesh's signed distance field as a PNG: Scene.signed_distance
on a grid of points in a plane through the mesh, negative (inside) in blue,
positive (outside) in red, the surface (the zero level set) drawn in black.

    python examples/sdf_slice.py [MESH] [--axis z] [--position 0.5] [--resolution 512]
                                 [--output sdf_slice.png] [--device pocl] [--builtin-colors]

MESH defaults to scenes/meshes/bunny.ply.  The plane is normal to --axis, at
--position (0 to 1) across the mesh's box along it, and covers the box's two
other sides with a margin; --resolution is the image's longer side in pixels.
With matplotlib installed the colour map is its diverging "RdBu_r" with the
zero level as a contour line; without it (or with --builtin-colors), a
three-colour ramp and the pixels where the sign changes.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if (ROOT / "hlbvh_cl" / "__init__.py").is_file():  # run from a checkout: use its hlbvh_cl
    sys.path.insert(0, str(ROOT))

import hlbvh_cl  # noqa: E402

MESH = ROOT / "scenes" / "meshes" / "bunny.ply"
AXES = "xyz"
#: the plane covers the box's sides grown by this fraction on each end
MARGIN = 0.15
#: the built-in map: inside, zero, outside (close to matplotlib's RdBu_r ends)
BUILTIN = np.array([[0.02, 0.19, 0.38], [0.97, 0.97, 0.97], [0.40, 0.0, 0.12]])


def plane_points(lo, hi, axis: int, position: float, resolution: int):
    """Pixel centres of the plane as (height, width, 3) float32 points, the
    image's first row at the top (the highest coordinate of the vertical side)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    across, up = [k for k in range(3) if k != axis]
    cut = lo[axis] + position * (hi[axis] - lo[axis])
    grow = (hi - lo) * MARGIN
    lo, hi = lo - grow, hi + grow
    extent = np.maximum(hi - lo, 1e-12)
    side = max(extent[across], extent[up])
    width = max(1, round(resolution * extent[across] / side))
    height = max(1, round(resolution * extent[up] / side))
    points = np.empty((height, width, 3))
    points[..., axis] = cut
    points[..., across] = lo[across] + (np.arange(width)[None, :] + 0.5) * extent[across] / width
    points[..., up] = hi[up] - (np.arange(height)[:, None] + 0.5) * extent[up] / height
    return points.astype(np.float32)


def builtin_colors(distance: np.ndarray) -> np.ndarray:
    """RGB uint8: BUILTIN's ramp over [-max|d|, max|d|], sign changes in black."""
    scale = max(float(np.abs(distance).max()), 1e-30)
    x = np.clip(distance / scale, -1, 1)[..., None]
    rgb = np.where(x < 0, BUILTIN[1] + (BUILTIN[1] - BUILTIN[0]) * x,
                   BUILTIN[1] + (BUILTIN[2] - BUILTIN[1]) * x)
    inside = distance < 0
    edge = np.zeros_like(inside)
    edge[:, 1:] |= inside[:, 1:] != inside[:, :-1]
    edge[1:, :] |= inside[1:, :] != inside[:-1, :]
    rgb[edge] = 0
    return (rgb * 255 + 0.5).astype(np.uint8)


def matplotlib_colors(distance: np.ndarray) -> np.ndarray:
    """RGB uint8 of the same size: RdBu_r over [-max|d|, max|d|], faint level
    lines, and the zero level as a black contour."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    height, width = distance.shape
    scale = max(float(np.abs(distance).max()), 1e-30)
    figure = plt.figure(figsize=(width / 100, height / 100), dpi=100)
    axes = figure.add_axes((0, 0, 1, 1))
    axes.imshow(distance, cmap="RdBu_r", vmin=-scale, vmax=scale, interpolation="nearest")
    if min(height, width) > 1 and distance.min() < 0 < distance.max():
        axes.contour(distance, levels=np.linspace(-scale, scale, 21), colors="k",
                     linewidths=0.3, alpha=0.25)
        axes.contour(distance, levels=[0.0], colors="k", linewidths=1.2)
    axes.set_axis_off()
    figure.canvas.draw()
    rgb = np.asarray(figure.canvas.buffer_rgba())[..., :3].copy()
    plt.close(figure)
    return rgb


def colors(distance: np.ndarray, builtin: bool = False) -> np.ndarray:
    if not builtin:
        try:
            return matplotlib_colors(distance)
        except ImportError:
            pass
    return builtin_colors(distance)


def _fraction(text: str) -> float:
    value = float(text)
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"--position must be within 0 to 1, got {text}")
    return value


def _pixels(text: str) -> int:
    value = int(text)
    if not 1 <= value <= 8192:
        raise argparse.ArgumentTypeError(f"--resolution must be 1 to 8192 pixels, got {text}")
    return value


def main(argv=None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mesh", nargs="?", type=Path, default=MESH, help="a .ply/.obj/.stl mesh")
    parser.add_argument("--axis", choices=list(AXES), default="z", help="the plane's normal")
    parser.add_argument("--position", type=_fraction, default=0.5,
                        help="where the plane cuts the mesh's box along --axis, 0 to 1")
    parser.add_argument("--resolution", type=_pixels, default=512,
                        help="the image's longer side, pixels")
    parser.add_argument("--output", type=Path, default=Path("sdf_slice.png"))
    parser.add_argument("--device", default=None, help="OpenCL device id (default: the best)")
    parser.add_argument("--builtin-colors", action="store_true",
                        help="the built-in colour map even when matplotlib is installed")
    args = parser.parse_args(argv)
    mesh = hlbvh_cl.Mesh.load(args.mesh)
    scene = hlbvh_cl.Scene([mesh], device=args.device)
    points = plane_points(*mesh.bounds, AXES.index(args.axis), args.position, args.resolution)
    distance = scene.signed_distance(points.reshape(-1, 3)).reshape(points.shape[:2])
    import imageio.v3 as iio
    args.output.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(args.output, colors(distance, args.builtin_colors))
    inside = float(np.mean(distance < 0))
    print(f"wrote {args.output}: {distance.shape[1]}x{distance.shape[0]}, {args.axis} = "
          f"{points[0, 0, AXES.index(args.axis)]:.4g}, distance {distance.min():.4g} to "
          f"{distance.max():.4g}, {inside:.1%} of the pixels inside")
    return args.output


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
