"""examples/sdf_slice.py on a cube: the PNG's size, and every pixel clearly
inside the cube on the map's inside (blue) side, every pixel clearly outside
on its outside (red) side, with matplotlib's map and with the built-in one."""
import importlib.util

import imageio.v3 as iio
import numpy as np
import pytest
from bench_support import ROOT

trimesh = pytest.importorskip("trimesh")

spec = importlib.util.spec_from_file_location("sdf_slice", ROOT / "examples" / "sdf_slice.py")
sdf_slice = importlib.util.module_from_spec(spec)
spec.loader.exec_module(sdf_slice)

HALF = np.array([1.0, 0.5, 0.75])  # the cube's half extents: the image is not square


@pytest.fixture(scope="module")
def cube(tmp_path_factory):
    path = tmp_path_factory.mktemp("sdf") / "box.ply"
    trimesh.creation.box(extents=2 * HALF).export(path)
    return path


@pytest.mark.parametrize("axis, position, builtin", [("z", 0.5, False), ("z", 0.5, True),
                                                     ("x", 0.3, False), ("y", 0.8, True)])
def test_slice_of_a_cube(cube, tmp_path, suite_device, axis, position, builtin):
    if not builtin:
        pytest.importorskip("matplotlib")
    output = tmp_path / "slice.png"
    argv = [str(cube), "--axis", axis, "--position", str(position), "--resolution", "60",
            "--output", str(output), "--device", suite_device.id]
    assert sdf_slice.main(argv + (["--builtin-colors"] if builtin else [])) == output
    image = iio.imread(output)
    k = "xyz".index(axis)
    across, up = [i for i in range(3) if i != k]
    extent = 2 * HALF * (1 + 2 * sdf_slice.MARGIN)
    side = max(extent[across], extent[up])
    expected = (round(60 * extent[up] / side), round(60 * extent[across] / side), 3)
    assert image.shape == expected and image.dtype == np.uint8
    points = sdf_slice.plane_points(-HALF, HALF, k, position, 60)
    assert points.shape[:2] == image.shape[:2]
    np.testing.assert_allclose(points[..., k], -HALF[k] + position * 2 * HALF[k], rtol=1e-6)
    # distance to the cube's surface within the plane, its own pixel units: away from
    # the surface by more than two pixels, the colour tells the side
    pixel = extent[across] / image.shape[1]
    gap = (np.abs(points) - HALF).max(axis=2)  # < 0 inside, > 0 outside (the plane cuts inside)
    red, blue = image[..., 0].astype(int), image[..., 2].astype(int)
    inside, outside = gap < -2 * pixel, gap > 2 * pixel
    assert inside.sum() > 100 and outside.sum() > 100
    assert (blue[inside] > red[inside]).all()
    assert (red[outside] > blue[outside]).all()
    edge = np.abs(gap) < pixel / 2  # the zero level is drawn dark
    assert image[edge].max(axis=1).mean() < 0.8 * image[outside | inside].max(axis=1).mean()


def test_bad_options_are_rejected_by_name(capsys):
    for argv, word in ((["--axis", "w"], "--axis"), (["--position", "1.5"], "--position"),
                       (["--resolution", "0"], "--resolution")):
        with pytest.raises(SystemExit):
            sdf_slice.main(argv)
        assert word in capsys.readouterr().err
