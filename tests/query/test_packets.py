"""Ray packets (kernels/query/rays.cl, PACKET_SIZE): on CPUs a work-item traces
8 consecutive rays together when they share direction signs and the axis of
the watertight test, and one by one otherwise.  Every packet size must give
the oracle's answers (tests/support/oracle.py), including watertightness; these
tests use rays that do form packets, and check that they do.
"""
from __future__ import annotations


import numpy as np
import pyopencl.array as cl_array
import pytest

import hlbvh_cl
from hlbvh_cl.query.rays import PACKET_SIZES, RayQuery
import built
from ray_cases import (MESHES, interior_points, unique_edges, assert_matches_oracle, random_rays,
                       scene_case, SceneCase)


def packet_keys(directions: np.ndarray) -> np.ndarray:
    """What prepare_packet compares between lanes: the axis of largest |d|
    (kz, ties as the kernel breaks them) and the sign bits of the direction."""
    a = np.abs(directions)
    kz = np.where((a[:, 0] >= a[:, 1]) & (a[:, 0] >= a[:, 2]), 0, np.where(a[:, 1] >= a[:, 2], 1, 2))
    return kz * 8 + (np.signbit(directions) * [1, 2, 4]).sum(axis=1)


def coherent_fraction(directions: np.ndarray, packet_size: int) -> float:
    """Fraction of the whole packets whose lanes prepare_packet accepts."""
    whole = len(directions) // packet_size * packet_size
    keys = packet_keys(directions[:whole]).reshape(-1, packet_size)
    return float(np.mean(np.all(keys == keys[:, :1], axis=1)))


def expected_packets(directions: np.ndarray, packet_size: int, origins=None, tree=None) -> int:
    """Work-items whose rays the kernel should trace as one packet: their
    lanes share packet_keys, their slopes across kz (d[kx] / d[kz] and
    d[ky] / d[kz]) lie within 1/4 of each other, and, given the origins and
    the tree, their interval ray's origins (moved along the rays onto the
    plane across kz through the middle of theirs, where that brings them
    closer: packet.h's interval_origins) span at most 1/16 of the scene's
    largest extent on each axis (packet_compact).  A last, part-full packet
    repeats its last ray in the lanes past the end."""
    keys = packet_keys(directions)
    pad = -len(keys) % packet_size
    keys = np.concatenate([keys, np.repeat(keys[-1:], pad)]).reshape(-1, packet_size)
    whole = np.all(keys == keys[:, :1], axis=1)

    def lanes(a):
        a = np.concatenate([a, np.repeat(a[-1:], pad, 0)]).astype(np.float32)
        return a.reshape(-1, packet_size, 3)[whole]

    spread = lambda a: a.max(axis=1) - a.min(axis=1)  # noqa: E731
    d = lanes(directions)
    kz = keys[whole, 0] // 8
    rows = np.arange(len(d))
    dkz = d[rows, :, kz]
    with np.errstate(all="ignore"):
        turn = [spread(d[rows, :, (kz + k) % 3] / dkz) for k in (1, 2)]
    narrow = (turn[0] <= np.float32(0.25)) & (turn[1] <= np.float32(0.25))
    if origins is not None:
        o = lanes(origins)
        okz = o[rows, :, kz]
        mid = np.float32(0.5) * (okz.min(axis=1) + okz.max(axis=1))
        with np.errstate(all="ignore"):
            move = (mid[:, None] - okz) * (np.float32(1) / dkz)
            moved = o + move[..., None] * d
        moved[rows, :, kz] = mid[:, None]
        closer = np.isfinite(moved).all(axis=(1, 2)) & (
            spread(moved).sum(axis=1) < spread(o).sum(axis=1))
        o = np.where(closer[:, None, None], moved, o)
        scene = np.max(tree.bounds_hi.astype(np.float32) - tree.bounds_lo.astype(np.float32))
        narrow &= np.all(spread(o) <= scene * np.float32(1 / 16), axis=1)
    whole[whole] = narrow
    return int(np.sum(whole))


def traced(q: RayQuery, query: str, case, origins, directions, **limits):
    """q's query, checking that the kernel formed exactly the packets expected."""
    q.count_packets = True
    tree = built.tree(case.scene)
    result = getattr(q, query)(tree, origins, directions, **limits)
    expected = (expected_packets(directions, q.packet_size, origins, tree)
                if q.packet_size > 1 else 0)
    assert q.last_packets == expected
    return result


def camera_rays(case, width: int, height: int):
    """Row-major pinhole rays (40 degrees) from outside the box, looking at its centre."""
    centre = (case.lo + case.hi) / 2
    eye = centre + np.array([0.2, 0.3, 1.0]) / np.linalg.norm([0.2, 0.3, 1.0]) * 1.3 * case.extent
    forward = (centre - eye) / np.linalg.norm(centre - eye)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    half = np.tan(np.radians(20.0))
    x = (2 * (np.arange(width) + 0.5) / width - 1) * half * width / height
    y = (1 - 2 * (np.arange(height) + 0.5) / height) * half
    directions = (forward + x[None, :, None] * right + y[:, None, None] * up).reshape(-1, 3)
    origins = np.broadcast_to(eye, directions.shape)
    return origins.astype(np.float32), directions.astype(np.float32)


def packet_query(scene, packet_size: int) -> RayQuery:
    """A RayQuery of ``packet_size`` rays a work-item on ``scene``'s device;
    skips where the device cannot compile that packet (its probe fell back:
    PyPI's PoCL 3.0 on a Zen 4 host runs packet1 only), as these tests are
    about packets."""
    q = RayQuery(built.runtime(scene), packet_size=packet_size)
    if q.packet_size != packet_size:
        pytest.skip(f"{q.rt.device.id} cannot run {packet_size}-ray packets "
                    f"(it runs {q.packet_size})")
    return q


def query(case, packet_size: int) -> RayQuery:
    return packet_query(case.scene, packet_size)


@pytest.mark.parametrize("packet_size", PACKET_SIZES)
@pytest.mark.parametrize("name", ["knight", "bunny_small", "teapot", "cube"])
def test_camera_rays_match_oracle(name, packet_size):
    case = scene_case(name)
    origins, directions = camera_rays(case, 48, 32)
    if packet_size > 1:  # most rays go in packets, some one by one (kz changes across the view)
        assert 0.5 < coherent_fraction(directions, packet_size) < 1.0
    q = query(case, packet_size)
    hits = traced(q, "intersect", case, origins, directions)
    assert_matches_oracle(case, hits, origins, directions)
    assert 0.1 < hits.hit.mean(), "the camera should see the mesh"
    np.testing.assert_array_equal(traced(q, "occluded", case, origins, directions), hits.hit)
    # per-ray limits that vary within packets: a tmax that cuts off about half
    # of the hits, and a tmin that skips the nearest surface of some rays
    rng = np.random.default_rng(3)
    tmax = np.where(hits.hit, hits.t * rng.uniform(0.5, 1.5, len(hits)), np.inf).astype(np.float32)
    cut = traced(q, "intersect", case, origins, directions, tmax=tmax)
    assert_matches_oracle(case, cut, origins, directions, tmax=tmax)
    assert 0 < cut.hit.sum() < hits.hit.sum()
    np.testing.assert_array_equal(traced(q, "occluded", case, origins, directions, tmax=tmax),
                                  cut.hit)
    tmin = np.where(hits.hit & (rng.random(len(hits)) < 0.5), hits.t * 1.001, 0).astype(np.float32)
    beyond = traced(q, "intersect", case, origins, directions, tmin=tmin)
    assert_matches_oracle(case, beyond, origins, directions, tmin=tmin)
    assert np.any(beyond.t[tmin > 0] > hits.t[tmin > 0])  # some rays went on to a farther surface


@pytest.mark.parametrize("packet_size", [8, 16])
def test_paced_launches_keep_the_callers_packets(packet_size):
    """A call paced by the last call of its kernel (Engine.paced) at a size
    that is not a whole number of packets still launches whole packets: each
    packet is the caller's consecutive rays, so the packets formed (and the
    hits) do not depend on how fast the last call ran."""
    case = scene_case("bunny_small")
    origins, directions = camera_rays(case, 48, 32)
    q = query(case, packet_size)
    whole = traced(q, "intersect", case, origins, directions)
    for paced in (1, packet_size + 3, 5 * packet_size - 1):
        q.engine.paced.update(closest=paced, any=paced)
        hits = traced(q, "intersect", case, origins, directions)
        np.testing.assert_array_equal(hits.t, whole.t)
        np.testing.assert_array_equal(hits.prim_id, whole.prim_id)
        np.testing.assert_array_equal(traced(q, "occluded", case, origins, directions), whole.hit)


@pytest.mark.parametrize("packet_size", [8, 16])
@pytest.mark.parametrize("mixed", [False, True], ids=["coherent", "mixed"])
def test_partial_and_mixed_packets_match_oracle(packet_size, mixed):
    """Ray counts that leave the last packet part-full, on camera rays, and on
    packets whose lanes mix coherent and random rays (traced one by one)."""
    case = scene_case("knight")
    origins, directions = camera_rays(case, 96, 64)  # 16 pixels of a row turn 0.18 apart
    if mixed:
        wild_o, wild_d = random_rays(case, len(origins), seed=9)
        every_fifth = np.arange(len(origins)) % 5 == 0
        origins, directions = origins.copy(), directions.copy()
        origins[every_fifth], directions[every_fifth] = wild_o[every_fifth], wild_d[every_fifth]
    q = query(case, packet_size)
    for count in (1, packet_size - 1, packet_size + 1, 3 * packet_size + 5, len(origins)):
        o, d = origins[:count], directions[:count]
        hits = traced(q, "intersect", case, o, d)
        assert_matches_oracle(case, hits, o, d)
        np.testing.assert_array_equal(traced(q, "occluded", case, o, d), hits.hit)
    if not mixed:
        assert q.last_packets > 0


@pytest.mark.parametrize("packet_size", [8, 16])
@pytest.mark.parametrize("name", ["knight", "armadillo"])
def test_rays_from_inside_in_packets_always_hit(name, packet_size):
    """test_watertight's rays at vertices and edge midpoints, ordered so that
    they form packets."""
    mesh = hlbvh_cl.Mesh.load(MESHES / f"{name}.ply")
    scene = hlbvh_cl.Scene([mesh])
    q = packet_query(scene, packet_size)
    vertices = mesh.vertices.astype(np.float64)
    edges = unique_edges(mesh.faces)
    midpoints = (vertices[edges[:, 0]] + vertices[edges[:, 1]]) / 2
    for origin in interior_points(mesh, 2, seed=4):
        for what, points in (("vertices", vertices), ("edge midpoints", midpoints)):
            directions = (points - origin).astype(np.float32)
            directions = directions[np.any(directions != 0, axis=1)]
            # by packet class, then by slope (eighths) within it: packets of near directions
            kz, rows = packet_keys(directions) // 8, np.arange(len(directions))
            slopes = [np.floor(8 * directions[rows, (kz + k) % 3] / directions[rows, kz])
                      for k in (1, 2)]
            directions = directions[np.lexsort((slopes[1], slopes[0], packet_keys(directions)))]
            assert coherent_fraction(directions, packet_size) > 0.6
            origins = np.repeat(origin[None].astype(np.float32), len(directions), 0)
            q.count_packets = True
            hits = q.intersect(built.tree(scene), origins, directions)
            expected = expected_packets(directions, packet_size)
            assert q.last_packets == expected > 0
            missed = np.flatnonzero(~hits.hit)
            assert len(missed) == 0, (f"{name}: {len(missed)} of {len(directions)} rays from "
                                      f"inside aimed at {what} escaped (first: directions "
                                      f"{directions[missed[:3]].tolist()})")
            assert q.occluded(built.tree(scene), origins, directions).all()


@pytest.mark.parametrize("zero", [0.0, -0.0], ids=["+0", "-0"])
@pytest.mark.parametrize("name", ["cube", "knight"])
def test_axis_parallel_packets_match_oracle(name, zero):
    """Packets of rays along -z whose x and y components are 0 (the inverse
    direction is infinite, and the interval test of a node's children meets
    0 * inf) and whose origins sit on a lattice through the mesh's bounds,
    so lanes start on box planes, and spread so that part of each packet
    misses: every answer is the oracle's, and the rays do form packets."""
    case = scene_case(name)
    # rows of 160 origins 1/128 of the box apart, through its planes at 0 and 128: each
    # packet's 8 lanes within 1/16 of the mesh's extent (origins_compact)
    x, y = np.meshgrid(case.lo[0] + np.arange(160) / 128 * (case.hi[0] - case.lo[0]),
                       case.lo[1] + np.linspace(0.0, 1.0, 16) * (case.hi[1] - case.lo[1]))
    origins = np.stack([x.ravel(), y.ravel(), np.full(x.size, case.hi[2] + 1.0)], axis=1)
    origins = origins.astype(np.float32)
    directions = np.tile(np.array([zero, zero, -1.0], np.float32), (len(origins), 1))
    q = query(case, 8)
    hits = traced(q, "intersect", case, origins, directions)
    assert q.last_packets == len(origins) // 8
    assert_matches_oracle(case, hits, origins, directions)
    assert 0 < hits.hit.sum() < len(origins)
    np.testing.assert_array_equal(traced(q, "occluded", case, origins, directions), hits.hit)


def _strip(x0: float, z: float, n: int = 8) -> hlbvh_cl.Mesh:
    """The unit grid x in [x0, x0 + n], y in [-n, n] at height z."""
    vertices = [(x0 + i, j, z) for i in range(n + 1) for j in range(-n, n + 1)]
    at = lambda i, j: i * (2 * n + 1) + j + n  # noqa: E731
    faces = []
    for i in range(n):
        for j in range(-n, n):
            faces += [[at(i, j), at(i + 1, j), at(i + 1, j + 1)],
                      [at(i, j), at(i + 1, j + 1), at(i, j + 1)]]
    return hlbvh_cl.Mesh(np.array(vertices, float), faces, name="strip")


@pytest.mark.parametrize("packet_size", [8, 16])
@pytest.mark.parametrize("sign", [1.0, -1.0], ids=["+0", "-0"])
def test_packets_with_zero_components_on_a_node_plane(sign, packet_size):
    """Lanes whose direction is 0 along x and whose origins lie on the
    plane x = x0 where a strip of triangles starts (the box of a node's child
    starts there): each such lane ignores that plane, and must still hit
    the strip's edge, in packets where other lanes move along x (the
    packet's interval ray must keep the child; kernels/query/rays/packet.h).  With +0
    some lanes start far apart along z, so the interval ray's origins move;
    with -0 none move."""
    zero = np.float32(0.0) * np.float32(sign)
    if sign > 0:
        scene = hlbvh_cl.Scene([_strip(0.0, -7.0)])
        lanes = [((0, .5, -10), (zero, 0, 1))] * 4 + [((0, .5, 0), (.25, 0, 1))] * 2 \
            + [((0, .5, 10), (zero, 0, 1))] * 2
    else:
        scene = hlbvh_cl.Scene([_strip(3.0, -7.0)])
        lanes = [((3, .5, -10), (zero, 0, 1))] * 4 + [((3, .5, -10), (-.25, 0, 1))] * 4
    origins = np.array([o for o, _ in lanes] * (packet_size // 8), np.float32)
    directions = np.array([d for _, d in lanes] * (packet_size // 8), np.float32)
    assert (np.signbit(directions[:, 0]) == (sign < 0)).all()  # one packet class
    want = np.array([3.0 if d[0] == 0 and o[2] == -10 else np.inf for o, d in lanes]
                    * (packet_size // 8), np.float32)
    tree = built.tree(scene)
    for size in (1, packet_size):
        q = packet_query(scene, size)
        q.count_packets = True
        hits = q.intersect(tree, origins, directions)
        assert q.last_packets == (1 if size > 1 else 0)
        np.testing.assert_array_equal(hits.t, want, err_msg=f"packets of {size}")
        np.testing.assert_array_equal(q.occluded(tree, origins, directions), want < np.inf)


STEPS = """#include "query/rays/packet.h"
__kernel void steps(__global const float* x, __global float* up, __global float* down)
{
    size_t i = get_global_id(0);
    up[i] = float_above(x[i]);
    down[i] = float_below(x[i]);
}
"""


def test_float_steps_are_nextafter(suite_device):
    """query/rays/packet.h's float_above and float_below (the packet box's one-ulp
    growth, by the bits) give C's nextafter toward +inf and -inf bit for bit,
    as numpy computes it: zeros of both signs, subnormals, the largest
    floats, infinities and NaN."""
    import pyopencl as cl
    from hlbvh_cl.device.runtime import quiet_build, runtime
    from hlbvh_cl.core.paths import kernel_dir
    rt = runtime(suite_device)
    if RayQuery(rt, packet_size=8).packet_size != 8:
        pytest.skip(f"{rt.device.id} cannot compile 8-ray packets")
    options = ["-I", str(kernel_dir())] + [f"-D{name}={value}" for name, value in
                                           {**rt.variant.defines, "PACKET_SIZE": 8}.items()]
    program = quiet_build(cl.Program(rt.context, STEPS), options, rt.device.cl_device)
    big, tiny = np.finfo(np.float32).max, np.finfo(np.float32).smallest_subnormal
    x = np.array([0.0, -0.0, tiny, -tiny, 2 * tiny, 1.17549435e-38, -5e-39, 1.0, -1.0, 3.5,
                  -2.75e10, big, -big, np.inf, -np.inf, np.nan], np.float32)
    flags = cl.mem_flags
    source = cl.Buffer(rt.context, flags.READ_ONLY | flags.COPY_HOST_PTR, hostbuf=x)
    up, down = (cl.Buffer(rt.context, flags.WRITE_ONLY, x.nbytes) for _ in range(2))
    program.steps(rt.queue, (len(x),), None, source, up, down)
    for buffer, toward in ((up, np.inf), (down, -np.inf)):
        got = np.empty_like(x)
        cl.enqueue_copy(rt.queue, got, buffer)
        with np.errstate(over="ignore"):  # FLT_MAX steps to inf
            want = np.nextafter(x, np.float32(toward))
        same = (got.view(np.int32) == want.view(np.int32)) | (np.isnan(got) & np.isnan(want))
        assert same.all(), (toward, x[~same], got[~same], want[~same])


@pytest.mark.parametrize("packet_size", [8, 16])
@pytest.mark.parametrize("name", ["knight", "teapot", "grid"])
def test_interleaved_walks_give_the_walks_one_by_one_s_answers(monkeypatch, name, packet_size):
    """A CPU work-item's rays that do not go as one packet walk interleaved
    (query/walk/walk.h's walks) where the tree is larger than a core's cache
    (engine.INTERLEAVED_MIN_TREE_BYTES, here forced to 0): the same hits
    and occlusion, bit for bit, as walked one after the other, and the
    oracle's; and the same counts and all hits (the walks with a state
    each), where max_hits=2 shrinks a ray's limit once its segment fills;
    the kernels built either way."""
    from hlbvh_cl.query import engine
    from hlbvh_cl.query.all_hits import AllHitsQuery
    case = scene_case(name)
    origins, directions = random_rays(case, 3000, seed=7)
    tree = built.tree(case.scene)
    answers = []
    for smallest in (0, 2**62):
        monkeypatch.setattr(engine, "INTERLEAVED_MIN_TREE_BYTES", smallest)
        q = packet_query(case.scene, packet_size)
        defines = engine.kernel_defines(q.rt, tree, q.variant, q.packet_size)
        assert ("INTERLEAVED_WALKS" in defines) == (smallest == 0 and not q.rt.profile.gpu)
        hits = q.intersect(tree, origins, directions)
        every = AllHitsQuery(q)
        answers.append((hits, q.occluded(tree, origins, directions),
                        every.count(tree, origins, directions),
                        [every.intersect_all(tree, origins, directions, max_hits=k)
                         for k in (None, 2)]))
    (interleaved, blocked, counts, all_hits), (alone, alone_blocked, alone_counts,
                                               alone_all_hits) = answers
    for field in ("t", "prim_id", "geom_id", "u", "v", "normal", "points"):
        np.testing.assert_array_equal(getattr(interleaved, field), getattr(alone, field))
    np.testing.assert_array_equal(blocked, alone_blocked)
    np.testing.assert_array_equal(blocked, interleaved.hit)
    assert_matches_oracle(case, interleaved, origins, directions)
    np.testing.assert_array_equal(counts, alone_counts)
    if name == "grid":
        assert counts.max() == 1  # one sheet: a ray crosses it once
    else:
        assert (counts > 2).any()  # rays that cross a closed mesh more than once
    for got, want in zip(all_hits, alone_all_hits):
        for field in ("offsets", "ray_index", "t", "prim_id", "geom_id", "u", "v"):
            np.testing.assert_array_equal(getattr(got, field), getattr(want, field))
    np.testing.assert_array_equal(all_hits[0].counts, counts)
    assert (all_hits[1].counts == np.minimum(counts, 2)).all()


def test_ties_at_shared_vertices_give_the_first_triangle_every_way(monkeypatch):
    """Rays from one eye through the vertices of nested subdivided boxes:
    each closest hit is at one t on every triangle around the vertex (or the
    edge) it meets first.  Of those the triangle first in the tree wins,
    so packets of 1, 8 and 16, walks interleaved or not, and a ray alone or
    among rays that make it walk one by one, give the same t, prim_id, u
    and v (a walk's order once decided)."""
    from hlbvh_cl.query import engine
    trimesh = pytest.importorskip("trimesh")
    box = trimesh.creation.box(extents=(2, 2, 2)).subdivide().subdivide()
    vertices = np.concatenate([box.vertices * s for s in (1.0, 0.75, 0.5, 0.25, 0.125)])
    faces = np.concatenate([box.faces + len(box.vertices) * k for k in range(5)])
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(vertices, faces, name="boxes")])
    eye = np.float32([0, 0, 5])
    targets = vertices[np.lexsort((vertices[:, 0], vertices[:, 1]))]
    directions = (targets - eye).astype(np.float32)
    origins = np.broadcast_to(eye, directions.shape)
    # each ray first, then 15 reversed rays: its work-item walks one by one
    mixed = np.concatenate([directions[:, None], np.repeat(-directions[:, None], 15, 1)],
                           axis=1).reshape(-1, 3)
    tree = built.tree(scene)
    fields = ("t", "prim_id", "u", "v")
    answers = []
    for smallest in (0, 2**62):
        monkeypatch.setattr(engine, "INTERLEAVED_MIN_TREE_BYTES", smallest)
        for packet_size in (1, 8, 16):
            q = packet_query(scene, packet_size)
            hits = q.intersect(tree, origins, directions)
            answers.append([getattr(hits, name) for name in fields])
            hits = q.intersect(tree, np.broadcast_to(eye, mixed.shape), mixed)
            answers.append([getattr(hits, name)[::16] for name in fields])
    assert np.isfinite(answers[0][0]).mean() > 0.9
    for other in answers[1:]:
        for name, got, want in zip(fields, other, answers[0]):
            np.testing.assert_array_equal(got, want, name)


def test_root_phase_gives_the_walks_one_by_one_s_answers(monkeypatch):
    """A CPU work-item's rays that do not go as one packet first have the
    root's leaves tested for all of them at once, a vector lane each
    (kernels/query/rays/trace.h's root phase; here the ground's, which the
    SAH top keeps at the root), and their walks start from what it found:
    the same closest hits, bit for bit, as one ray a work-item walked alone
    (packets of 1, no root phase), walks interleaved or not, with and
    without limits that cut some hits off, and the oracle's.  The rays end
    on the ground, on a mesh in front of it, or on nothing.  Any hit takes
    the phase too: a ray is occluded exactly where it has a closest hit."""
    from hlbvh_cl.query import engine
    from render_scene import render_meshes
    case = SceneCase(render_meshes())
    tree = built.tree(case.scene)
    root = tree.read_nodes(built.runtime(case.scene).queue)[0]
    ground = len(case.meshes) - 1
    assert (root["count"] > 0).any(), "the root holds no leaf: this test would not test the phase"
    wild_o, wild_d = random_rays(case, 2000, seed=11)
    rng = np.random.default_rng(12)  # and rays from above at the meshes, some past them
    meshes = np.concatenate([m.vertices for m in case.meshes[:-1]])
    lo, hi = meshes.min(axis=0), meshes.max(axis=0)
    above = lo + rng.random((1000, 3)) * (hi - lo) * [3, 1, 3] - (hi - lo) * [1, -2, 1]
    aimed = lo + rng.random((1000, 3)) * (hi - lo) - above
    origins = np.concatenate([wild_o, above]).astype(np.float32)
    directions = np.concatenate([wild_d, aimed]).astype(np.float32)
    tmin = np.where(np.arange(len(origins)) % 3 == 0, 0.25, 0.0).astype(np.float32)
    tmax = np.where(np.arange(len(origins)) % 4 == 0, 0.9, np.inf).astype(np.float32)
    fields = ("t", "geom_id", "prim_id", "u", "v", "normal")
    answers = []
    for smallest in (0, 2**62):
        monkeypatch.setattr(engine, "INTERLEAVED_MIN_TREE_BYTES", smallest)
        for packet_size in (1, 8, 16):
            q = packet_query(case.scene, packet_size)
            for limits in ({}, {"tmin": tmin, "tmax": tmax}):
                hits = q.intersect(tree, origins, directions, **limits)
                answers.append([getattr(hits, name) for name in fields])
                np.testing.assert_array_equal(q.occluded(tree, origins, directions, **limits),
                                              np.isfinite(hits.t))
                if packet_size == 1 and smallest == 0:
                    assert_matches_oracle(case, hits, origins, directions, **limits)
    first = answers[0][1]
    assert 0.1 < (first == ground).mean() and 0.1 < ((first >= 0) & (first != ground)).mean()
    assert (first < 0).any()
    for at, other in enumerate(answers[2:], 2):
        for name, got, want in zip(fields, other, answers[at % 2]):
            np.testing.assert_array_equal(got, want, name)


def test_two_lane_groups_a_work_item_give_one_group_s_answers(monkeypatch):
    """On a flat scene whose walks go interleaved, a CPU work-item traces two
    groups of rays (query/rays.cl's LANE_GROUPS, rays.py's lane_groups),
    their walks interleaved together: the same hits, occlusion and records,
    bit for bit, as one group a work-item, for batches that end inside a
    group or leave the second empty, and for launches cut small (their
    offsets count whole work-items)."""
    from hlbvh_cl.query import engine, rays
    from render_scene import render_meshes
    case = SceneCase(render_meshes())
    tree = built.tree(case.scene)
    monkeypatch.setattr(engine, "INTERLEAVED_MIN_TREE_BYTES", 0)
    q = packet_query(case.scene, 16)
    if q.rt.profile.gpu:  # GPUs hide misses with other work-items: no interleaved walks
        pytest.skip("the GPU profile walks no rays interleaved, so takes one group")
    assert rays.lane_groups(q.rt, tree, 16) == 2
    origins, directions = random_rays(case, 700, seed=5)
    fields = ("t", "geom_id", "prim_id", "u", "v", "normal", "points")
    answers = {}
    for groups in (2, 1):
        monkeypatch.setattr(rays, "lane_groups", lambda rt, tree, packet, g=groups: g)
        q = packet_query(case.scene, 16)
        for count in (1, 15, 17, 33, 700):
            for most in (None, 48):
                q.max_rays_per_launch = most or rays.MAX_RAYS_PER_LAUNCH
                hits = q.intersect(tree, origins[:count], directions[:count])
                occluded = q.occluded(tree, origins[:count], directions[:count])
                answers.setdefault((count, most), []).append(
                    [getattr(hits, name) for name in fields] + [occluded])
                # rays on the device: launches at global offsets of whole work-items
                on_device = [cl_array.to_device(q.rt.queue, np.ascontiguousarray(a[:count]))
                             for a in (origins, directions)]
                hits = q.intersect(tree, *on_device)
                answers.setdefault((count, most, "device"), []).append(
                    [getattr(hits, name).get() for name in fields]
                    + [q.occluded(tree, *on_device).get()])
    for key, (two, one) in answers.items():
        for name, got, want in zip((*fields, "occluded"), two, one):
            np.testing.assert_array_equal(got, want, f"{name}, {key}")
    for name, got, want in zip(fields, answers[700, 48][0], answers[700, 48, "device"][0]):
        np.testing.assert_array_equal(got, want, f"{name}: the device's rays")
    hits = packet_query(case.scene, 16).intersect(tree, origins, directions)
    assert_matches_oracle(case, hits, origins, directions)


@pytest.mark.parametrize("compact", [False, True], ids=["triangles", "compact"])
@pytest.mark.parametrize("name", ["knight", "split knight", "grid", "nested boxes"])
def test_leaf_quads_give_the_one_by_one_triangle_tests_answers(monkeypatch, name, compact):
    """On CPUs a single ray's walk tests a leaf's triangles four at a time,
    one vector lane each, and takes the lanes that pass in index order
    (kernels/query/rays/quad.h, engine.leaf_quads): the same closest hits,
    occlusion, counts and all hits, bit for bit, as the kernels built to test
    one triangle at a time, for packets of 1 and 16 and with limits that cut
    some hits off; and the oracle's.  In either leaf layout: Triangle
    records, or a compact tree's, whose lanes take their corners through
    its indices.  Besides random rays, rays aim at the centres of the
    triangles in the tree's largest leaves (the split knight, every edge cut
    in 5, has leaves of 5 and more: two quads), and the nested boxes' rays
    go from one eye through their shared vertices, ties that the first
    triangle in the tree wins whichever lane found it."""
    from hlbvh_cl.query import engine
    from hlbvh_cl.io.split import split_edges
    from hlbvh_cl.query.all_hits import AllHitsQuery
    if name == "split knight":
        knight = scene_case("knight").meshes[0]
        case = SceneCase([hlbvh_cl.Mesh(*split_edges(knight.vertices, knight.faces, 5),
                                        name="split knight")])
    elif name == "nested boxes":
        trimesh = pytest.importorskip("trimesh")
        box = trimesh.creation.box(extents=(2, 2, 2)).subdivide().subdivide()
        vertices = np.concatenate([box.vertices * s for s in (1.0, 0.75, 0.5, 0.25)])
        faces = np.concatenate([box.faces + len(box.vertices) * k for k in range(4)])
        case = SceneCase([hlbvh_cl.Mesh(vertices, faces, name="nested boxes")])
    else:
        case = scene_case(name)
    if compact:
        case = SceneCase(case.meshes, scene=hlbvh_cl.Scene(case.meshes, compact=True))
    tree = built.tree(case.scene)
    assert tree.indexed == compact
    rt = built.runtime(case.scene)
    nodes = tree.read_nodes(rt.queue)
    triangles, _ = tree.read_triangles(rt.queue)
    counts, firsts = nodes["count"].ravel(), nodes["child"].ravel()
    largest = np.argsort(counts)[::-1][:60]
    assert counts[largest[0]] >= (5 if name == "split knight" else 2), counts.max()
    within = np.concatenate([np.arange(firsts[k], firsts[k] + counts[k]) for k in largest
                             if counts[k] > 1])
    centres = np.stack([triangles[v] for v in ("v0", "v1", "v2")]).mean(axis=0)[within]
    origins, directions = random_rays(case, 1500, seed=5)
    aimed_from = origins[:len(centres)]
    origins = np.concatenate([origins, aimed_from]).astype(np.float32)
    directions = np.concatenate([directions, centres - aimed_from]).astype(np.float32)
    extra = 0
    if name == "nested boxes":
        eye = np.float32([0, 0, 5])
        vertices = case.meshes[0].vertices
        extra = len(vertices)
        origins = np.concatenate([origins, np.broadcast_to(eye, vertices.shape)])
        directions = np.concatenate([directions, (vertices - eye).astype(np.float32)])
    tmin = np.where(np.arange(len(origins)) % 3 == 0, 0.05, 0.0).astype(np.float32)
    tmax = np.where(np.arange(len(origins)) % 4 == 0, 0.5, np.inf).astype(np.float32)
    fields = ("t", "geom_id", "prim_id", "u", "v", "normal")
    answers = {}
    for quads in (True, False):
        monkeypatch.setattr(engine, "leaf_quads", lambda rt, quads=quads: quads)
        for packet_size in (1, 16):
            q = RayQuery(rt, packet_size=packet_size)
            defines = engine.kernel_defines(q.rt, tree, q.variant, q.packet_size)
            assert ("LEAF_QUADS" in defines) == quads
            every = AllHitsQuery(q)
            for limits in ({}, {"tmin": tmin, "tmax": tmax}):
                hits = q.intersect(tree, origins, directions, **limits)
                if quads and q.packet_size == 1:
                    assert_matches_oracle(case, hits, origins, directions, **limits)
                found = every.intersect_all(tree, origins, directions, **limits)
                answers[quads, q.packet_size, len(limits)] = (
                    [getattr(hits, f) for f in fields]
                    + [q.occluded(tree, origins, directions, **limits),
                       every.count(tree, origins, directions, **limits)]
                    + [getattr(found, f) for f in ("offsets", "ray_index", "t", "prim_id", "u",
                                                   "v")])
    aimed = answers[True, 1, 0][2][len(origins) - len(centres) - extra:len(origins) - extra]
    assert (aimed >= 0).mean() > 0.9  # the rays at the largest leaves' triangles hit
    for (quads, packet_size, limited), got in answers.items():
        want = answers[False, packet_size, limited]
        for at, (a, b) in enumerate(zip(got, want)):
            np.testing.assert_array_equal(a, b, f"{name}: field {at}, packets of {packet_size}")
