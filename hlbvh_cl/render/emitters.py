"""Emitters of the path integrator, with Mitsuba 3's names and parameters
(Renderer.emitters, a list):

- ``{"type": "area", "mesh": i, "radiance": rgb}``: mesh i emits
  ``radiance`` from the front side of each triangle (along its geometric
  normal cross(v1 - v0, v2 - v0)), as Mitsuba's area emitter;
- ``{"type": "constant", "radiance": rgb}``: light from every direction
  at infinity, as Mitsuba's constant emitter;
- ``{"type": "point", "position": [x, y, z], "intensity": rgb}``: a point
  light of that radiant intensity (Mitsuba's point emitter);
- ``{"type": "directional", "direction": [x, y, z], "irradiance": rgb}``:
  parallel light travelling along ``direction`` (Mitsuba's directional
  emitter), of that irradiance on a surface facing it;
- ``{"type": "envmap", "filename": "sky.exr", "scale": 1.0, "to_world": R}``:
  an equirectangular image of the light from every direction (Mitsuba's
  envmap emitter; envmap.py has its mapping and sampling): an OpenEXR or
  Radiance .hdr file, or instead of ``filename`` an ``image``, a numpy
  float array (H, W, 3) of linear RGB; ``to_world`` a rotation, 3 x 3 or
  4 x 4 (default the identity).

At most one environment (constant or envmap) lights a scene.

A radiance is a number or RGB, each >= 0 and finite.  Renderer.emitters =
None lights the scene with a constant environment of radiance 1, so that a
first render shows the scene; [] renders it dark.

Light sampling picks a light by its power (over pi, in luminance: a
point light's 4 I, a directional light's R^2 E for the scene's bounding
sphere of radius R, the triangles' sum of area times L, and for an
environment map the most its light samples can deliver to the scene's
surfaces, their area S times the luminance they sample (its excess over
the map's mean: envmap.py) integrated over the sphere over 4 pi), then a
triangle by its own power and a point uniform in its area.  Point and
directional lights are deltas: only light sampling reaches them.  A
constant environment takes no light samples: BSDF sampling alone reaches
it (integrators/path.py).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..core import inputs
from .envmap import LUMINANCE, Envmap, check_envmap
from .film import BRIGHTEST
from .plugins import plugin_type

#: The emitter types written so far, and the parameters each takes.
EMITTERS = {"area": ("mesh", "radiance"), "constant": ("radiance",),
            "point": ("position", "intensity"), "directional": ("direction", "irradiance"),
            "envmap": ("filename", "image", "scale", "to_world")}

#: The value each emitter type needs.
VALUES = {"area": "radiance", "constant": "radiance", "point": "intensity",
          "directional": "irradiance"}

#: Renderer.emitters = None: a white sky all around.
DEFAULT = ({"type": "constant", "radiance": 1.0},)



@dataclass(frozen=True)
class Emitters:
    """Checked emitters: radiance per emitting mesh, the constant
    environment's or the environment map, and the delta lights as (type,
    position or unit direction, value)."""
    area: dict[int, np.ndarray] = field(default_factory=dict)
    environment: np.ndarray | None = None
    deltas: tuple = ()
    envmap: Envmap | None = None


def check_emitters(emitters, mesh_count: int, names=None) -> Emitters:
    """Renderer.emitters (or None) -> Emitters, every entry checked; errors
    name entry i ``names[i]`` (default "emitters[i]")."""
    if emitters is None:
        emitters = DEFAULT
    if isinstance(emitters, (str, bytes, Mapping)) or not isinstance(emitters, Sequence):
        raise TypeError(f"emitters must be a list of emitters such as {DEFAULT[0]}, got "
                        f"{type(emitters).__name__}")
    area: dict[int, np.ndarray] = {}
    environment = envmap = None
    deltas: list = []
    first_environment = None
    for i, spec in enumerate(emitters):
        name = names[i] if names is not None else f"emitters[{i}]"
        kind = plugin_type(name, spec, EMITTERS, DEFAULT[0], "emitters")
        if kind in ("constant", "envmap"):
            if first_environment is not None:
                raise ValueError(f"{name}: a second environment ({kind}) besides "
                                 f"{first_environment}: one at most lights a scene")
            first_environment = f"{name} ({kind})"
        if kind == "envmap":
            envmap = check_envmap(name, spec)
            continue
        value = VALUES[kind]
        if value not in spec:
            raise ValueError(f"{name}: {kind} needs its {value!r}")
        radiance = inputs.color(f"{name}[{value!r}]", spec[value], BRIGHTEST)
        if kind in ("point", "directional"):
            where = "position" if kind == "point" else "direction"
            if where not in spec:
                raise ValueError(f"{name}: {kind} needs its {where!r}")
            largest = float(np.finfo(np.float32).max)  # the kernels' float32
            vector = inputs.vector3(f"{name}[{where!r}]", spec[where], -largest, largest)
            if kind == "directional":
                length = float(np.linalg.norm(vector))
                if not length > 0:
                    raise ValueError(f"{name}['direction'] is the zero vector")
                vector = vector / length
            deltas.append((kind, vector, radiance))
            continue
        if kind == "constant":
            environment = radiance
            continue
        mesh = spec.get("mesh")
        if isinstance(mesh, bool) or not isinstance(mesh, (int, np.integer)) \
                or not 0 <= mesh < mesh_count:
            raise ValueError(f"{name}['mesh'] = {mesh!r}: expected the index of a mesh, "
                             f"0..{mesh_count - 1}")
        if int(mesh) in area:
            raise ValueError(f"{name}: mesh {int(mesh)} has an area emitter already")
        area[int(mesh)] = radiance
    return Emitters(area, environment, tuple(deltas), envmap)


def luminance(radiance: np.ndarray) -> float:
    return float(LUMINANCE @ np.asarray(radiance, np.float64))
