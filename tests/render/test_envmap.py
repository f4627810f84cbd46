"""The environment map light on its own (hlbvh_cl/render/envmap.py,
kernels/render/envmap.h, through hlbvh_cl/render/sampling.py):

- its radiance by direction is Mitsuba 3's envmap emitter's, read from the
  same file with the same to_world (Mitsuba's eval as the oracle);
- chi-squared: the directions its sampling routine draws fall into bins of
  the sphere as often as its own density, integrated over each bin, says;
  each sample's density and radiance are those evaluation gives, and the
  samples draw the map where it stands above its mean (MIS compensation,
  hlbvh_cl/render/envmap.py);
- its files: OpenEXR and Radiance RGBE read as Mitsuba reads them.
"""
from __future__ import annotations

import numpy as np
import pytest

import chi2
from hlbvh_cl.io.exr import write_exr
from hlbvh_cl.render.envmap import read_radiance
from hlbvh_cl.render.sampling import eval_envmap, sample_envmap

mi = pytest.importorskip("mitsuba")

#: Bins in cos(theta) and phi (equal solid angles), samples drawn.
THETA_BINS, PHI_BINS, SAMPLES = 24, 48, 400_000

#: A turn about a tilted axis (Rodrigues), as a to_world.
AXIS, ANGLE = np.array([0.3, 0.9, 0.3]) / np.linalg.norm([0.3, 0.9, 0.3]), np.radians(50)


def turn() -> np.ndarray:
    k = np.array([[0, -AXIS[2], AXIS[1]], [AXIS[2], 0, -AXIS[0]], [-AXIS[1], AXIS[0], 0]])
    return np.eye(3) + np.sin(ANGLE) * k + (1 - np.cos(ANGLE)) * k @ k


def bright_spot(height=16, width=32, seed=0) -> np.ndarray:
    """A dim, uneven sky with a small bright patch (a sun) and a black row."""
    rng = np.random.default_rng(seed)
    image = rng.uniform(0.05, 0.3, (height, width, 3)).astype(np.float32)
    image[height // 4:height // 4 + 2, width // 3:width // 3 + 2] = [60.0, 50.0, 40.0]
    image[height - 3] = 0.0  # a band of no light: no sample may land there
    return image


def brightening_sky(height=16, width=32, seed=0) -> np.ndarray:
    """An uneven sky that brightens upwards (4x to 0.1x of 0.5 to 1.5), so
    that its upper bands stand above its mean, with bright_spot's sun and
    black row."""
    rng = np.random.default_rng(seed)
    image = rng.uniform(0.5, 1.5, (height, width, 3)) * np.linspace(4.0, 0.1, height)[:, None, None]
    image[height // 4:height // 4 + 2, width // 3:width // 3 + 2] = [30.0, 25.0, 20.0]
    image[height - 3] = 0.0
    return image.astype(np.float32)


def cell_values(image) -> tuple[np.ndarray, np.ndarray]:
    """Each bilinear cell's mean corner luminance and its solid angle, in
    float64, from the image alone (as envmap.py's docstring defines them)."""
    height, width, _ = image.shape
    lum = np.asarray(image, np.float64) @ [0.2126, 0.7152, 0.0722]
    right = np.roll(lum, -1, 1)
    values = 0.25 * (lum[:-1] + lum[1:] + right[:-1] + right[1:])
    cos = np.cos(np.pi * np.arange(height) / (height - 1))
    solid = np.repeat(((cos[:-1] - cos[1:]) * 2 * np.pi / width)[:, None], width, 1)
    return values, solid


def unit_rows(count, seed):
    d = np.random.default_rng(seed).normal(size=(count, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("rotated", [False, True], ids=["identity", "rotated"])
def test_the_radiance_is_mitsuba_s(rotated, tmp_path, suite_device):
    """Mitsuba's eval of its envmap emitter (scalar_rgb) along random
    directions, with scale and to_world: our device lookup gives the same
    bilinear radiance, so its lat-long mapping and texel alignment are
    Mitsuba's."""
    mi.set_variant("scalar_rgb")
    image = bright_spot(12, 20)
    write_exr(tmp_path / "sky.exr", image)
    matrix = np.eye(4)
    if rotated:
        matrix[:3, :3] = turn()
    theirs_emitter = mi.load_dict({"type": "envmap", "filename": str(tmp_path / "sky.exr"),
                                   "scale": 1.5, "to_world": mi.ScalarTransform4f(matrix)})
    directions = unit_rows(3000, 1)
    theirs = []
    for d in directions:
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*(-d))  # wi points back along the escaping ray
        theirs.append(np.array(theirs_emitter.eval(si)))
    ours = eval_envmap({"type": "envmap", "filename": tmp_path / "sky.exr", "scale": 1.5,
                        "to_world": matrix}, directions, device=suite_device)
    np.testing.assert_allclose(ours["radiance"], np.array(theirs), rtol=2e-4, atol=1e-5)


def bin_integrals(emitter, device, sub=12):
    """The density integrated over each (cos theta, phi) bin of the world
    by a sub x sub midpoint rule."""
    directions, cell = chi2.bin_directions(THETA_BINS, PHI_BINS, sub)
    pdfs = eval_envmap(emitter, directions, device=device)["pdfs"]
    return chi2.bin_shares(pdfs, cell, THETA_BINS, PHI_BINS, sub)


@pytest.mark.parametrize("rotated", [False, True], ids=["identity", "rotated"])
def test_sampling_matches_the_density_chi_squared(rotated, suite_device):
    """A 16 x 32 map with a bright spot over a sky brighter at the top: the
    drawn directions against the density the map evaluates (Mitsuba's chi2
    test's approach), pooled where a bin expects under 5 samples."""
    emitter = {"type": "envmap", "image": brightening_sky(),
               "to_world": turn() if rotated else np.eye(3)}
    drawn = sample_envmap(emitter, SAMPLES, seed=7, device=suite_device)
    d = drawn["directions"].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)
    assert (drawn["pdfs"] > 0).all() and (drawn["radiance"].max(1) > 0).all()
    observed = chi2.binned(d, THETA_BINS, PHI_BINS)
    shares = bin_integrals(emitter, suite_device)
    assert abs(shares.sum() - 1.0) < 3e-3, shares.sum()
    expected = shares * SAMPLES
    drawn_at = expected > 0
    assert 0.2 < drawn_at.mean() < 0.8, "the sky's upper bands are drawn, its lower ones not"
    assert expected.max() > 20 * np.median(expected[drawn_at]), "the spot should draw many"
    p, statistic, dof = chi2.p_value(observed, expected)
    assert p > 1e-3, f"chi2 {statistic:.1f} over {dof} dof: p = {p:.2e}"


def test_samples_draw_the_map_where_it_stands_above_its_mean(suite_device):
    """MIS compensation: a cell's density is its value's excess over the
    map's mean (0 where it has none) over the excess's integral, worked out
    here in float64 from the image; a map of one value has none, and takes
    no light samples in a render (tests/render/test_path.py)."""
    image = brightening_sky()
    values, solid = cell_values(image)
    excess = np.maximum(values - (values * solid).sum() / solid.sum(), 0.0)
    expected = excess / (excess * solid).sum()
    height, width = image.shape[:2]
    # a direction at each cell's centre, in the map's frame (envmap.py's mapping)
    theta = np.pi * (np.arange(height - 1) + 0.5) / (height - 1)
    phi = 2 * np.pi * (np.arange(width) + 1.0) / width  # between columns i and i + 1
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(tt) * np.sin(pp), np.cos(tt), -np.sin(tt) * np.cos(pp)], -1)
    got = eval_envmap({"type": "envmap", "image": image}, d.reshape(-1, 3),
                      device=suite_device)["pdfs"].reshape(height - 1, width)
    # (float32 CDFs: a cell's chance is a difference of two sums)
    np.testing.assert_allclose(got, expected, rtol=2e-3, atol=1e-6)
    np.testing.assert_array_equal(got == 0, expected == 0)
    assert (expected == 0).mean() > 0.2


def test_a_sample_s_density_and_radiance_are_its_evaluation_s(suite_device):
    emitter = {"type": "envmap", "image": brightening_sky(), "to_world": turn(), "scale": 2.0}
    drawn = sample_envmap(emitter, 4000, seed=3, device=suite_device)
    values = eval_envmap(emitter, drawn["directions"], device=suite_device)
    np.testing.assert_allclose(values["pdfs"], drawn["pdfs"], rtol=1e-4)
    np.testing.assert_allclose(values["radiance"], drawn["radiance"], rtol=1e-5, atol=1e-6)
    # radiance / pdf averages to the map's integral over the directions it
    # samples (its density > 0), by a fine midpoint rule of the same lookup
    # in (theta, phi)
    estimate = (drawn["radiance"] / drawn["pdfs"][:, None]).astype(np.float64).mean(0)
    n = 600
    theta = (np.arange(n) + 0.5) / n * np.pi
    phi = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * np.pi
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    grid = np.stack([np.sin(tt) * np.cos(pp), np.cos(tt), np.sin(tt) * np.sin(pp)], -1)
    values = eval_envmap(emitter, grid.reshape(-1, 3), device=suite_device)
    radiance = np.where(values["pdfs"][:, None] > 0, values["radiance"], 0.0)
    weights = (np.sin(tt) * (np.pi / n) ** 2).reshape(-1, 1)
    integral = (radiance.astype(np.float64) * weights).sum(0)
    np.testing.assert_allclose(estimate, integral, rtol=0.03)


@pytest.mark.parametrize("width", [6, 40], ids=["flat", "run-length"])
def test_rgbe_and_exr_files_read_as_mitsuba_reads_them(width, tmp_path):
    """Mitsuba writes a Radiance .hdr (flat scanlines under 8 pixels wide,
    run-length ones above) and reads it back; our reader gives its pixels.
    An EXR written by hlbvh_cl.io.exr comes back as written."""
    mi.set_variant("scalar_rgb")
    image = bright_spot(5, width, seed=width)
    image[0, 0] = 0.0
    mi.Bitmap(image).write(str(tmp_path / "sky.hdr"))
    theirs = np.asarray(mi.Bitmap(str(tmp_path / "sky.hdr")).convert(
        mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, False))
    np.testing.assert_array_equal(read_radiance(tmp_path / "sky.hdr"), theirs)
    # RGBE keeps 8 bits of mantissa under the pixel's largest channel
    assert (np.abs(theirs - image) <= image.max(-1, keepdims=True) / 128 + 1e-7).all()
    write_exr(tmp_path / "sky.exr", image)
    np.testing.assert_array_equal(read_radiance(tmp_path / "sky.exr"), image)


@pytest.mark.parametrize("size, words", [
    (b"-Y 400000 +X 800000", "gives 800000 x 400000 pixels, more than its 8 bytes"),
    (b"-Y 0 +X 8", "must give a positive height and width"),
    (b"-Y two +X 8", "must give a positive height and width"),
])
def test_an_rgbe_header_that_its_bytes_cannot_fill_is_refused(size, words, tmp_path):
    """A size line the file cannot hold (or no size at all) is an error
    naming the file, before anything is allocated for it."""
    path = tmp_path / "sky.hdr"
    path.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + size + b"\nabcdefgh")
    with pytest.raises(ValueError, match=f"cannot read the environment map .*sky.hdr: .*{words}"):
        read_radiance(path)


def write_channels(path, channels, header=None):
    import OpenEXR
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              **(header or {})}
    with OpenEXR.File(header, dict(channels)) as image:  # (it wraps the dict's values)
        image.write(str(path))
    return path


def test_an_exr_read_as_other_colours_is_refused_and_mixed_types_are_read(tmp_path):
    """EXRs whose colours are not Rec. 709 RGB: luminance-chroma (Y, RY, BY)
    and XYZ channels were read as grey from Y, and primaries named in the
    chromaticities attribute (ACES AP0) taken as Rec. 709's, up to 59 %
    off Mitsuba's conversion, in silence.  They are refused, naming the
    file; an attribute of Rec. 709's own primaries reads.  A file whose
    channels mix half and full floats (valid) had failed in OpenEXR's
    channel coalescing: it reads as written."""
    rng = np.random.default_rng(3)
    image = rng.uniform(0.05, 2.0, (6, 10, 3)).astype(np.float32)
    planes = {c: np.ascontiguousarray(image[..., k]) for k, c in enumerate("RGB")}
    luminance = (image @ np.array([0.2126, 0.7152, 0.0722], np.float32)).astype(np.float32)
    refused = {
        "yc.exr": ({"Y": luminance, "RY": planes["R"] / luminance - 1,
                    "BY": planes["B"] / luminance - 1}, None, "stores luminance and chroma"),
        "xyz.exr": ({"X": planes["R"], "Y": planes["G"], "Z": planes["B"]}, None,
                    "stores CIE XYZ"),
        "aces.exr": (planes, {"chromaticities": (0.7347, 0.2653, 0.0, 1.0, 0.0001, -0.077,
                                                 0.32168, 0.33767)},
                     r"its chromaticities \(0.7347, .*\) are not Rec. 709's"),
    }
    for name, (channels, header, words) in refused.items():
        path = write_channels(tmp_path / name, channels, header)
        with pytest.raises(ValueError, match=f"cannot read the environment map .*{name}: .*{words}"):
            read_radiance(path)
    # R, G, B beside a depth Z (a renderer's output) are still the colours
    depth = write_channels(tmp_path / "depth.exr", {**planes, "Z": planes["R"] * 0 + 3})
    np.testing.assert_array_equal(read_radiance(depth), image)
    rec709 = write_channels(tmp_path / "rec709.exr", planes,
                            {"chromaticities": (0.64, 0.33, 0.30, 0.60, 0.15, 0.06,
                                                0.3127, 0.3290)})
    np.testing.assert_array_equal(read_radiance(rec709), image)
    mixed = {**planes, "G": planes["G"].astype(np.float16)}
    np.testing.assert_array_equal(read_radiance(write_channels(tmp_path / "mixed.exr", mixed)),
                                  np.dstack([image[..., 0], image[..., 1].astype(np.float16),
                                             image[..., 2]]).astype(np.float32))
