"""Rendering a Scene: pinhole camera, closest hits, shading, shadows / AO.

Every per-pixel step runs on the device, in passes over whole rows of at
most PIXELS_PER_PASS pixels, and the host reads back one 8-bit image.  Per
sample of each pixel:

    camera.cl   primary_rays       one Ray per pixel
    traverse.cl intersect_closest  -> Hit
    shade.cl    shade_hits         colour without further rays; shadow ray
    traverse.cl intersect_any      (diffuse with shadows, and once per AO ray)
    shade.cl    add_unoccluded     adds the light a free shadow / AO ray lets through
    shade.cl    encode_image       (once, after the last sample) -> uint8 RGB

Definitions (tests/test_render.py rebuilds images from them with the
brute-force oracle):

- Random numbers: random_unit(pixel, s, k) = (h >> 8) / 2^24 with
  h = pcg(pixel + pcg(s + pcg(k))) in uint32 arithmetic, pcg the PCG hash of
  Jarzynski & Olano 2020 (kernels/hlbvh.h), pixel = y * width + x and s the
  sample: renders are deterministic.
- Rays: scenefile.py's camera convention.  Pixel (x, y), y counting down
  from the top row, is sampled at (x + jx, y + jy): the centre (0.5, 0.5)
  when spp = 1; with spp > 1, sample s takes jx = random_unit(pixel, s, 0),
  jy = random_unit(pixel, s, 1).  A pixel's colour is the mean of its samples.
- n is the unit geometric normal of the hit triangle, cross(v1 - v0, v2 - v0),
  turned to face the ray (n.d < 0); a is the mesh's colour, Renderer.colors[geom_id].
- "diffuse" (Lambert): a * (ambient + intensity * max(n.l, 0) * V), with
  Renderer.light = (l, intensity, ambient).  V = 0 when the shadow ray from
  p + offset * n along l hits anything (t in [0, inf)), else 1; V = 1 when
  shadows=False.  p = origin + t * direction, offset = max(1e-4 * D,
  2^-16 * M), D the diagonal of the scene's bounding box and M its largest
  absolute coordinate.  (That box is the tree's root box: for an instanced
  scene, the box around its instances' world boxes, which can be looser than
  the geometry, so its depth and ao images differ a little from those of the
  same geometry placed flat.  Limits of float32: p's error grows with the
  distance from the eye, so a camera about 1e6 times an object's size away
  from it shows shadow acne there; and an object about 1e4 times its size
  from the origin loses its shadow to the 2^-16 * M offset.)  A miss shows
  the sky:
  mix(SKY_HORIZON, SKY_ZENITH, clamp(unit(d) . unit(camera.up), 0, 1)).
- "normals": (n + 1) / 2; black on a miss.
- "depth": (far - |t * d|) / (far - near) clamped to [0, 1], where near and
  far are the smallest and largest distances from the eye to the scene's
  bounding box (near = 0 inside it); black on a miss.
- "ao" (ambient occlusion): a * (fraction of the ao_samples rays from
  p + offset * n that hit nothing with t in [0, ao_distance]); ao_distance
  defaults to AO_DISTANCE_SCALE * D.  Ray k of sample s is cosine-distributed
  about n (Malley's method): with u1 = random_unit(pixel, s, 2 + 2k) and
  u2 = random_unit(pixel, s, 3 + 2k), its direction is
  sqrt(u1) (cos(2 pi u2) b1 + sin(2 pi u2) b2) + sqrt(1 - u1) n, (b1, b2) the
  basis around n of Duff et al. 2017 (kernels/shade.cl).  A miss shows the sky.
- Encoding: channel = round(255 * c') with c' = sqrt(clamp(c, 0, 1)) for
  "diffuse" and "ao" (radiance; display gamma 2) and c' = clamp(c, 0, 1) for
  "normals" and "depth" (data).
"""
from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Sequence
import dataclasses
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from ..core import frame
from ..core import layout
from ..core.inputs import as_array
from ..device.runtime import Runtime, event_ms
from ..query.rays import RayQuery
from ..scene import Scene
from ..core.tree import Tree

SHADINGS = ("diffuse", "normals", "depth", "ao")

#: Image sides and samples beyond these are taken for mistakes.
MAX_IMAGE_SIDE = 16384
MAX_SPP = 1 << 16
MAX_AO_SAMPLES = 1024

#: Linear RGB of the background at and below the horizon, and straight up.
SKY_HORIZON = (0.86, 0.89, 0.93)
SKY_ZENITH = (0.42, 0.58, 0.82)

#: Secondary rays start max(RAY_OFFSET_SCALE * D, RAY_OFFSET_ULPS * M) off
#: the surface (D: the scene box's diagonal, M: its largest coordinate).
RAY_OFFSET_SCALE = 1e-4
RAY_OFFSET_ULPS = 2.0 ** -16

#: Default AO reach, as a fraction of the scene box's diagonal.
AO_DISTANCE_SCALE = 0.05

#: Default number of AO rays per pixel and sample.
AO_SAMPLES = 16

#: Pixels per pass at most (whole rows): enough work-items for any device,
#: and buffers (133 bytes a pixel) small enough to stay warm between passes
#: rather than touching fresh memory.  128K rather than more: a pass's rays
#: then cover a narrower band of the image, so fewer of a large tree's nodes
#: compete for the cache (measured faster on large scenes).
PIXELS_PER_PASS = 1 << 17

#: Colours of meshes 0, 1, 2, ... of a Scene that was given none (cycled).
PALETTE = ((0.85, 0.6, 0.5), (0.55, 0.7, 0.85), (0.9, 0.85, 0.7), (0.6, 0.8, 0.55),
           (0.8, 0.6, 0.8), (0.75, 0.75, 0.72))



def default_colors(count: int) -> list[tuple[float, float, float]]:
    return [PALETTE[i % len(PALETTE)] for i in range(count)]


#: What a number parameter may be: not a bool, nor a complex (np.number),
#: whose imaginary part float() would drop.
_REAL = (int, float, np.integer, np.floating)


def _real_number(name: str, value) -> float:
    """float(value), with a ValueError for an integer beyond float's range
    (TOML and Python integers have no bound)."""
    try:
        return float(value)
    except OverflowError:
        raise ValueError(f"{name} must be a finite number, got an integer of "
                         f"{value.bit_length()} bits, beyond float's range") from None


def _vector3(name: str, value) -> np.ndarray:
    if as_array(name, value).dtype.kind not in "fiu":  # not bool, nor e.g. timedelta64
        raise TypeError(f"{name} must be 3 numbers [x, y, z], got {value!r}")
    try:
        array = np.asarray(value, dtype=np.float64)
    except (ValueError, TypeError):
        raise TypeError(f"{name} must be 3 numbers [x, y, z], got {value!r}") from None
    if array.shape != (3,):
        raise ValueError(f"{name} must be 3 numbers [x, y, z], got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} = {array.tolist()} is not finite")
    return array


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
    Camera and scene files (scenefile.py) both ask."""
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


# -- light ----------------------------------------------------------------------

@dataclass(frozen=True)
class Light:
    """A directional light plus ambient light, as scene files describe it
    (scenefile.py): ``direction`` points from the surface towards the light
    and is normalised here; intensity >= 0; ambient in [0, 1]."""

    direction: tuple[float, float, float] = (1.0, 2.0, 1.0)
    intensity: float = 1.0
    ambient: float = 0.15

    def __post_init__(self):
        direction = unit(_vector3("light.direction", self.direction))
        if direction is None:
            raise ValueError("light.direction is the zero vector")
        object.__setattr__(self, "direction", tuple(float(x) for x in direction))
        # the kernels take it as float32
        object.__setattr__(self, "intensity", _number("light.intensity", self.intensity, 0.0,
                                                      float(np.finfo(np.float32).max)))
        object.__setattr__(self, "ambient", _number("light.ambient", self.ambient, 0.0, 1.0))


# -- camera -------------------------------------------------------------------


@dataclass(frozen=True)
class Camera:
    """A pinhole camera looking from ``eye`` at ``target``; ``fov_deg`` is the
    vertical field of view.  The image convention is scenefile.py's:
    forward = unit(target - eye), right = unit(forward x up),
    true_up = right x forward."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_deg: float = 45.0  # a scene file's default too (scenefile.py)

    def __post_init__(self):
        eye, target, up = (_vector3(name, getattr(self, name)) for name in ("eye", "target", "up"))
        if isinstance(self.fov_deg, bool) or not isinstance(self.fov_deg, _REAL):
            raise TypeError(f"fov_deg must be a number, got {type(self.fov_deg).__name__}")
        fov = _real_number("fov_deg", self.fov_deg)
        if not 0.0 < fov < 180.0:
            raise ValueError(f"fov_deg must be > 0 and < 180, got {self.fov_deg}")
        problem = view_problem(eye, target, up)
        if problem is not None:
            raise ValueError(" ".join(problem))
        for name, value in (("eye", eye), ("target", target), ("up", up)):
            object.__setattr__(self, name, tuple(float(x) for x in value))
        object.__setattr__(self, "fov_deg", fov)

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

    def rays(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """The primary rays of a width x height image, as a render with spp=1
        traces them: float32 (H*W, 3) origins and directions through the pixel
        centres, row-major from the top-left pixel, in camera.cl's float32
        arithmetic."""
        width = _integer("width", width, 1, MAX_IMAGE_SIDE)
        height = _integer("height", height, 1, MAX_IMAGE_SIDE)
        record = self.pinhole(width, height)
        f32 = np.float32
        ys, xs = np.mgrid[0:height, 0:width].astype(f32)
        sx = (f32(2) * (xs + f32(0.5)) / f32(width) - f32(1)).reshape(-1, 1)
        sy = (f32(1) - f32(2) * (ys + f32(0.5)) / f32(height)).reshape(-1, 1)
        directions = record["forward"] + sx * record["right"] + sy * record["up"]
        origins = np.broadcast_to(record["eye"], directions.shape).copy()
        return origins, np.ascontiguousarray(directions, f32)


# -- argument checks ------------------------------------------------------------

def _integer(name: str, value, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {type(value).__name__}")
    if not low <= value <= high:
        raise ValueError(f"{name} must be between {low} and {high}, got {value}")
    return int(value)


def _number(name: str, value, low: float, high: float | None = None,
            low_open: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, _REAL):
        raise TypeError(f"{name} must be a number, got {type(value).__name__}")
    number = _real_number(name, value)
    too_low = number <= low if low_open else number < low
    if not math.isfinite(number) or too_low or (high is not None and number > high):
        bound = f"{'>' if low_open else '>='} {low:g}" + (f" and <= {high:g}" if high is not None
                                                          else "")
        raise ValueError(f"{name} must be a finite number {bound}, got {value}")
    return number


def check_colors(colors, geometry_count: int) -> np.ndarray:
    """Renderer.colors -> float32 (G, 3), each channel in [0, 1]."""
    if isinstance(colors, (str, bytes)) or not isinstance(colors, (Sequence, np.ndarray)):
        raise TypeError(f"colors must be a list of RGB triples, got {type(colors).__name__}")
    if len(colors) != geometry_count:
        raise ValueError(f"colors has {len(colors)} entries but the scene has "
                         f"{geometry_count} meshes: one RGB colour per mesh")
    out = np.empty((geometry_count, 3), np.float32)
    for i, color in enumerate(colors):
        try:
            rgb = np.asarray(color, dtype=np.float64)
        except (ValueError, TypeError):
            raise TypeError(f"colors[{i}] = {color!r} is not 3 numbers") from None
        if rgb.shape != (3,) or not (np.isfinite(rgb).all() and (rgb >= 0).all()
                                     and (rgb <= 1).all()):
            raise ValueError(f"colors[{i}] = {color!r}: expected 3 numbers in 0..1 (RGB)")
        out[i] = rgb
    return out


def check_light(light) -> Light:
    """Renderer.light as a Light; anything with the same three fields is
    converted and checked."""
    if isinstance(light, Light):
        return light
    if not all(hasattr(light, f) for f in ("direction", "intensity", "ambient")):
        raise TypeError(f"light must be a hlbvh_cl.Light(direction, intensity, ambient), "
                        f"got {type(light).__name__}")
    return Light(light.direction, light.intensity, light.ambient)


@dataclass(frozen=True)
class RenderSettings:
    """The checked arguments of one render."""
    camera: Camera
    width: int
    height: int
    shading: str
    shadows: bool
    spp: int
    ao_samples: int
    ao_distance: float | None

    @classmethod
    def check(cls, camera, width, height, shading, shadows, spp, ao_samples, ao_distance):
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a hlbvh_cl.Camera, got {type(camera).__name__}")
        if not isinstance(shading, str):
            raise TypeError(f"shading must be a string, one of {SHADINGS}, "
                            f"got {type(shading).__name__}")
        if shading not in SHADINGS:
            raise ValueError(f"shading must be one of {SHADINGS}, got {shading!r}")
        if not isinstance(shadows, (bool, np.bool_)):
            raise TypeError(f"shadows must be True or False, got {type(shadows).__name__}")
        if ao_distance is not None:
            ao_distance = _number("ao_distance", ao_distance, 0.0, low_open=True)
        return cls(camera=camera,
                   width=_integer("width", width, 1, MAX_IMAGE_SIDE),
                   height=_integer("height", height, 1, MAX_IMAGE_SIDE),
                   shading=shading, shadows=bool(shadows),
                   spp=_integer("spp", spp, 1, MAX_SPP),
                   ao_samples=_integer("ao_samples", ao_samples, 1, MAX_AO_SAMPLES),
                   ao_distance=ao_distance)

    def in_frame(self, scale: float) -> RenderSettings:
        """These settings in a tree's frame (hlbvh_cl.core.frame): its positions
        and lengths times ``scale``."""
        if scale == 1.0:
            return self
        largest = float(np.finfo(np.float32).max)
        for name in ("eye", "target"):
            given = getattr(self.camera, name)
            if np.abs(np.multiply(given, scale)).max() > largest:
                raise ValueError(f"camera {name} {list(given)} is too far from the origin for "
                                 f"this scene: its frame is scaled by {frame.describe(scale)} "
                                 "(hlbvh_cl/frame.py), and there the point would not fit "
                                 f"float32; keep the camera within {largest / scale:.3g}")
        camera = dataclasses.replace(self.camera, eye=tuple(np.multiply(self.camera.eye, scale)),
                                     target=tuple(np.multiply(self.camera.target, scale)))
        distance = None if self.ao_distance is None else self.ao_distance * scale
        return dataclasses.replace(self, camera=camera, ao_distance=distance)


# -- scene-dependent parameters ---------------------------------------------------

def ray_offset(bounds_lo, bounds_hi) -> float:
    """How far off the surface secondary rays start (module docstring)."""
    lo, hi = np.asarray(bounds_lo, np.float64), np.asarray(bounds_hi, np.float64)
    diagonal = float(np.linalg.norm(hi - lo))
    largest = float(np.max(np.abs(np.concatenate([lo, hi]))))
    return max(RAY_OFFSET_SCALE * diagonal, RAY_OFFSET_ULPS * largest, np.finfo(np.float32).tiny)


def depth_range(eye, bounds_lo, bounds_hi) -> tuple[float, float]:
    """Smallest and largest distance from eye to the box [lo, hi]."""
    eye = np.asarray(eye, np.float64)
    lo, hi = np.asarray(bounds_lo, np.float64), np.asarray(bounds_hi, np.float64)
    near = float(np.linalg.norm(np.maximum(np.maximum(lo - eye, eye - hi), 0.0)))
    far = float(np.linalg.norm(np.maximum(np.abs(eye - lo), np.abs(eye - hi))))
    return near, max(far, near * (1 + 1e-6), near + 1e-30)


def shade_params(settings: RenderSettings, light: Light, bounds_lo, bounds_hi) -> np.ndarray:
    """The ShadeParams record (layout.SHADE_PARAMS) of one render."""
    lo, hi = np.asarray(bounds_lo, np.float64), np.asarray(bounds_hi, np.float64)
    diagonal = float(np.linalg.norm(hi - lo))
    record = np.zeros((), layout.SHADE_PARAMS)
    record["light_direction"] = light.direction
    record["light_intensity"] = light.intensity
    record["ambient"] = light.ambient
    record["sky_up"] = unit(np.asarray(settings.camera.up, np.float64))
    record["sky_horizon"] = SKY_HORIZON
    record["sky_zenith"] = SKY_ZENITH
    record["ray_offset"] = ray_offset(lo, hi)
    record["depth_near"], record["depth_far"] = depth_range(settings.camera.eye, lo, hi)
    distance = settings.ao_distance
    if distance is None:
        distance = AO_DISTANCE_SCALE * diagonal if diagonal > 0 else 1.0
    record["ao_distance"] = distance
    record["ao_weight"] = 1.0 / settings.ao_samples
    return record


# -- the pipeline -------------------------------------------------------------------

class _Buffers:
    """Device buffers for one pass of pixels plus the whole 8-bit image;
    grow-only, reused across renders."""

    PER_PIXEL = {"primary rays": layout.RAY.itemsize, "hits": layout.HIT.itemsize,
                 "secondary rays": layout.RAY.itemsize, "occluded": 1, "pending light": 16,
                 "accumulated colour": 16}

    def __init__(self):
        self.capacity = 0
        self.image_capacity = 0

    def reserve(self, rt: Runtime, pixels: int, image_pixels: int) -> None:
        grow = pixels > self.capacity
        grow_image = image_pixels > self.image_capacity
        if not (grow or grow_image):
            return
        needed = {name: max(pixels, self.capacity) * size for name, size in self.PER_PIXEL.items()}
        needed["image"] = 3 * max(image_pixels, self.image_capacity)
        rt.check_allocation(f"rendering {image_pixels:,} pixels, {pixels:,} at a time", needed)
        ctx, rw = rt.context, cl.mem_flags.READ_WRITE
        if grow:
            self.primary = cl.Buffer(ctx, rw, pixels * layout.RAY.itemsize)
            self.hits = cl.Buffer(ctx, rw, pixels * layout.HIT.itemsize)
            self.secondary = cl.Buffer(ctx, rw, pixels * layout.RAY.itemsize)
            self.occluded = cl.Buffer(ctx, rw, pixels)
            self.pending = cl.Buffer(ctx, rw, pixels * 16)  # float4
            self.accum = cl.Buffer(ctx, rw, pixels * 16)    # float4
            self.capacity = pixels
        if grow_image:
            self.image = cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY, image_pixels * 3)
            self.image_capacity = image_pixels


class _Pipeline:
    """The render pipeline on one device: kernels and reusable buffers.

    ``last_stats`` describes the last render: image size and options,
    primary_rays and secondary_rays (shadow or AO rays launched, one per pixel
    and pass: pixels that need none get an empty one), and device times in
    milliseconds per stage ("camera", "closest", "shade", "occluded",
    "resolve", "encode", "total") plus "wall" (the whole call) and "setup"
    (part of wall: building or loading camera.cl and shade.cl, allocating
    buffers).  PoCL finishes compiling a kernel at its first launch, and a
    tree's first query may prepare it for traversal: render once, small, to
    keep those out of a measurement.
    """

    def __init__(self, rt: Runtime, query: RayQuery | None = None):
        self.rt = rt
        # the default packet (1, 8 or 16 rays) is a pixel tile, half of one or one pixel
        self.query = query or RayQuery(rt)
        self._buffers = _Buffers()
        self._overflow = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, 4)
        self._albedo: cl.Buffer | None = None
        self._albedo_size = 0
        self._lock = threading.Lock()
        self.last_stats: dict = {}

    def chunk_rows(self, width: int, height: int) -> int:
        """Image rows rendered per pass (PIXELS_PER_PASS, or fewer if one
        traversal launch holds fewer rays); whole bands of pixel tiles
        (layout.TILE_ROWS rows) when a pass holds one, so that only the
        image's last pass may end in a part band."""
        pixels = min(PIXELS_PER_PASS, self.query.max_rays_per_launch)
        rows = max(1, min(height, pixels // width))
        if rows < height and rows >= layout.TILE_ROWS:
            rows -= rows % layout.TILE_ROWS
        return rows

    def render(self, tree: Tree, settings: RenderSettings, colors: np.ndarray, light: Light,
               progress: bool = False) -> np.ndarray:
        with self._lock:  # the buffers are shared
            try:
                return self._render(tree, settings.in_frame(tree.scale), colors, light, progress)
            except BaseException:
                # Ctrl-C: the steps in flight (at most two) end before the
                # buffers serve another render.
                self.rt.queue.finish()
                raise

    def _kernels(self, settings: RenderSettings) -> dict:
        defines = {"SHADING": f"SHADING_{settings.shading.upper()}",
                   "SHADOWS": int(settings.shadows)}
        kernels = {"camera": self.rt.kernel("render/camera.cl", "primary_rays")}
        for name in ("shade_hits", "ao_rays", "add_unoccluded", "encode_image"):
            kernels[name] = self.rt.kernel("render/shade.cl", name, **defines)
        return kernels

    def _upload_colors(self, colors: np.ndarray) -> cl.Buffer:
        data = np.ascontiguousarray(colors, np.float32)
        if self._albedo is None or self._albedo_size < data.nbytes:
            self._albedo = cl.Buffer(self.rt.context, cl.mem_flags.READ_ONLY, data.nbytes)
            self._albedo_size = data.nbytes
        cl.enqueue_copy(self.rt.queue, self._albedo, data)
        return self._albedo

    def _render(self, tree, settings: RenderSettings, colors, light, progress) -> np.ndarray:
        started = time.perf_counter()
        rt, queue = self.rt, self.rt.queue
        width, height = settings.width, settings.height
        kernels = self._kernels(settings)
        rows = self.chunk_rows(width, height)
        self._buffers.reserve(rt, rows * width, width * height)
        b = self._buffers
        albedo = self._upload_colors(colors)
        camera = settings.camera.pinhole(width, height)
        params = shade_params(settings, light, tree.bounds_lo, tree.bounds_hi)
        cl.enqueue_copy(queue, self._overflow, np.zeros(1, np.int32))
        setup = time.perf_counter() - started

        shading = settings.shading
        shadow_pass = shading == "diffuse" and settings.shadows
        secondary_passes = settings.ao_samples if shading == "ao" else int(shadow_pass)
        image = np.empty((height, width, 3), np.uint8)
        events = {name: [] for name in ("camera", "closest", "shade", "occluded", "resolve",
                                        "encode")}
        chunks = range(0, height, rows)
        bar = _progress_bar(progress, len(chunks) * settings.spp * (1 + secondary_passes))
        steps: list[cl.Event] = []

        def step_done(event: cl.Event) -> None:
            """At most two steps (a pass's rays of one kind) in flight, so that
            Ctrl-C, which waits for them, is answered soon; the bar advances."""
            steps.append(event)
            if len(steps) > 2:
                rt.wait(steps[-3:-2])
            _advance(bar, rt, event)

        with bar:
            for row in chunks:
                first_row, pass_rows = np.uint32(row), np.uint32(min(rows, height - row))
                count = int(pass_rows) * width
                n = np.uint32(count)
                # pixel_in_pass's 2D range (hlbvh.h): bands of TILE_ROWS rows
                tile_range = (layout.TILE_ROWS * width, -(-int(pass_rows) // layout.TILE_ROWS))
                for sample in range(settings.spp):
                    s = np.uint32(sample)
                    events["camera"].append(rt.run(
                        kernels["camera"], tile_range, camera, np.uint32(width), np.uint32(height),
                        first_row, pass_rows, s, np.int32(settings.spp > 1), b.primary))
                    events["closest"].append(self.query.enqueue_intersect(
                        tree, b.primary, b.hits, count, self._overflow))
                    events["shade"].append(rt.run(
                        kernels["shade_hits"], count, b.primary, b.hits, albedo, params, n, s,
                        b.secondary, b.pending, b.accum))
                    step_done(events["shade"][-1])
                    for k in range(secondary_passes):
                        if shading == "ao":
                            events["shade"].append(rt.run(
                                kernels["ao_rays"], tile_range, b.primary, b.hits, params,
                                np.uint32(width), first_row, pass_rows, s, np.uint32(k),
                                b.secondary))
                        events["occluded"].append(self.query.enqueue_occluded(
                            tree, b.secondary, b.occluded, count, self._overflow))
                        events["resolve"].append(rt.run(
                            kernels["add_unoccluded"], count, b.occluded, b.pending, n, b.accum))
                        step_done(events["resolve"][-1])
                events["encode"].append(rt.run(
                    kernels["encode_image"], tile_range, b.accum, np.uint32(width), first_row,
                    pass_rows, np.float32(1.0 / settings.spp), b.image))
        overflow = np.zeros(1, np.int32)
        rt.wait([cl.enqueue_copy(queue, image, b.image, is_blocking=False),
                 cl.enqueue_copy(queue, overflow, self._overflow, is_blocking=False)])
        if overflow[0]:
            raise RuntimeError("ray traversal overflowed its stack: the tree is deeper than "
                               "its depth field says")
        times = {name: event_ms(found) for name, found in events.items()}
        times["total"] = sum(times.values())
        times["setup"] = setup * 1e3
        times["wall"] = (time.perf_counter() - started) * 1e3
        pixels = width * height * settings.spp
        self.last_stats = {"width": width, "height": height, "shading": shading,
                           "shadows": settings.shadows, "spp": settings.spp,
                           "primary_rays": pixels, "secondary_rays": pixels * secondary_passes,
                           "times_ms": times}
        return image


class Renderer:
    """Renders a Scene through a Camera.

    ``colors`` holds one RGB triple (0..1) per mesh (by default PALETTE,
    cycled) and ``light`` a Light; both may be reassigned between renders,
    None giving the defaults again.
    ``stats`` describes the last render ({} before one): image size and
    options, primary_rays and secondary_rays (shadow or AO rays launched,
    one per pixel and pass), and device milliseconds per stage ("camera",
    "closest", "shade", "occluded", "resolve", "encode", "total") plus
    "wall" and "setup" (building or loading camera.cl and shade.cl,
    allocating buffers).  The first render compiles kernels: render once,
    small, to keep that out of a measurement.
    """

    def __init__(self, scene, colors=None, light: Light | None = None):
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a hlbvh_cl.Scene, got {type(scene).__name__}")
        self.scene = scene
        self.colors = default_colors(len(scene.meshes)) if colors is None else colors
        self.light = Light() if light is None else light
        self._pipeline: _Pipeline | None = None

    @property
    def stats(self) -> dict:
        return self._pipeline.last_stats if self._pipeline is not None else {}

    def render(self, camera: Camera, width: int, height: int, shading: str = "diffuse",
               shadows: bool = True, spp: int = 1, ao_samples: int = AO_SAMPLES,
               ao_distance: float | None = None, progress: bool = False) -> np.ndarray:
        """A (height, width, 3) uint8 RGB image.  shading is "diffuse",
        "normals", "depth" or "ao"; spp samples per pixel; ao_samples AO rays
        per sample, reaching ao_distance (default 5% of the scene's
        diagonal).  progress shows a tqdm bar on stderr for renders longer
        than a second.  The formulas are in this module's docstring."""
        settings = RenderSettings.check(camera, width, height, shading, shadows, spp,
                                        ao_samples, ao_distance)
        count = len(self.scene.meshes)
        colors = check_colors(default_colors(count) if self.colors is None else self.colors, count)
        light = check_light(Light() if self.light is None else self.light)
        with self.scene.borrow() as built:  # no rebuild or refit while the tree is read
            if self._pipeline is None:
                self._pipeline = _Pipeline(built.runtime)  # its own queries and buffers
            return self._pipeline.render(built.tree, settings, colors, light, progress=progress)


def _progress_bar(enabled: bool, total: int):
    from tqdm import tqdm
    # Shown only once a render has taken a second (tqdm's delay).
    return tqdm(total=total, desc="rendering", unit="pass", file=sys.stderr, delay=1.0,
                leave=False, disable=not enabled)


def _advance(bar, rt: Runtime, event: cl.Event) -> None:
    if not bar.disable:  # waiting costs a sync per pass: only with a visible bar
        rt.wait([event])
        bar.update(1)
