"""Launches sized on the host and counted on the device (RayQuery's
``counted``): the path integrator launches its closest-hit and shadow passes
over a bound and the kernels trace only the first counts[k] rays, which the
device wrote.  Those rays get the same answers as an uncounted launch, and
the records past the count are left as they were."""
from __future__ import annotations

import numpy as np
import pyopencl as cl
import pytest
import trimesh

import hlbvh_cl
from hlbvh_cl.core import layout
from hlbvh_cl.query.rays import RayQuery
import built


def sphere_and_rays(seed: int, count: int):
    """A 1,280-triangle sphere and `count` Ray records from around it in
    random directions (tmax inf)."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(sphere.vertices, sphere.faces)])
    rng = np.random.default_rng(seed)
    records = np.zeros(count, layout.RAY)
    records["origin"] = rng.uniform(-2, 2, (count, 3))
    records["direction"] = rng.normal(size=(count, 3))
    records["tmax"] = np.inf
    return scene, records


@pytest.mark.parametrize("count, counted", [(300, 0), (300, 1), (300, 37), (300, 200),
                                            (300, 500), (20000, 1), (20000, 2049),
                                            (20000, 9000), (20000, 19999)])
def test_a_counted_launch_traces_the_first_count_rays_and_writes_nothing_past_them(count,
                                                                                   counted):
    """Also where the launch has many work-groups, of which the kernels
    spread those with rays to trace over the launch (rays.cl's
    counted_rays): 20,000 rays are hundreds of groups on a CPU and ten of a
    GPU's (HLBVH_CL_PROFILE=gpu), of which a count puts some or all to work."""
    scene, records = sphere_and_rays(5, count)
    records["tmax"] = np.where(np.arange(count) % 3 == 0, 1.0, np.inf)  # some end short
    expected = scene.intersect(records["origin"], records["direction"], tmax=records["tmax"])
    blocked = scene.occluded(records["origin"], records["direction"], tmax=records["tmax"])
    assert 0 < expected.prim_id[expected.prim_id >= 0].size < count  # hits and misses both

    query, tree = RayQuery(built.runtime(scene)), built.tree(scene)
    context, queue = query.rt.context, query.rt.queue
    flags = cl.mem_flags
    rays = cl.Buffer(context, flags.READ_ONLY | flags.COPY_HOST_PTR, hostbuf=records)
    counts = cl.Buffer(context, flags.READ_ONLY | flags.COPY_HOST_PTR,
                       hostbuf=np.array([7, counted], np.uint32))
    sentinel = np.zeros(count, layout.HIT)
    sentinel["t"], sentinel["prim_id"] = -5.0, -7
    hits = cl.Buffer(context, flags.READ_WRITE | flags.COPY_HOST_PTR, hostbuf=sentinel)
    occluded = cl.Buffer(context, flags.READ_WRITE | flags.COPY_HOST_PTR,
                         hostbuf=np.full(count, 9, np.uint8))
    overflow = cl.Buffer(context, flags.READ_WRITE | flags.COPY_HOST_PTR,
                         hostbuf=np.zeros(2, np.int32))
    query.enqueue_intersect(tree, rays, hits, count, overflow, counted=(counts, 1)).wait()
    query.enqueue_occluded(tree, rays, occluded, count, overflow, counted=(counts, 1)).wait()
    got, got_occluded = np.empty(count, layout.HIT), np.empty(count, np.uint8)
    cl.enqueue_copy(queue, got, hits)
    cl.enqueue_copy(queue, got_occluded, occluded)

    traced = min(counted, count)
    np.testing.assert_array_equal(got["t"][:traced], expected.t[:traced])
    np.testing.assert_array_equal(got["prim_id"][:traced], expected.prim_id[:traced])
    np.testing.assert_array_equal(got["u"][:traced], expected.u[:traced])
    np.testing.assert_array_equal(got_occluded[:traced], blocked[:traced].astype(np.uint8))
    np.testing.assert_array_equal(got[traced:], sentinel[traced:])
    assert np.all(got_occluded[traced:] == 9)


def test_rays_made_on_the_device_with_a_nan_or_infinite_part_meet_nothing():
    """The renderer's bounce rays reach the kernels unchecked: one with a NaN or
    infinite origin or direction is a miss, not a walk into the nodes' unused
    lanes (whose boxes NaN slab distances do not exclude), and the finite
    rays of the same launch get their own hits."""
    count = 512
    scene, records = sphere_and_rays(11, count)
    expected = scene.intersect(records["origin"], records["direction"])
    bad = np.arange(count) % 4 != 0
    for k, value in enumerate((np.nan, np.inf, -np.inf)):
        records["origin"][bad & (np.arange(count) % 8 == 1 + k), k] = value
        records["direction"][bad & (np.arange(count) % 8 == 5 + k), k] = value
    bad &= ~np.isfinite(records["origin"]).all(1) | ~np.isfinite(records["direction"]).all(1)
    assert bad.sum() > count // 2 and (expected.prim_id[~bad] >= 0).any()
    assert np.isnan(records["direction"][bad]).any() and np.isinf(records["origin"][bad]).any()

    query, tree = RayQuery(built.runtime(scene)), built.tree(scene)
    context, queue = query.rt.context, query.rt.queue
    flags = cl.mem_flags
    rays = cl.Buffer(context, flags.READ_ONLY | flags.COPY_HOST_PTR, hostbuf=records)
    hits = cl.Buffer(context, flags.READ_WRITE, count * layout.HIT.itemsize)
    occluded = cl.Buffer(context, flags.READ_WRITE, count)
    overflow = cl.Buffer(context, flags.READ_WRITE | flags.COPY_HOST_PTR,
                         hostbuf=np.zeros(2, np.int32))
    query.enqueue_intersect(tree, rays, hits, count, overflow).wait()
    query.enqueue_occluded(tree, rays, occluded, count, overflow).wait()
    got, got_occluded = np.empty(count, layout.HIT), np.empty(count, np.uint8)
    flag = np.empty(2, np.int32)
    cl.enqueue_copy(queue, got, hits)
    cl.enqueue_copy(queue, got_occluded, occluded)
    cl.enqueue_copy(queue, flag, overflow)

    assert flag[0] == 0  # no walk ran past its stack
    assert np.all(got["t"][bad] == np.inf) and np.all(got["prim_id"][bad] == -1)
    assert np.all(got_occluded[bad] == 0)
    np.testing.assert_array_equal(got["t"][~bad], expected.t[~bad])
    np.testing.assert_array_equal(got["prim_id"][~bad], expected.prim_id[~bad])
