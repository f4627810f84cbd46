"""The camera: a pinhole camera's parameters (Camera), its record on the
device (layout.PINHOLE_CAMERA), and the stage that makes its primary rays
there (kernels/render/camera.cl).

Convention (scene files share it, hlbvh_cl.io.scenefile): forward =
unit(target - eye), right = unit(forward x up), true_up = right x forward.
Pixel (x, y), y counting down from the top row, is sampled at (x + jx,
y + jy): the centre (0.5, 0.5) with one sample per pixel; with more, sample
s takes jx = random_unit(pixel, s, 0), jy = random_unit(pixel, s, 1)
(kernels/render: the PCG hash of Jarzynski & Olano 2020), so renders are
deterministic.
"""
from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from ..core import inputs, layout
from ..core.paths import kernel_of
from ..device.runtime import Runtime

KERNEL = kernel_of(__name__)

#: Image sides beyond this are taken for mistakes.
MAX_IMAGE_SIDE = 16384


def unit(vector: np.ndarray) -> np.ndarray | None:
    """A finite float64 vector's direction, scaled to its largest component
    first so that the length neither overflows (1e300) nor underflows; None
    for the zero vector."""
    largest = np.abs(vector).max()
    if not largest > 0:
        return None
    vector = vector / largest
    return vector / np.linalg.norm(vector)


def view_problem(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> tuple[str, str] | None:
    """What stops a camera at finite ``eye`` looking at ``target`` with ``up``
    from making rays, as (field, what is wrong); None when nothing does.
    Camera and scene files (hlbvh_cl.io.scenefile) both ask."""
    largest = float(np.finfo(np.float32).max)
    for name, point in (("eye", eye), ("target", target)):
        if np.abs(point).max() > largest:
            return name, f"{point.tolist()} does not fit float32, as the rays must"
    forward = unit(target - eye)
    if forward is None:
        return "target", f"{target.tolist()} equals eye: the camera looks nowhere"
    up_unit = unit(up)
    if up_unit is None or not np.linalg.norm(np.cross(forward, up_unit)) > 1e-6:
        return "up", f"{up.tolist()} is zero or parallel to the view direction target - eye"
    return None


#: Mitsuba 3's fov_axis values: the image axis along which a sensor's field
#: of view holds, whatever the image's size.
FOV_AXES = ("x", "y", "diagonal", "smaller", "larger")


def vertical_fov_deg(fov_deg: float, axis: str, aspect: float) -> float:
    """Camera's vertical field of view for an image of ``aspect`` = width /
    height whose field of view along ``axis`` (FOV_AXES) is ``fov_deg``."""
    half = math.tan(math.radians(fov_deg) / 2)
    vertical = {"x": half / aspect, "y": half,
                "diagonal": half / math.hypot(aspect, 1.0),
                "smaller": half if aspect >= 1 else half / aspect,
                "larger": half / aspect if aspect >= 1 else half}[axis]
    return math.degrees(2 * math.atan(vertical))


@dataclass(frozen=True)
class Camera:
    """A pinhole camera looking from ``eye`` at ``target``; ``fov_deg`` is the
    vertical field of view (the module's convention).  A render's camera
    rays see only what lies between the planes ``near_clip`` and
    ``far_clip`` away from the eye along the view direction, as Mitsuba 3's
    perspective sensor's clip planes (its defaults are 0.01 and 10000; here
    nothing is cut unless asked).  Camera.rays leaves the limits to the
    query's tmin and tmax."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_deg: float = 45.0  # a scene file's default too (hlbvh_cl.io.scenefile)
    near_clip: float = 0.0
    far_clip: float = math.inf

    def __post_init__(self):
        eye, target, up = (inputs.vector3(name, getattr(self, name))
                           for name in ("eye", "target", "up"))
        fov = inputs.number("fov_deg", self.fov_deg, 0.0, 180.0, low_open=True, high_open=True)
        problem = view_problem(eye, target, up)
        if problem is not None:
            raise ValueError(" ".join(problem))
        near = inputs.number("near_clip", self.near_clip, 0.0)
        far = self.far_clip
        unbounded = (isinstance(far, inputs.REAL) and not isinstance(far, bool)
                     and float(far) == math.inf)
        far = math.inf if unbounded else inputs.number("far_clip", far, near, low_open=True)
        for name, value in (("eye", eye), ("target", target), ("up", up)):
            object.__setattr__(self, name, tuple(float(x) for x in value))
        object.__setattr__(self, "fov_deg", fov)
        object.__setattr__(self, "near_clip", near)
        object.__setattr__(self, "far_clip", far)

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """forward, right, true_up: unit vectors (float64)."""
        forward = unit(np.subtract(self.target, self.eye))
        right = unit(np.cross(forward, unit(np.asarray(self.up, np.float64))))
        return forward, right, np.cross(right, forward)

    def pinhole(self, width: int, height: int) -> np.ndarray:
        """The PinholeCamera record (layout.PINHOLE_CAMERA) of a width x height image."""
        forward, right, true_up = self.basis()
        half_height = math.tan(math.radians(self.fov_deg) / 2)
        record = np.zeros((), layout.PINHOLE_CAMERA)
        record["eye"] = self.eye
        record["forward"] = forward
        record["right"] = right * half_height * (width / height)
        record["up"] = true_up * half_height
        return record

    def rays(self, width: int, height: int, scene=None):
        """The primary rays of a width x height image, as a render with spp=1
        traces them: float32 (H*W, 3) origins and directions through the pixel
        centres, row-major from the top-left pixel, in camera.cl's float32
        arithmetic.  With a ``scene``, they are made on its device and
        returned as pyopencl arrays on scene.queue, which its ray queries
        take as they are (nothing crosses to the host; OpenCL may round the
        pixel's division differently from numpy, by an ulp)."""
        width = inputs.integer("width", width, 1, MAX_IMAGE_SIDE)
        height = inputs.integer("height", height, 1, MAX_IMAGE_SIDE)
        record = self.pinhole(width, height)
        if scene is not None:
            from ..scene import Scene  # (scene.py imports the renderer's modules)
            if not isinstance(scene, Scene):
                raise TypeError(f"scene must be a hlbvh_cl.Scene, whose device makes the rays, "
                                f"or None (numpy rays), got {type(scene).__name__}")
            return _device_rays(scene, record, width, height)
        f32 = np.float32
        ys, xs = np.mgrid[0:height, 0:width].astype(f32)
        sx = (f32(2) * (xs + f32(0.5)) / f32(width) - f32(1)).reshape(-1, 1)
        sy = (f32(1) - f32(2) * (ys + f32(0.5)) / f32(height)).reshape(-1, 1)
        directions = record["forward"] + sx * record["right"] + sy * record["up"]
        origins = np.broadcast_to(record["eye"], directions.shape).copy()
        return origins, np.ascontiguousarray(directions, f32)


def _device_rays(scene, record: np.ndarray, width: int, height: int):
    """Camera.rays made by camera.cl's camera_rays on the scene's device."""
    with scene.borrow() as built:
        rt = built.runtime
        origins, directions = (cla.empty(rt.queue, (width * height, 3), np.float32)
                               for _ in range(2))
        rt.run(rt.kernel(KERNEL, "camera_rays", FILTER_INTERVALS=FILTER_INTERVALS),
               width * height, record, np.uint32(width), np.uint32(height), origins.data,
               directions.data)
    return origins, directions


#: The reconstruction filters a render takes, by Mitsuba's names, and the
#: camera kernel's jitter for each (kernels/render/camera.cl).
FILTERS = {"box": 1, "gaussian": 2}

#: Mitsuba's Gaussian filter: f(t) = g(t) - g(r) on [-r, r], g(t) =
#: exp(-t^2 / (2 sigma^2)), sigma 0.5 pixel, r = 4 sigma.
GAUSSIAN_SIGMA, GAUSSIAN_RADIUS = 0.5, 2.0

#: Equal-probability intervals of the filter's inverse CDF table.
FILTER_INTERVALS = 1024


def gaussian_filter_table(intervals: int = FILTER_INTERVALS) -> np.ndarray:
    """float32 (intervals + 1,): offsets t_i with F(t_i) = i / intervals,
    F the Gaussian filter's CDF, in float64 (its integral in closed form,
    inverted by bisection).  The camera kernel draws an offset by
    interpolating between them, which samples the filter to within one
    interval's width (filter importance sampling, pbrt-v4 sec. 8.8)."""
    sigma, r = GAUSSIAN_SIGMA, GAUSSIAN_RADIUS
    erf = np.vectorize(math.erf)
    floor = math.exp(-r * r / (2 * sigma * sigma))

    def integral(x):  # of f from -r to x
        scale = sigma * math.sqrt(math.pi / 2)
        return scale * (erf(x / (sigma * math.sqrt(2))) + math.erf(r / (sigma * math.sqrt(2)))) \
            - floor * (x + r)
    targets = np.arange(intervals + 1) / intervals * integral(np.float64(r))
    lo, hi = np.full(intervals + 1, -r), np.full(intervals + 1, r)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        below = integral(mid) < targets
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    table = 0.5 * (lo + hi)
    table[0], table[-1] = -r, r
    return table.astype(np.float32)


#: Equal intervals of |t| in [0, GAUSSIAN_RADIUS] of the filter's weight table.
WEIGHT_INTERVALS = 256

#: Pixels on each side of its own whose centres a splatted sample can reach:
#: a sample lies in [x, x + 1), so within the radius of centres x + 0.5 + d
#: for |d| < radius + 0.5.
SPLAT_REACH = math.ceil(GAUSSIAN_RADIUS + 0.5) - 1


def gaussian_weight_table(intervals: int = WEIGHT_INTERVALS) -> np.ndarray:
    """float32 (intervals + 1,): the filter's value f(t) at t_i = i r /
    intervals, from float64; film.cl interpolates between them (linear
    interpolation's error is below |f''| h^2 / 8 <= h^2 / (8 sigma^2))."""
    t = np.arange(intervals + 1) * (GAUSSIAN_RADIUS / intervals)
    g = lambda x: np.exp(-x * x / (2 * GAUSSIAN_SIGMA ** 2))  # noqa: E731
    return np.maximum(g(t) - g(GAUSSIAN_RADIUS), 0.0).astype(np.float32)


def filter_table(rt: Runtime, kind: str = "offsets") -> cl.Buffer:
    """A table of the Gaussian filter on ``rt``'s device, made once per
    runtime: its inverse CDF ("offsets": gaussian_filter_table, for the
    camera) or its values ("weights": gaussian_weight_table, for the film)."""
    tables = _FILTER_TABLES.setdefault(rt, {})
    if kind not in tables:
        values = gaussian_filter_table() if kind == "offsets" else gaussian_weight_table()
        tables[kind] = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                                 hostbuf=values)
    return tables[kind]


_FILTER_TABLES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def enqueue_primary_rays(rt: Runtime, camera: Camera, pinhole: np.ndarray, width: int,
                         height: int, band, sample: int, jitter: int,
                         rays: cl.Buffer) -> cl.Event:
    """One Ray per pixel of ``band`` (the rows of a pass, renderer.Band) into
    ``rays``, in the band's tile order, between ``camera``'s clip planes
    (``pinhole``, its record, has a unit forward, so t is the distance along
    it); ``jitter`` 0 through the pixels' centres, else a FILTERS value."""
    kernel = rt.kernel(KERNEL, "primary_rays", FILTER_INTERVALS=FILTER_INTERVALS)
    return rt.run(kernel, band.tile_range, pinhole,
                  np.uint32(width), np.uint32(height), band.first_row, band.rows,
                  np.uint32(sample), np.int32(jitter), np.float32(camera.near_clip),
                  np.float32(camera.far_clip), filter_table(rt), rays)
