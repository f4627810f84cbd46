"""Mitsuba 3's XML scene format, a documented subset, read into a
SceneDescription (hlbvh_cl.io.description) that renders with the path
integrator as Mitsuba would render the file.

The subset::

    <scene version="3.0.0">
      <default name="spp" value="64"/>            $spp substitutions
      <integrator type="path">                      max_depth (default -1), rr_depth (5)
      <sensor type="perspective">                   fov (deg), fov_axis (x, y, diagonal,
        <transform name="to_world">...</transform>  smaller, larger; default x), or
                                                    focal_length ("50mm" where neither is
                                                    given), to_world, near_clip, far_clip
                                                    (0.01, 10000)
        <film type="hdrfilm">                       width, height (768 x 576)
          <rfilter type="box"/>                     box or gaussian (the default)
        <sampler type="independent">                sample_count (default 4), seed (the
                                                    render's, modulo 65536)
      <bsdf type="..." id="...">                    diffuse, conductor, roughconductor,
                                                    dielectric, roughdielectric, plastic,
                                                    roughplastic, twosided; named or inline
      <shape type="...">                            ply, obj (filename, face_normals),
                                                    rectangle, cube, sphere (center, radius);
        <transform name="to_world">                 translate, rotate, scale, matrix, lookat
        <ref id="..."/>  or an inline <bsdf>
        <emitter type="area">                       radiance
      <emitter type="...">                          point (position or to_world, intensity),
                                                    directional (direction, irradiance),
                                                    constant (radiance), envmap (filename,
                                                    relative to the file's folder; scale;
                                                    to_world, a rotation); a value
                                                    left out is Mitsuba's 1, a point
                                                    light's position the origin, a
                                                    directional light's direction +z

Values: rgb, float, integer, string, boolean and point, and ref.  Anything
else, an element, an attribute or a parameter, is an error naming it and
its line: the loader never renders a silently different scene.  What
Mitsuba refuses is refused (a value, child or id given twice, a light placed
by both a vector and to_world, depths out of range, an unknown index name),
and so is what Mitsuba would render otherwise (pixel formats other than
rgb, a shearing camera, a stretched or mirrored sphere, a rotate about an
axis that is not a unit vector, max_depth 0).  Mitsuba's rules
hold elsewhere: the first <default> of a name wins from its line on, a
default the caller gives must be used, a <lookat> without up takes
Mitsuba's, and of several sensors the first frames the render (as
mi.render takes sensors()[0]); no <integrator> renders with path's
defaults.  Mesh shapes shade as
Mitsuba's: with the file's vertex normals, or ones computed as Mitsuba
computes them (hlbvh_cl.mesh.vertex_normals), after to_world; with each
triangle's own normal where face_normals is true.
"""
from __future__ import annotations

import copy
import math
import os
import re
import xml.parsers.expat
from collections.abc import Collection
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..mesh import Mesh, unit_rows
from ..render.camera import FOV_AXES, MAX_IMAGE_SIDE, Camera, vertical_fov_deg
from ..render.light import Light
from ..render.materials import BSDFS, check_material
from ..render.settings import MAX_DEPTH, MAX_RR_DEPTH, MAX_SEED, MAX_SPP
from .description import MeshEntry, SceneDescription, SceneFileError, shape_mesh

#: Mitsuba's defaults that the subset uses.
FILM_SIZE = (768, 576)
SAMPLE_COUNT = 4
NEAR_CLIP, FAR_CLIP = 0.01, 10000.0

#: Named indices of refraction Mitsuba accepts for int_ior and ext_ior: its
#: whole table (include/mitsuba/render/ior.h), no name it lacks.
IORS = {"vacuum": 1.0, "helium": 1.000036, "hydrogen": 1.000132, "air": 1.000277,
        "carbon dioxide": 1.00045, "water": 1.3330, "acetone": 1.36, "ethanol": 1.361,
        "carbon tetrachloride": 1.461, "glycerol": 1.4729, "benzene": 1.501,
        "silicone oil": 1.52045, "bromine": 1.661, "water ice": 1.31, "fused quartz": 1.458,
        "pyrex": 1.470, "acrylic glass": 1.49, "polypropylene": 1.49, "bk7": 1.5046,
        "sodium chloride": 1.544, "amber": 1.55, "pet": 1.5750, "diamond": 2.419}

_VALUE_TAGS = ("rgb", "float", "integer", "string", "boolean", "point", "vector", "transform",
               "ref", "bsdf", "emitter", "rfilter", "film", "sampler")

#: The plugin types read, and the parameters each takes: the BSDFs are
#: materials.py's (twosided's inner BSDF is an element, not a parameter).
_BSDFS = {kind: () if kind == "twosided" else params for kind, params in BSDFS.items()}
#: Mitsuba's sample_visible: its rough BSDFs sample D(m) cos(m) with false.
#: Ours always sample visible normals; either way the estimate is the same
#: and only its noise differs, so both values are read.
_BSDFS.update({kind: params + ("sample_visible",) for kind, params in _BSDFS.items()
               if "distribution" in params})
_EMITTERS = {"area": ("radiance",), "point": ("position", "intensity", "to_world"),
             "directional": ("direction", "irradiance", "to_world"), "constant": ("radiance",),
             "envmap": ("filename", "scale", "to_world")}
_SHAPES = {"ply": ("filename", "face_normals", "to_world", "flip_normals"),
           "obj": ("filename", "face_normals", "to_world", "flip_normals"),
           "rectangle": ("to_world", "face_normals", "flip_normals"),
           "cube": ("to_world", "face_normals", "flip_normals"),
           "sphere": ("to_world", "center", "radius", "flip_normals")}

#: The value elements each parameter takes, as Mitsuba's properties are
#: typed (a float also takes an integer, a colour a number); the values
#: themselves are checked by materials.check_material for the BSDFs'.
_NUMBER, _COLOUR = ("float", "integer"), ("rgb", "float", "integer")
_TAGS = {**{name: ("integer",) for name in ("max_depth", "rr_depth", "sample_count", "seed",
                                            "width", "height")},
         **{name: _NUMBER for name in ("fov", "near_clip", "far_clip", "radius", "scale")},
         **{name: ("string",) for name in ("fov_axis", "focal_length", "filename",
                                           "pixel_format", "component_format")},
         **{name: ("boolean",) for name in ("face_normals", "flip_normals")},
         **{name: _COLOUR for name in ("radiance", "intensity", "irradiance", "reflectance",
                                       "diffuse_reflectance", "specular_reflectance",
                                       "specular_transmittance", "eta", "k")},
         **{name: ("string",) for name in ("distribution", "material")},
         **{name: _NUMBER + ("string",) for name in ("int_ior", "ext_ior")},
         "alpha": _NUMBER, "nonlinear": ("boolean",), "sample_visible": ("boolean",),
         **{name: ("point", "vector") for name in ("center", "position", "direction")},
         "to_world": ("transform",)}

#: The attributes each element takes (Mitsuba refuses any other, so a typo
#: such as <translate X="5"/> is an error, not a step of 0).
_OBJECT_ATTRIBUTES = ("type", "id", "name")
_ATTRIBUTES = {"scene": ("version",), "default": ("name", "value"),
               **{tag: _OBJECT_ATTRIBUTES for tag in ("integrator", "sensor", "film", "sampler",
                                                      "rfilter", "bsdf", "shape", "emitter")},
               **{tag: ("name", "value") for tag in ("float", "integer", "string", "boolean",
                                                     "rgb")},
               **{tag: ("name", "value", "x", "y", "z") for tag in ("point", "vector")},
               "transform": ("name",), "ref": ("id", "name"),
               **{tag: ("value", "x", "y", "z") for tag in ("translate", "scale")},
               "rotate": ("value", "x", "y", "z", "angle"), "matrix": ("value",),
               "lookat": ("origin", "target", "up")}

#: The largest <lookat> coordinate: squared norms of its frame stay finite;
#: and its view (target - origin), its up and their cross at least
#: 1 / LOOKAT_RANGE long, so that they do not vanish squared.
LOOKAT_RANGE = 1e150

#: The pixel and component formats of an hdrfilm that the image we return
#: is (RGB, float32; Mitsuba's default stores float16, which only the
#: file's precision changes).
PIXEL_FORMATS, COMPONENT_FORMATS = ("rgb",), ("float16", "float32")


@dataclass
class _Node:
    tag: str
    attributes: dict
    line: int
    children: list = field(default_factory=list)
    column: int = 0  # (line, column): where the element starts, in document order

    def get(self, key, default=None):
        return self.attributes.get(key, default)


#: Elements nested deeper than this are refused: the reader walks the tree
#: recursively (a <scene>'s <shape> holds a <bsdf>, a twosided <bsdf> one
#: more, and a <texture> or <transform> its own: a real scene nests a few
#: deep), and 1000 nested <bsdf> had ended in Python's RecursionError.
MAX_NESTING = 64


def _parse(path: Path) -> _Node:
    """The XML as a tree of _Node, each with its line (expat)."""
    root = _Node("document", {}, 0)
    stack = [root]
    parser = xml.parsers.expat.ParserCreate()

    def start(tag, attributes):
        node = _Node(tag, dict(attributes), parser.CurrentLineNumber,
                     column=parser.CurrentColumnNumber)
        if len(stack) > MAX_NESTING:
            raise SceneFileError(f"{path}:{node.line}: <{tag}> is nested {len(stack)} elements "
                                 f"deep; this reader takes {MAX_NESTING} at most")
        stack[-1].children.append(node)
        stack.append(node)

    def end(tag):
        stack.pop()
    parser.StartElementHandler, parser.EndElementHandler = start, end
    try:
        parser.Parse(path.read_bytes(), True)
    except xml.parsers.expat.ExpatError as error:
        raise SceneFileError(f"{path}: not well-formed XML: {error}") from None
    if len(root.children) != 1 or root.children[0].tag != "scene":
        raise SceneFileError(f"{path}: expected one <scene> element at the top")
    return root.children[0]


def _parsed(kind, text: str):
    """float(text) or int(text) of what Mitsuba reads as a number: not
    Python's digit separators (float("0_5") is 5.0), other scripts' digits
    (int("١٦") is 16) or a signed integer's "+" (Mitsuba refuses "+16")."""
    if "_" in text or not text.isascii() or (kind is int and text.strip().startswith("+")):
        raise ValueError(text)
    return kind(text)


class _Reader:
    def __init__(self, path: Path, scene: _Node, overrides: dict):
        self.path = path
        # Mitsuba's: the first <default> of a name holds, from its line on
        # (a use above it is an error), and an override holds everywhere
        self.defaults: dict[str, str] = {}
        self.default_nodes: dict[str, _Node] = {}
        self.ids: dict[str, _Node] = {}
        for node in scene.children:
            if node.tag == "default":
                name, value = node.get("name"), node.get("value")
                if name is None or value is None:
                    raise self.error(node, "needs a name and a value attribute")
                if name not in self.defaults:
                    self.defaults[name] = value
                    self.default_nodes[name] = node
        self.overrides = {name: str(value) for name, value in overrides.items()}
        self.defaults.update(self.overrides)
        self.used: set[str] = set()

    def check_attributes(self, node: _Node) -> None:
        """Every element under ``node`` has only the attributes it takes,
        and a vector's value or its x, y, z, not both."""
        allowed = _ATTRIBUTES.get(node.tag)
        if allowed is not None:
            for key in node.attributes:
                if key not in allowed:
                    raise self.error(node, f"takes the attributes {', '.join(allowed)}, "
                                           f"not {key!r}")
            if node.get("value") is not None and any(node.get(a) is not None for a in "xyz"):
                raise self.error(node, "give either its value or x, y, z, not both")
        for child in node.children:
            self.check_attributes(child)

    def error(self, node: _Node, message: str) -> SceneFileError:
        return SceneFileError(f"{self.path}:{node.line}: <{node.tag}"
                              + (f" type=\"{node.get('type')}\"" if node.get("type") else "")
                              + (f" name=\"{node.get('name')}\"" if node.get("name") else "")
                              + f">: {message}")

    def text(self, node: _Node, key: str = "value") -> str:
        value = node.get(key)
        if value is None:
            raise self.error(node, f"needs a {key} attribute")
        return re.sub(r"\$(\w+)", lambda m: self._default(node, m.group(1)), value)

    def shown(self, node: _Node, key: str = "value") -> str:
        """Attribute ``key`` as written, with what its $names made of it."""
        raw, text = node.get(key), self.text(node, key)
        return repr(raw) if text == raw else f"{raw!r} (= {text!r})"

    def _default(self, node: _Node, name: str) -> str:
        if name not in self.defaults:
            raise self.error(node, f"${name} has no <default name=\"{name}\">")
        default = self.default_nodes.get(name)
        if name not in self.overrides and (default.line, default.column) > (node.line,
                                                                            node.column):
            raise self.error(node, f"${name} is used above its <default name=\"{name}\"> "
                                   f"(line {default.line})")
        self.used.add(name)
        return self.defaults[name]

    def number(self, node: _Node, key: str = "value") -> float:
        """The finite number in attribute ``key``."""
        text = self.text(node, key)
        which = "" if key == "value" else f" for {key}"
        try:
            value = _parsed(float, text)
        except ValueError:
            raise self.error(node, f"expected a number{which}, "
                                   f"got {self.shown(node, key)}") from None
        if not math.isfinite(value):
            raise self.error(node, f"expected a finite number{which}, "
                                   f"got {self.shown(node, key)}")
        return value

    def numbers(self, node: _Node, count: int, key: str = "value") -> list[float]:
        parts = re.split(r"[,\s]+", self.text(node, key).strip())  # (text raises first)
        try:
            values = [_parsed(float, x) for x in parts if x]
        except ValueError:
            raise self.error(node, f"expected {count} numbers, "
                                   f"got {self.shown(node, key)}") from None
        if len(values) == 1 and count == 3 and key == "value":
            values *= 3  # Mitsuba's: one value for all three (not a lookat's)
        if len(values) != count or not all(math.isfinite(v) for v in values):
            raise self.error(node, f"expected {count} finite numbers, "
                                   f"got {self.shown(node, key)}")
        return values

    def _coordinate(self, node: _Node, axis: str, default: float) -> float:
        """The number in attribute ``axis`` (x, y or z), or ``default``."""
        return default if node.get(axis) is None else self.number(node, axis)

    def value(self, node: _Node):
        """A parameter's value: float, int, str, bool, RGB list, point."""
        if node.tag == "float":
            return self.number(node)
        if node.tag == "integer":
            text = self.text(node)
            try:
                return _parsed(int, text)
            except ValueError:
                raise self.error(node, f"expected an integer, got {self.shown(node)}") from None
        if node.tag == "string":
            return self.text(node)
        if node.tag == "boolean":
            text = self.text(node).lower()
            if text not in ("true", "false"):
                raise self.error(node, f"expected true or false, got {node.get('value')!r}")
            return text == "true"
        if node.tag == "rgb":
            return self.numbers(node, 3)
        if node.tag in ("point", "vector"):
            if node.get("value") is not None:
                return self.numbers(node, 3)
            for axis in "xyz":  # Mitsuba's: all three (a step's may be left out)
                if node.get(axis) is None:
                    raise self.error(node, f"needs its value, or x, y and z: {axis} is missing")
            return [self.number(node, axis) for axis in "xyz"]
        if node.tag == "transform":
            return self.transform(node)
        raise self.error(node, "is not a value this reader takes (rgb, float, integer, string, "
                               "boolean, point, transform)")

    def parameters(self, node: _Node, known: tuple, skip=()) -> dict:
        """The named values inside ``node``: every child with a name must be
        one of ``known``; children that are not values must be in ``skip``."""
        found = {}
        for child in node.children:
            if child.tag in skip:
                continue
            if child.tag not in _VALUE_TAGS or child.get("name") is None:
                raise self.error(child, f"is not read inside <{node.tag} "
                                        f"type=\"{node.get('type')}\"> (line {node.line})")
            name = child.get("name")
            if name not in known:
                raise self.error(child, f"{node.get('type')} takes {known or 'no parameters'}, "
                                        f"not {name!r}")
            tags = _TAGS.get(name)
            if tags is not None and child.tag not in tags:
                raise self.error(child, f"{name} takes <{'>, <'.join(tags)}>, not <{child.tag}>")
            if name in found:
                raise self.error(child, f"{name} is given twice in <{node.tag} "
                                        f"type=\"{node.get('type')}\"> (line {node.line})")
            found[name] = self.value(child)
        return found

    def transform(self, node: _Node) -> np.ndarray:
        """A <transform>'s 4 x 4 matrix: each step applied after the ones
        before it, as Mitsuba composes them."""
        matrix = np.eye(4)
        for step in node.children:
            try:
                change = self._step(step)
            except SceneFileError:
                raise
            except (ValueError, TypeError, ZeroDivisionError) as error:
                raise self.error(step, f"expected numbers: {error}") from None
            matrix = change @ matrix
        return matrix

    def _step(self, step: _Node) -> np.ndarray:
        """One step of a <transform> as a 4 x 4 matrix."""
        if step.tag == "translate":
            offset = (self.numbers(step, 3) if step.get("value") is not None else
                      [self._coordinate(step, a, 0.0) for a in "xyz"])
            change = np.eye(4)
            change[:3, 3] = offset
        elif step.tag == "scale":
            if step.get("value") is not None:
                parts = re.split(r"[,\s]+", self.text(step).strip())
                factors = [self.number(step)] * 3 if len(parts) == 1 else self.numbers(step, 3)
            else:
                factors = [self._coordinate(step, a, 1.0) for a in "xyz"]
            change = np.diag([*factors, 1.0])
        elif step.tag == "rotate":
            axis = (self.numbers(step, 3, "value") if step.get("value") is not None else
                    [self._coordinate(step, a, 0.0) for a in "xyz"])
            if not math.isclose(float(np.linalg.norm(axis)), 1.0, rel_tol=1e-5):
                # Mitsuba builds a longer axis's matrix (which then scales) but
                # keeps its transpose as its inverse, so it shades with normals
                # that are not the surface's
                raise self.error(step, f"its axis must be a unit vector, got length "
                                       f"{np.linalg.norm(axis):g}")
            change = _rotation(np.array(axis), self.number(step, "angle"))
        elif step.tag == "matrix":
            parts = [x for x in re.split(r"[,\s]+", self.text(step).strip()) if x]
            change = np.eye(4)
            if len(parts) == 9:  # Mitsuba's 3 x 3 form: the linear part alone
                change[:3, :3] = np.array(self.numbers(step, 9)).reshape(3, 3)
            else:
                change = np.array(self.numbers(step, 16)).reshape(4, 4)
            if not np.array_equal(change[3], [0.0, 0.0, 0.0, 1.0]):
                raise self.error(step, f"the last row must be 0 0 0 1 (an affine map), got "
                                       f"{' '.join(f'{x:g}' for x in change[3])}")
        elif step.tag == "lookat":
            origin, target = self.numbers(step, 3, "origin"), self.numbers(step, 3, "target")
            if max(map(abs, origin + target)) > LOOKAT_RANGE:  # the frame's norms overflow past it
                raise self.error(step, f"its origin and target must lie within "
                                       f"{LOOKAT_RANGE:g} of 0, got {self.shown(step, 'origin')} "
                                       f"and {self.shown(step, 'target')}")
            view = np.subtract(target, origin)
            if not np.any(view):
                raise self.error(step, "its target is its origin: no direction to look in")
            if np.abs(view).max() < 1.0 / LOOKAT_RANGE:
                raise self.error(step, f"its target lies within {1.0 / LOOKAT_RANGE:g} of its "
                                       f"origin: too close to give a direction to look in")
            up = self.numbers(step, 3, "up") if step.get("up") else _default_up(view)
            if max(map(abs, up)) > LOOKAT_RANGE:
                raise self.error(step, f"its up must lie within {LOOKAT_RANGE:g} of 0, got "
                                       f"{self.shown(step, 'up')}")
            if not np.any(np.cross(up, view)):
                raise self.error(step, "its up is parallel to the direction it looks in")
            left = np.cross(up, view / np.linalg.norm(view))  # as _look_at makes it
            if not np.linalg.norm(left) >= 1.0 / LOOKAT_RANGE:
                raise self.error(step, f"its up ({self.shown(step, 'up')}) is too short, or too "
                                       f"near the direction it looks in, to make a frame: "
                                       f"their cross is under {1.0 / LOOKAT_RANGE:g} long")
            change = _look_at(np.array(origin), np.array(target), np.array(up))
        else:
            raise self.error(step, "is not a transform step this reader takes (translate, "
                                   "rotate, scale, matrix, lookat)")
        return change


def _rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    """Rodrigues' rotation about the unit ``axis`` as Mitsuba builds it."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    x, y, z = axis
    out = np.eye(4)
    out[:3, :3] = [[c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
                   [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
                   [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)]]
    return out


def _default_up(view) -> list[float]:
    """The up Mitsuba's <lookat> takes where none is given: the first
    vector of its coordinate_system around the unit view direction (Duff et
    al. 2017, "Building an Orthonormal Basis, Revisited")."""
    x, y, z = np.asarray(view, np.float64) / np.linalg.norm(view)
    sign = math.copysign(1.0, z)
    a = -1.0 / (sign + z)
    return [1.0 + sign * x * x * a, sign * x * y * a, -sign * x]


def _look_at(origin, target, up) -> np.ndarray:
    """Mitsuba's look_at: columns left, up, direction, origin."""
    direction = (target - origin) / np.linalg.norm(target - origin)
    left = np.cross(up, direction)
    left /= np.linalg.norm(left)
    new_up = np.cross(direction, left)
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2], out[:3, 3] = left, new_up, direction, origin
    return out


def read_xml(path, defaults: dict | None = None,
             replaced: Collection[str] = ()) -> SceneDescription:
    """A Mitsuba 3 XML scene (the module's subset) as a SceneDescription,
    with its render options (shading "path", spp, max_depth, rr_depth,
    rfilter) in ``options``; ``defaults`` override its <default> values,
    as mitsuba.load_file's keyword arguments do.  ``replaced`` names the
    values the caller renders with its own ("spp", "max_depth", "width",
    "height": the CLI's flags): those may exceed this renderer's limits
    (Mitsuba's are wider), as long as they are values Mitsuba reads."""
    path = Path(os.fspath(path))
    scene = _parse(path)
    reader = _Reader(path, scene, defaults or {})
    if scene.get("version") is None:
        raise reader.error(scene, "needs its version attribute (e.g. version=\"3.0.0\"), "
                                  "as Mitsuba does")
    if not re.fullmatch(r"3\.\d+\.\d+", scene.get("version")):
        # Mitsuba 3 renames an older file's parameters as it loads it; this
        # reader does not, so it reads version 3 files only
        raise reader.error(scene, f"version {scene.get('version')!r}: this reader reads "
                                  f"Mitsuba 3 files (version=\"3.x.y\")")
    _substitute_names(reader, scene)
    reader.check_attributes(scene)
    _collect_ids(reader, scene)
    options = {"shading": "path", "spp": SAMPLE_COUNT, "max_depth": -1, "rr_depth": 5,
               "rfilter": "gaussian"}
    camera, size, fov = None, FILM_SIZE, None
    meshes, emitters, emitter_names = [], [], []
    integrator = None
    for node in scene.children:
        if node.tag == "default":
            continue
        if node.tag == "integrator":
            if integrator is not None:
                raise reader.error(node, f"a second <integrator> (the first is on line "
                                         f"{integrator.line})")
            integrator = node
            if node.get("type") != "path":
                raise reader.error(node, "only the path integrator is read")
            values = reader.parameters(node, ("max_depth", "rr_depth"))
            highest = _INT32_MAX if "max_depth" in replaced else MAX_DEPTH
            if not -1 <= values.get("max_depth", -1) <= highest:
                raise reader.error(node, f"max_depth must be -1 (no limit) or 1..{highest}, "
                                         f"got {values['max_depth']}")
            if values.get("max_depth") == 0:
                raise reader.error(node, "max_depth 0 (an image of nothing, in Mitsuba) is not "
                                         "rendered here: give -1 (no limit) or 1 and more")
            # past every bounce a path takes, roulette never starts: Mitsuba's
            # render, whatever the value (its rr_depth is an int32 too)
            if not 1 <= values.get("rr_depth", 1) <= MAX_RR_DEPTH:
                raise reader.error(node, f"rr_depth must be 1..{MAX_RR_DEPTH}, got "
                                         f"{values['rr_depth']}")
            options.update({k: int(v) for k, v in values.items()})
        elif node.tag == "sensor":
            # every sensor is read (and checked); a render takes the first, as
            # Mitsuba's mi.render(scene) takes sensors()[0]
            found = _sensor(reader, node, options if camera is None else dict(options),
                            replaced)
            if camera is None:
                camera, size, fov = found
        elif node.tag == "bsdf":
            _bsdf(reader, node)  # checked here; used where a shape refers to it
        elif node.tag == "shape":
            meshes.append(_shape(reader, node))
        elif node.tag == "emitter":
            emitters.append(_emitter(reader, node))
            emitter_names.append(_emitter_name(reader, node))
        else:
            raise reader.error(node, "is not an element this reader takes (integrator, sensor, "
                                     "bsdf, shape, emitter, default)")
    if meshes and all(entry.sphere is not None for entry in meshes):
        # a Scene holds at least one mesh: a file of spheres alone has them
        # traced as their icospheres (5,120 triangles each), as before they
        # were analytic
        meshes = [replace(entry, sphere=None) for entry in meshes]
    from ..render.emitters import check_emitters
    try:  # together: one environment at most
        check_emitters(emitters, 0, names=emitter_names)
    except (TypeError, ValueError) as error:
        raise SceneFileError(str(error)) from None
    unused = sorted(set(reader.overrides) - reader.used)
    if unused:
        raise SceneFileError(f"{path}: defaults given that the file never uses (no $name): "
                             f"{', '.join(unused)}")
    if camera is None:
        raise SceneFileError(f"{path}: no <sensor>: the scene needs a camera")
    if not meshes:
        raise SceneFileError(f"{path}: no <shape>: nothing to render")
    return SceneDescription(path=path, width=size[0], height=size[1], camera=camera,
                            light=Light(), meshes=meshes, emitters=emitters, options=options,
                            sensor_fov=fov, default_sky=False)  # Mitsuba: no emitter, black


def _collect_ids(reader: _Reader, node: _Node) -> None:
    """Every element's id, each once (Mitsuba refuses a duplicate); a <ref>'s
    id names another's."""
    for child in node.children:
        name = child.get("id")
        if name is not None and child.tag != "ref":
            if name in reader.ids:
                raise reader.error(child, f"id {name!r} is already the id of the element on "
                                          f"line {reader.ids[name].line}")
            reader.ids[name] = child
        _collect_ids(reader, child)


def _one_each(reader: _Reader, node: _Node, tags: tuple) -> None:
    """At most one child of each tag in ``tags`` inside ``node``."""
    seen: dict[str, _Node] = {}
    for child in node.children:
        key = "bsdf" if child.tag == "ref" else child.tag
        if key in tags:
            if key in seen:
                raise reader.error(child, f"a second <{key}> inside <{node.tag}> (the first is "
                                          f"on line {seen[key].line})")
            seen[key] = child


#: The largest values Mitsuba reads where a caller replaces this renderer's
#: (read_xml's ``replaced``): its film sizes and sample counts are uint32,
#: its depths int.
_UINT32_MAX = 2**32 - 1
_INT32_MAX = 2**31 - 1


def _sensor(reader: _Reader, node: _Node, options: dict, replaced: Collection[str]):
    if node.get("type") != "perspective":
        raise reader.error(node, "only the perspective sensor is read")
    values = reader.parameters(node, ("fov", "fov_axis", "focal_length", "to_world",
                                      "near_clip", "far_clip"), skip=("film", "sampler"))
    size = FILM_SIZE
    _one_each(reader, node, ("film", "sampler"))
    for child in node.children:
        if child.tag == "film":
            if child.get("type") != "hdrfilm":
                raise reader.error(child, "only the hdrfilm film is read")
            film = reader.parameters(child, ("width", "height", "pixel_format",
                                             "component_format"), skip=("rfilter",))
            size = (film.get("width", FILM_SIZE[0]), film.get("height", FILM_SIZE[1]))
            for name, side in zip(("width", "height"), size):
                highest = _UINT32_MAX if name in replaced else MAX_IMAGE_SIDE
                if not 1 <= side <= highest:
                    raise reader.error(child, f"width and height must be 1..{highest}, got "
                                              f"{size[0]} x {size[1]}")
            for key, formats in (("pixel_format", PIXEL_FORMATS),
                                 ("component_format", COMPONENT_FORMATS)):
                if film.get(key, formats[0]) not in formats:
                    raise reader.error(child, f"{key} {film[key]!r} is not read (this reader "
                                              f"renders {' or '.join(formats)})")
            _one_each(reader, child, ("rfilter",))
            for kid in child.children:
                if kid.tag == "rfilter":
                    if kid.get("type") not in ("box", "gaussian"):
                        raise reader.error(kid, "only the box and gaussian filters are read")
                    reader.parameters(kid, ())
                    options["rfilter"] = kid.get("type")
        elif child.tag == "sampler":
            if child.get("type") != "independent":
                raise reader.error(child, "only the independent sampler is read")
            sampler = reader.parameters(child, ("sample_count", "seed"))
            options["spp"] = int(sampler.get("sample_count", SAMPLE_COUNT))
            highest = _UINT32_MAX if "spp" in replaced else MAX_SPP
            if not 1 <= options["spp"] <= highest:
                raise reader.error(child, f"sample_count must be 1..{highest}, got "
                                          f"{options['spp']}")
            if "seed" in sampler:  # the render's seed (Renderer.render's)
                if sampler["seed"] < 0:  # Mitsuba's is a size_t
                    raise reader.error(child, f"seed must be >= 0, got {sampler['seed']}")
                # a render's seeds are 16 bits (render.settings); Mitsuba's any size
                options["seed"] = sampler["seed"] % (MAX_SEED + 1)
    if "fov" in values and "focal_length" in values:
        raise reader.error(node, "give either its fov or its focal_length, not both")
    if "fov" not in values:  # Mitsuba's parse_fov: a focal length, 50mm unless given
        if "fov_axis" in values:  # Mitsuba leaves it unread, and refuses the file
            raise reader.error(node, "fov_axis applies to a fov; without one the sensor's "
                                     "focal_length gives the field of view along the diagonal")
        values["fov"], values["fov_axis"] = _focal_fov(reader, node,
                                                       values.get("focal_length", "50mm"))
    if not 0 < values["fov"] < 180:
        raise reader.error(node, f"fov must be between 0 and 180 degrees, got {values['fov']:g}")
    matrix = values.get("to_world", np.eye(4))
    if np.linalg.det(matrix[:3, :3]) < 0:  # look_at's frame (left, up, direction) has det 1
        raise reader.error(node, "a to_world that mirrors the image (det < 0) is not read")
    eye, forward, up = matrix[:3, 3], matrix[:3, 2], matrix[:3, 1]
    width, height = size
    axis = values.get("fov_axis", "x")
    if axis not in FOV_AXES:
        raise reader.error(node, f"fov_axis {axis!r} is not one of {FOV_AXES}")
    fov_deg = vertical_fov_deg(values["fov"], axis, width / height)
    # a to_world that scales is refused, as Mitsuba refuses it: the clip
    # distances are then the same in the world
    if not np.allclose(matrix[:3, :3].T @ matrix[:3, :3], np.eye(3), rtol=0, atol=1e-5):
        raise reader.error(node, "its to_world scales or shears (a scale step, or a matrix "
                                 "whose columns are not orthonormal), which a camera may not")
    near, far = values.get("near_clip", NEAR_CLIP), values.get("far_clip", FAR_CLIP)
    if not 0 < near < far:
        raise reader.error(node, f"needs 0 < near_clip < far_clip, got {near:g} and {far:g}")
    try:
        camera = Camera(tuple(eye), tuple(eye + forward), tuple(up), fov_deg=fov_deg,
                        near_clip=near, far_clip=far)
    except ValueError as error:
        raise reader.error(node, f"its to_world makes no camera: {error}") from None
    return camera, size, (values["fov"], axis)


def _substitute_names(reader: _Reader, node: _Node) -> None:
    """The $names in every element's type, id and name attributes (a
    value's are read where it is), as Mitsuba substitutes them in every
    attribute: <bsdf type="$t">."""
    for child in node.children:
        if child.tag != "default":
            for key in ("type", "id", "name"):
                if "$" in (child.get(key) or ""):
                    child.attributes[key] = reader.text(child, key)
            _substitute_names(reader, child)


def _focal_fov(reader: _Reader, node: _Node, focal_length: str) -> tuple[float, str]:
    """The diagonal field of view (degrees, "diagonal") of a lens of
    ``focal_length`` ("<x>mm", or x alone, as Mitsuba reads it) on a 35 mm
    film frame of 36 x 24 mm, as Mitsuba's parse_fov gives it when a sensor
    has no fov."""
    text = focal_length[:-2] if focal_length.endswith("mm") else focal_length
    try:
        value = _parsed(float, text)
    except ValueError:
        value = math.nan
    fov = 2.0 * math.degrees(math.atan(math.hypot(36.0, 24.0) / (2.0 * value))) \
        if math.isfinite(value) and value > 0 else math.nan
    if not 0 < fov < 180:  # a length so short that the view is flat is refused too
        raise reader.error(node, f"focal_length must be <x>mm with x > 0, got {focal_length!r}")
    return fov, "diagonal"


def _bsdf(reader: _Reader, node: _Node) -> dict:
    """A <bsdf> (or a <ref> to one) as a materials.py spec."""
    if node.tag == "ref":
        if node.get("id") is None:
            raise reader.error(node, "needs the id of the <bsdf> it refers to")
        target = reader.ids.get(node.get("id"))
        if target is None or target.tag != "bsdf":
            raise reader.error(node, f"refers to no <bsdf id=\"{node.get('id')}\">")
        node = target
    kind = node.get("type")
    if kind not in _BSDFS:
        raise reader.error(node, f"BSDF type {kind!r} is not read (this reader takes "
                                 f"{', '.join(_BSDFS)})")
    if kind == "twosided":
        inner = [c for c in node.children if c.tag in ("bsdf", "ref")]
        if len(inner) != 1 or len(inner) != len(node.children):
            raise reader.error(node, "twosided takes one <bsdf> (or <ref>) and nothing else")
        spec = {"type": "twosided", "bsdf": _bsdf(reader, inner[0])}
    else:
        spec = {"type": kind, **reader.parameters(node, _BSDFS[kind])}
        spec.pop("sample_visible", None)  # (_BSDFS)
        if isinstance(spec.get("distribution"), str):  # Mitsuba's names in any case
            spec["distribution"] = spec["distribution"].lower()
    for key in ("int_ior", "ext_ior"):
        if isinstance(spec.get(key), str):
            name = spec[key].lower()
            if name not in IORS:
                raise reader.error(node, f"{key} {spec[key]!r} is not a named index this reader "
                                         f"knows ({', '.join(IORS)})")
            spec[key] = IORS[name]
    try:  # (twosided too: what it may wrap)
        check_material(f"{reader.path}:{node.line}: <bsdf type=\"{kind}\">", spec)
    except (TypeError, ValueError) as error:
        raise SceneFileError(str(error)) from None
    return spec


def _shape(reader: _Reader, node: _Node) -> MeshEntry:
    kind = node.get("type")
    if kind not in _SHAPES:
        raise reader.error(node, f"shape type {kind!r} is not read (this reader takes "
                                 f"{', '.join(_SHAPES)})")
    values = reader.parameters(node, _SHAPES[kind], skip=("bsdf", "ref", "emitter"))
    _one_each(reader, node, ("bsdf", "emitter"))
    if values.get("flip_normals"):
        raise reader.error(node, "flip_normals = true is not read (false, Mitsuba's default, is)")
    if kind in ("ply", "obj"):
        if "filename" not in values:
            raise reader.error(node, "needs its filename")
        file = reader.path.parent / values["filename"]
        if file.suffix.lower() != f".{kind}":  # Mitsuba's ply and obj read their own format
            raise reader.error(node, f"{kind} shapes read .{kind} files, got {file.name}")
        try:
            mesh = Mesh.load(file)
        except FileNotFoundError:
            raise reader.error(node, f"mesh file not found: {file}") from None
        except (ValueError, TypeError) as error:
            raise reader.error(node, str(error)) from None
        declared = _ply_faces(file) if kind == "ply" else None
        if declared is not None and mesh.triangle_count > declared:
            # Mitsuba's ply reads triangles alone ("is this a triangle mesh?!")
            raise reader.error(node, f"{file.name} has faces of more than 3 corners, which "
                                     "Mitsuba's ply refuses; triangulate it")
    else:
        mesh = shape_mesh(kind)
    matrix = values.get("to_world", np.eye(4))
    if kind == "sphere":
        if values.get("radius", 1.0) < 0:
            raise reader.error(node, f"a sphere's radius must be positive, got "
                                     f"{values['radius']:g}")
        centre, radius = np.array(values.get("center", [0.0] * 3)), values.get("radius", 1.0)
        matrix = matrix @ np.array([[radius, 0, 0, centre[0]], [0, radius, 0, centre[1]],
                                    [0, 0, radius, centre[2]], [0, 0, 0, 1]])
        _check_sphere_map(reader, node, matrix[:3, :3])
    if not np.linalg.det(matrix[:3, :3]):
        raise reader.error(node, "its to_world (with its radius) is singular: it would flatten "
                                 "the shape to a plane, a line or a point")
    points = mesh.vertices.astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
    faces = mesh.faces
    # normals go by the inverse transpose; computed ones are computed anew
    # from the placed vertices, as Mitsuba computes them after to_world
    normals = unit_rows(mesh.normals.astype(np.float64) @ np.linalg.inv(matrix[:3, :3])) \
        if mesh.has_file_normals else None
    face_normals = mesh.face_normals or bool(values.get("face_normals", False))
    # A mirror turns the winding inside out, and Mitsuba 3.9.1 keeps it for a
    # file's mesh: its geometric normals and the ones it computes then point
    # inward, the file's own (by the inverse transpose) outward.  Its cube
    # and rectangle carry their own normals, outward: there the faces are
    # turned outward with them (their shading normal is the face's).  (Its
    # source after 3.9.1 flips a mirrored mesh's winding: revisit on upgrade.)
    if np.linalg.det(matrix[:3, :3]) < 0 and kind not in ("ply", "obj"):
        faces = faces[:, ::-1]
    material, emitter = None, None
    for child in node.children:
        if child.tag in ("bsdf", "ref"):
            material = _bsdf(reader, child)
        elif child.tag == "emitter":
            emitter = _emitter(reader, child, area=True)
    try:
        placed = Mesh(points, faces, name=mesh.name, normals=normals, face_normals=face_normals)
    except ValueError as error:
        raise reader.error(node, f"its to_world gives an invalid mesh: {error}") from None
    # A sphere is analytic, as Mitsuba's (Scene's spheres)
    sphere = None
    if kind == "sphere":
        radius = math.sqrt(float(np.trace(matrix[:3, :3].T @ matrix[:3, :3])) / 3)
        sphere = np.array([*matrix[:3, 3], radius], np.float64)
    if material is None:  # Mitsuba's: a diffuse of 0.5, or black for an emitter's shape
        material = {"type": "diffuse", "reflectance": 0.0 if emitter else 0.5}
    return MeshEntry(mesh=placed, color=(0.8, 0.8, 0.8),
                     path=file if kind in ("ply", "obj") else None, material=material,
                     emitter=emitter, sphere=sphere)


def _ply_faces(path: Path) -> int | None:
    """The faces a PLY file's header declares (None where it declares
    none): Mesh.load splits a polygon into triangles, so more triangles
    than this means polygons."""
    with open(path, "rb") as file:
        for line in file:
            words = line.split()
            if words[:2] == [b"element", b"face"] and len(words) == 3 and words[2].isdigit():
                return int(words[2])
            if words[:1] == [b"end_header"]:
                break
    return None


#: How far a sphere's to_world may scale its axes apart, relative to the
#: largest (_check_sphere_map): rounding, not a stretch.
SPHERE_SCALE_SPREAD = 1e-3


def _check_sphere_map(reader: _Reader, node: _Node, linear: np.ndarray) -> None:
    """A sphere's to_world (with its radius) may only rotate, move and scale
    alike on every axis: Mitsuba's sphere stays a sphere under any other
    map (it warns and keeps one radius) and turns dark inside out under a
    mirror, where the mesh would follow the map.  Scales alike to within
    SPHERE_SCALE_SPREAD pass, so that a rotation written with a few decimals
    (0.7071) is one.  A zero scale is left to the singular-map check."""
    scales = np.linalg.svd(linear, compute_uv=False)
    mirrors = np.linalg.det(linear) < 0
    if scales[0] > 0 and (mirrors or scales[-1] < (1.0 - SPHERE_SCALE_SPREAD) * scales[0]):
        how = "mirrors" if mirrors else \
            f"scales its axes by {scales[-1]:.6g} to {scales[0]:.6g}"
        raise reader.error(node, f"a sphere's to_world may rotate, translate and scale alike on "
                                 f"every axis (to within {SPHERE_SCALE_SPREAD:g}), not stretch, "
                                 f"shear or mirror it; this one {how} (Mitsuba renders a sphere "
                                 "whatever the map)")


def _emitter(reader: _Reader, node: _Node, area: bool = False) -> dict:
    kind = node.get("type")
    if kind not in _EMITTERS or (kind == "area") != area:
        where = "inside a <shape>" if area else "at the top of the scene"
        raise reader.error(node, f"emitter type {kind!r} is not read {where} (this reader "
                                 "takes area inside shapes; point, directional, constant "
                                 "and envmap at the top)")
    values = reader.parameters(node, _EMITTERS[kind])
    matrix = values.pop("to_world", None)
    if kind == "envmap":
        if "filename" in values:  # Mitsuba resolves it against the file's folder
            values["filename"] = str(reader.path.parent / values["filename"])
        if matrix is not None:
            values["to_world"] = matrix
    elif matrix is not None:
        key = "position" if kind == "point" else "direction"
        if key in values:
            raise reader.error(node, f"give either its {key} or its to_world, not both "
                                     "(Mitsuba refuses both)")
        if kind == "directional":
            # Mitsuba sends its light along to_world's z axis as mapped, not
            # normalised: a to_world that lengthens it brightens a diffuse
            # surface by that length, and other BSDFs otherwise
            length = float(np.linalg.norm(matrix[:3, 2]))
            if not math.isclose(length, 1.0, rel_tol=1e-5):
                raise reader.error(node, f"a directional light's to_world must keep its z axis "
                                         f"unit long (Mitsuba renders the light otherwise), "
                                         f"got length {length:.6g}")
        values[key] = list(matrix[:3, 3]) if kind == "point" else \
            list(matrix[:3, :3] @ [0.0, 0.0, 1.0])
    # Mitsuba's defaults: a value of 1, a point light at the origin, a
    # directional light along +z (its frame's z axis); an envmap needs its file
    spec = {"type": kind, **copy.deepcopy(_EMITTER_DEFAULTS[kind]), **values}
    if kind == "envmap" and "filename" not in spec:
        raise reader.error(node, "needs its filename")
    from ..render.emitters import check_emitters
    try:
        check_emitters([{**spec, "mesh": 0} if area else spec], 1,
                       names=[_emitter_name(reader, node)])
    except (TypeError, ValueError) as error:
        raise SceneFileError(str(error)) from None
    return spec


#: What Mitsuba 3 takes for an emitter's value or placement left out
#: (get_emissive_texture(..., 1.f); an identity to_world).
_EMITTER_DEFAULTS = {"area": {"radiance": 1.0}, "constant": {"radiance": 1.0}, "envmap": {},
                     "point": {"intensity": 1.0, "position": [0.0, 0.0, 0.0]},
                     "directional": {"irradiance": 1.0, "direction": [0.0, 0.0, 1.0]}}


def _emitter_name(reader: _Reader, node: _Node) -> str:
    return f"{reader.path}:{node.line}: <emitter type=\"{node.get('type')}\">"
