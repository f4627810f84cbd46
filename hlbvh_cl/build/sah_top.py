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
# Device bytes build_top takes per cluster it can hold (max_clusters): first
# primitive, root, two record buffers, cost, height, box, the serial level's
# task stack, two child links, top box.  (The two task lists hold the
# parallel levels' tasks only: task_lists_bytes.)
BYTES_PER_CLUSTER = (4 + 4 + 2 * CLUSTER_RECORD_BYTES + 4 + 4 + layout.AABB.itemsize
                     + TOP_TASK_BYTES + 2 * 4 + layout.AABB.itemsize)


def max_clusters(triangle_count: int) -> int:
    """The most clusters a build over triangle_count triangles can have."""
    return min(triangle_count, 1 << layout.CLUSTER_BITS)


def task_lists_bytes(triangle_count: int) -> int:
    """The most bytes of the two task lists: level L holds at most 2^L
    tasks, and _serial_depth stops where 2^L reaches clusters / 64."""
    return 2 * TOP_TASK_BYTES * max(1, max_clusters(triangle_count) // 64)


@dataclass
class TopTree:
    """SAH nodes above the clusters: clusters - 1 top nodes (the root is the
    node of the first split, info[1]), none where one cluster holds
    everything (then the radix tree stands).  The cluster count, the depth
    and the root stay on the device, in info (issue 57; flatten.cl reads
    them): the buffers are sized for `capacity` clusters, as many as there
    can be."""

    capacity: int
    info: cl.Buffer          # int32[3]: the tree's depth, the root top node, the cluster count
    top_left: cl.Buffer      # int32: >= 0 a top node, < 0 the cluster ~ref
    top_right: cl.Buffer
    top_boxes: cl.Buffer     # Aabb; the top node splitting at m is node m - 1
    cluster_roots: cl.Buffer  # int32: radix-tree node of each cluster
    cluster_boxes: cl.Buffer  # Aabb of each cluster (its root's box, gathered compactly)
    sah_cost: cl.Buffer      # float32: of the whole tree, not normalised
    spent: list              # build_top's scratch, dead once its kernels have run

    def buffers(self) -> list[cl.Buffer]:
        """The buffers above (not spent), which only flatten reads."""
        return [self.info, self.top_left, self.top_right, self.top_boxes, self.cluster_roots,
                self.cluster_boxes, self.sah_cost]


def build_top(rt, keys: cl.Buffer, bits: int, tree: RadixTree, metrics: RadixTreeMetrics,
              spare: list | None = None, wait_for=None) -> tuple[TopTree, list[cl.Event]]:
    """Find the clusters and, when there are two or more, build the SAH top
    over them, all without the host reading anything back: the buffers and
    the launches are sized for max_clusters(n), and the kernels read the
    actual count from the device.  ``spare``: dead buffers of the build to
    reuse first (BufferPool.take_spare)."""
    n = tree.n
    q = rt.queue
    kernel = functools.partial(rt.kernel, "build/sah_top.cl", MORTON_BITS=bits,
                               TOP_COST_GROUP=TOP_COST_GROUP, TOP_GROUP=TOP_GROUP)
    capacity = max_clusters(n)
    spare = [] if spare is None else spare

    def buf(count, itemsize=4):
        return rt.pool.take_spare(spare, count * itemsize)
    # the larger first, so that they find the larger spare buffers
    records, records_odd = buf(capacity, CLUSTER_RECORD_BYTES), buf(capacity, CLUSTER_RECORD_BYTES)
    cluster_box, boxes = buf(capacity, layout.AABB.itemsize), buf(capacity, layout.AABB.itemsize)
    stack = buf(capacity, TOP_TASK_BYTES)
    scan = buf(n + 1)
    first, roots, left, right = buf(capacity), buf(capacity), buf(capacity), buf(capacity)
    cluster_cost, cluster_height = buf(capacity), buf(capacity)
    info, root_cost = buf(3), buf(1)
    # One launch per level, levels 0..serial_depth: tasks at serial_depth
    # build their whole subtrees, so nothing is left after them.  Level L has
    # at most 2^L tasks (each task queues at most two), so the launches are
    # sized without reading the counts back.  The parallel levels stop where
    # there would be enough subtrees to fill the device with work (about 64
    # clusters each), counted for as many clusters as there can be: the
    # levels past the tree's depth find no tasks.
    serial_depth = _serial_depth(capacity, rt.device.compute_units, rt.profile.gpu)
    tasks_at_most = min(1 << serial_depth, capacity)
    tasks, next_tasks = buf(tasks_at_most, TOP_TASK_BYTES), buf(tasks_at_most, TOP_TASK_BYTES)
    task_counts = buf(serial_depth + 2)  # [L]: tasks queued for level L
    events = [rt.run(kernel("mark_cluster_starts"), n, keys, n, scan, wait_for=wait_for)]
    events += exclusive_scan(rt, scan, n, wait_for=events[-1:])
    events.append(rt.run(kernel("gather_cluster_starts"), n, scan, n, first, wait_for=events[-1:]))
    events.append(cl.enqueue_fill_buffer(q, info, np.int32(0), 0, 12, wait_for=events[-1:]))
    events.append(cl.enqueue_fill_buffer(q, task_counts, np.int32(0), 0, (serial_depth + 2) * 4,
                                         wait_for=events[-1:]))
    # also the cluster count into info and, if two or more, the root task
    events.append(rt.run(kernel("gather_clusters"), capacity, scan, n, first, tree.range_first,
                         tree.range_last, metrics.boxes, metrics.sah_cost, metrics.height, roots,
                         cluster_box, records, cluster_cost, cluster_height, tasks, task_counts,
                         info, wait_for=events[-1:]))
    group_levels = _group_levels(serial_depth, rt.device.compute_units, rt.profile.gpu)
    group_kernel = kernel("split_top_group")
    group = min(TOP_GROUP, rt.largest_group(group_kernel))
    for level in range(serial_depth + 1):
        level_tasks = min(1 << level, capacity)
        if level < group_levels:  # one work-group per task
            events.append(rt.run(group_kernel, level_tasks * group, tasks, level, next_tasks,
                                 task_counts, records, records_odd, cluster_height, left, right,
                                 boxes, info, wait_for=events[-1:], local_size=group))
        else:  # one work-item per task
            events.append(rt.run(kernel("split_top_level"), level_tasks, tasks, level,
                                 serial_depth, next_tasks, task_counts, stack, records,
                                 records_odd, cluster_height, left, right, boxes, info,
                                 wait_for=events[-1:], local_size=1))
        tasks, next_tasks = next_tasks, tasks
    events.append(rt.run(kernel("sum_top_cost"), TOP_COST_GROUP, info, boxes, cluster_cost,
                         root_cost, wait_for=events[-1:], local_size=TOP_COST_GROUP))
    spent = [scan, first, records, records_odd, cluster_cost, cluster_height, stack, tasks,
             next_tasks, task_counts]
    return TopTree(capacity, info, left, right, boxes, roots, cluster_box, root_cost,
                   spent), events


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
