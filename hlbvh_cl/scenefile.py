"""TOML scene files: meshes with colours and transforms, a ground, a camera, a light.

``read(path)`` parses one with tomllib into a SceneDescription whose meshes
are already loaded, split and transformed; ``load(path)`` also builds its
Scene and returns a LoadedScene (scene, camera, light, colours, image size).

Schema (every table and key is listed here; any other key is an error)::

    [render]                      # required
    width = 1280                  # image size in pixels, integers 1..16384
    height = 720

    [camera]                      # required; a pinhole camera
    eye = [0.0, 1.0, 4.0]         # position
    target = [0.0, 1.0, 0.0]      # point looked at
    up = [0.0, 1.0, 0.0]          # default [0, 1, 0]; must not be parallel to target - eye
    fov_deg = 45.0                # vertical field of view in degrees, 0 < fov < 180; default 45

    [light]                       # optional; a directional light
    direction = [1.0, 2.0, 1.0]   # from the surface towards the light (normalised on load);
                                  # default [1, 2, 1]
    intensity = 1.0               # >= 0, default 1
    ambient = 0.15                # 0..1, default 0.15

    [ground]                      # optional; a square of two triangles facing +y
    y = "auto"                    # height: a number, or "auto" = the lowest mesh point (default)
    size = 10.0                   # side length; default 4 x the meshes' larger x/z extent.
                                  # Centred on the centre of the meshes' x/z bounds.
    color = [0.8, 0.8, 0.8]       # RGB, each 0..1; default 0.8 grey

    [[mesh]]                      # one table per mesh, at least one; mesh[0] is the first
    path = "meshes/bunny.ply"     # relative to this TOML file (or absolute)
    color = [0.8, 0.8, 0.8]       # RGB, each 0..1; default 0.8 grey
    split = 1                     # cut every edge in k parts (k*k triangles each); default 1
    scale = 1.0                   # > 0: one number, or three (per axis)
    rotate_deg = [0.0, 0.0, 0.0]  # Euler angles in degrees: about x, then y, then z (fixed axes)
    fit_height = 1.0              # > 0: uniform scale so the mesh's y extent equals it
    translate = [0.0, 0.0, 0.0]
    place_on_ground = false       # move along y so the mesh's lowest point is at the ground's y

Each mesh is split first, then scaled (scale, then fit_height), rotated and
translated (translate, then place_on_ground).  fit_height measures the y
extent after scale and rotation; since a uniform scale commutes with a
rotation this equals scaling first by the right factor.  place_on_ground uses
the ground's y when it is a number, and 0 when there is no ground or its y is
"auto" (the ground then sits at the lowest mesh point).

Camera convention (for renderers): forward = normalise(target - eye),
right = normalise(forward x up), true_up = right x forward.  Pixel (x, y),
y counting down from the top row, has its centre at
``forward + ((2 (x + 0.5) / width - 1) * aspect * right
+ (1 - 2 (y + 0.5) / height) * true_up) * tan(fov_deg / 2)``, aspect = width / height.

Every error is a SceneFileError naming the file and the key, e.g.
``reference.toml: mesh[2].split: expected an integer >= 1, got 0``.
"""
from __future__ import annotations

import math
import os
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .mesh import Mesh
from .render import Camera, Light, Renderer
from .scene import Scene
from .split import split_edges

Color = tuple[float, float, float]
Vec3 = tuple[float, float, float]

_DEFAULT_COLOR: Color = (0.8, 0.8, 0.8)
_MAX_IMAGE_SIDE = 16384


class SceneFileError(ValueError):
    """A scene file that cannot be read; the message names the file and the key."""


@dataclass(frozen=True)
class Ground:
    mesh: Mesh  # two triangles facing +y
    y: float
    size: float
    color: Color


@dataclass(frozen=True)
class MeshEntry:
    mesh: Mesh  # split and transformed
    color: Color
    path: Path
    split: int = 1


@dataclass
class SceneDescription:
    path: Path
    width: int
    height: int
    camera: Camera
    light: Light
    meshes: list[MeshEntry] = field(default_factory=list)
    ground: Ground | None = None

    @property
    def triangle_count(self) -> int:
        return sum(m.triangle_count for m, _ in self.geometries())

    def geometries(self) -> list[tuple[Mesh, Color]]:
        """(mesh, colour) of every surface: the meshes in file order, then the ground."""
        found = [(entry.mesh, entry.color) for entry in self.meshes]
        if self.ground is not None:
            found.append((self.ground.mesh, self.ground.color))
        return found


_TOP_KEYS = ("render", "camera", "light", "ground", "mesh")
_RENDER_KEYS = ("width", "height")
_CAMERA_KEYS = ("eye", "target", "up", "fov_deg")
_LIGHT_KEYS = ("direction", "intensity", "ambient")
_GROUND_KEYS = ("y", "size", "color")
_MESH_KEYS = ("path", "color", "split", "scale", "rotate_deg", "fit_height", "translate",
              "place_on_ground")


class _Reader:
    """Typed access to the parsed TOML; every error names the file and the key."""

    def __init__(self, path: Path):
        self.label = str(path)

    def error(self, key: str, message: str) -> SceneFileError:
        return SceneFileError(f"{self.label}: {key}: {message}")

    def table(self, value, key: str, known: tuple[str, ...]) -> dict:
        if not isinstance(value, dict):
            raise self.error(key, f"expected a table, got {_describe(value)}")
        for name in value:
            if name not in known:
                where = f"{key}.{name}" if key else name
                raise self.error(where, f"unknown key (expected one of: {', '.join(known)})")
        return value

    def integer(self, value, key: str, minimum: int, maximum: int | None = None) -> int:
        bound = f"an integer >= {minimum}" + (f" and <= {maximum}" if maximum is not None else "")
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, f"expected {bound}, got {_describe(value)}")
        if value < minimum or (maximum is not None and value > maximum):
            raise self.error(key, f"expected {bound}, got {value}")
        return value

    def number(self, value, key: str, low: float | None = None, high: float | None = None,
               low_open: bool = False, high_open: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(key, f"expected a number, got {_describe(value)}")
        number = float(value)
        if not math.isfinite(number):
            raise self.error(key, f"expected a finite number, got {value}")
        too_low = low is not None and (number <= low if low_open else number < low)
        too_high = high is not None and (number >= high if high_open else number > high)
        if too_low or too_high:
            parts = []
            if low is not None:
                parts.append(f"{'>' if low_open else '>='} {low:g}")
            if high is not None:
                parts.append(f"{'<' if high_open else '<='} {high:g}")
            raise self.error(key, f"expected a number {' and '.join(parts)}, got {value}")
        return number

    def vector3(self, value, key: str, low: float | None = None, low_open: bool = False,
                high: float | None = None) -> Vec3:
        if not isinstance(value, list) or len(value) != 3:
            raise self.error(key, f"expected 3 numbers [x, y, z], got {_describe(value)}")
        return tuple(self.number(x, f"{key}[{n}]", low=low, low_open=low_open, high=high)
                     for n, x in enumerate(value))

    def color(self, value, key: str) -> Color:
        if not isinstance(value, list) or len(value) != 3:
            raise self.error(key, f"expected an RGB colour [r, g, b] with values 0..1, "
                                  f"got {_describe(value)}")
        return self.vector3(value, key, low=0.0, high=1.0)

    def boolean(self, value, key: str) -> bool:
        if not isinstance(value, bool):
            raise self.error(key, f"expected true or false, got {_describe(value)}")
        return value


def _describe(value) -> str:
    kinds = {bool: "a boolean", int: "an integer", float: "a number", str: "a string",
             list: "an array", dict: "a table"}
    kind = next((name for t, name in kinds.items() if type(value) is t), type(value).__name__)
    shown = repr(value)
    return f"{kind} {shown if len(shown) <= 40 else shown[:37] + '...'}"


@dataclass
class _MeshSpec:
    """One [[mesh]] table, checked but not loaded yet."""
    key: str
    path: Path
    color: Color
    split: int
    scale: Vec3
    rotate_deg: Vec3
    fit_height: float | None
    translate: Vec3
    place_on_ground: bool


@dataclass(frozen=True)
class LoadedScene:
    """A scene file's Scene, built, with what the file says about rendering
    it.  load_seconds is the time spent reading, splitting and transforming
    the meshes; build_seconds the Scene's construction (kernel compilation
    included on a first build)."""

    scene: Scene
    camera: Camera
    light: Light
    colors: tuple[Color, ...]  # one per mesh of scene.meshes (the ground last)
    width: int
    height: int
    path: Path
    load_seconds: float
    build_seconds: float

    def renderer(self) -> Renderer:
        """A Renderer of the scene with the file's colours and light."""
        return Renderer(self.scene, colors=list(self.colors), light=self.light)


def load(path, device=None, builder: str = "hlbvh", morton_bits: int = 30) -> LoadedScene:
    """Read a scene file (``read``) and build its Scene on ``device``."""
    started = time.perf_counter()
    description = read(path)
    loaded = time.perf_counter()
    geometries = description.geometries()
    scene = Scene([mesh for mesh, _ in geometries], device=device, builder=builder,
                  morton_bits=morton_bits)
    return LoadedScene(scene=scene, camera=description.camera, light=description.light,
                       colors=tuple(color for _, color in geometries), width=description.width,
                       height=description.height, path=description.path,
                       load_seconds=loaded - started,
                       build_seconds=time.perf_counter() - loaded)


def read(path) -> SceneDescription:
    """Read a TOML scene file (schema in this module's docstring).

    Raises FileNotFoundError if the scene file itself is missing and
    SceneFileError (a ValueError) for anything wrong inside it, including
    missing or unreadable mesh files.
    """
    path = Path(os.fspath(path))
    reader = _Reader(path)
    try:
        with open(path, "rb") as file:
            data = tomllib.load(file)
    except tomllib.TOMLDecodeError as error:
        raise SceneFileError(f"{reader.label}: TOML syntax error: {error}") from None
    except UnicodeDecodeError as error:
        raise SceneFileError(f"{reader.label}: not UTF-8 text: {error}") from None

    reader.table(data, "", _TOP_KEYS)
    for required in ("render", "camera", "mesh"):
        if required not in data:
            raise reader.error(required, "missing (required)")

    render = reader.table(data["render"], "render", _RENDER_KEYS)
    for required in _RENDER_KEYS:
        if required not in render:
            raise reader.error(f"render.{required}", "missing (required)")
    width = reader.integer(render["width"], "render.width", 1, _MAX_IMAGE_SIDE)
    height = reader.integer(render["height"], "render.height", 1, _MAX_IMAGE_SIDE)
    camera = _read_camera(reader, data["camera"])
    light = _read_light(reader, data.get("light", {}))
    ground_spec = _read_ground(reader, data["ground"]) if "ground" in data else None
    specs = _read_mesh_specs(reader, data["mesh"], path.parent)

    ground_y = 0.0 if ground_spec is None or ground_spec["y"] is None else ground_spec["y"]
    meshes = _load_meshes(reader, specs, ground_y)
    ground = _make_ground(ground_spec, [entry.mesh for entry in meshes]) if ground_spec else None
    return SceneDescription(path=path, width=width, height=height, camera=camera, light=light,
                            meshes=meshes, ground=ground)


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
    forward = np.subtract(target, eye)
    if not np.any(forward):
        raise reader.error("camera.target", "equals camera.eye: the camera looks nowhere")
    side = np.cross(forward / np.linalg.norm(forward), up)
    if not np.linalg.norm(side) > 1e-6 * max(np.linalg.norm(up), 1e-300):
        raise reader.error("camera.up", f"{list(up)} is zero or parallel to the view direction "
                                        f"target - eye")
    return Camera(eye=eye, target=target, up=up, fov_deg=fov)


def _read_light(reader: _Reader, value) -> Light:
    table = reader.table(value, "light", _LIGHT_KEYS)
    direction = np.array(reader.vector3(table.get("direction", [1.0, 2.0, 1.0]),
                                        "light.direction"))
    length = np.linalg.norm(direction)
    if not length > 0:
        raise reader.error("light.direction", "is the zero vector")
    intensity = reader.number(table.get("intensity", 1.0), "light.intensity", low=0.0)
    ambient = reader.number(table.get("ambient", 0.15), "light.ambient", low=0.0, high=1.0)
    return Light(direction=tuple(float(x) for x in direction / length), intensity=intensity,
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
    return {"y": y, "size": size, "color": color}


def _read_mesh_specs(reader: _Reader, value, folder: Path) -> list[_MeshSpec]:
    if not isinstance(value, list) or not value:
        raise reader.error("mesh", f"expected one or more [[mesh]] tables, got {_describe(value)}")
    specs = []
    for index, item in enumerate(value):
        key = f"mesh[{index}]"
        table = reader.table(item, key, _MESH_KEYS)
        if "path" not in table:
            raise reader.error(f"{key}.path", "missing (required)")
        if not isinstance(table["path"], str) or not table["path"]:
            raise reader.error(f"{key}.path", f"expected a file name, got {_describe(table['path'])}")
        scale = table.get("scale", 1.0)
        if isinstance(scale, list):
            scale = reader.vector3(scale, f"{key}.scale", low=0.0, low_open=True)
        else:
            scale = (reader.number(scale, f"{key}.scale", low=0.0, low_open=True),) * 3
        fit_height = table.get("fit_height")
        if fit_height is not None:
            fit_height = reader.number(fit_height, f"{key}.fit_height", low=0.0, low_open=True)
        specs.append(_MeshSpec(
            key=key,
            path=folder / table["path"],
            color=reader.color(table.get("color", list(_DEFAULT_COLOR)), f"{key}.color"),
            split=reader.integer(table.get("split", 1), f"{key}.split", 1),
            scale=scale,
            rotate_deg=reader.vector3(table.get("rotate_deg", [0.0, 0.0, 0.0]), f"{key}.rotate_deg"),
            fit_height=fit_height,
            translate=reader.vector3(table.get("translate", [0.0, 0.0, 0.0]), f"{key}.translate"),
            place_on_ground=reader.boolean(table.get("place_on_ground", False),
                                           f"{key}.place_on_ground"),
        ))
    return specs


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
            bar.set_description_str(f"loading scene: {doing} {spec.path.name}", refresh=False)
            bar.update(1)
        return [_load_mesh(reader, spec, ground_y, step) for spec in specs]


def _load_mesh(reader: _Reader, spec: _MeshSpec, ground_y: float, step) -> MeshEntry:
    try:
        mesh = Mesh.load(spec.path)
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
        extent = np.ptp(points[used, 1])
        if not extent > 0:
            raise reader.error(f"{spec.key}.fit_height", "the mesh is flat in y (height 0)")
        points *= spec.fit_height / extent
    points += np.array(spec.translate)
    if spec.place_on_ground:
        points[:, 1] += ground_y - points[used, 1].min()
    try:
        transformed = Mesh(points, faces, name=mesh.name)
    except ValueError as error:  # e.g. a scale that overflows float32
        raise reader.error(f"{spec.key}.scale", f"the transformed mesh is invalid: {error}") from None
    step(spec, "done")
    return MeshEntry(mesh=transformed, color=spec.color, path=spec.path, split=spec.split)


def _make_ground(spec: dict, meshes: list[Mesh]) -> Ground:
    lo = np.min([m.bounds[0] for m in meshes], axis=0)
    hi = np.max([m.bounds[1] for m in meshes], axis=0)
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
    return Ground(mesh=Mesh(vertices, faces, name="ground"), y=y, size=size, color=spec["color"])
