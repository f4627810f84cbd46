"""The path integrator's BSDFs on their own (hlbvh_cl/render/sampling.py),
as Mitsuba 3's chi2 tests check its plugins:

- chi-squared: the directions a BSDF samples fall into bins of the sphere
  as often as its own density, integrated over each bin from its
  evaluation, says;
- each sample's weight is f cos / pdf of its own evaluation, and its
  density the one evaluation gives;
- delta BSDFs: the mirror direction, and glass's reflected share equal to
  Fresnel's reflectance in float64 with every refracted direction on
  Snell's law; plastic's mirror lobe: its share and weight in float64;
- values and densities against Mitsuba 3's own BSDFs (scalar_rgb), at
  random directions.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

import chi2
from hlbvh_cl.render.sampling import eval_bsdf, sample_bsdf, turn_angles

#: Bins in cos(theta) and phi (equal solid angles), samples drawn.
THETA_BINS, PHI_BINS, SAMPLES = 24, 48, 400_000

GLOSSY = [
    ({"type": "diffuse", "reflectance": 0.7}, (0.3, 0.2, 0.9)),
    ({"type": "twosided", "bsdf": {"type": "diffuse"}}, (0.2, 0.1, -0.9)),  # its back side
    ({"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}, (0.5, 0.1, 0.8)),
    ({"type": "roughconductor", "distribution": "ggx", "alpha": 0.08,
      "eta": [0.2, 0.9, 1.1], "k": [3.9, 2.4, 2.2]}, (0.1, -0.3, 0.9)),
    ({"type": "roughconductor", "distribution": "ggx", "alpha": 0.6}, (0.9, 0.0, 0.15)),  # grazing
    ({"type": "roughconductor", "alpha": 0.3}, (0.5, 0.1, 0.8)),  # Mitsuba's default: beckmann
    ({"type": "roughconductor", "alpha": 0.5, "eta": [0.2, 0.9, 1.1], "k": [3.9, 2.4, 2.2]},
     (0.9, 0.0, 0.2)),
    # plastic: its smooth lobe only (samples of the mirror lobe have no density)
    ({"type": "plastic", "diffuse_reflectance": [0.2, 0.5, 0.8]}, (0.6, 0.1, 0.5)),
    ({"type": "roughplastic", "distribution": "ggx", "alpha": 0.3}, (0.5, 0.1, 0.8)),
    ({"type": "roughplastic", "alpha": 0.2, "diffuse_reflectance": 0.1, "int_ior": 1.8,
      "nonlinear": True}, (0.8, 0.2, 0.3)),
    ({"type": "roughdielectric", "distribution": "ggx", "alpha": 0.3, "int_ior": 1.5,
      "ext_ior": 1.0}, (0.4, 0.1, 0.9)),
    ({"type": "roughdielectric", "distribution": "ggx", "alpha": 0.4, "int_ior": 1.5,
      "ext_ior": 1.0}, (0.5, 0.2, -0.7)),  # from inside
    ({"type": "roughdielectric", "alpha": 0.3, "int_ior": 1.33, "ext_ior": 1.0},
     (0.7, 0.0, 0.5)),
    ({"type": "roughdielectric", "alpha": 0.5, "int_ior": 1.5, "ext_ior": 1.0},
     (0.6, 0.3, -0.5)),  # from inside, beckmann
]
GLOSSY_IDS = ["diffuse", "twosided-back", "ggx-0.3", "ggx-0.08-colour", "ggx-0.6-grazing",
              "beckmann-0.3", "beckmann-0.5-colour", "plastic", "roughplastic-ggx",
              "roughplastic-beckmann-nonlinear", "roughdielectric-ggx",
              "roughdielectric-ggx-inside", "roughdielectric-beckmann",
              "roughdielectric-beckmann-inside"]


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def bin_integrals(material, wo, device, sub=6):
    """The BSDF's density integrated over each (cos theta, phi) bin by a
    sub x sub midpoint rule: the share of samples each bin should get."""
    directions, cell = chi2.bin_directions(THETA_BINS, PHI_BINS, sub)
    pdfs = eval_bsdf(material, wo, directions, device=device)["pdfs"]
    return chi2.bin_shares(pdfs, cell, THETA_BINS, PHI_BINS, sub)


@pytest.mark.parametrize("material, wo", GLOSSY, ids=GLOSSY_IDS)
def test_sampling_matches_the_density_chi_squared(material, wo, suite_device):
    wo = unit(wo)
    drawn = sample_bsdf(material, wo, SAMPLES, seed=7, device=suite_device)
    # the smooth lobes' samples: a delta lobe's (density 0) lie outside the density
    ok = (drawn["weights"].max(axis=1) > 0) & (drawn["pdfs"] > 0)
    assert ok.mean() > 0.5, "most samples should be taken"
    observed = chi2.binned(drawn["directions"][ok], THETA_BINS, PHI_BINS)
    shares = bin_integrals(material, wo, suite_device)
    # the density integrates to the share of samples taken (the rest fail:
    # reflected below the surface), up to the midpoint rule's error
    assert abs(shares.sum() - ok.mean()) < 0.02, (shares.sum(), ok.mean())
    p, statistic, dof = chi2.p_value(observed, shares * SAMPLES)
    assert p > 1e-3, f"chi2 {statistic:.1f} over {dof} dof: p = {p:.2e}"


@pytest.mark.parametrize("material, wo", GLOSSY, ids=GLOSSY_IDS)
def test_a_sample_s_weight_and_density_are_its_evaluation_s(material, wo, suite_device):
    wo = unit(wo)
    drawn = sample_bsdf(material, wo, 2000, seed=3, device=suite_device)
    ok = (drawn["weights"].max(axis=1) > 0) & (drawn["pdfs"] > 0)
    values = eval_bsdf(material, wo, drawn["directions"][ok], device=suite_device)
    np.testing.assert_allclose(values["pdfs"], drawn["pdfs"][ok], rtol=2e-4, atol=1e-7)
    np.testing.assert_allclose(values["values"] / values["pdfs"][:, None],
                               drawn["weights"][ok], rtol=2e-3)


def beckmann_visible_density(alpha, wo, px, py):
    """Heitz & d'Eon 2014's visible-normal density of Beckmann, eq. 2:
    G1(wo) max(0, wo . m) D(m) / wo.z with Smith's exact G1 (their eq. 18's
    Lambda through erf), in float64, per unit area of the slopes
    (px, py) = -(m.x, m.y) / (alpha m.z), where d omega = alpha^2 cos^3 d p
    (the slope density D cos^4 is a Gaussian); and the directions m."""
    from scipy.special import erf
    r2 = px * px + py * py
    cos_m = 1 / np.sqrt(1 + alpha * alpha * r2)
    m = np.stack([-alpha * px * cos_m, -alpha * py * cos_m, cos_m], -1)
    d = np.exp(-r2) / (np.pi * alpha**2 * cos_m**4)
    a = wo[2] / (alpha * np.hypot(wo[0], wo[1]))
    lam = (erf(a) - 1) / 2 + np.exp(-a * a) / (2 * a * np.sqrt(np.pi))
    density = np.clip(m @ wo, 0, None) * d / ((1 + lam) * wo[2])
    return density * alpha**2 * cos_m**3, m


@pytest.mark.parametrize("alpha", [0.1, 0.6])
@pytest.mark.parametrize("cos_o", [0.1, 0.95], ids=["grazing", "near-normal"])
def test_beckmann_samples_its_visible_normals(alpha, cos_o, suite_device):
    """The microfacet normals Beckmann samples (the half vectors of a
    perfect rough mirror's samples) against the analytic visible-normal
    density, binned in their slopes (in units of alpha, so that a narrow
    lobe is resolved): chi-squared on where they fall, and binomial on how
    many reflect above the surface."""
    wo = np.array([np.sqrt(1 - cos_o**2), 0.0, cos_o])
    count, bins, extent, sub = 200_000, 36, 4.5, 16
    drawn = sample_bsdf({"type": "roughconductor", "alpha": alpha}, wo, count, seed=13,
                        device=suite_device)
    ok = drawn["weights"].max(axis=1) > 0
    m = wo + drawn["directions"][ok].astype(np.float64)
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    slopes = -m[:, :2] / (alpha * m[:, 2:])
    observed = np.histogram2d(slopes[:, 0], slopes[:, 1], bins=bins,
                              range=[[-extent, extent]] * 2)[0]
    centres = (np.arange(bins * sub) + 0.5) * (2 * extent / (bins * sub)) - extent
    px, py = np.meshgrid(centres, centres, indexing="ij")
    density, normals = beckmann_visible_density(alpha, wo, px, py)
    above = (2 * (normals @ wo)[..., None] * normals - wo)[..., 2] > 0  # the mirror's wi
    cell = (2 * extent / (bins * sub)) ** 2
    shares = (density * cell).reshape(bins, sub, bins, sub).sum(axis=(1, 3))
    reflected = (density * above * cell).reshape(bins, sub, bins, sub).sum(axis=(1, 3))
    assert abs(shares.sum() - 1) < 2e-3, shares.sum()  # the density and its Jacobian
    assert stats.binomtest(int(ok.sum()), count, reflected.sum()).pvalue > 1e-3, (
        ok.mean(), reflected.sum())
    p, statistic, dof = chi2.p_value(observed, reflected * count)
    assert p > 1e-3, f"chi2 {statistic:.1f} over {dof} dof: p = {p:.2e}"


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


@pytest.mark.parametrize("wo, albedo, specular", [((0.4, 0.0, 0.9), 0.5, 1.0),
                                                  ((0.9, 0.1, 0.2), [0.1, 0.6, 0.3], 0.7)],
                         ids=["default", "grazing-tinted"])
def test_plastic_s_mirror_lobe_takes_its_share_and_fresnel_s_weight(wo, albedo, specular,
                                                                     suite_device):
    """Mitsuba's plastic picks its coating with probability F s / (F s + (1
    - F) d), s and d the tints' means, and weighs the mirror sample by F /
    that probability times the specular tint."""
    wo = unit(wo)
    eta = 1.49 / 1.000277
    material = {"type": "plastic", "diffuse_reflectance": albedo,
                "specular_reflectance": specular}
    drawn = sample_bsdf(material, wo, 100_000, seed=11, device=suite_device)
    delta = (drawn["pdfs"] == 0) & (drawn["weights"].max(axis=1) > 0)
    f = fresnel_dielectric(wo[2], eta)
    s, d = np.mean(specular), np.mean(albedo)
    weight = s / (s + d)
    share = f * weight / (f * weight + (1 - f) * (1 - weight))
    assert stats.binomtest(int(delta.sum()), len(delta), share).pvalue > 1e-3, (delta.mean(),
                                                                                share)
    np.testing.assert_allclose(drawn["directions"][delta],
                               np.broadcast_to([-wo[0], -wo[1], wo[2]], (delta.sum(), 3)),
                               atol=1e-5)
    np.testing.assert_allclose(drawn["weights"][delta], specular * f / share, rtol=1e-4)


#: Local directions where BSDFs are compared with Mitsuba's: wo above (and,
#: for a dielectric, below) the surface, wi anywhere.
def _directions(count, seed):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(count, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("material", [
    {"type": "plastic", "diffuse_reflectance": [0.2, 0.5, 0.8]},
    {"type": "plastic", "diffuse_reflectance": 0.7, "nonlinear": True, "int_ior": 1.7,
     "specular_reflectance": 0.6},
    {"type": "roughplastic", "distribution": "ggx", "alpha": 0.2,
     "diffuse_reflectance": [0.2, 0.5, 0.8]},
    {"type": "roughplastic", "alpha": 0.4, "nonlinear": True, "diffuse_reflectance": 0.8},
    {"type": "roughdielectric", "distribution": "ggx", "alpha": 0.3, "int_ior": 1.5,
     "ext_ior": 1.0},
    {"type": "roughdielectric", "alpha": 0.2, "specular_transmittance": [0.9, 0.5, 0.3]},
    {"type": "roughconductor", "alpha": 0.3, "eta": [0.2, 0.9, 1.1], "k": [3.9, 2.4, 2.2]},
], ids=["plastic", "plastic-nonlinear", "roughplastic-ggx", "roughplastic-beckmann",
        "roughdielectric-ggx", "roughdielectric-beckmann", "roughconductor-beckmann"])
def test_values_agree_with_mitsuba_3(material, suite_device):
    """f cos at random pairs of directions equals Mitsuba 3's eval (its
    smooth lobes: plastic's mirror has no value), and so does the density,
    both sampling GGX and Beckmann by their visible normals."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")

    def theirs_of(value):
        return {"type": "rgb", "value": value} if isinstance(value, list) else value
    bsdf = mi.load_dict({key: theirs_of(value) for key, value in material.items()})
    two_sided = material["type"] == "roughdielectric"
    for k, wo in enumerate(_directions(6, 1)):
        wo = wo if two_sided else np.array([wo[0], wo[1], abs(wo[2])])
        wi = _directions(200, 10 + k)
        ours = eval_bsdf(material, wo, wi, device=suite_device)
        context = mi.BSDFContext()
        interaction = mi.SurfaceInteraction3f()
        interaction.wi = mi.Vector3f(*wo)
        values = np.array([list(bsdf.eval(context, interaction, mi.Vector3f(*w))) for w in wi])
        pdfs = np.array([bsdf.pdf(context, interaction, mi.Vector3f(*w)) for w in wi])
        # roughplastic's coating transmittance is a quadrature of ours (128^2
        # nodes) and of Mitsuba's (32^2), which differ by a few 0.1%; its
        # density picks the coating by 1 - transmittance, a small number,
        # of which that difference is a few %
        rough_plastic = material["type"] == "roughplastic"
        rtol = 1e-2 if rough_plastic else 2e-3
        np.testing.assert_allclose(ours["values"], values, rtol=rtol, atol=1e-6)
        assert ((ours["pdfs"] > 0) == (pdfs > 0)).all()
        np.testing.assert_allclose(ours["pdfs"], pdfs, rtol=2.5e-2 if rough_plastic else rtol,
                                   atol=1e-6)


@pytest.mark.parametrize("kind", ["roughconductor", "roughdielectric", "roughplastic"])
@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
def test_nearly_smooth_lobes_agree_with_mitsuba_3(kind, distribution, suite_device):
    """At the loader's smallest roughness (alpha 1e-4) and a little above,
    f cos and the density near the mirror direction, where D peaks, equal
    Mitsuba 3's, and every sample's weight is finite.  D and G1 formed from
    1 - cos^2 cancelled there in float32: GGX's D went to inf at 1e-4 (a
    rough glass ball rendered nearly black inside, its samples' weights NaN)
    and Beckmann's highlight came out 5x too bright."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    wo = np.array([0.3, 0.1, 0.9])
    wo /= np.linalg.norm(wo)
    for alpha in (1e-4, 3e-4, 1e-3):
        material = {"type": kind, "distribution": distribution, "alpha": alpha}
        # directions within a few alpha of the mirror direction, and it
        rng = np.random.default_rng(7)
        mirror = np.array([-wo[0], -wo[1], wo[2]])
        wi = mirror + 2.0 * alpha * rng.normal(size=(64, 3))
        wi = np.vstack([mirror, wi / np.linalg.norm(wi, axis=1, keepdims=True)])
        wi = wi.astype(np.float32).astype(np.float64)  # the very directions ours reads
        ours = eval_bsdf(material, wo, wi, device=suite_device)
        bsdf = mi.load_dict(material)
        context, interaction = mi.BSDFContext(), mi.SurfaceInteraction3f()
        interaction.wi = mi.Vector3f(*wo)
        values = np.array([list(bsdf.eval(context, interaction, mi.Vector3f(*w))) for w in wi])
        pdfs = np.array([bsdf.pdf(context, interaction, mi.Vector3f(*w)) for w in wi])
        assert np.isfinite(ours["values"]).all() and np.isfinite(ours["pdfs"]).all()
        # the peak is 1 / (pi alpha^2) high: compare relative to it where the
        # lobe is, as the tails fall off over a few float32 steps of wi
        peak = values.max()
        np.testing.assert_allclose(ours["values"], values, rtol=2e-2, atol=1e-4 * peak)
        np.testing.assert_allclose(ours["pdfs"], pdfs, rtol=5e-2, atol=1e-4 * pdfs.max())
        samples = sample_bsdf(material, wo, 20_000, seed=3, device=suite_device)
        assert np.isfinite(samples["weights"]).all(), (alpha, samples["weights"])


@pytest.mark.parametrize("eta", [1 / 1.5, 1.33, 1.49, 2.0])
def test_the_coatings_averages_are_fresnel_s_integrals(eta):
    """hlbvh_cl.render.coating against float64 quadrature of Fresnel's
    reflectance: the diffuse mean 2 int F(mu) mu dmu within Mitsuba's fits'
    stated accuracy (1%), and a nearly smooth rough coating (alpha 1e-3)
    letting in 1 - F(mu) away from grazing (and from the critical angle
    seen from inside)."""
    from scipy.integrate import quad
    from hlbvh_cl.render import coating
    exact = quad(lambda mu: 2 * fresnel_dielectric(mu, eta) * mu, 0, 1, limit=200)[0]
    assert abs(coating.diffuse_fresnel(eta) - exact) < 0.01 * exact + 1e-4
    cosines = np.linspace(0.3, 1.0, 8)
    for kind in ("ggx", "beckmann"):
        transmitted = coating.rough_transmission(kind, 1e-3, eta, cosines)
        expected = [1 - fresnel_dielectric(mu, eta) for mu in cosines]
        np.testing.assert_allclose(transmitted, expected, rtol=2e-3, atol=1e-4)


def test_the_samplers_angles_are_sin_and_cos_of_the_turn(suite_device):
    """sincos_turn (kernels/render/angles.h) against float64 numpy, at
    every 24-bit u the random numbers give (a stride through them, plus
    the quarter turns and their neighbours) and on (1, 2], where the
    environment map's cells can reach (1.5 for a map one texel wide):
    within 2 float32 ulps of 1, and on the unit circle as closely."""
    grid = np.arange(0, 1 << 24, 97, dtype=np.int64)
    quarters = np.array([0, 1, 2, 3, 4], np.int64) << 22
    edges = np.concatenate([quarters, quarters[1:] - 1, quarters[:-1] + 1, [(1 << 24) - 1]])
    u = np.concatenate([grid, edges]).astype(np.float64) * 2.0**-24
    u = np.concatenate([u, np.linspace(1.0, 2.0, 4001)]).astype(np.float32)
    got = turn_angles(u, device=suite_device)
    angle = 2.0 * np.pi * u.astype(np.float64)
    assert np.abs(got["sin"] - np.sin(angle)).max() < 2.4e-7
    assert np.abs(got["cos"] - np.cos(angle)).max() < 2.4e-7
    assert np.abs(got["sin"].astype(np.float64) ** 2 + got["cos"].astype(np.float64) ** 2
                  - 1.0).max() < 4.8e-7
    with pytest.raises(ValueError, match=r"u\[1\] must be in \[0, 2\]"):
        turn_angles([0.5, -0.1], device=suite_device)
