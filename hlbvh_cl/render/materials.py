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
  defaults, eta 0 and k 1, make a perfect mirror.  One-sided.  Or
  ``"material": "Au"``: a metal Mitsuba names, its eta and k from
  metals.METALS (Mitsuba's RGB values; "none", the default, is the
  mirror); naming one and giving eta or k too is an error, as in Mitsuba.
- ``{"type": "roughconductor", "distribution": "beckmann", "alpha": 0.1,
  "eta": 0, "k": 1, "specular_reflectance": 1}``: a rough metal (eta and
  k, or a "material", as the conductor's), a
  microfacet model, "beckmann" (Mitsuba's default) or "ggx", each
  sampled by its visible normals.  Isotropic only (alpha, not
  alpha_u and alpha_v).
- ``{"type": "dielectric", "int_ior": 1.5046, "ext_ior": 1.000277,
  "specular_reflectance": 1, "specular_transmittance": 1}``: smooth glass,
  Fresnel reflection or refraction (Mitsuba's defaults: BK7 in air; an
  index is a number > 0).  It has no back side.
- ``{"type": "roughdielectric", "distribution": "beckmann", "alpha": 0.1,
  "int_ior": 1.5046, "ext_ior": 1.000277, "specular_reflectance": 1,
  "specular_transmittance": 1}``: rough glass (Walter et al. 2007); the
  indices must differ.  No back side.
- ``{"type": "plastic", "diffuse_reflectance": 0.5, "specular_reflectance":
  1, "int_ior": 1.49, "ext_ior": 1.000277, "nonlinear": False}``: a diffuse
  base under a smooth dielectric coating (Mitsuba's defaults:
  polypropylene in air); ``nonlinear`` scales the light bouncing inside the
  coating by the base's albedo.  One-sided.
- ``{"type": "roughplastic", "distribution": "beckmann", "alpha": 0.1, ...}``:
  the same under a rough coating, with plastic's parameters besides; the
  indices must differ.  One-sided.
- ``{"type": "twosided", "bsdf": {...}}``: a one-sided BSDF on both sides.

Renderer.materials = None gives every mesh a two-sided diffuse BSDF of its
Renderer.colors entry, which, as the preview modes do, forgives meshes
wound either way.  Other Mitsuba BSDFs are errors until they are written.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ..core import inputs, layout
from . import coating
from .metals import METALS
from .plugins import plugin_type

_PLASTIC = ("diffuse_reflectance", "specular_reflectance", "int_ior", "ext_ior", "nonlinear")

#: The BSDF types written so far, and the parameters each takes.
BSDFS = {"diffuse": ("reflectance",),
         "conductor": ("eta", "k", "specular_reflectance", "material"),
         "roughconductor": ("eta", "k", "specular_reflectance", "material", "distribution",
                            "alpha"),
         "dielectric": ("int_ior", "ext_ior", "specular_reflectance", "specular_transmittance"),
         "roughdielectric": ("int_ior", "ext_ior", "specular_reflectance",
                             "specular_transmittance", "distribution", "alpha"),
         "plastic": _PLASTIC,
         "roughplastic": (*_PLASTIC, "distribution", "alpha"),
         "twosided": ("bsdf",)}

#: PathMaterial.bsdf of each (kernels/render/bsdfs/bsdf.h).
CODES = {"diffuse": 0, "conductor": 1, "dielectric": 2, "roughconductor": 3, "plastic": 4,
         "roughplastic": 5, "roughdielectric": 6}

#: PathMaterial.distribution of each (kernels/render/bsdfs/microfacet.h).
DISTRIBUTIONS = {"ggx": 0, "beckmann": 1}

#: Mitsuba's default roughness.
DEFAULT_ALPHA = 0.1

#: Mitsuba's default diffuse reflectance, and its default indices of
#: refraction for a dielectric (BK7 inside, air outside).
DEFAULT_REFLECTANCE = 0.5
BK7, AIR = 1.5046, 1.000277

#: Mitsuba's default inside index of plastic: polypropylene.
POLYPROPYLENE = 1.49

#: An index of refraction (int_ior, ext_ior) at most.
_LARGE = float(np.finfo(np.float32).max) ** 0.25

#: A conductor's eta and k at most: the kernel's fresnel_conductor
#: (render/bsdfs/fresnel.h) squares eta^2 + k^2, which float32 then holds
#: (2^126 at most; at 4e9 each it overflowed, and the metal rendered black).
CONDUCTOR_INDEX_MAX = 2.0 ** 31

#: The relative index of a dielectric interface (int_ior / ext_ior) lies in
#: [1 / RELATIVE_INDEX_MAX, RELATIVE_INDEX_MAX]: the kernels scale radiance
#: by its inverse square and square it in the Fresnel terms, in float32 (at
#: 1e-20 a roughplastic rendered black).  Real interfaces lie within 0.1 to
#: 10.
RELATIVE_INDEX_MAX = 1e6


def _bsdf(name: str, spec) -> np.void:
    """One BSDF spec -> its PathMaterial record (no emission)."""
    kind = plugin_type(name, spec, BSDFS, {"type": "diffuse", "reflectance": 0.5}, "materials")
    record = np.zeros((), layout.PATH_MATERIAL)
    if kind == "twosided":
        if "bsdf" not in spec:
            raise ValueError(f"{name}: twosided needs the BSDF it wraps ('bsdf')")
        inner = _bsdf(f"{name}['bsdf']", spec["bsdf"])
        if inner["twosided"] or inner["bsdf"] in (CODES["dielectric"], CODES["roughdielectric"]):
            raise ValueError(f"{name}['bsdf'] has no back side to wrap (twosided or dielectric)")
        inner["twosided"] = 1
        return inner
    record["bsdf"] = CODES[kind]

    def color(key, default, high=1.0):
        return inputs.color(f"{name}[{key!r}]", spec.get(key, default), high)
    if kind.startswith("rough"):
        _microfacet(name, spec, record)
    if kind == "diffuse":
        record["reflectance"] = color("reflectance", DEFAULT_REFLECTANCE)
    elif kind in ("conductor", "roughconductor"):
        record["reflectance"] = color("specular_reflectance", 1.0)
        record["eta"], record["k"] = _conductor_index(name, spec)
    elif kind in ("dielectric", "roughdielectric"):
        record["reflectance"] = color("specular_reflectance", 1.0)
        record["transmittance"] = color("specular_transmittance", 1.0)
        record["eta"] = _eta(name, spec, BK7, differ=kind == "roughdielectric")
    else:  # plastic, roughplastic
        albedo = color("diffuse_reflectance", DEFAULT_REFLECTANCE)
        specular = color("specular_reflectance", 1.0)
        nonlinear = spec.get("nonlinear", False)
        if not isinstance(nonlinear, (bool, np.bool_)):
            raise TypeError(f"{name}['nonlinear'] must be True or False, got {nonlinear!r}")
        eta = _eta(name, spec, POLYPROPYLENE, differ=kind == "roughplastic")
        record["reflectance"], record["specular"], record["eta"] = albedo, specular, eta
        record["nonlinear"] = int(nonlinear)
        # Mitsuba's steering of samples: the tints' means
        means = float(albedo.mean()) + float(specular.mean())
        record["specular_weight"] = specular.mean() / means if means > 0 else 0.5
        if kind == "plastic":
            record["internal"] = coating.diffuse_fresnel(1.0 / eta)
        else:
            record["transmission"], record["internal"] = coating.roughplastic_tables(
                spec.get("distribution", "beckmann"), float(record["alpha"]), eta,
                layout.TRANSMISSION_TABLE)
    return record


def _conductor_index(name: str, spec) -> tuple:
    """A conductor's (eta, k): those given (Mitsuba's defaults 0 and 1), or
    the named metal's.  Mitsuba refuses a name beside eta, and leaves a k
    beside it unread, an error too."""
    material = spec.get("material", "none")
    if not isinstance(material, str):
        raise TypeError(f"{name}['material'] must be a metal's name (a string such as 'Au'), "
                        f"got {type(material).__name__}")
    if material == "none":
        return (inputs.color(f"{name}['eta']", spec.get("eta", 0.0), CONDUCTOR_INDEX_MAX),
                inputs.color(f"{name}['k']", spec.get("k", 1.0), CONDUCTOR_INDEX_MAX))
    if material not in METALS:
        cased = [known for known in METALS if known.lower() == material.lower()]
        hint = f" (names are case-sensitive: {cased[0]!r}?)" if cased else ""
        raise ValueError(f"{name}['material'] = {material!r} is not a metal Mitsuba names{hint}; "
                         f"the names are 'none' (a perfect mirror) and {', '.join(METALS)}")
    given = [key for key in ("eta", "k") if key in spec]
    if given:
        raise ValueError(f"{name}: give either the material {material!r} or eta and k, not "
                         f"both (it also has {' and '.join(given)})")
    return METALS[material]


def _microfacet(name: str, spec, record: np.void) -> None:
    """A rough BSDF's distribution and roughness into ``record``."""
    distribution = spec.get("distribution", "beckmann")
    if not isinstance(distribution, str) or distribution not in DISTRIBUTIONS:
        raise ValueError(f"{name}['distribution'] must be one of {tuple(DISTRIBUTIONS)}, got "
                         f"{distribution!r} (Mitsuba's default is 'beckmann')")
    record["distribution"] = DISTRIBUTIONS[distribution]
    record["alpha"] = inputs.number(f"{name}['alpha']", spec.get("alpha", DEFAULT_ALPHA),
                                    1e-4, 1.0)


def _eta(name: str, spec, inside_default: float, differ: bool) -> float:
    """int_ior / ext_ior, each a number > 0; ``differ``: a rough interface
    of equal indices is refused, as Mitsuba refuses it."""
    inside = inputs.number(f"{name}['int_ior']", spec.get("int_ior", inside_default), 0.0,
                           _LARGE, low_open=True)
    outside = inputs.number(f"{name}['ext_ior']", spec.get("ext_ior", AIR), 0.0, _LARGE,
                            low_open=True)
    if differ and inside == outside:
        raise ValueError(f"{name}: int_ior and ext_ior are both {inside}: a rough interface "
                         "needs two different indices")
    ratio = inside / outside
    if not 1.0 / RELATIVE_INDEX_MAX <= ratio <= RELATIVE_INDEX_MAX:
        raise ValueError(f"{name}: int_ior / ext_ior = {inside:g} / {outside:g} = {ratio:.3g}, "
                         f"outside [{1.0 / RELATIVE_INDEX_MAX:g}, {RELATIVE_INDEX_MAX:g}]: "
                         "float32 radiance cannot take its square or inverse square (real "
                         "interfaces lie within 0.1 to 10)")
    return ratio


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
                         "geometries: one material per mesh, then per sphere (geom_id order)")
    for i, spec in enumerate(materials):
        table[i] = _bsdf(f"materials[{i}]", spec)
    return table


def instance_material_table(instance_materials, instance_meshes) -> tuple[np.ndarray, np.ndarray]:
    """Renderer.instance_materials (None, or a sequence with one entry per
    instance: None for its mesh's material, else a material spec) ->
    (PathMaterial records of the instances that have their own, with no
    emission yet; int32 per instance: its row among those records, -1 for
    its mesh's).  ``instance_meshes``: the scene's mesh per instance (None
    for a scene without instances)."""
    if instance_materials is None:
        count = 0 if instance_meshes is None else len(instance_meshes)
        return np.zeros(0, layout.PATH_MATERIAL), np.full(count, -1, np.int32)
    if instance_meshes is None:
        raise ValueError("instance_materials is for a scene with instances "
                         "(Scene(meshes, instances=...)); this scene has none: give each "
                         "mesh its material in materials")
    if isinstance(instance_materials, (str, bytes, Mapping)) \
            or not isinstance(instance_materials, Sequence):
        raise TypeError("instance_materials must be a list with one entry per instance (None: "
                        f"its mesh's material), got {type(instance_materials).__name__}")
    if len(instance_materials) != len(instance_meshes):
        raise ValueError(f"instance_materials has {len(instance_materials)} entries but the "
                         f"scene has {len(instance_meshes)} instances: one per instance "
                         "(None: its mesh's material)")
    rows = np.full(len(instance_meshes), -1, np.int32)
    own = [k for k, spec in enumerate(instance_materials) if spec is not None]
    table = np.zeros(len(own), layout.PATH_MATERIAL)
    for row, k in enumerate(own):
        table[row] = _bsdf(f"instance_materials[{k}]", instance_materials[k])
        rows[k] = row
    return table, rows
