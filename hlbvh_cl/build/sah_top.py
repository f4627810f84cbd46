"""Stage 5 host side: the HLBVH's SAH top over Morton clusters (kernels/build/sah_top.cl)."""
from __future__ import annotations

from dataclasses import dataclass

import functools

import numpy as np
import pyopencl as cl

from ..core import layout
from .radix_tree import RadixTree, RadixTreeMetrics
from ..parallel.scan import exclusive_scan

TOP_TASK_BYTES = 16  # struct TopTask in sah_top.cl: four ints
CLUSTER_RECORD_BYTES = 32  # struct ClusterRecord in sah_top.cl: two float4s
TOP_COST_GROUP = 64  # work-items of sum_top_cost's one work-group (a -D define)
#: Work-items of split_top_group's groups at most (TOP_GROUP in sah_top.cl,
#: whose local arrays it sizes: about 23 KB, under OpenCL 1.2's 32 KB minimum).
TOP_GROUP = 256
#: Work-groups a compute unit holds at once, for the levels split by whole
#: groups (_group_levels): a GPU's multiprocessor runs several (2048 threads
#: on NVIDIA's, 8 groups of 256).
GROUPS_PER_UNIT = 8
# Device bytes build_top takes per cluster: first primitive, root, two record
# buffers, cost, height, box, three task lists, two child links, top box.
BYTES_PER_CLUSTER = (4 + 4 + 2 * CLUSTER_RECORD_BYTES + 4 + 4 + layout.AABB.itemsize
                     + 3 * TOP_TASK_BYTES + 2 * 4 + layout.AABB.itemsize)


def max_clusters(triangle_count: int) -> int:
    """The most clusters a build over triangle_count triangles can have."""
    return min(triangle_count, 1 << layout.CLUSTER_BITS)


@dataclass
class TopTree:
    """SAH nodes above the clusters: top_count = clusters - 1 nodes (the root
    is the node of the first split, `root`)."""

    cluster_count: int
    top_count: int
    root: int                # the top node splitting at m is node m - 1: the root is anywhere
    top_left: cl.Buffer      # int32: >= 0 a top node, < 0 the cluster ~ref
    top_right: cl.Buffer
    top_boxes: cl.Buffer     # Aabb
    cluster_roots: cl.Buffer  # int32: radix-tree node of each cluster
    cluster_boxes: cl.Buffer  # Aabb of each cluster (its root's box, gathered compactly)
    depth: int
    sah_cost: float          # of the whole tree, not normalised


def build_top(rt, keys: cl.Buffer, bits: int, tree: RadixTree, metrics: RadixTreeMetrics,
              wait_for=None) -> tuple[TopTree | None, list[cl.Event]]:
    """Find the clusters and, when there are two or more, build the SAH top.
    Returns None when one cluster holds everything (the radix tree is kept)."""
    n = tree.n
    q = rt.queue
    kernel = functools.partial(rt.kernel, "build/sah_top.cl", MORTON_BITS=bits,
                               TOP_COST_GROUP=TOP_COST_GROUP, TOP_GROUP=TOP_GROUP)
    scan = rt.pool.take((n + 1) * 4)
    events = [rt.run(kernel("mark_cluster_starts"), n,
                     keys, n, scan, wait_for=wait_for)]
    events += exclusive_scan(rt, scan, n, wait_for=events[-1:])
    cluster_count = np.empty(1, np.uint32)
    cl.enqueue_copy(q, cluster_count, scan, src_offset=n * 4, wait_for=events[-1:])
    clusters = int(cluster_count[0])
    if clusters < 2:
        return None, events

    def buf(count, itemsize=4):
        return rt.pool.take(count * itemsize)
    first, roots = buf(clusters), buf(clusters)
    records, records_odd = buf(clusters, CLUSTER_RECORD_BYTES), buf(clusters, CLUSTER_RECORD_BYTES)
    cluster_cost, cluster_height = buf(clusters), buf(clusters)
    cluster_box = buf(clusters, layout.AABB.itemsize)
    tasks, next_tasks, stack = (buf(clusters, TOP_TASK_BYTES) for _ in range(3))
    left, right = buf(clusters), buf(clusters)
    boxes = buf(clusters, layout.AABB.itemsize)
    info, root_cost = buf(2), buf(1)  # info: depth, root
    events.append(rt.run(kernel("gather_cluster_starts"), n, scan, n, first, wait_for=events[-1:]))
    events.append(rt.run(kernel("gather_clusters"), clusters, scan, n, first, tree.range_first,
                         tree.range_last, metrics.boxes, metrics.sah_cost, metrics.height, roots,
                         cluster_box, records, cluster_cost, cluster_height, tasks,
                         wait_for=events[-1:]))
    events.append(cl.enqueue_fill_buffer(q, info, np.int32(0), 0, 8, wait_for=events[-1:]))
    # One launch per level, levels 0..serial_depth: tasks at serial_depth
    # build their whole subtrees, so nothing is left after them.  Level L has
    # at most 2^L tasks (each task queues at most two), so the launches are
    # sized without reading the counts back: a read-back per level cost each
    # build a round trip to the device.  The parallel
    # levels stop where there are enough subtrees to fill the device with
    # work (about 64 clusters each).
    serial_depth = _serial_depth(clusters, rt.device.compute_units, rt.profile.gpu)
    task_counts = buf(serial_depth + 2)  # [L]: tasks queued for level L
    events.append(cl.enqueue_fill_buffer(q, task_counts, np.int32(0), 0, (serial_depth + 2) * 4,
                                         wait_for=events[-1:]))
    events.append(cl.enqueue_fill_buffer(q, task_counts, np.int32(1), 0, 4,
                                         wait_for=events[-1:]))  # the root task
    group_levels = _group_levels(serial_depth, rt.device.compute_units, rt.profile.gpu)
    group_kernel = kernel("split_top_group")
    group = min(TOP_GROUP, rt.largest_group(group_kernel))
    for level in range(serial_depth + 1):
        tasks_at_most = min(1 << level, clusters)
        if level < group_levels:  # one work-group per task
            events.append(rt.run(group_kernel, tasks_at_most * group, tasks, level, next_tasks,
                                 task_counts, records, records_odd, cluster_height, left, right,
                                 boxes, info, wait_for=events[-1:], local_size=group))
        else:  # one work-item per task
            events.append(rt.run(kernel("split_top_level"), tasks_at_most, tasks, level,
                                 serial_depth, next_tasks, task_counts, stack, records,
                                 records_odd, cluster_height, left, right, boxes, info,
                                 wait_for=events[-1:], local_size=1))
        tasks, next_tasks = next_tasks, tasks
    events.append(rt.run(kernel("sum_top_cost"), TOP_COST_GROUP, clusters - 1, boxes, clusters,
                         cluster_cost, root_cost, wait_for=events[-1:],
                         local_size=TOP_COST_GROUP))
    depth_and_root = np.empty(2, np.int32)
    total = np.empty(1, np.float32)
    cl.enqueue_copy(q, depth_and_root, info, wait_for=events[-1:])
    cl.enqueue_copy(q, total, root_cost, wait_for=events[-1:])
    return TopTree(clusters, clusters - 1, int(depth_and_root[1]), left, right, boxes, roots,
                   cluster_box, int(depth_and_root[0]), float(total[0])), events


def _serial_depth(clusters: int, compute_units: int, gpu: bool) -> int:
    """Levels built one launch each: until about 64 clusters per subtree, and
    no further than needed for 16 subtrees per compute unit (256 on GPUs)."""
    per_unit = 256 if gpu else 16
    by_work = max(0, (clusters // 64).bit_length() - 1)
    by_width = max(1, (per_unit * compute_units).bit_length() - 1)
    return min(by_work, by_width)


def _group_levels(serial_depth: int, compute_units: int, gpu: bool) -> int:
    """Levels 0 .. n-1 split one task per work-group (split_top_group), the
    others one task per work-item (issue 57).  On a GPU while a level's
    tasks, at most 2^L, are no more than the work-groups the device holds
    at once: there one work-item per task would leave most of the device
    idle while each scans a large share of the clusters serially.  Never the
    serial level (its tasks build whole subtrees).  Not on the CPU profile:
    a core runs a work-group's items one after another anyway, and there the
    group split measured slower than one work-item per task."""
    if not gpu:
        return 0
    resident = GROUPS_PER_UNIT * compute_units
    return min(serial_depth, resident.bit_length())
