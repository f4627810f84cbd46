"""The build pipeline: bounds -> Morton codes -> radix sort -> radix tree with
its boxes (+ SAH collapse) -> SAH top over clusters -> flat binary tree ->
8-wide tree (Lauterbach et al. 2009 and Pantaleoni & Luebke 2010 for the
HLBVH, Karras 2012 for the radix tree, Wald et al. 2008 for the wide nodes).

Every stage runs on the device; this module only sequences them, sizes the
buffers (failing before any allocation when the device is too small) and
collects per-stage times from profiling events.  Its one product is a Tree
and its BuildStats: everything else, the binary tree included, is scratch.

The host does not wait between stages (issue 57): every buffer is sized
from the triangle count for as much as the stage can need, the kernels read
the sizes the stages before them found from the device, and the host reads
the figures it needs (the scene's box, the flat tree's summary, the wide
levels) in one batch, before the last kernel, which writes the wide nodes
into a buffer of their exact size; then it waits for that kernel.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from ..core import layout
from .bounds import scene_bounds
from ..device.runtime import Runtime, event_ms
from .flatten import box_area, flatten_nodes
from .morton import key_dtype, morton_codes
from .radix_tree import RadixTree, RadixTreeMetrics, build_radix_tree
from .sah_top import BYTES_PER_CLUSTER, build_top, max_clusters, task_lists_bytes
from ..parallel.radix_sort import sorter
from ..core.tree import Tree, leaf_bytes
from .widen import Widening, read_back

#: The builders.  A better tree is not where traversal loses to Embree: the
#: bunny's triangles under a full binned SAH (32 bins a node, on the host),
#: widened by the same widen stage, gave the same hits and fewer wide nodes
#: but traced bounces and incoherent rays barely faster than the HLBVH's
#: tree (figures in the commit that says so).
BUILDERS = ("hlbvh", "lbvh")
STAGES = ("bounds", "morton", "sort", "radix_tree", "sah_top", "flatten", "widen")
MAX_TRIANGLES = 2**30  # node indices are int32 (2n - 1 of them must fit)
MAX_VERTICES = 2**31 - 1  # the meshes' faces are joined into one int32 index array


@dataclass
class Geometry:
    """The scene's meshes on the device, concatenated.  Kept between builds
    so that refits and rebuilds need no upload but the moved vertices."""

    vertices: cl.Buffer        # float32[V*3]
    faces: cl.Buffer           # int32[M*3], indices into the concatenated vertices
    mesh_first_face: cl.Buffer  # int32[G]
    vertex_count: int
    triangle_count: int
    mesh_count: int

    @classmethod
    def upload(cls, rt: Runtime, vertices: np.ndarray, faces: np.ndarray,
               mesh_first_face: np.ndarray) -> "Geometry":
        flags = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
        return cls(cl.Buffer(rt.context, flags, hostbuf=np.ascontiguousarray(vertices, np.float32)),
                   cl.Buffer(rt.context, flags, hostbuf=np.ascontiguousarray(faces, np.int32)),
                   cl.Buffer(rt.context, flags,
                             hostbuf=np.ascontiguousarray(mesh_first_face, np.int32)),
                   len(vertices), len(faces), len(mesh_first_face))


def copy_vertices(rt: Runtime, vertices: cl.Buffer, vertex_count: int, triangle_count: int,
                  leaves: cl.Buffer, wait_for=None) -> cl.Event:
    """An indexed tree's vertices (the scene's, already in the tree's frame)
    into their place after its ``triangle_count`` leaf records: by a build,
    and by a refit after they moved."""
    return cl.enqueue_copy(rt.queue, leaves, vertices,
                           dst_offset=triangle_count * layout.INDEXED_TRIANGLE.itemsize,
                           byte_count=vertex_count * 12, wait_for=wait_for)


def build_memory(vertex_count: int, triangle_count: int, morton_bits: int,
                 indexed: bool = False) -> dict[str, int]:
    """Bytes of every device buffer a build holds at its peak."""
    n = triangle_count
    key = key_dtype(morton_bits).itemsize
    return {
        "vertices": vertex_count * 12, "faces": n * 12, "centroids": n * 16,
        "morton keys (x2 for the sort)": 2 * n * key, "primitive ids (x2 for the sort)": 2 * n * 4,
        "radix tree links": (6 * n - 5) * 4,
        "radix tree walk (far ends, arrival counts)": 3 * max(1, n - 1) * 4,
        "radix tree boxes": (2 * n - 1) * layout.AABB.itemsize,
        "radix tree costs, heights, flags": (2 * n - 1) * 8 + 2 * n * 4,
        "scans": 2 * (n + 1) * 4,
        "flat nodes": max(1, n - 1) * layout.FLAT_NODE.itemsize,
        "triangles": leaf_bytes(vertex_count, n, indexed),
        "triangle refs": n * layout.TRIANGLE_REF.itemsize,
        "triangle vertex ids": 0 if indexed else n * 12,
        "SAH top (clusters)": max_clusters(n) * BYTES_PER_CLUSTER,
        "SAH top (task lists)": task_lists_bytes(n),
    }


def check_fits(rt: Runtime, vertex_count: int, triangle_count: int, morton_bits: int,
               indexed: bool = False) -> None:
    if vertex_count > MAX_VERTICES:
        raise ValueError(f"the scene has {vertex_count} vertices over all its meshes; at most "
                         f"{MAX_VERTICES} fit the int32 face indices they are joined by")
    if triangle_count > MAX_TRIANGLES:
        raise ValueError(f"the scene has {triangle_count} triangles; at most {MAX_TRIANGLES} fit "
                         "int32 node indices")
    if indexed and triangle_count + vertex_count > MAX_VERTICES:
        raise ValueError(f"the scene has {triangle_count} triangles and {vertex_count} vertices; "
                         f"a compact tree's int32 leaf records reach at most {MAX_VERTICES} of "
                         "both together (build it with compact=False)")
    rt.check_allocation(f"building a BVH over {triangle_count:,} triangles",
                        build_memory(vertex_count, triangle_count, morton_bits, indexed))


@dataclass(frozen=True)
class BuildStats:
    """What one build made and what it took; a refit replaces only refit_ms.

    nodes, leaves, depth and sah_cost (C_t = C_i = 1, relative to the root's
    area) describe the binary tree as built; a refit keeps its topology and
    these fields, though the boxes move.  clusters is the SAH top's input
    (1 for lbvh).  wide_nodes and wide_depth describe the 8-wide tree that
    traversal reads.  times_ms holds the device milliseconds of each stage
    (STAGES), device_ms their sum and wall_ms the host's whole build.
    node_bytes and triangle_bytes are the device memory traversal reads
    (Tree.memory: the wide nodes and the leaves' triangles), tree_bytes
    their sum; the refs and vertex ids that map hits back to meshes and
    feed refits are not in it.
    refit_ms is None, or after update_vertices the device milliseconds of
    its upload and refit and its wall time: {"upload", "refit", "wall"}.
    """

    builder: str
    morton_bits: int
    triangles: int
    nodes: int
    leaves: int
    depth: int
    sah_cost: float
    clusters: int
    wide_nodes: int
    wide_depth: int
    node_bytes: int
    triangle_bytes: int
    times_ms: dict
    device_ms: float
    wall_ms: float
    refit_ms: dict | None = None

    @property
    def tree_bytes(self) -> int:
        return self.node_bytes + self.triangle_bytes


def build(rt: Runtime, geometry: Geometry, builder: str = "hlbvh", morton_bits: int = 30,
          scale: float = 1.0, indexed: bool = False) -> tuple[Tree, BuildStats]:
    """Build the Tree over ``geometry`` (its coordinates multiplied by
    ``scale``, hlbvh_cl.core.frame) and its BuildStats; with ``indexed`` its
    leaves name the geometry's vertices (Scene(..., compact=True)).  Every stage's scratch,
    the binary tree included, goes back to the runtime's pool when the
    build ends, for the next build; an indexed build's is let go, the
    sorter's scratch pair too, as a compact scene keeps nothing but its
    tree.  Builds on one runtime are serialised: they share the sorter's
    scratch buffers."""
    if builder not in BUILDERS:
        raise ValueError(f"builder must be one of {BUILDERS}, got {builder!r}")
    started = time.perf_counter()
    with rt.build_lock, rt.pool.build(keep_scratch=not indexed):
        try:
            tree, stats, stage_events = _build(rt, geometry, builder, morton_bits, scale,
                                               indexed)
        finally:  # (OpenCL frees a released buffer once the commands queued on it are done)
            if indexed:
                sorter(rt, key_dtype(morton_bits)).release_scratch()
    times = {name: event_ms(events) for name, events in stage_events.items()}
    return tree, BuildStats(**stats, times_ms=times, device_ms=sum(times.values()),
                            wall_ms=(time.perf_counter() - started) * 1e3)


def _build(rt: Runtime, geometry: Geometry, builder: str, morton_bits: int, scale: float,
           indexed: bool):
    dtype = key_dtype(morton_bits)
    n = geometry.triangle_count
    check_fits(rt, geometry.vertex_count, n, morton_bits, indexed)
    hlbvh = builder == "hlbvh"
    stage_events: dict[str, list] = {name: [] for name in STAGES}
    buf = rt.pool.take

    bounds, centroids, inverse_extent = buf(2 * layout.AABB.itemsize), buf(n * 16), buf(16)
    stage_events["bounds"] = scene_bounds(rt, geometry.vertices, geometry.faces, n, bounds,
                                          centroids, inverse_extent)

    keys, primitive_ids = buf(n * dtype.itemsize), buf(n * 4)
    unsorted = (keys, primitive_ids)
    stage_events["morton"] = morton_codes(rt, centroids, n, bounds, inverse_extent, keys,
                                          primitive_ids, morton_bits,
                                          wait_for=stage_events["bounds"][-1:])

    # The result may sit in the sorter's scratch, which the next build on this
    # runtime reuses: nothing sorted outlives this build (refits use refs).
    keys, primitive_ids, stage_events["sort"] = sorter(rt, dtype).sort(
        keys, primitive_ids, n, morton_bits, wait_for=stage_events["morton"][-1:])

    radix, metrics = RadixTree.allocate(rt, n), RadixTreeMetrics.allocate(rt, n)
    triangles = buf(leaf_bytes(geometry.vertex_count, n, indexed))
    # an indexed tree's records name its vertices: no vertex ids beside them
    refs, vertex_ids = buf(n * layout.TRIANGLE_REF.itemsize), None if indexed else buf(n * 12)
    rt.pool.keep(*(b for b in (triangles, refs, vertex_ids) if b is not None))
    stage_events["radix_tree"] = build_radix_tree(
        rt, keys, morton_bits, geometry.vertices, geometry.faces, primitive_ids,
        geometry.mesh_first_face, geometry.mesh_count, radix, metrics, triangles, refs,
        vertex_ids, collapse_leaves=hlbvh, indexed=indexed, wait_for=stage_events["sort"][-1:])
    if indexed:  # the vertices the records name, after them
        stage_events["radix_tree"].append(
            copy_vertices(rt, geometry.vertices, geometry.vertex_count, n, triangles))
    # Buffers no later stage reads (the centroids, the radix tree's walk, the
    # sort's input where its result is not): the stages sized for the most
    # they can need take from these first (BufferPool.take_spare).
    spare = [centroids, radix.far_end, radix.visits, *(b for b in unsorted if b is not keys)]

    top = None
    if hlbvh and n > 1:
        top, stage_events["sah_top"] = build_top(rt, keys, morton_bits, radix, metrics, spare,
                                                 wait_for=stage_events["radix_tree"][-1:])
        spare += top.spent

    last = (stage_events["sah_top"] or stage_events["radix_tree"])[-1:]
    # the binary tree: scratch, read only by widen
    bvh2, bvh2_capacity, summary, stage_events["flatten"] = flatten_nodes(
        rt, keys, morton_bits, radix, metrics, top, use_clusters=hlbvh, spare=spare,
        wait_for=last)
    spare += [*radix.buffers(), *metrics.buffers(), *(top.buffers() if top else [])]
    widening = Widening(rt, bvh2, bvh2_capacity, summary, spare,
                        wait_for=stage_events["flatten"][-1:])

    # The build's one read: everything the host needs to know of it
    scene_box, flat = np.empty(2, layout.AABB), np.empty(1, layout.FLAT_SUMMARY)
    read_back(rt, [(scene_box, bounds), (flat, summary), *widening.pending()])
    while not widening.advance():  # a tree deeper than the levels launched
        read_back(rt, widening.pending())
    nodes, levels, stage_events["widen"] = widening.write()
    rt.wait(stage_events["widen"][-1:])

    tree = Tree(nodes=nodes, triangles=triangles, refs=refs, vertex_ids=vertex_ids,
                node_count=levels[-1][0] + levels[-1][1], levels=levels, triangle_count=n,
                bounds_lo=scene_box[0]["lo"].copy(), bounds_hi=scene_box[0]["hi"].copy(),
                scale=scale, indexed=indexed, vertex_count=geometry.vertex_count if indexed else 0)
    flat = flat[0]
    root_box = np.zeros(1, layout.AABB)[0]
    root_box["lo"], root_box["hi"] = flat["lo"], flat["hi"]
    root_area = box_area(root_box)
    leaf_count = int(flat["leaf_count"])
    # a leaf root: the root node (C_t A) over one leaf of n triangles (C_i n A)
    cost = root_area * (1.0 + n) if flat["root_is_leaf"] else float(flat["sah_cost"])
    stats = {
        "builder": builder, "morton_bits": morton_bits, "triangles": n,
        "nodes": int(flat["node_count"]), "leaves": leaf_count, "depth": int(flat["depth"]),
        "sah_cost": cost / root_area if root_area > 0 else float(leaf_count),
        "clusters": int(flat["clusters"]), "wide_nodes": tree.node_count,
        "wide_depth": tree.depth, **tree.memory(),
    }
    return tree, stats, stage_events
