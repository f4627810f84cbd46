"""The checked arguments of one render (RenderSettings) and the scene's
colours: what every integrator reads besides the scene."""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..core import frame, inputs
from .camera import FILTERS, MAX_IMAGE_SIDE, Camera

#: Samples per pixel, and AO rays per sample, beyond these are taken for mistakes.
MAX_SPP = 1 << 16
#: The largest seed: seed * MAX_SPP + sample must fit 32 bits.
MAX_SEED = 2**32 // MAX_SPP - 1
MAX_AO_SAMPLES = 1024

#: Default number of AO rays per pixel and sample.
AO_SAMPLES = 16

#: Path depths (Mitsuba's max_depth: segments per path; -1 for no limit)
#: beyond this are taken for mistakes; Russian roulette's default start
#: (Mitsuba's rr_depth), and its latest: any int32, as Mitsuba reads it (the
#: kernels' PathParams holds an int32).  A start past a path's last bounce
#: means no roulette, which renders as Mitsuba does.
MAX_DEPTH = 1024
RR_DEPTH = 5
MAX_RR_DEPTH = 2**31 - 1

#: Colours of meshes 0, 1, 2, ... of a Scene that was given none (cycled).
PALETTE = ((0.85, 0.6, 0.5), (0.55, 0.7, 0.85), (0.9, 0.85, 0.7), (0.6, 0.8, 0.55),
           (0.8, 0.6, 0.8), (0.75, 0.75, 0.72))


def default_colors(count: int) -> list[tuple[float, float, float]]:
    return [PALETTE[i % len(PALETTE)] for i in range(count)]


def check_colors(colors, geometry_count: int) -> np.ndarray:
    """Renderer.colors -> float32 (G, 3), each channel in [0, 1]."""
    if isinstance(colors, (str, bytes)) or not isinstance(colors, (Sequence, np.ndarray)):
        raise TypeError(f"colors must be a list of RGB triples, got {type(colors).__name__}")
    if len(colors) != geometry_count:
        raise ValueError(f"colors has {len(colors)} entries but the scene has "
                         f"{geometry_count} geometries: one RGB colour per mesh, then per "
                         "sphere (geom_id order)")
    out = np.empty((geometry_count, 3), np.float32)
    for i, color in enumerate(colors):
        if any(isinstance(c, (bool, np.bool_)) for c in np.ravel(np.asarray(color, object))):
            raise TypeError(f"colors[{i}] = {color!r}: expected 3 numbers in 0..1 (RGB), "
                            "not booleans")
        try:
            rgb = np.asarray(color, dtype=np.float64)
        except (ValueError, TypeError):
            raise TypeError(f"colors[{i}] = {color!r} is not 3 numbers") from None
        if rgb.shape != (3,) or not (np.isfinite(rgb).all() and (rgb >= 0).all()
                                     and (rgb <= 1).all()):
            raise ValueError(f"colors[{i}] = {color!r}: expected 3 numbers in 0..1 (RGB)")
        out[i] = rgb
    return out


@dataclass(frozen=True)
class RenderSettings:
    """The checked arguments of one render; ``shading`` names an integrator's
    mode (hlbvh_cl.render.integrators)."""
    camera: Camera
    width: int
    height: int
    shading: str
    shadows: bool
    spp: int
    ao_samples: int
    ao_distance: float | None
    max_depth: int = -1
    rr_depth: int = RR_DEPTH
    seed: int = 0
    rfilter: str = "box"

    def jitter(self) -> int:
        """The camera kernel's jitter: the pixels' centres for one sample of
        seed 0, else the filter's (camera.FILTERS), uniform in the pixel
        when the film splats."""
        if self.spp == 1 and self.seed == 0:
            return 0
        return FILTERS["box"] if self.splats() else FILTERS[self.rfilter]

    def splats(self) -> bool:
        """Whether the film splats each sample over the pixels around
        (film.py), as Mitsuba's does under a filter wider than a pixel: the
        path integrator's Gaussian.  (The previews draw its offsets instead.)"""
        return self.shading == "path" and self.rfilter == "gaussian"

    def stream(self, sample: int) -> int:
        """The random stream of sample ``sample`` (render/random.h's
        `sample` argument): seed 0 gives the sample itself."""
        return self.seed * MAX_SPP + sample

    @classmethod
    def check(cls, camera, width, height, shading, shadows, spp, ao_samples, ao_distance,
              shadings: tuple[str, ...], max_depth=-1, rr_depth=RR_DEPTH, seed=0,
              rfilter="box"):
        """The settings, each argument checked; ``shading`` must be one of
        ``shadings``."""
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a hlbvh_cl.Camera, got {type(camera).__name__}")
        if not isinstance(shading, str):
            raise TypeError(f"shading must be a string, one of {shadings}, "
                            f"got {type(shading).__name__}")
        if shading not in shadings:
            raise ValueError(f"shading must be one of {shadings}, got {shading!r}")
        if not isinstance(shadows, (bool, np.bool_)):
            raise TypeError(f"shadows must be True or False, got {type(shadows).__name__}")
        if ao_distance is not None:
            ao_distance = inputs.number("ao_distance", ao_distance, 0.0,
                                        float(np.finfo(np.float32).max), low_open=True)
        if not isinstance(rfilter, str) or rfilter not in FILTERS:
            raise ValueError(f"rfilter must be one of {tuple(FILTERS)} (Mitsuba's names), got "
                             f"{rfilter!r}")
        max_depth = inputs.integer("max_depth", max_depth, -1, MAX_DEPTH)
        if max_depth == 0:
            raise ValueError("max_depth must be -1 (no limit) or 1..1024 (segments per path: "
                             "1 shows only what the camera sees emitting), got 0")
        return cls(camera=camera,
                   width=inputs.integer("width", width, 1, MAX_IMAGE_SIDE),
                   height=inputs.integer("height", height, 1, MAX_IMAGE_SIDE),
                   shading=shading, shadows=bool(shadows),
                   spp=inputs.integer("spp", spp, 1, MAX_SPP),
                   ao_samples=inputs.integer("ao_samples", ao_samples, 1, MAX_AO_SAMPLES),
                   ao_distance=ao_distance, max_depth=max_depth,
                   rr_depth=inputs.integer("rr_depth", rr_depth, 1, MAX_RR_DEPTH),
                   seed=inputs.integer("seed", seed, 0, MAX_SEED), rfilter=rfilter)

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
                                 "(hlbvh_cl/core/frame.py), and there the point would not fit "
                                 f"float32; keep the camera within {largest / scale:.3g}")
        camera = dataclasses.replace(self.camera, eye=tuple(np.multiply(self.camera.eye, scale)),
                                     target=tuple(np.multiply(self.camera.target, scale)),
                                     near_clip=self.camera.near_clip * scale,
                                     far_clip=self.camera.far_clip * scale)
        distance = None if self.ao_distance is None else self.ao_distance * scale
        return dataclasses.replace(self, camera=camera, ao_distance=distance)
