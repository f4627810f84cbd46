"""The path integrator's BSDFs on their own (hlbvh_cl/render/sampling.py),
as Mitsuba 3's chi2 tests check its plugins:

- chi-squared: the directions a BSDF samples fall into bins of the sphere
  as often as its own density, integrated over each bin from its
  evaluation, says;
- each sample's weight is f cos / pdf of its own evaluation, and its
  density the one evaluation gives;
- delta BSDFs: the mirror direction, and glass's reflected share equal to
  Fresnel's reflectance in float64 with every refracted direction on
  Snell's law.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

import chi2
from hlbvh_cl.render.sampling import eval_bsdf, sample_bsdf

#: Bins in cos(theta) and phi (equal solid angles), samples drawn.
THETA_BINS, PHI_BINS, SAMPLES = 24, 48, 400_000

GLOSSY = [
    ({"type": "diffuse", "reflectance": 0.7}, (0.3, 0.2, 0.9)),
    ({"type": "twosided", "bsdf": {"type": "diffuse"}}, (0.2, 0.1, -0.9)),  # its back side
    ({"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}, (0.5, 0.1, 0.8)),
    ({"type": "roughconductor", "distribution": "ggx", "alpha": 0.08,
      "eta": [0.2, 0.9, 1.1], "k": [3.9, 2.4, 2.2]}, (0.1, -0.3, 0.9)),
    ({"type": "roughconductor", "distribution": "ggx", "alpha": 0.6}, (0.9, 0.0, 0.15)),  # grazing
]


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def bin_integrals(material, wo, device, sub=6):
    """The BSDF's density integrated over each (cos theta, phi) bin by a
    sub x sub midpoint rule: the share of samples each bin should get."""
    directions, cell = chi2.bin_directions(THETA_BINS, PHI_BINS, sub)
    pdfs = eval_bsdf(material, wo, directions, device=device)["pdfs"]
    return chi2.bin_shares(pdfs, cell, THETA_BINS, PHI_BINS, sub)


@pytest.mark.parametrize("material, wo", GLOSSY,
                         ids=["diffuse", "twosided-back", "ggx-0.3", "ggx-0.08-colour",
                              "ggx-0.6-grazing"])
def test_sampling_matches_the_density_chi_squared(material, wo, suite_device):
    wo = unit(wo)
    drawn = sample_bsdf(material, wo, SAMPLES, seed=7, device=suite_device)
    ok = drawn["weights"].max(axis=1) > 0
    assert ok.mean() > 0.5, "most samples should be taken"
    observed = chi2.binned(drawn["directions"][ok], THETA_BINS, PHI_BINS)
    shares = bin_integrals(material, wo, suite_device)
    # the density integrates to the share of samples taken (the rest fail:
    # reflected below the surface), up to the midpoint rule's error
    assert abs(shares.sum() - ok.mean()) < 0.02, (shares.sum(), ok.mean())
    p, statistic, dof = chi2.p_value(observed, shares * SAMPLES)
    assert p > 1e-3, f"chi2 {statistic:.1f} over {dof} dof: p = {p:.2e}"


@pytest.mark.parametrize("material, wo", GLOSSY, ids=["diffuse", "twosided-back", "ggx-0.3",
                                                      "ggx-0.08-colour", "ggx-0.6-grazing"])
def test_a_sample_s_weight_and_density_are_its_evaluation_s(material, wo, suite_device):
    wo = unit(wo)
    drawn = sample_bsdf(material, wo, 2000, seed=3, device=suite_device)
    ok = drawn["weights"].max(axis=1) > 0
    values = eval_bsdf(material, wo, drawn["directions"][ok], device=suite_device)
    np.testing.assert_allclose(values["pdfs"], drawn["pdfs"][ok], rtol=2e-4, atol=1e-7)
    np.testing.assert_allclose(values["values"] / values["pdfs"][:, None],
                               drawn["weights"][ok], rtol=2e-3)


def fresnel_dielectric(cos_i, eta):
    """Unpolarised Fresnel reflectance in float64 (cos_i > 0: from outside)."""
    ratio = eta if cos_i >= 0 else 1 / eta
    c = abs(cos_i)
    sin2_t = (1 - c * c) / ratio**2
    if sin2_t >= 1:
        return 1.0
    t = np.sqrt(1 - sin2_t)
    a_s = (c - ratio * t) / (c + ratio * t)
    a_p = (t - ratio * c) / (t + ratio * c)
    return 0.5 * (a_s**2 + a_p**2)


@pytest.mark.parametrize("wo, eta", [((0.4, 0.0, 0.9), 1.5), ((0.7, 0.2, 0.3), 1.5),
                                     ((0.3, 0.1, -0.9), 1.5), ((0.95, 0.0, -0.3), 1.5),
                                     ((0.5, 0.5, 0.7), 1 / 1.33)],
                         ids=["outside", "outside-grazing", "inside", "inside-beyond-critical",
                              "denser-outside"])
def test_glass_reflects_fresnel_s_share_and_refracts_by_snell(wo, eta, suite_device):
    wo = unit(wo)
    n = np.array([0.0, 0.0, 1.0])
    material = {"type": "dielectric", "int_ior": eta, "ext_ior": 1.0}
    drawn = sample_bsdf(material, wo, 100_000, seed=5, device=suite_device)
    d = drawn["directions"].astype(np.float64)
    assert (drawn["pdfs"] == 0).all(), "a delta BSDF has no density"
    mirror = 2 * (wo @ n) * n - wo
    reflected = np.abs(d - mirror).max(axis=1) < 1e-5
    share = fresnel_dielectric(wo[2], eta)
    k = reflected.sum()
    assert stats.binomtest(int(k), len(d), share).pvalue > 1e-3, (k / len(d), share)
    refracted = d[~reflected]
    if share < 1:
        # Snell: eta_i sin_i = eta_t sin_t, the tangent parts opposite, on the other side
        eta_it = eta if wo[2] > 0 else 1 / eta
        np.testing.assert_allclose(np.linalg.norm(refracted[:, :2], axis=1),
                                   np.linalg.norm(wo[:2]) / eta_it, rtol=1e-5)
        assert (np.sign(refracted[:, 2]) == -np.sign(wo[2])).all()
        np.testing.assert_allclose(refracted[:, :2] / np.linalg.norm(refracted[:, :2], axis=1,
                                                                     keepdims=True),
                                   np.broadcast_to(-wo[:2] / np.linalg.norm(wo[:2]),
                                                   refracted[:, :2].shape), atol=1e-5)
        # refraction scales radiance by 1 / eta_it^2 (Mitsuba's radiance mode)
        np.testing.assert_allclose(drawn["weights"][~reflected], 1 / eta_it**2, rtol=1e-5)
    else:
        assert not len(refracted), "total internal reflection"


def test_a_conductor_reflects_in_the_mirror_direction_with_fresnel_s_weight(suite_device):
    wo = unit((0.6, -0.2, 0.7))
    eta, k = np.array([0.2, 0.9, 1.1]), np.array([3.9, 2.4, 2.2])
    drawn = sample_bsdf({"type": "conductor", "eta": eta.tolist(), "k": k.tolist()}, wo, 16,
                        device=suite_device)
    np.testing.assert_allclose(drawn["directions"], np.tile([-wo[0], -wo[1], wo[2]], (16, 1)),
                               atol=1e-6)
    # Fresnel for a conductor in complex float64 (Born & Wolf)
    c = wo[2]
    n_complex = eta + 1j * k
    sin2 = 1 - c * c
    cos_t = np.sqrt(1 - sin2 / n_complex**2)
    r_s = (c - n_complex * cos_t) / (c + n_complex * cos_t)
    r_p = (n_complex * c - cos_t) / (n_complex * c + cos_t)
    expected = 0.5 * (np.abs(r_s) ** 2 + np.abs(r_p) ** 2)
    np.testing.assert_allclose(drawn["weights"][0], expected, rtol=1e-4)
    perfect = sample_bsdf({"type": "conductor"}, wo, 4, device=suite_device)
    np.testing.assert_allclose(perfect["weights"], 1.0, rtol=1e-6)
