"""The direct integrator: the fast previews, each one ray or a few per
sample past the primary hit (kernels/render/integrators/direct.cl).  Its modes:

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
  basis around n of Duff et al. 2017.  A miss shows the sky.
- "diffuse" and "ao" are radiance, encoded with display gamma 2 by the
  film; "normals" and "depth" are data, encoded as they are.

tests/render/test_render.py rebuilds images from these definitions with a
brute-force oracle.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from ...core import layout
from ...core.paths import kernel_of
from ...device.runtime import Runtime
from ..camera import unit
from .base import Integrator, Look, Step

KERNEL = kernel_of(__name__)

#: Linear RGB of the background at and below the horizon, and straight up.
SKY_HORIZON = (0.86, 0.89, 0.93)
SKY_ZENITH = (0.42, 0.58, 0.82)

#: Secondary rays start max(RAY_OFFSET_SCALE * D, RAY_OFFSET_ULPS * M) off
#: the surface (D: the scene box's diagonal, M: its largest coordinate).
RAY_OFFSET_SCALE = 1e-4
RAY_OFFSET_ULPS = 2.0 ** -16

#: Default AO reach, as a fraction of the scene box's diagonal.
AO_DISTANCE_SCALE = 0.05


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


def shade_params(settings, light, bounds_lo, bounds_hi) -> np.ndarray:
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


class Direct(Integrator):
    """Diffuse shading with shadows, normals, depth and ambient occlusion
    (the module's definitions): one shading pass per sample, then the
    shadow ray or each AO ray, whose light is added where it is free."""

    modes = ("diffuse", "normals", "depth", "ao")

    #: Bytes per pixel of a pass of the integrator's own buffers.
    PER_PIXEL = {"secondary rays": layout.RAY.itemsize, "occluded": 1, "pending light": 16}

    def __init__(self):
        self._pixels = 0
        self._albedo: cl.Buffer | None = None
        self._albedo_size = 0

    def buffer_sizes(self, pixels: int) -> dict[str, int]:
        return {name: size * pixels for name, size in self.PER_PIXEL.items()}

    def prepare(self, rt: Runtime, settings, tree, look: Look, pixels: int) -> None:
        self.rt, self.settings = rt, settings
        defines = {"SHADING": f"SHADING_{settings.shading.upper()}",
                   "SHADOWS": int(settings.shadows)}
        self._kernels = {name: rt.kernel(KERNEL, name, **defines)
                         for name in ("shade_hits", "ao_rays", "add_unoccluded")}
        if pixels > self._pixels:
            context, rw = rt.context, cl.mem_flags.READ_WRITE
            self.secondary = cl.Buffer(context, rw, pixels * layout.RAY.itemsize)
            self.occluded = cl.Buffer(context, rw, pixels)
            self.pending = cl.Buffer(context, rw, pixels * 16)  # float4
            self._pixels = pixels
        data = np.ascontiguousarray(look.colors, np.float32)
        if self._albedo is None or self._albedo_size < data.nbytes:
            self._albedo = cl.Buffer(rt.context, cl.mem_flags.READ_ONLY, data.nbytes)
            self._albedo_size = data.nbytes
        cl.enqueue_copy(rt.queue, self._albedo, data)
        self._params = shade_params(settings, look.light, tree.bounds_lo, tree.bounds_hi)

    def passes(self, settings) -> int:
        if settings.shading == "ao":
            return settings.ao_samples
        return int(settings.shading == "diffuse" and settings.shadows)

    def radiance(self, settings) -> bool:
        return settings.shading in ("diffuse", "ao")

    def shade(self, step: Step) -> None:
        rt, band, kernels, events = step.rt, step.band, self._kernels, step.events
        n, s = np.uint32(band.count), np.uint32(step.sample)
        events["shade"].append(rt.run(
            kernels["shade_hits"], band.count, step.rays, step.hits, self._albedo, self._params,
            n, s, self.secondary, self.pending, step.accum))
        step.done(events["shade"][-1])
        for k in range(self.passes(self.settings)):
            if self.settings.shading == "ao":
                events["shade"].append(rt.run(
                    kernels["ao_rays"], band.tile_range, step.rays, step.hits, self._params,
                    np.uint32(band.width), band.first_row, band.rows, np.uint32(step.stream),
                    np.uint32(k),
                    self.secondary))
            events["occluded"].append(step.query.enqueue_occluded(
                step.tree, self.secondary, self.occluded, band.count, step.overflow))
            events["resolve"].append(rt.run(
                kernels["add_unoccluded"], band.count, self.occluded, self.pending, n,
                step.accum))
            step.done(events["resolve"][-1])
