"""Rays and points that are already on the device: pyopencl arrays given to
a ray or point query, whose results then stay on the device too (issue 57; Warp's and Open3D's
queries take and give device arrays the same way).

What is taken: ``origins`` and ``directions``, both pyopencl arrays of
float32 of the same shape (..., 3), on the scene's context (Scene.queue
makes them), or Open3D's packed (..., 6) rays as one such array in
``origins`` (unpacked on the device); ``tmin`` and ``tmax`` as numbers or
float32 pyopencl arrays of the rays' leading shape; ``mask`` as one
integer, None, or a uint32 pyopencl array of the rays' leading shape (one
per ray, Embree's rule as on the numpy path).  Anything else is refused by
name.  The rays are checked on the device
(kernels/query/on_device.cl) as core/inputs.py checks numpy rays, in the
same queue as the query's own kernel, so that the call still waits once; a
ray that fails is then named as inputs.rays names it, from a copy of the
arrays (the error's path, not the call's).

Points for the point queries come the same way, as one float32 pyopencl
array (..., 3), checked on the device (finite, and within the range the
point queries take), and walked in the order given (numpy points are
walked in Morton order where a batch is big: a caller on the device orders
them).

Results are pyopencl arrays on Scene.queue, in the inputs' leading shape.
count_intersections counts on the device; intersect_all's hits, whose
number only its count pass finds, are sized there too (query/all_hits.py):
the count pass, then a scan of each ray's kept hits into its segment's
offset and one read of their total, then the fill pass; the rays are
walked in the order given (numpy rays of a big batch are counted in Morton
order).
Where the scene's tree is built in a scaled frame (hlbvh_cl.core.frame), or
where a ray's hit could lie past float32's range, the rays are traced from
the host instead (query/rays.py's into_frame scales them there) and the
results copied back up: same answers, a slower call.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import pyopencl.tools  # noqa: F401  (cl.tools: the memory pool)

from ..core import frame
from ..core import inputs
from ..core.paths import kernel_of
from ..device.runtime import Runtime
from ..parallel import scan

KERNEL = kernel_of(__name__)

#: float32's largest t the box and triangle tests take without overflow
#: (query/rays.py's _SAFE_T, as a float32).
SAFE_T = np.float32(np.finfo(np.float32).max / 4)


def is_device_array(value) -> bool:
    """Whether ``value`` is a pyopencl array."""
    return isinstance(value, cla.Array)


@dataclass
class DeviceRays:
    """Rays on the device, their shapes checked: (R, 3) float32 arrays
    without offset, limits as float32 0-d numpy values or (R,) pyopencl
    arrays, the mask as uint32 0-d or an (R,) pyopencl array, and the
    leading shape of the results; ``packed``: the caller's (R, 6) rays,
    where they came so (the error path names their rows)."""

    origins: cla.Array
    directions: cla.Array
    tmin: object
    tmax: object
    mask: object
    shape: tuple
    packed: cla.Array | None = None

    def __len__(self) -> int:
        return len(self.origins)

    def host(self) -> tuple:
        """origins, directions, tmin and tmax copied to the host in the
        caller's shapes (packed rays as one (..., 6) array, directions
        None), as the numpy queries take them (the fallback's and the error
        path's)."""
        rays = (self.packed.get().reshape(*self.shape, 6), None) if self.packed is not None \
            else (self.origins.get().reshape(*self.shape, 3),
                  self.directions.get().reshape(*self.shape, 3))
        return (*rays, *(limit if isinstance(limit, np.ndarray) else
                         limit.get().reshape(self.shape) for limit in (self.tmin, self.tmax)))

    def host_mask(self) -> np.ndarray:
        """The masks as the numpy queries take them (the fallback's)."""
        return self.mask if isinstance(self.mask, np.ndarray) else \
            self.mask.get().reshape(self.shape)


def device_rays(rt: Runtime, origins, directions, tmin, tmax, mask,
                pool: "ResultArrays") -> DeviceRays | None:
    """The rays as DeviceRays when any of them is a pyopencl array, else
    None (numpy rays: core/inputs.py's).  Shapes, types and the context are
    checked here; values on the device (check_rays).  Packed rays are
    unpacked into arrays from ``pool``."""
    given = {"origins": origins, "directions": directions, "tmin": tmin, "tmax": tmax,
             "mask": mask}
    if not any(is_device_array(value) for value in given.values()):
        return None
    packed = directions is None and is_device_array(origins) and origins.ndim >= 1 \
        and origins.shape[-1] == 6
    if directions is None and is_device_array(origins) and not packed \
            and (origins.ndim < 1 or origins.shape[-1] != 3):
        raise ValueError(f"rays must have shape (..., 6): origin then direction, got "
                         f"{origins.shape} (or give origins and directions as two pyopencl "
                         "arrays of shape (..., 3))")
    for name in ("origins",) if packed else ("origins", "directions"):
        if not is_device_array(given[name]):
            raise TypeError(f"{name} is {'missing' if given[name] is None else 'not a pyopencl array'}"
                            " while another ray input is one: give origins and directions as "
                            "two pyopencl arrays of shape (..., 3) (or packed rays (..., 6) as "
                            "one), or all inputs as numpy arrays")
    for name, one, per_ray in (("tmin", "number", "float32"), ("tmax", "number", "float32"),
                               ("mask", "integer", "uint32")):
        if not is_device_array(given[name]) and np.ndim(given[name]):
            raise TypeError(f"{name} is a host array while the rays are pyopencl arrays: give "
                            f"one {one}, or one per ray as a {per_ray} pyopencl array")
    for name, value in given.items():
        if is_device_array(value) and value.context != rt.context:
            raise ValueError(f"{name} is a pyopencl array of another OpenCL context than this "
                             f"scene's ({rt.device.id}): make it with scene.queue")
    origins, directions, tmin, tmax, mask = (_on_queue(rt, value) if is_device_array(value)
                                             else value for value in given.values())
    shape = origins.shape[:-1]
    if packed:
        _check_array("rays", origins, np.float32)
    for name, value in () if packed else (("origins", origins), ("directions", directions)):
        _check_array(name, value, np.float32)
        if value.ndim < 1 or value.shape[-1] != 3:
            raise ValueError(f"{name} must have shape (..., 3), got {value.shape}")
        if value.shape[:-1] != shape:
            raise ValueError(f"{name} must have the shape of origins {origins.shape}, got "
                             f"{value.shape}")
    count = math.prod(shape)
    if count > inputs.MAX_BATCH:
        raise ValueError(f"{count} rays in one call: at most {inputs.MAX_BATCH}")
    limits = {}
    for name, value in (("tmin", tmin), ("tmax", tmax)):
        if is_device_array(value):
            _check_array(name, value, np.float32)
            if value.shape != shape:
                raise ValueError(f"{name} must have the rays' leading shape {shape}, "
                                 f"got {value.shape}")
            limits[name] = _flat(value, count)
        else:
            limits[name] = inputs.limits(name, value, ())
    if not is_device_array(tmin):  # one tmin for all is checked here, as inputs.rays does
        inputs.check_limits(limits["tmin"], limits["tmax"] if not is_device_array(tmax)
                            else np.float64(np.inf), ())
    # float32, rounded inward as inputs.rays rounds them
    scalars = inputs.inward(*(limits[name] if not is_device_array(limits[name])
                              else np.float64(0.0) for name in ("tmin", "tmax")))
    for name, value in zip(("tmin", "tmax"), scalars):
        if not is_device_array(limits[name]):
            limits[name] = value.reshape(())
    if is_device_array(mask):
        _check_array("mask", mask, np.uint32)
        if mask.shape != shape:
            raise ValueError(f"mask must have the rays' leading shape {shape}, got {mask.shape}")
        masks = _flat(mask, count)
    else:
        masks = (np.array(inputs.ALL_BITS, np.uint32) if mask is None else
                 inputs.ray_masks(mask, ())).reshape(())
    if packed:
        rows = _flat(origins, count, 6)
        o, d = pool.empty((count, 3), np.float32), pool.empty((count, 3), np.float32)
        if count:
            rt.run(rt.kernel(KERNEL, "unpack_rays"), count, rows.data, o.data, d.data,
                   np.uint32(count))
        return DeviceRays(o, d, limits["tmin"], limits["tmax"], masks, shape, rows)
    return DeviceRays(_flat(origins, count, 3), _flat(directions, count, 3), limits["tmin"],
                      limits["tmax"], masks, shape)


def device_points(rt: Runtime, points) -> tuple[cla.Array, tuple] | None:
    """Points given as a pyopencl array: (N, 3) float32 rows without
    offset, and their leading shape; None for any other points (numpy's,
    core/inputs.py)."""
    if not is_device_array(points):
        return None
    if points.context != rt.context:
        raise ValueError("points is a pyopencl array of another OpenCL context than this "
                         f"scene's ({rt.device.id}): make it with scene.queue")
    points = _on_queue(rt, points)
    _check_array("points", points, np.float32)
    if points.ndim < 1 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., 3), got {points.shape}")
    shape = points.shape[:-1]
    count = math.prod(shape)
    if count > inputs.MAX_BATCH:
        raise ValueError(f"{count} points in one call: at most {inputs.MAX_BATCH}")
    return _flat(points, count, 3), shape


def _on_queue(rt: Runtime, value: cla.Array) -> cla.Array:
    """``value`` on the scene's queue, where what reads it goes after what
    still writes it: the events it records (Array.events, as pyopencl's own
    operations wait for them), and the commands already on its own queue
    where that is another (a marker there).  Rays of another queue, or with
    their upload pending, were traced before their data arrived, a silent
    wrong answer; an array of no queue failed in pyopencl's copy of an
    offset view (a bare AssertionError)."""
    waits = list(value.events)
    if value.queue is not None and value.queue != rt.queue:
        waits.append(cl.enqueue_marker(value.queue))
    if waits:  # the queue is in order: what is enqueued after the marker waits for it
        cl.enqueue_marker(rt.queue, wait_for=waits)
    return value if value.queue == rt.queue else value.with_queue(rt.queue)


def _check_array(name: str, value: cla.Array, dtype) -> None:
    if value.dtype != dtype:
        what = {"mask": "masks", "points": "points", "tmin": "limits",
                "tmax": "limits"}.get(name, "rays")
        raise TypeError(f"{name} is a pyopencl array of {value.dtype}; {what} on the device must "
                        f"be {np.dtype(dtype).name} ({name}.astype(np.{np.dtype(dtype).name}))")
    if not value.flags.c_contiguous:
        raise ValueError(f"{name} is a pyopencl array that is not C-contiguous; give a "
                         "contiguous one (e.g. its .copy())")


def _flat(value: cla.Array, count: int, width: int = 0) -> cla.Array:
    """``value`` as (count, width) rows (or (count,)) over a buffer of its
    own from offset 0, which is what a kernel argument can take: a view at
    an offset is copied on the device."""
    if value.offset:
        value = value.copy()
    return value.reshape((count, width) if width else (count,))


def walk_limits(rays: DeviceRays, flat: bool, pool: "ResultArrays") -> dict:
    """The stepped values (engine.Batch.stepped) of the walks of the rays:
    tmin, tmax and mask as given, but on a flat scene, whose kernels take no
    mask (query/rays.py's masked), a ray of mask 0 walks with tmax -inf:
    one mask 0 for all here, per-ray masks by check_rays, which then writes
    each ray's walked tmax into an array from ``pool``; the caller's tmax
    is then ``given_tmax`` (what check_rays checks)."""
    stepped = {"tmin": rays.tmin, "tmax": rays.tmax, "mask": rays.mask}
    if flat and is_device_array(rays.mask):
        stepped.update(given_tmax=rays.tmax, tmax=pool.empty(len(rays), np.float32))
    elif flat and rays.mask == 0:
        stepped.update(given_tmax=rays.tmax, tmax=np.array(-np.inf, np.float32))
    return stepped


def checker(rt: Runtime, rays: DeviceRays, counters: cl.Buffer):
    """The engine's Batch.check for the rays (check_rays), over the steps
    of walk_limits's values."""
    def check(buffers, steps):
        check_rays(rt, rays, steps, counters)
    return check


def check_rays(rt: Runtime, rays: DeviceRays, steps: dict, counters: cl.Buffer) -> None:
    """Enqueues check_rays over the rays (the buffers and steps of the
    engine's launch of walk_limits's values), setting counters[2] and [3],
    and each ray's walked tmax where walk_limits asks for it."""
    kernel = rt.kernel(KERNEL, "check_rays")
    walked, _ = steps["tmax"]
    rt.run(kernel, len(rays), rays.origins.data, rays.directions.data, *steps["tmin"],
           *steps.get("given_tmax", steps["tmax"]), *steps["mask"], walked,
           np.uint32(is_device_array(rays.mask) and "given_tmax" in steps),
           np.float32(frame.SAFE_RANGE[1]), SAFE_T, counters, np.uint32(len(rays)))


def check_points(rt: Runtime, points: cla.Array, limit: float, counters: cl.Buffer) -> None:
    """Enqueues check_points over (N, 3) points, setting counters[2] where
    one is not finite or lies beyond ``limit`` in a coordinate."""
    kernel = rt.kernel(KERNEL, "check_points")
    rt.run(kernel, len(points), points.data, np.float32(limit), counters,
           np.uint32(len(points)))


def hit_offsets(rt: Runtime, counts: cla.Array, limit: np.uint32, scanned: cl.Buffer,
                offsets: cla.Array, counters: cl.Buffer) -> None:
    """Enqueues intersect_all's segments for the int32 ``counts`` of rays on
    the device: ``offsets`` (int64 (R + 1,)) the exclusive prefix sum of
    min(counts, limit), through ``scanned`` (uint32, R + 1: the project's
    scan is uint32), with counters[1] set where that sum wraps
    (kernels/query/on_device.cl)."""
    count = len(counts)
    rt.run(rt.kernel(KERNEL, "kept_hits"), count, counts.data, limit, scanned, np.uint32(count))
    scan.exclusive_scan(rt, scanned, count)
    rt.run(rt.kernel(KERNEL, "hit_offsets"), count + 1, scanned, counts.data, limit,
           offsets.data, counters, np.uint32(count))


def raise_for_bad_ray(rays: DeviceRays) -> None:
    """The ValueError core/inputs.py raises for the first ray that
    check_rays refused, read from a copy of the rays."""
    inputs.rays(*rays.host())
    raise RuntimeError("hlbvh_cl internal error: check_rays refused a ray that inputs.rays "
                       "takes")


def fill(array, value) -> None:
    """Every element of a result array, numpy's or pyopencl's (contiguous),
    set to ``value``.  On the device by clEnqueueFillBuffer rather than
    pyopencl's Array.fill, whose kernel is built at its first use (and
    NVIDIA's compiler log then reaches the user as a CompilerWarning)."""
    if isinstance(array, np.ndarray):
        array[...] = value
    elif array.size:  # the array's event, as Array.fill leaves it: its reads wait for it
        array.add_event(cl.enqueue_fill_buffer(array.queue, array.base_data,
                                               np.array(value, array.dtype), array.offset,
                                               array.nbytes))


class ResultArrays:
    """Result arrays on the device, from a pyopencl memory pool: the buffers
    of results the caller has dropped are handed out again instead of being
    allocated afresh (issue 57: results come from a pool)."""

    def __init__(self, queue: cl.CommandQueue):
        self.queue = queue
        self.pool = cl.tools.MemoryPool(cl.tools.ImmediateAllocator(queue))

    def empty(self, shape, dtype) -> cla.Array:
        return cla.empty(self.queue, shape, dtype, allocator=self.pool)

    def upload(self, array: np.ndarray) -> cla.Array:
        return cla.to_device(self.queue, np.ascontiguousarray(array), allocator=self.pool)
