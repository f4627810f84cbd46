"""Rays that are already on the device (pyopencl arrays) and results that
stay there (issue 57; hlbvh_cl/query/on_device.py): the same answers as the
numpy queries, which tests/query/test_rays.py checks against brute force,
bit for bit; checks made on the device that name a bad ray as the numpy
queries do; one wait per call."""
from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import pytest

import hlbvh_cl
from hlbvh_cl import Mesh
from oracle import brute_force_intersect
from shapes import grid_mesh


def sphere_rays(rng, count: int, radius: float = 2.0):
    """Rays from a sphere around the unit cube towards points inside it."""
    origins = rng.normal(size=(count, 3))
    origins *= radius / np.linalg.norm(origins, axis=1, keepdims=True)
    origins += 0.5
    directions = rng.uniform(0.0, 1.0, (count, 3)) - origins
    return origins.astype(np.float32), directions.astype(np.float32)


def assert_same_hits(on_device, on_host):
    for name, expected in vars(on_host).items():
        got = getattr(on_device, name)
        assert isinstance(got, cla.Array), name
        np.testing.assert_array_equal(got.get(), expected, err_msg=name)


@pytest.fixture(scope="module")
def two_meshes():
    rng = np.random.default_rng(3)
    soup = Mesh(rng.uniform(0, 1, (600, 3)), np.arange(600).reshape(200, 3))
    return [grid_mesh(12), soup]


def test_rays_on_the_device_hit_as_numpy_rays_do(suite_device, two_meshes):
    """More rays than one launch takes, in an image's (H, W, 3) shape, with
    limits given once and per ray on the device; the answers are the numpy
    queries' and, on a sample, brute force's."""
    scene = hlbvh_cl.Scene(two_meshes, device=suite_device)
    origins, directions = sphere_rays(np.random.default_rng(1), 150_000)
    origins, directions = origins.reshape(300, 500, 3), directions.reshape(300, 500, 3)
    tmax = np.random.default_rng(2).uniform(0.5, 3.0, (300, 500)).astype(np.float32)
    q = scene.queue
    o, d, t = (cla.to_device(q, a) for a in (origins, directions, tmax))
    unlimited = None
    for limits in ({}, {"tmin": 0.25, "tmax": 2.0}, {"tmax": t}):
        host = {k: (v.get() if isinstance(v, cla.Array) else v) for k, v in limits.items()}
        hits = scene.intersect(o, d, **limits)
        expected = scene.intersect(origins, directions, **host)
        assert hits.t.shape == (300, 500) and hits.normal.shape == (300, 500, 3)
        assert_same_hits(hits, expected)
        unlimited = unlimited if limits else hits
        occluded = scene.occluded(o, d, **limits)
        assert occluded.dtype == bool
        np.testing.assert_array_equal(occluded.get(), scene.occluded(origins, directions, **host))
    vertices = np.concatenate([m.vertices for m in two_meshes])
    faces = np.concatenate([two_meshes[0].faces, two_meshes[1].faces + len(two_meshes[0].vertices)])
    sample = slice(0, 500)
    brute = brute_force_intersect(vertices, faces, origins[0][sample], directions[0][sample])
    np.testing.assert_allclose(unlimited.t.get()[0][sample], brute["t"], rtol=1e-5)


def test_instanced_scenes_and_masks_on_the_device(suite_device, two_meshes):
    maps = [np.eye(3, 4), np.hstack([np.eye(3), [[1.5], [0.0], [0.0]]])]
    scene = hlbvh_cl.Scene(two_meshes, device=suite_device, instances=[(0, maps[0]), (1, maps[1])],
                           masks=[1, 2])
    origins, directions = sphere_rays(np.random.default_rng(4), 5_000, radius=3.0)
    o, d = cla.to_device(scene.queue, origins), cla.to_device(scene.queue, directions)
    for mask in (None, 1, 2, 0):
        assert_same_hits(scene.intersect(o, d, mask=mask),
                         scene.intersect(origins, directions, mask=mask))
    flat = hlbvh_cl.Scene(two_meshes, device=suite_device)
    blind = flat.intersect(cla.to_device(flat.queue, origins), cla.to_device(flat.queue, directions),
                           mask=0)
    assert (blind.geom_id.get() == -1).all() and np.isinf(blind.t.get()).all()


def test_a_scene_in_a_scaled_frame_gives_the_same_hits(suite_device):
    """A tiny scene's tree is built in a scaled frame (hlbvh_cl.core.frame):
    rays on the device are traced from the host there, same answers."""
    tiny = grid_mesh(6)
    tiny = Mesh(tiny.vertices * 1e-9, tiny.faces)
    scene = hlbvh_cl.Scene([tiny], device=suite_device)
    origins, directions = sphere_rays(np.random.default_rng(5), 2_000)
    origins *= np.float32(1e-9)
    hits = scene.intersect(cla.to_device(scene.queue, origins),
                           cla.to_device(scene.queue, directions))
    expected = scene.intersect(origins, directions)
    assert expected.hit.sum() > 100
    assert_same_hits(hits, expected)


def test_camera_rays_made_on_the_device(suite_device, meshes):
    scene = hlbvh_cl.Scene([meshes["bunny"]], device=suite_device)
    camera = hlbvh_cl.Camera(eye=(0, 0.1, 0.4), target=(0, 0.1, 0))
    origins, directions = camera.rays(64, 48, scene=scene)
    assert isinstance(origins, cla.Array) and origins.shape == (64 * 48, 3)
    host = camera.rays(64, 48)
    np.testing.assert_array_equal(origins.get(), host[0])
    # OpenCL's division may round an ulp away from numpy's
    np.testing.assert_array_max_ulp(directions.get(), host[1], maxulp=1)
    hits = scene.intersect(origins, directions)
    assert hits.hit.dtype == bool
    np.testing.assert_array_equal(hits.hit.get(), scene.intersect(*host).hit)
    assert hits.hit.get().sum() > 200


def test_bad_rays_on_the_device_are_named(suite_device):
    scene = hlbvh_cl.Scene([grid_mesh(4)], device=suite_device)
    q = scene.queue
    origins = np.zeros((4, 5, 3), np.float32)
    directions = np.ones((4, 5, 3), np.float32)
    bad = origins.copy()
    bad[2, 3, 1] = np.nan
    with pytest.raises(ValueError, match=r"origins\[2, 3\] = .* is not finite"):
        scene.intersect(cla.to_device(q, bad), cla.to_device(q, directions))
    short = directions.copy()
    short[1, 4] = 0.0
    with pytest.raises(ValueError, match=r"directions\[1, 4\]"):
        scene.occluded(cla.to_device(q, origins), cla.to_device(q, short))
    tmin = np.zeros((4, 5), np.float32)
    tmin[3, 0] = -1.0
    with pytest.raises(ValueError, match=r"tmin\[.*\] = -1.0 must be finite and >= 0"):
        scene.intersect(cla.to_device(q, origins), cla.to_device(q, directions),
                        tmin=cla.to_device(q, tmin))
    with pytest.raises(ValueError, match="is greater than tmax"):
        scene.intersect(cla.to_device(q, origins), cla.to_device(q, directions), tmin=2.0,
                        tmax=cla.to_device(q, np.ones((4, 5), np.float32)))
    o, d = cla.to_device(q, origins), cla.to_device(q, directions)
    with pytest.raises(TypeError, match=r"origins is a pyopencl array of float64; .*astype"):
        scene.intersect(cla.to_device(q, origins.astype(np.float64)), d)
    with pytest.raises(TypeError, match="directions is not a pyopencl array"):
        scene.intersect(o, directions)
    with pytest.raises(TypeError, match="directions is missing"):
        scene.intersect(o)
    with pytest.raises(ValueError, match=r"directions must have shape \(\.\.\., 3\)"):
        scene.intersect(o, cla.to_device(q, directions.reshape(20, 3)))
    with pytest.raises(ValueError, match="tmax must have the rays' leading shape"):
        scene.intersect(o, d, tmax=cla.to_device(q, np.ones(20, np.float32)))
    with pytest.raises(TypeError, match="mask is a pyopencl array"):
        scene.intersect(o, d, mask=cla.to_device(q, np.ones((4, 5), np.uint32)))
    context = cl.Context([q.device])  # kept: Intel's runtime drops a context nothing holds
    other = cl.CommandQueue(context)
    with pytest.raises(ValueError, match="another OpenCL context"):
        scene.intersect(cla.to_device(other, origins), cla.to_device(other, directions))
    # the checks of the device set nothing that stays: a good call then passes
    assert scene.intersect(o, d).t.shape == (4, 5)


def test_a_view_at_an_offset_is_taken(suite_device):
    scene = hlbvh_cl.Scene([grid_mesh(4)], device=suite_device)
    origins, directions = sphere_rays(np.random.default_rng(6), 100)
    o = cla.to_device(scene.queue, origins)[10:]
    d = cla.to_device(scene.queue, directions)[10:]
    assert o.offset
    assert_same_hits(scene.intersect(o, d), scene.intersect(origins[10:], directions[10:]))


def test_points_on_the_device_give_the_numpy_answers(suite_device, meshes):
    """closest_points, signed_distance, winding_number and contains of
    points given as a pyopencl array, in more launches than one, flat and
    instanced: the numpy queries' answers (winding numbers up to the order
    of their sums)."""
    bunny = meshes["bunny"]
    lo, hi = bunny.vertices.min(axis=0), bunny.vertices.max(axis=0)
    rng = np.random.default_rng(7)
    points = (lo + rng.uniform(-0.2, 1.2, (40_000, 3)) * (hi - lo)).astype(np.float32)
    points = points.reshape(200, 200, 3)
    shifted = np.hstack([np.eye(3), (hi - lo)[:, None] * 0.3])
    for scene in (hlbvh_cl.Scene([bunny], device=suite_device),
                  hlbvh_cl.Scene([bunny], device=suite_device,
                                 instances=[(0, np.eye(3, 4)), (0, shifted)])):
        on_device = cla.to_device(scene.queue, points)
        found, expected = scene.closest_points(on_device, 0.02), scene.closest_points(points, 0.02)
        assert found.distance.shape == (200, 200) and found.found.dtype == bool
        for name, value in vars(expected).items():
            np.testing.assert_array_equal(getattr(found, name).get(), value, err_msg=name)
        np.testing.assert_allclose(scene.winding_number(on_device).get(),
                                   scene.winding_number(points), atol=1e-5)
        distance = scene.signed_distance(on_device).get()
        np.testing.assert_allclose(distance, scene.signed_distance(points), rtol=1e-6)
        inside = scene.contains(on_device)
        assert inside.dtype == bool
        np.testing.assert_array_equal(inside.get(), distance < 0)


def test_bad_points_on_the_device_are_named(suite_device):
    scene = hlbvh_cl.Scene([grid_mesh(4)], device=suite_device)
    points = np.zeros((3, 4, 3), np.float32)
    points[1, 2, 0] = np.inf
    with pytest.raises(ValueError, match=r"points\[1, 2\] = .* is not finite"):
        scene.closest_points(cla.to_device(scene.queue, points))
    points[1, 2, 0] = 1e30
    with pytest.raises(ValueError, match=r"points\[1, 2\] = .* is too far from the origin"):
        scene.signed_distance(cla.to_device(scene.queue, points))
    with pytest.raises(TypeError, match="points is a pyopencl array of float64"):
        scene.winding_number(cla.to_device(scene.queue, points.astype(np.float64)))
    with pytest.raises(ValueError, match=r"points must have shape \(\.\.\., 3\)"):
        scene.contains(cla.to_device(scene.queue, np.zeros((4, 2), np.float32)))
    tiny = Mesh(grid_mesh(4).vertices * 1e-9, grid_mesh(4).faces)  # a scaled frame: via the host
    small = hlbvh_cl.Scene([tiny], device=suite_device)
    near = np.random.default_rng(8).uniform(0, 1e-9, (500, 3)).astype(np.float32)
    np.testing.assert_array_equal(
        small.closest_points(cla.to_device(small.queue, near)).distance.get(),
        small.closest_points(near).distance)
