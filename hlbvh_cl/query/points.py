"""Point queries on a finished Tree (kernels/query/points.cl): the closest surface
point, the generalized winding number, and from both the signed distance and
inside/outside.  Query points walk the wide tree with the same walk as the
rays (kernels/query/walk/walk.h), as another visitor: on a flat tree a packet of nearby
points per work-item (kernels/query/points/point_packet.h; big batches run in fine Morton
order so that a packet's points lie close together), on an instanced one a
point per work-item.

Conventions, shared with tests/support/point_oracle.py:
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

from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from ..core import frame
from ..core import inputs
from . import on_device
from .order import COHERENT_MIN, FINE_ORDER_BITS, device_order
from ..device.runtime import Runtime
from ..build.instances import InstancedTree
from .engine import (Batch, Engine, check_tree, engine_setting, kernel_defines,
                     work_group_size, refuse_spheres)
from .rays import check_packet_size
from .results import ResultPool, on_page, starts_on_page
from ..build.dipoles import dipoles as make_dipoles
from ..core.paths import kernel_of
from ..core.tree import Tree

KERNEL = kernel_of(__name__)

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
        """bool, of distance's shape: which points have a surface point
        within max_distance (a pyopencl array where the results are)."""
        found = self.geom_id >= 0
        return found if isinstance(found, np.ndarray) else found.view(bool)  # int8 0 or 1


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


def nothing_found(out: dict) -> None:
    """The results (numpy's or pyopencl's, by field) of points with no
    surface point: as ClosestPoints has them; a winding number of 0."""
    for name, value in {"distance": np.inf, "geom_id": -1, "prim_id": -1, "instance_id": -1,
                        "u": 0.0, "v": 0.0, "normal": 0.0, "points": np.nan,
                        "winding": 0.0}.items():
        if name in out:
            on_device.fill(out[name], value)


def point_scene_args(tree) -> tuple:
    """A point kernel's POINT_SCENE_PARAMS (kernels/query/points.cl): a flat tree's
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
    reused between calls, which only grow (or pinned staging buffers on
    request: hlbvh_cl.query.engine).  ``max_points_per_launch`` caps
    the points per kernel launch (bigger batches go in chunks).
    ``packet_size`` sets the points a work-item walks together on flat
    trees (query.PACKET_SIZES; by default the runtime's kernel variant's, as
    RayQuery's): every size gives the same closest points, and the same
    winding numbers up to rounding (the same terms, summed in another order:
    kernels/query/points/point_packet.h)."""

    def __init__(self, rt: Runtime, max_points_per_launch: int | None = None,
                 packet_size: int | None = None):
        self.rt = rt
        self.variant = rt.variant if packet_size is None else \
            rt.packet_variant(check_packet_size(packet_size))
        self.work_group_size = work_group_size(rt)
        most = max(1, min(MAX_POINTS_PER_LAUNCH,
                          int(max_points_per_launch or MAX_POINTS_PER_LAUNCH)))
        #: the launches (hlbvh_cl.query.engine)
        self.engine = Engine(rt, most)
        #: the host memory of results: a closest_points's arrays, kept and
        #: made again, and the points' copy on a page (results.ResultPool)
        self.results = ResultPool(keep=2 * len(CLOSEST_FIELDS) + 2)
        #: the device memory of results of points given on the device
        self._device_results: on_device.ResultArrays | None = None

    max_points_per_launch = engine_setting("most", "Points per kernel launch at most.")
    staging = engine_setting(
        "staging", "Off zero copy: whether points and results travel through pinned staging "
        "buffers (off by default: hlbvh_cl.query.engine.staging says why; settable).")

    # -- public queries ---------------------------------------------------

    def closest_points(self, tree: Tree, points, max_distance=np.inf) -> ClosestPoints:
        """The nearest surface point of each point within max_distance, in
        the points' leading shape (pyopencl arrays for points given as one:
        query/on_device.py)."""
        refuse_spheres(tree, "closest_points")
        max_distance = check_max_distance(max_distance)
        fields = {name: ((n,) if n > 1 else (), dtype)
                  for name, (dtype, n) in CLOSEST_FIELDS.items()}
        on_device_points = on_device.device_points(self.rt, points)
        if on_device_points is not None:
            return ClosestPoints(**self._on_device(
                tree, *on_device_points, fields, lambda t: self._closest(
                    t, squared_limit(max_distance)),
                lambda host: vars(self.closest_points(tree, host, max_distance)), "closest"))
        points, shape = inputs.points(points)
        count = len(points)
        out = {name: self.results.empty((count, n) if n > 1 else count, dtype)
               for name, (dtype, n) in CLOSEST_FIELDS.items()}
        if count and check_tree(self.rt, tree):
            framed = self._into_frame(points, shape, tree)
            self._run(framed, self._closest(tree, squared_limit(max_distance * tree.scale)), out,
                      "closest")
            if tree.scale != 1.0:  # back from the frame: powers of two, exact
                out["distance"][:] = frame.to_frame(out["distance"], 1.0 / tree.scale)
                out["points"][:] = frame.to_frame(out["points"], 1.0 / tree.scale)
        elif count:
            nothing_found(out)
        return ClosestPoints(**{name: array.reshape(shape + array.shape[1:])
                                for name, array in out.items()})

    def winding_numbers(self, tree: Tree, points) -> np.ndarray:
        """float32: the generalized winding number of each point, in the
        points' leading shape (as closest_points, on the device)."""
        refuse_spheres(tree, "winding_number")
        on_device_points = on_device.device_points(self.rt, points)
        if on_device_points is not None:
            return self._on_device(
                tree, *on_device_points, {"winding": ((), np.float32)}, self._winding,
                lambda host: {"winding": self.winding_numbers(tree, host)}, "winding")["winding"]
        points, shape = inputs.points(points)
        out = {"winding": self.results.empty(len(points), np.float32)}
        if not (len(points) and check_tree(self.rt, tree)):
            out["winding"][:] = 0.0
        else:
            self._run(self._into_frame(points, shape, tree), self._winding(tree), out, "winding")
        return out["winding"].reshape(shape)

    def signed_distance(self, tree: Tree, points) -> np.ndarray:
        """float32: the distance to the surface, negative inside (|winding
        number| >= 0.5), in the points' leading shape (as closest_points,
        on the device)."""
        refuse_spheres(tree, "signed_distance")
        on_device_points = on_device.device_points(self.rt, points)
        if on_device_points is not None:
            return self._on_device(
                tree, *on_device_points, {name: ((), np.float32) for name in ("distance",
                                                                             "winding")},
                self._signed, lambda host: {"distance": self.signed_distance(tree, host)},
                "signed")["distance"]
        points, shape = inputs.points(points)
        out = {name: self.results.empty(len(points), np.float32)
               for name in ("distance", "winding")}
        if not (len(points) and check_tree(self.rt, tree)):
            out["distance"][:] = np.inf
        else:
            self._run(self._into_frame(points, shape, tree), self._signed(tree), out, "signed")
            if tree.scale != 1.0:
                out["distance"][:] = frame.to_frame(out["distance"], 1.0 / tree.scale)
        return out["distance"].reshape(shape)

    # -- the launches (the engine's ``launch``): over the points [first,
    #    first + n) of the arrays (a global offset of whole packets) or
    #    over the launch's slots (QUERY_POINTS in kernels/query/points.cl)

    def _launch(self, tree, name: str, before: tuple, after: tuple, outputs: tuple):
        kernel, packet = self._kernel(tree, name)

        def launch(n, run):
            b = run.buffers
            return self.rt.run(kernel, -(-n // packet), *point_scene_args(tree), *before,
                               b["input"], run.slots, run.indexed, np.uint32(run.first + n),
                               *after, *(b[name] for name in outputs), self.engine.counters,
                               local_size=self.work_group_size, offset=run.first // packet)
        return launch

    def _closest(self, tree, max_d2: np.float32):
        return self._launch(tree, "closest_points", (), (max_d2,), tuple(CLOSEST_FIELDS))

    def _winding(self, tree):
        return self._launch(tree, "winding_numbers", (make_dipoles(self.rt, tree),), (),
                            ("winding",))

    def _signed(self, tree):
        return self._launch(tree, "signed_distances", (make_dipoles(self.rt, tree),), (),
                            ("distance", "winding"))

    def _on_device(self, tree, points, shape: tuple, fields: dict, launch_of, host_query,
                   key: str) -> dict:
        """A point query of points on the device: the results, by
        ``fields`` (name: (trailing shape, dtype)), as pyopencl arrays in
        the points' leading shape.  The points are checked there
        (query/on_device.py) and walked in the order given; a scene in a
        scaled frame takes them through ``host_query`` (the numpy query,
        whose results go back up); ``key`` paces the launches (Batch.key)."""
        if self._device_results is None:
            self._device_results = on_device.ResultArrays(self.rt.queue)
        pool, count = self._device_results, len(points)
        out = {name: pool.empty((count, *trailing), dtype)
               for name, (trailing, dtype) in fields.items()}
        if not (count and check_tree(self.rt, tree)):
            nothing_found(out)
        elif tree.scale != 1.0:
            host = host_query(points.get().reshape(*shape, 3))
            out = {name: pool.upload(host[name].reshape(count, *fields[name][0]))
                   for name in host}
        else:
            packet = self._kernel(tree, "closest_points")[1]
            counters = self.engine.run(Batch(
                count, {"input": points}, out, whole=True, slots=False, granule=packet,
                first=FIRST_LAUNCH, key=key,
                check=lambda buffers, steps: on_device.check_points(
                    self.rt, points, POINT_RANGE, self.engine.counters)), launch_of(tree))
            if counters[2]:  # named as the numpy query names it
                host = points.get().reshape(*shape, 3)
                self._into_frame(*inputs.points(host), tree)
                raise RuntimeError("hlbvh_cl internal error: check_points refused a point "
                                   "that the point queries take")
        # one tuple: pyopencl's reshape() of no arguments fails, and one point has shape ()
        return {name: array.reshape((*shape, *fields[name][0])) for name, array in out.items()}

    # -- internals ----------------------------------------------------------

    @staticmethod
    def _into_frame(points: np.ndarray, shape: tuple, tree: Tree) -> np.ndarray:
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
                     f"hlbvh_cl/core/frame.py)" if tree.scale != 1.0 else "")
            raise ValueError(f"{inputs.row_name('points', row, shape)} = {inputs.shown(points[row])} "
                             f"is too far from the origin: point queries take coordinates up to "
                             f"{POINT_RANGE / tree.scale:.3g}{where}, where squared distances "
                             "stay finite in float32")
        return framed

    def _kernel(self, tree: Tree, name: str) -> tuple[cl.Kernel, int]:
        """The point kernel `name` for `tree` (an instanced one's walks its
        top tree, kernels/query/points.cl), and how many points each
        work-item takes: on a flat tree the walks go in packets of the
        variant (by default the runtime's, which its probe chose), on an
        instanced tree one point each."""
        packet = 1 if isinstance(tree, InstancedTree) else self.variant.packet_size
        return self.rt.kernel(KERNEL, name, **kernel_defines(self.rt, tree, self.variant,
                                                              packet)), packet

    def _run(self, points: np.ndarray, launch, outputs: dict[str, np.ndarray], key: str) -> None:
        """Runs ``launch`` over the points (the engine's launches; the
        points are ``input``; slots and indexed: QUERY_POINTS in
        kernels/query/points.cl); the results land in the arrays of
        ``outputs``.

        Big batches run in Morton order (order.device_order), fine enough
        for packets.  Where the kernels can use the arrays themselves (zero
        copy on PoCL; on Intel's runtime where they start on a page), each
        launch takes a run of that order as its slots over the whole arrays
        in place; elsewhere the points of a run go up in that order and its
        results are put back."""
        engine = self.engine
        order, whole = None, False
        if len(points) >= COHERENT_MIN:
            # (outputs too small for the pool stay off a page: then no copy)
            if engine.outputs_in_place and starts_on_page(*outputs.values()) and \
                    self.rt.fits_one_buffer(points, *outputs.values()):
                points = on_page(self.results, points)
            arrays = [points, *outputs.values()]
            whole = self.rt.fits_one_buffer(*arrays) and (
                engine.zero_copy or (engine.outputs_in_place and starts_on_page(*arrays)))
            order = device_order(self.rt, points, FINE_ORDER_BITS, whole)
        engine.run(Batch(len(points), {"input": points}, outputs, order=order, whole=whole,
                         first=FIRST_LAUNCH, key=key), launch)
