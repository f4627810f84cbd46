"""Materials of the path integrator, with Mitsuba 3's names and parameters,
one per mesh (Renderer.materials), so that a Mitsuba scene translates one
to one:

- ``{"type": "diffuse", "reflectance": 0.5}``: Lambert's BSDF, albedo
  ``reflectance`` (a number or RGB, each in [0, 1]; Mitsuba's default 0.5).
  As in Mitsuba it reflects on the front side only, the side the geometric
  normal cross(v1 - v0, v2 - v0) points to; the back side is black.
- ``{"type": "conductor", "eta": 0, "k": 1, "specular_reflectance": 1}``:
  a smooth metal, mirror reflection weighted by Fresnel's conductor
  equations for the complex index eta + i k (numbers or RGB); Mitsuba's
  defaults, eta 0 and k 1, make a perfect mirror.  One-sided.  Named
  metals ("material": "Au") are refused: give eta and k.
- ``{"type": "roughconductor", "distribution": "ggx", "alpha": 0.1, "eta": 0,
  "k": 1, "specular_reflectance": 1}``: a rough metal, the GGX microfacet
  model sampled by its visible normals.  Mitsuba's default distribution is
  "beckmann", which is not written yet: name "ggx".  Isotropic only
  (alpha, not alpha_u and alpha_v).
- ``{"type": "dielectric", "int_ior": 1.5046, "ext_ior": 1.000277,
  "specular_reflectance": 1, "specular_transmittance": 1}``: smooth glass,
  Fresnel reflection or refraction (Mitsuba's defaults: BK7 in air; an
  index is a number > 0).  It has no back side.
- ``{"type": "twosided", "bsdf": {...}}``: a one-sided BSDF on both sides.

Renderer.materials = None gives every mesh a two-sided diffuse BSDF of its
Renderer.colors entry, which, as the preview modes do, forgives meshes
wound either way.  Other Mitsuba BSDFs are errors until they are written.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ..core import inputs, layout
from .plugins import plugin_type

#: The BSDF types written so far, and the parameters each takes.
BSDFS = {"diffuse": ("reflectance",),
         "conductor": ("eta", "k", "specular_reflectance", "material"),
         "roughconductor": ("eta", "k", "specular_reflectance", "material", "distribution",
                            "alpha"),
         "dielectric": ("int_ior", "ext_ior", "specular_reflectance", "specular_transmittance"),
         "twosided": ("bsdf",)}

#: PathMaterial.bsdf of each (kernels/render/bsdfs/bsdf.h).
CODES = {"diffuse": 0, "conductor": 1, "dielectric": 2, "roughconductor": 3}

#: Mitsuba's default roughness.
DEFAULT_ALPHA = 0.1

#: Mitsuba's default diffuse reflectance, and its default indices of
#: refraction for a dielectric (BK7 inside, air outside).
DEFAULT_REFLECTANCE = 0.5
BK7, AIR = 1.5046, 1.000277

_LARGE = float(np.finfo(np.float32).max) ** 0.25  # eta and k are squared twice


def _bsdf(name: str, spec) -> np.void:
    """One BSDF spec -> its PathMaterial record (no emission)."""
    kind = plugin_type(name, spec, BSDFS, {"type": "diffuse", "reflectance": 0.5}, "materials")
    record = np.zeros((), layout.PATH_MATERIAL)
    if kind == "twosided":
        if "bsdf" not in spec:
            raise ValueError(f"{name}: twosided needs the BSDF it wraps ('bsdf')")
        inner = _bsdf(f"{name}['bsdf']", spec["bsdf"])
        if inner["twosided"] or inner["bsdf"] == CODES["dielectric"]:
            raise ValueError(f"{name}['bsdf'] has no back side to wrap (twosided or dielectric)")
        inner["twosided"] = 1
        return inner
    record["bsdf"] = CODES[kind]

    def color(key, default, high=1.0):
        return inputs.color(f"{name}[{key!r}]", spec.get(key, default), high)
    if kind == "diffuse":
        record["reflectance"] = color("reflectance", DEFAULT_REFLECTANCE)
    elif kind in ("conductor", "roughconductor"):
        if kind == "roughconductor":
            distribution = spec.get("distribution", "beckmann")
            if distribution != "ggx":
                raise ValueError(f"{name}: distribution {distribution!r} is not written yet "
                                 "(Mitsuba's default is 'beckmann'); give 'distribution': 'ggx'")
            record["alpha"] = inputs.number(f"{name}['alpha']", spec.get("alpha", DEFAULT_ALPHA),
                                            1e-4, 1.0)
        material = spec.get("material", "none")
        if material != "none":
            raise ValueError(f"{name}: named conductors ({material!r}) are not written yet; "
                             "give its 'eta' and 'k' instead")
        record["reflectance"] = color("specular_reflectance", 1.0)
        record["eta"] = color("eta", 0.0, _LARGE)
        record["k"] = color("k", 1.0, _LARGE)
    else:  # dielectric
        record["reflectance"] = color("specular_reflectance", 1.0)
        record["transmittance"] = color("specular_transmittance", 1.0)
        inside = inputs.number(f"{name}['int_ior']", spec.get("int_ior", BK7), 0.0, _LARGE,
                               low_open=True)
        outside = inputs.number(f"{name}['ext_ior']", spec.get("ext_ior", AIR), 0.0, _LARGE,
                                low_open=True)
        record["eta"] = inside / outside
    return record


def check_material(name: str, spec) -> np.void:
    """One material spec -> its PathMaterial record (no emission); errors
    name it ``name``."""
    return _bsdf(name, spec)


def material_table(materials, colors: np.ndarray) -> np.ndarray:
    """Renderer.materials (a sequence, one spec per mesh, or None) ->
    PathMaterial records (layout.PATH_MATERIAL) with no emission yet;
    ``colors``: the checked Renderer.colors, used where materials is None."""
    count = len(colors)
    table = np.zeros(count, layout.PATH_MATERIAL)
    if materials is None:
        table["reflectance"] = colors
        table["twosided"] = 1
        return table
    if isinstance(materials, (str, bytes, Mapping)) or not isinstance(materials, Sequence):
        raise TypeError("materials must be a list with one material per mesh, got "
                        f"{type(materials).__name__}")
    if len(materials) != count:
        raise ValueError(f"materials has {len(materials)} entries but the scene has {count} "
                         "meshes: one material per mesh")
    for i, spec in enumerate(materials):
        table[i] = _bsdf(f"materials[{i}]", spec)
    return table
