"""The Gaussian reconstruction filter's inverse-CDF table (camera.py), which
the camera kernel interpolates to draw each sample's offset: checked
against the filter's CDF by quadrature in float64, an oracle independent of
the table's closed-form integral."""
import numpy as np

from hlbvh_cl.render.camera import GAUSSIAN_RADIUS, GAUSSIAN_SIGMA, gaussian_filter_table


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
