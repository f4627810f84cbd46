"""Mitsuba 3's XML scenes (hlbvh_cl/io/mitsuba.py) against Mitsuba 3
itself reading the same files: the camera's rays, the shapes' placement,
and the Cornell box (scenes/cornell_box.xml) rendered by both; and the
errors an element outside the subset gets, with its line."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

import hlbvh_cl
from hlbvh_cl.io.mitsuba import read_xml
from hlbvh_cl.io.scenefile import SceneFileError, load
from hlbvh_cl.render.materials import check_material
import places
from agreement import assert_blocks_agree, assert_falls_as_one_over_spp, relmse

mi = pytest.importorskip("mitsuba")

CORNELL = places.SCENES / "cornell_box.xml"


@pytest.fixture(autouse=True)
def scalar_variant():
    mi.set_variant("scalar_rgb")


def scene_xml(body: str, width=40, height=24, fov=50.0, axis="x", to_world=None) -> str:
    to_world = to_world or '<lookat origin="1, 2, 5" target="0, 0.5, 0" up="0, 1, 0"/>'
    return f"""<scene version="3.0.0">
  <sensor type="perspective">
    <float name="fov" value="{fov}"/>
    <string name="fov_axis" value="{axis}"/>
    <transform name="to_world">{to_world}</transform>
    <film type="hdrfilm">
      <integer name="width" value="{width}"/>
      <integer name="height" value="{height}"/>
    </film>
  </sensor>
  {body}
</scene>"""


CUBE = '<shape type="cube"/>'


@pytest.mark.parametrize("axis", ["x", "y", "diagonal", "smaller", "larger", "no fov", "28mm"])
@pytest.mark.parametrize("size", [(40, 24), (24, 40)])
def test_the_camera_sends_mitsuba_s_rays(tmp_path, axis, size):
    """Through each pixel centre, our camera's ray has the direction of
    Mitsuba's sensor ray, for every fov_axis and either orientation, with a
    look_at turned further by a rotation; and for a sensor without a fov,
    whose lens is then a focal length, 50mm unless given."""
    path = tmp_path / "scene.xml"
    text = scene_xml(CUBE, *size, axis=axis, to_world=(
        '<lookat origin="1, 2, 5" target="0, 0.5, 0" up="0, 1, 0"/>'
        '<rotate y="1" angle="20"/>'))
    if axis in ("no fov", "28mm"):
        lens = f'<string name="focal_length" value="{axis}"/>' if axis == "28mm" else ""
        text = text.replace('<float name="fov" value="50.0"/>', lens, 1).replace(
            f'<string name="fov_axis" value="{axis}"/>', "", 1)
        assert "fov" not in text.replace("focal", "")
    path.write_text(text)
    width, height = size
    described = read_xml(path)
    origins, ours = described.camera.rays(width, height)
    ours = ours / np.linalg.norm(ours, axis=1, keepdims=True)
    sensor = mi.load_file(str(path)).sensors()[0]
    theirs = []
    for y in range(height):
        for x in range(width):
            ray, _ = sensor.sample_ray(0.0, 0.0, [(x + 0.5) / width, (y + 0.5) / height],
                                       [0.5, 0.5])
            theirs.append(np.array(ray.d))
    np.testing.assert_allclose(ours, np.array(theirs), atol=2e-5)
    # Mitsuba starts its rays at the near clip: our eye lies on its ray, behind
    behind = origins[-1] - np.array(ray.o)
    assert np.linalg.norm(np.cross(behind, np.array(ray.d))) < 1e-5 and behind @ ray.d < 0


@pytest.mark.parametrize("axis", ["x", "y", "diagonal", "smaller", "larger"])
def test_a_render_at_another_size_keeps_the_fov_along_the_sensor_s_axis(tmp_path, suite_device,
                                                                       axis):
    """A file's 40x24 film rendered at 24x40 (the CLI's --width, --height):
    LoadedScene.camera_at sends Mitsuba's rays for a 24x40 film with the
    same fov and fov_axis, where the file's camera (its vertical fov) would
    not; at the file's own size it is the file's camera."""
    path = tmp_path / "scene.xml"
    path.write_text(scene_xml(CUBE, 40, 24, axis=axis))
    loaded = load(path, suite_device)
    assert loaded.camera_at(40, 24) == loaded.camera and loaded.camera_at(20, 12) == loaded.camera
    other = tmp_path / "other.xml"
    other.write_text(scene_xml(CUBE, 24, 40, axis=axis))
    sensor = mi.load_file(str(other)).sensors()[0]
    _, ours = loaded.camera_at(24, 40).rays(24, 40)
    ours = ours / np.linalg.norm(ours, axis=1, keepdims=True)
    theirs = np.array([np.array(sensor.sample_ray(0.0, 0.0, [(x + 0.5) / 24, (y + 0.5) / 40],
                                                  [0.5, 0.5])[0].d)
                       for y in range(40) for x in range(24)])
    np.testing.assert_allclose(ours, theirs, atol=2e-5)
    if axis != "y":  # a vertical fov holds under "y" alone
        assert not np.allclose(loaded.camera.rays(24, 40)[1][0] / np.linalg.norm(
            loaded.camera.rays(24, 40)[1][0]), theirs[0], atol=1e-3)


@pytest.mark.parametrize("near, far", [(None, None), (4.6, None), (None, 5.0), (4.8, 5.6)])
def test_the_clip_planes_cut_what_mitsuba_s_cut(tmp_path, suite_device, near, far):
    """With near_clip and far_clip (or Mitsuba's defaults), each pixel's
    camera ray hits a cube exactly where Mitsuba's sensor ray does: the
    planes cut away the near faces, the far ones, or both."""
    clips = "".join(f'<float name="{name}" value="{value}"/>'
                    for name, value in (("near_clip", near), ("far_clip", far)) if value)
    path = tmp_path / "scene.xml"
    path.write_text(scene_xml(CUBE).replace("<film", clips + "<film"))
    loaded = load(path, suite_device.id)
    depth = loaded.renderer().render(loaded.camera, 40, 24, shading="depth", hdr=True)[..., 0]
    scene = mi.load_file(str(path))
    sensor = scene.sensors()[0]
    theirs = np.array([[scene.ray_intersect(sensor.sample_ray(
        0.0, 0.0, [(x + 0.5) / 40, (y + 0.5) / 24], [0.5, 0.5])[0]).is_valid()
        for x in range(40)] for y in range(24)])
    assert 0 < theirs.sum() < theirs.size
    np.testing.assert_array_equal(depth > 0, theirs)


def test_shapes_land_where_mitsuba_puts_them(tmp_path):
    """Every transform step (translate, rotate, scale, matrix) in Mitsuba's
    order, a sphere by centre and radius, and a rectangle: the same boxes
    as Mitsuba's shapes."""
    body = """
  <shape type="cube">
    <transform name="to_world">
      <scale x="0.5" y="1" z="2"/><rotate x="0.6" y="0.8" angle="30"/><translate value="1 -2 3"/>
      <matrix value="1 0 0 0.5  0 0 -1 0  0 1 0 0  0 0 0 1"/>
    </transform>
  </shape>
  <shape type="sphere"><point name="center" x="-1" y="0.5" z="2"/><float name="radius"
      value="0.7"/></shape>
  <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/>
      <scale value="3"/></transform></shape>"""
    path = tmp_path / "scene.xml"
    path.write_text(scene_xml(body))
    described = read_xml(path)
    theirs = [shape.bbox() for shape in mi.load_file(str(path)).shapes()]
    assert len(theirs) == len(described.meshes) == 3
    for entry in described.meshes:
        lo, hi = entry.mesh.bounds
        # Mitsuba lists its shapes in an order of its own: the nearest box
        box = min(theirs, key=lambda b: np.abs(np.array(b.min) - lo).sum()
                  + np.abs(np.array(b.max) - hi).sum())
        # the icosphere's vertices lie on Mitsuba's analytic sphere: its box
        # is within the sphere's by the mesh's sag
        tolerance = 0.01 if entry.mesh.name == "sphere" else 1e-5
        np.testing.assert_allclose(lo, np.array(box.min), atol=tolerance)
        np.testing.assert_allclose(hi, np.array(box.max), atol=tolerance)


def test_the_cornell_box_renders_as_in_mitsuba(suite_device):
    """scenes/cornell_box.xml (diffuse walls, a box, a glass ball, an area
    light; max depth 6, Mitsuba's Gaussian filter by default) at 32 x 32
    and 16 spp through both loaders and renderers: every 8 x 8 block's mean
    within 5 combined standard errors over 4 independent seeds each."""
    seeds, size, spp = 4, 32, 16
    overrides = {"res": size, "spp": spp}
    scene = mi.load_file(str(CORNELL), **overrides)
    theirs = np.stack([np.asarray(mi.render(scene, seed=s))[..., :3] for s in range(seeds)])
    loaded = load(CORNELL, suite_device.id, defaults=overrides)
    assert loaded.options == {"shading": "path", "spp": spp, "max_depth": 6, "rr_depth": 5,
                              "rfilter": "gaussian"}
    renderer = loaded.renderer()
    ours = np.stack([renderer.render(loaded.camera, loaded.width, loaded.height, hdr=True,
                                     seed=s + 1, **loaded.options) for s in range(seeds)])
    assert ours.shape == theirs.shape == (seeds, size, size, 3)
    # the glass ball's caustics make heavy-tailed noise: the means agree to a few percent
    assert abs(ours.mean() - theirs.mean()) < 0.05 * theirs.mean()
    assert_blocks_agree(theirs, ours, 8)


def test_the_cornell_box_s_relmse_against_mitsuba_falls_as_one_over_spp(tmp_path,
                                                                       suite_device):
    """Issue 55's convergence check on its XML file: scenes/cornell_box.xml
    at 32 x 32 against Mitsuba 3's render of the same file at 4,096 spp.
    Over 64 to 1,024 spp (4 seeds each) the relMSE falls as 1 / spp once the
    reference's own share is counted: no bias levels it off at this size
    and these counts (the ball is an analytic sphere in both).  From fewer
    spp the
    glass ball's heavy-tailed caustics are seldom met by a few seeds.  With
    a box filter: the scalar variants tabulate the Gaussian in 31 steps
    (rfilter.h's eval_discretized), which widens it (a sharp edge's first
    pixel 0.166 where the Gaussian gives 0.159, as the JIT variants and this
    renderer do), and the light's edges would differ by a few percent."""
    text = CORNELL.read_text()
    assert '<rfilter type="gaussian"/>' in text
    path = scene_of(tmp_path, text.replace('<rfilter type="gaussian"/>', '<rfilter type="box"/>'))
    reference_spp, size = 4096, 32
    reference = np.asarray(mi.render(mi.load_file(str(path), res=size, spp=reference_spp),
                                     seed=99))[..., :3]
    loaded = load(path, suite_device.id, defaults={"res": size})
    assert loaded.options["rfilter"] == "box"
    renderer = loaded.renderer()
    counts = np.array([64, 256, 1024])
    errors = [np.mean([relmse(renderer.render(loaded.camera, size, size, hdr=True,
                                              **{**loaded.options, "spp": int(n), "seed": s}),
                              reference) for s in range(1, 5)]) for n in counts]
    assert_falls_as_one_over_spp(errors, counts, reference_spp)


def test_the_materials_scene_renders_as_in_mitsuba(tmp_path, suite_device):
    """scenes/materials.toml (2.9M triangles: glass, rough gold, rough
    plastic and diffuse under an area light and a sky), written as XML
    (hlbvh_cl.io.to_mitsuba) and read by both, at 48 x 36, 16 spp, max depth
    8: every 12 x 12 block within 5 combined standard errors over 4 seeds."""
    from hlbvh_cl.io.to_mitsuba import write_xml
    seeds, overrides = 4, {"res_x": 48, "res_y": 36, "spp": 16}
    path = write_xml(places.SCENES / "materials.toml", tmp_path, max_depth=8)
    scene = mi.load_file(str(path), **overrides)
    theirs = np.stack([np.asarray(mi.render(scene, seed=s))[..., :3] for s in range(seeds)])
    loaded = load(path, suite_device.id, defaults=overrides)
    renderer = loaded.renderer()
    ours = np.stack([renderer.render(loaded.camera, loaded.width, loaded.height, hdr=True,
                                     seed=s + 1, **loaded.options) for s in range(seeds)])
    assert ours.shape == theirs.shape == (seeds, 36, 48, 3)
    assert abs(ours.mean() - theirs.mean()) < 0.05 * theirs.mean()
    assert_blocks_agree(theirs, ours, block=12)


def test_spheres_under_a_sphere_light_render_as_in_mitsuba(tmp_path, suite_device):
    """Analytic spheres on both sides (glass, rough metal, diffuse) on a
    diffuse ground, lit by an emitting sphere (both renderers sample the
    cone it subtends) and a dim sky: at 16 spp every 8 x 8 block agrees
    within 5 combined standard errors over 4 seeds each."""
    seeds, spp = 4, 16
    body = """
  <integrator type="path"><integer name="max_depth" value="6"/></integrator>
  <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/>
    <scale value="4"/></transform><bsdf type="diffuse"/></shape>
  <shape type="sphere"><point name="center" x="-0.8" y="0.5" z="0"/>
    <float name="radius" value="0.5"/><bsdf type="dielectric"/></shape>
  <shape type="sphere"><point name="center" x="0.6" y="0.4" z="0.3"/>
    <float name="radius" value="0.4"/><bsdf type="roughconductor">
    <float name="alpha" value="0.2"/></bsdf></shape>
  <shape type="sphere"><point name="center" x="0.2" y="0.25" z="-0.9"/>
    <float name="radius" value="0.25"/><bsdf type="diffuse"/></shape>
  <shape type="sphere"><point name="center" x="0.5" y="2.2" z="0.5"/>
    <float name="radius" value="0.3"/>
    <emitter type="area"><rgb name="radiance" value="8"/></emitter></shape>
  <emitter type="constant"><rgb name="radiance" value="0.1"/></emitter>"""
    path = scene_of(tmp_path, scene_xml(body, width=32, height=24).replace(
        "</film>", '<rfilter type="box"/></film><sampler type="independent">'
        f'<integer name="sample_count" value="{spp}"/></sampler>'))
    theirs = np.stack([np.asarray(mi.render(mi.load_file(str(path)), seed=s))[..., :3]
                       for s in range(seeds)])
    loaded = load(path, suite_device.id)
    assert len(loaded.scene.spheres) == 4 and len(loaded.scene.meshes) == 1
    renderer = loaded.renderer()
    ours = np.stack([renderer.render(loaded.camera, loaded.width, loaded.height, hdr=True,
                                     seed=s + 1, **loaded.options) for s in range(seeds)])
    assert ours.shape == theirs.shape == (seeds, 24, 32, 3)
    assert abs(ours.mean() - theirs.mean()) < 0.05 * theirs.mean()
    assert_blocks_agree(theirs, ours, 8)


def sun_and_sky(height=16, width=32) -> np.ndarray:
    """A small synthetic sky: a blue-white gradient over a dark ground half,
    and a bright sun 2 x 2 pixels wide."""
    v = (np.arange(height) + 0.5) / height
    image = np.empty((height, width, 3), np.float32)
    image[:] = (np.where(v < 0.5, 1 - v, 0.1)[:, None] * [0.6, 0.8, 1.2])[:, None]
    image[:, :, 0] *= 1 + 0.5 * np.sin(np.linspace(0, 2 * np.pi, width))  # uneven in phi
    image[3:5, 9:11] = [150.0, 130.0, 100.0]
    return image


@pytest.mark.parametrize("rotated", [False, True], ids=["identity", "rotated"])
def test_an_environment_map_lights_a_scene_as_in_mitsuba(rotated, tmp_path, suite_device):
    """A diffuse and a mirror ball on a diffuse ground, lit only by an
    envmap with a sun (a temporary EXR, with and without a to_world
    rotation), rendered by both from one XML file: every 6 x 6 block's mean
    within 5 combined standard errors over 4 independent seeds each, plus
    2% of its level for the balls' facets."""
    import trimesh
    from hlbvh_cl.io.exr import write_exr
    seeds, width, height, spp = 4, 36, 24, 32
    (tmp_path / "maps").mkdir()
    write_exr(tmp_path / "maps" / "sky.exr", sun_and_sky())
    for name, centre in (("diffuse", (-0.6, 0.5, 0.0)), ("mirror", (0.6, 0.5, 0.2))):
        ball = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
        ball.apply_translation(centre)
        ball.export(tmp_path / f"{name}.ply")
    turn = '<rotate y="1" angle="120"/><rotate x="1" angle="20"/>' if rotated else ""
    body = f"""
  <integrator type="path"><integer name="max_depth" value="5"/></integrator>
  <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/>
    <scale value="3"/></transform><bsdf type="diffuse"><rgb name="reflectance"
    value="0.5, 0.45, 0.4"/></bsdf></shape>
  <shape type="ply"><string name="filename" value="diffuse.ply"/>
    <boolean name="face_normals" value="true"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.8, 0.3, 0.2"/></bsdf></shape>
  <shape type="ply"><string name="filename" value="mirror.ply"/>
    <boolean name="face_normals" value="true"/><bsdf type="conductor"/></shape>
  <emitter type="envmap"><string name="filename" value="maps/sky.exr"/>
    <float name="scale" value="0.8"/><transform name="to_world">{turn}</transform></emitter>"""
    path = tmp_path / "scene.xml"
    path.write_text(scene_xml(body, width, height, fov=45).replace(
        "<film type=\"hdrfilm\">", "<film type=\"hdrfilm\"><rfilter type=\"box\"/>"))
    scene = mi.load_file(str(path))
    theirs = np.stack([np.asarray(mi.render(scene, spp=spp, seed=s))[..., :3]
                       for s in range(seeds)])
    loaded = load(path, suite_device.id)
    assert loaded.emitters[0]["filename"] == str(tmp_path / "maps" / "sky.exr")
    renderer = loaded.renderer()
    options = {**loaded.options, "spp": spp}
    ours = np.stack([renderer.render(loaded.camera, width, height, hdr=True, seed=s + 1,
                                     **options) for s in range(seeds)])
    assert ours.shape == theirs.shape == (seeds, height, width, 3)
    # the image means, within 5 combined standard errors (the sun's
    # reflections make heavy-tailed noise) and 1%
    a, b = theirs.mean((1, 2, 3)), ours.mean((1, 2, 3))
    assert abs(a.mean() - b.mean()) < 5 * np.sqrt((a.var(ddof=1) + b.var(ddof=1)) / seeds) \
        + 0.01 * a.mean(), (a.mean(), b.mean())
    assert_blocks_agree(theirs, ours, 6)


@pytest.mark.parametrize("body, words", [
    ('<shape type="cylinder"/>', ":11: <shape type=\"cylinder\">: shape type 'cylinder' is "
                                 "not read"),
    ('<shape type="cube"><bsdf type="principled"/></shape>',
     ":11: <bsdf type=\"principled\">: BSDF type 'principled' is not read"),
    ('<shape type="cube"><bsdf type="roughplastic"><string name="distribution" value="phong"/>'
     '</bsdf></shape>', "['distribution'] must be one of ('ggx', 'beckmann'), got 'phong'"),
    ('<shape type="cube"><bsdf type="roughdielectric"><float name="alpha" value="-0.2"/>'
     '</bsdf></shape>', "['alpha'] must be a finite number >= 0.0001 and <= 1, got -0.2"),
    ('<shape type="cube"><bsdf type="plastic"><float name="alpha" value="0.2"/>'
     '</bsdf></shape>', "plastic takes ('diffuse_reflectance', "),
    ('<shape type="ply"><string name="filename" value="m.ply"/></shape>',
     "mesh file not found"),
    ('<shape type="cube"><float name="radius" value="1"/></shape>',
     "cube takes ('to_world', 'face_normals', 'flip_normals'), not 'radius'"),
    ('<emitter type="spot"/>', "emitter type 'spot' is not read at the top"),
    ('<emitter type="envmap"/>', ":11: <emitter type=\"envmap\">: needs its filename"),
    ('<emitter type="envmap"><string name="filename" value="nowhere.exr"/></emitter>',
     "cannot read the environment map"),
    ('<emitter type="envmap"><string name="filename" value="sky.exr"/>'
     '<float name="gamma" value="2.2"/></emitter>',
     "envmap takes ('filename', 'scale', 'to_world'), not 'gamma'"),
    ('<emitter type="envmap"><string name="filename" value="sky.exr"/><transform '
     'name="to_world"><scale value="2"/></transform></emitter>', "must be a rotation"),
    ('<emitter type="constant"><rgb name="radiance" value="1"/></emitter><emitter '
     'type="envmap"><string name="filename" value="sky.exr"/></emitter>',
     "a second environment (envmap) besides"),
    ('<shape type="cube"><bsdf type="diffuse"><rgb name="reflectance" value="2, 0, 0"/>'
     '</bsdf></shape>', "['reflectance'][0] must be a finite number >= 0 and <= 1, got 2.0"),
    ('<shape type="cube"><ref id="nowhere"/></shape>', "refers to no <bsdf id=\"nowhere\">"),
    ('<integrator type="volpath"/>', "only the path integrator is read"),
    ('<medium type="homogeneous"/>', "is not an element this reader takes"),
    ('<shape type="sphere"><float name="radius" value="$missing"/></shape>',
     "$missing has no <default name=\"missing\">"),
    ('<shape type="sphere"><string name="radius" value="big"/></shape>',
     "<string name=\"radius\">: radius takes <float>, <integer>, not <string>"),
    ('<shape type="sphere"><float name="radius" value="0"/></shape>',
     "its to_world (with its radius) is singular"),
    ('<shape type="cube"><transform name="to_world"><scale value="0"/></transform></shape>',
     "its to_world (with its radius) is singular"),
    ('<shape type="sphere"><point name="center" x="abc" y="0" z="0"/></shape>',
     "<point name=\"center\">: expected a number for x, got 'abc'"),
    ('<shape type="cube"><float name="to_world" value="1"/></shape>',
     "to_world takes <transform>, not <float>"),
    ('<shape type="cube"><transform name="to_world"><matrix value="1 0 0 0 0 1 0 0 0 0 1 0 '
     '0 0 1 1"/></transform></shape>', "the last row must be 0 0 0 1 (an affine map), got "
                                       "0 0 1 1"),
    ('<integrator type="path"><float name="max_depth" value="8.5"/></integrator>',
     "max_depth takes <integer>, not <float>"),
    ('<emitter type="point"><float name="to_world" value="1"/><rgb name="intensity" '
     'value="1"/></emitter>', "to_world takes <transform>, not <float>"),
])
def test_an_element_outside_the_subset_names_itself_and_its_line(tmp_path, body, words):
    from hlbvh_cl.io.exr import write_exr
    write_exr(tmp_path / "sky.exr", np.ones((4, 8, 3), np.float32))
    path = tmp_path / "scene.xml"
    path.write_text(scene_xml(body))
    with pytest.raises(SceneFileError) as error:
        read_xml(path)
    assert str(error.value).startswith(str(path)) and words in str(error.value)


def test_plastics_and_rough_glass_read_as_mitsuba_names_them(tmp_path):
    """Each new BSDF's parameters arrive as the materials.py spec of the
    same names, named indices looked up, and twosided wraps a plastic;
    Mitsuba 3 loads the same file."""
    body = """
  <bsdf type="twosided" id="coated"><bsdf type="roughplastic">
    <string name="distribution" value="ggx"/><float name="alpha" value="0.2"/>
    <rgb name="diffuse_reflectance" value="0.1, 0.2, 0.3"/>
    <string name="int_ior" value="polypropylene"/><boolean name="nonlinear" value="true"/>
  </bsdf></bsdf>
  <shape type="cube"><ref id="coated"/></shape>
  <shape type="sphere"><bsdf type="plastic"><float name="specular_reflectance" value="0.5"/>
  </bsdf></shape>
  <shape type="sphere"><bsdf type="roughdielectric"><float name="alpha" value="0.3"/>
    <string name="ext_ior" value="water"/><rgb name="specular_transmittance" value="1, 0.9, 0.8"/>
  </bsdf></shape>"""
    path = tmp_path / "scene.xml"
    path.write_text(scene_xml(body))
    mi.load_file(str(path))
    materials = read_xml(path).materials()
    assert materials == [
        {"type": "twosided", "bsdf": {"type": "roughplastic", "distribution": "ggx",
                                      "alpha": 0.2, "diffuse_reflectance": [0.1, 0.2, 0.3],
                                      "int_ior": 1.49, "nonlinear": True}},
        {"type": "plastic", "specular_reflectance": 0.5},
        {"type": "roughdielectric", "alpha": 0.3, "ext_ior": 1.333,
         "specular_transmittance": [1.0, 0.9, 0.8]}]


def test_a_named_metal_reads_as_mitsuba_names_it(tmp_path):
    """<string name="material" value="Au"/> in a roughconductor arrives as
    the spec's "material", whose eta and k are the RGB values Mitsuba 3
    loads from the same file; a name Mitsuba does not know, or a name
    beside eta, is an error naming the line, as Mitsuba refuses both."""
    body = """
  <shape type="sphere"><bsdf type="roughconductor" id="gold">
    <string name="material" value="Au"/><float name="alpha" value="0.2"/>
  </bsdf></shape>"""
    path = tmp_path / "scene.xml"
    path.write_text(scene_xml(body))
    theirs = mi.traverse(mi.load_file(str(path)).shapes()[0].bsdf())
    materials = read_xml(path).materials()
    assert materials == [{"type": "roughconductor", "material": "Au", "alpha": 0.2}]
    record = check_material("gold", materials[0])
    for key in ("eta", "k"):
        assert record[key] == pytest.approx(np.ravel(theirs[f"{key}.value"]), rel=1e-6)
    for inside, words in (('<string name="material" value="Gold"/>',
                           "['material'] = 'Gold' is not a metal Mitsuba names"),
                          ('<string name="material" value="Au"/><float name="eta" value="1"/>',
                           "give either the material 'Au' or eta and k, not both")):
        path.write_text(scene_xml(f'<shape type="sphere"><bsdf type="roughconductor">{inside}'
                                  '</bsdf></shape>'))
        with pytest.raises(RuntimeError):
            mi.load_file(str(path))
        with pytest.raises(SceneFileError, match=r"scene.xml:11: <bsdf type=\"roughconductor\">"
                                                 ) as error:
            read_xml(path)
        assert words in str(error.value)


def test_the_cli_renders_an_xml_scene_with_its_own_options(tmp_path, capsys, suite_device):
    from hlbvh_cl.cli import main
    from hlbvh_cl.io.exr import read_exr
    out = tmp_path / "cbox.exr"
    assert main(["render", str(CORNELL), "-o", str(out), "--width", "24", "--height", "24",
                 "--spp", "2", "--device", suite_device.id]) == 0
    assert "24x24, path, 2 spp" in capsys.readouterr().out
    image = read_exr(out)
    assert image.shape == (24, 24, 3) and 0.05 < image.mean() < 1.0
    assert isinstance(hlbvh_cl.Renderer, type)
    # the file's sampler seed is the CLI render's: a seed of 7 written in, the
    # image is the API's render at seed 7 (not seed 0's)
    seeded = tmp_path / "cbox7.xml"
    seeded.write_text(CORNELL.read_text().replace(
        '<sampler type="independent">', '<sampler type="independent">'
        '<integer name="seed" value="7"/>', 1))
    assert 'name="seed"' in seeded.read_text()
    out7 = tmp_path / "cbox7.exr"
    assert main(["render", str(seeded), "-o", str(out7), "--width", "24", "--height", "24",
                 "--spp", "2", "--device", suite_device.id]) == 0
    loaded = load(seeded, suite_device)
    options = {**loaded.options, "spp": 2}
    api = loaded.renderer().render(loaded.camera_at(24, 24), 24, 24, hdr=True, aovs=True,
                                   **options)
    cli = read_exr(out7)
    np.testing.assert_allclose(cli, api.image, rtol=1e-6, atol=1e-7)
    assert not np.allclose(cli, image)


#: A sensor's fov and fov_axis lines in scene_xml.
LENS = '<float name="fov" value="50.0"/>\n    <string name="fov_axis" value="x"/>'


@pytest.mark.parametrize("change, words", [
    (('name="width" value="40"', 'name="width" value="abc"'), "expected an integer, got 'abc'"),
    (('<integer name="width" value="40"/>', '<float name="width" value="8.7"/>'),
     "width takes <integer>, not <float>"),
    (('name="height" value="24"', 'name="height" value="0"'),
     "width and height must be 1..16384, got 40 x 0"),
    (('name="width" value="40"', 'name="width" value="20000"'),
     "width and height must be 1..16384, got 20000 x 24"),
    (('name="width" value="40"', 'name="width" value="1_6"'), "expected an integer, got '1_6'"),
    (('name="width" value="40"', 'name="width" value="-8"'),
     "width and height must be 1..16384, got -8 x 24"),
    (('<float name="fov" value="50.0"/>', '<string name="fov" value="45"/>'),
     "fov takes <float>, <integer>, not <string>"),
    (('name="fov" value="50.0"', 'name="fov" value="180"'),
     "fov must be between 0 and 180 degrees, got 180"),
    ((LENS, '<string name="focal_length" value="-5mm"/>'),
     "focal_length must be <x>mm with x > 0, got '-5mm'"),
    ((LENS, '<string name="focal_length" value="wide"/>'),
     "focal_length must be <x>mm with x > 0, got 'wide'"),
    ((LENS, '<string name="focal_length" value="5_0mm"/>'),
     "focal_length must be <x>mm with x > 0, got '5_0mm'"),
    ((LENS, '<string name="focal_length" value="1e-300mm"/>'),
     "focal_length must be <x>mm with x > 0, got '1e-300mm'"),
    (('<float name="fov" value="50.0"/>', ''),
     "fov_axis applies to a fov; without one the sensor's focal_length gives the field of "
     "view along the diagonal"),
    (('<float name="fov" value="50.0"/>', '<float name="fov" value="50.0"/><string '
      'name="focal_length" value="35mm"/>'), "give either its fov or its focal_length, not both"),
    (('target="0, 0.5, 0"', 'target="1, 2, 5"'), "its target is its origin"),
    (('up="0, 1, 0"', 'up="-1, -1.5, -5"'), "its up is parallel to the direction it looks in"),
    (('<film', '<float name="near_clip" value="2"/><float name="far_clip" value="1"/><film'),
     "needs 0 < near_clip < far_clip, got 2 and 1"),
    (('<film', '<float name="near_clip" value="0"/><film'),
     "needs 0 < near_clip < far_clip, got 0 and 10000"),
    (('</transform>', '<scale value="2"/></transform>'), "its to_world scales"),
    (('<sensor type="perspective">\n    <float name="fov" value="50.0"/>',
      '<default name="fov" value="abc"/><sensor type="perspective">'
      '<float name="fov" value="$fov"/>'),
     "<float name=\"fov\">: expected a number, got '$fov' (= 'abc')"),
    (('origin="1, 2, 5"', 'origin="1, 2, 1e300"'),
     "its origin and target must lie within 1e+150 of 0, got '1, 2, 1e300' and '0, 0.5, 0'"),
])
def test_a_bad_sensor_names_its_element_and_line(tmp_path, change, words):
    """A sensor value of the wrong element, out of range, or a camera that
    cannot be: an error naming the element and its line, not Python's."""
    text = scene_xml(CUBE)
    assert change[0] in text
    path = tmp_path / "scene.xml"
    path.write_text(text.replace(change[0], change[1], 1))
    with pytest.raises(SceneFileError) as error:
        read_xml(path)
    assert str(error.value).startswith(f"{path}:") and words in str(error.value), error.value


def test_the_sampler_s_seed_is_the_render_s(tmp_path, suite_device):
    """<sampler>'s seed reaches the render options (which the CLI renders with):
    seeds 0 and 7 give two images, seed 7 the image Renderer.render(seed=7)
    gives."""
    body = (CUBE + '<emitter type="constant"><rgb name="radiance" value="1"/></emitter>'
            '<integrator type="path">'
            '<integer name="max_depth" value="3"/></integrator>')
    images = []
    for seed in (0, 7):
        sampler = (f'</film><sampler type="independent"><integer name="sample_count" '
                   f'value="2"/><integer name="seed" value="{seed}"/></sampler>')
        path = tmp_path / f"seed{seed}.xml"
        path.write_text(scene_xml(body).replace("</film>", sampler, 1))
        loaded = load(path, suite_device)
        assert loaded.options["seed"] == seed
        renderer = loaded.renderer()
        images.append(renderer.render(loaded.camera, 40, 24, hdr=True, **loaded.options))
    assert not np.array_equal(images[0], images[1])
    options = {**loaded.options, "seed": 7}
    np.testing.assert_array_equal(renderer.render(loaded.camera, 40, 24, hdr=True, **options),
                                  images[1])
    # Mitsuba's seeds are any size; a render's 16 bits: 65543 is seed 7
    path.write_text(path.read_text().replace('name="seed" value="7"', 'name="seed" value="65543"'))
    assert load(path, suite_device).options["seed"] == 7


def test_a_bad_number_in_a_transform_names_its_step(tmp_path):
    path = tmp_path / "scene.xml"
    path.write_text(scene_xml('<shape type="cube"><transform name="to_world">'
                              '<translate x="one"/></transform></shape>'))
    with pytest.raises(SceneFileError,
                       match=r"scene.xml:11: <translate>: expected a number for x, got 'one'"):
        read_xml(path)


@pytest.mark.parametrize("mirror", [False, True], ids=["plain", "mirrored"])
@pytest.mark.parametrize("file_normals", [False, True])
def test_mesh_normals_are_mitsuba_s_after_to_world(tmp_path, file_normals, mirror):
    """A PLY with or without vertex normals under a shearing, non-uniform
    to_world, and under one that also mirrors: the loaded mesh's winding
    and shading normals point as Mitsuba's own (the file's by the inverse
    transpose, or computed after the transform: under a mirror Mitsuba keeps
    the file's winding, which then faces inward, and so do the normals it
    computes), and face_normals = true turns them off."""
    import trimesh
    s = trimesh.creation.icosphere(subdivisions=1)
    rng = np.random.default_rng(5)
    vertices = s.vertices + rng.normal(0.0, 0.05, s.vertices.shape)
    given = vertices + rng.normal(0.0, 0.2, vertices.shape) if file_normals else None
    (tmp_path / "m.ply").write_bytes(trimesh.exchange.ply.export_ply(
        trimesh.Trimesh(vertices, s.faces, vertex_normals=given, process=False),
        vertex_normal=file_normals))
    shape = ('<shape type="ply"><string name="filename" value="m.ply"/>{}'
             '<transform name="to_world"><matrix value="%s 0.4 0 0.2  0 0.8 0.3 0  '
             '0.1 0 1.2 -0.5  0 0 0 1"/></transform></shape>') % ("-1.5" if mirror else "1.5")
    path = tmp_path / "scene.xml"
    path.write_text(scene_xml(shape.format("")))
    ours = read_xml(path).meshes[0].mesh
    assert ours.has_file_normals == file_normals and not ours.face_normals
    theirs_shape = mi.load_file(str(path)).shapes()[0]
    theirs = np.array(mi.traverse(theirs_shape)["vertex_normals"]).reshape(-1, 3)
    np.testing.assert_allclose(np.array(mi.traverse(theirs_shape)["vertex_positions"])
                               .reshape(-1, 3), ours.vertices, atol=1e-5)
    np.testing.assert_array_equal(np.array(mi.traverse(theirs_shape)["faces"]).reshape(-1, 3),
                                  ours.faces)
    # as they are, not normalised here: Mitsuba normalises a file's normals
    # after to_world (they had kept the file's and the map's lengths, which
    # weighed the interpolation: shading normals 17-22 degrees off)
    np.testing.assert_allclose(ours.normals, theirs, atol=2e-5)
    path.write_text(scene_xml(shape.format('<boolean name="face_normals" value="true"/>')))
    assert read_xml(path).meshes[0].mesh.face_normals


HARD_CUBE_OBJ = ("".join(f"v {x} {y} {z}\n" for x in (-1, 1) for y in (-1, 1) for z in (-1, 1))
                 + "vn -1 0 0\nvn 1 0 0\nvn 0 -1 0\nvn 0 1 0\nvn 0 0 -1\nvn 0 0 1\n"
                 + "".join(f"f {a}//{n} {b}//{n} {c}//{n} {d}//{n}\n" for a, b, c, d, n in
                           ((1, 2, 4, 3, 1), (5, 7, 8, 6, 2), (1, 5, 6, 2, 3), (3, 4, 8, 7, 4),
                            (1, 3, 7, 5, 5), (2, 6, 8, 4, 6))))
# a ridge whose two slopes meet with a UV seam along it (vt only: normals computed)
SEAM_OBJ = ("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0.5\nv 2 1 0.5\n"
            "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvt 0.5 0.5\n"
            "f 1/1 2/2 3/3 4/4\nf 2/5 5/2 6/3 3/5\n")
# smooth: normals indexed apart from the vertices, but one per vertex
SMOOTH_OBJ = ("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0.2\n"
              "vn 0 0.1 1\nvn 0.1 0 1\nvn 0 0 1\nvn 0.2 0.2 1\n"
              "f 1//3 2//1 3//2\nf 2//1 4//4 3//2\n")


@pytest.mark.parametrize("text", [HARD_CUBE_OBJ, SEAM_OBJ, SMOOTH_OBJ],
                         ids=["hard edges", "uv seam", "smooth"])
def test_an_obj_s_corners_shade_as_in_mitsuba(tmp_path, text):
    """An OBJ's faces index normals and texture coordinates apart from the
    vertices.  Mitsuba makes a vertex of each distinct (position, texture
    coordinate, normal) a corner names, so a hard edge keeps each face's
    normal and a UV seam computes its normals on each side apart.  The
    loaded mesh gives every face corner Mitsuba's position and shading
    normal, and keeps the file's vertex rows first, in place; a smooth
    file, one normal per vertex, keeps exactly its rows."""
    path = tmp_path / "m.obj"
    path.write_text(text)
    ours = hlbvh_cl.Mesh.load(path)
    theirs = mi.traverse(mi.load_dict({"type": "obj", "filename": str(path)}))
    their_points = np.array(theirs["vertex_positions"]).reshape(-1, 3)
    their_normals = np.array(theirs["vertex_normals"]).reshape(-1, 3)
    their_faces = np.array(theirs["faces"]).reshape(-1, 3)

    def corners(points, normals, faces):
        """(face centre, corner position) -> unit shading normal, every corner."""
        found = {}
        for face in faces:
            centre = tuple(np.round(points[face].mean(axis=0), 5))
            for k in face:
                normal = normals[k] / np.linalg.norm(normals[k])
                found[centre, tuple(np.round(points[k], 5))] = normal
        return found

    ours_at = corners(ours.vertices, ours.normals, ours.faces)
    theirs_at = corners(their_points, their_normals, their_faces)
    assert ours_at.keys() == theirs_at.keys()
    for key, normal in theirs_at.items():
        np.testing.assert_allclose(ours_at[key], normal, atol=1e-6, err_msg=str(key))
    rows = np.float32([line.split()[1:] for line in text.splitlines() if line.startswith("v ")])
    np.testing.assert_array_equal(ours.vertices[:len(rows)], rows)
    if text is SMOOTH_OBJ:
        assert ours.vertex_count == len(rows)
    else:
        assert ours.vertex_count == len(their_points)


@pytest.mark.parametrize("bare, given", [
    ('<emitter type="point"/>', '<emitter type="point"><float name="intensity" value="1"/>'
                                '<point name="position" value="0, 0, 0"/></emitter>'),
    ('<emitter type="directional"/>', '<emitter type="directional"><float name="irradiance" '
                                      'value="1"/><vector name="direction" value="0, 0, 1"/>'
                                      '</emitter>'),
    ('<emitter type="constant"/>', '<emitter type="constant"><float name="radiance" value="1"/>'
                                   '</emitter>'),
    ('<shape type="rectangle"><emitter type="area"/></shape>',
     '<shape type="rectangle"><emitter type="area"><float name="radiance" value="1"/></emitter>'
     '</shape>'),
], ids=["point", "directional", "constant", "area"])
def test_an_emitter_s_values_left_out_are_mitsuba_s_defaults(tmp_path, bare, given):
    """Mitsuba gives an emitter without its value a value of 1 (and a point
    light without a position the origin, a directional light without a
    direction +z, its frame's z axis): such a file reads as the one that
    says them, where it was refused."""
    bare_path = scene_of(tmp_path, scene_xml(CUBE + bare))
    mi.load_file(str(bare_path))
    ours = read_xml(bare_path)
    theirs = read_xml(scene_of(tmp_path, scene_xml(CUBE + given)))
    assert ours.emitters == theirs.emitters
    assert [m.emitter for m in ours.meshes] == [m.emitter for m in theirs.meshes]
    assert ours.emitters or any(m.emitter for m in ours.meshes)
    for emitter in ours.emitters:  # each file's defaults its own, not shared lists
        for value in emitter.values():
            if isinstance(value, list):
                value[0] = 7.0
    assert read_xml(bare_path).emitters == theirs.emitters


def test_an_emitting_shape_without_a_bsdf_is_black_as_in_mitsuba(tmp_path):
    """Mitsuba gives a shape with no <bsdf> a diffuse of 0.5, and one that
    emits a black one: a lamp shows its own radiance and reflects nothing
    (it had taken 0.5 too, and lit a lamp under a point light 2.3x as
    bright as Mitsuba)."""
    body = ('<shape type="rectangle"><emitter type="area"/></shape>'
            '<shape type="cube"><transform name="to_world"><translate y="3"/></transform>'
            '</shape>')
    path = scene_of(tmp_path, scene_xml(body))
    theirs = {shape.emitter() is not None:
              float(np.ravel(mi.traverse(shape.bsdf())["reflectance.value"])[0])
              for shape in mi.load_file(str(path)).shapes()}
    ours = {entry.emitter is not None: entry.material["reflectance"]
            for entry in read_xml(path).meshes}
    assert ours == theirs == {True: 0.0, False: 0.5}


def test_forms_mitsuba_reads_are_read_as_it_reads_them(tmp_path):
    """One value for a translate's or a point's three (Mitsuba's broadcast),
    a 3 x 3 matrix (the linear part), a distribution's name in capitals,
    sample_visible (ours always sample visible normals: the same estimate)
    and face_normals on a cube and a rectangle (flat: they shade alike),
    each refused before: the same shapes, light and BSDF as Mitsuba's."""
    body = ('<shape type="cube"><boolean name="face_normals" value="true"/>'
            '<transform name="to_world"><matrix value="1 0.5 0  0 2 0  0.25 0 1"/>'
            '<translate value="2"/></transform>'
            '<bsdf type="roughconductor"><string name="distribution" value="GGX"/>'
            '<boolean name="sample_visible" value="false"/></bsdf></shape>'
            '<shape type="rectangle"><boolean name="face_normals" value="true"/>'
            '<transform name="to_world"><translate value="-3"/></transform></shape>'
            '<emitter type="point"><point name="position" value="4"/></emitter>')
    path = scene_of(tmp_path, scene_xml(body))
    theirs = mi.load_file(str(path))
    ours = read_xml(path)
    boxes = sorted((tuple(np.array(shape.bbox().min)), tuple(np.array(shape.bbox().max)))
                   for shape in theirs.shapes())
    np.testing.assert_allclose(
        sorted((tuple(entry.mesh.bounds[0]), tuple(entry.mesh.bounds[1]))
               for entry in ours.meshes), boxes, atol=1e-5)
    cube = next(entry for entry in ours.meshes if entry.mesh.triangle_count == 12)
    assert cube.material["distribution"] == "ggx" and "sample_visible" not in cube.material
    assert "distribution = ggx" in str(next(s.bsdf() for s in theirs.shapes()
                                            if "Conductor" in str(s.bsdf())))
    assert ours.emitters[0]["position"] == [4.0, 4.0, 4.0]
    assert list(np.ravel(mi.traverse(theirs.emitters()[0])["position"])) == [4.0, 4.0, 4.0]


def test_a_type_id_or_name_takes_its_default_s_value(tmp_path):
    """Mitsuba substitutes $names in every attribute, a plugin's type, an id
    and a parameter's name too: such a file reads as the one that spells
    them out, where it was refused."""
    spelled = ('<bsdf type="diffuse" id="mat"><rgb name="reflectance" value="0.2, 0.3, 0.4"/>'
               '</bsdf><shape type="cube"><ref id="mat"/></shape>')
    named = ('<default name="t" value="diffuse"/><default name="k" value="reflectance"/>'
             '<default name="i" value="mat"/><bsdf type="$t" id="$i"><rgb name="$k" '
             'value="0.2, 0.3, 0.4"/></bsdf><shape type="cube"><ref id="$i"/></shape>')
    path = scene_of(tmp_path, scene_xml(named))
    assert float(np.ravel(mi.traverse(mi.load_file(str(path)))["mat.reflectance.value"])[1]) \
        == pytest.approx(0.3)
    ours = read_xml(path)
    assert ours.meshes[0].material == read_xml(scene_of(tmp_path, scene_xml(spelled))
                                               ).meshes[0].material
    assert ours.meshes[0].material["reflectance"] == pytest.approx([0.2, 0.3, 0.4])


def scene_of(tmp_path, text: str):
    path = tmp_path / "scene.xml"
    path.write_text(text)
    return path


SPHERE = '<shape type="sphere">{}</shape>'
SHAPE_INSIDE = '<shape type="cube">{}</shape>'
DIFFUSE = '<bsdf type="diffuse"/>'
LIGHT = '<emitter type="area"><rgb name="radiance" value="1"/></emitter>'


@pytest.mark.parametrize("body, words", [
    ('<shape type="cube"><transform name="to_world"><translate X="5"/></transform></shape>',
     "<translate>: takes the attributes value, x, y, z, not 'X'"),
    ('<shape type="cube"><transform name="to_world"><translate value="1 0 0" x="5"/>'
     '</transform></shape>', "<translate>: give either its value or x, y, z, not both"),
    (SPHERE.format('<float name="radius" value="1" foo="2"/>'),
     "takes the attributes name, value, not 'foo'"),
    (SPHERE.format('<float name="radius" value="1"/><float name="radius" value="2"/>'),
     "radius is given twice in <shape type=\"sphere\">"),
    (SHAPE_INSIDE.format(DIFFUSE + DIFFUSE), "a second <bsdf> inside <shape>"),
    (SHAPE_INSIDE.format(LIGHT + LIGHT), "a second <emitter> inside <shape>"),
    ('<bsdf type="diffuse" id="a"/><bsdf type="diffuse" id="a"/>',
     "id 'a' is already the id of the element on line 11"),
    ('<integrator type="path"/><integrator type="path"/>', "a second <integrator>"),
    ('<emitter type="point"><point name="position" value="0 1 0"/><rgb name="intensity" '
     'value="1"/><transform name="to_world"><translate y="2"/></transform></emitter>',
     "give either its position or its to_world, not both"),
    ('<emitter type="directional"><vector name="direction" value="0 -1 0"/><rgb '
     'name="irradiance" value="1"/><transform name="to_world"><lookat origin="0 0 0" '
     'target="0 0 1" up="0 1 0"/></transform></emitter>',
     "give either its direction or its to_world, not both"),
    ('<integrator type="path"><integer name="max_depth" value="-2"/></integrator>',
     "max_depth must be -1 (no limit) or 1..1024, got -2"),
    ('<integrator type="path"><integer name="rr_depth" value="0"/></integrator>',
     "rr_depth must be 1..2147483647, got 0"),
    ('<integrator type="path"><integer name="rr_depth" value="2147483648"/></integrator>',
     "rr_depth must be 1..2147483647, got 2147483648"),
    (SHAPE_INSIDE.format('<ref/>'), "<ref>: needs the id of the <bsdf> it refers to"),
    (SHAPE_INSIDE.format('<bsdf type="diffuse"><point name="reflectance" value="0.5 0.5 0.5"/>'
                         '</bsdf>'), "reflectance takes <rgb>, <float>, <integer>, not <point>"),
    (SHAPE_INSIDE.format('<bsdf type="twosided"><bsdf type="dielectric"/></bsdf>'),
     '<bsdf type="twosided">[\'bsdf\'] has no back side to wrap'),
    (SPHERE.format('<float name="radius" value="0_5"/>'), "expected a number, got \'0_5\'"),
    (SHAPE_INSIDE.format('<bsdf type="dielectric"><string name="int_ior" value="glass"/>'
                         '</bsdf>'), "int_ior 'glass' is not a named index"),
    # a point or vector by coordinates takes all three (filled with 0 before)
    (SPHERE.format('<point name="center" x="1" y="2"/>'),
     '<point name="center">: needs its value, or x, y and z: z is missing'),
    (CUBE + '<emitter type="directional"><vector name="direction" x="1"/></emitter>',
     '<vector name="direction">: needs its value, or x, y and z: y is missing'),
    # numbers as Mitsuba reads them (Python's int and float took these)
    ('<integrator type="path"><integer name="max_depth" value="+16"/></integrator>',
     "expected an integer, got '+16'"),
    (SHAPE_INSIDE.format('<bsdf type="diffuse"><float name="reflectance" value="\u0660.\u0665"/>'
                         '</bsdf>'), "expected a number, got '\u0660.\u0665'"),
    # a default after its use on the same line (lines alone were compared)
    ('<shape type="cube"><bsdf type="diffuse"><float name="reflectance" value="$a"/></bsdf>'
     '</shape><default name="a" value="0.3"/>', "$a is used above its <default name=\"a\">"),
])
def test_what_mitsuba_refuses_is_refused_with_its_line(tmp_path, body, words):
    """Files Mitsuba 3 refuses to load (a mistyped attribute, a value given
    twice, two BSDFs or area lights in one shape, a duplicate id, a light
    placed twice over, depths out of range, an index of refraction it does
    not name): an error naming the element and its line here too, never
    one of the clashing values kept in silence."""
    path = scene_of(tmp_path, scene_xml(body))
    with pytest.raises(Exception):
        mi.load_file(str(path))
    with pytest.raises(SceneFileError) as error:
        read_xml(path)
    assert str(error.value).startswith(f"{path}:") and words in str(error.value), error.value


DEEP = ('<shape type="cube">' + '<bsdf type="twosided">' * 1000 + '<bsdf type="diffuse"/>'
        + '</bsdf>' * 1000 + '</shape>')


@pytest.mark.parametrize("body, to_world, words", [
    (DEEP, None, '<bsdf> is nested 65 elements deep; this reader takes 64 at most'),
    ('<shape type="cube"/>', '<lookat origin="1, 2, 5" target="0, 0.5, 0" up="0, 1e-300, 0"/>',
     "<lookat>: its up ('0, 1e-300, 0') is too short, or too near the direction it looks in"),
    ('<shape type="cube"/>', '<lookat origin="0, 0, 5" target="0, 0, 0" up="1e-320, 0, 1"/>',
     "their cross is under 1e-150 long"),
    ('<shape type="cube"/>', '<lookat origin="0, 0, 0" target="1e-320, 0, 0" up="0, 1, 0"/>',
     "<lookat>: its target lies within 1e-150 of its origin"),
])
def test_degenerate_files_are_refused_with_their_line(tmp_path, body, to_world, words):
    """Elements nested past what the reader walks (1000 twosided BSDFs had
    ended in a bare RecursionError), and a <lookat> whose up or view is too
    short to normalise (it had been called a scale or shear, with numpy's
    warnings): an error naming the file, the line and the cause."""
    path = scene_of(tmp_path, scene_xml(body, to_world=to_world))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy warning on the way
        with pytest.raises(SceneFileError) as error:
            read_xml(path)
    assert str(error.value).startswith(f"{path}:") and words in str(error.value), error.value


@pytest.mark.parametrize("version, mitsuba_loads", [("banana", False), ("2.0.0", True)])
def test_a_file_of_another_version_than_3_is_refused(tmp_path, version, mitsuba_loads):
    """Mitsuba refuses a version it cannot parse and renames an older file's
    parameters as it loads it, which this reader does not: it reads version
    3 files only, and says so on the scene's line."""
    path = scene_of(tmp_path, scene_xml(CUBE).replace('version="3.0.0"', f'version="{version}"'))
    if mitsuba_loads:
        mi.load_file(str(path))
    else:
        with pytest.raises(Exception):
            mi.load_file(str(path))
    with pytest.raises(SceneFileError, match=rf"scene.xml:1: <scene>: version '{version}': "
                                             r"this reader reads Mitsuba 3 files"):
        read_xml(path)


@pytest.mark.parametrize("kind, other", [("ply", "obj"), ("obj", "ply")])
def test_a_mesh_shape_reads_its_own_format_only(tmp_path, kind, other):
    """A ply shape naming an .obj file (or the reverse) is refused, as
    Mitsuba's parsers refuse the other format, rather than read by its
    extension."""
    import trimesh
    trimesh.creation.box().export(tmp_path / f"m.{other}")
    path = scene_of(tmp_path, scene_xml(f'<shape type="{kind}"><string name="filename" '
                                        f'value="m.{other}"/></shape>'))
    with pytest.raises(Exception):
        mi.load_file(str(path))
    with pytest.raises(SceneFileError, match=rf"{kind} shapes read \.{kind} files, got "
                                             rf"m\.{other}"):
        read_xml(path)


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian"])
def test_a_ply_of_polygons_is_refused_as_mitsuba_refuses_it(tmp_path, encoding):
    """Mitsuba's ply reads triangles alone; Mesh.load splits a quad, so the
    XML reader had rendered a file Mitsuba refuses.  A triangle PLY reads."""
    header = (f"ply\nformat {encoding} 1.0\nelement vertex 4\nproperty float x\n"
              "property float y\nproperty float z\nelement face {}\n"
              "property list uchar int vertex_indices\nend_header\n")
    corners = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    for name, faces in (("quad", [[0, 1, 2, 3]]), ("pair", [[0, 1, 2], [0, 2, 3]])):
        text = header.format(len(faces)).encode()
        if encoding == "ascii":
            text += "".join(" ".join(map(str, row)) + "\n" for row in corners).encode()
            text += "".join(f"{len(f)} " + " ".join(map(str, f)) + "\n" for f in faces).encode()
        else:
            text += corners.tobytes() + b"".join(
                np.uint8(len(f)).tobytes() + np.array(f, "<i4").tobytes() for f in faces)
        (tmp_path / f"{name}.ply").write_bytes(text)
        path = scene_of(tmp_path, scene_xml(f'<shape type="ply"><string name="filename" '
                                            f'value="{name}.ply"/></shape>'))
        if name == "pair":
            mi.load_file(str(path))
            assert read_xml(path).meshes[0].mesh.triangle_count == 2
            continue
        with pytest.raises(Exception):
            mi.load_file(str(path))
        with pytest.raises(SceneFileError, match="quad.ply has faces of more than 3 corners"):
            read_xml(path)


@pytest.mark.parametrize("change, words", [
    (('</film>', '</film><film type="hdrfilm"/>'), "a second <film> inside <sensor>"),
    (('</film>', '</film><sampler type="independent"/><sampler type="independent"/>'),
     "a second <sampler> inside <sensor>"),
    (('</film>', '<rfilter type="box"/><rfilter type="box"/></film>'),
     "a second <rfilter> inside <film>"),
    (('</film>', '<string name="pixel_format" value="luminance"/></film>'),
     "pixel_format 'luminance' is not read (this reader renders rgb)"),
    (('</film>', '<string name="component_format" value="bogus"/></film>'),
     "component_format 'bogus' is not read"),
    (('</film>', '</film><sampler type="independent"><integer name="sample_count" '
                 'value="0"/></sampler>'), "sample_count must be 1..65536, got 0"),
    (('</film>', '</film><sampler type="independent"><integer name="sample_count" '
                 'value="100000"/></sampler>'), "sample_count must be 1..65536, got 100000"),
    (('</film>', '</film><sampler type="independent"><integer name="seed" '
                 'value="-1"/></sampler>'), "seed must be >= 0, got -1"),
    (('<lookat origin="1, 2, 5" target="0, 0.5, 0" up="0, 1, 0"/>',
      '<matrix value="-1 0.6 0 0  0 0.8 0 0  0 0 -1 4  0 0 0 1"/>'), "its to_world scales or "
                                                                      "shears"),
])
def test_a_sensor_mitsuba_refuses_or_renders_otherwise_is_an_error(tmp_path, change, words):
    """Inside a sensor: two films, samplers or filters; a pixel format
    other than the RGB this renders (Mitsuba would write luminance, XYZ or
    alpha) or one that is none; no samples; a to_world that shears."""
    text = scene_xml(CUBE)
    assert change[0] in text
    path = scene_of(tmp_path, text.replace(change[0], change[1], 1))
    with pytest.raises(SceneFileError) as error:
        read_xml(path)
    assert str(error.value).startswith(f"{path}:") and words in str(error.value), error.value


@pytest.mark.parametrize("inside, words", [
    ('<float name="radius" value="-1.5"/>', "a sphere's radius must be positive, got -1.5"),
    ('<transform name="to_world"><scale x="2" y="0.6" z="1"/></transform>',
     "a sphere's to_world may rotate, translate and scale alike on every axis"),
    ('<transform name="to_world"><scale value="-1"/></transform>',
     "a sphere's to_world may rotate, translate and scale alike on every axis"),
])
def test_a_sphere_that_mitsuba_would_not_render_as_placed_is_an_error(tmp_path, inside, words):
    """Mitsuba keeps a sphere a sphere under a stretching to_world (it warns,
    and renders one radius) and turns it inside out, dark, under a mirror or
    a negative radius, where the mesh here would follow the map: refused."""
    path = scene_of(tmp_path, scene_xml(SPHERE.format(inside)))
    mi.load_file(str(path))  # Mitsuba loads it ...
    with pytest.raises(SceneFileError) as error:  # ... and renders something else
        read_xml(path)
    assert words in str(error.value)
    # a uniform scale, a rotation and a move keep a sphere
    path = scene_of(tmp_path, scene_xml(SPHERE.format(
        '<float name="radius" value="0.5"/><transform name="to_world"><rotate x="1" '
        'angle="30"/><scale value="2"/><translate x="1"/></transform>')))
    vertices = read_xml(path).meshes[0].mesh.vertices
    np.testing.assert_allclose(np.linalg.norm(vertices - [1, 0, 0], axis=1), 1.0, atol=1e-5)


def test_a_sphere_placed_by_a_rounded_matrix_loads(tmp_path):
    """A rotation written with four decimals scales its axes apart by about
    1e-4: rounding, so the sphere loads, its radius the map's scale; a
    stretch of 1% is still refused, and says how far the axes part."""
    c = 0.7071  # cos 45 degrees, as a hand-written file gives it
    rotated = (f'<transform name="to_world"><matrix value="{2 * c} 0 {2 * c} 1  0 2 0 0  '
               f'{-2 * c} 0 {2 * c} 0  0 0 0 1"/></transform>')
    body = SPHERE.format(rotated) + CUBE  # beside a mesh: analytic (alone, an icosphere)
    sphere = read_xml(scene_of(tmp_path, scene_xml(body))).meshes[0].sphere
    np.testing.assert_allclose(sphere[:3], [1, 0, 0])
    assert sphere[3] == pytest.approx(2.0, rel=1e-4)
    stretched = '<transform name="to_world"><scale x="1.01" y="1" z="1"/></transform>'
    with pytest.raises(SceneFileError, match=r"scales its axes by 1 to 1\.01"):
        read_xml(scene_of(tmp_path, scene_xml(SPHERE.format(stretched) + CUBE)))


def test_defaults_hold_as_mitsuba_s(tmp_path):
    """The first <default> of a name holds (Mitsuba keeps the first); a $name
    above its <default> is an error unless given by the caller; a default
    given by the caller that the file never uses is an error (Mitsuba's
    "Found unused parameters"); a scene needs its version."""
    body = CUBE.replace("/>", "></shape>")
    text = scene_xml(body, fov="$fov").replace(
        "<sensor", '<default name="fov" value="40"/><default name="fov" value="80"/><sensor', 1)
    path = scene_of(tmp_path, text)
    theirs = mi.traverse(mi.load_file(str(path)).sensors()[0])["x_fov"]
    assert read_xml(path).camera == read_xml(scene_of(tmp_path, scene_xml(body, fov=40.0))
                                             ).camera
    assert float(np.ravel(theirs)[0]) == pytest.approx(40.0)
    late = scene_xml(body, fov="$fov").replace("</scene>", '<default name="fov" value="40"/>'
                                                           "</scene>")
    path = scene_of(tmp_path, late)
    with pytest.raises(SceneFileError, match=r"scene.xml:3: <float name=\"fov\">: \$fov is used "
                                             r"above its <default name=\"fov\"> \(line 12\)"):
        read_xml(path)
    assert read_xml(path, {"fov": 40}).camera.fov_deg == pytest.approx(
        read_xml(scene_of(tmp_path, scene_xml(body, fov=40.0))).camera.fov_deg)
    with pytest.raises(SceneFileError, match="defaults given that the file never uses "
                                             r"\(no \$name\): spp"):
        read_xml(scene_of(tmp_path, scene_xml(body)), {"spp": 4})
    with pytest.raises(SceneFileError, match="scene.xml:1: <scene>: needs its version"):
        read_xml(scene_of(tmp_path, scene_xml(body).replace(' version="3.0.0"', "")))


def test_a_lookat_without_up_and_several_sensors_frame_as_in_mitsuba(tmp_path):
    """<lookat> without up takes Mitsuba's own up (its coordinate_system
    around the view direction), for views along and across the axes; of
    several sensors, the first frames the render, as mi.render(scene)
    renders sensors()[0]."""
    for target in ("0, 0, 0", "0.3, -2, 0.1", "1, 2, 4", "2, 5, 5"):
        path = scene_of(tmp_path, scene_xml(CUBE, to_world=f'<lookat origin="1, 2, 5" '
                                                           f'target="{target}"/>'))
        camera = read_xml(path).camera
        matrix = np.array(mi.load_file(str(path)).sensors()[0].world_transform().matrix)
        forward, _, up = camera.basis()
        np.testing.assert_allclose(forward, matrix[:3, 2], atol=1e-6)
        np.testing.assert_allclose(up, matrix[:3, 1], atol=1e-6)
    second = scene_xml(CUBE, fov=40.0).replace("</scene>", """<sensor type="perspective">
    <float name="fov" value="70"/></sensor></scene>""")
    path = scene_of(tmp_path, second)
    assert mi.traverse(mi.load_file(str(path)).sensors()[0])["x_fov"] == pytest.approx(40.0)
    assert read_xml(path).camera == read_xml(scene_of(tmp_path, scene_xml(CUBE, fov=40.0))
                                             ).camera


def test_every_index_mitsuba_names_reads_as_its_value(tmp_path):
    """Mitsuba's whole table of named indices of refraction, each the eta
    Mitsuba 3 loads for it."""
    from hlbvh_cl.io.mitsuba import IORS
    for name, value in IORS.items():
        bsdf = mi.load_dict({"type": "dielectric", "int_ior": name, "ext_ior": "vacuum"})
        assert float(np.ravel(mi.traverse(bsdf)["eta"])[0]) == pytest.approx(value, rel=1e-6)


@pytest.mark.parametrize("body, words", [
    ('<shape type="cube"><transform name="to_world"><rotate x="1" y="1" angle="40"/>'
     '</transform></shape>', "<rotate>: its axis must be a unit vector, got length 1.41421"),
    ('<integrator type="path"><integer name="max_depth" value="0"/></integrator>',
     "max_depth 0 (an image of nothing, in Mitsuba) is not rendered here"),
    ('<integrator type="path"><integer name="max_depth" value="2000"/></integrator>',
     "max_depth must be -1 (no limit) or 1..1024, got 2000"),
    ('<shape type="cube"><transform name="to_world"><scale value="inf"/></transform></shape>',
     "<scale>: expected a finite number, got \'inf\'"),
    # Mitsuba sends the light along to_world's z axis unnormalised: a diffuse
    # ground under this one came out twice as bright (loaded as unit before)
    (CUBE + '<emitter type="directional"><transform name="to_world"><scale value="2"/>'
     '</transform></emitter>',
     "a directional light's to_world must keep its z axis unit long"),
])
def test_what_mitsuba_loads_but_renders_otherwise_is_an_error(tmp_path, body, words):
    """A rotate about a longer axis: Mitsuba scales by it but keeps the
    matrix's transpose as its inverse, so its shading normals leave the
    surface (a mirror cube's highlights moved, 5 % off in its mean); max
    depth 0, which this renderer does not take; depths past the renderer's
    limits (which a render would refuse, naming no file); an infinite
    scale.  Mitsuba loads them all."""
    path = scene_of(tmp_path, scene_xml(body))
    mi.load_file(str(path))
    with pytest.raises(SceneFileError) as error:
        read_xml(path)
    assert str(error.value).startswith(f"{path}:") and words in str(error.value), error.value


def test_a_roulette_that_starts_past_every_bounce_is_no_roulette(tmp_path, suite_device):
    """Mitsuba reads any int32 rr_depth; one past a path's last bounce never
    starts the roulette.  Such a file loads here too, and renders the very
    image of the roulette's latest start that still comes too late (the
    path's depth), bit for bit; one start sooner, the roulette ends paths
    and the image differs."""
    from hlbvh_cl.io.scenefile import load
    text = CORNELL.read_text()
    images = {}
    for rr_depth in (4, 6, 100000, 2**31 - 1):
        body = text.replace('<integer name="max_depth" value="6"/>',
                            f'<integer name="max_depth" value="6"/>'
                            f'<integer name="rr_depth" value="{rr_depth}"/>', 1)
        assert body != text
        path = scene_of(tmp_path, body)
        mi.load_file(str(path))
        loaded = load(path, suite_device, defaults={"res": 16, "spp": 2})
        assert loaded.options["rr_depth"] == rr_depth
        images[rr_depth] = loaded.renderer().render(loaded.camera, 16, 16, hdr=True,
                                                    **loaded.options)
    np.testing.assert_array_equal(images[100000], images[6])
    np.testing.assert_array_equal(images[2**31 - 1], images[6])
    assert not np.array_equal(images[4], images[6])


def test_values_past_the_renderers_limits_yield_to_the_flags_that_replace_them(
        tmp_path, capsys, suite_device):
    """Mitsuba loads sample counts, depths and film sides past this
    renderer's limits.  Read alone, such a file is refused at the line that
    says them; with the values replaced (the CLI's --spp, --max-depth,
    --width and --height) it loads, and renders with the flags' values.  A
    value no flag replaces is still refused, and one Mitsuba itself refuses
    (a film side of 0) is refused whatever replaces it."""
    from hlbvh_cl.cli import main
    from hlbvh_cl.io.exr import read_exr
    text = CORNELL.read_text()
    for old, new in (('name="max_depth" value="6"', 'name="max_depth" value="5000"'),
                     ('name="sample_count" value="$spp"', 'name="sample_count" value="100000"'),
                     ('name="width" value="$res"', 'name="width" value="20000"')):
        assert old in text
        text = text.replace(old, new, 1)
    path = scene_of(tmp_path, text)
    for replaced, words in (((), "max_depth must be -1 (no limit) or 1..1024, got 5000"),
                            ({"max_depth"}, "sample_count must be 1..65536, got 100000"),
                            ({"max_depth", "spp"}, "width and height must be 1..16384, got 20000"),
                            ({"max_depth", "spp", "height"}, "got 20000")):
        with pytest.raises(SceneFileError, match=r"scene\.xml:\d+: ") as error:
            read_xml(path, replaced=replaced)
        assert words in str(error.value), (replaced, error.value)
    read = read_xml(path, replaced={"max_depth", "spp", "width"})
    assert (read.options["max_depth"], read.options["spp"], read.width) == (5000, 100000, 20000)

    out = tmp_path / "big.exr"
    argv = ["render", str(path), "-o", str(out), "--device", suite_device.id,
            "--width", "16", "--height", "12", "--spp", "2"]
    assert main(argv) == 2  # --max-depth not given: the file's 5000 is refused
    assert "max_depth must be -1 (no limit) or 1..1024, got 5000" in capsys.readouterr().err
    assert main(argv + ["--max-depth", "3"]) == 0
    assert "16x12, path, 2 spp" in capsys.readouterr().out
    assert read_exr(out).shape == (12, 16, 3)

    assert main(argv + ["--max-depth", "3", "--time", "0.2"]) == 0  # --time replaces spp too
    capsys.readouterr()
    assert main(["info", str(path), "--device", suite_device.id]) == 0  # renders nothing
    assert "triangles" in capsys.readouterr().out

    # a value replaced must still be one Mitsuba reads (its film sides and
    # sample counts are uint32, its depths int)
    every = {"max_depth", "spp", "width", "height"}
    for old, new, words in (('value="20000"', 'value="0"',
                             "width and height must be 1..4294967295, got 0"),
                            ('value="20000"', 'value="1' + "0" * 400 + '"',
                             "width and height must be 1..4294967295, got 1000"),
                            ('value="100000"', 'value="4294967296"',
                             "sample_count must be 1..4294967295, got 4294967296"),
                            ('value="5000"', 'value="2147483648"',
                             "max_depth must be -1 (no limit) or 1..2147483647, got 2147483648")):
        bad = scene_of(tmp_path, text.replace(old, new, 1))
        with pytest.raises(SceneFileError, match=r"scene\.xml:\d+: ") as error:
            read_xml(bad, replaced=every)
        assert words in str(error.value), (new[:20], error.value)


def test_a_scene_with_no_emitter_is_black_as_in_mitsuba(tmp_path, suite_device):
    """Mitsuba renders a scene with no emitter black; the loader left its
    emitters empty and the renderer lit it with its default sky of 1 (a
    TOML file's, as documented there): a white-lit cube where Mitsuba's
    image is 0."""
    path = tmp_path / "dark.xml"
    path.write_text('<scene version="3.0.0">\n'
                    '  <sensor type="perspective"><float name="fov" value="40"/>\n'
                    '    <transform name="to_world"><lookat origin="0, 3, 9" target="0, 0.8, 0" '
                    'up="0, 1, 0"/></transform>\n'
                    '    <film type="hdrfilm"><integer name="width" value="16"/>'
                    '<integer name="height" value="12"/></film>\n'
                    '  </sensor>\n'
                    '  <shape type="cube"><bsdf type="diffuse"/></shape>\n'
                    '</scene>\n')
    loaded = load(path, suite_device.id)
    assert loaded.emitters == []
    image = loaded.renderer().render(loaded.camera, 16, 12, shading="path", spp=4, hdr=True)
    assert image.max() == 0.0


def test_a_toml_file_without_materials_or_emitters_is_written_as_it_renders(tmp_path):
    """write_xml failed on a file with no material (a TypeError on None), and
    wrote no emitter for one with none, which this renderer lights by its
    sky of 1 and Mitsuba then rendered black; instances are refused by name
    (they were dropped: one copy written)."""
    from hlbvh_cl.io.to_mitsuba import write_xml
    xml = write_xml(places.SCENES / "bunny_small.toml", tmp_path)
    back = read_xml(xml)
    assert back.emitters == [{"type": "constant", "radiance": 1.0}]
    assert all(entry.material["type"] == "twosided" for entry in back.meshes)
    instanced = tmp_path / "copies.toml"
    instanced.write_text((places.SCENES / "bunny_small.toml").read_text().replace(
        '"meshes/', f'"{places.MESHES}/') + '\n[[instance]]\nmesh = 0\n')
    with pytest.raises(ValueError, match="instance"):
        write_xml(instanced, tmp_path)
