"""Materials per instance (Renderer.instance_materials): two instances of
one sphere, each with a material of its own, render as the same scene made
flat, each copy a mesh with that material (the oracle: the per-mesh path
every other render test checks); their AOV albedo is their own material's;
bad entries are named."""
import numpy as np
import pytest
import trimesh

import hlbvh_cl

RED = {"type": "diffuse", "reflectance": [0.8, 0.1, 0.1]}
GOLD = {"type": "roughconductor", "material": "Au", "alpha": 0.2}
GREY = {"type": "diffuse", "reflectance": 0.5}
EMITTERS = [{"type": "constant", "radiance": 1.0},
            {"type": "point", "position": [0.0, 3.0, 2.0], "intensity": 8.0}]
WIDTH, HEIGHT, SPP, SEEDS = 48, 32, 4, 4


def sphere_and_ground():
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    ground = np.array([[-4, -0.5, -4], [4, -0.5, -4], [4, -0.5, 4], [-4, -0.5, 4]], np.float64)
    return (hlbvh_cl.Mesh(s.vertices, s.faces, name="sphere"),
            hlbvh_cl.Mesh(ground, [[0, 2, 1], [0, 3, 2]], name="ground"))


def shifted(x):
    return np.hstack([np.eye(3), [[x], [0.0], [0.0]]])


def moved(mesh, x):
    return hlbvh_cl.Mesh(np.asarray(mesh.vertices) + [x, 0.0, 0.0], mesh.faces)


CAMERA = hlbvh_cl.Camera(eye=(0, 0.6, 3.2), target=(0, 0, 0), fov_deg=45)


def renders(renderer):
    images = [renderer.render(CAMERA, WIDTH, HEIGHT, shading="path", spp=SPP, max_depth=4,
                              hdr=True, seed=seed) for seed in range(1, SEEDS + 1)]
    return np.stack(images).astype(np.float64)


@pytest.fixture(scope="module")
def scenes(suite_device):
    ball, ground = sphere_and_ground()
    instanced = hlbvh_cl.Scene([ball, ground], device=suite_device,
                               instances=[(0, shifted(-0.7)), (0, shifted(0.7)),
                                          (1, shifted(0.0))])
    flat = hlbvh_cl.Scene([moved(ball, -0.7), moved(ball, 0.7), ground], device=suite_device)
    return instanced, flat


def test_each_instance_shows_its_own_material_as_the_flat_scene_does(scenes):
    instanced, flat = scenes
    ours = renders(hlbvh_cl.Renderer(instanced, materials=[GREY, GREY], emitters=EMITTERS,
                                     instance_materials=[RED, GOLD, None]))
    oracle = renders(hlbvh_cl.Renderer(flat, materials=[RED, GOLD, GREY], emitters=EMITTERS))
    # The same random numbers per pixel and the same surfaces: the two differ
    # only where a ray's hit moves by rounding (instances map rays in double).
    stderr = np.sqrt(ours.var(0, ddof=1).mean() / SEEDS)
    blocks = (ours.mean(0) - oracle.mean(0)).reshape(HEIGHT // 8, 8, WIDTH // 8, 8, 3)
    assert np.abs(blocks.mean((1, 3))).max() < 3 * stderr
    # The left ball is red, and without the instances' own materials grey:
    # the colours the comparison above agrees on are the materials'.
    left = flat.intersect(*CAMERA.rays(WIDTH, HEIGHT)).geom_id.reshape(HEIGHT, WIDTH) == 0
    assert left.sum() > 20
    red = ours.mean(0)[left].mean(0)
    assert red[0] > 3 * red[1] and red[0] > 3 * red[2]
    grey = renders(hlbvh_cl.Renderer(instanced, materials=[GREY, GREY], emitters=EMITTERS))
    grey = grey.mean(0)[left].mean(0)
    assert grey.max() < 1.1 * grey.min()


def test_the_albedo_aov_is_the_instance_s_material(scenes):
    instanced, flat = scenes
    renderer = hlbvh_cl.Renderer(instanced, materials=[GREY, GREY], emitters=EMITTERS,
                                 instance_materials=[RED, None, None])
    result = renderer.render(CAMERA, WIDTH, HEIGHT, shading="path", spp=1, aovs=True)
    albedo = result.albedo
    hits = flat.intersect(*CAMERA.rays(WIDTH, HEIGHT))
    geom = hits.geom_id.reshape(HEIGHT, WIDTH)
    assert (geom == 0).any() and (geom == 1).any()
    np.testing.assert_allclose(albedo[geom == 0], np.tile([0.8, 0.1, 0.1], ((geom == 0).sum(), 1)),
                               atol=1e-6)
    np.testing.assert_allclose(albedo[geom == 1], 0.5, atol=1e-6)


@pytest.mark.parametrize("instance_materials, message", [
    ([RED], "instance_materials has 1 entries but the scene has 3 instances"),
    ("diffuse", "instance_materials must be a list with one entry per instance"),
    ([None, {"type": "diffuse", "reflectance": 2.0}, None], "instance_materials[1]"),
    ([None, {"type": "velvet"}, None], "instance_materials[1]"),
])
def test_bad_instance_materials_are_named(scenes, instance_materials, message):
    instanced, _ = scenes
    renderer = hlbvh_cl.Renderer(instanced, instance_materials=instance_materials)
    with pytest.raises((TypeError, ValueError)) as error:
        renderer.render(CAMERA, 4, 4, shading="path")
    assert message in str(error.value)


def test_instance_materials_on_a_flat_scene_is_an_error(scenes):
    _, flat = scenes
    renderer = hlbvh_cl.Renderer(flat, instance_materials=[RED, None, None])
    with pytest.raises(ValueError, match="instance_materials is for a scene with instances"):
        renderer.render(CAMERA, 4, 4, shading="path")


@pytest.mark.parametrize("instanced", [True, False], ids=["instance", "flat"])
def test_an_emitter_no_ray_can_hit_lights_nothing(suite_device, instanced):
    """A lamp of mask 0, which no render ray can hit (they carry every mask
    bit), over a ground lit by nothing else: the image is black, as without
    the lamp.  Its light samples had still lit the ground (mean 0.24, where
    the lamp seen by every ray gives 1.35): half an estimate of a lamp that
    was not there.  With mask 1 it lights the ground."""
    ground_v = np.array([[-3, 0, -3], [3, 0, -3], [3, 0, 3], [-3, 0, 3]], float)
    faces = np.array([[0, 2, 1], [0, 3, 2]])
    lamp_v, lamp_f = ground_v / 2 + [0.0, 0.4, 0.0], faces[:, ::-1].copy()  # facing down
    camera = hlbvh_cl.Camera((0.0, 0.3, 2.5), (0.0, 0.0, 0.0), fov_deg=50)
    materials = [{"type": "diffuse", "reflectance": 0.8}, {"type": "diffuse", "reflectance": 0.0}]
    emitters = [{"type": "area", "mesh": 1, "radiance": 5.0}]

    def render(mask):
        if instanced:
            meshes = [hlbvh_cl.Mesh(ground_v, faces), hlbvh_cl.Mesh(lamp_v - [0, 0.4, 0], lamp_f)]
            lifted = np.hstack([np.eye(3), [[0.0], [0.4], [0.0]]])
            scene = hlbvh_cl.Scene(meshes, device=suite_device, masks=[1, mask],
                                   instances=[(0, np.eye(3, 4)), (1, lifted)])
        else:
            scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(ground_v, faces), hlbvh_cl.Mesh(lamp_v, lamp_f)],
                                   device=suite_device, masks=[1, mask])
        return np.asarray(hlbvh_cl.Renderer(scene, materials=materials, emitters=emitters).render(
            camera, 32, 24, shading="path", spp=8, seed=0, hdr=True, max_depth=2))

    assert render(0).max() == 0.0
    assert render(1).mean() > 0.5
