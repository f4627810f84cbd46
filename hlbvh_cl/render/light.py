"""Lights of the direct integrator: one directional light plus ambient
light, as scene files describe it (hlbvh_cl.io.scenefile)."""
from __future__ import annotations

from dataclasses import dataclass

from ..core import inputs
from .camera import unit
from .film import BRIGHTEST


@dataclass(frozen=True)
class Light:
    """A directional light plus ambient light: ``direction`` points from the
    surface towards the light and is normalised here; intensity >= 0 (it
    must fit float32: the kernels take it so); ambient in [0, 1]."""

    direction: tuple[float, float, float] = (1.0, 2.0, 1.0)
    intensity: float = 1.0
    ambient: float = 0.15

    def __post_init__(self):
        direction = unit(inputs.vector3("light.direction", self.direction))
        if direction is None:
            raise ValueError("light.direction is the zero vector")
        object.__setattr__(self, "direction", tuple(float(x) for x in direction))
        object.__setattr__(self, "intensity", inputs.number(
            "light.intensity", self.intensity, 0.0, BRIGHTEST))
        object.__setattr__(self, "ambient", inputs.number("light.ambient", self.ambient, 0.0, 1.0))


def check_light(light) -> Light:
    """Renderer.light as a Light; anything with the same three fields is
    converted and checked."""
    if isinstance(light, Light):
        return light
    if not all(hasattr(light, f) for f in ("direction", "intensity", "ambient")):
        raise TypeError(f"light must be a hlbvh_cl.Light(direction, intensity, ambient), "
                        f"got {type(light).__name__}")
    return Light(light.direction, light.intensity, light.ambient)
