"""TOML scene files: meshes with colours and transforms, instances of them, a
ground, a camera, a light.

``read(path)`` parses one with tomllib into a SceneDescription whose meshes
are already loaded, split and transformed; ``load(path)`` also builds its
Scene and returns a LoadedScene (scene, camera, light, colours, image size).
Both also take a mesh file (``bunny.ply``: Mesh.load's formats) and make a
scene of that one mesh on a ground, framed by a camera (read_mesh).

Schema (every table and key is listed here; any other key is an error)::

    [render]                      # required
    width = 1280                  # image size in pixels, integers 1..16384
    height = 720

    [camera]                      # required; a pinhole camera
    eye = [0.0, 1.0, 4.0]         # position
    target = [0.0, 1.0, 0.0]      # point looked at
    up = [0.0, 1.0, 0.0]          # default [0, 1, 0]; must not be parallel to target - eye
    fov_deg = 45.0                # vertical field of view in degrees, 0 < fov < 180; default 45

    [light]                       # optional; the preview modes' directional light (a path
                                  # render ignores it: its lights are [[emitter]] and emitters)
    direction = [1.0, 2.0, 1.0]   # from the surface towards the light (normalised on load);
                                  # default [1, 2, 1]
    intensity = 1.0               # >= 0, default 1
    ambient = 0.15                # 0..1, default 0.15

    [ground]                      # optional; a square of two triangles facing +y
    y = "auto"                    # height: a number, or "auto" = the lowest mesh point (default)
    size = 10.0                   # side length; default 4 x the meshes' larger x/z extent.
                                  # Centred on the centre of the meshes' x/z bounds.
    color = [0.8, 0.8, 0.8]       # RGB, each 0..1; default 0.8 grey
    material = { type = "diffuse", reflectance = 0.5 }   # as a mesh's

    [[emitter]]                   # optional, any number: the path integrator's other lights
    type = "point"                # "point" (position, intensity), "directional" (direction,
    position = [0.0, 3.0, 0.0]    # irradiance), "constant" (radiance) or "envmap" (filename,
    intensity = [10.0, 10.0, 10.0]  # relative to this file; scale; to_world, a 3 x 3 or 4 x 4
                                  # rotation): Mitsuba's emitters (hlbvh_cl/render/emitters.py);
                                  # one environment (constant or envmap) at most

    [[mesh]]                      # one table per mesh, at least one; mesh[0] is the first
    path = "meshes/bunny.ply"     # relative to this TOML file (or absolute); or instead:
    shape = "rectangle"           # Mitsuba's shapes: "rectangle" ([-1, 1]^2 at z = 0, facing
                                  # +z), "cube" ([-1, 1]^3) or "sphere" (radius 1, centre 0)
    color = [0.8, 0.8, 0.8]       # RGB, each 0..1; default 0.8 grey
    material = { type = "dielectric", int_ior = 1.5 }
                                  # the path integrator's BSDF (hlbvh_cl/render/materials.py,
                                  # Mitsuba's names); default a two-sided diffuse of `color`
    emitter = { type = "area", radiance = [5.0, 5.0, 5.0] }
                                  # makes the mesh an area light (the path integrator)
    split = 1                     # cut every edge in k parts (k*k triangles each); default 1
    scale = 1.0                   # > 0: one number, or three (per axis)
    rotate_deg = [0.0, 0.0, 0.0]  # Euler angles in degrees: about x, then y, then z (fixed axes)
    fit_height = 1.0              # > 0: uniform scale so the mesh's y extent equals it
    translate = [0.0, 0.0, 0.0]
    place_on_ground = false       # move along y so the mesh's lowest point is at the ground's y
    face_normals = false          # true: shade with each triangle's own normal (Mitsuba's
                                  # face_normals); default the file's vertex normals, or
                                  # ones computed as Mitsuba does (hlbvh_cl.Mesh.normals)

    [[instance]]                  # optional, any number: copies of one mesh (Instances, below)
    mesh = 0                      # required: the [[mesh]] table drawn, counting from 0
    scale = 1.0                   # > 0: one number, or three (per axis)
    rotate_deg = [0.0, 0.0, 0.0]  # as a mesh's
    translate = [0.0, 0.0, 0.0]   # one position, or a list of them [[x, y, z], ...]: a copy at each
    grid = { count = [100, 50], spacing = [2.0, 4.0], origin = [0.0, 0.0, 0.0], jitter = 0.0 }
                                  # instead of translate: count[0] x count[1] copies (integers >= 1)
                                  # at origin + [i * spacing[0], 0, j * spacing[1]] (spacing > 0,
                                  # origin default [0, 0, 0]); jitter (0..0.5, default 0) moves
                                  # each copy by a random amount up to jitter x spacing in x and z
    random_yaw_deg = 0.0          # 0..180: turn each copy about +y by a random angle in +-it
    seed = 0                      # integer >= 0 for yaw and jitter; default the table's index
    place_on_ground = false       # set each copy's y so its lowest point is at the ground's y

A file with no emitter, in a [[mesh]] table or an [[emitter]] one, is lit
for the path integrator by a constant sky of radiance 1 (emitters.DEFAULT);
the preview modes use [light] and the colours.

Each mesh is split first, then scaled (scale, then fit_height), rotated and
translated (translate, then place_on_ground).  fit_height measures the y
extent after scale and rotation; since a uniform scale commutes with a
rotation this equals scaling first by the right factor.  place_on_ground uses
the ground's y when it is a number, and 0 when there is no ground or its y is
"auto" (the ground then sits at the lowest mesh point).

Instances: a file with no [[instance]] table draws each mesh once, where its
own keys put it.  A file with any draws only instances: each mesh, shaped
by its keys as above, is a prototype built once however many copies draw it
(a mesh no instance names is an error: it would be missing), and the ground is one more mesh
drawn once where it lies.  Copy k of an instance maps a prototype point p to
Ry(yaw_k) R S p + position_k: S the table's scale, R its rotate_deg (the
mesh's rotation convention), Ry(yaw_k) a turn about +y by the random yaw
(none without random_yaw_deg), and position_k its translate, or its grid
place plus jitter, with y replaced when place_on_ground is set.  The Scene
gets the copies in file order, a grid's with i varying fastest, then the
ground's; Hits.geom_id is the mesh's index in the file (the ground's is the
number of meshes) and colours stay per mesh.  The ground's "auto" y is the
lowest point of all copies, and its default size and centre come from the
copies' boxes (each copy's prototype box, scaled, rotated and then turned
and moved with the copy).  Random draws come from numpy's default_rng(seed):
for a table of n copies, first the n yaws, then the grid's n (x, z) jitters.

Camera convention (for renderers): forward = normalise(target - eye),
right = normalise(forward x up), true_up = right x forward.  Pixel (x, y),
y counting down from the top row, has its centre at
``forward + ((2 (x + 0.5) / width - 1) * aspect * right
+ (1 - 2 (y + 0.5) / height) * true_up) * tan(fov_deg / 2)``, aspect = width / height.

Every error is a SceneFileError naming the file and the key, e.g.
``reference.toml: mesh[2].split: expected an integer >= 1, got 0`` or
``field.toml: instance[3].grid.count[1]: expected an integer >= 1, got 0``.
"""
from __future__ import annotations

import math
import os
import re
import sys
import time
import tomllib
from collections.abc import Callable, Collection
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..build.instances import check_resolved, check_transforms
from ..mesh import MESH_EXTENSIONS, Mesh, unit_rows
from ..render.camera import Camera, unit, vertical_fov_deg, view_problem
from ..render.film import BRIGHTEST
from ..render.light import Light
from ..render.renderer import Renderer
from ..scene import Scene
from .split import split_edges
from ..core import inputs

from .description import (Color, Ground, InstanceEntry, MeshEntry, SceneDescription,  # noqa: F401
                          SceneFileError, Vec3, shape_mesh)

_DEFAULT_COLOR: Color = (0.8, 0.8, 0.8)
_MAX_IMAGE_SIDE = 16384
# Copies in one file; a bound checked before any array of them is made.
MAX_INSTANCES = 1 << 24


_TOP_KEYS = ("render", "camera", "light", "ground", "mesh", "instance", "emitter")
_RENDER_KEYS = ("width", "height")
_CAMERA_KEYS = ("eye", "target", "up", "fov_deg")
_LIGHT_KEYS = ("direction", "intensity", "ambient")
_GROUND_KEYS = ("y", "size", "color", "material")
#: fit_height refuses a mesh whose y extent is under this much of its
#: largest extent: flat, up to rounding.
FLAT_RATIO = 1e-9

_MESH_KEYS = ("path", "shape", "color", "material", "emitter", "split", "scale", "rotate_deg",
              "fit_height", "translate", "place_on_ground", "face_normals")

#: Mitsuba's shapes a [[mesh]] table may name instead of a file.
SHAPES = ("rectangle", "cube", "sphere")
_INSTANCE_KEYS = ("mesh", "scale", "rotate_deg", "translate", "grid", "random_yaw_deg", "seed",
                  "place_on_ground", "material")
_GRID_KEYS = ("count", "spacing", "origin", "jitter")


class _Reader:
    """Typed access to the parsed TOML; every error names the file and the key."""

    def __init__(self, path: Path):
        self.label = str(path)
        self.path = Path(path)

    def error(self, key: str, message: str) -> SceneFileError:
        return SceneFileError(f"{self.label}: {key}: {message}")

    def table(self, value, key: str, known: tuple[str, ...]) -> dict:
        if not isinstance(value, dict):
            raise self.error(key, f"expected a table, got {inputs.describe(value)}")
        for name in value:
            if name not in known:
                where = f"{key}.{name}" if key else name
                raise self.error(where, f"unknown key (expected one of: {', '.join(known)})")
        return value

    def checked(self, check, key: str, *args, **kwargs):
        """``check(key, ...)`` of hlbvh_cl.core.inputs, its error worded for
        the file: "scene.toml: key: expected ..., got ..."."""
        try:
            return check(key, *args, **kwargs)
        except (inputs.BadType, inputs.BadValue) as error:
            raise self.error(error.name, f"expected {error.expected}, got {error.got}") from None

    def integer(self, value, key: str, minimum: int, maximum: int | None = None) -> int:
        return self.checked(inputs.integer, key, value, minimum, maximum)

    def number(self, value, key: str, low: float | None = None, high: float | None = None,
               low_open: bool = False, high_open: bool = False) -> float:
        return self.checked(inputs.number, key, value, low, high, low_open, high_open)

    def vector3(self, value, key: str, low: float | None = None, low_open: bool = False,
                high: float | None = None) -> Vec3:
        if not isinstance(value, list):  # an array in TOML; inputs.vector3 takes tuples too
            raise self.error(key, f"expected 3 numbers [x, y, z], got {inputs.describe(value)}")
        return tuple(self.checked(inputs.vector3, key, value, low, high, low_open).tolist())

    def color(self, value, key: str) -> Color:
        if not isinstance(value, list) or len(value) != 3:
            raise self.error(key, f"expected an RGB colour [r, g, b] with values 0..1, "
                                  f"got {inputs.describe(value)}")
        return self.vector3(value, key, low=0.0, high=1.0)

    def boolean(self, value, key: str) -> bool:
        if not isinstance(value, bool):
            raise self.error(key, f"expected true or false, got {inputs.describe(value)}")
        return value

    def scale(self, value, key: str) -> Vec3:
        if isinstance(value, list):
            return self.vector3(value, key, low=0.0, low_open=True)
        return (self.number(value, key, low=0.0, low_open=True),) * 3

    def pair(self, value, key: str, read) -> tuple:
        """Two values [x, z], each checked by read(item, key)."""
        if not isinstance(value, list) or len(value) != 2:
            raise self.error(key, f"expected 2 values [x, z], got {inputs.describe(value)}")
        return tuple(read(item, f"{key}[{n}]") for n, item in enumerate(value))


@dataclass
class _MeshSpec:
    """One [[mesh]] table, checked but not loaded yet."""
    key: str
    path: Path | None
    color: Color
    split: int
    scale: Vec3
    rotate_deg: Vec3
    fit_height: float | None
    translate: Vec3
    place_on_ground: bool
    shape: str | None = None
    material: dict | None = None
    emitter: dict | None = None
    face_normals: bool = False


@dataclass
class _InstanceSpec:
    """One [[instance]] table, checked; positions before place_on_ground."""
    key: str
    mesh: int
    scale: Vec3
    rotate_deg: Vec3
    positions: np.ndarray  # (copies, 3) float64
    yaw_deg: np.ndarray  # (copies,) float64
    place_on_ground: bool
    material: dict | None = None


@dataclass(frozen=True)
class LoadedScene:
    """A scene file's Scene, built, with what the file says about rendering
    it.  load_seconds is the time spent reading, splitting and transforming
    the meshes; build_seconds the Scene's construction (kernel compilation
    included on a first build)."""

    scene: Scene
    camera: Camera
    light: Light
    colors: tuple[Color, ...]  # one per geom_id: scene.meshes (the ground last), its spheres
    width: int
    height: int
    path: Path
    load_seconds: float
    build_seconds: float
    materials: list | None = None
    emitters: list | None = None
    options: dict = field(default_factory=dict)  # SceneDescription.options
    instance_materials: list | None = None
    sensor_fov: tuple[float, str] | None = None  # SceneDescription.sensor_fov
    inputs: tuple[Path, ...] = ()  # SceneDescription.inputs: the files it read

    def camera_at(self, width: int, height: int) -> Camera:
        """The camera for an image of width x height: ``camera`` itself,
        except for a Mitsuba sensor rendered at another aspect than its
        film's, whose fov holds along its fov_axis (Mitsuba's rule) where
        ``camera``'s vertical fov would not."""
        if self.sensor_fov is None or width * self.height == height * self.width:
            return self.camera
        fov, axis = self.sensor_fov
        return replace(self.camera, fov_deg=vertical_fov_deg(fov, axis, width / height))

    def renderer(self) -> Renderer:
        """A Renderer of the scene with the file's colours, light, materials
        (the instances' own too) and emitters."""
        return Renderer(self.scene, colors=list(self.colors), light=self.light,
                        materials=self.materials, emitters=self.emitters,
                        instance_materials=self.instance_materials)


def load(path, device=None, builder: str = "hlbvh", morton_bits: int = 30,
         defaults: dict | None = None, replaced: Collection[str] = (),
         compact: bool = False,
         check: Callable[[SceneDescription], None] | None = None) -> LoadedScene:
    """Read a scene file (``read``) and build its Scene on ``device`` (with
    ``compact`` leaves where asked: hlbvh_cl.Scene);
    ``defaults`` override a Mitsuba XML file's <default> values, and the
    render values named in ``replaced`` may exceed the renderer's limits
    (the caller renders with its own).  ``check``, where given, sees the
    file's description before the build, which it stops by raising (the
    CLI refuses an output file the scene reads there, before a build that
    can take seconds)."""
    started = time.perf_counter()
    description = read(path, defaults, replaced)
    if check is not None:
        check(description)
    loaded = time.perf_counter()
    geometries = description.geometries()
    meshes = [mesh for mesh, _ in geometries]
    placements = description.placements()
    if placements:
        try:
            scene = Scene(meshes, instances=placements, device=device, builder=builder,
                          morton_bits=morton_bits, compact=compact)
        except ValueError as error:  # a check only the built frames can make
            raise _name_the_entry(description, error) from None
    else:  # a flat scene, as the file says: each mesh drawn once as it is
        scene = Scene(meshes, device=device, builder=builder, morton_bits=morton_bits,
                      spheres=description.spheres(), compact=compact)
    colors = [color for _, color in geometries]
    colors += [entry.color for entry in description.surfaces()[len(colors):]]  # the spheres'
    return LoadedScene(scene=scene, camera=description.camera, light=description.light,
                       colors=tuple(colors), width=description.width,
                       height=description.height, path=description.path,
                       load_seconds=loaded - started,
                       build_seconds=time.perf_counter() - loaded,
                       materials=description.materials(), emitters=description.all_emitters(),
                       options=dict(description.options),
                       instance_materials=description.instance_materials(),
                       sensor_fov=description.sensor_fov, inputs=description.inputs())


def _name_the_entry(description: SceneDescription, error: ValueError) -> ValueError:
    """The Scene's error about its instance k as a SceneFileError naming the
    [[instance]] table (and copy) that made it; other errors as they are."""
    found = re.match(r"instance (\d+)'s ", str(error))
    if not found:
        return error
    k = int(found.group(1))
    copies = np.cumsum([len(entry.transforms) for entry in description.instances])
    entry = int(np.searchsorted(copies, k, side="right"))
    if entry == len(copies):
        key = "ground"
    else:
        copy = k - (int(copies[entry - 1]) if entry else 0)
        several = len(description.instances[entry].transforms) > 1
        key = f"instance[{entry}]" + (f", copy {copy}" if several else "")
    return SceneFileError(f"{_Reader(description.path).label}: {key}: {error}")


#: The image size, view and ground of a mesh file read as a scene (read_mesh).
MESH_VIEW = {"width": 1280, "height": 720, "fov_deg": 45.0, "from": (0.0, 0.35, 1.0)}


def read_mesh(path) -> SceneDescription:
    """A mesh file (Mesh.load's formats) as a scene: the mesh in the default
    colour on a ground square at its lowest point, lit by the default
    light, seen at MESH_VIEW's size from the front (+z) and a little above
    (y up, as the Stanford meshes are), far enough back that its bounding
    sphere fills the view's height."""
    path = Path(os.fspath(path))
    mesh = Mesh.load(path)
    lo, hi = mesh.bounds
    centre, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-30)
    distance = radius / math.sin(math.radians(MESH_VIEW["fov_deg"]) / 2)
    eye = centre + distance * unit(np.array(MESH_VIEW["from"]))
    camera = Camera(tuple(eye), tuple(centre), fov_deg=MESH_VIEW["fov_deg"])
    reader = _Reader(path)
    ground = _make_ground(reader, {"y": None, "size": None, "color": _DEFAULT_COLOR}, lo, hi)
    return SceneDescription(path=path, width=MESH_VIEW["width"], height=MESH_VIEW["height"],
                            camera=camera, light=Light(),
                            meshes=[MeshEntry(mesh=mesh, color=_DEFAULT_COLOR, path=path)],
                            ground=ground)


def is_mesh_file(path) -> bool:
    """Whether ``path`` names a mesh file by its extension (a .gz too)."""
    suffixes = [suffix.lower() for suffix in Path(os.fspath(path)).suffixes]
    if suffixes[-1:] == [".gz"]:
        suffixes = suffixes[:-1]
    return bool(suffixes) and suffixes[-1][1:] in MESH_EXTENSIONS


def read(path, defaults: dict | None = None,
         replaced: Collection[str] = ()) -> SceneDescription:
    """Read a TOML scene file (schema in this module's docstring); a mesh
    file (``bunny.ply``) is read as a scene of that mesh (read_mesh), and a
    .xml file as Mitsuba 3's scene format (hlbvh_cl.io.mitsuba).
    ``replaced`` names the render values ("width", "height", and in XML
    "spp", "max_depth") that the caller replaces with its own: the file's
    may then exceed the renderer's limits (read_xml).

    Raises FileNotFoundError if the scene file itself is missing and
    SceneFileError (a ValueError) for anything wrong inside it, including
    missing or unreadable mesh files.
    """
    path = Path(os.fspath(path))
    if is_mesh_file(path):
        return read_mesh(path)
    if path.suffix.lower() == ".xml":
        from .mitsuba import read_xml
        return read_xml(path, defaults, replaced)
    reader = _Reader(path)
    if path.is_char_device() or path.is_block_device():
        # (a device such as /dev/zero would be read whole; a pipe is read)
        raise SceneFileError(f"{reader.label}: not a regular file, so not a scene file")
    try:
        with open(path, "rb") as file:
            data = tomllib.load(file)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
        if path.suffix.lower() not in ("", ".toml"):
            # (a mesh format this reader does not take, a .gltf, was named a TOML error)
            raise SceneFileError(
                f"{reader.label}: a {path.suffix} file is neither a scene file (.toml, .xml) "
                f"nor a mesh file this reader takes "
                f"({', '.join('.' + e for e in MESH_EXTENSIONS)}, optionally .gz), and it does "
                f"not read as TOML ({type(error).__name__})") from None
        if isinstance(error, tomllib.TOMLDecodeError):
            raise SceneFileError(f"{reader.label}: TOML syntax error: {error}") from None
        raise SceneFileError(f"{reader.label}: not UTF-8 text, so not a TOML scene file (expected "
                             f"a .toml scene file, or a mesh file: "
                             f"{', '.join('.' + e for e in MESH_EXTENSIONS)}): {error}") from None
    except (IsADirectoryError, PermissionError) as error:
        raise SceneFileError(f"{reader.label}: cannot read the scene file: "
                             f"{error.strerror}") from None

    reader.table(data, "", _TOP_KEYS)
    for required in ("render", "camera", "mesh"):
        if required not in data:
            raise reader.error(required, "missing (required)")

    render = reader.table(data["render"], "render", _RENDER_KEYS)
    for required in _RENDER_KEYS:
        if required not in render:
            raise reader.error(f"render.{required}", "missing (required)")
    width, height = (reader.integer(render[side], f"render.{side}", 1,
                                    2**32 - 1 if side in replaced else _MAX_IMAGE_SIDE)
                     for side in ("width", "height"))
    camera = _read_camera(reader, data["camera"])
    light = _read_light(reader, data.get("light", {}))
    ground_spec = _read_ground(reader, data["ground"]) if "ground" in data else None
    specs = _read_mesh_specs(reader, data["mesh"], path.parent)
    instance_specs = (_read_instance_specs(reader, data["instance"], len(specs))
                      if "instance" in data else [])

    ground_y = 0.0 if ground_spec is None or ground_spec["y"] is None else ground_spec["y"]
    meshes = _load_meshes(reader, specs, ground_y)
    placed = [_place(reader, spec, meshes[spec.mesh].mesh, ground_y) for spec in instance_specs]
    instances = [entry for entry, _ in placed]
    # The boxes of what is drawn: the copies' when there are instances.
    boxes = [box for _, box in placed] or [entry.mesh.bounds for entry in meshes]
    ground = None
    if ground_spec:
        lo = np.min([lo for lo, _ in boxes], axis=0)
        hi = np.max([hi for _, hi in boxes], axis=0)
        ground = _make_ground(reader, ground_spec, lo, hi)
    emitters = _read_emitters(reader, data["emitter"]) if "emitter" in data else []
    return SceneDescription(path=path, width=width, height=height, camera=camera, light=light,
                            meshes=meshes, ground=ground, instances=instances, emitters=emitters)


def _read_camera(reader: _Reader, value) -> Camera:
    table = reader.table(value, "camera", _CAMERA_KEYS)
    for required in ("eye", "target"):
        if required not in table:
            raise reader.error(f"camera.{required}", "missing (required)")
    eye = reader.vector3(table["eye"], "camera.eye")
    target = reader.vector3(table["target"], "camera.target")
    up = reader.vector3(table.get("up", [0.0, 1.0, 0.0]), "camera.up")
    fov = reader.number(table.get("fov_deg", Camera.fov_deg), "camera.fov_deg", 0.0, 180.0,
                        low_open=True, high_open=True)
    problem = view_problem(*(np.array(v, np.float64) for v in (eye, target, up)))
    if problem is not None:
        raise reader.error(f"camera.{problem[0]}", problem[1])
    return Camera(eye=eye, target=target, up=up, fov_deg=fov)


def _read_light(reader: _Reader, value) -> Light:
    table = reader.table(value, "light", _LIGHT_KEYS)
    direction = unit(np.array(reader.vector3(table.get("direction", [1.0, 2.0, 1.0]),
                                             "light.direction"), np.float64))
    if direction is None:
        raise reader.error("light.direction", "is the zero vector")
    intensity = reader.number(table.get("intensity", 1.0), "light.intensity", low=0.0,
                              high=BRIGHTEST)  # Light's bound, named here with the file
    ambient = reader.number(table.get("ambient", 0.15), "light.ambient", low=0.0, high=1.0)
    return Light(direction=tuple(float(x) for x in direction), intensity=intensity,
                 ambient=ambient)


def _read_ground(reader: _Reader, value) -> dict:
    table = reader.table(value, "ground", _GROUND_KEYS)
    y = table.get("y", "auto")
    if isinstance(y, str):
        if y != "auto":
            raise reader.error("ground.y", f"expected a number or \"auto\", got {y!r}")
        y = None
    else:
        y = reader.number(y, "ground.y")
    size = table.get("size")
    if size is not None:
        size = reader.number(size, "ground.size", low=0.0, low_open=True)
    color = reader.color(table.get("color", list(_DEFAULT_COLOR)), "ground.color")
    return {"y": y, "size": size, "color": color, "material": _material(reader, table, "ground")}


def _read_mesh_specs(reader: _Reader, value, folder: Path) -> list[_MeshSpec]:
    if not isinstance(value, list) or not value:
        raise reader.error("mesh", f"expected one or more [[mesh]] tables, got {inputs.describe(value)}")
    specs = []
    for index, item in enumerate(value):
        key = f"mesh[{index}]"
        table = reader.table(item, key, _MESH_KEYS)
        shapes = " | ".join(map(repr, SHAPES))
        if "path" not in table and "shape" not in table:
            raise reader.error(f"{key}.path", "missing (required): a mesh file, or instead one "
                                              f"of Mitsuba's shapes (shape = {shapes})")
        if "path" in table and "shape" in table:
            raise reader.error(f"{key}.path", "a mesh file (path) or one of Mitsuba's shapes "
                                              f"(shape = {shapes}), not both")
        if "shape" in table and table["shape"] not in SHAPES:
            raise reader.error(f"{key}.shape", f"expected one of {', '.join(SHAPES)}, got "
                                               f"{inputs.describe(table['shape'])}")
        if "path" in table and (not isinstance(table["path"], str) or not table["path"]):
            raise reader.error(f"{key}.path", f"expected a file name, got {inputs.describe(table['path'])}")
        scale = reader.scale(table.get("scale", 1.0), f"{key}.scale")
        fit_height = table.get("fit_height")
        if fit_height is not None:
            fit_height = reader.number(fit_height, f"{key}.fit_height", low=0.0, low_open=True)
        specs.append(_MeshSpec(
            key=key,
            path=folder / table["path"] if "path" in table else None,
            shape=table.get("shape"),
            material=_material(reader, table, key),
            emitter=_area_emitter(reader, table, key),
            color=reader.color(table.get("color", list(_DEFAULT_COLOR)), f"{key}.color"),
            split=reader.integer(table.get("split", 1), f"{key}.split", 1),
            scale=scale,
            rotate_deg=reader.vector3(table.get("rotate_deg", [0.0, 0.0, 0.0]), f"{key}.rotate_deg"),
            fit_height=fit_height,
            translate=reader.vector3(table.get("translate", [0.0, 0.0, 0.0]), f"{key}.translate"),
            place_on_ground=reader.boolean(table.get("place_on_ground", False),
                                           f"{key}.place_on_ground"),
            face_normals=reader.boolean(table.get("face_normals", False),
                                        f"{key}.face_normals"),
        ))
    return specs


def _read_instance_specs(reader: _Reader, value, mesh_count: int) -> list[_InstanceSpec]:
    if not isinstance(value, list) or not value:
        raise reader.error("instance", f"expected one or more [[instance]] tables, "
                                       f"got {inputs.describe(value)}")
    specs = []
    total = 0
    for index, item in enumerate(value):
        key = f"instance[{index}]"
        table = reader.table(item, key, _INSTANCE_KEYS)
        if "mesh" not in table:
            raise reader.error(f"{key}.mesh", "missing (required)")
        mesh = table["mesh"]
        if isinstance(mesh, bool) or not isinstance(mesh, int):
            raise reader.error(f"{key}.mesh", f"expected the index of a [[mesh]] table, counting "
                                              f"from 0, got {inputs.describe(mesh)}")
        if not 0 <= mesh < mesh_count:
            raise reader.error(f"{key}.mesh", f"no [[mesh]] table {mesh}: the file has "
                                              f"{mesh_count} (mesh[0] to mesh[{mesh_count - 1}])")
        if "grid" in table and "translate" in table:
            raise reader.error(f"{key}.grid", "give either translate or grid, not both")
        grid = _read_grid(reader, table["grid"], f"{key}.grid", MAX_INSTANCES - total) \
            if "grid" in table else None
        if grid is None:
            positions = _read_positions(reader, table.get("translate", [0.0, 0.0, 0.0]),
                                        f"{key}.translate")
            if total + len(positions) > MAX_INSTANCES:
                raise reader.error(f"{key}.translate", f"more than {MAX_INSTANCES:,} copies "
                                                       f"in the file")
        else:
            positions, jitter = grid
        copies = len(positions)
        total += copies
        yaw_range = reader.number(table.get("random_yaw_deg", 0.0), f"{key}.random_yaw_deg",
                                  0.0, 180.0)
        rng = np.random.default_rng(reader.integer(table.get("seed", index), f"{key}.seed", 0))
        yaw = rng.uniform(-yaw_range, yaw_range, copies)
        if grid is not None:
            positions[:, [0, 2]] += rng.uniform(-1.0, 1.0, (copies, 2)) * jitter
        specs.append(_InstanceSpec(
            key=key,
            mesh=mesh,
            scale=reader.scale(table.get("scale", 1.0), f"{key}.scale"),
            rotate_deg=reader.vector3(table.get("rotate_deg", [0.0, 0.0, 0.0]),
                                      f"{key}.rotate_deg"),
            positions=positions,
            yaw_deg=yaw,
            place_on_ground=reader.boolean(table.get("place_on_ground", False),
                                           f"{key}.place_on_ground"),
            material=_material(reader, table, key),
        ))
    drawn = {spec.mesh for spec in specs}
    for mesh in range(mesh_count):
        if mesh not in drawn:
            raise reader.error(f"mesh[{mesh}]", "no [[instance]] table draws it, and a file with "
                                                "[[instance]] tables draws only instances: add "
                                                f"one with mesh = {mesh}, or remove the table")
    return specs


def _read_positions(reader: _Reader, value, key: str) -> np.ndarray:
    """translate: [x, y, z], or a list of them; (copies, 3) float64."""
    if isinstance(value, list) and any(isinstance(item, list) for item in value):
        return np.array([reader.vector3(item, f"{key}[{n}]") for n, item in enumerate(value)],
                        dtype=np.float64)
    if isinstance(value, list) and len(value) == 3:
        return np.array([reader.vector3(value, key)], dtype=np.float64)
    raise reader.error(key, f"expected a position [x, y, z] or a list of them, "
                            f"got {inputs.describe(value)}")


def _read_grid(reader: _Reader, value, key: str, room: int) -> tuple[np.ndarray, np.ndarray]:
    """A grid table: its positions (copies, 3), i fastest, and the x/z jitter amplitude."""
    table = reader.table(value, key, _GRID_KEYS)
    for required in ("count", "spacing"):
        if required not in table:
            raise reader.error(f"{key}.{required}", "missing (required)")
    nx, nz = reader.pair(table["count"], f"{key}.count",
                         lambda item, where: reader.integer(item, where, 1))
    if nx * nz > room:
        raise reader.error(f"{key}.count", f"{nx} x {nz} copies: more than {MAX_INSTANCES:,} "
                                           f"in the file")
    spacing = np.array(reader.pair(table["spacing"], f"{key}.spacing",
                                   lambda item, where: reader.number(item, where, low=0.0,
                                                                     low_open=True)))
    origin = reader.vector3(table.get("origin", [0.0, 0.0, 0.0]), f"{key}.origin")
    jitter = reader.number(table.get("jitter", 0.0), f"{key}.jitter", 0.0, 0.5)
    positions = np.empty((nx * nz, 3))
    positions[:, 0] = origin[0] + spacing[0] * np.tile(np.arange(nx), nz)
    positions[:, 1] = origin[1]
    positions[:, 2] = origin[2] + spacing[1] * np.repeat(np.arange(nz), nx)
    return positions, jitter * spacing


def _rotation(degrees: Vec3) -> np.ndarray:
    """Rotation about x, then y, then z (fixed axes): Rz @ Ry @ Rx."""
    cx, cy, cz = np.cos(np.radians(degrees))
    sx, sy, sz = np.sin(np.radians(degrees))
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _used_rows(faces: np.ndarray, count: int) -> np.ndarray:
    used = np.zeros(count, dtype=bool)
    used[faces.ravel()] = True
    return used


def _load_meshes(reader: _Reader, specs: list[_MeshSpec], ground_y: float) -> list[MeshEntry]:
    from tqdm import tqdm

    # Three steps per mesh (read, split, transform); the bar only appears on a
    # terminal, and only when loading takes more than half a second.
    bar = tqdm(total=3 * len(specs), desc="loading scene", file=sys.stderr, delay=0.5,
               leave=False, disable=not sys.stderr.isatty(), bar_format="{desc} |{bar}| {elapsed}")
    with bar:
        def step(spec: _MeshSpec, doing: str) -> None:
            what = spec.path.name if spec.path else spec.shape
            bar.set_description_str(f"loading scene: {doing} {what}", refresh=False)
            bar.update(1)
        return [_load_mesh(reader, spec, ground_y, step) for spec in specs]


def _load_mesh(reader: _Reader, spec: _MeshSpec, ground_y: float, step) -> MeshEntry:
    try:
        mesh = shape_mesh(spec.shape) if spec.shape else Mesh.load(spec.path)
    except FileNotFoundError:
        raise reader.error(f"{spec.key}.path", f"mesh file not found: {spec.path}") from None
    except (ValueError, TypeError) as error:
        raise reader.error(f"{spec.key}.path", str(error)) from None
    step(spec, f"splitting (k={spec.split})" if spec.split > 1 else "read")
    try:
        vertices, faces = split_edges(mesh.vertices, mesh.faces, spec.split)
    except ValueError as error:
        raise reader.error(f"{spec.key}.split", str(error)) from None
    step(spec, "transforming")

    used = _used_rows(faces, len(vertices))
    points = vertices.astype(np.float64) * np.array(spec.scale)
    # einsum, not a matrix product: BLAS threads spin on after the call and
    # would slow the build kernels that follow on a CPU device.
    points = np.einsum("ij,kj->ik", points, _rotation(spec.rotate_deg))
    if spec.fit_height is not None:
        extent, across = np.ptp(points[used, 1]), np.ptp(points[used], axis=0).max()
        # flat up to rounding too: a plane turned upright by rotate_deg keeps
        # a height of cos(90 degrees) = 6e-17 times its size
        if not extent > FLAT_RATIO * across:
            raise reader.error(f"{spec.key}.fit_height", f"the mesh is flat in y (height "
                                                         f"{extent:g}, {across:g} across)")
        points *= spec.fit_height / extent
    points += np.array(spec.translate)
    if spec.place_on_ground:
        points[:, 1] += ground_y - points[used, 1].min()
    # The file's normals go by the inverse transpose of the linear part,
    # normalised (split cuts new vertices: then they are computed); computed
    # ones are computed anew from the transformed vertices, as Mitsuba does.
    normals = None
    if mesh.has_file_normals and spec.split == 1:
        linear = np.einsum("ij,kj->ik", np.diag(spec.scale), _rotation(spec.rotate_deg))
        normals = unit_rows(np.einsum("ij,jk->ik", mesh.normals.astype(np.float64),
                                      np.linalg.inv(linear).T))
    try:
        transformed = Mesh(points, faces, name=mesh.name, normals=normals,
                           face_normals=mesh.face_normals or spec.face_normals)
    except ValueError as error:  # e.g. a scale, height or offset that overflows float32
        raise reader.error(spec.key, "its scale, rotate_deg, fit_height and translate give an "
                                     f"invalid mesh: {error}") from None
    step(spec, "done")
    return MeshEntry(mesh=transformed, color=spec.color, path=spec.path, split=spec.split,
                     material=spec.material, emitter=spec.emitter)


def _place(reader: _Reader, spec: _InstanceSpec, mesh: Mesh, ground_y: float
           ) -> tuple[InstanceEntry, tuple[np.ndarray, np.ndarray]]:
    """An instance table's transforms, and the box around all its copies."""
    linear = _rotation(spec.rotate_deg) * np.array(spec.scale)  # R @ diag(scale)
    points = mesh.vertices[_used_rows(mesh.faces, mesh.vertex_count)].astype(np.float64)
    # einsum, not a matrix product: see _load_mesh.
    points = np.einsum("ij,kj->ik", points, linear)
    lo, hi = points.min(axis=0), points.max(axis=0)
    positions = spec.positions.copy()
    if spec.place_on_ground:  # a turn about y leaves every point's height as it is
        positions[:, 1] = ground_y - lo[1]
    c, s = np.cos(np.radians(spec.yaw_deg)), np.sin(np.radians(spec.yaw_deg))
    transforms = np.zeros((len(positions), 3, 4))
    yaw = np.zeros((len(positions), 3, 3))
    yaw[:, 0, 0], yaw[:, 0, 2], yaw[:, 1, 1], yaw[:, 2, 0], yaw[:, 2, 2] = c, s, 1.0, -s, c
    transforms[:, :, :3] = np.einsum("nij,jk->nik", yaw, linear)
    transforms[:, :, 3] = positions
    # The box (lo, hi) turned by each yaw: x' = c x + s z and z' = c z - s x
    # range independently over the box's x and z intervals.
    def turned(a, b, lo_a, hi_a, lo_b, hi_b):
        return (np.minimum(a * lo_a, a * hi_a) + np.minimum(b * lo_b, b * hi_b),
                np.maximum(a * lo_a, a * hi_a) + np.maximum(b * lo_b, b * hi_b))
    x_lo, x_hi = turned(c, s, lo[0], hi[0], lo[2], hi[2])
    z_lo, z_hi = turned(c, -s, lo[2], hi[2], lo[0], hi[0])
    copies_lo = np.stack([x_lo, np.full_like(x_lo, lo[1]), z_lo], axis=1) + positions
    copies_hi = np.stack([x_hi, np.full_like(x_hi, hi[1]), z_hi], axis=1) + positions
    box = copies_lo.min(axis=0), copies_hi.max(axis=0)
    reach = max(np.abs(box[0]).max(), np.abs(box[1]).max())
    if not reach < np.finfo(np.float32).max:
        raise reader.error(spec.key, f"its scale and positions put copies at {reach:.3g}, "
                                     "beyond float32")
    try:  # the Scene's own checks (a scale of 1e-300 is singular)
        check_transforms(transforms, lambda k: f"copy {k}'s transform")
        check_resolved(copies_lo, copies_hi, lambda k: f"copy {k}'s transform")
    except ValueError as error:
        raise reader.error(spec.key, str(error)) from None
    return InstanceEntry(mesh=spec.mesh, transforms=transforms, material=spec.material), box


def _make_ground(reader: _Reader, spec: dict, lo: np.ndarray, hi: np.ndarray) -> Ground:
    """The ground square under the box (lo, hi) of what is drawn."""
    y = float(lo[1]) if spec["y"] is None else spec["y"]
    size = spec["size"]
    if size is None:
        size = 4.0 * float(max(hi[0] - lo[0], hi[2] - lo[2]))
        if not size > 0:
            size = 1.0
    cx, cz = (lo[0] + hi[0]) / 2, (lo[2] + hi[2]) / 2
    h = size / 2
    vertices = [[cx - h, y, cz - h], [cx + h, y, cz - h], [cx + h, y, cz + h], [cx - h, y, cz + h]]
    # Wound so that cross(v1 - v0, v2 - v0) points to +y.
    faces = [[0, 2, 1], [0, 3, 2]]
    try:
        mesh = Mesh(vertices, faces, name="ground")
    except ValueError as error:  # a size or height beyond float32
        raise reader.error("ground", f"its size {size:.3g} at y {y:.3g} gives an invalid "
                                     f"square: {error}") from None
    return Ground(mesh=mesh, y=y, size=size, color=spec["color"], material=spec.get("material"))


def _material(reader: _Reader, table: dict, key: str) -> dict | None:
    """A table's `material`, checked as Renderer.materials checks one."""
    if "material" not in table:
        return None
    from ..render.materials import check_material
    try:
        check_material(f"{key}.material", table["material"])
    except (TypeError, ValueError) as error:
        raise SceneFileError(f"{reader.label}: {error}") from None
    return dict(table["material"])


def _area_emitter(reader: _Reader, table: dict, key: str) -> dict | None:
    """A [[mesh]] table's `emitter`: an area emitter, checked."""
    if "emitter" not in table:
        return None
    spec = table["emitter"]
    if not isinstance(spec, dict) or spec.get("type") != "area":
        raise reader.error(f"{key}.emitter", "expected an area emitter: { type = \"area\", "
                                             "radiance = [r, g, b] }, got "
                                             f"{inputs.describe(spec)}")
    if "mesh" in spec:  # check_emitters would take it; here the table's mesh is the one lit
        raise reader.error(f"{key}.emitter.mesh", "a [[mesh]]'s emitter lights that mesh: "
                                                  "give no mesh key")
    from ..render.emitters import check_emitters
    try:
        check_emitters([{**spec, "mesh": 0}], 1, names=[f"{key}.emitter"])
    except (TypeError, ValueError) as error:
        raise SceneFileError(f"{reader.label}: {error}") from None
    return dict(spec)


def _read_emitters(reader: _Reader, value) -> list[dict]:
    """The [[emitter]] tables: point, directional, constant or envmap lights."""
    if not isinstance(value, list) or not value:
        raise reader.error("emitter", f"expected one or more [[emitter]] tables, "
                                      f"got {inputs.describe(value)}")
    names = [f"emitter[{k}]" for k in range(len(value))]
    value = [dict(spec) if isinstance(spec, dict) else spec for spec in value]
    for name, spec in zip(names, value):
        if isinstance(spec, dict) and spec.get("type") == "area":
            raise reader.error(name, "an area emitter belongs in its [[mesh]] table (emitter = "
                                     "{ type = \"area\", radiance = ... })")
        if isinstance(spec, dict) and isinstance(spec.get("filename"), str):
            spec["filename"] = str(reader.path.parent / spec["filename"])  # relative to the file
    from ..render.emitters import check_emitters
    try:
        check_emitters(value, 0, names=names)
    except (TypeError, ValueError) as error:
        raise SceneFileError(f"{reader.label}: {error}") from None
    return [dict(spec) for spec in value]
