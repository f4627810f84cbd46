"""Next-event estimation's light samples (render/lights.h, drawn by
hlbvh_cl.render.sampling.sample_lights) against their density worked out
here in float64: the environment picked against the emissive triangles by
the power each can deliver (path.py's rule), a triangle by its area times its
radiance's luminance, a point uniform on it, so a density per solid angle of
P(triangle) / area * distance^2 / cos; and the environment map SKY_MAP, 4
rows (at theta = 0, pi / 3, 2 pi / 3, pi) of which the last is dark: its
cells hold L above theta = 2 pi / 3 and L / 2 below, in a cap of pi sr
around -y where no lamp lies, so its mean is 7 L / 8, and its light samples,
which take its excess over that mean (envmap.py), are uniform outside the
cap, 1 / (3 pi), with power S (L / 8) (3 pi) / (4 pi) = 3 S L / 32 (S the
scene's surface area).  A constant environment takes no light samples
(BSDF sampling alone reaches it).  A chi-squared test over the sphere, in
bins about +y (the cap's edge then a bin edge), as Mitsuba 3's chi2 tests
check their emitters, and each sample's own density and radiance."""
import numpy as np
import pytest

import chi2
import hlbvh_cl
from hlbvh_cl.render.sampling import sample_lights

THETA_BINS, PHI_BINS, SUB = 32, 64, 12
SAMPLES = 400_000
SKY = 0.2
SKY_MAP = np.full((4, 4, 3), SKY, np.float32)
SKY_MAP[3] = 0.0
#: the chi-squared bins' frame, a rotation from the world's: world +y is its +z
BINS = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
X = np.array([0.2, 0.5, 0.1])

GROUND = np.array([[-3, 0, -3], [3, 0, -3], [3, 0, 3], [-3, 0, 3]], np.float64)
LAMP = np.array([[-0.5, 2, -0.5], [0.5, 2, -0.5], [0.5, 2, 0.5], [-0.5, 2, 0.5]], np.float64)
#: two tilted triangles on either side of the point: the first faces it,
#: the second shows it its back, where samples are none (density 0)
PANE = np.array([[1.5, 0.2, -1.0], [1.5, 0.2, 1.0], [1.2, 1.8, 0.0],
                 [-1.5, 0.2, -1.0], [-1.5, 0.2, 1.0], [-1.2, 1.8, 0.0]], np.float64)
PANE_FACES = [[0, 1, 2], [3, 4, 5]]
LAMP_RADIANCE, PANE_RADIANCE = 5.0, [1.0, 2.0, 3.0]


def luminance(rgb):
    return float(np.dot([0.2126, 0.7152, 0.0722], np.broadcast_to(rgb, 3)))


def triangles():
    """The emissive triangles (T, 3, 3) and each one's luminance."""
    lamp, pane = LAMP[[[0, 1, 2], [0, 2, 3]]], PANE[PANE_FACES]
    return (np.concatenate([lamp, pane]),
            np.array([luminance(LAMP_RADIANCE)] * 2 + [luminance(PANE_RADIANCE)] * 2))


def density(directions):
    """The solid-angle density of a light sample towards each unit direction
    from X, and the radiance arriving along it from the light it came from
    (the environment's where no triangle is met: the sampler ignores
    occlusion, as next-event estimation leaves it to the shadow ray)."""
    tris, lum = triangles()
    e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    cross = np.cross(e1, e2)
    areas = 0.5 * np.linalg.norm(cross, axis=1)
    normals = cross / (2 * areas[:, None])
    surface = sum(0.5 * np.linalg.norm(np.cross(t[1] - t[0], t[2] - t[0])) for t in
                  [*GROUND[[[0, 2, 1], [0, 3, 2]]], *tris])
    sky_power, lamp_power = 3 * surface * luminance(SKY) / 32, float((areas * lum).sum())
    p_sky = sky_power / (sky_power + lamp_power)
    pdf = np.where(directions[:, 1] > -0.5, p_sky / (3 * np.pi), 0.0)
    # Moller-Trumbore, every direction against every triangle
    d = directions[:, None, :]
    p = np.cross(d, e2[None])
    det = (e1[None] * p).sum(-1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = X[None, None] - tris[None, :, 0]
    u = (s * p).sum(-1) * inv
    q = np.cross(s, e1[None])
    v = (d * q).sum(-1) * inv
    t = (e2[None] * q).sum(-1) * inv
    met = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    cosine = -(d * normals[None]).sum(-1)
    front = met & (cosine > 0)
    share = (1 - p_sky) * areas * lum / lamp_power  # P(triangle)
    pdf += np.where(front, share[None] / areas[None] * t**2 / np.where(front, cosine, 1.0),
                    0.0).sum(1)
    return pdf, front


@pytest.fixture(scope="module")
def renderer(suite_device):
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(GROUND, [[0, 2, 1], [0, 3, 2]]),
                            hlbvh_cl.Mesh(LAMP, [[0, 1, 2], [0, 2, 3]]),
                            hlbvh_cl.Mesh(PANE, PANE_FACES)], device=suite_device)
    return hlbvh_cl.Renderer(scene, emitters=[
        {"type": "area", "mesh": 1, "radiance": LAMP_RADIANCE},
        {"type": "area", "mesh": 2, "radiance": PANE_RADIANCE},
        {"type": "envmap", "image": SKY_MAP}])


def test_light_samples_follow_their_density_chi_squared(renderer):
    drawn = sample_lights(renderer, X, SAMPLES, seed=5)
    valid = drawn["pdfs"] > 0
    directions = drawn["directions"][valid].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-5)
    midpoints, cell = chi2.bin_directions(THETA_BINS, PHI_BINS, SUB)  # in the bins' frame
    shares = chi2.bin_shares(density(midpoints @ BINS)[0], cell, THETA_BINS, PHI_BINS, SUB)
    # the mass that falls on the pane's back: samples that are none
    lost = 1.0 - shares.sum()
    assert 0.005 < lost < 0.5, lost
    sigma = np.sqrt(SAMPLES * lost * (1 - lost))
    assert abs((~valid).sum() - SAMPLES * lost) < 5 * sigma + 0.002 * SAMPLES, (
        (~valid).sum(), SAMPLES * lost)
    observed = chi2.binned(directions @ BINS.T, THETA_BINS, PHI_BINS)
    p, statistic, dof = chi2.p_value(observed, shares * SAMPLES)
    assert p > 1e-3, f"chi2 {statistic:.1f} over {dof} dof: p = {p:.2e}"


def test_a_light_sample_s_density_and_radiance_are_its_light_s(renderer):
    drawn = sample_lights(renderer, X, 20_000, seed=9)
    valid = drawn["pdfs"] > 0
    directions = drawn["directions"][valid].astype(np.float64)
    reach = drawn["reaches"][valid].astype(np.float64)
    sky = np.isinf(reach)  # the environment's samples reach no surface
    pdf, front = density(directions)
    on_lamp, on_pane = front[:, :2].any(1) & ~sky, front[:, 2:].any(1) & ~sky
    assert (on_lamp | on_pane | sky).all()
    assert on_lamp.sum() > 1000 and on_pane.sum() > 100 and sky.sum() > 1000
    # a triangle's sample: its own density (the environment's share of the
    # direction is not in it: MIS weighs the two strategies apart), and the
    # distance to the point drawn on it
    # the environment's alone: just above its dark cap, towards the ground
    # (no light there), and in the cap
    probes = np.array([[0.0, -0.49, 0.9], [0.0, -1.0, 0.0]])
    above, inside = density(probes / np.linalg.norm(probes, axis=1, keepdims=True))[0]
    assert above > 0 and inside == 0
    assert (directions[sky, 1] > -0.5).all(), "no sample of the map in its dark cap"
    sky_pdf = np.where(directions[:, 1] > -0.5, above, 0.0)
    got = drawn["pdfs"][valid].astype(np.float64)
    np.testing.assert_allclose(got[~sky], (pdf - sky_pdf)[~sky], rtol=2e-3)
    np.testing.assert_allclose(got[sky], sky_pdf[sky], rtol=1e-5)
    radiance = drawn["radiance"][valid]
    np.testing.assert_allclose(radiance[on_lamp], LAMP_RADIANCE, rtol=1e-6)
    np.testing.assert_allclose(radiance[on_pane], np.tile(PANE_RADIANCE, (on_pane.sum(), 1)),
                               rtol=1e-6)
    np.testing.assert_allclose(radiance[sky], SKY, rtol=1e-6)  # outside the cap: all SKY
    points = X + directions[~sky] * reach[~sky, None]
    lamp_y = points[on_lamp[~sky], 1]
    np.testing.assert_allclose(lamp_y, 2.0, atol=1e-4)


def test_an_instanced_scene_samples_its_lights_as_the_flat_one(renderer, suite_device):
    """The same meshes drawn as identity instances: the emissive triangles
    are every instance's, in the world, so the samples are the flat scene's."""
    flat = renderer.scene
    instanced = hlbvh_cl.Scene(list(flat.meshes), device=suite_device,
                               instances=[(k, np.eye(3, 4)) for k in range(len(flat.meshes))])
    twin = hlbvh_cl.Renderer(instanced, emitters=renderer.emitters)
    ours, theirs = (sample_lights(r, X, 5000, seed=2) for r in (twin, renderer))
    for name in ("directions", "radiance", "pdfs", "reaches"):
        np.testing.assert_allclose(ours[name], theirs[name], rtol=1e-5, atol=1e-6,
                                   err_msg=name)


def test_a_constant_environment_takes_no_light_samples(renderer):
    """BSDF sampling alone reaches a constant environment (path.py): beside
    the lamps, it leaves their light samples as they are without it."""
    lamps = [emitter for emitter in renderer.emitters if emitter["type"] == "area"]
    assert len(lamps) == 2
    with_sky = hlbvh_cl.Renderer(renderer.scene, emitters=[
        *lamps, {"type": "constant", "radiance": SKY}])
    alone = hlbvh_cl.Renderer(renderer.scene, emitters=lamps)
    ours, theirs = (sample_lights(r, X, 5000, seed=4) for r in (with_sky, alone))
    assert (ours["pdfs"] > 0).sum() > 2000
    assert not np.isinf(ours["reaches"][ours["pdfs"] > 0]).any()
    for name in ("directions", "radiance", "pdfs", "reaches"):
        np.testing.assert_array_equal(ours[name], theirs[name], err_msg=name)
