"""Point queries on a finished Tree (kernels/points.cl): the closest surface
point, the generalized winding number, and from both the signed distance and
inside/outside.  Query points walk the wide tree with the same walk as the
rays (kernels/walk.h), as another visitor: on a flat tree a packet of nearby
points per work-item (kernels/point_packet.h; big batches run in fine Morton
order so that a packet's points lie close together), on an instanced one a
point per work-item.

Conventions, shared with tests/point_oracle.py:
  - the closest point is exact per triangle in float (Ericson 2005, sec.
    5.1.5: vertex, edge and face regions); points = (1-u-v)*v0 + u*v1 + v*v2,
    the normal is the unit cross(v1 - v0, v2 - v0) (it follows the winding);
    a point farther than max_distance from every triangle gets distance inf,
    ids -1, u = v = 0, normal 0 and points NaN;
  - the winding number w is the sum of the triangles' solid angles over 4 pi
    (Jacobson, Kavan & Sorkine-Hornung 2013, "Robust Inside-Outside
    Segmentation using Generalized Winding Numbers"), with the far field of
    Barill et al. 2018 ("Fast Winding Numbers for Soups and Clouds"): 1
    inside a closed outward-oriented surface, -1 inside an inward-oriented
    one, 0 outside;
  - inside means |w| >= 0.5, so that a closed mesh's inside is found
    whichever way its faces turn (scanned meshes such as the Stanford bunny
    come oriented inward), as parity ray casting finds it.  On an open mesh
    (holes, a missing cap) or a triangle soup w takes fractional values near
    the openings, and |w| >= 0.5 closes each hole "minimally", as the surface
    of least area spanning it would.  Self-intersections and small holes
    move w little, so the sign stays robust.  Where shells of opposite
    orientation overlap, their windings cancel;
  - signed distance: the closest distance, negative inside;
  - instanced scenes (hlbvh_cl.build.instances): the closest point is exact in the
    world for any affine map (each mesh's tree is walked with the point
    mapped in, its triangles measured mapped out); w is the sum over the
    instances of sign(det) times the mesh's own w at the mapped point, the
    flattened scene's on closed meshes (docs/queries.md); point queries
    take no mask and see every instance.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from ..core import frame
from ..core import inputs
from ..core import layout
from .order import COHERENT_MIN, FINE_ORDER_BITS, device_order, put_rows, take_rows
from ..device.runtime import Runtime
from ..build.instances import InstancedTree
from .rays import (LaunchSizes, check_packet_size, outputs_in_place, stack_size,
                    work_group_size, zero_copy, check_tree, collect)
from .results import ResultPool, on_page, starts_on_page
from ..core.tree import Tree

#: Points per kernel launch at most (as query.MAX_RAYS_PER_LAUNCH: a launch
#: ends soon, so that Ctrl-C is answered quickly).
MAX_POINTS_PER_LAUNCH = 1 << 18

#: Points in a batch's first launch (query.LaunchSizes), fewer than rays as
#: a point's walk costs more than a ray's.
FIRST_LAUNCH = 1 << 13

#: Largest coordinate magnitude of a query point in the tree's frame: the
#: kernels square distances in float32, which stay finite below 2^127.
POINT_RANGE = 2.0**60

#: Per-point outputs of the closest_points kernel: dtype and values per point.
CLOSEST_FIELDS = {"distance": (np.float32, 1), "geom_id": (np.int32, 1),
                  "prim_id": (np.int32, 1), "instance_id": (np.int32, 1),
                  "u": (np.float32, 1), "v": (np.float32, 1), "normal": (np.float32, 3),
                  "points": (np.float32, 3)}


@dataclass
class ClosestPoints:
    """Closest surface points of N query points; beyond max_distance:
    distance inf, ids -1, u = v = 0, normal 0 and points NaN."""

    points: np.ndarray    # float32 (N, 3) nearest surface point, in the caller's coordinates
    distance: np.ndarray  # float32 (N,)
    prim_id: np.ndarray   # int32 (N,) face index within its own mesh
    geom_id: np.ndarray   # int32 (N,) mesh index in the scene
    instance_id: np.ndarray  # int32 (N,) the instance it lies on (-1 without instances)
    u: np.ndarray         # float32 (N,)
    v: np.ndarray         # float32 (N,)
    normal: np.ndarray    # float32 (N, 3) unit geometric normal (0 on a zero-area triangle)

    def __len__(self) -> int:
        return len(self.distance)

    @property
    def found(self) -> np.ndarray:
        """bool (N,): which points have a surface point within max_distance."""
        return self.geom_id >= 0


def check_max_distance(value) -> float:
    array = inputs.numeric_array("max_distance", value)
    if array.ndim != 0:
        raise ValueError(f"max_distance must be a scalar, got shape {array.shape}")
    distance = float(array)
    if np.isnan(distance) or distance < 0:
        raise ValueError(f"max_distance = {distance} must be >= 0 (inf for no limit)")
    return distance


def squared_limit(limit: float) -> np.float32:
    """The kernels' limit on squared distances for distances up to ``limit``
    (>= 0, in the tree's frame): the greatest float32 whose float32 square
    root, the distance they report, is at most ``limit``.  So a point is
    kept exactly when its reported distance is within the limit, where
    float32(limit**2) could drop a point whose distance is the limit
    itself, or keep one beyond a limit that falls between two floats."""
    with np.errstate(over="ignore"):
        top = np.float32(limit)
    if float(top) > limit:  # the greatest float32 distance within the limit
        top = np.nextafter(top, np.float32(0))
    exact = np.float64(top) ** 2
    if not exact <= np.finfo(np.float32).max:  # squares that overflow are kept too
        return np.float32(np.inf)
    square = np.float32(exact)
    while square > 0 and np.sqrt(square) > top:
        square = np.nextafter(square, np.float32(0))
    with np.errstate(over="ignore"):  # the float after FLT_MAX is inf, whose root is too far
        while np.sqrt(np.nextafter(square, np.float32(np.inf))) <= top:
            square = np.nextafter(square, np.float32(np.inf))
    return square


def point_scene_args(tree) -> tuple:
    """A point kernel's POINT_SCENE_PARAMS (kernels/points.cl): a flat tree's
    nodes, triangles and refs; an instanced one's top tree, instances and
    meshes' trees (query.scene_args without the rays' masks: point queries
    see every instance)."""
    if isinstance(tree, InstancedTree):
        return (tree.top.nodes, tree.top.triangles, tree.top.refs, tree.instances,
                tree.meshes.nodes, tree.meshes.triangles, tree.meshes.refs)
    return tree.nodes, tree.triangles, tree.refs


class PointQuery:
    """Closest points, winding numbers and signed distances on one device.

    On CPU runtimes the kernels read the points and write the results in
    the numpy arrays themselves: any array on PoCL (query.zero_copy), arrays
    that start on a page on Intel's (the results are lent from a pool that
    starts them there, results.ResultPool); elsewhere through device buffers
    reused between calls, which only grow.  ``max_points_per_launch`` caps
    the points per kernel launch (bigger batches go in chunks).
    ``packet_size`` sets the points a work-item walks together on flat
    trees (query.PACKET_SIZES; by default the runtime's kernel variant's, as
    RayQuery's): every size gives the same closest points, and the same
    winding numbers up to rounding (the same terms, summed in another order:
    kernels/point_packet.h)."""

    def __init__(self, rt: Runtime, max_points_per_launch: int | None = None,
                 packet_size: int | None = None):
        self.rt = rt
        self.variant = rt.variant if packet_size is None else \
            rt.packet_variant(check_packet_size(packet_size))
        self.work_group_size = work_group_size(rt)
        self.max_points_per_launch = max(1, min(MAX_POINTS_PER_LAUNCH,
                                                int(max_points_per_launch or MAX_POINTS_PER_LAUNCH)))
        self.zero_copy = zero_copy(rt)
        # Intel's CPU runtime uses host memory in place only where it starts
        # on a page: results lent from the pool do, and big points are put
        # on one (results.on_page)
        self.on_pages = outputs_in_place(rt)
        # a closest_points's arrays, kept and made again, and the points' copy
        self._results = ResultPool(keep=2 * len(CLOSEST_FIELDS) + 2)
        self._buffers: dict[str, cl.Buffer] = {}
        self._overflow = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 4)
        self._no_slots = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY, 4)  # launches not indexed
        self._lock = threading.Lock()

    # -- public queries ---------------------------------------------------

    def closest_points(self, tree: Tree, points, max_distance=np.inf) -> ClosestPoints:
        """The nearest surface point of each point within max_distance, in
        the points' leading shape."""
        points, shape = inputs.points(points)
        max_distance = check_max_distance(max_distance)
        count = len(points)
        out = {name: self._results.empty((count, n) if n > 1 else count, dtype)
               for name, (dtype, n) in CLOSEST_FIELDS.items()}
        if count and self._usable(tree):
            framed = self.into_frame(points, shape, tree)
            max_d2 = squared_limit(max_distance * tree.scale)
            kernel, packet = self._kernel(tree, "closest_points")

            def launch(n, b, slots, indexed):
                return self.rt.run(kernel, -(-n // packet), *point_scene_args(tree), b["input"],
                                   slots, np.uint32(indexed), np.uint32(n), max_d2,
                                   b["distance"], b["geom_id"], b["prim_id"], b["instance_id"],
                                   b["u"], b["v"], b["normal"], b["points"], self._overflow,
                                   local_size=self.work_group_size)
            self._run(framed, launch, out)
            if tree.scale != 1.0:  # back from the frame: powers of two, exact
                out["distance"][:] = frame.to_frame(out["distance"], 1.0 / tree.scale)
                out["points"][:] = frame.to_frame(out["points"], 1.0 / tree.scale)
        elif count:
            out["distance"][:] = np.inf
            out["geom_id"][:] = out["prim_id"][:] = out["instance_id"][:] = -1
            out["u"][:] = out["v"][:] = out["normal"][:] = 0.0
            out["points"][:] = np.nan
        return ClosestPoints(**{name: array.reshape(shape + array.shape[1:])
                                for name, array in out.items()})

    def winding_numbers(self, tree: Tree, points) -> np.ndarray:
        """float32: the generalized winding number of each point, in the
        points' leading shape."""
        points, shape = inputs.points(points)
        out = {"winding": self._results.empty(len(points), np.float32)}
        if not (len(points) and self._usable(tree)):
            out["winding"][:] = 0.0
        else:
            framed = self.into_frame(points, shape, tree)
            dipoles = self._dipoles(tree)
            kernel, packet = self._kernel(tree, "winding_numbers")

            def launch(n, b, slots, indexed):
                return self.rt.run(kernel, -(-n // packet), *point_scene_args(tree), dipoles,
                                   b["input"], slots, np.uint32(indexed), np.uint32(n),
                                   b["winding"], self._overflow, local_size=self.work_group_size)
            self._run(framed, launch, out)
        return out["winding"].reshape(shape)

    def signed_distance(self, tree: Tree, points) -> np.ndarray:
        """float32: the distance to the surface, negative inside (|winding
        number| >= 0.5), in the points' leading shape."""
        points, shape = inputs.points(points)
        out = {name: self._results.empty(len(points), np.float32)
               for name in ("distance", "winding")}
        if not (len(points) and self._usable(tree)):
            out["distance"][:] = np.inf
        else:
            framed = self.into_frame(points, shape, tree)
            dipoles = self._dipoles(tree)
            kernel, packet = self._kernel(tree, "signed_distances")

            def launch(n, b, slots, indexed):
                return self.rt.run(kernel, -(-n // packet), *point_scene_args(tree), dipoles,
                                   b["input"], slots, np.uint32(indexed), np.uint32(n),
                                   b["distance"], b["winding"], self._overflow,
                                   local_size=self.work_group_size)
            self._run(framed, launch, out)
            if tree.scale != 1.0:
                out["distance"][:] = frame.to_frame(out["distance"], 1.0 / tree.scale)
        return out["distance"].reshape(shape)

    # -- internals ----------------------------------------------------------

    def _usable(self, tree: Tree) -> bool:
        """Validates the tree as ray queries do; False when it holds no triangle."""
        return check_tree(self.rt, tree)

    @staticmethod
    def into_frame(points: np.ndarray, shape: tuple, tree: Tree) -> np.ndarray:
        """The points in the tree's frame (hlbvh_cl.core.frame), each within
        POINT_RANGE there, else a ValueError naming the first that is not."""
        framed = frame.to_frame(points, tree.scale)
        if len(framed) and -POINT_RANGE <= framed.min() and framed.max() <= POINT_RANGE:
            return framed  # (two fast passes; the rows below only to name one)
        with np.errstate(invalid="ignore"):
            far = ~(np.abs(framed) <= POINT_RANGE).all(axis=1)
        if far.any():
            row = int(np.argmax(far))
            # the limit in the caller's units: a scaled frame's is POINT_RANGE there
            where = (f" in this scene (its frame is scaled by {frame.describe(tree.scale)}, "
                     f"hlbvh_cl/frame.py)" if tree.scale != 1.0 else "")
            raise ValueError(f"{inputs.row_name('points', row, shape)} = {inputs.shown(points[row])} "
                             f"is too far from the origin: point queries take coordinates up to "
                             f"{POINT_RANGE / tree.scale:.3g}{where}, where squared distances "
                             "stay finite in float32")
        return framed

    def _kernel(self, tree: Tree, name: str) -> tuple[cl.Kernel, int]:
        """The point kernel `name` for `tree` (an instanced one's walks its
        top tree, kernels/points.cl), and how many points each work-item
        takes: on a flat tree the walks go in packets of the variant (by
        default the runtime's, which its probe chose), on an instanced tree
        one point each."""
        packet = 1 if isinstance(tree, InstancedTree) else self.variant.packet_size
        defines = {"STACK_SIZE": stack_size(tree), "PACKET_SIZE": packet,
                   **self.variant.defines, **self.rt.prefetch_defines}
        if isinstance(tree, InstancedTree):
            defines["INSTANCES"] = 1
        return self.rt.kernel("query/points.cl", name, **defines), packet

    def _dipoles(self, tree) -> cl.Buffer:
        """The tree's dipoles (WideDipoles per node), made on the device on
        first use after a build or refit: one launch per level, bottom-up.
        An instanced scene's are its meshes' trees' (MeshTrees.dipoles, one
        buffer in the nodes' places, made once for every top tree over
        them)."""
        owner = tree.meshes if isinstance(tree, InstancedTree) else tree
        rt = self.rt
        # under the build lock from the check to the store: views of one scene
        # (hlbvh_cl.travel) share the tree, and a buffer taken during a build
        # would go back with its scratch
        with rt.build_lock:
            if owner.dipoles is None:
                dipoles = rt.pool.take(owner.node_count * layout.WIDE_DIPOLES.itemsize)
                kernel = rt.kernel("build/dipoles.cl", "dipoles_level")
                if isinstance(tree, InstancedTree):
                    parts = zip(owner.levels, owner.node_base, owner.triangle_base)
                else:
                    parts = [(tree.levels, 0, 0)]
                events = []
                for levels, node_base, triangle_base in parts:
                    for first, count in reversed(levels):
                        events.append(rt.run(kernel, count, first, count, np.int32(node_base),
                                             np.int32(triangle_base), owner.nodes,
                                             owner.triangles, dipoles,
                                             wait_for=events[-1:] or None))
                owner.dipoles = dipoles
            return owner.dipoles

    def _reserve(self, fields: dict[str, int]) -> None:
        count = self.max_points_per_launch
        wanted = {name: count * size for name, size in fields.items()}
        if all(name in self._buffers and self._buffers[name].size >= size
               for name, size in wanted.items()):
            return
        self._buffers = {}  # release the old ones before allocating
        self.rt.check_allocation("point query buffers", wanted)
        self._buffers = {name: cl.Buffer(self.rt.context, cl.mem_flags.READ_WRITE, size)
                         for name, size in wanted.items()}

    def _run(self, points: np.ndarray, launch, outputs: dict[str, np.ndarray]) -> None:
        """Runs ``launch(n, buffers, slots, indexed)`` over chunks of at most
        max_points_per_launch points (buffers["input"]: the points; slots
        and indexed: QUERY_POINTS in kernels/points.cl); the results land in
        the arrays of ``outputs``.  Raises if a walk ran out of stack.

        Big batches run in Morton order (order.device_order), fine enough
        for packets.  Where the kernels use the arrays themselves
        (_in_place), each launch takes a run of that order as its slots and
        reads and writes the whole arrays in place; elsewhere the points go
        up in that order, chunk by chunk, and the results are put back on
        the host."""
        order, in_place = None, False
        if len(points) >= COHERENT_MIN:
            # (outputs too small for the pool stay off a page: then no copy)
            if self.on_pages and starts_on_page(*outputs.values()) and \
                    self.rt.fits_one_buffer(points, *outputs.values()):
                points = on_page(self._results, points)
            in_place = self._in_place([points, *outputs.values()])
            order = device_order(self.rt, points, FINE_ORDER_BITS, in_place)
        with self._lock:
            try:
                if in_place:
                    self._run_indexed(points, order, launch, outputs)
                elif order is not None:
                    results = {name: np.empty_like(array) for name, array in outputs.items()}
                    self._run_chunks(take_rows(points, order), launch, results)
                    for name, array in outputs.items():
                        put_rows(array, order, results[name])
                else:
                    self._run_chunks(points, launch, outputs)
            except BaseException:
                self.rt.queue.finish()  # launches in flight may still write the arrays
                raise

    def _in_place(self, arrays: list[np.ndarray]) -> bool:
        """Whether the kernels use these whole arrays themselves
        (USE_HOST_PTR): on zero copy (PoCL), or where each starts on a page
        (self.on_pages); and only where the device allows a buffer of each."""
        if not self.rt.fits_one_buffer(*arrays):
            return False
        return self.zero_copy or (self.on_pages and starts_on_page(*arrays))

    def _wrap(self, array: np.ndarray, name: str) -> cl.Buffer:
        """The array's own memory as a buffer (in place): read-only for the
        points and slots, write-only for results."""
        flags = cl.mem_flags.READ_ONLY if name in ("input", "slots") else cl.mem_flags.WRITE_ONLY
        return cl.Buffer(self.rt.context, flags | cl.mem_flags.USE_HOST_PTR, hostbuf=array)

    def _run_indexed(self, points, order, launch, outputs) -> None:
        chunk, count = self.max_points_per_launch, len(points)
        buffers = {name: self._wrap(array, name)
                   for name, array in {"input": points, **outputs}.items()}
        cl.enqueue_copy(self.rt.queue, self._overflow, np.zeros(1, np.int32))
        held = []
        sizes, start = LaunchSizes(chunk, FIRST_LAUNCH), 0
        while start < count:
            stop = min(start + sizes.next(self.rt), count)
            held.append(self._wrap(order[start:stop], "slots"))
            sizes.launched(launch(stop - start, buffers, held[-1], 1), stop - start)
            start = stop
        held += [collect(self.rt.queue, buffers[name], array, True)
                 for name, array in outputs.items()]
        self._check_overflow()

    def _run_chunks(self, points, launch, outputs) -> None:
        queue, chunk, count = self.rt.queue, self.max_points_per_launch, len(points)
        arrays = {"input": points, **outputs}
        if not self.zero_copy:
            self._reserve({name: array.itemsize * (array.size // max(1, len(array)))
                           for name, array in arrays.items()})
        cl.enqueue_copy(queue, self._overflow, np.zeros(1, np.int32))
        transfers = []
        sizes, start = LaunchSizes(chunk, FIRST_LAUNCH), 0
        while start < count:
            part = slice(start, min(start + sizes.next(self.rt), count))
            start = part.stop
            if self.zero_copy:
                buffers = {name: self._wrap(array[part], name) for name, array in arrays.items()}
            else:
                buffers = self._buffers
                transfers.append(cl.enqueue_copy(queue, buffers["input"], points[part],
                                                 is_blocking=False))
            sizes.launched(launch(part.stop - part.start, buffers, self._no_slots, 0),
                           part.stop - part.start)
            transfers += [collect(queue, buffers[name], array[part], self.zero_copy)
                          for name, array in outputs.items()]
        self._check_overflow()

    def _check_overflow(self) -> None:
        """Waits for the launches; raises if a walk ran out of stack."""
        overflow = np.zeros(1, np.int32)
        self.rt.wait([cl.enqueue_copy(self.rt.queue, overflow, self._overflow,
                                      is_blocking=False)])
        if overflow[0]:
            raise RuntimeError("a point query's walk overflowed its stack (sized from "
                               "Tree.depth): the tree is deeper than its depth field says")
