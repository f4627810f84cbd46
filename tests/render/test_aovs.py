"""The path render's AOVs (Renderer.render(..., aovs=True), Mitsuba 3's aov
integrator's albedo, sh_normal and depth) against float64 oracles: a tilted
plane's distance along each pixel's ray, an ellipsoid's analytic normal
(an instanced, scaled sphere), a mesh's reflectance; the pixel's samples
averaged as the radiance is (an emitter seen directly is its own albedo
image, every pixel, with either filter); and the CLI's EXR channels."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

import hlbvh_cl
import built


def pixel_rays(camera, width, height):
    """float64 origins and directions through the pixel centres (spp=1,
    seed=0 traces these), (H, W, 3) each."""
    origins, directions = camera.rays(width, height)
    return (origins.astype(np.float64).reshape(height, width, 3),
            directions.astype(np.float64).reshape(height, width, 3))


def test_depth_is_the_distance_along_the_ray(suite_device):
    """A plane through p0 with normal n, filling the view at a slant: each
    pixel's depth is |d| (p0 - o).n / (d.n), in float64."""
    p0, n = np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.3, 1.0]) / np.hypot(0.3, 1.0)
    u = np.cross(n, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    corners = [p0 + 50 * (a * u + b * v) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    faces = [[0, 1, 2], [0, 2, 3]]
    if np.cross(corners[1] - corners[0], corners[2] - corners[0]) @ n < 0:
        faces = [[0, 2, 1], [0, 3, 2]]
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(corners, faces)], device=suite_device)
    camera = hlbvh_cl.Camera(eye=(0.7, 1.1, 4.0), target=(0.2, -0.3, 0.0), fov_deg=50)
    width, height = 24, 16
    result = hlbvh_cl.Renderer(scene, materials=[{"type": "diffuse", "reflectance": 0.3}]).render(
        camera, width, height, shading="path", hdr=True, aovs=True, max_depth=2)
    origins, directions = pixel_rays(camera, width, height)
    expected = np.linalg.norm(directions, axis=-1) * ((p0 - origins) @ n) / (directions @ n)
    assert result.depth.shape == (height, width) and result.depth.dtype == np.float32
    np.testing.assert_allclose(result.depth, expected, rtol=2e-5)
    np.testing.assert_array_equal(result.albedo, np.full((height, width, 3), 0.3, np.float32))
    np.testing.assert_allclose(result.normal, np.broadcast_to(n, (height, width, 3)), atol=1e-6)
    assert result.image.shape == (height, width, 3) and result.image.dtype == np.float32


def test_the_normal_is_the_ellipsoid_s_own(suite_device):
    """A unit icosphere with its exact normals at the vertices, placed by an
    instance as the ellipsoid x = A s + c: each pixel's shading normal is the
    ellipsoid's analytic normal, inv(A)^T s normalised, at the point its
    ray meets it (float64), within the mesh's interpolation error; misses
    give zeros in every AOV, as Mitsuba's."""
    s = trimesh.creation.icosphere(subdivisions=5)
    a = np.array([[1.2, 0.3, 0.0], [0.0, 0.7, 0.0], [0.2, 0.0, 0.9]])
    c = np.array([0.1, -0.2, 0.3])
    camera = hlbvh_cl.Camera(eye=(0.5, 1.0, 4.5), target=(0.1, -0.2, 0.3), fov_deg=45)
    width = height = 32

    def render(face_normals):
        mesh = hlbvh_cl.Mesh(s.vertices, s.faces, normals=s.vertices, face_normals=face_normals)
        scene = hlbvh_cl.Scene([mesh], instances=[(0, np.hstack([a, c[:, None]]))],
                               device=suite_device)
        return hlbvh_cl.Renderer(scene, materials=[{"type": "conductor"}]).render(
            camera, width, height, shading="path", hdr=True, aovs=True, max_depth=2)
    result = render(False)
    origins, directions = pixel_rays(camera, width, height)
    inverse = np.linalg.inv(a)
    o, d = (origins - c) @ inverse.T, directions @ inverse.T  # in the unit sphere's frame
    qa, qb, qc = (d * d).sum(-1), 2 * (o * d).sum(-1), (o * o).sum(-1) - 1
    disc = qb * qb - 4 * qa * qc
    t = (-qb - np.sqrt(np.maximum(disc, 0))) / (2 * qa)
    on_sphere = o + t[..., None] * d
    expected = on_sphere @ inverse
    expected /= np.linalg.norm(expected, axis=-1, keepdims=True)
    hit = result.depth > 0
    inside = hit & (disc > 0.05 * qa)  # away from the silhouette, where the mesh sags
    assert inside.sum() > 200
    error = np.linalg.norm(result.normal[inside] - expected[inside], axis=-1)
    assert error.max() < 5e-3, error.max()
    # can fail: face normals miss it by the facets' angle
    flat = render(True).normal
    assert np.linalg.norm(flat[inside] - expected[inside], axis=-1).max() > 1e-2
    # the conductor's albedo: its specular reflectance (1 by default)
    np.testing.assert_array_equal(result.albedo[hit], 1.0)
    missed = ~hit
    assert missed.sum() > 100
    assert not result.albedo[missed].any() and not result.normal[missed].any()
    assert not result.depth[missed].any()


@pytest.mark.parametrize("rfilter", ["box", "gaussian"])
def test_aovs_average_the_pixel_s_samples_as_the_radiance_does(rfilter, suite_device):
    """A white emitting sphere (radiance 1, reflectance 1) in the dark, seen
    by camera rays only (max_depth 1): each sample's radiance and albedo
    are both 1 on it and 0 beside it, so the image and the albedo AOV are
    the same coverage in every pixel, silhouettes included.  (Face normals:
    with smooth ones a grazing sample can see the emitter's back, dark, as
    Mitsuba's would.)"""
    s = trimesh.creation.icosphere(subdivisions=3)
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(s.vertices, s.faces, face_normals=True)],
                           device=suite_device)
    renderer = hlbvh_cl.Renderer(scene, materials=[{"type": "diffuse", "reflectance": 1.0}],
                                 emitters=[{"type": "area", "mesh": 0, "radiance": 1.0}])
    camera = hlbvh_cl.Camera(eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), fov_deg=50)
    reserved = []  # what each render reserves, by buffer (Runtime.check_allocation)
    check = type(built.runtime(scene)).check_allocation
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(type(built.runtime(scene)), "check_allocation",
                      lambda rt, what, buffers: (reserved.append(buffers),
                                                 check(rt, what, buffers))[1])
        result = renderer.render(camera, 20, 20, shading="path", hdr=True, aovs=True, spp=16,
                                 seed=3, max_depth=1, rfilter=rfilter)
    # a Gaussian filter splats the AOVs with the radiance: no AOV image of its own
    aov_images = [buffers["AOV image"] for buffers in reserved if "AOV image" in buffers]
    assert aov_images == ([] if rfilter == "gaussian" else [20 * 20 * 7 * 4])
    partial = (result.image[..., 0] > 0.05) & (result.image[..., 0] < 0.95)
    assert partial.sum() >= 8  # the test sees silhouettes
    np.testing.assert_allclose(result.albedo, result.image, atol=1e-6)
    # the normal's mean has the coverage's length at most
    assert (np.linalg.norm(result.normal, axis=-1) <= result.image[..., 0] + 1e-5).all()


def test_aovs_need_the_path_integrator(suite_device):
    s = trimesh.creation.icosphere(subdivisions=1)
    renderer = hlbvh_cl.Renderer(hlbvh_cl.Scene([hlbvh_cl.Mesh(s.vertices, s.faces)],
                                                device=suite_device))
    camera = hlbvh_cl.Camera(eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="aovs=True needs shading='path'"):
        renderer.render(camera, 8, 8, shading="diffuse", aovs=True)
    with pytest.raises(TypeError, match="aovs must be True or False"):
        renderer.render(camera, 8, 8, shading="path", aovs="yes")
    image = renderer.render(camera, 8, 8, shading="path", hdr=True)
    assert isinstance(image, np.ndarray)  # without aovs: the image alone, as before


def test_the_cli_writes_the_aovs_as_exr_channels(tmp_path, suite_device):
    OpenEXR = pytest.importorskip("OpenEXR")
    from hlbvh_cl.cli import main
    from hlbvh_cl.io.exr import read_exr
    scene = tmp_path / "scene.toml"
    (tmp_path / "ball.ply").write_bytes(trimesh.exchange.ply.export_ply(
        trimesh.creation.icosphere(subdivisions=3)))
    scene.write_text('[render]\nwidth = 16\nheight = 16\n[camera]\neye = [0.0, 0.0, 3.0]\ntarget = [0.0, 0.0, 0.0]\n'
                     '[[mesh]]\npath = "ball.ply"\n'
                     'material = { type = "diffuse", reflectance = [0.2, 0.4, 0.6] }\n')
    out = tmp_path / "out.exr"
    assert main(["render", str(scene), "-o", str(out), "--width", "16", "--height", "16",
                 "--shading", "path", "--spp", "1", "--device", suite_device.id]) == 0
    with OpenEXR.File(str(out), separate_channels=True) as image:
        channels = {name: np.asarray(c.pixels, np.float32) for name, c in image.channels().items()}
    assert set(channels) == {"R", "G", "B", "albedo.R", "albedo.G", "albedo.B", "normal.X",
                             "normal.Y", "normal.Z", "depth.T"}
    rgb = read_exr(out)
    np.testing.assert_array_equal(rgb[..., 1], channels["G"])
    hit = channels["depth.T"] > 0
    assert 20 < hit.sum() < 256
    np.testing.assert_allclose(channels["depth.T"][8, 8], 2.0, atol=0.01)  # the ball's front
    np.testing.assert_array_equal(channels["albedo.B"][hit], np.float32(0.6))
    normal = np.stack([channels[f"normal.{k}"] for k in "XYZ"], -1)
    np.testing.assert_allclose(np.linalg.norm(normal[hit], axis=-1), 1.0, atol=1e-5)
    assert not normal[~hit].any() and not channels["albedo.R"][~hit].any()
