"""A scene as its files describe it, before it is built: the plain records
that every reader (TOML scene files, Mitsuba 3's XML, a bare mesh file)
makes and scenefile.load builds (pbrt-v4's parse-then-create split)."""
from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..mesh import Mesh
from ..render.camera import Camera
from ..render.light import Light

Color = tuple[float, float, float]
Vec3 = tuple[float, float, float]


class SceneFileError(ValueError):
    """A scene file that cannot be read; the message names the file and the key."""


@dataclass(frozen=True)
class Ground:
    mesh: Mesh  # two triangles facing +y
    y: float
    size: float
    color: Color
    material: dict | None = None


@dataclass(frozen=True)
class MeshEntry:
    mesh: Mesh  # split and transformed
    color: Color
    path: Path | None  # None for a shape
    split: int = 1
    material: dict | None = None  # the path integrator's BSDF spec (None: the default)
    emitter: dict | None = None   # an area emitter's spec, without its "mesh"
    #: (4,) centre and radius where the shape is an analytic sphere (Scene's
    #: spheres, after every mesh); ``mesh`` is then its tessellation, which
    #: only the peers that trace triangles read (bench/)
    sphere: np.ndarray | None = None


@dataclass(frozen=True)
class InstanceEntry:
    """One [[instance]] table: copies of meshes[mesh]."""
    mesh: int
    transforms: np.ndarray  # (copies, 3, 4) float64, object -> world: [A | t]
    material: dict | None = None  # every copy's own BSDF spec (None: its mesh's)


@dataclass
class SceneDescription:
    path: Path
    width: int
    height: int
    camera: Camera
    light: Light
    meshes: list[MeshEntry] = field(default_factory=list)
    ground: Ground | None = None
    instances: list[InstanceEntry] = field(default_factory=list)  # empty: no [[instance]]
    emitters: list[dict] = field(default_factory=list)  # the [[emitter]] tables
    #: what the file says about rendering it besides the size (Mitsuba's
    #: XML: shading, spp, max_depth, rr_depth, rfilter); a TOML file says none
    options: dict = field(default_factory=dict)
    #: a Mitsuba sensor's (fov in degrees, fov_axis): that fov holds along
    #: that axis at any image size (LoadedScene.camera_at); None: the
    #: camera's vertical fov holds (a TOML file's)
    sensor_fov: tuple[float, str] | None = None
    #: what lights a file with no emitter: the renderer's default sky (a
    #: TOML file's, as documented), or nothing (Mitsuba's XML: black)
    default_sky: bool = True

    def surfaces(self) -> list:
        """Every surface's entry in geom_id order: the triangle meshes in
        file order, the ground, then the analytic spheres (Scene's order)."""
        return ([entry for entry in self.meshes if entry.sphere is None]
                + ([self.ground] if self.ground is not None else [])
                + [entry for entry in self.meshes if entry.sphere is not None])

    def spheres(self) -> np.ndarray | None:
        """Scene's ``spheres``: (S, 4) centres and radii, or None."""
        found = [entry.sphere for entry in self.meshes if entry.sphere is not None]
        return np.array(found, np.float64) if found else None

    def materials(self) -> list[dict] | None:
        """Renderer.materials of every surface (surfaces' order): each
        entry's, else a two-sided diffuse of its colour; None when no entry
        names one."""
        entries = self.surfaces()
        if all(entry.material is None for entry in entries):
            return None
        return [entry.material or {"type": "twosided", "bsdf": {
            "type": "diffuse", "reflectance": list(entry.color)}} for entry in entries]

    def inputs(self) -> tuple[Path, ...]:
        """The files the scene reads: its own, its meshes' and its
        environment maps' (a renderer writing one of them would destroy its
        own input)."""
        files = [self.path] + [entry.path for entry in self.meshes if entry.path is not None]
        files += [Path(e["filename"]) for e in self.emitters
                  if isinstance(e, dict) and isinstance(e.get("filename"), (str, Path))]
        return tuple(dict.fromkeys(files))

    def all_emitters(self) -> list[dict] | None:
        """Renderer.emitters: the meshes' area emitters, then the [[emitter]]
        tables; when there are none, None (the default sky) for a file whose
        default_sky says so, else none at all."""
        found = [{**entry.emitter, "mesh": k} for k, entry in enumerate(self.surfaces())
                 if getattr(entry, "emitter", None) is not None] + list(self.emitters)
        return found or (None if self.default_sky else [])

    @property
    def triangle_count(self) -> int:
        """Triangles stored: each mesh (and the ground) once, however often drawn."""
        return sum(m.triangle_count for m, _ in self.geometries())

    @property
    def drawn_triangle_count(self) -> int:
        """Triangles in the picture's world: each mesh times its copies."""
        if not self.instances:
            return self.triangle_count
        ground = 0 if self.ground is None else self.ground.mesh.triangle_count
        return ground + sum(len(entry.transforms) * self.meshes[entry.mesh].mesh.triangle_count
                            for entry in self.instances)

    def placements(self) -> list[tuple[int, np.ndarray]]:
        """Scene's ``instances``: (mesh index, (3, 4) transform) of every copy
        in file order, then the ground's (identity); [] without [[instance]]."""
        if not self.instances:
            return []
        found = [(entry.mesh, transform) for entry in self.instances
                 for transform in entry.transforms]
        if self.ground is not None:
            found.append((len(self.meshes), np.eye(3, 4)))
        return found

    def instance_materials(self) -> list[dict | None] | None:
        """Renderer.instance_materials, in placements' order: each copy's
        [[instance]] material (None: its mesh's, and the ground's); None when
        no table names one."""
        if all(entry.material is None for entry in self.instances):
            return None
        found = [entry.material for entry in self.instances for _ in entry.transforms]
        if self.ground is not None:
            found.append(None)
        return found

    def geometries(self) -> list[tuple[Mesh, Color]]:
        """(mesh, colour) of every triangle surface: the meshes in file
        order, then the ground (the spheres follow them: surfaces)."""
        found = [(entry.mesh, entry.color) for entry in self.meshes if entry.sphere is None]
        if self.ground is not None:
            found.append((self.ground.mesh, self.ground.color))
        return found


def shape_mesh(shape: str) -> Mesh:
    """One of Mitsuba's shapes as a mesh, in its own frame: "rectangle"
    ([-1, 1]^2 at z = 0, its normal +z), "cube" ([-1, 1]^3, normals out) or
    "sphere" (radius 1 about the origin: an icosphere of 20 * 4^4 faces).
    Shaded as Mitsuba's: the cube's faces flat (its own face_normals), the
    sphere with its exact normals at the vertices (Mitsuba's sphere is
    analytic), the flat rectangle either way."""
    if shape == "rectangle":
        return Mesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]],
                    name="rectangle")
    vertices, faces = _unit_shape(shape)
    if shape == "cube":
        return Mesh(vertices, faces, name=shape, face_normals=True)
    return Mesh(vertices, faces, name=shape, normals=vertices)


@functools.lru_cache(maxsize=None)
def _unit_shape(shape: str) -> tuple[np.ndarray, np.ndarray]:
    """The cube's or the sphere's vertices and faces, made once rather than
    subdivided anew for each shape (an XML file may hold thousands of
    spheres).  Read only (Mesh copies what it is given)."""
    import trimesh
    made = (trimesh.creation.box(extents=(2.0, 2.0, 2.0)) if shape == "cube"
            else trimesh.creation.icosphere(subdivisions=4, radius=1.0))
    vertices, faces = np.array(made.vertices), np.array(made.faces)
    vertices.flags.writeable = faces.flags.writeable = False
    return vertices, faces
