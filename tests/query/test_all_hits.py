"""Scene.intersect_all and Scene.count_intersections (kernels/query/all_hits.cl)
against the float64 brute force (tests/support/oracle.py), exact crossing counts
through shared edges and vertices of closed meshes, and Open3D's
RaycastingScene on the bunny."""
from __future__ import annotations

import numpy as np
import pyopencl as cl
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hlbvh_cl
import built
from all_hits_cases import assert_matches_brute_force, plates
from ray_cases import SceneCase, cube_mesh, random_rays


def icosphere(subdivisions: int = 2, radius: float = 1.0, name="sphere") -> hlbvh_cl.Mesh:
    trimesh = pytest.importorskip("trimesh")
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return hlbvh_cl.Mesh(sphere.vertices, sphere.faces, name=name)


def grid_box(n: int = 4) -> hlbvh_cl.Mesh:
    """The surface of the cube [0, n]^3, each face an n x n grid of unit
    squares cut into two triangles: a closed mesh with integer vertices."""
    faces, vertices, index = [], [], {}

    def vertex(p):
        key = tuple(p)
        if key not in index:
            index[key] = len(vertices)
            vertices.append(key)
        return index[key]
    for axis in range(3):
        for side in (0, n):
            for i in range(n):
                for j in range(n):
                    quad = []
                    for a, b in ((i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)):
                        p = [0, 0, 0]
                        p[axis], p[(axis + 1) % 3], p[(axis + 2) % 3] = side, a, b
                        quad.append(vertex(p))
                    # alternate the diagonal, so that vertices meet 1 or 2 per square
                    if (i + j) % 2:
                        faces += [[quad[0], quad[1], quad[2]], [quad[0], quad[2], quad[3]]]
                    else:
                        faces += [[quad[0], quad[1], quad[3]], [quad[1], quad[2], quad[3]]]
    return hlbvh_cl.Mesh(np.array(vertices, float), faces, name="grid_box")


def tiny_scene_meshes():
    """A closed sphere over a ground box, two meshes (as the Oclgrind tier)."""
    trimesh = pytest.importorskip("trimesh")
    ground = trimesh.creation.box(extents=(4.0, 0.2, 4.0))
    ground.apply_translation((0.0, -1.2, 0.0))
    return [icosphere(2), hlbvh_cl.Mesh(ground.vertices, ground.faces, name="ground")]


@pytest.fixture(scope="module")
def tiny():
    return SceneCase(tiny_scene_meshes())


def as_the_scene_makes(scene):
    """A RayQuery and the AllHitsQuery over it that ``scene`` would make
    for itself (Scene.intersect_all: count passes in wide_count_packets),
    and the tree they walk: a test may change their settings, as it may not
    the scene's own."""
    from hlbvh_cl.query.all_hits import AllHitsQuery, wide_count_packets
    from hlbvh_cl.query.rays import RayQuery
    query = RayQuery(built.runtime(scene))
    return query, AllHitsQuery(query, wide_count_packets(query)), built.tree(scene)


def recording(monkeypatch, engine) -> list:
    """The Batch of each of ``engine``'s runs (which still run)."""
    batches, run = [], engine.run
    monkeypatch.setattr(engine, "run",
                        lambda batch, launch: batches.append(batch) or run(batch, launch))
    return batches


def test_random_rays_match_brute_force(tiny):
    origins, directions = random_rays(tiny, 600, seed=3)
    compared, got = assert_matches_brute_force(tiny, origins, directions)
    assert compared > 500
    assert (got.counts >= 2).sum() > 100, "the rays should cross the sphere and the ground"
    assert set(np.unique(got.geom_id)) == {0, 1}


@pytest.mark.parametrize("k", [1, 2, 3])
def test_max_hits_gives_the_first_k(tiny, k):
    origins, directions = random_rays(tiny, 400, seed=4)
    every = tiny.scene.intersect_all(origins, directions)
    first = tiny.scene.intersect_all(origins, directions, max_hits=k)
    np.testing.assert_array_equal(first.counts, np.minimum(every.counts, k))
    rank = np.arange(len(every)) - every.offsets[every.ray_index]
    for name in ("t", "u", "v", "prim_id", "geom_id", "ray_index"):
        np.testing.assert_array_equal(getattr(first, name), getattr(every, name)[rank < k], name)
    assert_matches_brute_force(tiny, origins, directions, max_hits=k)


def test_first_hit_is_the_closest_hit(tiny):
    origins, directions = random_rays(tiny, 500, seed=6)
    first = tiny.scene.intersect_all(origins, directions, max_hits=1)
    hits = tiny.scene.intersect(origins, directions)
    np.testing.assert_array_equal(first.counts, hits.hit)
    np.testing.assert_array_equal(first.t, hits.t[hits.hit])


def test_tmin_tmax_windows(tiny):
    origins, directions = random_rays(tiny, 500, seed=7)
    rng = np.random.default_rng(8)
    tmin = rng.uniform(0, 0.6, len(origins)).astype(np.float32)
    tmax = (tmin + rng.uniform(0, 0.8, len(origins))).astype(np.float32)
    compared, got = assert_matches_brute_force(tiny, origins, directions, tmin, tmax)
    assert compared > 400
    every = tiny.scene.intersect_all(origins, directions)
    assert got.counts.sum() < every.counts.sum()
    assert ((got.t >= tmin[got.ray_index]) & (got.t <= tmax[got.ray_index])).all()
    assert_matches_brute_force(tiny, origins, directions, 0.5, 1.5)


def test_rays_that_hit_nothing(tiny):
    origins = np.tile(np.float32([10, 10, 10]), (5, 1))
    directions = np.tile(np.float32([1, 0, 0]), (5, 1))
    got = tiny.scene.intersect_all(origins, directions)
    assert len(got) == 0 and got.offsets.tolist() == [0] * 6
    assert tiny.scene.count_intersections(origins, directions).tolist() == [0] * 5
    empty = tiny.scene.intersect_all(np.zeros((0, 3)), np.zeros((0, 3)))
    assert len(empty) == 0 and empty.offsets.tolist() == [0]
    assert tiny.scene.count_intersections(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)


def test_bad_input_is_named(tiny):
    o, d = np.zeros((2, 3)), np.ones((2, 3))
    for bad, error in ((0, ValueError), (-3, ValueError), (1.5, TypeError), (True, TypeError)):
        with pytest.raises(error, match="max_hits"):
            tiny.scene.intersect_all(o, d, max_hits=bad)
    huge = tiny.scene.intersect_all(o, d, max_hits=2**40)  # more than any ray has
    np.testing.assert_array_equal(huge.counts, tiny.scene.count_intersections(o, d))
    d[1] = 0
    with pytest.raises(ValueError, match=r"directions\[1\]"):
        tiny.scene.intersect_all(o, d)
    with pytest.raises(ValueError, match=r"directions\[1\]"):
        tiny.scene.count_intersections(o, d)


# -- shared edges and vertices: one crossing counts once -------------------------

def through(scene, origins, targets):
    origins = np.asarray(origins, np.float32)
    directions = (np.asarray(targets, np.float64) - origins).astype(np.float32)
    return scene.count_intersections(origins, directions), directions


def test_cube_through_diagonals_and_corners():
    scene = hlbvh_cl.Scene([cube_mesh()])
    # face diagonals' midpoints (the edge two triangles of a face share),
    # corners, and edge midpoints, from outside through the centre
    centre = np.array([0.5, 0.5, 0.5])
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    diagonal_points = []
    for axis in range(3):
        for side in (0.0, 1.0):
            for s in (0.25, 0.5, 0.75):
                for flip in (False, True):
                    p = [0.0, 0.0, 0.0]
                    p[axis], p[(axis + 1) % 3], p[(axis + 2) % 3] = side, s, (1 - s if flip else s)
                    diagonal_points.append(p)
    edge_midpoints = (corners[:, None] + corners[None]) / 2
    edge_midpoints = edge_midpoints.reshape(-1, 3)
    on_edge = (np.sum((edge_midpoints == 0.5), axis=1) == 1)
    targets = np.concatenate([corners, diagonal_points, edge_midpoints[on_edge]])
    origins = centre + 3 * (targets - centre)  # outside, aimed through the target and the centre
    counts, _ = through(scene, origins, targets)
    assert counts.tolist() == [2] * len(targets)
    # from the centre: one crossing each
    counts, _ = through(scene, np.tile(centre, (len(targets), 1)), targets)
    assert counts.tolist() == [1] * len(targets)
    # and the hits of intersect_all are at the entry and the exit
    origins = origins.astype(np.float32)
    got = scene.intersect_all(origins, (targets - origins).astype(np.float32))
    np.testing.assert_allclose(got.t[0::2], 1.0, rtol=1e-5)
    np.testing.assert_allclose(got.t[1::2], 2.0, rtol=1e-5)  # out through c - (target - c)


def test_icosphere_through_vertices_and_edges():
    mesh = icosphere(2)
    scene = hlbvh_cl.Scene([mesh])
    vertices = mesh.vertices.astype(np.float64)
    edges = np.concatenate([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]], mesh.faces[:, [2, 0]]])
    midpoints = vertices[edges].mean(axis=1)
    for targets in (vertices, midpoints):
        counts, _ = through(scene, np.zeros_like(targets), targets)  # from the centre
        assert counts.tolist() == [1] * len(targets)
        rng = np.random.default_rng(2)  # from outside, through the target, inwards
        origins = targets * 2.5 + rng.normal(scale=0.3, size=targets.shape)
        counts, _ = through(scene, origins, targets)
        assert counts.tolist() == [2] * len(targets)


def test_closed_grid_through_vertices_and_edges():
    n = 4
    scene = hlbvh_cl.Scene([grid_box(n)])
    ticks = np.arange(n + 1, dtype=float)
    half = np.arange(n) + 0.5
    # points on the face z = 0: grid vertices and edge midpoints (both kinds)
    points = [(x, y) for x in ticks for y in ticks] + [(x, y) for x in half for y in ticks] \
        + [(x, y) for x in ticks for y in half] + [(x, y) for x in half for y in half]
    targets = np.array([(x, y, 0.0) for x, y in points])
    inside = (targets[:, 0] > 0) & (targets[:, 0] < n) & (targets[:, 1] > 0) & (targets[:, 1] < n)
    # straight down the z axis: the rays through the face's inside enter and
    # leave; those along the box's side faces graze them (an even count)
    origins = targets + [0, 0, -5]
    counts, _ = through(scene, origins, targets)
    assert counts[inside].tolist() == [2] * inside.sum()
    assert (counts[~inside] % 2 == 0).all()
    # tilted, through the interior points towards the opposite corner region
    tilted = targets[inside]
    counts, _ = through(scene, tilted + [-1.0, -2.0, -6.0], tilted)
    assert counts.tolist() == [2] * len(tilted)


def test_grazing_rays_give_even_counts():
    """Rays in the plane of a face, from outside the cube across the face (a
    ray that starts on the surface may count one crossing: it is not this)."""
    scene = hlbvh_cl.Scene([cube_mesh()])
    rng = np.random.default_rng(5)
    angle = rng.uniform(0, 2 * np.pi, 300)
    around = np.stack([np.cos(angle), np.sin(angle)], axis=1) * 2 + 0.5
    across = rng.uniform(0, 1, (300, 2))
    counts = []
    for axis, side in ((0, 0.0), (2, 1.0), (1, 1.0)):
        others = [a for a in range(3) if a != axis]
        origins = np.full((300, 3), side)
        targets = np.full((300, 3), side)
        origins[:, others], targets[:, others] = around, across
        found, _ = through(scene, origins, targets)
        counts.append(found)
    counts = np.concatenate(counts)
    assert (counts % 2 == 0).all(), counts
    assert (counts == 0).any()  # the grazing rays do not all cross


@pytest.mark.parametrize("subdivisions", [1, 3])
def test_parity_tells_inside_from_outside(subdivisions):
    mesh = icosphere(subdivisions)
    scene = hlbvh_cl.Scene([mesh])
    rng = np.random.default_rng(subdivisions)
    radius = rng.uniform(0, 2, 4000)
    # the icosphere's faces lie between its inscribed and circumscribed spheres
    inscribed = np.abs(np.einsum("ij,ij->i", mesh.vertices[mesh.faces[:, 0]].astype(float),
                                 _unit_normals(mesh))).min()
    keep = (radius < inscribed - 0.02) | (radius > 1.02)
    radius = radius[keep]
    origins = _unit(rng.normal(size=(len(radius), 3))) * radius[:, None]
    directions = rng.normal(size=origins.shape)
    counts = scene.count_intersections(origins.astype(np.float32), directions.astype(np.float32))
    np.testing.assert_array_equal(counts % 2, radius < 1)
    # every ray from outside crosses an even number of times; aimed at the
    # sphere's vertices (through them) as well
    targets = mesh.vertices[rng.integers(0, mesh.vertex_count, len(radius))]
    counts, _ = through(scene, origins, targets)
    np.testing.assert_array_equal(counts % 2, radius < 1)


def _unit(v):
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _unit_normals(mesh):
    v = mesh.vertices.astype(float)
    f = mesh.faces
    return _unit(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]))


# -- frames, meshes, devices ---------------------------------------------------

def test_scaled_frame_gives_the_callers_t():
    """A scene far from unit size is traced in a scaled frame (hlbvh_cl.core.frame):
    t comes back in the caller's units, with the same hits as at scale 1."""
    scale = 2.0 ** 40
    meshes = tiny_scene_meshes()
    big = [hlbvh_cl.Mesh(m.vertices.astype(np.float64) * scale, m.faces) for m in meshes]
    small_scene, big_scene = hlbvh_cl.Scene(meshes), hlbvh_cl.Scene(big)
    assert built.tree(big_scene).scale != 1.0
    case = SceneCase(meshes, scene=small_scene)
    origins, directions = random_rays(case, 300, seed=9)
    small = small_scene.intersect_all(origins, directions)
    large = big_scene.intersect_all(origins * np.float32(scale), directions)
    np.testing.assert_array_equal(large.offsets, small.offsets)
    np.testing.assert_array_equal(large.prim_id, small.prim_id)
    np.testing.assert_allclose(large.t, small.t * scale, rtol=1e-6)  # scale times as far
    # t in units of |direction|: twice as long a direction, half the t
    half = big_scene.intersect_all(origins * np.float32(scale), directions * 2)
    np.testing.assert_allclose(half.t, large.t / 2, rtol=1e-6)
    window = big_scene.count_intersections(origins * np.float32(scale), directions,
                                           tmax=np.float32(scale))
    np.testing.assert_array_equal(window, small_scene.count_intersections(origins, directions,
                                                                          tmax=1.0))


def test_bunny_agrees_with_open3d(meshes):
    o3d = pytest.importorskip("open3d")
    bunny = meshes["bunny"]
    scene = hlbvh_cl.Scene([bunny])
    rays = o3d.t.geometry.RaycastingScene()
    rays.add_triangles(o3d.core.Tensor(bunny.vertices.astype(np.float32)),
                       o3d.core.Tensor(bunny.faces.astype(np.uint32)))
    rng = np.random.default_rng(10)
    lo, hi = bunny.vertices.min(axis=0), bunny.vertices.max(axis=0)
    centre, size = (lo + hi) / 2, float((hi - lo).max())
    origins = (centre + rng.uniform(-1, 1, (4000, 3)) * size).astype(np.float32)
    directions = (centre - origins).astype(np.float32)
    packed = o3d.core.Tensor(np.concatenate([origins, directions], axis=1))
    theirs = rays.count_intersections(packed).numpy()
    mine = scene.count_intersections(origins, directions)
    differ = np.flatnonzero(mine != theirs)
    assert mine.sum() > 4000
    assert len(differ) <= 4, f"{len(differ)} of 4000 rays count differently: {differ[:10]}"
    listed = rays.list_intersections(packed)
    every = scene.intersect_all(origins, directions)
    splits = listed["ray_splits"].numpy()
    agree = np.flatnonzero(mine == theirs)
    t_theirs, prim_theirs = listed["t_hit"].numpy(), listed["primitive_ids"].numpy()
    for r in agree[:1000]:
        theirs_r = slice(splits[r], splits[r + 1])
        order = np.argsort(t_theirs[theirs_r], kind="stable")
        mine_r = slice(every.offsets[r], every.offsets[r + 1])
        np.testing.assert_allclose(every.t[mine_r], t_theirs[theirs_r][order], rtol=1e-4)
        assert set(every.prim_id[mine_r]) == set(prim_theirs[theirs_r])


@pytest.mark.parametrize("copies, staging", [(False, False), (True, False), (True, True)],
                         ids=["in-place", "device-copies", "staging"])
def test_small_chunks_give_the_same_hits(tiny, monkeypatch, copies, staging):
    """Launches cut into chunks of few rays and few hits (a ray with more
    hits than a chunk holds goes alone) give what one launch gives: in
    place over the whole arrays (CPU devices), and with each chunk's rays
    and results copied, through device buffers or pinned staging buffers
    (GPUs; forced here by INDEXED_COPY_MAX 0)."""
    from hlbvh_cl.query import all_hits
    origins, directions = random_rays(tiny, 300, seed=11)
    tmax = np.random.default_rng(12).uniform(0.5, 3, len(origins)).astype(np.float32)
    whole = tiny.scene.intersect_all(origins, directions, tmax=tmax)
    counts = tiny.scene.count_intersections(origins, directions, tmax=tmax)
    assert whole.counts.max() >= 3
    query, every, tree = as_the_scene_makes(tiny.scene)
    batches = recording(monkeypatch, every.engine)
    if copies:
        monkeypatch.setattr(query, "zero_copy", False)
        monkeypatch.setattr(query, "staging", staging)
        monkeypatch.setattr(all_hits, "INDEXED_COPY_MAX", 0)
    monkeypatch.setattr(all_hits, "HITS_PER_LAUNCH", 2)
    monkeypatch.setattr(all_hits, "COPIED_RAYS_PER_LAUNCH", 5)
    monkeypatch.setattr(query, "max_rays_per_launch", 7)
    chunked = every.intersect_all(tree, origins, directions, tmax=tmax)
    for name in ("offsets", "ray_index", "t", "u", "v", "prim_id", "geom_id"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name), name)
    np.testing.assert_array_equal(every.count(tree, origins, directions, tmax=tmax), counts)
    first = every.intersect_all(tree, origins, directions, tmax=tmax, max_hits=2)
    np.testing.assert_array_equal(first.counts, np.minimum(counts, 2))
    # each pass over the whole arrays by slots (CPU devices), or each chunk copied
    whole = not copies and not query.rt.profile.gpu
    assert batches and all(batch.whole == whole for batch in batches)


def test_outputs_bigger_than_a_device_buffer_come_back_in_chunks(tiny, monkeypatch):
    """Where a whole array would not fit one buffer of the device
    (CL_DEVICE_MAX_MEM_ALLOC_SIZE), even on CPU devices the passes copy
    their rays and results chunk by chunk, through buffers that fit, and
    give the same hits."""
    import dataclasses
    from hlbvh_cl.query import all_hits
    origins, directions = random_rays(tiny, 3000, seed=51)
    want = tiny.scene.intersect_all(origins, directions)
    query, every, tree = as_the_scene_makes(tiny.scene)
    rt = query.rt
    limit = want.ray_index.nbytes // 4
    assert limit < origins.nbytes  # no whole array fits: the count pass copies too
    monkeypatch.setattr(rt, "device", dataclasses.replace(rt.device, max_mem_alloc_size=limit))
    # chunks whose buffers fit: 32 bytes of kept hits a ray, 8 of ray_index a hit
    monkeypatch.setattr(all_hits, "COPIED_RAYS_PER_LAUNCH", limit // 64)
    monkeypatch.setattr(all_hits, "HITS_PER_LAUNCH", limit // 16)
    made, buffer = [], cl.Buffer  # the bytes of every buffer the passes make

    def recorded(context, flags, size=0, hostbuf=None):
        made.append(size if hostbuf is None else hostbuf.nbytes)
        return buffer(context, flags, size, hostbuf)
    monkeypatch.setattr(cl, "Buffer", recorded)
    batches = recording(monkeypatch, every.engine)
    got = every.intersect_all(tree, origins, directions)
    assert len(batches) == 2 and not any(batch.whole for batch in batches)
    assert len(made) > 2 and max(made) <= limit
    for name in ("offsets", "ray_index", "t", "u", "v", "prim_id", "geom_id"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), name)


def test_rays_the_kernels_read_in_place_start_on_a_page(tiny, monkeypatch):
    """Off zero copy, on CPU devices, the count and fill passes read the
    whole ray arrays in place: big arrays that do not start on a page are
    copied once onto one (a runtime such as Intel's would otherwise copy
    them for each buffer), and the hits are those of zero copy."""
    from hlbvh_cl.query.results import ALIGNMENT, MIN_POOLED_BYTES, starts_on_page
    query, every, tree = as_the_scene_makes(tiny.scene)
    if query.rt.profile.gpu:
        pytest.skip("GPUs take each chunk's rays (device copies)")
    count = MIN_POOLED_BYTES // 12 + 4097
    origins, directions = random_rays(tiny, count + 1, seed=41)
    origins, directions = origins[1:], directions[1:]  # off the page their arrays start on
    tmax = np.random.default_rng(42).uniform(0.5, 3, count).astype(np.float32)
    assert origins.ctypes.data % ALIGNMENT and directions.ctypes.data % ALIGNMENT
    monkeypatch.setattr(query, "zero_copy", True)
    want = every.intersect_all(tree, origins, directions, tmax=tmax)
    monkeypatch.setattr(query, "zero_copy", False)
    batches = recording(monkeypatch, every.engine)  # what each pass was given
    reserved = []  # launches that copied their rays or results (none should)
    monkeypatch.setattr(every.engine, "reserve", lambda sizes:
                        reserved.append(sizes) or pytest.fail("a pass copied its rays"))
    got = every.intersect_all(tree, origins, directions, tmax=tmax)
    assert not reserved and all(batch.whole for batch in batches)
    read = [[batch.inputs["origins"], batch.inputs["directions"], *batch.stepped.values()]
            for batch in batches]
    big = [a for rays in read for a in rays if a.nbytes >= MIN_POOLED_BYTES]
    assert len(read) == 2 and len(big) == 4  # each pass's origins and directions
    assert starts_on_page(*big)
    for name in ("offsets", "ray_index", "t", "u", "v", "prim_id", "geom_id"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), name)
    np.testing.assert_array_equal(every.count(tree, origins, directions, tmax=tmax), want.counts)


def test_scenes_count_in_packets_twice_their_querys_on_cpus(tiny, monkeypatch):
    """A scene's count pass runs in packets twice its query's on CPU devices
    (a count's lanes never part) where that variant passes its probe, and in
    its query's elsewhere (GPUs trace one ray per work-item); the fill pass
    in its query's."""
    from hlbvh_cl.query import all_hits
    from hlbvh_cl.device import probe
    from hlbvh_cl.query.rays import RayQuery
    query = RayQuery(built.runtime(tiny.scene))  # configured as the scene's own
    rt, wider = query.rt, 2 * query.packet_size
    wide = not rt.profile.gpu and query.packet_size > 1 and wider <= 16 and \
        probe.usable(rt.device, rt.profile, query.variant.with_packet(wider)) is None
    ran = []  # each kernel the passes ran, with its rays per work-item
    kernel = all_hits.AllHitsQuery.kernel
    monkeypatch.setattr(all_hits.AllHitsQuery, "kernel", lambda self, tree, name, *args:
                        ran.append((name, kernel(self, tree, name, *args)[1])) or
                        kernel(self, tree, name, *args))
    origins, directions = random_rays(tiny, 200, seed=61)
    tiny.scene.intersect_all(origins, directions)
    counting = wider if wide else query.packet_size
    assert ran == [("count_hits_arrays", counting), ("fill_hits_arrays", query.packet_size)]


@pytest.mark.parametrize("copies", [None, "gpu", "big"])
def test_big_batches_traced_in_morton_order_answer_in_the_callers_order(tiny, monkeypatch,
                                                                         copies):
    """A batch of COHERENT_MIN rays and more is counted by class, then in
    Morton order of its origins (hlbvh_cl.query.order), in launches of a few hundred rays: each ray's
    hits, counts and t (with per-ray limits) are those it gets in small
    batches, which run as given.  Both ways to run that order: slots into
    the whole arrays (CPU devices), and rays taken per launch with the
    results put back (staged copies on GPUs, forced with `copies`, and
    device copies for batches over INDEXED_COPY_MAX off zero copy)."""
    from hlbvh_cl.query import all_hits, engine, order
    from hlbvh_cl.query.order import COHERENT_MIN
    traced = []  # the orders the big batches were traced in
    monkeypatch.setattr(all_hits, "device_order",
                        lambda rt, points, *args, **named: traced.append(
                            order.device_order(rt, points, *args, **named)) or traced[-1])
    count = 2 * COHERENT_MIN + 37
    origins, directions = random_rays(tiny, count, seed=31)
    tmax = np.random.default_rng(32).uniform(0.5, 3, count).astype(np.float32)
    query, every, tree = as_the_scene_makes(tiny.scene)
    monkeypatch.setattr(query, "max_rays_per_launch", 700)
    monkeypatch.setattr(all_hits, "COPIED_RAYS_PER_LAUNCH", 300)
    taken = []  # the launches whose rays the host took
    take_rows = engine.take_rows
    monkeypatch.setattr(engine, "take_rows", lambda array, rows, **out: taken.append(len(rows))
                        or take_rows(array, rows, **out))
    if copies:
        monkeypatch.setattr(query, "zero_copy", False)
    if copies == "gpu":  # the GPU profile, through pinned staging buffers (on request)
        from hlbvh_cl.device.profile import Profile
        monkeypatch.setattr(query.rt, "profile", Profile("gpu"))
        monkeypatch.setattr(query, "staging", True)
    if copies == "big":
        monkeypatch.setattr(all_hits, "INDEXED_COPY_MAX", count - 1)
    for max_hits in (None, 2):
        whole = every.intersect_all(tree, origins, directions, tmax=tmax, max_hits=max_hits)
        parts = [every.intersect_all(tree, origins[i:i + 500], directions[i:i + 500],
                                     tmax=tmax[i:i + 500], max_hits=max_hits)
                 for i in range(0, count, 500)]
        assert whole.counts.max() >= 3 - (max_hits == 2)
        np.testing.assert_array_equal(whole.counts, np.concatenate([p.counts for p in parts]))
        for name in ("t", "u", "v", "prim_id", "geom_id"):
            np.testing.assert_array_equal(getattr(whole, name),
                                          np.concatenate([getattr(p, name) for p in parts]), name)
        np.testing.assert_array_equal(whole.ray_index, np.repeat(np.arange(count), whole.counts))
    np.testing.assert_array_equal(every.count(tree, origins, directions, tmax=tmax),
                                  every.intersect_all(tree, origins, directions, tmax=tmax).counts)
    assert len(traced) == 4 and all((o != np.arange(count)).any() for o in traced)
    # CPU devices read the whole arrays by slots, up to INDEXED_COPY_MAX rays
    assert bool(taken) == (copies is not None or query.rt.profile.gpu)


def test_orders_the_count_chooses(tiny, monkeypatch):
    """The count sorts a big batch only where sorting makes packets of it:
    not rays in a coherent order already (a camera's pixels), nor, where
    the kernel interleaves the walks of rays that make no packet (forced
    here), rays neither nearly parallel nor aimed at one point, which
    walk faster one by one; parallel rays from random points and rays aimed
    at one point are sorted.  Every way, the counts are those of one ray a
    work-item."""
    from hlbvh_cl.query import all_hits, engine, order
    from hlbvh_cl.query.all_hits import AllHitsQuery
    from hlbvh_cl.query.rays import RayQuery
    sorted_batches = []
    monkeypatch.setattr(all_hits, "device_order", lambda *args, **named: sorted_batches.append(
        named["by_direction"]) or order.device_order(*args, **named))
    rng = np.random.default_rng(51)
    count = 3 * order.COHERENT_MIN
    points = rng.uniform(tiny.lo - 0.2, tiny.hi + 0.2, (count, 3)).astype(np.float32)
    side = np.linspace(-0.4, 0.4, 64)
    pixels = np.stack(np.broadcast_arrays(side[None, :], side[:, None], -1.0), axis=-1)
    camera = (np.broadcast_to(np.float32([0.05, 0.1, 4.0]), (64 * 64, 3)),
              pixels.reshape(-1, 3).astype(np.float32))
    shuffle = rng.permutation(len(camera[0]))
    cone = np.float32([0.2, -1.0, 0.1]) + rng.normal(0, 0.3, (count, 3)).astype(np.float32)
    batches = {  # name: (rays, sorted without interleaving, sorted interleaved)
        "camera": (camera, False, False),
        "camera shuffled": ((camera[0], camera[1][shuffle]), True, False),
        "random": (random_rays(tiny, count, seed=52), True, False),
        "wide cone": ((points, cone), True, False),
        "parallel": ((points, np.broadcast_to(np.float32([0.2, -1.0, 0.1]), (count, 3))), True,
                     True),
        "aimed": ((points, (np.float32(tiny.lo + tiny.hi) / 2 - points)), True, True)}
    assert order.rays_in_order(*camera) and not order.rays_in_order(*batches["random"][0])
    assert order.nearly_parallel(batches["parallel"][0][1])
    assert not order.nearly_parallel(cone)
    tree = built.tree(tiny.scene)
    alone = AllHitsQuery(RayQuery(built.runtime(tiny.scene), packet_size=1))
    for smallest in (2**62, 0):
        monkeypatch.setattr(engine, "INTERLEAVED_MIN_TREE_BYTES", smallest)
        query = AllHitsQuery(RayQuery(built.runtime(tiny.scene), packet_size=8))
        interleaved = "INTERLEAVED_WALKS" in engine.kernel_defines(
            query.rt, tree, query.query.variant, query.count_packet_size)
        # interleaving takes a work-item of several rays: not on a device that
        # cannot compile packets (PyPI's PoCL on a Zen 4 runs packet1 only)
        assert interleaved == (smallest == 0 and not query.rt.profile.gpu
                               and query.query.variant.packet_size > 1)
        for name, (rays, plain, when_interleaved) in batches.items():
            sorted_batches.clear()
            counts = query.count(tree, *rays)
            assert bool(sorted_batches) == (when_interleaved if interleaved else plain), name
            np.testing.assert_array_equal(counts, alone.count(tree, *rays), err_msg=name)
            assert counts.max() >= 2, name


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), k=st.integers(1, 4),
       window=st.tuples(st.floats(0, 2), st.floats(0, 3)))
def test_properties(tiny, seed, k, window):
    """Any rays and window: counts agree with intersect_all, each ray's hits
    are sorted and inside [tmin, tmax], and max_hits=k is their prefix."""
    origins, directions = random_rays(tiny, 64, seed=seed)
    tmin, tmax = window[0], window[0] + window[1]
    every = tiny.scene.intersect_all(origins, directions, tmin, tmax)
    np.testing.assert_array_equal(every.counts,
                                  tiny.scene.count_intersections(origins, directions, tmin, tmax))
    same = every.ray_index[1:] == every.ray_index[:-1]
    assert (every.t[1:][same] >= every.t[:-1][same]).all()
    assert ((every.t >= np.float32(tmin)) & (every.t <= np.float32(tmax))).all()
    first = tiny.scene.intersect_all(origins, directions, tmin, tmax, max_hits=k)
    rank = np.arange(len(every)) - every.offsets[every.ray_index]
    np.testing.assert_array_equal(first.t, every.t[rank < k])
    np.testing.assert_array_equal(first.prim_id, every.prim_id[rank < k])


@pytest.mark.parametrize("packet_size", [1, 8, 16])
def test_count_packets_cross_shared_edges_once(packet_size):
    """Counting in packets (kernels/query/all_hits.cl: walk.h's packet path with
    the counting visitor) keeps one crossing per shared edge and vertex: a
    big batch (Morton order; packets of nearby rays that share their
    direction signs) aimed at a closed grid's inner vertices and cell
    centres on one face enters and leaves once each; random rays count as
    the fill pass (one ray per work-item) finds them."""
    from hlbvh_cl.query.all_hits import AllHitsQuery
    from hlbvh_cl.query.order import COHERENT_MIN
    from hlbvh_cl.query.rays import RayQuery
    n = 4
    scene = hlbvh_cl.Scene([grid_box(n)])
    ticks = np.arange(n + 1, dtype=float)
    half = np.arange(n) + 0.5
    points = [(x, y) for x in ticks for y in ticks] + [(x, y) for x in half for y in half]
    targets = np.array([(x, y, 0.0) for x, y in points])
    inside = (targets[:, 0] > 0) & (targets[:, 0] < n) & (targets[:, 1] > 0) & (targets[:, 1] < n)
    targets = targets[inside]
    copies = -(-COHERENT_MIN // len(targets)) + 1
    jitter = np.random.default_rng(8).uniform(-0.01, 0.01, (len(targets) * copies, 3))
    jitter[:, 2] = 0
    origins = np.repeat(targets, copies, axis=0) + [0.3, 0.2, -5] + jitter
    aims = np.repeat(targets, copies, axis=0)
    query = AllHitsQuery(RayQuery(built.runtime(scene), packet_size=packet_size))
    directions = (aims - origins).astype(np.float32)
    counts = query.count(built.tree(scene), origins.astype(np.float32), directions)
    assert counts.tolist() == [2] * len(origins)
    case = SceneCase([grid_box(n)])
    random_origins, random_directions = random_rays(case, 2 * COHERENT_MIN, seed=12)
    got = query.count(built.tree(scene), random_origins, random_directions)
    np.testing.assert_array_equal(got, scene.intersect_all(random_origins,
                                                            random_directions).counts)


@pytest.mark.parametrize("packet_size", [1, 8, 16])
def test_rays_aimed_at_one_point_count_each_crossing_once(packet_size, monkeypatch):
    """Rays from scattered origins aimed at one point of a closed grid's
    face (an inner vertex, an edge's midpoint, a cell's centre: shared by
    several triangles) run ordered by direction (hlbvh_cl.query.order's
    concurrent_rays), so that a packet's rays lie along nearly one line but
    start up to 80 units apart along it: the packet's interval ray is
    taken from origins moved along their rays (kernels/query/rays/packet.h).  Every ray
    enters and leaves the grid once, and crosses each face of a wide slab
    below it that it starts under."""
    from hlbvh_cl.query import all_hits
    from hlbvh_cl.query import order
    from hlbvh_cl.query.all_hits import AllHitsQuery
    from hlbvh_cl.query.order import COHERENT_MIN
    from hlbvh_cl.query.rays import RayQuery
    by_direction = []
    monkeypatch.setattr(all_hits, "device_order", lambda *args, **named: by_direction.append(
        named["by_direction"]) or order.device_order(*args, **named))
    n = 4
    slab = cube_mesh()
    slab = hlbvh_cl.Mesh(slab.vertices * [80, 80, 10] + [-40, -40, -40], slab.faces, name="slab")
    scene = hlbvh_cl.Scene([grid_box(n), slab])
    query = AllHitsQuery(RayQuery(built.runtime(scene), packet_size=packet_size))
    rng = np.random.default_rng(14)
    count = COHERENT_MIN + 300
    for target in ([1.0, 2.0, 0.0], [1.5, 2.0, 0.0], [2.5, 1.5, 0.0]):
        slant = np.column_stack([rng.uniform(-0.6, 0.6, (count, 2)), -np.ones(count)])
        depth = rng.uniform(0.5, 80.0, count)
        depth[np.abs(depth - 30) < 0.01] += 0.05  # off the slab's faces
        depth[np.abs(depth - 40) < 0.01] += 0.05
        origins = (target + depth[:, None] * slant).astype(np.float32)
        directions = (np.float32(target) - origins).astype(np.float32)
        counts = query.count(built.tree(scene), origins, directions)
        want = 2 + (origins[:, 2] < -30) + (origins[:, 2] < -40)
        assert (want > 2).any() and (want == 2).any()
        np.testing.assert_array_equal(counts, want, err_msg=str(target))
    assert by_direction == [True] * 3


@pytest.mark.parametrize("max_hits", [None, 1, 3])
def test_fill_packets_give_the_hits_of_one_ray(tiny, max_hits):
    """The fill pass in packets of 8 and 16 (each lane into its own
    segment, a full segment lowering that lane's limit) stores exactly the
    hits one ray per work-item stores, on a big batch of camera-like rays
    (packets) and of random ones (mostly one by one)."""
    from hlbvh_cl.query.all_hits import AllHitsQuery
    from hlbvh_cl.query.order import COHERENT_MIN
    from hlbvh_cl.query.rays import RayQuery
    side = np.linspace(-0.4, 0.4, 48)
    grid = np.stack(np.broadcast_arrays(side[:, None], side[None, :], -1.0), axis=-1)
    camera = grid.reshape(-1, 3).astype(np.float32)
    origins, directions = random_rays(tiny, COHERENT_MIN, seed=41)
    origins = np.concatenate([np.broadcast_to(np.float32([0.05, 0.1, 4.0]), camera.shape),
                              origins]).astype(np.float32)
    directions = np.concatenate([camera, directions]).astype(np.float32)
    tree = built.tree(tiny.scene)
    want = AllHitsQuery(RayQuery(built.runtime(tiny.scene), packet_size=1)).intersect_all(
        tree, origins, directions, max_hits=max_hits)
    assert (want.counts[:len(camera)] >= min(2, max_hits or 2)).sum() > 100, \
        "camera rays should cross the sphere"
    for packet_size in (8, 16):
        got = AllHitsQuery(RayQuery(built.runtime(tiny.scene), packet_size=packet_size)).intersect_all(
            tree, origins, directions, max_hits=max_hits)
        for name in ("offsets", "ray_index", "t", "u", "v", "prim_id", "geom_id", "instance_id"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name),
                                          err_msg=f"packets of {packet_size}: {name}")


@pytest.mark.parametrize("max_hits", [None, 2, 6])
def test_rays_with_more_hits_than_kept_walk_again(max_hits, monkeypatch):
    """The count pass keeps each ray's first KEEP_HITS hit triangles, and the
    fill pass tests those again instead of walking where they are all its
    hits; rays with more walk again, in packets among rays that do not.
    Through KEEP_HITS + 4 stacked plates with random tmax (0 to all of them
    hit), a batch big enough for Morton order and packets matches the brute
    force, and is exactly what kernels that keep one triangle give."""
    from hlbvh_cl.query import all_hits
    from hlbvh_cl.query.order import COHERENT_MIN
    layers = all_hits.KEEP_HITS + 4
    case = SceneCase([plates(layers)])
    count = 2 * COHERENT_MIN + 5
    rng = np.random.default_rng(7)
    origins = np.column_stack([rng.uniform(-0.9, 0.9, (count, 2)), np.full(count, -0.5)])
    directions = np.column_stack([rng.uniform(-0.05, 0.05, (count, 2)), np.ones(count)])
    origins, directions = origins.astype(np.float32), directions.astype(np.float32)
    tmax = rng.uniform(0, layers + 0.5, count).astype(np.float32)
    compared, got = assert_matches_brute_force(case, origins, directions, tmax=tmax,
                                               max_hits=max_hits)
    assert compared > 0.9 * count
    counts = case.scene.count_intersections(origins, directions, tmax=tmax)
    assert ((counts > all_hits.KEEP_HITS).sum() > 100
            and ((counts > 0) & (counts <= all_hits.KEEP_HITS)).sum() > 100)
    monkeypatch.setattr(all_hits, "KEEP_HITS", 1)
    again = case.scene.intersect_all(origins, directions, tmax=tmax, max_hits=max_hits)
    for name in ("offsets", "t", "u", "v", "prim_id", "geom_id", "instance_id"):
        np.testing.assert_array_equal(getattr(again, name), getattr(got, name), err_msg=name)
