"""The build pipeline on PoCL: tree invariants on every build, Morton codes
against numpy, refit against fresh builds, and the Scene's errors."""
from __future__ import annotations

import dataclasses

import numpy as np
import pyopencl as cl
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import hlbvh_cl
from hlbvh_cl import Mesh
from hlbvh_cl import Scene
from hlbvh_cl.build.bounds import scene_bounds
from hlbvh_cl.build.pipeline import STAGES, BuildStats, Geometry
from hlbvh_cl.device.runtime import Runtime, runtime
from hlbvh_cl.build.morton import morton_codes
from hlbvh_cl.build import sah_top
from hlbvh_cl.io import scenefile

import built
from invariants import check_tree
import places

REAL_MESHES = ["bunny", "armadillo", "lucy", "bunny_small", "knight", "teapot", "dragon_small"]
BUILDS = [("hlbvh", 30), ("hlbvh", 63), ("lbvh", 30), ("lbvh", 63)]


@pytest.mark.parametrize("builder,bits", BUILDS)
@pytest.mark.parametrize("name", REAL_MESHES)
def test_real_mesh_tree_invariants(meshes, name, builder, bits):
    scene = Scene([meshes[name]], builder=builder, morton_bits=bits)
    check_tree(scene)


@pytest.mark.parametrize("builder,bits", BUILDS)
def test_several_meshes_in_one_tree(meshes, builder, bits):
    parts = [meshes[k] for k in ("knight", "teapot", "bunny_small", "dragon_small")]
    scene = Scene(parts, builder=builder, morton_bits=bits)
    derived = check_tree(scene)
    counts = np.bincount(derived["refs"]["geom_id"], minlength=len(parts))
    assert counts.tolist() == [m.triangle_count for m in parts]


def _soup(rng, n, scale_lo=-3.0, scale_hi=6.0):
    """Random triangles whose sizes and positions span 10**scale_lo..10**scale_hi."""
    centers = rng.normal(size=(n, 3)) * 10.0 ** rng.uniform(scale_lo, scale_hi, size=(n, 1))
    edges = rng.normal(size=(n, 3, 3)) * 10.0 ** rng.uniform(scale_lo, scale_hi, size=(n, 1, 1))
    vertices = (centers[:, None, :] + edges).reshape(-1, 3)
    return Mesh(vertices, np.arange(3 * n).reshape(n, 3))


SPECIAL_INPUTS = {
    "one triangle": lambda rng: Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]),
    "two triangles": lambda rng: Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]],
                                      [[0, 1, 2], [2, 1, 3]]),
    # boxes symmetric about the origin: every triangle's centroid is 0
    "identical centroids": lambda rng: _symmetric_triangles(rng, 300),
    "soup 1e-3..1e6": lambda rng: _soup(rng, 5000),
    "degenerate triangles": lambda rng: Mesh(np.repeat(rng.normal(size=(50, 3)), 3, axis=0),
                                             np.arange(150).reshape(50, 3)),
    # clusters whose centres lie 1e-38 apart, in a frame set to 1 by a unit
    # triangle: the SAH top's bins / extent passes float32's range
    "centres 1e-38 apart": lambda rng: Mesh(
        np.concatenate([(rng.uniform(0, 4e-37, (3000, 1, 3))
                         + rng.uniform(0, 1e-38, (3000, 3, 3))).reshape(-1, 3),
                        np.eye(3)]), np.arange(3 * 3001).reshape(3001, 3)),
}


def _symmetric_triangles(rng, n):
    half = rng.uniform(0.1, 2.0, size=(n, 3))
    inside = half * rng.uniform(-1, 1, size=(n, 3))
    vertices = np.stack([-half, half, inside], axis=1).reshape(-1, 3)
    return Mesh(vertices, np.arange(3 * n).reshape(n, 3))


@pytest.mark.parametrize("builder,bits", BUILDS)
@pytest.mark.parametrize("kind", list(SPECIAL_INPUTS))
def test_special_inputs(kind, builder, bits):
    mesh = SPECIAL_INPUTS[kind](np.random.default_rng(7))
    scene = Scene([mesh], builder=builder, morton_bits=bits)
    check_tree(scene)


def test_identical_centroids_really_are():
    mesh = SPECIAL_INPUTS["identical centroids"](np.random.default_rng(7))
    tri = mesh.vertices[mesh.faces]
    centers = 0.5 * (tri.min(axis=1) + tri.max(axis=1))
    assert np.ptp(centers, axis=0).max() == 0.0


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(1, 300), seed=st.integers(0, 2**31 - 1),
       builder=st.sampled_from(["hlbvh", "lbvh"]), bits=st.sampled_from([30, 63]),
       spread=st.sampled_from([0.0, 1e-3, 1.0, 1e4]))
def test_property_any_soup_builds_a_valid_tree(n, seed, builder, bits, spread):
    rng = np.random.default_rng(seed)
    # spread 0 puts every vertex on a few lattice points: many equal Morton codes
    base = rng.integers(0, 3, size=(3 * n, 3)).astype(np.float64)
    vertices = base + spread * rng.normal(size=(3 * n, 3))
    mesh = Mesh(vertices, rng.permutation(3 * n).reshape(n, 3))
    check_tree(Scene([mesh], builder=builder, morton_bits=bits))


def _numpy_morton(mesh: Mesh, bits: int) -> np.ndarray:
    """Reference: centroid of each triangle's box, quantised over the
    centroid bounds, bits interleaved x (high) y z (low)."""
    tri = mesh.vertices[mesh.faces]
    centroid = 0.5 * (tri.min(axis=1) + tri.max(axis=1))  # float32, as on the device
    lo, hi = centroid.min(axis=0), centroid.max(axis=0)
    per_axis = bits // 3
    cells = np.float32(2**per_axis)
    extent = hi - lo
    scale = np.where(extent > 0, cells / np.where(extent > 0, extent, 1), 0).astype(np.float32)
    q = np.clip((centroid - lo) * scale, 0, cells - 1).astype(np.uint64)
    code = np.zeros(len(q), np.uint64)
    for bit in range(per_axis):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + 2 - axis)
    return code


@pytest.mark.parametrize("bits", [30, 63])
@pytest.mark.parametrize("name", ["bunny", "lucy", "knight"])
def test_morton_codes_match_numpy(meshes, name, bits):
    mesh = meshes[name]
    rt = runtime()
    geometry = Geometry.upload(rt, mesh.vertices, mesh.faces, np.zeros(1, np.int32))
    n = mesh.triangle_count
    bounds = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 48)
    keys = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, n * (4 if bits == 30 else 8))
    ids = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, n * 4)
    centroids = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, n * 16)
    inverse_extent = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 16)
    scene_bounds(rt, geometry.vertices, geometry.faces, n, bounds, centroids, inverse_extent)
    morton_codes(rt, centroids, n, bounds, inverse_extent, keys, ids, bits)
    got = np.empty(n, np.uint32 if bits == 30 else np.uint64)
    got_ids = np.empty(n, np.uint32)
    cl.enqueue_copy(rt.queue, got, keys)
    cl.enqueue_copy(rt.queue, got_ids, ids)
    expected = _numpy_morton(mesh, bits)
    # every step is one correctly rounded float operation, as in numpy (the
    # scale's divide too: bounds.cl's divide_nearest), so the codes are equal
    assert np.array_equal(got.astype(np.uint64), expected)
    assert np.array_equal(got_ids, np.arange(n))
    assert got.max() < 2**bits


@pytest.mark.parametrize("builder", ["hlbvh", "lbvh"])
def test_refit_matches_fresh_build(meshes, builder):
    rng = np.random.default_rng(3)
    parts = [meshes["knight"], meshes["bunny_small"]]
    scene = Scene(parts, builder=builder)
    nodes_before = built.tree(scene).read_nodes(built.runtime(scene).queue)
    moved = parts[1].vertices * 1.5 + rng.normal(scale=0.01, size=parts[1].vertices.shape)
    moved += [0.3, -2.0, 0.1]
    scene.update_vertices(1, moved)
    derived = check_tree(scene)  # every box is again exactly its triangles' box
    nodes_after = derived["nodes"]
    for field in ("child", "count"):
        assert np.array_equal(nodes_before[field], nodes_after[field]), "refit changed topology"
    fresh = Scene([parts[0], Mesh(moved, parts[1].faces)], builder=builder)
    fresh_derived = check_tree(fresh)
    assert np.array_equal(derived["root_lo"], fresh_derived["root_lo"])
    assert np.array_equal(derived["root_hi"], fresh_derived["root_hi"])
    np.testing.assert_array_equal(built.tree(scene).bounds_lo, derived["root_lo"])
    # rebuild gives a tree over the moved vertices too
    scene.rebuild()
    check_tree(scene)


def test_stats_and_stage_times(meshes):
    scene = Scene([meshes["bunny"]])
    stats = scene.stats
    assert isinstance(stats, BuildStats) and stats.refit_ms is None
    assert tuple(stats.times_ms) == STAGES
    for stage in STAGES:
        assert np.isfinite(stats.times_ms[stage]) and stats.times_ms[stage] >= 0
    assert stats.device_ms == pytest.approx(sum(stats.times_ms.values())) and stats.device_ms > 0
    assert stats.wall_ms > 0
    # tree memory: the wide nodes read back and one Triangle per mesh face, and
    # no more than the device buffers hold
    with scene.borrow() as built:
        tree, queue = built.tree, built.runtime.queue
        nodes, (triangles, _) = tree.read_nodes(queue), tree.read_triangles(queue)
        node_buffer, triangle_buffer = tree.nodes.size, tree.triangles.size
    assert len(triangles) == meshes["bunny"].triangle_count
    assert stats.node_bytes == len(nodes) * nodes.dtype.itemsize <= node_buffer
    assert stats.triangle_bytes == meshes["bunny"].triangle_count * triangles.dtype.itemsize
    assert stats.triangle_bytes <= triangle_buffer
    assert stats.tree_bytes == stats.node_bytes + stats.triangle_bytes
    with pytest.raises(dataclasses.FrozenInstanceError):
        stats.nodes = 0


@pytest.mark.parametrize("builder", ["hlbvh", "lbvh"])
def test_rebuilds_are_bit_for_bit_the_same(builder):
    """The walkers of the radix tree meet in an order that varies from run to
    run; neither the tree nor its SAH cost may depend on it.  (The LBVH's
    cost once did, in its last bits: about one rebuild in 150 of this
    scene differed.)"""
    scenes = places.SCENES
    description = scenefile.read(scenes / "bunny_small.toml")
    scene = Scene([mesh for mesh, _ in description.geometries()], builder=builder)
    first_cost = scene.stats.sah_cost
    first_nodes = built.tree(scene).read_nodes(built.runtime(scene).queue).tobytes()
    for _ in range(300):
        scene.rebuild()
        assert scene.stats.sah_cost == first_cost
    assert built.tree(scene).read_nodes(built.runtime(scene).queue).tobytes() == first_nodes


@pytest.mark.parametrize("builder", ["hlbvh", "lbvh"])
def test_every_device_builds_the_same_tree(meshes, builder):
    """One code path: every working device (the simulator aside: slow)
    builds the bunny's tree bit for bit alike, with the same SAH cost.  No
    kernel lets its compiler fuse multiply-adds (core/portable.h), which would pick
    other SAH splits on a device that fuses."""
    from hlbvh_cl import devices
    ids = [d.id for d in devices() if d.problem is None and not d.simulator]
    if len(ids) < 2:
        pytest.skip("one device here")
    trees = {}
    for device in ids:
        scene = Scene([meshes["bunny"]], device=device, builder=builder)
        trees[device] = (scene.stats.sah_cost,
                         built.tree(scene).read_nodes(built.runtime(scene).queue).tobytes())
    first = trees[ids[0]]
    assert all(tree == first for tree in trees.values()), sorted(
        (device, cost) for device, (cost, _) in trees.items())


@pytest.mark.parametrize("builder", ["hlbvh", "lbvh"])
def test_both_handoffs_give_the_same_tree(meshes, builder, monkeypatch):
    """The bottom-up walkers hand results on with acquire-release atomics
    where the compiler has them, else (OpenCL C 1.2: GPUs, Oclgrind) through
    an atomic per word (kernels/build/handoff.h).  Here, on the suite's device, the
    second path runs with real concurrency and must build and refit the same
    trees as the first, bit for bit."""
    if runtime().device.acquire_release_std is None:
        pytest.skip("this device compiles OpenCL C 1.2 only: the 1.2 handoff is its one path, "
                    "which every other build test runs")
    rng = np.random.default_rng(5)
    parts = [meshes["knight"], meshes["bunny_small"]]
    moved = parts[1].vertices * 1.1 + rng.normal(scale=0.01, size=parts[1].vertices.shape)
    results = []
    for acquire_release in (1, 0):
        monkeypatch.setattr(Runtime, "handoff_defines",
                            property(lambda self, a=acquire_release: {"ACQUIRE_RELEASE": a}))
        scene = Scene(parts, builder=builder)
        fresh = built.tree(scene).read_nodes(built.runtime(scene).queue).tobytes()
        scene.update_vertices(1, moved)
        refit = built.tree(scene).read_nodes(built.runtime(scene).queue).tobytes()
        results.append((fresh, refit, scene.stats.sah_cost, scene.stats.depth))
    assert results[0] == results[1]


@pytest.mark.parametrize("group", [256, 4])
def test_group_split_gives_the_same_tree(meshes, group, monkeypatch):
    """Issue 57: the SAH top's upper levels split by whole work-groups
    (split_top_group) must build the tree that one work-item per task builds
    (split_top_level, the oracle), bit for bit, with the isolation of a
    ground plane (whose corners hold -0 and +0, the ties of the box's fold)
    and with groups of a few work-items (many tiles in each partition).
    Record order within a node barely shows in the tree (the splits depend
    on the sets), so what this checks is the choice of every split."""
    def ground(mesh, zero=False):
        """One big triangle (one cluster) through the middle of mesh, which
        centroid bins cannot cut off, or a flat one at y = +-0 (x, z = +-0
        too) under it."""
        lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        middle, size = (lo + hi) / 2, 3 * (hi - lo).max()
        corners = middle + size * np.array([[-1.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
        if zero:
            corners = np.array([[-size, -0.0, -size], [size, 0.0, -0.0], [-0.0, -0.0, size]])
        return Mesh(corners, np.array([[0, 1, 2]]), name="ground")
    monkeypatch.setattr(sah_top, "TOP_GROUP", group)
    results, levels = [], []
    for forced in (False, True):
        monkeypatch.setattr(sah_top, "_group_levels",
                            lambda serial_depth, units, gpu, f=forced:
                            levels.append(serial_depth * f) or serial_depth * f)
        trees = []
        for parts in ([meshes["bunny"]], [meshes["knight"], ground(meshes["knight"])],
                      [meshes["teapot"], ground(meshes["teapot"]), ground(meshes["teapot"], True)]):
            scene = Scene(parts, builder="hlbvh")
            trees.append((built.tree(scene).read_nodes(built.runtime(scene).queue).tobytes(),
                          scene.stats.sah_cost, scene.stats.depth))
        results.append(trees)
    assert max(levels) >= 2  # the group kernel ran on some levels
    assert results[0] == results[1]


@pytest.mark.parametrize("name", ["bunny", "armadillo", "lucy"])
def test_hlbvh_sah_is_lower_than_lbvh(meshes, name):
    """Quality, not speed: the SAH top and the collapse must pay off."""
    h = Scene([meshes[name]], builder="hlbvh").stats.sah_cost
    l = Scene([meshes[name]], builder="lbvh").stats.sah_cost
    assert h < l


# ---- the public names --------------------------------------------------------

def test_public_api_is_small():
    assert set(hlbvh_cl.__all__) >= {"Scene", "Mesh", "devices"}
