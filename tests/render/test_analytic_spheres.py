"""The renderer on a scene's analytic spheres (Scene(spheres=...)): the
path integrator's white furnaces and pbrt's analytic sphere, exact here
where a tessellated sphere needed slack; the previews' normals; Mitsuba
XML spheres loaded as analytic ones; and emitting spheres: a ground under
one, and their light samples against their density (the cone a sphere
subtends)."""
from __future__ import annotations

import numpy as np
import pytest

import hlbvh_cl
from hlbvh_cl.io.scenefile import load
from test_path import FURNACE, assert_blocks, seeded

#: A square far below the unit sphere, out of the cameras' view: a Scene
#: holds at least one mesh.
FLOOR = ([[-1, -50, -1], [1, -50, -1], [1, -50, 1], [-1, -50, 1]], [[0, 2, 1], [0, 3, 2]])
UNIT = [[0.0, 0.0, 0.0, 1.0]]


def scene_with_a_sphere(device, sphere=UNIT) -> hlbvh_cl.Scene:
    return hlbvh_cl.Scene([hlbvh_cl.Mesh(*FLOOR, name="floor")], device=device, spheres=sphere)


@pytest.mark.parametrize("material", [
    {"type": "diffuse", "reflectance": 1.0},
    {"type": "conductor"},
    {"type": "dielectric"},
    {"type": "dielectric", "int_ior": 1.0, "ext_ior": 1.33},  # denser outside
])
def test_a_white_sphere_in_a_white_furnace_is_white(material, suite_device):
    """Nothing absorbs: 1 comes back along every path.  Glass tests the
    rays that leave the sphere from inside (the near root of a ray from
    its surface must not be taken again)."""
    scene = scene_with_a_sphere(suite_device)
    camera = hlbvh_cl.Camera(eye=(0, 0.5, 3.5), target=(0, 0, 0), fov_deg=40)
    renderer = hlbvh_cl.Renderer(scene, materials=[{"type": "diffuse", "reflectance": 1.0},
                                                   material], emitters=FURNACE)
    images = seeded(renderer, camera, 20, 20, spp=8)
    hits = scene.intersect(*camera.rays(20, 20)).geom_id.reshape(20, 20) == 1
    assert hits.mean() > 0.25
    assert_blocks(images, 1.0, slack=1e-3, label=material["type"])


def test_pbrt_s_analytic_sphere_is_exact(suite_device):
    """Inside a two-sided diffuse sphere of radius 1 and albedo 0.5, a point
    light of intensity pi at its centre gives radiance 1 everywhere: 0.5
    directly (exactly: every point is at distance 1), as much again over
    the bounces."""
    scene = scene_with_a_sphere(suite_device)
    white = {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": 0.5}}
    renderer = hlbvh_cl.Renderer(scene, materials=[white, white], emitters=[
        {"type": "point", "position": [0, 0, 0], "intensity": np.pi}])
    camera = hlbvh_cl.Camera(eye=(0.1, 0.2, 0.3), target=(0, 0, -1), fov_deg=60)
    direct = renderer.render(camera, 16, 12, shading="path", hdr=True, spp=1, max_depth=2)
    np.testing.assert_allclose(direct, 0.5, rtol=2e-5)
    # Russian roulette from bounce 100 on (at rr_depth 5 its rare large
    # weights make the seeds' spread a poor standard error)
    assert_blocks(seeded(renderer, camera, 16, 12, spp=8, rr_depth=100), 1.0, slack=1e-3,
                  label="all")


def test_path_stats_count_the_shadow_rays_the_light_samples_cast(suite_device):
    """The renderer's ray counts are the device's, not an estimate.  Inside
    pbrt's sphere (above) every camera ray hits the sphere, and every hit
    faces the point light at distance 1: at max depth 2 each of the 16 x 12
    paths casts one shadow ray at its first vertex, goes on (Russian roulette
    starts at depth 5) and ends at its second, where it samples no light.
    Under a constant environment alone no vertex samples a light (BSDF
    sampling alone reaches it), and no shadow ray is cast."""
    scene = scene_with_a_sphere(suite_device)
    white = {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": 0.5}}
    camera = hlbvh_cl.Camera(eye=(0.1, 0.2, 0.3), target=(0, 0, -1), fov_deg=60)
    lit = hlbvh_cl.Renderer(scene, materials=[white, white], emitters=[
        {"type": "point", "position": [0, 0, 0], "intensity": np.pi}])
    lit.render(camera, 16, 12, shading="path", hdr=True, spp=1, max_depth=2)
    pixels = 16 * 12
    assert lit.stats["depths"]["paths"] == [pixels, pixels]
    assert lit.stats["depths"]["shadow_rays"] == [pixels, 0]
    assert lit.stats["primary_rays"] == pixels
    assert lit.stats["secondary_rays"] == 2 * pixels  # the bounces and the shadow rays

    furnace = hlbvh_cl.Renderer(scene, materials=[white, white], emitters=FURNACE)
    furnace.render(camera, 16, 12, shading="path", hdr=True, spp=2, max_depth=3)
    depths = furnace.stats["depths"]
    assert depths["paths"][:2] == [2 * pixels, 2 * pixels], depths["paths"]
    assert depths["shadow_rays"] == [0] * len(depths["paths"])
    assert furnace.stats["secondary_rays"] == sum(depths["paths"][1:])


def test_the_normals_preview_shows_the_sphere_s_normals(suite_device):
    scene = scene_with_a_sphere(suite_device)
    camera = hlbvh_cl.Camera(eye=(0, 0, 4), target=(0, 0, 0), fov_deg=40)
    image = hlbvh_cl.Renderer(scene).render(camera, 32, 32, shading="normals")
    hits = scene.intersect(*camera.rays(32, 32))
    on = hits.geom_id.reshape(32, 32) == 1
    assert on.mean() > 0.2
    # the preview encodes n as (n + 1) / 2 in 8 bits
    shown = image[on].astype(np.float64) / 255 * 2 - 1
    np.testing.assert_allclose(shown, hits.normal.reshape(32, 32, 3)[on], atol=0.02)


def test_mitsuba_spheres_load_as_analytic_spheres(tmp_path, suite_device):
    """A sphere shape is Scene's analytic sphere, by centre and radius or by
    to_world, an emitting one too."""
    path = tmp_path / "balls.xml"
    path.write_text("""<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 0, 6" target="0, 0, 0" up="0, 1, 0"/>
    </transform>
    <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="16"/>
    </film></sensor>
  <shape type="sphere"><point name="center" x="1" y="0" z="0"/><float name="radius" value="0.5"/>
    <bsdf type="conductor"/></shape>
  <shape type="rectangle"/>
  <shape type="sphere"><transform name="to_world"><scale value="0.25"/>
    <translate x="-1" y="0.5" z="0"/></transform></shape>
  <shape type="sphere"><point name="center" x="0" y="2" z="0"/><float name="radius" value="0.3"/>
    <emitter type="area"><rgb name="radiance" value="4"/></emitter></shape>
</scene>""")
    loaded = load(path, suite_device)
    scene = loaded.scene
    assert [m.name for m in scene.meshes] == ["rectangle"]
    np.testing.assert_allclose(scene.spheres, [[1, 0, 0, 0.5], [-1, 0.5, 0, 0.25],
                                               [0, 2, 0, 0.3]])
    assert [m["type"] for m in loaded.materials] == ["diffuse", "conductor", "diffuse",
                                                     "diffuse"]
    assert loaded.emitters == [{"type": "area", "radiance": [4.0, 4.0, 4.0], "mesh": 3}]
    assert len(loaded.colors) == 4
    hits = scene.intersect([[1, 0, 6], [-1, 0.5, 6], [0, 2, 6]], [[0, 0, -1]] * 3)
    np.testing.assert_array_equal(hits.geom_id, [1, 2, 3])
    np.testing.assert_allclose(hits.t, [5.5, 5.75, 5.7], rtol=1e-6)
    image = loaded.renderer().render(loaded.camera, 24, 16, shading="path", spp=2, hdr=True)
    assert np.isfinite(image).all() and image.max() > 0


def test_a_ground_under_a_sphere_light_is_lit_as_by_a_point(suite_device):
    """A sphere of radius R and radiance L wholly above a diffuse ground
    gives it the irradiance of a point of intensity pi R^2 L at its centre
    (Lambert: E = L pi R^2 cos theta / d^2), so the ground shows
    rho L R^2 cos theta / d^2 (max_depth 2: direct light, its light samples
    and its BSDF samples that meet the sphere weighed by MIS)."""
    rho, radiance, radius, centre = 0.7, 4.0, 0.5, np.array([0.3, 1.5, -0.2])
    ground = hlbvh_cl.Mesh([[-6, 0, -6], [6, 0, -6], [6, 0, 6], [-6, 0, 6]],
                           [[0, 2, 1], [0, 3, 2]], name="ground")
    scene = hlbvh_cl.Scene([ground], device=suite_device, spheres=[[*centre, radius]])
    renderer = hlbvh_cl.Renderer(scene, materials=[{"type": "diffuse", "reflectance": rho},
                                                   {"type": "diffuse", "reflectance": 0.5}],
                                 emitters=[{"type": "area", "mesh": 1, "radiance": radiance}])
    camera = hlbvh_cl.Camera(eye=(0, 0.6, 1.5), target=(0, 0, 0.5), fov_deg=40)
    width, height = 24, 16
    hits = scene.intersect(*camera.rays(width, height))
    assert (hits.geom_id == 0).all(), "the camera sees only the ground"
    to_centre = centre - hits.points.reshape(height, width, 3).astype(np.float64)
    squared = (to_centre ** 2).sum(-1)
    expected = rho * radiance * radius ** 2 * to_centre[..., 1] / squared ** 1.5
    images = seeded(renderer, camera, width, height, spp=32, max_depth=2)
    # slack: a pixel's mean over its footprint against its centre's value
    assert_blocks(images, expected, slack=1e-2, label="sphere light")


def test_light_samples_of_a_sphere_fill_the_cone_it_subtends(suite_device):
    """Light samples on an emitting sphere seen from a point X outside it go
    uniformly into the cone it subtends (Mitsuba's and pbrt's sphere
    sampling): 1 - cos theta over 1 - cos theta_max and the azimuth about
    the axis to its centre are uniform (a chi-squared test), the density is
    1 / (2 pi (1 - cos theta_max)) per solid angle, and each sample reaches
    the near side of the sphere, bringing its radiance.  From inside, the
    sphere shows its back, which does not emit: no sample."""
    import chi2
    from hlbvh_cl.render.sampling import sample_lights
    radius, centre, radiance = 0.6, np.array([0.4, 1.6, -0.3]), [2.0, 3.0, 1.0]
    x = np.array([0.1, 0.2, 0.3])
    scene = scene_with_a_sphere(suite_device, [[*centre, radius]])
    renderer = hlbvh_cl.Renderer(scene, emitters=[{"type": "area", "mesh": 1,
                                                   "radiance": radiance}])
    count = 200_000
    drawn = sample_lights(renderer, x, count, seed=3)
    assert (drawn["pdfs"] > 0).all()
    directions = drawn["directions"].astype(np.float64)
    distance = np.linalg.norm(centre - x)
    axis = (centre - x) / distance
    one_minus_cos = 1 - np.sqrt(1 - (radius / distance) ** 2)
    side = np.cross(axis, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    up = np.cross(axis, side)
    drop = np.clip((1 - directions @ axis) / one_minus_cos, 0, 1 - 1e-12)
    azimuth = np.arctan2(directions @ up, directions @ side) % (2 * np.pi) / (2 * np.pi)
    observed = np.histogram2d(drop, azimuth, bins=(16, 32), range=((0, 1), (0, 1)))[0]
    p, statistic, dof = chi2.p_value(observed, np.full_like(observed, count / observed.size))
    assert p > 1e-3, f"chi2 {statistic:.1f} over {dof} dof: p = {p:.2e}"
    np.testing.assert_allclose(drawn["pdfs"], 1 / (2 * np.pi * one_minus_cos), rtol=1e-4)
    np.testing.assert_allclose(drawn["radiance"], np.tile(radiance, (count, 1)), rtol=1e-6)
    points = x + directions * drawn["reaches"][:, None].astype(np.float64)
    normals = (points - centre) / radius
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-4)
    assert ((normals * (x - points)).sum(1) > -1e-4).all(), "the near side"
    inside = sample_lights(renderer, centre + [0.1, 0.0, 0.2], 1000, seed=4)
    assert not (inside["pdfs"] > 0).any()


def test_an_emitting_sphere_does_not_light_itself(suite_device):
    """A convex emitter never sees itself: a rough glass sphere emitting 1
    in the dark shows exactly 1 (max_depth 2), where light samples from a
    point of its surface rounded outside once took the sphere for a
    hemisphere around it and found it at t near 0 (up to 1.017)."""
    from scipy.ndimage import binary_erosion
    scene = scene_with_a_sphere(suite_device)
    camera = hlbvh_cl.Camera(eye=(0, 0, 4), target=(0, 0, 0), fov_deg=30)
    on = binary_erosion(scene.intersect(*camera.rays(24, 24)).geom_id.reshape(24, 24) == 1,
                        iterations=2)
    assert on.sum() > 100
    for alpha in (0.1, 0.6):
        renderer = hlbvh_cl.Renderer(scene, materials=[
            {"type": "diffuse"}, {"type": "roughdielectric", "alpha": alpha}], emitters=[
            {"type": "area", "mesh": 1, "radiance": 1.0}, {"type": "constant", "radiance": 0.0}])
        image = renderer.render(camera, 24, 24, shading="path", spp=16, max_depth=2, hdr=True)
        np.testing.assert_allclose(image[on], 1.0, rtol=1e-6, err_msg=f"alpha {alpha}")


def test_the_depth_preview_reaches_a_sphere_beyond_the_meshes(suite_device):
    """The previews' depth range and offsets come from the tree's box, which
    takes in the spheres: a sphere far behind a small mesh is not shown as
    a miss."""
    small = hlbvh_cl.Mesh([[-0.4, -0.4, 0], [0.4, -0.4, 0], [0, 0.4, 0]], [[0, 1, 2]])
    scene = hlbvh_cl.Scene([small], device=suite_device, spheres=[[0, 0, -20, 5]])
    camera = hlbvh_cl.Camera(eye=(0, 0, 2), target=(0, 0, 0), fov_deg=60)
    geom = scene.intersect(*camera.rays(16, 16)).geom_id.reshape(16, 16)
    assert (geom == 1).sum() > 10 and (geom == 0).sum() > 6 and (geom == -1).sum() > 3
    depth = hlbvh_cl.Renderer(scene).render(camera, 16, 16, shading="depth")[..., 0]
    assert len(np.unique(depth[geom == -1])) == 1
    sphere, miss, mesh = depth[geom == 1], depth[geom == -1][0], depth[geom == 0]
    assert (sphere != miss).all() and (sphere != mesh.min()).all()


def test_a_mitsuba_file_of_spheres_alone_loads_them_as_meshes(tmp_path, suite_device):
    """A Scene holds at least one mesh: a file of spheres alone traces them
    as their icospheres, as it did before spheres were analytic."""
    path = tmp_path / "ball.xml"
    path.write_text("""<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="40"/>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/>
    </film></sensor>
  <shape type="sphere"><point name="center" x="0" y="0" z="5"/><float name="radius" value="1"/>
  </shape></scene>""")
    loaded = load(path, suite_device)
    assert [m.name for m in loaded.scene.meshes] == ["sphere"]
    assert loaded.scene.spheres.shape == (0, 4)
    assert loaded.scene.intersect([[0, 0, 0]], [[0, 0, 1]]).geom_id[0] == 0
