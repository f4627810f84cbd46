"""Instanced scenes (hlbvh_cl.build.instances, kernels/query/walk/instance_leaf.h) against the same
scene flattened with its transforms baked in: a float64 numpy brute force on
small meshes, Embree on the bunny; masks against a filtered brute force;
invariants of both levels; and the errors bad instances get."""
from __future__ import annotations

from types import SimpleNamespace

import warnings

import numpy as np
import pyopencl as cl
import pytest
import trimesh

import hlbvh_cl
from hlbvh_cl.query.rays import RayQuery
import built
from instance_cases import flattened, random_transforms, rotation
from invariants import check_tree
from oracle import brute_force_all_hits, brute_force_intersect, brute_force_occluded
from point_oracle import brute_force_closest, brute_force_winding, closest_on_triangles


def _rays_at_centroids(rng, vertices, faces, count: int, reach: float = 15.0):
    """Rays from random points on a sphere of radius ``reach`` (outside the
    instances, so t is not tiny: a float32 origin is only good to a relative
    2^-24 of its coordinates) towards random triangles' centroids (well
    inside them, so no ray grazes an edge where rounding picks a side)."""
    chosen = rng.integers(0, len(faces), count)
    target = vertices[faces[chosen]].mean(axis=1)
    origins = rng.normal(size=(count, 3))
    origins *= reach / np.linalg.norm(origins, axis=1, keepdims=True)
    return origins.astype(np.float32), (target - origins).astype(np.float32)


def _steep(directions, normals) -> np.ndarray:
    """Rays that meet their triangle at more than a grazing angle: where t is
    well conditioned (at a grazing angle the float32 rounding of any
    position becomes a large error along the ray)."""
    cosine = (directions * normals).sum(axis=1) / (
        np.linalg.norm(directions, axis=1) * np.linalg.norm(normals, axis=1))
    return np.abs(cosine) > 0.2


def _small_meshes():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    box = trimesh.creation.box(extents=(1.0, 0.5, 2.0))
    return [hlbvh_cl.Mesh(sphere.vertices, sphere.faces, name="sphere"),
            hlbvh_cl.Mesh(box.vertices, box.faces, name="box")]


def _check_against_oracle(scene, meshes, instance_meshes, maps, rng, count=3000, mask=None,
                          visible=None):
    vertices, faces, owner, prim = flattened(meshes, instance_meshes, maps)
    origins, directions = _rays_at_centroids(rng, vertices, faces, count)
    keep = np.ones(len(faces), bool) if visible is None else visible[owner]
    hits = scene.intersect(origins, directions, mask=mask)
    want = brute_force_intersect(vertices, faces[keep], origins, directions)
    index = np.flatnonzero(keep)
    found = want["prim"] >= 0
    assert (hits.hit == found).all()
    k = index[want["prim"][found]]
    np.testing.assert_array_equal(hits.instance_id[found], owner[k])
    np.testing.assert_array_equal(hits.geom_id[found], instance_meshes[owner[k]])
    np.testing.assert_array_equal(hits.prim_id[found], prim[k])
    # t to 1e-5 where it is well conditioned
    steep = _steep(directions[found], want["normal"][found])
    np.testing.assert_allclose(hits.t[found][steep], want["t"][found][steep], rtol=1e-5)
    # world normals: cross(v1 - v0, v2 - v0) of the mapped vertices
    np.testing.assert_allclose(hits.normal[found], want["normal"][found], atol=1e-4)
    np.testing.assert_array_equal(
        scene.occluded(origins, directions, mask=mask),
        brute_force_occluded(vertices, faces[keep], origins, directions))
    return hits


@pytest.fixture(scope="module")
def small():
    return _small_meshes()


def test_mirrored_scaled_rotated_overlapping_instances_match_the_brute_force(small,
                                                                              suite_device):
    rng = np.random.default_rng(25)
    maps = random_transforms(rng, 12, spread=2.0)
    instance_meshes = np.arange(12) % 2
    scene = hlbvh_cl.Scene(small, device=suite_device,
                           instances=[(int(m), a) for m, a in zip(instance_meshes, maps)])
    hits = _check_against_oracle(scene, small, instance_meshes, maps, rng)
    assert len(set(hits.instance_id[hits.hit].tolist())) == 12  # every instance was hit


@pytest.mark.parametrize("case", ["mirror of one mesh", "faces in another order"])
@pytest.mark.parametrize("packet", [1, 8, 16])
def test_instances_that_coincide_keep_one_instance_s_whole_hit(case, packet, suite_device):
    """Two instances whose surfaces coincide are hit at one t by every ray:
    the record is one instance's own triangle, t, u and v, and the first
    walked keeps the tie (docs/queries.md).  Tree order broke ties across
    the two meshes, and a tie replaced the triangle and u, v but not the
    instance: 93 of 200 rays named a triangle they do not hit."""
    if case == "mirror of one mesh":
        ico = trimesh.creation.icosphere(subdivisions=2)
        meshes = [hlbvh_cl.Mesh(ico.vertices, ico.faces)]
        mirror = np.eye(3, 4)
        mirror[0, 0] = -1.0
        instance_meshes, maps = [0, 0], [np.eye(3, 4), mirror]
    else:
        square = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
        faces = np.array([[0, 1, 2], [0, 2, 3]])
        meshes = [hlbvh_cl.Mesh(square, faces), hlbvh_cl.Mesh(square, faces[::-1].copy())]
        instance_meshes, maps = [0, 1], [np.eye(3, 4), np.eye(3, 4)]
    scene = hlbvh_cl.Scene(meshes, device=suite_device,
                           instances=list(zip(instance_meshes, maps)))
    vertices, faces, owner, prim = flattened(meshes, instance_meshes, maps)
    rng = np.random.default_rng(3)
    first = faces[owner == 0]
    targets = np.einsum("rk,rkd->rd", rng.dirichlet([1, 1, 1], 300),
                        vertices[first[rng.integers(0, len(first), 300)]])
    origins = rng.normal(size=(300, 3)) * 3.0
    origins[:, 2] = np.abs(origins[:, 2]) + 1.0  # the square is seen from above
    origins, directions = origins.astype(np.float32), (targets - origins).astype(np.float32)
    hits = RayQuery(built.runtime(scene), packet_size=packet).intersect(
        built.tree(scene), origins, directions)
    assert hits.hit.all()
    assert np.array_equal(hits.geom_id, np.asarray(instance_meshes)[hits.instance_id])
    # the named triangle of the named instance holds the ray's point at t, and
    # u, v are its barycentrics there (but on grazing rays, where float32's
    # u, v drift from float64's by up to ~1e-3)
    first_face = np.searchsorted(owner, np.arange(len(instance_meshes)))
    corners = vertices[faces[first_face[hits.instance_id] + hits.prim_id]]
    at_t = origins.astype(np.float64) + hits.t[:, None].astype(np.float64) * directions
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    normal = np.cross(e1, e2)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    offset = at_t - corners[:, 0]
    assert np.abs(np.einsum("rd,rd->r", offset, normal)).max() < 1e-5
    gram = np.stack([np.stack([np.einsum("rd,rd->r", a, b) for b in (e1, e2)], -1)
                     for a in (e1, e2)], -2)
    uv = np.linalg.solve(gram, np.stack([np.einsum("rd,rd->r", offset, e) for e in (e1, e2)],
                                        -1)[..., None])[..., 0]
    assert (uv >= -1e-5).all() and (uv.sum(axis=1) <= 1 + 1e-5).all()
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    steep = np.abs(np.einsum("rd,rd->r", unit, normal)) > 0.05
    np.testing.assert_allclose(np.stack([hits.u, hits.v], -1)[steep], uv[steep], atol=1e-5)
    # of the two instances' equal hits, the one walked first: the same for every packet size
    alone = RayQuery(built.runtime(scene), packet_size=1).intersect(built.tree(scene), origins,
                                                                   directions)
    assert np.array_equal(hits.instance_id, alone.instance_id)


def test_coherent_rays_trace_as_packets_through_rotated_instances(small, suite_device):
    """Camera rays: packets at the top, mapped per instance into packets or,
    where a rotation splits their direction signs, one ray at a time; the
    same hits as the brute force either way."""
    rng = np.random.default_rng(31)
    maps = random_transforms(rng, 10, spread=2.0)
    instance_meshes = np.arange(10) % 2
    scene = hlbvh_cl.Scene(small, device=suite_device,
                           instances=[(int(m), a) for m, a in zip(instance_meshes, maps)])
    side = np.linspace(-0.45, 0.45, 72)
    directions = np.stack(np.broadcast_arrays(side[:, None], side[None, :], -1.0), axis=-1)
    directions = directions.reshape(-1, 3).astype(np.float32)
    origins = np.array([0.3, -0.2, 9.0], np.float32)
    query = RayQuery(built.runtime(scene))  # the query a scene makes, counting packets
    query.count_packets = True
    hits = query.intersect(built.tree(scene), origins, directions)
    packets = query.last_packets
    vertices, faces, owner, prim = flattened(small, instance_meshes, maps)
    want = brute_force_intersect(vertices, faces, np.broadcast_to(origins, directions.shape),
                                 directions)
    found = want["prim"] >= 0
    assert found.mean() > 0.3
    np.testing.assert_array_equal(hits.hit, found)
    np.testing.assert_array_equal(hits.instance_id[found], owner[want["prim"][found]])
    np.testing.assert_array_equal(hits.prim_id[found], prim[want["prim"][found]])
    steep = _steep(directions[found], want["normal"][found])
    np.testing.assert_allclose(hits.t[found][steep], want["t"][found][steep], rtol=1e-5)
    np.testing.assert_array_equal(scene.occluded(origins, directions), found)
    if query.packet_size > 1:
        assert packets > 0, "no work-item traced its rays as a packet"


def test_4x4_transforms_and_set_transforms(small, suite_device):
    rng = np.random.default_rng(7)
    maps = random_transforms(rng, 6)
    four = np.tile(np.eye(4), (6, 1, 1))
    four[:, :3] = maps
    scene = hlbvh_cl.Scene(small, device=suite_device,
                           instances=[(k % 2, four[k]) for k in range(6)])
    np.testing.assert_array_equal(scene.transforms, maps)
    _check_against_oracle(scene, small, np.arange(6) % 2, maps, rng, count=1000)
    moved = random_transforms(rng, 3, spread=6.0)
    scene.set_transforms([1, 4, 5], moved)
    maps[[1, 4, 5]] = moved
    _check_against_oracle(scene, small, np.arange(6) % 2, maps, rng, count=1000)
    scene.set_transforms(2, four[0])  # one id, one 4x4
    maps[2] = maps[0]
    _check_against_oracle(scene, small, np.arange(6) % 2, maps, rng, count=1000)


def test_instance_masks_against_a_filtered_oracle(small, suite_device):
    rng = np.random.default_rng(3)
    maps = random_transforms(rng, 8)
    masks = np.array([1, 2, 4, 8, 3, 5, 0xFFFFFFFF, 0x80000000], np.uint32)
    instance_meshes = np.arange(8) % 2
    scene = hlbvh_cl.Scene(small, device=suite_device, masks=masks,
                           instances=[(int(m), a) for m, a in zip(instance_meshes, maps)])
    for ray_mask in (1, 2, 6, 0x80000000, 0):
        _check_against_oracle(scene, small, instance_meshes, maps, rng, count=800,
                              mask=ray_mask, visible=(masks & np.uint32(ray_mask)) != 0)
    # per-ray masks: each ray against only what it sees
    vertices, faces, owner, _ = flattened(small, instance_meshes, maps)
    origins, directions = _rays_at_centroids(rng, vertices, faces, 600)
    ray_masks = rng.choice([1, 2, 4, 8, 0], len(origins)).astype(np.uint32)
    hits = scene.intersect(origins, directions, mask=ray_masks)
    occluded = scene.occluded(origins, directions, mask=ray_masks)
    for value in np.unique(ray_masks):
        rows = ray_masks == value
        keep = ((masks & value) != 0)[owner]
        want = brute_force_intersect(vertices, faces[keep], origins[rows], directions[rows])
        np.testing.assert_allclose(hits.t[rows], want["t"], rtol=1e-5)
        np.testing.assert_array_equal(occluded[rows], want["prim"] >= 0)


def test_mesh_masks_of_a_flat_scene(small, suite_device):
    """Masks on a scene without instances: each mesh in place (instances of
    the masks' making, which hits do not report: instance_id -1)."""
    scene = hlbvh_cl.Scene(small, device=suite_device, masks=[1, 2])
    rng = np.random.default_rng(4)
    vertices, faces, owner, prim = flattened(small, np.arange(2), np.tile(np.eye(3, 4),
                                                                           (2, 1, 1)))
    origins, directions = _rays_at_centroids(rng, vertices, faces, 500)
    for ray_mask in (1, 2, 3):
        keep = ((np.array([1, 2]) & ray_mask) != 0)[owner]
        got = scene.intersect(origins, directions, mask=ray_mask)
        want = brute_force_intersect(vertices, faces[keep], origins, directions)
        np.testing.assert_allclose(got.t, want["t"], rtol=1e-5)
        found = want["prim"] >= 0
        k = np.flatnonzero(keep)[want["prim"][found]]
        np.testing.assert_array_equal(got.geom_id[found], owner[k])
        np.testing.assert_array_equal(got.prim_id[found], prim[k])
        assert (got.instance_id == -1).all()


def test_identity_instances_trace_as_the_flat_scene(meshes, suite_device):
    """Under identity maps the mapped ray is the ray itself: the same hits as
    the flat tree over the same meshes, bit for bit (normals aside)."""
    parts = [meshes["bunny"], _small_meshes()[1]]
    flat = hlbvh_cl.Scene(parts, device=suite_device)
    instanced = hlbvh_cl.Scene(parts, device=suite_device,
                               instances=[(0, np.eye(3, 4)), (1, np.eye(4))])
    rng = np.random.default_rng(11)
    origins = rng.uniform(-0.3, 0.3, (5000, 3)).astype(np.float32)
    directions = rng.normal(size=(5000, 3)).astype(np.float32)
    a, b = flat.intersect(origins, directions), instanced.intersect(origins, directions)
    for name in ("t", "geom_id", "prim_id", "u", "v", "points"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    # the normal goes through the (identity) inverse transpose: rounding only
    np.testing.assert_allclose(a.normal, b.normal, atol=3e-7)
    np.testing.assert_array_equal(b.instance_id, np.where(a.hit, a.geom_id, -1))
    assert (a.instance_id == -1).all()


def test_bunny_instances_agree_with_embree(meshes, suite_device):
    embreex = pytest.importorskip("embreex.rtcore_scene")
    bunny = meshes["bunny"]
    rng = np.random.default_rng(5)
    maps = random_transforms(rng, 20, spread=0.4)
    scene = hlbvh_cl.Scene([bunny], device=suite_device,
                           instances=[(0, a) for a in maps])
    vertices, faces, owner, prim = flattened([bunny], np.zeros(20, int), maps)
    reference = embreex.EmbreeScene()
    from embreex.mesh_construction import TriangleMesh
    TriangleMesh(reference, vertices.astype(np.float32)[faces])
    origins, directions = _rays_at_centroids(rng, vertices, faces, 20000, reach=2.0)
    result = reference.run(origins, directions, output=1)
    hits = scene.intersect(origins, directions)
    found = result["geomID"] >= 0
    agree = hits.hit == found
    assert agree.mean() > 0.999
    both = found & hits.hit
    # overlapping bunnies cross each other: where two surfaces meet within
    # rounding, either may be nearest
    same = (hits.instance_id[both] == owner[result["primID"][both]]) & \
        (hits.prim_id[both] == prim[result["primID"][both]])
    assert same.mean() > 0.999
    rows = np.flatnonzero(both)[same]
    corners = vertices[faces[result["primID"][rows]]]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    steep = _steep(directions[rows], normals)
    np.testing.assert_allclose(hits.t[rows][steep], result["tfar"][rows][steep], rtol=1e-5)


def test_both_levels_hold_their_invariants(small, suite_device):
    rng = np.random.default_rng(9)
    maps = random_transforms(rng, 40, spread=20.0)
    scene = hlbvh_cl.Scene(small, device=suite_device,
                           instances=[(k % 2, a) for k, a in enumerate(maps)])
    tree, queue = built.tree(scene), built.runtime(scene).queue
    # the top: one proxy triangle per instance spanning its world box
    tris, _ = tree.top.read_triangles(queue)
    proxies = np.stack([tris["v0"], tris["v1"], tris["v2"]], axis=1)
    refs = tree.top.read_triangles(queue)[1]
    proxy_vertices = np.empty((40, 3, 3), np.float32)
    proxy_vertices[refs["prim_id"]] = proxies / np.float32(tree.top.scale)
    proxy_mesh = hlbvh_cl.Mesh(proxy_vertices.reshape(-1, 3), np.arange(120).reshape(-1, 3))
    check_tree(SimpleNamespace(meshes=[proxy_mesh], stats=scene.stats, builder=scene.builder),
               tree.top, queue)
    # each world box holds its instance's mapped vertices
    lo, hi = proxy_vertices[:, 0], proxy_vertices[:, 1]
    for k, a in enumerate(maps):
        world = small[k % 2].vertices.astype(np.float64) @ a[:, :3].T + a[:, 3]
        assert (world >= lo[k]).all() and (world <= hi[k]).all()
    # each mesh's tree, read from its place among the meshes' trees
    trees = tree.meshes
    for m, mesh in enumerate(small):
        count = sum(c for _, c in trees.levels[m])
        nodes = np.empty(count, hlbvh_cl.core.layout.WIDE_NODE)
        cl.enqueue_copy(queue, nodes, trees.nodes,
                        src_offset=int(trees.node_base[m]) * nodes.itemsize)
        tris = np.empty(mesh.triangle_count, hlbvh_cl.core.layout.TRIANGLE)
        refs = np.empty(mesh.triangle_count, hlbvh_cl.core.layout.TRIANGLE_REF)
        first = int(trees.triangle_base[m])
        cl.enqueue_copy(queue, tris, trees.triangles, src_offset=first * tris.itemsize)
        cl.enqueue_copy(queue, refs, trees.refs, src_offset=first * refs.itemsize)
        view = SimpleNamespace(read_nodes=lambda q, n=nodes: n,
                               read_triangles=lambda q, t=tris, r=refs: (t, r),
                               triangle_count=mesh.triangle_count, node_count=count,
                               levels=trees.levels[m], depth=len(trees.levels[m]),
                               scale=trees.scales[m])
        check_tree(SimpleNamespace(meshes=[mesh], stats=trees.stats[m], builder=scene.builder),
                   view, queue)


def test_every_hit_and_counts_through_instances(small, suite_device):
    """intersect_all and count_intersections on mirrored, scaled, overlapping
    instances with masks, against the brute force of the flattened scene:
    the same hits per ray as sets of (instance, face), t to 1e-5 where well
    conditioned; max_hits keeps the nearest."""
    rng = np.random.default_rng(17)
    maps = random_transforms(rng, 8, spread=1.5)
    instance_meshes = np.arange(8) % 2
    masks = np.array([1, 1, 2, 1, 3, 1, 2, 1], np.uint32)
    scene = hlbvh_cl.Scene(small, device=suite_device, masks=masks,
                           instances=[(int(m), a) for m, a in zip(instance_meshes, maps)])
    vertices, faces, owner, prim = flattened(small, instance_meshes, maps)
    origins, directions = _rays_at_centroids(rng, vertices, faces, 1500)
    keep = ((masks & 1) != 0)[owner]
    index = np.flatnonzero(keep)
    want = brute_force_all_hits(vertices, faces[keep], origins, directions)
    clean = want["margin"] > 1e-4  # rays that pass no edge within rounding
    got = scene.intersect_all(origins, directions, mask=1)
    counts = scene.count_intersections(origins, directions, mask=1)
    np.testing.assert_array_equal(counts[clean], np.diff(want["offsets"])[clean])
    np.testing.assert_array_equal(got.counts, counts)
    assert clean.mean() > 0.95 and counts.sum() > 2 * len(origins)
    for r in np.flatnonzero(clean)[:400]:
        mine = slice(got.offsets[r], got.offsets[r + 1])
        theirs = slice(want["offsets"][r], want["offsets"][r + 1])
        k = index[want["prim"][theirs]]
        assert sorted(zip(got.instance_id[mine], got.prim_id[mine])) == \
            sorted(zip(owner[k], prim[k]))
        np.testing.assert_array_equal(got.geom_id[mine], instance_meshes[got.instance_id[mine]])
        np.testing.assert_allclose(got.t[mine], want["t"][theirs], rtol=1e-4)
    nearest = scene.intersect_all(origins, directions, mask=1, max_hits=1)
    closest = scene.intersect(origins, directions, mask=1)
    hit = closest.hit & clean
    np.testing.assert_array_equal(nearest.counts[hit], 1)
    np.testing.assert_array_equal(nearest.t[nearest.offsets[:-1][hit]], closest.t[hit])
    np.testing.assert_array_equal(nearest.instance_id[nearest.offsets[:-1][hit]],
                                  closest.instance_id[hit])
    assert (scene.count_intersections(origins, directions, mask=0) == 0).all()


@pytest.mark.parametrize("instances, message", [
    ([], "instances is empty"),
    ([(2, np.eye(3, 4))], r"instances\[0\]\[0\] = 2 is not a mesh index"),
    ([(0, np.eye(3))], r"instances\[0\]\[1\] \(transform\) has shape \(3, 3\)"),
    ([(0, np.eye(3, 4)), (0, np.zeros((3, 4)))], r"instances\[1\]\[1\] is singular"),
    # squashed flat between two rotations: was accepted (determinant 2^-15.5 of the rows'
    # product), its mapped rays gaining and losing hits near the surface against the
    # mesh flattened (an axis-aligned squash keeps the ratio at 1: accepted)
    ([(0, np.hstack([rotation(np.random.default_rng(1)) @ np.diag([1.0, 1e-5, 1.0])
                     @ rotation(np.random.default_rng(2)), np.zeros((3, 1))]))],
     r"instances\[0\]\[1\] is singular for float32 work .* rays mapped into it gain or "
     r"lose hits"),
    ([(0, np.diag([1.0, 1.0, 1.0, 2.0]))], r"instances\[0\]\[1\] has last row"),
    ([(0, np.full((3, 4), np.nan))], r"instances\[0\]\[1\] is not finite"),
    ([(0, np.eye(3, 4)), (0, np.eye(3, 4) * 1e200)],
     r"instances\[1\]\[1\] does not fit float32: an entry is 1e\+200"),
    ([(0.5, np.eye(3, 4))], r"instances\[0\]\[0\] \(mesh_index\) must be an int"),
    ([np.eye(3, 4)], r"instances\[0\] must be a \(mesh_index, transform\) pair"),
    # not singular, but its inverse overflows float32 in the scene's frames
    ([(0, np.eye(3, 4)), (0, np.hstack([np.diag([1e20, 1.0, 1e-20]), np.zeros((3, 1))]))],
     r"instance 1's transform does not fit float32"),
    # a plain move, refused in the frame that instance 0's 3e38 scale sets: named so
    ([(0, np.hstack([np.eye(3) * 3e38, np.zeros((3, 1))])),
      (1, np.hstack([np.eye(3), [[6.0], [0.0], [0.0]]]))],
     r"instance 1's transform does not fit float32: .* \(instance 0 reaches [0-9.]+e\+38 "
     r"from the origin, which sets the scale of the top frame\)"),
    # the sphere 2e-12 across at x = 3, where float32's steps are 2.4e-7
    ([(0, np.eye(3, 4)), (0, np.hstack([np.eye(3) * 1e-12, [[3.0], [0.0], [0.0]]]))],
     r"instance 1's transform makes its mesh too small for its place in the world: it spans "
     r"2e-12 at 3 from the origin, under 4 float32 steps of 2.4e-07"),
])
def test_bad_instances_are_named(small, suite_device, instances, message):
    with pytest.raises((ValueError, TypeError), match=message):
        # one more instance places mesh 1, which a Scene refuses to leave out
        placed = [*instances, (1, np.eye(3, 4))] if instances else instances
        hlbvh_cl.Scene(small, device=suite_device, instances=placed)


def test_bad_masks_and_updates_are_named(small, suite_device):
    with pytest.raises(ValueError, match=r"masks\[1\] = 4294967296 does not fit 32 bits"):
        hlbvh_cl.Scene(small, device=suite_device, masks=[1, 2**32])
    with pytest.raises(ValueError, match=r"masks has shape \(3,\), expected \(2,\)"):
        hlbvh_cl.Scene(small, device=suite_device, masks=[1, 2, 3])
    flat = hlbvh_cl.Scene(small, device=suite_device)
    with pytest.raises(ValueError, match="set_transforms needs an instanced Scene"):
        flat.set_transforms([0], np.eye(3, 4)[None])
    with pytest.raises(ValueError, match=r"mask\[1\] = -2147483649 does not fit 32 bits"):
        flat.intersect(np.zeros((2, 3)), np.ones((2, 3)), mask=[1, -2**31 - 1])
    scene = hlbvh_cl.Scene(small[:1], device=suite_device, instances=[(0, np.eye(3, 4))])
    with pytest.raises(ValueError, match=r"instance_ids\[0\] = 3 is out of range"):
        scene.set_transforms([3], np.eye(3, 4)[None])
    with pytest.raises(ValueError, match=r"transforms\[0\] is singular"):
        scene.set_transforms([0], np.zeros((1, 3, 4)))
    scene.set_transforms([], np.zeros((0, 3, 4)))  # nothing to move
    with pytest.raises(ValueError, match=r"instance_ids\[1\] = 0 is given twice"):
        scene.set_transforms([0, 0, 0], np.tile(np.eye(3, 4), (3, 1, 1)))
    hits = scene.intersect(np.zeros((1, 3)) - 5, np.ones((1, 3)))
    assert hits.instance_id[0] == 0  # the scene still holds its instance


def test_meshes_whose_joined_trees_pass_int32_are_refused(small, suite_device, monkeypatch):
    """Each mesh's tree may fit int32 indices while the buffers they are
    joined into do not (instances find their tree by int32 offsets): a
    clear error before anything is built, here with the bound lowered to
    just under the meshes' total."""
    import hlbvh_cl.build.instances
    total = sum(mesh.triangle_count for mesh in small)
    monkeypatch.setattr(hlbvh_cl.build.instances, "MAX_TRIANGLES", total - 1)
    with pytest.raises(ValueError, match=f"the scene's meshes hold {total} triangles together; "
                                         f"at most {total - 1} fit the int32 offsets"):
        hlbvh_cl.Scene(small, device=suite_device,
                       instances=[(0, np.eye(3, 4)), (1, np.eye(3, 4))])


def test_negative_masks_are_their_two_s_complement(small, suite_device):
    """Python's ~2 (-3) is every bit but bit 1, in a ray's mask as in a
    scene's: the same hits as 0xFFFFFFFD."""
    rng = np.random.default_rng(9)
    origins, directions = _rays_at_centroids(rng, small[0].vertices, small[0].faces, 300)
    place = [(0, np.eye(3, 4)), (1, np.eye(3, 4))]
    spelled = hlbvh_cl.Scene(small, device=suite_device, instances=place, masks=[-1, 2])
    plain = hlbvh_cl.Scene(small, device=suite_device, instances=place, masks=[2**32 - 1, 2])
    for mask, bits in ((~2, 0xFFFFFFFD), ([~2] * 300, [0xFFFFFFFD] * 300), (-1, 2**32 - 1)):
        got = spelled.intersect(origins, directions, mask=mask)
        expected = plain.intersect(origins, directions, mask=bits)
        for field in ("t", "prim_id", "geom_id", "instance_id"):
            np.testing.assert_array_equal(getattr(got, field), getattr(expected, field))
    skipping = spelled.intersect(origins, directions, mask=~2)
    assert skipping.hit.sum() > 100 and (skipping.instance_id[skipping.hit] == 0).all()


@pytest.mark.parametrize("change", ["set_transforms", "update_vertices"])
def test_a_change_the_build_rejects_leaves_the_scene_as_it_was(small, suite_device, change):
    """Maps and vertices that pass the checks but overflow float32 in the
    frames the scene is built in are refused by the build; the scene keeps
    its content and its tree."""
    scene = hlbvh_cl.Scene(small, device=suite_device,
                           instances=[(0, np.eye(3, 4)), (1, np.eye(3, 4))])
    rng = np.random.default_rng(5)
    origins, directions = _rays_at_centroids(rng, small[0].vertices, small[0].faces, 500)
    before = scene.intersect(origins, directions)
    assert before.hit.sum() > 100
    with pytest.raises(ValueError, match=r"instance \d's transform does not fit float32"), \
            warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # refused before numpy overflows
        if change == "set_transforms":  # the top frame then shrinks instance 0's past float32
            scene.set_transforms(1, np.hstack([np.eye(3), [[3e38], [0], [0]]]))
        else:  # mesh 1 grown to 1e30 under instance 1's scale of 1e10: beyond float32
            scene.set_transforms(1, np.hstack([np.eye(3) * 1e10, np.zeros((3, 1))]))
            scene.update_vertices(1, small[1].vertices * np.float32(1e30))
    if change == "update_vertices":
        np.testing.assert_array_equal(scene.meshes[1].vertices, small[1].vertices)
        scene.set_transforms(1, np.eye(3, 4))
    np.testing.assert_array_equal(scene.transforms, np.tile(np.eye(3, 4), (2, 1, 1)))
    after = scene.intersect(origins, directions)
    for field in ("t", "prim_id", "geom_id", "instance_id"):
        np.testing.assert_array_equal(getattr(after, field), getattr(before, field))


def test_an_instance_too_small_for_its_place_is_refused_but_a_flattened_one_is_traced(
        small, suite_device):
    """An instance spanning under 4 float32 steps at its place is refused
    (rays would miss it, or hit it anywhere), and the scene keeps what it
    held; one squashed flat far out keeps its other sides and is hit where
    the brute force hits its flattened copy.  So is one spanning 6 steps."""
    sphere = small[0]
    scene = hlbvh_cl.Scene([sphere], device=suite_device, instances=[(0, np.eye(3, 4))])
    step = float(np.spacing(np.float32(1000.0)))
    with pytest.raises(ValueError, match=r"instance 0's transform makes its mesh too small"):
        scene.set_transforms(0, np.hstack([np.eye(3) * step, [[1000.0], [0.0], [0.0]]]))
    np.testing.assert_array_equal(scene.transforms, np.eye(3, 4)[None])
    rng = np.random.default_rng(3)
    for linear, place in ((np.diag([1.0, 1.0, 1e-7]), (0.5, 0.2, 1000.0)),
                          (np.eye(3) * 3 * step, (1000.0, 0.0, 0.0))):
        transform = np.hstack([linear, np.array(place)[:, None]])
        scene.set_transforms(0, transform)
        reach = float(np.abs(linear).max())
        across = rng.uniform(-0.6, 0.6, (400, 3)) * reach
        across[:, 2] = 0.0
        origins = (np.array(place) + across + (0.0, 0.0, 3 * reach)).astype(np.float32)
        directions = np.tile(np.float32([0.0, 0.0, -1.0]), (len(origins), 1))
        vertices, faces, _, _ = flattened([sphere], [0], transform[None])
        expected = brute_force_intersect(vertices, faces, origins.astype(np.float64),
                                         directions.astype(np.float64))
        got = scene.intersect(origins, directions)
        np.testing.assert_array_equal(got.hit, np.isfinite(expected["t"]))
        assert got.hit.all()
        np.testing.assert_allclose(got.t, expected["t"], rtol=0, atol=4 * step / reach)


def test_an_interrupted_rebuild_of_the_meshes_is_named_until_rebuilt(small, suite_device,
                                                                     monkeypatch):
    """Ctrl-C while an instanced scene rebuilds its meshes' trees leaves it
    without them: queries and set_transforms say so (not an AttributeError
    on None), and a rebuild restores the same answers."""
    from hlbvh_cl.build import instances as instances_module
    scene = hlbvh_cl.Scene(small[:1], device=suite_device, instances=[(0, np.eye(3, 4))])
    rng = np.random.default_rng(2)
    origins, directions = _rays_at_centroids(rng, small[0].vertices, small[0].faces, 200)
    before = scene.intersect(origins, directions)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(instances_module, "build_mesh_trees", interrupted)
        with pytest.raises(KeyboardInterrupt):
            scene.rebuild()
    with pytest.raises(RuntimeError, match="no tree"):
        scene.intersect(origins, directions)
    with pytest.raises(RuntimeError, match="meshes have no trees: its last rebuild failed"):
        scene.set_transforms(0, np.eye(3, 4))
    scene.rebuild()
    after = scene.intersect(origins, directions)
    for field in ("t", "prim_id", "instance_id"):
        np.testing.assert_array_equal(getattr(after, field), getattr(before, field))


# -- point queries ---------------------------------------------------------------

def _counts_first(meshes, instance_meshes) -> np.ndarray:
    """The first flattened face of each instance (flattened's order)."""
    counts = [meshes[m].triangle_count for m in instance_meshes]
    return np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)


def _near_surface(rng, vertices, faces, count: int, offsets) -> np.ndarray:
    """Points on random flattened triangles, moved along their normals by
    each of ``offsets`` in turn."""
    from point_cases import surface_samples
    on, normal, _ = surface_samples(rng, vertices, faces, count)
    return on + np.resize(np.asarray(offsets, np.float64), count)[:, None] * normal


def _assert_closest_matches(got, points, meshes, instance_meshes, maps, max_distance=np.inf,
                            instance_id=None):
    """closest_points against the float64 brute force of the flattened scene:
    found, distance (1e-5 relative, plus the float32 rounding of the mapped
    vertices), the point on the named (instance, face) at that distance,
    its normal, and the ids where the nearest face is unique by a margin.
    ``instance_id``: the instances as the flattened scene numbers them, where
    ``got`` reports none (a masked flat scene: its meshes)."""
    vertices, faces, owner, prim = flattened(meshes, instance_meshes, maps)
    instance_id = got.instance_id if instance_id is None else instance_id
    points64 = np.asarray(points, np.float64)
    want = brute_force_closest(vertices, faces, points64)
    distance = want["distance"]
    tolerance = 1e-5 * distance + 1e-6
    edge = np.abs(distance - max_distance) <= tolerance  # either answer is right
    found = distance <= max_distance
    np.testing.assert_array_equal(got.found[~edge], found[~edge])
    both = got.found & found
    assert np.all(np.abs(got.distance[both] - distance[both]) <= tolerance[both]), \
        np.abs(got.distance[both] - distance[both]).max()
    missed = ~got.found
    assert np.isinf(got.distance[missed]).all() and np.isnan(got.points[missed]).all()
    assert (got.instance_id[missed] == -1).all() and (got.geom_id[missed] == -1).all()
    assert (got.prim_id[missed] == -1).all() and (got.normal[missed] == 0).all()
    g = got.found
    np.testing.assert_array_equal(got.geom_id[g], np.asarray(instance_meshes)[instance_id[g]])
    k = _counts_first(meshes, instance_meshes)[instance_id[g]] + got.prim_id[g]
    tri = vertices[faces[k]]
    u, v = got.u[g].astype(np.float64), got.v[g].astype(np.float64)
    assert np.all((u >= -1e-6) & (v >= -1e-6) & (u + v <= 1 + 1e-6))
    on = tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
    np.testing.assert_allclose(got.points[g], on, atol=2e-6)
    gap = np.linalg.norm(got.points[g] - points64[g], axis=1)
    assert np.all(np.abs(gap - got.distance[g]) <= tolerance[g] + 1e-6)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    np.testing.assert_allclose(got.normal[g], normal, atol=1e-5)
    a, b, c = (vertices[faces[:, j]] for j in range(3))
    ordered = np.sort(np.sqrt(closest_on_triangles(points64, a, b, c)[0]), axis=1)
    unique = both & (ordered[:, 1] - ordered[:, 0] > 10 * tolerance)
    index = want["index"][unique]
    np.testing.assert_array_equal(instance_id[unique], owner[index])
    np.testing.assert_array_equal(got.prim_id[unique], prim[index])
    return int(unique.sum())


def _point_scene(small, device, count: int, spread: float, seed: int):
    """Mirrored, scaled, rotated, overlapping instances of the small meshes,
    and two of extreme aspect (where the closest walk's bound, 1 / s_min^2,
    is far from tight)."""
    rng = np.random.default_rng(seed)
    stretched = np.zeros((2, 3, 4))
    stretched[0, :, :3] = rotation(rng) @ np.diag([4.0, 0.25, 1.0])
    stretched[1, :, :3] = rotation(rng) @ np.diag([-0.2, 3.0, 1.5])
    stretched[:, :, 3] = rng.uniform(-spread, spread, (2, 3))
    maps = np.concatenate([random_transforms(rng, count, spread=spread), stretched])
    instance_meshes = np.arange(len(maps)) % 2
    scene = hlbvh_cl.Scene(small, device=device,
                           instances=[(int(m), a) for m, a in zip(instance_meshes, maps)])
    return scene, instance_meshes, maps, rng


def test_closest_points_through_instances_match_the_brute_force(small, suite_device):
    scene, instance_meshes, maps, rng = _point_scene(small, suite_device, 12, 2.0, 41)
    vertices, faces, owner, _ = flattened(small, instance_meshes, maps)
    points = np.concatenate([
        rng.uniform(-5, 5, (1500, 3)),
        _near_surface(rng, vertices, faces, 600, [1e-3, -1e-3, 0.05, -0.05, 0.0, 0.3])])
    points = points.astype(np.float32)
    got = scene.closest_points(points)
    assert got.found.all()
    assert _assert_closest_matches(got, points, small, instance_meshes, maps) > 700
    assert len(set(got.instance_id.tolist())) == len(maps)  # every instance was nearest
    for max_distance in (0.0, 0.3, 1.0):
        cut = scene.closest_points(points, max_distance=max_distance)
        _assert_closest_matches(cut, points, small, instance_meshes, maps, max_distance)
        assert 0 < cut.found.sum() < len(points)
    # the leading shape, and the same answers point by point
    grid = scene.closest_points(points[:60].reshape(3, 20, 3))
    assert grid.instance_id.shape == (3, 20)
    np.testing.assert_array_equal(grid.distance.reshape(-1), got.distance[:60])


def test_winding_numbers_and_signs_through_overlapping_instances(small, suite_device):
    """On closed meshes the winding number of the instanced scene is the
    flattened scene's (a mirrored copy winds the other way, so where it
    overlaps an unmirrored one their windings cancel, as they do flattened)."""
    scene, instance_meshes, maps, rng = _point_scene(small, suite_device, 12, 2.0, 43)
    vertices, faces, _, _ = flattened(small, instance_meshes, maps)
    points = np.concatenate([rng.uniform(-5, 5, (1500, 3)),
                             _near_surface(rng, vertices, faces, 500, [1e-3, -1e-3])])
    points = points.astype(np.float32)
    expected = brute_force_winding(vertices, faces, points)
    winding = scene.winding_number(points)
    # Barill's far field, in each instance's mesh: the instances' errors add up
    error = np.abs(winding - expected)
    assert error.max() < 0.1 and np.median(error) < 0.01
    inside = np.abs(expected) >= 0.5
    decided = np.abs(np.abs(expected) - 0.5) > 0.1
    assert 100 < inside[decided].sum() < decided.sum() - 100
    assert (np.abs(expected) > 1.5).any() and (expected < -0.5).any()  # overlaps, mirrors
    np.testing.assert_array_equal(scene.contains(points)[decided], inside[decided])
    sdf = scene.signed_distance(points)
    np.testing.assert_array_equal(np.abs(sdf), scene.closest_points(points).distance)
    np.testing.assert_array_equal((sdf < 0)[decided], inside[decided])


def _watertight_instances(device, seed):
    """A watertight icosphere and box, each placed four times (rotated,
    scaled non-uniformly, every third mirrored) on a grid wide enough that
    no two copies meet: parity ray casting then decides inside."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    box = trimesh.creation.box(extents=(1.0, 0.5, 2.0))
    meshes = [hlbvh_cl.Mesh(sphere.vertices, sphere.faces, name="sphere"),
              hlbvh_cl.Mesh(box.vertices, box.faces, name="box")]
    rng = np.random.default_rng(seed)
    maps = random_transforms(rng, 8)
    cells = np.stack(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij"), -1).reshape(-1, 3)
    maps[:, :, 3] = cells * 2.5
    instance_meshes = np.arange(8) % 2
    scene = hlbvh_cl.Scene(meshes, device=device,
                           instances=[(int(m), a) for m, a in zip(instance_meshes, maps)])
    return scene, meshes, instance_meshes, maps, rng


def test_signs_agree_with_parity_on_watertight_instances(suite_device):
    from point_cases import parity_inside
    scene, meshes, instance_meshes, maps, rng = _watertight_instances(suite_device, 47)
    vertices, faces, _, _ = flattened(meshes, instance_meshes, maps)
    points = rng.uniform(-5, 5, (4000, 3)).astype(np.float32)
    expected = parity_inside(vertices, faces, points.astype(np.float64))
    nearest = scene.closest_points(points).distance
    clear = nearest > 1e-4
    assert expected[clear].sum() > 150
    sdf = scene.signed_distance(points)
    np.testing.assert_array_equal(np.abs(sdf), nearest)
    np.testing.assert_array_equal((sdf < 0)[clear], expected[clear])
    np.testing.assert_array_equal(scene.contains(points)[clear], expected[clear])
    # each copy winds once, the mirrored ones the other way
    winding = scene.winding_number(points[clear])
    want = brute_force_winding(vertices, faces, points[clear])
    assert np.abs(winding - np.round(want)).max() < 0.05
    assert set(np.round(want).astype(int).tolist()) == {-1, 0, 1}


def test_signs_hold_1e_6_off_instanced_surfaces(suite_device):
    scene, meshes, instance_meshes, maps, rng = _watertight_instances(suite_device, 53)
    from point_cases import assert_signs_off_the_surface, surface_samples
    vertices, faces, owner, _ = flattened(meshes, instance_meshes, maps)
    on, normal, chosen = surface_samples(rng, vertices, faces, 1500)
    # both meshes are convex: outward is away from the copy's centre (a
    # mirrored copy's normals point inward)
    outward = normal * np.sign(np.einsum("fd,fd->f", normal,
                                         on - maps[owner[chosen], :, 3]))[:, None]
    assert_signs_off_the_surface(scene, on, outward, 1000)


@pytest.mark.parametrize("scale", [1e-19, 1e-20, 1e-25])
def test_a_point_on_a_tiny_instance_is_found_within_max_distance_0(scale, suite_device):
    """An instance scaled so small that its reach scale (1 / s^2) is inf in
    float32: a point on it is found at distance 0 with max_distance 0 (or
    one whose square underflows), as with no max_distance."""
    triangle = hlbvh_cl.Mesh(np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]]), [[0, 1, 2]])
    tiny = np.hstack([scale * np.eye(3), np.zeros((3, 1))])
    beside = np.hstack([np.eye(3), [[5.0], [0.0], [0.0]]])
    scene = hlbvh_cl.Scene([triangle], instances=[(0, tiny), (0, beside)], device=suite_device)
    on_it = np.zeros((1, 3), np.float32)
    for max_distance in (0.0, 1e-30, np.inf):
        got = scene.closest_points(on_it, max_distance)
        assert got.distance[0] == 0.0 and got.instance_id[0] == 0, max_distance


def test_point_queries_of_a_masked_flat_scene(small, suite_device):
    """Masks make a flat scene's meshes identity instances: point queries
    see every mesh whatever its mask, at the flat scene's distances, and
    report no instance."""
    flat = hlbvh_cl.Scene(small, device=suite_device)
    masked = hlbvh_cl.Scene(small, device=suite_device, masks=[1, 0])
    rng = np.random.default_rng(59)
    points = rng.uniform(-2, 2, (1500, 3)).astype(np.float32)
    a, b = flat.closest_points(points), masked.closest_points(points)
    np.testing.assert_array_equal(a.distance, b.distance)
    assert (a.instance_id == -1).all() and (b.instance_id == -1).all()
    identity = np.tile(np.eye(3, 4), (2, 1, 1))
    assert _assert_closest_matches(b, points, small, np.arange(2), identity,
                                   instance_id=b.geom_id) > 300
    vertices, faces, _, _ = flattened(small, np.arange(2), identity)
    expected = brute_force_winding(vertices, faces, points)
    np.testing.assert_allclose(masked.winding_number(points), expected, atol=0.05)
    decided = np.abs(np.abs(expected) - 0.5) > 0.1
    np.testing.assert_array_equal(masked.contains(points)[decided],
                                  (np.abs(expected) >= 0.5)[decided])
    np.testing.assert_array_equal(np.abs(masked.signed_distance(points)), b.distance)


def test_mesh_dipoles_are_made_once_and_follow_the_meshes(small, suite_device):
    """The meshes' trees share one dipole buffer, made by the first winding
    query: set_transforms keeps it (the meshes stand), a mesh's new vertices
    drop it with the trees they replace."""
    rng = np.random.default_rng(61)
    maps = random_transforms(rng, 6, spread=2.0)
    instance_meshes = np.arange(6) % 2
    scene = hlbvh_cl.Scene(small, device=suite_device,
                           instances=[(int(m), a) for m, a in zip(instance_meshes, maps)])
    points = rng.uniform(-4, 4, (800, 3)).astype(np.float32)

    def check():
        vertices, faces, _, _ = flattened(scene.meshes, instance_meshes, maps)
        np.testing.assert_allclose(scene.winding_number(points),
                                   brute_force_winding(vertices, faces, points), atol=0.05)

    trees = built.tree(scene).meshes
    assert trees.dipoles is None
    check()
    dipoles = trees.dipoles
    assert dipoles is not None
    maps[[0, 3]] = random_transforms(rng, 2, spread=2.0)
    scene.set_transforms([0, 3], maps[[0, 3]])
    assert built.tree(scene).meshes is trees and trees.dipoles is dipoles
    check()
    scene.update_vertices(1, scene.meshes[1].vertices * np.float32(1.5))
    assert trees.dipoles is None and built.tree(scene).meshes.dipoles is None
    check()
    assert _assert_closest_matches(scene.closest_points(points), points, scene.meshes,
                                   instance_meshes, maps) > 150


def test_reach_scales_bound_the_shrinking_of_distances():
    from hlbvh_cl.build.instances import reach_scales
    rng = np.random.default_rng(67)
    linear = np.stack([rotation(rng) @ np.diag(rng.uniform(0.1, 3.0, 3)) @ rotation(rng)
                       for _ in range(50)] + [np.diag([2.0, 0.5, -1.0])])
    scales = reach_scales(linear)
    assert scales.dtype == np.float32 and scales[-1] == 4.0
    x = rng.normal(size=(50, 1000, 3))
    shrunk = np.einsum("kij,knj->kni", linear[:50], x)
    ratio = (np.linalg.norm(x, axis=2) ** 2 / np.linalg.norm(shrunk, axis=2) ** 2).max(axis=1)
    assert np.all(ratio <= scales[:50])  # never more than 1 / s_min^2
    # the direction it shrinks most (the last right singular vector) reaches it
    worst = np.linalg.svd(linear[:50])[2][:, -1]
    ratio = 1.0 / np.linalg.norm(np.einsum("kij,kj->ki", linear[:50], worst), axis=1) ** 2
    assert np.all(ratio <= scales[:50]) and np.all(scales[:50] <= ratio * (1 + 2**-22))
