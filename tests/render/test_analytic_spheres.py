"""The renderer on a scene's analytic spheres (Scene(spheres=...)): the
path integrator's white furnaces and pbrt's analytic sphere, exact here
where a tessellated sphere needed slack; the previews' normals; Mitsuba
XML spheres loaded as analytic ones (but an emitting one); and the error
for an area emitter on a sphere."""
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
    to_world; one with an area emitter stays a mesh (the renderer samples
    light from triangles)."""
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
    assert [m.name for m in scene.meshes] == ["rectangle", "sphere"]  # the lamp: a mesh
    np.testing.assert_allclose(scene.spheres, [[1, 0, 0, 0.5], [-1, 0.5, 0, 0.25]])
    assert [m["type"] for m in loaded.materials] == ["diffuse", "diffuse", "conductor",
                                                     "diffuse"]
    assert loaded.emitters == [{"type": "area", "radiance": [4.0, 4.0, 4.0], "mesh": 1}]
    assert len(loaded.colors) == 4
    hits = scene.intersect([[1, 0, 6], [-1, 0.5, 6], [0, 2, 6]], [[0, 0, -1]] * 3)
    np.testing.assert_array_equal(hits.geom_id, [2, 3, 1])
    np.testing.assert_allclose(hits.t[:2], [5.5, 5.75], rtol=1e-6)
    image = loaded.renderer().render(loaded.camera, 24, 16, shading="path", spp=2, hdr=True)
    assert np.isfinite(image).all() and image.max() > 0


def test_an_area_emitter_on_a_sphere_is_refused(suite_device):
    scene = scene_with_a_sphere(suite_device)
    renderer = hlbvh_cl.Renderer(scene, emitters=[{"type": "area", "mesh": 1, "radiance": 1.0}])
    camera = hlbvh_cl.Camera(eye=(0, 0, 4), target=(0, 0, 0))
    with pytest.raises(ValueError, match=r"an area emitter on geom_id 1, an analytic sphere"):
        renderer.render(camera, 8, 8, shading="path")
