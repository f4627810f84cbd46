"""The renderer (hlbvh_cl/render/, kernels/render/camera.cl, kernels/render/integrators/direct.cl)
against images rebuilt here from the documented definitions (hlbvh_cl/render/integrators/direct.py's
docstring, scenefile.py's camera convention) with the float64 brute-force
oracle (tests/support/oracle.py) in place of the BVH.  Bad arguments: test_validation.py.

The device works in float32 and the oracle in float64, so a pixel whose ray
grazes a triangle's edge, or whose shadow / AO ray grazes one, may go either
way: a small fraction of pixels may differ, the rest must agree to within one
level of 8 bits.
"""
from __future__ import annotations


import numpy as np
import pytest

import hlbvh_cl
from hlbvh_cl.render import integrators, settings as render_settings
from hlbvh_cl.render.integrators import direct
from hlbvh_cl.render.renderer import Pipeline, check_settings
from hlbvh_cl.query.rays import PACKET_SIZES, RayQuery
import built
from oracle import brute_force_intersect, brute_force_occluded
from render_scene import CAMERA, COLORS, LIGHT, render_meshes, renderer, scene  # noqa: F401

WIDTH, HEIGHT = 64, 48
LEVELS = 1                # 8-bit levels a matching pixel may be off by
MAX_DIFFERENT = 0.01      # fraction of pixels that may differ by more


# -- the scene (tests/support/render_scene.py) as float64 arrays -----------------------------

@pytest.fixture(scope="module")
def geometry():
    """Concatenated float64 vertices, faces, and the mesh of every face."""
    meshes = render_meshes()
    offsets = np.cumsum([0] + [m.vertex_count for m in meshes])
    vertices = np.concatenate([m.vertices.astype(np.float64) for m in meshes])
    faces = np.concatenate([m.faces + off for m, off in zip(meshes, offsets)])
    geom = np.concatenate([np.full(m.triangle_count, g) for g, m in enumerate(meshes)])
    return vertices, faces, geom


# -- the documented definitions, restated ---------------------------------------------

def pcg(value) -> np.ndarray:
    """Jarzynski & Olano 2020's PCG hash on uint32 (wrapping arithmetic)."""
    state = np.asarray(value, np.uint32) * np.uint32(747796405) + np.uint32(2891336453)
    word = ((state >> ((state >> np.uint32(28)) + np.uint32(4))) ^ state) * np.uint32(277803737)
    return (word >> np.uint32(22)) ^ word


def random_unit(pixel, sample, dimension) -> np.ndarray:
    pixel = np.asarray(pixel, np.uint32)
    h = pcg(pixel + pcg(np.full(pixel.shape, sample, np.uint32)
                        + pcg(np.full(pixel.shape, dimension, np.uint32))))
    return (h >> np.uint32(8)).astype(np.float64) * 2.0 ** -24


def camera_rays(camera, width, height, sample=None):
    """Eye and (H*W, 3) directions: pixel centres, or sample `sample`'s jitter."""
    forward = np.subtract(camera.target, camera.eye)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, camera.up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    y, x = np.mgrid[0:height, 0:width]
    pixel = (y * width + x).ravel()
    jx = jy = 0.5
    if sample is not None:
        jx, jy = random_unit(pixel, sample, 0), random_unit(pixel, sample, 1)
    sx = 2 * (x.ravel() + jx) / width - 1
    sy = 1 - 2 * (y.ravel() + jy) / height
    half = np.tan(np.radians(camera.fov_deg) / 2)
    directions = forward + ((sx * width / height)[:, None] * right + sy[:, None] * true_up) * half
    return np.asarray(camera.eye, np.float64), directions


def primary_hits(geometry, eye, directions):
    vertices, faces, geom = geometry
    found = brute_force_intersect(vertices, faces, np.broadcast_to(eye, directions.shape),
                                  directions)
    hit = found["prim"] >= 0
    normal = found["normal"]
    facing = np.where((np.einsum("ij,ij->i", normal, directions) > 0)[:, None], -normal, normal)
    return {"hit": hit, "t": found["t"], "geom": np.where(hit, geom[found["prim"]], -1),
            "normal": facing, "point": eye + found["t"][:, None] * directions}


def scene_box(geometry):
    vertices, faces, _ = geometry
    used = vertices[faces.ravel()]
    return used.min(axis=0), used.max(axis=0)


def ray_offset(geometry) -> float:
    lo, hi = scene_box(geometry)
    return max(1e-4 * np.linalg.norm(hi - lo), 2.0 ** -16 * np.abs(np.concatenate([lo, hi])).max())


def sky(directions, camera):
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    up = np.asarray(camera.up) / np.linalg.norm(camera.up)
    s = np.clip(unit @ up, 0, 1)[:, None]
    horizon, zenith = np.asarray(direct.SKY_HORIZON), np.asarray(direct.SKY_ZENITH)
    return (1 - s) * horizon + s * zenith


def encode(linear, gamma: bool, width=WIDTH, height=HEIGHT) -> np.ndarray:
    value = np.clip(linear, 0, 1)
    if gamma:
        value = np.sqrt(value)
    return np.floor(255 * value + 0.5).reshape(height, width, 3)


def diffuse_reference(geometry, shadows: bool) -> np.ndarray:
    vertices, faces, _ = geometry
    eye, directions = camera_rays(CAMERA, WIDTH, HEIGHT)
    h = primary_hits(geometry, eye, directions)
    albedo = np.asarray(COLORS)[h["geom"]]
    light = np.asarray(LIGHT.direction)
    cosine = np.clip(h["normal"] @ light, 0, None)
    visible = np.ones(len(directions))
    lit = h["hit"] & (cosine > 0)
    if shadows:
        origins = h["point"][lit] + ray_offset(geometry) * h["normal"][lit]
        visible[lit] = ~brute_force_occluded(vertices, faces, origins,
                                             np.broadcast_to(light, origins.shape))
    colour = albedo * (LIGHT.ambient + LIGHT.intensity * cosine * visible)[:, None]
    colour = np.where(h["hit"][:, None], colour, sky(directions, CAMERA))
    return encode(colour, gamma=True), h, visible


def assert_images_match(rendered, expected, levels=LEVELS, max_different=MAX_DIFFERENT):
    assert rendered.dtype == np.uint8 and rendered.shape == expected.shape
    off = np.abs(rendered.astype(np.int64) - expected).max(axis=2)
    different = np.count_nonzero(off > levels)
    assert different <= max_different * off.size, (
        f"{different} of {off.size} pixels differ by more than {levels} levels; "
        f"first at {np.argwhere(off > levels)[:5].tolist()}")


# -- images against the oracle ---------------------------------------------------------

def test_diffuse_with_shadows_matches_the_oracle(scene, renderer, geometry):
    expected, h, visible = diffuse_reference(geometry, shadows=True)
    # the view must hold what the test is about: every mesh, sky, and shadows
    assert set(np.unique(h["geom"])) == {-1, 0, 1, 2}
    assert np.count_nonzero(visible == 0) > 50
    rendered = renderer.render(CAMERA, WIDTH, HEIGHT)
    assert_images_match(rendered, expected)


def test_diffuse_without_shadows_matches_the_oracle(scene, renderer, geometry):
    expected, _, _ = diffuse_reference(geometry, shadows=False)
    with_shadows, _, _ = diffuse_reference(geometry, shadows=True)
    rendered = renderer.render(CAMERA, WIDTH, HEIGHT, shadows=False)
    assert_images_match(rendered, expected)
    assert not np.array_equal(rendered, renderer.render(CAMERA, WIDTH, HEIGHT, shadows=True))
    assert not np.array_equal(expected, with_shadows)


# Sizes whose widths and heights are not multiples of the pixel tiles that
# rays are traced in (render/tiles.h, pixel_in_pass: last bands of 1, 2 and 3 rows,
# last columns of 1, 2 and 3), as well as one that is.
@pytest.mark.parametrize("width, height", [(WIDTH, HEIGHT), (50, 37), (33, 17), (3, 5), (21, 19),
                                           (13, 30)])
def test_normals_match_the_oracle(scene, renderer, geometry, width, height):
    eye, directions = camera_rays(CAMERA, width, height)
    h = primary_hits(geometry, eye, directions)
    colour = np.where(h["hit"][:, None], (h["normal"] + 1) / 2, 0.0)
    rendered = renderer.render(CAMERA, width, height, shading="normals")
    assert_images_match(rendered, encode(colour, gamma=False, width=width, height=height))


def test_depth_matches_the_oracle_and_falls_with_distance(scene, renderer, geometry):
    eye, directions = camera_rays(CAMERA, WIDTH, HEIGHT)
    h = primary_hits(geometry, eye, directions)
    lo, hi = scene_box(geometry)
    near = np.linalg.norm(np.maximum(np.maximum(lo - eye, eye - hi), 0))
    far = np.linalg.norm(np.maximum(np.abs(eye - lo), np.abs(eye - hi)))
    distance = np.where(h["hit"], h["t"] * np.linalg.norm(directions, axis=1), np.inf)
    value = np.where(h["hit"], np.clip((far - distance) / (far - near), 0, 1), 0.0)
    rendered = renderer.render(CAMERA, WIDTH, HEIGHT, shading="depth")
    assert_images_match(rendered, encode(np.repeat(value[:, None], 3, axis=1), gamma=False))
    # grey, and darker the farther: sorted by distance, never brighter by more
    # than rounding (pixels the oracle and the device disagree on left out)
    assert (rendered == rendered[..., :1]).all()
    grey = rendered[..., 0].ravel().astype(np.int64)
    agree = h["hit"] & (np.abs(grey - np.floor(255 * value + 0.5)) <= LEVELS)
    order = np.argsort(distance[agree], kind="stable")
    assert np.all(np.diff(grey[agree][order]) <= 2 * LEVELS)
    assert grey[agree].max() - grey[agree].min() > 100  # a real range of depths


def test_ambient_occlusion_matches_the_oracle(scene, renderer, geometry):
    vertices, faces, _ = geometry
    samples = 6
    eye, directions = camera_rays(CAMERA, WIDTH, HEIGHT)
    h = primary_hits(geometry, eye, directions)
    lo, hi = scene_box(geometry)
    reach = direct.AO_DISTANCE_SCALE * np.linalg.norm(hi - lo)
    pixels = np.flatnonzero(h["hit"])
    n = h["normal"][pixels]
    # Duff et al. 2017's basis around n, then Malley's cosine-weighted directions
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    b1 = np.stack([1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    b2 = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    origins = h["point"][pixels] + ray_offset(geometry) * n
    free = np.zeros(len(pixels))
    for k in range(samples):
        u1, u2 = random_unit(pixels, 0, 2 + 2 * k), random_unit(pixels, 0, 3 + 2 * k)
        radius, angle = np.sqrt(u1)[:, None], 2 * np.pi * u2[:, None]
        ray = radius * (np.cos(angle) * b1 + np.sin(angle) * b2) + np.sqrt(1 - u1)[:, None] * n
        free += ~brute_force_occluded(vertices, faces, origins, ray, 0.0, reach)
    colour = sky(directions, CAMERA)
    colour[pixels] = np.asarray(COLORS)[h["geom"][pixels]] * (free / samples)[:, None]
    assert 0 < np.count_nonzero(free < samples) < len(pixels)  # some occlusion, not all
    rendered = renderer.render(CAMERA, WIDTH, HEIGHT, shading="ao", ao_samples=samples)
    assert_images_match(rendered, encode(colour, gamma=True))


def test_samples_per_pixel_average_jittered_samples(scene, renderer, geometry):
    spp = 3
    total = np.zeros((WIDTH * HEIGHT, 3))
    for sample in range(spp):
        eye, directions = camera_rays(CAMERA, WIDTH, HEIGHT, sample=sample)
        h = primary_hits(geometry, eye, directions)
        total += np.where(h["hit"][:, None], (h["normal"] + 1) / 2, 0.0)
    rendered = renderer.render(CAMERA, WIDTH, HEIGHT, shading="normals", spp=spp)
    assert_images_match(rendered, encode(total / spp, gamma=False))
    # antialiased: some edge pixels are blends, unlike the one-sample image
    assert not np.array_equal(rendered, renderer.render(CAMERA, WIDTH, HEIGHT, shading="normals"))


# -- determinism, chunks, reuse -----------------------------------------------------------

@pytest.mark.parametrize("length", [1e300, 1e-200])
def test_the_length_of_up_changes_nothing(scene, renderer, length):
    """up is a direction: the sky's gradient (along up) too is the same for
    any length, with no overflow to NaN at 1e300 or underflow at 1e-200."""
    import dataclasses
    camera = dataclasses.replace(CAMERA, up=tuple(length * np.asarray(CAMERA.up)))
    image = renderer.render(CAMERA, 40, 30)
    assert (image == image[0, 0]).all(axis=2).sum() > 10  # some sky in view
    assert np.array_equal(renderer.render(camera, 40, 30), image)


@pytest.mark.parametrize("options", [{}, {"spp": 4}, {"shading": "ao", "ao_samples": 4, "spp": 2}])
def test_renders_are_deterministic(scene, renderer, options):
    first = renderer.render(CAMERA, 40, 30, **options)
    second = renderer.render(CAMERA, 40, 30, **options)
    assert np.array_equal(first, second)


def test_a_pass_fits_one_allocation_a_buffer_and_a_quarter_of_the_device(scene):
    """Passes shrink where their buffers (bytes a pixel, by name) would not
    fit the device: each in one allocation, all in a quarter of its memory."""
    rt = built.runtime(scene)
    pipeline = Pipeline(rt)
    device, width = rt.device, 100
    assert pipeline.chunk_rows(width, 10_000) > 1_000  # whole passes otherwise
    quarter = device.global_mem_size // 4
    per_pixel = {"a": quarter // 3_000, "b": quarter // 3_000}  # 1,500 pixels fit
    rows = pipeline.chunk_rows(width, 10_000, per_pixel)
    assert 1 <= rows and rows * width * sum(per_pixel.values()) <= quarter
    assert rows * width > 1_500 // 2  # not below the last whole band of tiles
    rows = pipeline.chunk_rows(width, 10_000, {"one": device.max_mem_alloc_size // 250})
    assert 1 <= rows <= 2


@pytest.mark.parametrize("options", [{"spp": 2}, {"shading": "ao", "ao_samples": 3}])
def test_rendering_in_row_chunks_gives_the_same_image(scene, renderer, options):
    whole = renderer.render(CAMERA, 50, 37, **options)
    # at most 3 rows of 50 pixels per launch: 13 chunks, the last one short
    rt = built.runtime(scene)
    small = Pipeline(rt, RayQuery(rt, max_rays_per_launch=170))
    assert small.chunk_rows(50, 37) == 3
    settings = check_settings(CAMERA, 50, 37, options.get("shading", "diffuse"), True,
                              options.get("spp", 1), options.get("ao_samples", 16), None)
    chunked = small.render(built.tree(scene), settings, renderer.look())
    assert np.array_equal(chunked, whole)


@pytest.mark.parametrize("options", [{}, {"shading": "ao", "ao_samples": 3}])
def test_every_packet_size_renders_the_same_image(scene, options):
    # 50 x 37: tiles cut short at the right and bottom edges; a packet of 8 is
    # half a tile, one of 16 a whole one (the runtime's kernel variant)
    settings = check_settings(CAMERA, 50, 37, options.get("shading", "diffuse"), True, 1,
                              options.get("ao_samples", 16), None)
    images = {}
    rt, tree = built.runtime(scene), built.tree(scene)
    look = hlbvh_cl.Renderer(scene, COLORS, LIGHT).look()
    for size in PACKET_SIZES:
        renderer = Pipeline(rt, RayQuery(rt, packet_size=size))
        images[size] = renderer.render(tree, settings, look)
    assert images[1].shape == (37, 50, 3) and images[1].std() > 0
    for size, image in images.items():
        assert np.array_equal(image, images[1]), f"packet size {size} renders another image"


def test_every_mode_gives_an_image_of_the_asked_size(scene, renderer):
    for shading in integrators.SHADINGS:
        image = renderer.render(CAMERA, 33, 17, shading=shading, ao_samples=2, max_depth=3)
        assert image.shape == (17, 33, 3) and image.dtype == np.uint8
        assert len(np.unique(image.reshape(-1, 3), axis=0)) >= 5
        stats = renderer.stats
        assert stats["shading"] == shading and stats["primary_rays"] == 33 * 17
        assert stats["times_ms"]["total"] > 0
    assert renderer.render(CAMERA, 1, 1).shape == (1, 1, 3)


def test_default_colors_and_light():
    meshes = render_meshes()
    plain = hlbvh_cl.Renderer(hlbvh_cl.Scene(meshes))
    assert plain.colors == [render_settings.PALETTE[i] for i in range(len(meshes))]
    assert np.allclose(np.linalg.norm(plain.light.direction), 1.0)
    image = plain.render(CAMERA, 20, 15)
    assert image.shape == (15, 20, 3)
