"""Integrators: the ways a built scene becomes an image (Mitsuba 3's
integrator plugins), one module each behind the interface of base.py, and
their kernels in kernels/render/integrators/.  ``INTEGRATORS`` lists them:
adding one is its module and its line there.  It imports core, device,
query (the rays' entry points) and the render room's camera, light,
settings and film."""
from __future__ import annotations

from .base import Integrator
from .direct import Direct
from .path import Path

#: Every integrator, each once.
INTEGRATORS: tuple[type[Integrator], ...] = (Direct, Path)

#: The shading names Renderer.render takes: every integrator's modes.
SHADINGS: tuple[str, ...] = tuple(mode for cls in INTEGRATORS for mode in cls.modes)


def integrator_for(shading: str) -> type[Integrator]:
    """The integrator that renders mode ``shading`` (one of SHADINGS)."""
    return next(cls for cls in INTEGRATORS if shading in cls.modes)
