"""Chi-squared tests of a sampling routine against its own density, as
Mitsuba 3's chi2 tests run them: bins of equal solid angle over the sphere
(cos theta by phi), the density integrated over each by a midpoint rule,
and the bins expected to hold under 5 samples pooled into one."""
from __future__ import annotations

import numpy as np
from scipy import stats


def bin_directions(theta_bins: int, phi_bins: int, sub: int) -> tuple[np.ndarray, float]:
    """The midpoints of sub x sub cells in each (cos theta, phi) bin about
    +z: unit directions (theta_bins * sub * phi_bins * sub, 3), rows in
    (z, then phi) order, and each cell's solid angle."""
    z_edges = np.linspace(-1, 1, theta_bins * sub + 1)
    phi_edges = np.linspace(0, 2 * np.pi, phi_bins * sub + 1)
    z = (z_edges[:-1] + z_edges[1:]) / 2
    phi = (phi_edges[:-1] + phi_edges[1:]) / 2
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(1 - zz**2)
    directions = np.stack([r * np.cos(pp), r * np.sin(pp), zz], -1).reshape(-1, 3)
    return directions, (2.0 / len(z)) * (2 * np.pi / len(phi))


def bin_shares(pdfs: np.ndarray, cell: float, theta_bins: int, phi_bins: int,
               sub: int) -> np.ndarray:
    """The density at bin_directions' midpoints summed over each bin:
    (theta_bins, phi_bins) shares of the samples."""
    per_cell = (np.asarray(pdfs, np.float64) * cell).reshape(theta_bins, sub, phi_bins, sub)
    return per_cell.sum(axis=(1, 3))


def binned(directions: np.ndarray, theta_bins: int, phi_bins: int) -> np.ndarray:
    """How many of the unit directions fall in each (cos theta, phi) bin."""
    d = np.asarray(directions, np.float64)
    z_bin = np.clip(((d[:, 2] + 1) / 2 * theta_bins).astype(int), 0, theta_bins - 1)
    phi = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
    phi_bin = np.clip((phi / (2 * np.pi) * phi_bins).astype(int), 0, phi_bins - 1)
    observed = np.zeros((theta_bins, phi_bins))
    np.add.at(observed, (z_bin, phi_bin), 1)
    return observed


def p_value(observed: np.ndarray, expected: np.ndarray) -> tuple[float, float, int]:
    """(p, chi2, degrees of freedom) of the counts against the expected
    counts, bins expecting under 5 pooled; where those expect nothing,
    they must have drawn nothing (asserted)."""
    observed, expected = np.ravel(observed), np.ravel(expected)
    small = expected < 5
    observed_pooled, expected_pooled = observed[~small], expected[~small]
    if expected[small].sum() > 0:
        observed_pooled = np.append(observed_pooled, observed[small].sum())
        expected_pooled = np.append(expected_pooled, expected[small].sum())
    else:  # no density there: no sample either
        assert observed[small].sum() == 0
    expected_pooled = expected_pooled * observed_pooled.sum() / expected_pooled.sum()
    chi2 = float(((observed_pooled - expected_pooled) ** 2 / expected_pooled).sum())
    dof = len(observed_pooled) - 1
    return float(stats.chi2.sf(chi2, dof)), chi2, dof
