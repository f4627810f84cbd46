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


@pytest.mark.parametrize("query", ["intersect", "occluded", "count_intersections",
                                   "intersect_all"])
def test_bad_ray_values_on_the_device_are_named(suite_device, query):
    """Each ray query's checks made on the device: a bad ray named as the
    numpy queries name it; nothing stays set for the next call."""
    scene = hlbvh_cl.Scene([grid_mesh(4)], device=suite_device)
    call, q = getattr(scene, query), scene.queue
    origins = np.zeros((4, 5, 3), np.float32)
    directions = np.ones((4, 5, 3), np.float32)
    bad = origins.copy()
    bad[2, 3, 1] = np.nan
    with pytest.raises(ValueError, match=r"origins\[2, 3\] = .* is not finite"):
        call(cla.to_device(q, bad), cla.to_device(q, directions))
    short = directions.copy()
    short[1, 4] = 0.0
    with pytest.raises(ValueError, match=r"directions\[1, 4\]"):
        call(cla.to_device(q, origins), cla.to_device(q, short))
    tmin = np.zeros((4, 5), np.float32)
    tmin[3, 0] = -1.0
    with pytest.raises(ValueError, match=r"tmin\[3, 0\] = -1.0 must be finite and >= 0"):
        call(cla.to_device(q, origins), cla.to_device(q, directions),
             tmin=cla.to_device(q, tmin))
    with pytest.raises(ValueError, match="is greater than tmax"):
        call(cla.to_device(q, origins), cla.to_device(q, directions), tmin=2.0,
             tmax=cla.to_device(q, np.ones((4, 5), np.float32)))
    result = call(cla.to_device(q, origins), cla.to_device(q, directions))
    assert (result.counts if query == "intersect_all" else
            getattr(result, "t", result)).shape == (4, 5)


def test_bad_ray_arrays_on_the_device_are_named(suite_device):
    scene = hlbvh_cl.Scene([grid_mesh(4)], device=suite_device)
    q = scene.queue
    origins = np.zeros((4, 5, 3), np.float32)
    directions = np.ones((4, 5, 3), np.float32)
    o, d = cla.to_device(q, origins), cla.to_device(q, directions)
    with pytest.raises(TypeError, match=r"origins is a pyopencl array of float64; .*astype"):
        scene.intersect(cla.to_device(q, origins.astype(np.float64)), d)
    with pytest.raises(TypeError, match="directions is not a pyopencl array"):
        scene.intersect(o, directions)
    with pytest.raises(TypeError, match="directions is missing"):
        scene.intersect(o)
    with pytest.raises(ValueError, match=r"directions must have the shape of origins "
                                         r"\(4, 5, 3\), got \(20, 3\)"):
        scene.intersect(o, cla.to_device(q, directions.reshape(20, 3)))
    four = cla.to_device(q, np.zeros((2, 4), np.float32))
    with pytest.raises(ValueError, match=r"^origins must have shape \(\.\.\., 3\), got \(2, 4\)$"):
        scene.intersect(four, four)
    with pytest.raises(ValueError, match=r"^rays must have shape \(\.\.\., 6\): origin then "
                                         r"direction, got \(2, 5\)"):
        scene.intersect(cla.to_device(q, np.zeros((2, 5), np.float32)))
    with pytest.raises(ValueError, match="tmax must have the rays' leading shape"):
        scene.intersect(o, d, tmax=cla.to_device(q, np.ones(20, np.float32)))
    with pytest.raises(TypeError, match=r"mask is a pyopencl array of int32; masks on the "
                                        r"device must be uint32 .*astype"):
        scene.intersect(o, d, mask=cla.to_device(q, np.ones((4, 5), np.int32)))
    with pytest.raises(ValueError, match="mask must have the rays' leading shape"):
        scene.occluded(o, d, mask=cla.to_device(q, np.ones(20, np.uint32)))
    with pytest.raises(TypeError, match="mask is a host array while the rays are pyopencl"):
        scene.intersect(o, d, mask=np.ones((4, 5), np.uint32))
    with pytest.raises(TypeError, match="tmax is a host array while the rays are pyopencl"):
        scene.occluded(o, d, tmax=[[1.0] * 5] * 4)
    with pytest.raises(TypeError, match="origins is not a pyopencl array while another"):
        scene.intersect(origins, directions, mask=cla.to_device(q, np.ones((4, 5), np.uint32)))
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


def test_inputs_still_being_written_are_waited_for(suite_device):
    """Rays and points whose data was still on its way (an upload on another
    queue of the scene's context, or one recorded in Array.events, held back
    here by a user event) were traced as they were: a silent wrong answer.
    A query now waits for what writes its inputs; arrays of no queue are
    taken too (an offset view of one failed in pyopencl's copy, a bare
    AssertionError)."""
    import threading
    scene = hlbvh_cl.Scene([grid_mesh(8)], device=suite_device)
    origins, directions = sphere_rays(np.random.default_rng(7), 500)
    expected = scene.intersect(origins, directions)
    expected_points = scene.closest_points(origins).distance
    other = cl.CommandQueue(scene.queue.context)

    uploads = []

    def hold_back(array, values, record: bool):
        """``values`` into ``array`` by an upload on the other queue that
        waits 0.3 s for a user event, recorded in the array's events where
        ``record``.  Nothing may block holding the GIL from the timer until
        then: every array is made before, and the upload's event is kept
        (pyopencl's event of a host copy waits for it when dropped)."""
        go = cl.UserEvent(scene.queue.context)
        uploads.append(cl.enqueue_copy(other, array.data, values, wait_for=[go],
                                       is_blocking=False))
        if record:
            array.add_event(uploads[-1])
        threading.Timer(0.3, lambda: go.set_status(cl.command_execution_status.COMPLETE)).start()
        return array

    directions_there = cla.to_device(scene.queue, directions)
    for queue, record in ((other, False), (scene.queue, True)):
        arrays = [cla.to_device(queue, np.zeros_like(origins)) for _ in range(2)]
        queue.finish()
        hits = scene.intersect(hold_back(arrays[0], origins, record), directions_there)
        np.testing.assert_array_equal(hits.t.get(), expected.t)
        found = scene.closest_points(hold_back(arrays[1], origins, record))
        np.testing.assert_array_equal(found.distance.get(), expected_points)
        other.finish()
    no_queue = cla.to_device(scene.queue, np.vstack([origins[:5], origins])).with_queue(None)
    got = scene.intersect(no_queue[5:], cla.to_device(scene.queue, directions).with_queue(None))
    np.testing.assert_array_equal(got.t.get(), expected.t)


def test_one_ray_or_point_on_the_device_gives_0d_answers(suite_device):
    """A single ray (3,) + (3,) or packed (6,), and a single point (3,), on
    the device: 0-d results, as the numpy queries give (pyopencl reshapes
    and views no 0-d array as numpy does)."""
    scene = hlbvh_cl.Scene([grid_mesh(4)], device=suite_device)
    q = scene.queue
    origin, direction = np.float32([0.3, 0.4, 2.0]), np.float32([0.0, 0.0, -1.0])
    o, d = cla.to_device(q, origin), cla.to_device(q, direction)
    packed = cla.to_device(q, np.concatenate([origin, direction]))
    assert_same_hits(scene.intersect(o, d), scene.intersect(origin, direction))
    for got in (scene.occluded(o, d), scene.occluded(packed)):
        assert got.shape == () and got.dtype == bool
        assert bool(got.get()) == bool(scene.occluded(origin, direction))
    point = np.float32([0.3, 0.4, 0.25])
    on_device = cla.to_device(q, point)
    found, expected = scene.closest_points(on_device), scene.closest_points(point)
    for name, value in vars(expected).items():
        assert getattr(found, name).shape == np.shape(value), name
        np.testing.assert_array_equal(getattr(found, name).get(), value, err_msg=name)
    for query in ("signed_distance", "winding_number"):
        got = getattr(scene, query)(on_device)
        assert got.shape == ()
        np.testing.assert_allclose(got.get(), getattr(scene, query)(point), atol=1e-6)


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
    with pytest.raises(TypeError, match="points is a pyopencl array of float64; points on the "
                                        "device must be float32"):
        scene.winding_number(cla.to_device(scene.queue, points.astype(np.float64)))
    with pytest.raises(ValueError, match=r"points must have shape \(\.\.\., 3\)"):
        scene.contains(cla.to_device(scene.queue, np.zeros((4, 2), np.float32)))
    tiny = Mesh(grid_mesh(4).vertices * 1e-9, grid_mesh(4).faces)  # a scaled frame: via the host
    small = hlbvh_cl.Scene([tiny], device=suite_device)
    near = np.random.default_rng(8).uniform(0, 1e-9, (500, 3)).astype(np.float32)
    np.testing.assert_array_equal(
        small.closest_points(cla.to_device(small.queue, near)).distance.get(),
        small.closest_points(near).distance)


def assert_same_all_hits(on_device, on_host, what=""):
    assert on_device.shape == on_host.shape, what
    for name, expected in vars(on_host).items():
        if name != "shape":
            got = getattr(on_device, name)
            assert isinstance(got, cla.Array), (what, name)
            np.testing.assert_array_equal(got.get(), expected, err_msg=f"{what} {name}")
    np.testing.assert_array_equal(on_device.counts.get(), on_host.counts, err_msg=what)


@pytest.fixture(scope="module")
def stacked():
    """The two meshes and stacked plates: rays through them have more hits
    than the count pass keeps (the fill pass walks again) and fewer."""
    from all_hits_cases import plates
    from hlbvh_cl.query.all_hits import KEEP_HITS
    return plates(KEEP_HITS + 3)


def test_all_hits_and_counts_on_the_device_are_the_numpy_ones(suite_device, stacked):
    """count_intersections and intersect_all of rays on the device, in an
    (H, W) shape and in launches of a few packets at global offsets, with
    limits given once and per ray there, every hit and the first k: the
    numpy queries' answers bit for bit, and the float64 brute force's
    counts where float32 cannot decide otherwise."""
    from all_hits_cases import EDGE_TOLERANCE
    from oracle import brute_force_all_hits
    from hlbvh_cl.query.all_hits import AllHitsQuery, wide_count_packets
    from hlbvh_cl.query.rays import RayQuery
    import built
    scene = hlbvh_cl.Scene([stacked], device=suite_device)
    rng = np.random.default_rng(11)
    origins = np.column_stack([rng.uniform(-1.2, 1.2, (600, 2)), np.full(600, -0.5)])
    directions = np.column_stack([rng.uniform(-0.1, 0.1, (600, 2)), np.ones(600)])
    origins, directions = (a.astype(np.float32).reshape(20, 30, 3) for a in (origins,
                                                                             directions))
    tmax = rng.uniform(0.0, 13.0, (20, 30)).astype(np.float32)
    q = scene.queue
    o, d, t = (cla.to_device(q, a) for a in (origins, directions, tmax))
    query = RayQuery(built.runtime(scene))
    query.max_rays_per_launch = 48  # a few packets per launch, at global offsets
    all_hits, tree = AllHitsQuery(query, wide_count_packets(query)), built.tree(scene)
    for limits in ({}, {"tmin": 2.5, "tmax": 9.0}, {"tmax": t}):
        host = {k: (v.get() if isinstance(v, cla.Array) else v) for k, v in limits.items()}
        counts = all_hits.count(tree, o, d, **limits)
        expected = all_hits.count(tree, origins, directions, **host)
        assert isinstance(counts, cla.Array) and counts.shape == (20, 30)
        np.testing.assert_array_equal(counts.get(), expected)
        for max_hits in (None, 1, 3):
            assert_same_all_hits(all_hits.intersect_all(tree, o, d, max_hits=max_hits, **limits),
                                 all_hits.intersect_all(tree, origins, directions,
                                                        max_hits=max_hits, **host),
                                 f"{limits} {max_hits}")
    want = brute_force_all_hits(stacked.vertices, stacked.faces, origins.reshape(-1, 3),
                                directions.reshape(-1, 3), 0.0, tmax.reshape(-1))
    clear = want["margin"] > EDGE_TOLERANCE
    assert clear.sum() > 400
    from hlbvh_cl.query.all_hits import KEEP_HITS
    found = scene.count_intersections(o, d, tmax=t).get().reshape(-1)
    np.testing.assert_array_equal(found[clear], np.diff(want["offsets"])[clear])
    assert (found > KEEP_HITS).sum() > 20 and ((found > 0) & (found <= KEEP_HITS)).sum() > 20


def test_masks_per_ray_on_the_device(suite_device, two_meshes):
    """A uint32 pyopencl array of masks, one per ray: every ray query gives
    the numpy queries' answers to the same masks given as a numpy array,
    flat (where a ray of mask 0 sees nothing) and instanced with masks."""
    maps = [np.eye(3, 4), np.hstack([np.eye(3), [[1.5], [0.0], [0.0]]])]
    origins, directions = sphere_rays(np.random.default_rng(12), 4_000, radius=3.0)
    masks = np.random.default_rng(13).integers(0, 4, 4_000).astype(np.uint32)
    masks[:4] = [0, 1, 2, 3]
    for scene in (hlbvh_cl.Scene(two_meshes, device=suite_device),
                  hlbvh_cl.Scene(two_meshes, device=suite_device,
                                 instances=[(0, maps[0]), (1, maps[1])], masks=[1, 2])):
        q = scene.queue
        o, d, m = (cla.to_device(q, a) for a in (origins, directions, masks))
        assert_same_hits(scene.intersect(o, d, mask=m), scene.intersect(origins, directions,
                                                                         mask=masks))
        np.testing.assert_array_equal(scene.occluded(o, d, mask=m).get(),
                                      scene.occluded(origins, directions, mask=masks))
        counts = scene.count_intersections(o, d, mask=m).get()
        np.testing.assert_array_equal(counts, scene.count_intersections(origins, directions,
                                                                        mask=masks))
        assert_same_all_hits(scene.intersect_all(o, d, mask=m, tmax=2.5),
                             scene.intersect_all(origins, directions, mask=masks, tmax=2.5))
        # the rays of mask 0 see nothing; the others of mask 3 what unmasked rays see
        unmasked = scene.count_intersections(origins, directions)
        assert (counts[masks == 0] == 0).all() and unmasked[masks == 0].sum() > 100
        np.testing.assert_array_equal(counts[masks == 3], unmasked[masks == 3])


def test_packed_rays_on_the_device(suite_device, two_meshes):
    """Open3D's (..., 6) rays as one pyopencl array: the answers of the same
    rays given as two arrays; a bad one named as the numpy queries name it."""
    scene = hlbvh_cl.Scene(two_meshes, device=suite_device)
    origins, directions = sphere_rays(np.random.default_rng(14), 3_000)
    packed = np.concatenate([origins, directions], axis=1).reshape(30, 100, 6)
    rays = cla.to_device(scene.queue, packed)
    apart = origins.reshape(30, 100, 3), directions.reshape(30, 100, 3)
    assert_same_hits(scene.intersect(rays, tmax=2.0), scene.intersect(*apart, tmax=2.0))
    np.testing.assert_array_equal(scene.occluded(rays).get(), scene.occluded(*apart))
    np.testing.assert_array_equal(scene.count_intersections(rays).get(),
                                  scene.count_intersections(*apart))
    assert_same_all_hits(scene.intersect_all(rays, max_hits=2),
                         scene.intersect_all(*apart, max_hits=2))
    packed[1, 2, 4] = np.inf
    with pytest.raises(ValueError, match=r"rays\[1, 2\]\[3:6\] = .* is not finite"):
        scene.intersect_all(cla.to_device(scene.queue, packed))
    with pytest.raises(TypeError, match="rays is a pyopencl array of float64"):
        scene.count_intersections(cla.to_device(scene.queue, packed.astype(np.float64)))


def test_bad_arguments_for_all_hits_on_the_device_are_named(suite_device):
    scene = hlbvh_cl.Scene([grid_mesh(4)], device=suite_device)
    q = scene.queue
    o, d = (cla.to_device(q, np.ones((4, 5, 3), np.float32)) for _ in range(2))
    with pytest.raises(TypeError, match="directions is not a pyopencl array while another"):
        scene.intersect_all(o, np.ones((4, 5, 3), np.float32))
    with pytest.raises(TypeError, match="mask is a pyopencl array of int64"):
        scene.count_intersections(o, d, mask=cla.to_device(q, np.ones((4, 5), np.int64)))
    with pytest.raises(ValueError, match="max_hits"):
        scene.intersect_all(o, d, max_hits=0)


def test_all_hits_on_the_device_of_no_rays_and_no_hits(suite_device):
    scene = hlbvh_cl.Scene([grid_mesh(4)], device=suite_device)
    q = scene.queue
    empty = cla.to_device(q, np.zeros((0, 3), np.float32))
    none = scene.intersect_all(empty, empty)
    assert none.offsets.get().tolist() == [0] and len(none) == 0
    assert scene.count_intersections(empty, empty).shape == (0,)
    away = cla.to_device(q, np.tile(np.float32([1, 0, 0]), (7, 1)))
    origins = cla.to_device(q, np.tile(np.float32([10, 10, 10]), (7, 1)))
    missed = scene.intersect_all(origins, away)
    assert len(missed) == 0 and missed.offsets.get().tolist() == [0] * 8
    assert missed.t.dtype == np.float32 and missed.ray_index.dtype == np.int64


def test_all_hits_on_the_device_in_a_scaled_frame_or_past_float32(suite_device):
    """A tiny scene's tree (a scaled frame), and rays whose hits could lie
    past float32's t: counted and filled from the host, same answers."""
    tiny = grid_mesh(6)
    tiny = Mesh(tiny.vertices * 1e-9, tiny.faces)
    scene = hlbvh_cl.Scene([tiny], device=suite_device)
    origins, directions = sphere_rays(np.random.default_rng(15), 2_000)
    origins *= np.float32(1e-9)
    o, d = cla.to_device(scene.queue, origins), cla.to_device(scene.queue, directions)
    expected = scene.intersect_all(origins, directions)
    assert len(expected) > 100
    assert_same_all_hits(scene.intersect_all(o, d), expected)
    np.testing.assert_array_equal(scene.count_intersections(o, d).get(),
                                  scene.count_intersections(origins, directions))
    flat = hlbvh_cl.Scene([grid_mesh(6)], device=suite_device)
    origins = np.tile(np.float32([0.3, 0.4, -1.0]), (40, 1))
    directions = np.tile(np.float32([0.0, 0.0, 1e-30]), (40, 1))
    origins[::2, 2] = -1e9  # a hit at t = 1e39, past float32
    o, d = cla.to_device(flat.queue, origins), cla.to_device(flat.queue, directions)
    counts = flat.count_intersections(o, d).get()
    np.testing.assert_array_equal(counts, flat.count_intersections(origins, directions))
    assert counts.tolist() == [1] * 40
