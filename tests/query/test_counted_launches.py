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


@pytest.mark.parametrize("counted", [0, 1, 37, 200, 500])
def test_a_counted_launch_traces_the_first_count_rays_and_writes_nothing_past_them(counted):
    sphere = trimesh.creation.icosphere(subdivisions=3)
    scene = hlbvh_cl.Scene([hlbvh_cl.Mesh(sphere.vertices, sphere.faces)])
    rng = np.random.default_rng(5)
    count = 300
    records = np.zeros(count, layout.RAY)
    records["origin"] = rng.uniform(-2, 2, (count, 3))
    records["direction"] = rng.normal(size=(count, 3))
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
