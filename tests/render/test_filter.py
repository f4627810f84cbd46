"""The Gaussian reconstruction filter: its inverse-CDF table (camera.py),
which the previews' camera interpolates to draw each sample's offset,
checked against the filter's CDF by quadrature in float64, an oracle
independent of the table's closed-form integral; and the path integrator's
splatting film (film.cl), checked pixel by pixel against Mitsuba's
weighted sum recomputed in float64 from the same sample positions."""
import numpy as np
import pytest

import hlbvh_cl
from hlbvh_cl.render.camera import GAUSSIAN_RADIUS, GAUSSIAN_SIGMA, gaussian_filter_table
from hlbvh_cl.render.settings import MAX_SPP


def test_the_table_inverts_mitsuba_s_gaussian_filter():
    table = gaussian_filter_table(256).astype(np.float64)
    r, sigma = GAUSSIAN_RADIUS, GAUSSIAN_SIGMA
    t = np.linspace(-r, r, 400_001)
    f = np.exp(-t * t / (2 * sigma * sigma)) - np.exp(-r * r / (2 * sigma * sigma))
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(t))])
    cdf /= cdf[-1]
    # each entry sits at its CDF value i / 256: an interval holds 1/256 of the filter's mass
    np.testing.assert_allclose(np.interp(table, t, cdf), np.arange(257) / 256, atol=2e-6)
    np.testing.assert_allclose(table, -table[::-1], atol=1e-6)  # symmetric
    assert table[0] == -r and table[-1] == r and (np.diff(table) > 0).all()
    # the middle interval's width: 1/256 of the mass over the filter's peak density
    assert abs(table[129] - table[128] - cdf[-1] / 256 / (f.max() / np.trapezoid(f, t))) < 1e-4


def hash_pcg(value):
    """render/random.h's hash, in numpy uint32 (wrapping) arithmetic."""
    with np.errstate(over="ignore"):  # uint32 wraps, as in OpenCL C
        state = value * np.uint32(747796405) + np.uint32(2891336453)
        word = ((state >> ((state >> np.uint32(28)) + np.uint32(4))) ^ state) \
            * np.uint32(277803737)
    return (word >> np.uint32(22)) ^ word


def random_unit(pixel, sample, dimension):
    h = hash_pcg(pixel + hash_pcg(np.uint32(sample) + hash_pcg(np.uint32(dimension))))
    return (h >> np.uint32(8)).astype(np.float64) * 2.0 ** -24


@pytest.mark.parametrize("seed", [0, 4])
def test_path_samples_are_splatted_as_mitsuba_s_film_does(seed, suite_device):
    """An emitting half-plane seen directly (max_depth 1): a sample is 1 left
    of the edge and 0 right of it.  Mitsuba's film (ImageBlock::put) adds
    each sample, uniform in its pixel, to every pixel whose centre is
    within the filter's radius, weighted by f(dx) f(dy), and divides by the
    weights' sum; recomputed here in float64 from the sample positions the
    camera draws (render/random.h's hash, repeated in numpy), with the
    filter's exact formula, the image's borders included."""
    distance, fov, width, height, spp = 4.0, 30.0, 13, 7, 6
    edge_x = 0.123
    quad = hlbvh_cl.Mesh([[-9, -9, 0], [edge_x, -9, 0], [edge_x, 9, 0], [-9, 9, 0]],
                         [[0, 1, 2], [0, 2, 3]])
    renderer = hlbvh_cl.Renderer(hlbvh_cl.Scene([quad], device=suite_device),
                                 emitters=[{"type": "area", "mesh": 0, "radiance": 1.0}])
    camera = hlbvh_cl.Camera(eye=(0, 0, distance), target=(0, 0, 0), fov_deg=fov)
    image = renderer.render(camera, width, height, shading="path", spp=spp, max_depth=1,
                            rfilter="gaussian", seed=seed, hdr=True)
    half_width = np.tan(np.radians(fov) / 2) * width / height
    edge = (edge_x / (distance * half_width) + 1) * width / 2  # in pixels from the left

    ys, xs = np.mgrid[0:height, 0:width]
    pixel = (ys * width + xs).astype(np.uint32)
    r, sigma = GAUSSIAN_RADIUS, GAUSSIAN_SIGMA

    def f(t):
        g = lambda u: np.exp(-u * u / (2 * sigma * sigma))  # noqa: E731
        return np.where(np.abs(t) < r, np.maximum(g(t) - g(r), 0.0), 0.0)

    sums, weights = np.zeros((height, width)), np.zeros((height, width))
    for sample in range(spp):
        stream = seed * MAX_SPP + sample
        px = xs + random_unit(pixel, stream, 0)  # the sample's position on the image
        py = ys + random_unit(pixel, stream, 1)
        assert np.abs(px - edge).min() > 1e-4  # no sample the float32 ray could put either side
        value = (px < edge).astype(np.float64)
        for y in range(height):
            for x in range(width):
                w = f(px - (x + 0.5)) * f(py - (y + 0.5))
                sums[y, x] += (w * value).sum()
                weights[y, x] += w.sum()
    expected = sums / weights
    assert ((expected > 0.01) & (expected < 0.99)).sum() >= 2 * height  # a blurred edge
    for channel in range(3):
        np.testing.assert_allclose(image[..., channel], expected, atol=2e-4)
