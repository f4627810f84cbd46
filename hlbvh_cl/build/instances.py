"""Two-level scenes: each mesh's own tree, built once by the usual pipeline
(hlbvh_cl.build.pipeline), and a top tree over the instances' world boxes, built by
the same pipeline (kernels/query/walk/instance_leaf.h has the rays' traversal side,
kernels/query/points.cl the point queries').

An instance is a mesh under an affine map (object -> world), with a 32-bit
mask.  Many instances share their mesh's tree.  The top tree is built over
one proxy triangle per instance whose box is the instance's world box (its
corners lo and hi and their midpoint), so Morton codes, the radix sort, the
Karras radix tree, the SAH top, flatten and widen all run unchanged; the top
tree's refs give, for each of its leaf slots, the instance (prim_id) it
holds.  set_transforms rebuilds only that top tree.

With compact=True each mesh's tree has compact leaves (records naming
its vertices, kernels/core/leaf.h), and the joined trees hold every
mesh's records and then every mesh's vertices (kernels/build/instances.cl).

Frames (hlbvh_cl.core.frame): each mesh's tree is built in its own power-of-two
frame, the top tree in one for the world boxes; an instance's record maps
the top frame straight into its mesh's frame, so a ray is mapped once per
instance visited.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from ..core import frame
from ..core import layout
from .pipeline import MAX_TRIANGLES, MAX_VERTICES, BuildStats, Geometry, build
from ..device.runtime import Runtime
from ..core.inputs import ALL_BITS, as_array, mask_bits
from ..mesh import Mesh
from ..core.tree import Tree, leaf_bytes

#: Transforms whose linear part has a determinant this small relative to the
#: product of its row lengths are singular for float32 work: the inverse
#: would amplify the rounding of every mapped ray by more than 2^23.
SINGULAR = 2.0**-23
#: And below this, nearly so: rows this close to dependent (a mesh squashed
#: flat between two rotations; an axis-aligned squash keeps the ratio 1)
#: amplify the rounding of the mapped ray until rays near the surface gain
#: or lose hits against the same mesh flattened.  An icosphere squashed to
#: 1e-5 of its height so (a ratio of 2^-15.5) did for 10 of 20,000 rays
#: whose answer held with the origin moved by 1e-4, to 6e-5 (2^-12.9) for
#: 1 of 40,000; to 1e-4 (2^-12.2) for none of 20,000.  Refused with a margin.
NEARLY_SINGULAR = 2.0**-12


def check_transforms(transforms, label) -> np.ndarray:
    """float64 (K, 3, 4) affine maps from (K, 3, 4) or (K, 4, 4) input (a
    4x4's last row must be 0 0 0 1); ``label(k)`` names transform k in errors
    (e.g. "transforms[3]")."""
    array = as_array(label(0).partition('[')[0], transforms)
    if array.dtype.kind not in "fiu":
        raise TypeError(f"{label(0).partition('[')[0]} has dtype {array.dtype}, expected real "
                        "numbers")
    if array.ndim != 3 or array.shape[1:] not in ((3, 4), (4, 4)):
        raise ValueError(f"{label(0).partition('[')[0]} has shape {array.shape}, expected "
                         "(K, 3, 4) or (K, 4, 4)")
    array = array.astype(np.float64)
    flat = array.reshape(len(array), array.shape[1] * array.shape[2])  # (K may be 0)
    bad = ~np.isfinite(flat).all(axis=1)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{label(k)} is not finite (NaN or inf)")
    large = np.abs(flat).max(axis=1, initial=0.0)
    if (large > np.finfo(np.float32).max).any():  # (its determinant would overflow too)
        k = int(np.argmax(large))
        raise ValueError(f"{label(k)} does not fit float32: an entry is {large[k]:.3g}")
    if array.shape[1] == 4:
        wrong = np.abs(array[:, 3] - (0.0, 0.0, 0.0, 1.0)).max(axis=1) != 0
        if wrong.any():
            k = int(np.flatnonzero(wrong)[0])
            raise ValueError(f"{label(k)} has last row {array[k, 3].tolist()}, expected "
                             "[0, 0, 0, 1] (an affine map)")
        array = array[:, :3]
    linear = array[:, :, :3]
    rows = np.linalg.norm(linear, axis=2)
    det = np.linalg.det(linear)
    ratio = np.abs(det) / np.maximum(np.prod(rows, axis=1), np.finfo(np.float64).tiny)
    refused = ~(ratio >= NEARLY_SINGULAR)
    if refused.any():
        k = int(np.flatnonzero(refused)[0])
        shape = f"(determinant {det[k]:.3g}, rows of length {rows[k].round(6).tolist()})"
        if not ratio[k] > SINGULAR:
            raise ValueError(f"{label(k)} is singular {shape}: it flattens its mesh, so rays "
                             "cannot be mapped into it")
        raise ValueError(f"{label(k)} is singular for float32 work {shape}: its rows are so "
                         "near dependent (the determinant under 2^-12 of their lengths' "
                         "product) that rays mapped into it gain or lose hits near the "
                         "surface; give the mesh's mapped vertices as a Mesh instead")
    return np.ascontiguousarray(array)


def check_instances(instances, mesh_count: int) -> tuple[np.ndarray, np.ndarray]:
    """(mesh index int32 (K,), float64 (K, 3, 4) transforms) from a sequence
    of (mesh_index, transform) pairs; errors name instances[k]."""
    if isinstance(instances, (str, bytes)) or not hasattr(instances, "__len__"):
        raise TypeError("instances must be a sequence of (mesh_index, transform) pairs, got "
                        f"{type(instances).__name__}")
    if len(instances) == 0:
        raise ValueError("instances is empty: an instanced Scene needs at least one instance")
    meshes = np.empty(len(instances), np.int32)
    transforms = np.zeros((len(instances), 4, 4))
    transforms[:, 3, 3] = 1.0
    for k, item in enumerate(instances):
        if not (isinstance(item, (tuple, list)) and len(item) == 2):
            raise TypeError(f"instances[{k}] must be a (mesh_index, transform) pair, got "
                            f"{type(item).__name__}")
        index, transform = item
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)):
            raise TypeError(f"instances[{k}][0] (mesh_index) must be an int, got "
                            f"{type(index).__name__}")
        if not 0 <= index < mesh_count:
            raise ValueError(f"instances[{k}][0] = {index} is not a mesh index: the scene has "
                             f"{mesh_count} mesh(es)")
        meshes[k] = index
        array = as_array(f"instances[{k}][1]", transform)
        if array.shape not in ((3, 4), (4, 4)) or array.dtype.kind not in "fiu":
            raise ValueError(f"instances[{k}][1] (transform) has shape {array.shape} and dtype "
                             f"{array.dtype}, expected a (3, 4) or (4, 4) array of numbers")
        transforms[k, :len(array)] = array
    maps = check_transforms(transforms, lambda k: f"instances[{k}][1]")
    unplaced = np.setdiff1d(np.arange(mesh_count), meshes)
    if len(unplaced):
        # Only instances are drawn: a mesh none places would vanish silently.
        listed = ", ".join(str(i) for i in unplaced[:8]) + (", ..." if len(unplaced) > 8 else "")
        first = int(unplaced[0])
        raise ValueError(f"no instance places mesh{'es' * (len(unplaced) > 1)} {listed}: with "
                         "instances, a Scene holds only what they place, so it would be missing; "
                         f"add an instance such as ({first}, np.eye(4)) to keep a mesh where it "
                         "lies, or leave it out of meshes")
    return meshes, maps


def check_masks(masks, count: int, what: str) -> np.ndarray:
    """uint32 (count,) masks: None (all bits), one int, or one per item
    (inputs.mask_bits: ~2 is every bit but bit 1)."""
    if masks is None:
        return np.full(count, ALL_BITS, np.uint32)
    array = as_array("masks", masks)
    if array.dtype.kind not in "iu":
        raise TypeError(f"masks has dtype {array.dtype}, expected integers (32-bit masks)")
    if array.ndim == 0:
        array = np.full(count, array)
    if array.shape != (count,):
        raise ValueError(f"masks has shape {array.shape}, expected ({count},): one per {what}")
    return mask_bits(array, "masks")


@dataclass
class MeshTrees:
    """Every mesh's tree, one after another in one set of device buffers: mesh
    m's wide nodes start at node_base[m] and its triangles at
    triangle_base[m] (the kernels offset their pointers by these, so each
    tree keeps its own indices)."""

    nodes: cl.Buffer
    triangles: cl.Buffer
    refs: cl.Buffer
    node_base: np.ndarray      # int64 (M,)
    triangle_base: np.ndarray  # int64 (M,)
    scales: np.ndarray         # float64 (M,) each tree's frame
    lo: np.ndarray             # float64 (M, 3) each mesh's box, its own coordinates
    hi: np.ndarray
    depth: int                 # the deepest tree's
    triangle_count: int
    stats: list                # BuildStats per mesh
    levels: list               # each tree's Tree.levels (its own node indices)
    #: compact leaves (Scene(..., compact=True)): `triangles` holds every
    #: tree's IndexedTriangle records, then every tree's vertices
    #: (vertex_count of them; kernels/build/instances.cl)
    indexed: bool = False
    vertex_count: int = 0
    #: WideDipoles per wide node of every tree (in the nodes' places), made
    #: by the first winding-number query (hlbvh_cl.query.points)
    dipoles: cl.Buffer | None = None

    @property
    def node_count(self) -> int:
        return int(self.node_base[-1]) + sum(count for _, count in self.levels[-1])

    def memory(self) -> dict[str, int]:
        """Device bytes the meshes' trees take for traversal, as Tree.memory."""
        return {"node_bytes": self.node_count * layout.WIDE_NODE.itemsize,
                "triangle_bytes": leaf_bytes(self.vertex_count, self.triangle_count,
                                             self.indexed)}

    def release(self, pool) -> None:
        pool.give(self.nodes, self.triangles, self.refs, self.dipoles)
        self.nodes = self.triangles = self.refs = self.dipoles = None


def _mesh_boxes(meshes: list[Mesh]) -> tuple[np.ndarray, np.ndarray]:
    """float64 (M, 3) lo and hi of each mesh's triangles (its used vertices)."""
    used = [frame.used_vertices(m.vertices, m.faces) for m in meshes]
    return (np.array([u.min(axis=0) for u in used], np.float64),
            np.array([u.max(axis=0) for u in used], np.float64))


def build_mesh_trees(rt: Runtime, meshes: list[Mesh], builder: str,
                     morton_bits: int, checked: Sequence[Mesh] = (),
                     indexed: bool = False) -> MeshTrees:
    """Each mesh's tree by the usual build, copied into shared buffers
    (with ``indexed``, compact leaves: _join_vertices).  Meshes are
    immutable: one that is ``checked``'s at its index was warned about
    (frame.warn_vanishing) when it was built before."""
    total = sum(mesh.triangle_count for mesh in meshes)
    if total > MAX_TRIANGLES:  # each alone may fit; their joined trees not
        raise ValueError(f"the scene's meshes hold {total} triangles together; at most "
                         f"{MAX_TRIANGLES} fit the int32 offsets (layout.INSTANCE's node_base "
                         "and triangle_base) by which instances find their mesh's tree")
    vertices = sum(mesh.vertex_count for mesh in meshes)
    if indexed and total + vertices > MAX_VERTICES:
        raise ValueError(f"the scene's meshes hold {total} triangles and {vertices} vertices "
                         f"together; their compact trees' int32 leaf records reach at most "
                         f"{MAX_VERTICES} of both (build the scene with compact=False)")
    trees, stats, scales = [], [], []
    try:
        for geom_id, mesh in enumerate(meshes):
            largest = frame.largest_used(mesh.vertices, mesh.faces)
            scale = frame.scale_for(largest)
            # each mesh has a frame of its own: only its own largest coordinate can
            # make its small triangles degenerate
            if geom_id >= len(checked) or checked[geom_id] is not mesh:
                frame.warn_vanishing(mesh, geom_id, scale, largest, "its own")
            geometry = Geometry.upload(rt, frame.to_frame(mesh.vertices, scale), mesh.faces,
                                       np.zeros(1, np.int32))
            tree, stat = build(rt, geometry, builder, morton_bits, scale, indexed)
            trees.append(tree)
            stats.append(stat)
            scales.append(scale)
        node_counts = np.array([t.node_count for t in trees], np.int64)
        triangle_counts = np.array([t.triangle_count for t in trees], np.int64)
        node_base = np.concatenate([[0], np.cumsum(node_counts)[:-1]])
        triangle_base = np.concatenate([[0], np.cumsum(triangle_counts)[:-1]])
        vertex_counts = np.array([t.vertex_count for t in trees], np.int64)
        # an indexed tree's leaves are 12-byte cells: its records, then its vertices
        leaf = layout.INDEXED_TRIANGLE if indexed else layout.TRIANGLE
        sizes = {"nodes": (int(node_counts.sum()), layout.WIDE_NODE.itemsize),
                 "triangles": (int(triangle_counts.sum() + vertex_counts.sum()), leaf.itemsize),
                 "refs": (int(triangle_counts.sum()), layout.TRIANGLE_REF.itemsize)}
        if len(trees) == 1:  # its own buffers: no copy, no second set in memory
            joined = {"nodes": trees[0].nodes, "triangles": trees[0].triangles,
                      "refs": trees[0].refs}
        else:
            rt.check_allocation("the meshes' trees", {name: n * size for name, (n, size)
                                                      in sizes.items()})
            joined = {name: cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, n * size)
                      for name, (n, size) in sizes.items()}
            for tree, nb, tb in zip(trees, node_base, triangle_base):
                for name, source, base in (("nodes", tree.nodes, nb),
                                           ("triangles", tree.triangles, tb),
                                           ("refs", tree.refs, tb)):
                    size = sizes[name][1]
                    count = tree.node_count if name == "nodes" else tree.triangle_count
                    cl.enqueue_copy(rt.queue, joined[name], source, byte_count=count * size,
                                    dst_offset=int(base) * size)
            if indexed:
                _join_vertices(rt, trees, joined["triangles"], triangle_base,
                               int(triangle_counts.sum()))
        rt.queue.finish()
    finally:
        # Freed (but for what `joined` holds), not pooled: no later build takes
        # buffers of these sizes, and pooled they would double the meshes'
        # trees in memory.
        for tree in trees:
            tree.nodes = tree.triangles = tree.refs = tree.vertex_ids = None
            tree.released = True
    return MeshTrees(joined["nodes"], joined["triangles"], joined["refs"], node_base,
                     triangle_base, np.array(scales), *_mesh_boxes(meshes),
                     max(t.depth for t in trees), int(triangle_counts.sum()), stats,
                     [t.levels for t in trees], indexed=indexed,
                     vertex_count=int(vertex_counts.sum()))


def _join_vertices(rt: Runtime, trees: list[Tree], joined: cl.Buffer,
                   triangle_base: np.ndarray, triangle_total: int) -> None:
    """The compact trees' vertices after all their records (copied in
    already, each tree's at its triangle_base), and each tree's records
    shifted to name them there (kernels/build/instances.cl): a record at
    cell triangle_base + i named vertex v at its tree's cell
    triangle_count + v, which now lies at triangle_total + vertex_base + v."""
    cell = layout.INDEXED_TRIANGLE.itemsize
    kernel = rt.kernel("build/instances.cl", "shift_corners")
    vertex_base = triangle_total
    for tree, base in zip(trees, triangle_base):
        cl.enqueue_copy(rt.queue, joined, tree.triangles, byte_count=tree.vertex_count * cell,
                        src_offset=tree.triangle_count * cell, dst_offset=vertex_base * cell)
        delta = vertex_base - tree.triangle_count - int(base)
        if delta and tree.triangle_count:
            rt.run(kernel, tree.triangle_count, joined, np.uint32(base),
                   np.uint32(tree.triangle_count), np.int32(delta))
        vertex_base += tree.vertex_count


def world_boxes(transforms: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray,
                                                                                  np.ndarray]:
    """The world boxes (float64 (K, 3) lo, hi) of boxes [lo, hi] (K, 3)
    under the maps (K, 3, 4): each axis's extreme over the 8 corners is the
    map's offset plus, per column, the larger or smaller of the two
    products (Arvo 1990, "Transforming Axis-Aligned Bounding Boxes")."""
    linear, offset = transforms[:, :, :3], transforms[:, :, 3]
    a = linear * lo[:, None, :]
    b = linear * hi[:, None, :]
    return offset + np.minimum(a, b).sum(axis=2), offset + np.maximum(a, b).sum(axis=2)


def _outward(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 boxes that hold the float64 ones, grown by a little more than
    the rounding a mapped ray sees, so a hit near an instance's boundary is
    never culled at the top."""
    pad = (np.abs(lo) + np.abs(hi) + (hi - lo)) * 2.0**-20
    with np.errstate(over="ignore"):  # a box past float32 becomes infinite, as it should
        return ((lo - pad).astype(np.float32), (hi + pad).astype(np.float32))


def reach_scales(linear: np.ndarray) -> np.ndarray:
    """float32 (K,): 1 / s^2 for each (K, 3, 3) linear map, s its least
    singular value, rounded up: |A x - A y| >= s |x - y|, so a box whose
    squared distance from the mapped point exceeds reach_scale times the
    best squared distance so far cannot hold a nearer point."""
    least = np.linalg.svd(linear, compute_uv=False)[:, -1]
    with np.errstate(divide="ignore", over="ignore"):
        exact = 1.0 / least**2
        rounded = exact.astype(np.float32)
    return np.where(rounded < exact, np.nextafter(rounded, np.float32(np.inf)), rounded)


def instance_records(transforms: np.ndarray, meshes: np.ndarray, masks: np.ndarray,
                     trees: MeshTrees, top_scale: float) -> np.ndarray:
    """layout.INSTANCE records: each map from the top frame (world coordinates
    times top_scale) into its mesh's frame (mesh coordinates times that
    tree's scale), and back (to_world, with the reach_scale that bounds how
    much it can shrink a distance, for the closest-point walk)."""
    linear, offset = transforms[:, :, :3], transforms[:, :, 3]
    inverse = np.linalg.inv(linear)
    mesh_scale = trees.scales[meshes]
    to_mesh = np.empty((len(meshes), 3, 4))
    to_mesh[:, :, :3] = inverse * (mesh_scale / top_scale)[:, None, None]
    to_mesh[:, :, 3] = -np.einsum("kij,kj->ki", inverse, offset) * mesh_scale[:, None]
    to_world = np.empty((len(meshes), 3, 4))
    to_world[:, :, :3] = linear * (top_scale / mesh_scale)[:, None, None]
    to_world[:, :, 3] = offset * top_scale
    with np.errstate(over="ignore"):
        held = (np.isfinite(to_mesh.astype(np.float32)).all(axis=(1, 2))
                & np.isfinite(to_world.astype(np.float32)).all(axis=(1, 2)))
    lo, hi = world_boxes(transforms, trees.lo[meshes], trees.hi[meshes])
    if not held.all():  # its instance would be silently missed by every query
        k = int(np.flatnonzero(~held)[0])
        reach = ""
        if top_scale < 1:  # the top frame is shrunk: name the instance that shrinks it
            far = int(np.argmax(np.maximum(np.abs(lo), np.abs(hi)).max(axis=1)))
            who = "it" if far == k else f"instance {far}"
            reach = (f" ({who} reaches {np.abs([lo[far], hi[far]]).max():.3g} from the "
                     "origin, which sets the scale of the top frame)")
        raise ValueError(f"instance {k}'s transform does not fit float32: its map into the "
                         f"mesh (or back) overflows in the frames the scene is built in{reach}; "
                         "scale its axes less far apart, or keep the instances within a "
                         "smaller range")
    check_resolved(lo, hi, lambda k: f"instance {k}'s transform")
    records = np.zeros(len(meshes), layout.INSTANCE)
    records["to_mesh"] = to_mesh.reshape(-1, 12)
    records["to_world"] = to_world.reshape(-1, 12)
    records["reach_scale"] = reach_scales(to_world[:, :, :3])
    records["normal_sign"] = np.sign(np.linalg.det(linear))
    records["mask"] = masks
    records["mesh"] = meshes
    records["node_base"] = trees.node_base[meshes]
    records["triangle_base"] = trees.triangle_base[meshes]
    return records


#: The fewest float32 steps (spacings at its farthest coordinate) an
#: instance's world box may span (check_resolved).  Rounding a world point
#: to float32, and the map into the mesh in float32 entries, move it by a
#: few steps, in world units whatever the map, so an instance smaller than
#: that is missed, or hit anywhere, by every ray.  A map that squashes a
#: mesh flat keeps its other sides, and is hit as a flat mesh there would be.
FEWEST_STEPS = 4


def check_resolved(lo: np.ndarray, hi: np.ndarray, label) -> None:
    """Raises the ValueError that names (``label(k)``, e.g. "instance 3's
    transform") the first instance whose world box [lo, hi] (float64 (K, 3))
    spans fewer than FEWEST_STEPS float32 steps at its place (a mesh of no
    extent, every triangle a point, is never hit anyway)."""
    span = (hi - lo).max(axis=1, initial=0.0)
    farthest = np.maximum(np.abs(lo), np.abs(hi)).max(axis=1, initial=0.0)
    with np.errstate(over="ignore"):
        step = np.spacing(farthest.astype(np.float32)).astype(np.float64)
    small = (span > 0) & (span < FEWEST_STEPS * step)
    if small.any():
        k = int(np.argmax(small))
        raise ValueError(f"{label(k)} makes its mesh too small for its place in the world: it "
                         f"spans {span[k]:.3g} at {farthest[k]:.3g} from the origin, under "
                         f"{FEWEST_STEPS} float32 steps of {step[k]:.2g} there, so rays would "
                         "miss it or hit it anywhere; scale it up or place it nearer the origin")


@dataclass
class InstancedTree:
    """A two-level scene on the device, as the queries read it: the top
    tree over the instances (its refs' prim_id is the instance of each leaf
    slot), the instance records and every mesh's tree."""

    top: Tree
    meshes: MeshTrees
    instances: cl.Buffer
    instance_count: int
    released: bool = False

    @property
    def depth(self) -> int:
        """The deeper of the two levels (each walk has its own stack)."""
        return max(self.top.depth, self.meshes.depth)

    @property
    def scale(self) -> float:
        return self.top.scale

    @property
    def nodes(self) -> cl.Buffer:
        return self.top.nodes

    @property
    def node_count(self) -> int:
        return self.top.node_count

    @property
    def triangle_count(self) -> int:
        return self.meshes.triangle_count

    @property
    def indexed(self) -> bool:
        """Whether the meshes' trees have compact leaves (core/tree.py's leaf_defines)."""
        return self.meshes.indexed

    @property
    def bounds_lo(self) -> np.ndarray:
        return self.top.bounds_lo

    @property
    def bounds_hi(self) -> np.ndarray:
        return self.top.bounds_hi

    def scene_args(self, masks: cl.Buffer, mask_step: int) -> tuple:
        """The SCENE_PARAMS of kernels built with INSTANCES (query/rays.cl)."""
        return (self.top.nodes, self.top.triangles, self.top.refs, self.instances, masks,
                np.uint32(mask_step), self.meshes.nodes, self.meshes.triangles, self.meshes.refs)

    def release(self, pool) -> None:
        """Give the top tree and the instance records back (the meshes' trees
        stay with their Scene, which may build a new top over them)."""
        self.top.release(pool)
        pool.give(self.instances)
        self.instances = None
        self.released = True


class TwoLevel:
    """What an instanced Scene keeps between top builds: the meshes' trees,
    the instances' meshes, maps and masks, and the proxy geometry buffers."""

    def __init__(self, rt: Runtime, meshes: list[Mesh], instance_meshes: np.ndarray,
                 transforms: np.ndarray, masks: np.ndarray, builder: str, morton_bits: int,
                 compact: bool = False):
        self.rt = rt
        self.builder, self.morton_bits = builder, morton_bits
        self.compact = compact
        self.instance_meshes = instance_meshes
        self.transforms = transforms
        self.masks = masks
        self.trees = build_mesh_trees(rt, meshes, builder, morton_bits, indexed=compact)
        self.meshes = tuple(meshes)  # the ones the trees hold
        # The meshes' build scratch is not kept for a rebuild, as a flat
        # scene's is: their trees are rebuilt seldom, the top tree often.
        rt.pool.clear()
        count = len(instance_meshes)
        self._geometry = Geometry.upload(rt, np.zeros((3 * count, 3), np.float32),
                                         np.arange(3 * count, dtype=np.int32).reshape(-1, 3),
                                         np.zeros(1, np.int32))

    def rebuild_meshes(self, meshes: list[Mesh]) -> None:
        old, self.trees = self.trees, None
        if old is not None:  # None after a rebuild that failed
            old.release(self.rt.pool)
        self.trees = build_mesh_trees(self.rt, meshes, self.builder, self.morton_bits,
                                      checked=self.meshes, indexed=self.compact)
        self.meshes = tuple(meshes)
        self.rt.pool.clear()

    def build_top(self) -> tuple[InstancedTree, BuildStats]:
        """The top tree over the instances as they stand, with their records."""
        rt = self.rt
        if self.trees is None:  # a rebuild of the meshes' trees failed or was interrupted
            raise RuntimeError("this Scene's meshes have no trees: its last rebuild failed; "
                               "call scene.rebuild() to build them")
        lo, hi = world_boxes(self.transforms, self.trees.lo[self.instance_meshes],
                             self.trees.hi[self.instance_meshes])
        lo, hi = _outward(lo, hi)
        largest = max(float(np.abs(lo).max()), float(np.abs(hi).max()))
        top_scale = frame.scale_for(largest)
        # first: maps that overflow float32 in these frames are refused before any build
        records = instance_records(self.transforms, self.instance_meshes, self.masks, self.trees,
                                   top_scale)
        proxies = np.empty((len(lo), 3, 3), np.float32)
        proxies[:, 0], proxies[:, 1] = lo, hi
        proxies[:, 2] = (lo.astype(np.float64) + hi) / 2
        proxies = frame.to_frame(proxies.reshape(-1, 3), top_scale)
        cl.enqueue_copy(rt.queue, self._geometry.vertices, np.ascontiguousarray(proxies))
        top, stats = build(rt, self._geometry, self.builder, self.morton_bits, top_scale)
        instances = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                              hostbuf=records)
        return InstancedTree(top, self.trees, instances, len(records)), stats
