"""Shading normals (hlbvh_cl.Mesh.normals, kernels/render/integrators/path.cl)
against Mitsuba 3: its computed vertex normals (angle-weighted), checked
against a float64 loop of the formula and against Mitsuba's own mesh; and
a low-poly sphere's render, smooth from the file's normals or computed ones,
against Mitsuba's render of the same PLY, while face normals visibly differ."""
from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

import hlbvh_cl
from hlbvh_cl.mesh import vertex_normals

SEEDS = 4


def lumpy_sphere(seed=3) -> trimesh.Trimesh:
    """A low-poly sphere (80 faces), squashed and jittered so that the
    angle weights matter: its computed normals are not the radial ones."""
    s = trimesh.creation.icosphere(subdivisions=1)
    rng = np.random.default_rng(seed)
    vertices = s.vertices * [1.0, 0.8, 1.1] + rng.normal(0.0, 0.04, s.vertices.shape)
    return trimesh.Trimesh(vertices, s.faces, process=False)


def oracle_normals(vertices, faces) -> np.ndarray:
    """Mitsuba's Mesh::recompute_vertex_normals in float64, one corner at a
    time: each face's unit normal weighted by the corner's angle, summed and
    normalised ((1, 0, 0) where nothing was added)."""
    v = np.asarray(vertices, np.float64)
    total = np.zeros_like(v)
    for face in faces:
        p = v[face]
        n = np.cross(p[1] - p[0], p[2] - p[0])
        if not np.linalg.norm(n) > 0:
            continue
        n /= np.linalg.norm(n)
        for k in range(3):
            a = p[(k + 1) % 3] - p[k]
            b = p[(k + 2) % 3] - p[k]
            cosine = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
            total[face[k]] += n * math.acos(min(1.0, max(-1.0, cosine)))
    length = np.linalg.norm(total, axis=1)
    out = np.tile([1.0, 0.0, 0.0], (len(v), 1))
    out[length > 0] = total[length > 0] / length[length > 0, None]
    return out


def test_computed_vertex_normals_follow_mitsuba_s_formula(tmp_path):
    s = lumpy_sphere()
    # a zero-area triangle adds nothing, and an unused vertex gets (1, 0, 0)
    vertices = np.vstack([s.vertices, [[5.0, 5.0, 5.0]]])
    faces = np.vstack([s.faces, [[0, 0, 1]]])
    expected = oracle_normals(vertices, faces)
    np.testing.assert_allclose(vertex_normals(vertices, faces), expected, atol=1e-12)
    mesh = hlbvh_cl.Mesh(vertices, faces)
    assert not mesh.has_file_normals and mesh.normals.dtype == np.float32
    np.testing.assert_allclose(mesh.normals, expected, atol=1e-6)
    # the weights are angles, not areas: a mean weighted by area is another answer
    p = vertices[s.faces]
    area = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    by_area = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(by_area, s.faces[:, k], area)
    by_area = by_area[:-1] / np.linalg.norm(by_area[:-1], axis=1, keepdims=True)
    assert np.abs(by_area - expected[:-1]).max() > 1e-3
    # Mitsuba's own mesh, loaded from a PLY without normals
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    s.export(tmp_path / "lumpy.ply")
    shape = mi.load_dict({"type": "ply", "filename": str(tmp_path / "lumpy.ply")})
    theirs = np.array(mi.traverse(shape)["vertex_normals"]).reshape(-1, 3)
    ours = hlbvh_cl.Mesh.load(tmp_path / "lumpy.ply")
    assert theirs.shape == ours.normals.shape
    np.testing.assert_allclose(ours.normals, theirs, atol=2e-6)


def test_normals_come_from_the_file_when_it_has_them(tmp_path):
    s = lumpy_sphere()
    given = s.vertices / np.linalg.norm(s.vertices, axis=1, keepdims=True) * 2.0  # not unit
    for name, data in [
            ("with.ply", trimesh.exchange.ply.export_ply(
                trimesh.Trimesh(s.vertices, s.faces, vertex_normals=given, process=False),
                vertex_normal=True)),
            ("with.obj", trimesh.exchange.obj.export_obj(
                trimesh.Trimesh(s.vertices, s.faces, vertex_normals=given, process=False),
                include_normals=True).encode())]:
        (tmp_path / name).write_bytes(data)
        mesh = hlbvh_cl.Mesh.load(tmp_path / name)
        assert mesh.has_file_normals, name
        # normalised, as Mitsuba's loaders normalise them (a file's lengths
        # had weighed the interpolation)
        np.testing.assert_allclose(mesh.normals, given / 2.0, atol=1e-6, err_msg=name)
    (tmp_path / "without.ply").write_bytes(trimesh.exchange.ply.export_ply(s, vertex_normal=False))
    mesh = hlbvh_cl.Mesh.load(tmp_path / "without.ply")
    assert not mesh.has_file_normals
    np.testing.assert_allclose(mesh.normals, oracle_normals(s.vertices, s.faces), atol=1e-6)
    with pytest.raises(ValueError, match=r"normals has shape \(2, 3\), expected \(42, 3\)"):
        hlbvh_cl.Mesh(s.vertices, s.faces, normals=[[0, 0, 1], [0, 1, 0]])
    with pytest.raises(ValueError, match=r"normals\[1\] = \[0.0, 0.0, 0.0\] is not a finite"):
        hlbvh_cl.Mesh(s.vertices, s.faces, normals=np.vstack([given[:1], np.zeros((41, 3))]))


def block_stats(images, block):
    """Per block of pixels: the mean over seeds and pixels, and its
    standard error from the seeds' spread, (rows, cols, 3) each."""
    seeds, height, width, _ = images.shape
    x = images.astype(np.float64).reshape(seeds, height // block, block, width // block, block, 3)
    per_seed = x.mean((2, 4))
    return per_seed.mean(0), per_seed.std(0, ddof=1) / np.sqrt(seeds)


@pytest.mark.parametrize("file_normals", [False, True])
def test_a_smooth_sphere_renders_as_in_mitsuba(file_normals, tmp_path, suite_device):
    """A one-sided diffuse low-poly sphere (80 faces) under a directional
    light, its PLY with or without vertex normals: Mitsuba 3
    (scalar_rgb) and ours agree per 4 x 4 block within 5 combined standard
    errors; the same sphere with face normals differs from Mitsuba's smooth
    one by many more."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    s = lumpy_sphere()
    given = None
    if file_normals:  # the radial directions, unlike the computed ones
        given = s.vertices / np.linalg.norm(s.vertices, axis=1, keepdims=True)
    ply = tmp_path / "sphere.ply"
    ply.write_bytes(trimesh.exchange.ply.export_ply(
        trimesh.Trimesh(s.vertices, s.faces, vertex_normals=given, process=False),
        vertex_normal=file_normals))
    width = height = 32
    spp, depth = 16, 3
    eye, target, fov = (0.4, 0.9, 3.2), (0.0, 0.0, 0.0), 45.0
    sun = {"direction": [-0.4, -1.0, -0.6], "irradiance": [2.0, 1.8, 1.5]}
    described = {
        "type": "scene", "integrator": {"type": "path", "max_depth": depth},
        "sensor": {"type": "perspective", "fov": fov, "fov_axis": "y",
                   "to_world": mi.ScalarTransform4f().look_at(origin=list(eye),
                                                              target=list(target), up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": width, "height": height,
                            "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "sun": {"type": "directional", "direction": sun["direction"],
                "irradiance": {"type": "rgb", "value": sun["irradiance"]}},
        "ball": {"type": "ply", "filename": str(ply),
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb",
                                                             "value": [0.7, 0.6, 0.5]}}}}
    theirs = np.stack([np.asarray(mi.render(mi.load_dict(described), seed=seed))[..., :3]
                       for seed in range(SEEDS)])
    loaded = hlbvh_cl.Mesh.load(ply)
    assert loaded.has_file_normals == file_normals

    def ours_with(mesh):
        renderer = hlbvh_cl.Renderer(
            hlbvh_cl.Scene([mesh], device=suite_device),
            materials=[{"type": "diffuse", "reflectance": [0.7, 0.6, 0.5]}],
            emitters=[{"type": "directional", **sun}])
        camera = hlbvh_cl.Camera(eye=eye, target=target, fov_deg=fov)
        return np.stack([renderer.render(camera, width, height, shading="path", hdr=True,
                                         spp=spp, max_depth=depth, seed=seed)
                         for seed in range(1, SEEDS + 1)])
    smooth = ours_with(loaded)
    flat = ours_with(hlbvh_cl.Mesh(loaded.vertices, loaded.faces, face_normals=True))
    mean_t, err_t = block_stats(theirs, 4)
    mean_s, err_s = block_stats(smooth, 4)
    mean_f, err_f = block_stats(flat, 4)
    bound = 5 * np.hypot(err_t, err_s) + 0.01 * mean_t + 1e-6
    assert (np.abs(mean_s - mean_t) <= bound).all(), (
        f"blocks off: {np.argwhere((np.abs(mean_s - mean_t) > bound).any(-1)).tolist()}, "
        f"worst {np.abs(mean_s - mean_t).max()}")
    # can fail: face normals are another picture, far beyond the errors in
    # many pixels (per block, the facets would average out)
    mean_t, err_t = block_stats(theirs, 1)
    lit = mean_t.sum(-1) > 0.05
    for ours, flat_ones in ((smooth, False), (flat, True)):
        mean_o, err_o = block_stats(ours, 1)
        off = (np.abs(mean_o - mean_t) > 5 * np.hypot(err_t, err_o) + 0.01 * mean_t).any(-1)
        share = off[lit].mean()
        assert (share > 0.2) if flat_ones else (share < 0.02), (flat_ones, share)


def test_normals_of_any_magnitude_shade_alike(suite_device):
    """Vertex normals need not be unit (Mesh.normals): scaled by 2^70 or
    2^-80 (exactly, in float32), a mesh's, an emitting mesh's and an
    instance's normal map (an instance scaled by 2^-70) give the unit
    normals' image bit for bit, where their squared lengths had left
    float32's range and the surfaces rendered black."""
    s = lumpy_sphere()
    vertices, faces = np.asarray(s.vertices, np.float32), np.asarray(s.faces)
    normals = vertex_normals(vertices, faces).astype(np.float32)
    lamp = trimesh.creation.icosphere(subdivisions=1)
    lamp_vertices = (np.asarray(lamp.vertices) * 0.3 + [0.0, 2.0, 1.0]).astype(np.float32)
    lamp_normals = vertex_normals(lamp_vertices, np.asarray(lamp.faces)).astype(np.float32)
    camera = hlbvh_cl.Camera(eye=(0.3, 0.4, 3.2), target=(0, 0, 0), fov_deg=40)
    emitters = [{"type": "area", "mesh": 1, "radiance": 4.0},
                {"type": "constant", "radiance": 0.2}]
    materials = [{"type": "roughplastic", "alpha": 0.2}, {"type": "diffuse"}]

    def render(scale, instance_scale=1.0):
        meshes = [hlbvh_cl.Mesh(vertices, faces, normals=normals * np.float32(scale)),
                  hlbvh_cl.Mesh(lamp_vertices, lamp.faces,
                                normals=lamp_normals * np.float32(scale))]
        maps = [(k, np.hstack([np.eye(3) * instance_scale, np.zeros((3, 1))])) for k in (0, 1)]
        scene = hlbvh_cl.Scene(meshes, device=suite_device,
                               instances=None if instance_scale == 1.0 else maps)
        eye = np.asarray(camera.eye) * instance_scale
        view = hlbvh_cl.Camera(eye=eye, target=(0, 0, 0), fov_deg=40)
        return hlbvh_cl.Renderer(scene, materials=materials, emitters=emitters).render(
            view, 24, 18, shading="path", spp=4, max_depth=4, hdr=True)

    unit = render(1.0)
    assert unit.mean() > 0.05
    for scale in (2.0 ** 70, 2.0 ** -80):
        np.testing.assert_array_equal(render(scale), unit, err_msg=f"normals x {scale:g}")
    # an instance's map is the inverse transpose: 2^70 here; against a scale
    # it steadies as it is (2^-8), up to how the paths' bits differ
    small, near = render(1.0, instance_scale=2.0 ** -70), render(1.0, instance_scale=2.0 ** -8)
    assert abs(small.mean() - near.mean()) < 0.005 and np.abs(small - near).max() < 0.05
