"""The path integrator ("path"): unidirectional path tracing, as pbrt-v4's
PathIntegrator and Mitsuba 3's ``path`` (kernels/render/integrators/path.cl).

Each sample of a pixel follows one path from the camera.  At each vertex x
(a closest hit) with throughput T it adds:

- the radiance the vertex sees emitted: an area emitter's front side, or the
  environment where the ray escapes, times T and, past the camera's ray,
  the power-heuristic weight of the BSDF sample against a light sample of
  that direction (Veach 1997, eq. 9.13);
- next-event estimation: one light sample (materials.py, emitters.py:
  an environment map (envmap.py), a delta light or a triangle, by power),
  T * f * cos * L / p_light times its weight against the BSDF's density,
  where its shadow ray is free.  A constant environment takes no light
  samples (below);

then samples the BSDF for the next direction (diffuse: cosine-distributed,
so T takes the albedo).  ``max_depth`` is Mitsuba's: the most segments a
path has (1: only what the camera sees emitting; 2: direct light; -1: no
limit), and from ``rr_depth`` on a path goes on with probability
q = min(max channel of T, 0.95) and T /= q (Russian roulette, Mitsuba's
rule), which keeps the estimate unbiased.

A constant environment is reached by BSDF sampling alone, as in pbrt-v4's
PathIntegrator (its UniformInfiniteLight draws no light sample where the
integrator allows incomplete densities, as that one does): against a constant
radiance the integrand is f cos V, which the BSDF's own sampling follows up
to the visibility, so directions uniform on the sphere only add noise (for
an opaque surface, half of them below it).  Unlike pbrt, whose light
sampler still picks the light and gets nothing, the light samples go to
the other lights.  A ray that escapes then takes the full weight, where no
light sample could have drawn it.

The stages run as a wavefront (Laine, Karras & Aila 2013): the path states
live in a device buffer, and per bounce the host enqueues the surface
stage, the shadow rays (query/rays.cl's any-hit walk), their resolve, and
the next closest hits (its closest-hit walk).  The paths that go on are
compacted on the device into the next bounce's first slots (a counter that
each work-group advances once, by atomic, for all its paths that go on; a
path's random numbers follow its pixel, so the image does not depend on the
order).  No bounce waits on the host: it reads each bounce's
count of live paths one bounce behind the device (while the device works
on the bounce it has queued), launches the next bounce over that many (an
upper bound, as paths only end), and stops when none is left.  The shadow
rays are compacted too, and each stage reads its count on the device: the
work-items past it return at once, and the surface stage and the walks
spread their work-groups that have paths or rays over the launch, so that a
CPU runtime's threads share them (kernels/core/launch.h).

Shading follows Mitsuba 3's rules (shading_tables; kernels/render/
integrators/path.cl): BSDFs and area emitters see each mesh's shading
normal, its vertex normals (Mesh.normals) interpolated at the hit and
normalised, or the geometric normal where the mesh has ``face_normals``; the
geometric normal decides only which side of the surface a new ray leaves
from.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from ...core import layout
from ...core.frame import warn_user
from ...core.paths import kernel_of
from ...device.runtime import Runtime, fold_events
from ..emitters import luminance
from ..random import salts8
from .base import Integrator, Look, Step

KERNEL = kernel_of(__name__)

#: Bounces at most when max_depth is -1 (no limit): Russian roulette ends a
#: path long before, with probability 1 - 0.95^(1024 - 5) at the least.
UNLIMITED_BOUNCES = 1024

#: How many bounces the host runs ahead of its count of live paths: one
#: keeps a bounce queued on the device while the host waits, and launches
#: each bounce over the paths of the one before; more would launch it over
#: an earlier bounce's, whose paths that ended since are empty rays.
LOOKAHEAD = 1

#: The random numbers' dimensions (random_unit's, kernels/render/random.h):
#: the camera's 0 and 1, then each bounce's light choice, three for its light
#: sample, three for its BSDF sample and its Russian roulette, whose salts
#: path_surface takes (random.salts8).
FIRST_BOUNCE_DIMENSION, DIMENSIONS_PER_BOUNCE = 2, 8

#: path_surface's work-group size on CPUs, and on GPUs
#: (kernels/render/integrators/path.h).
SURFACE_GROUP: int = layout.CONSTANTS["SURFACE_GROUP"]
SURFACE_GROUP_GPU: int = layout.CONSTANTS["SURFACE_GROUP_GPU"]

#: Mitsuba 3's RayEpsilon: a new ray starts (1 + max |x_i|) RAY_EPSILON off
#: the surface at x (path.h; path.cl's spawn_offset).
RAY_EPSILON: float = layout.CONSTANTS["RAY_EPSILON"]

#: DeltaLight.type (kernels/render/integrators/path.h).
LIGHT_POINT, LIGHT_DIRECTIONAL = 0, 1

#: The stages of a bounce that Path.depth_stats times: the closest hits
#: (at depth 0 the camera rays'), the surface stage, the shadow rays and
#: their resolve.
DEPTH_STAGES = ("closest", "shade", "occluded", "resolve")


#: Directions the kernels normalise in float32 (shading normals, the
#: instances' normal maps) keep their largest |component| within
#: [1 / STEADY, STEADY]: a mesh's normals of 1e20 (a scene file's scale
#: 1e-20 maps them so) had squared lengths past float32's range, and the
#: surface rendered black.
STEADY = 2.0 ** 16


def steadied(values, axis=None) -> np.ndarray:
    """float64 ``values``, each slice along ``axis`` (all at once for None)
    times the power of two that brings its largest |component| near 1,
    where that lies outside [1 / STEADY, STEADY]; else as they are.  A power
    of two scales every float32 operation of the kernels' interpolation and
    normalisation exactly, so the directions they give are the same bits."""
    values = np.array(values, np.float64)
    largest = np.abs(values).max(axis=axis, keepdims=True, initial=0.0)
    exponent = np.frexp(largest)[1]
    steady = (largest == 0) | ((1.0 / STEADY <= largest) & (largest <= STEADY))
    return values * np.ldexp(1.0, np.where(steady, 0, -exponent))


def spawn_floor(tree) -> float:
    """PathParams.ray_offset: the constant part of how far a new ray starts
    off the surface (path.cl's spawn_offset), in the tree's frame: Mitsuba
    3's RayEpsilon times 1 in the user's units, as its offset_p takes it, or
    times the scene's largest coordinate where that is smaller.  Mitsuba's
    1 alone is 8.9e-5 of the user's units whatever the scene's size: a
    scene 1e-4 across lost its shadows (its rays started past their
    occluders), one 1e-5 across all of them.  A scene of 1 or more, which
    the renders against Mitsuba are, keeps Mitsuba's offset; a small object
    beside a large ground keeps it too (the largest coordinate is the
    ground's)."""
    lo, hi = np.asarray(tree.bounds_lo, np.float64), np.asarray(tree.bounds_hi, np.float64)
    largest = float(max(np.abs(lo).max(), np.abs(hi).max()))  # in the frame
    return RAY_EPSILON * min(tree.scale, largest) if largest > 0 else RAY_EPSILON * tree.scale


#: A scene whose spawn offset (Mitsuba's RayEpsilon of its coordinates)
#: passes this fraction of its extent is warned of (warn_far_from_origin).
FAR_FRACTION = 1e-3


def warn_far_from_origin(tree) -> None:
    """A RuntimeWarning where the scene lies so far from the origin for its
    size that the offset of a new ray off a surface there (spawn_offset:
    RayEpsilon of the point's largest coordinate, as Mitsuba's offset_p,
    which float32's rounding there asks for in part) passes FAR_FRACTION
    of the scene's extent: shadows and contacts finer than it are lost
    there, as in Mitsuba (a unit scene 1e4 from the origin lost most of a
    shadow)."""
    lo, hi = (np.asarray(b, np.float64) / tree.scale for b in (tree.bounds_lo, tree.bounds_hi))
    largest, extent = float(max(np.abs(lo).max(), np.abs(hi).max())), float(np.linalg.norm(hi - lo))
    offset = RAY_EPSILON * (min(1.0, largest) + largest)  # spawn_floor's, and x's term
    if extent > 0 and offset > FAR_FRACTION * extent:
        warn_user(f"hlbvh_cl: the scene lies far from the origin for its size (coordinates up "
                  f"to {largest:.3g}, {extent:.3g} across): path-traced rays start up to "
                  f"{offset:.3g} off a surface there (Mitsuba's RayEpsilon rule), so shadows "
                  "and contacts finer than that are lost; move the scene nearer the origin")


def check_light_density(mesh: int, pdf: float, area: float, scale: float) -> None:
    """Refuses an area light (of `area`, the user's units) whose density per
    unit area in the tree's frame float32 cannot hold: a light far smaller
    than the scene's largest coordinate, by which the frame scales the scene
    (hlbvh_cl.core.frame), whose samples would all weigh nothing."""
    # headroom: the kernel multiplies it by a squared distance (up to 12 in
    # the frame) before it divides by a cosine
    if float(pdf) > float(np.finfo(np.float32).max) / 16:
        raise ValueError(
            f"the area emitter of mesh {mesh} is too small for its scene: its area is "
            f"{area:.3g} where the scene's coordinates reach about {1.0 / scale:.3g}, so its "
            f"sampling density overflows float32 in the scene's frame; bring the scene's "
            f"extent closer to its lights'")


def light_tables(look: Look, scale: float, bounds_lo, bounds_hi) -> dict:
    """The light sampling tables, in a tree's frame (coordinates times
    ``scale``): "materials", PathMaterial records with their emission;
    "vertices", float32 (K, 9) of the emissive triangles; "normals", float32
    (K, 9), their corners' shading normals (zeros: face normals); "cdf", their
    float32 CDF by power; "owners", the mesh of each; "deltas", DeltaLight
    records; "envmap_image" and "envmap_cdf", the environment map's pixels
    and CDFs (envmap.py; stand-ins without one); and the chances a light
    sample picks the environment map (0 for a constant environment) or a
    delta light (emitters.py)."""
    materials = look.materials.copy()
    vertices, normals, weights, owners, areas = [], [], [], [], {}
    # the triangles first, then the spheres (geom_ids after the meshes'),
    # as render/lights.h reads the table
    for mesh, radiance in sorted(look.emitters.area.items()):
        if mesh >= len(look.meshes):  # an analytic sphere: its row, centre and radius
            row = np.asarray(look.emissive[mesh], np.float64) * scale
            materials[mesh]["light_sphere"] = row  # render/lights.h's emitter_density
            area, keep = np.array([4.0 * np.pi * row[3] ** 2]), np.array([True])
            vertices.append(np.concatenate([row, np.zeros(5)])[None])
            normals.append(np.zeros((1, 9)))
        else:
            triangles = np.asarray(look.emissive[mesh], np.float64) * scale
            area = 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0],
                                                 triangles[:, 2] - triangles[:, 0]), axis=1)
            keep = area > 0
            vertices.append(triangles[keep].reshape(-1, 9))
            smooth = look.emissive_normals.get(mesh)
            # each triangle's corners alone are interpolated (render/lights.h)
            normals.append(np.zeros((int(keep.sum()), 9)) if smooth is None
                           else steadied(np.asarray(smooth)[keep].reshape(-1, 9), axis=1))
        areas[mesh] = float(area.sum())
        weights.append(area[keep] * luminance(radiance))
        owners.append(np.full(int(keep.sum()), mesh, np.int32))
        materials[mesh]["radiance"] = radiance
    weights = np.concatenate(weights) if weights else np.zeros(0)
    triangle_power = float(weights.sum())
    lo, hi = np.asarray(bounds_lo, np.float64), np.asarray(bounds_hi, np.float64)
    radius = 0.5 * float(np.linalg.norm(hi - lo)) or 1.0
    envmap = look.emitters.envmap
    # The power an environment map's light samples can deliver to the
    # scene's surfaces (area S): at most the cosine-weighted integral of
    # the luminance they sample (its excess over the map's mean: envmap.py)
    # per unit area, whose mean over orientations is a quarter of its
    # integral over the sphere.  pbrt-v4's power sampler counts the flux
    # through the scene's bounding sphere instead, 4 pi R^2 L (over pi),
    # which gave an open scene's sky most light samples and a small bright
    # lamp few.  A constant environment takes none (BSDF sampling alone: the
    # module's docstring).
    environment_power = 0.0 if envmap is None else \
        look.surface_area * scale * scale / (4.0 * np.pi) * envmap.tables[1]
    deltas = np.zeros(max(1, len(look.emitters.deltas)), layout.DELTA_LIGHT)
    delta_powers = []
    for k, (kind, vector, value) in enumerate(look.emitters.deltas):
        point = kind == "point"
        deltas[k]["type"] = LIGHT_POINT if point else LIGHT_DIRECTIONAL
        deltas[k]["position"] = vector * scale if point else vector
        # In the frame lengths are times `scale`: a point light's irradiance
        # I / d^2 stays the user's with I times scale^2; a directional
        # light's irradiance and every radiance need nothing.
        deltas[k]["value"] = value * (scale * scale) if point else value
        delta_powers.append(luminance(deltas[k]["value"]) * (4.0 if point else radius * radius))
    total = environment_power + triangle_power + sum(delta_powers)
    chance = (lambda power: power / total) if total > 0 else (lambda power: 0.0)
    for k, power in enumerate(delta_powers):
        deltas[k]["probability"] = chance(power)
    if triangle_power > 0:
        for mesh, radiance in look.emitters.area.items():
            pdf = chance(triangle_power) * luminance(radiance) / triangle_power
            check_light_density(mesh, pdf, areas[mesh] / (scale * scale), scale)
            materials[mesh]["emitter_pdf"] = pdf
        cdf = np.cumsum(weights) / triangle_power
        cdf[-1] = 1.0
    else:
        cdf = np.zeros(0)
    if envmap is not None:
        envmap_image, envmap_cdf = envmap.image, envmap.tables[0]
    else:  # none: stand-ins, since OpenCL has no empty buffers
        envmap_image, envmap_cdf = np.zeros(4, np.float32), np.zeros(4, np.float32)
    return {"materials": materials, "envmap_image": envmap_image, "envmap_cdf": envmap_cdf,
            "vertices": (np.concatenate(vertices).astype(np.float32) if vertices
                         else np.zeros((0, 9), np.float32)),
            "normals": (np.concatenate(normals).astype(np.float32) if normals
                        else np.zeros((0, 9), np.float32)),
            "cdf": cdf.astype(np.float32),
            "owners": np.concatenate(owners) if owners else np.zeros(0, np.int32),
            "deltas": deltas, "delta_count": len(look.emitters.deltas),
            "environment_probability": chance(environment_power),
            "delta_probability": sum(chance(power) for power in delta_powers)}


def shading_tables(meshes) -> dict:
    """The shading normals of the meshes without face normals, as the kernels
    read them: "faces", uint32 (T, 3) vertex rows into "normals", float32
    (V, 3), the meshes one after another; "bases", int32 per mesh, its first
    row of "faces" (-1: face normals)."""
    faces, normals, bases = [], [], np.full(len(meshes), -1, np.int32)
    triangles = vertices = 0
    for k, mesh in enumerate(meshes):
        if mesh.face_normals:
            continue
        bases[k] = triangles
        faces.append(np.asarray(mesh.faces, np.int64) + vertices)
        normals.append(steadied(mesh.normals))  # one factor: a mesh's are interpolated together
        triangles += mesh.triangle_count
        vertices += mesh.vertex_count
    if vertices >= 2 ** 32 or triangles >= 2 ** 31:
        raise ValueError(f"the meshes' shading normals ({vertices:,} vertices, {triangles:,} "
                         "triangles) overflow the path integrator's 32-bit indices; give the "
                         "largest meshes face_normals=True")
    return {"faces": (np.concatenate(faces).astype(np.uint32) if faces
                      else np.zeros((0, 3), np.uint32)),
            "normals": (np.concatenate(normals).astype(np.float32) if normals
                        else np.zeros((0, 3), np.float32)),
            "bases": bases}


def instance_materials(materials: np.ndarray, look: Look) -> tuple[np.ndarray, np.ndarray]:
    """The meshes' PathMaterial records (emission and shading normals set)
    followed by the instances' own (look.instance_materials), each taking its
    mesh's emission and shading normals; and int32 per instance, the record
    its hits read (-1: its mesh's, geom_id; a stand-in row for a flat
    scene, which reads none)."""
    rows = look.instance_material_rows
    if look.instance_meshes is None or not len(rows):
        return materials, np.full(1, -1, np.int32)
    own = np.asarray(look.instance_materials).copy()
    which = np.flatnonzero(rows >= 0)
    meshes = np.asarray(look.instance_meshes)[which]
    for name in ("radiance", "emitter_pdf", "shading_base"):
        own[name][rows[which]] = materials[name][meshes]
    index = np.where(rows >= 0, rows + len(materials), -1).astype(np.int32)
    return np.concatenate([materials, own]), index


def light_params(look: Look, tables: dict) -> np.ndarray:
    """PathParams with the lights' fields set from light_tables' ``tables``
    (the environment, the chances of picking it or a delta light, the
    counts of emissive triangles and delta lights, the map's size and
    rotation); the path's fields are the caller's."""
    params = np.zeros((), layout.PATH_PARAMS)
    environment = look.emitters.environment
    params["environment"] = environment if environment is not None else 0.0
    params["environment_probability"] = tables["environment_probability"]
    params["delta_probability"] = tables["delta_probability"]
    params["light_spheres"] = int((tables["owners"] >= len(look.meshes)).sum())
    params["light_triangles"] = len(tables["cdf"]) - params["light_spheres"]
    params["delta_lights"] = tables["delta_count"]
    envmap_params(params, look.emitters.envmap)
    return params


def envmap_params(params: np.ndarray, envmap) -> None:
    """PathParams' environment map fields: its size and rotation (width 0
    without one: the environment is constant)."""
    if envmap is None:
        params["envmap_width"] = params["envmap_height"] = 0
        params["envmap_to_world"] = np.eye(3).reshape(-1)
        return
    params["envmap_height"], params["envmap_width"] = envmap.image.shape[:2]
    params["envmap_to_world"] = envmap.to_world.reshape(-1)


class Path(Integrator):
    """Path tracing with next-event estimation and MIS (the module's
    definitions)."""

    modes = ("path",)
    progressive = True
    needs_instances = True

    #: Bytes per pixel of a pass of the integrator's own buffers.
    PER_PIXEL = {"path states": layout.PATH_STATE.itemsize, "shadow rays": layout.RAY.itemsize,
                 "occluded": 1, "pending light": 16, "shadow paths": 4,
                 "next rays": layout.RAY.itemsize, "path numbers": 8}

    #: float4 of AOV sums per pixel: (albedo, depth) and (shading normal, 0);
    #: bytes per pixel of the AOV sums and of the AOV image (7 floats).
    AOV_GROUPS = 2
    AOV_SUMS, AOV_IMAGE = 16 * AOV_GROUPS, 28

    def __init__(self):
        self._pixels = 0
        self._aov_pixels = self._aov_image_pixels = 0
        self._aovs = False
        self._tables: dict[str, cl.Buffer] = {}
        self._shading: tuple = ((), {})  # (the meshes, their shading buffers)
        self.last_bounces: list[int] = []
        self.last_shadow_rays: list[int] = []
        self._reset_depths()

    def _reset_depths(self) -> None:
        """No bounce timed or counted yet (depth_stats): the launches in
        flight and the milliseconds of those done, by (stage, depth)."""
        self._depth_events: dict[tuple[str, int], list[cl.Event]] = {}
        self._depth_ms: dict[tuple[str, int], float] = {}
        self._depth_paths: list[int] = []
        self._depth_shadow_rays: list[int] = []

    def depth_stats(self) -> dict:
        """Where the last render's paths spent their device time, bounce by
        bounce: "paths", how many paths each depth shaded (depth d: where
        the path's segment d + 1 ends; depth 0: one per pixel and sample),
        and per DEPTH_STAGES stage its milliseconds at each depth, summed over
        the render's samples (a sample that Ctrl-C cut short is left out);
        and "shadow_rays", the shadow rays each depth's light samples cast,
        as the device counted them (none where a vertex took no light
        sample, or its sample carried no light).  The renderer's stats give
        it as "depths"."""
        self.rt.wait([event for found in self._depth_events.values() for event in found])
        fold_events(self._depth_events, self._depth_ms)
        depths = range(len(self._depth_paths))
        return {"paths": list(self._depth_paths),
                "shadow_rays": list(self._depth_shadow_rays),
                **{stage: [self._depth_ms.get((stage, d), 0.0) for d in depths]
                   for stage in DEPTH_STAGES}}

    def buffer_sizes(self, pixels: int) -> dict[str, int]:
        return {name: size * pixels for name, size in self.PER_PIXEL.items()}

    def passes(self, settings) -> int:
        return 0  # the bounces are counted as they happen (last_bounces)

    def radiance(self, settings) -> bool:
        return True

    def prepare(self, rt: Runtime, settings, tree, look: Look, pixels: int) -> None:
        self.rt, self.settings = rt, settings
        self._kernels = {name: path_kernel(rt, name) for name in
                         ("path_surface", "path_unoccluded", "path_finish")}
        if pixels > self._pixels:
            context, rw = rt.context, cl.mem_flags.READ_WRITE
            self.states = cl.Buffer(context, rw, pixels * layout.PATH_STATE.itemsize)
            self.shadow = cl.Buffer(context, rw, pixels * layout.RAY.itemsize)
            self.occluded = cl.Buffer(context, rw, pixels)
            self.pending = cl.Buffer(context, rw, pixels * 16)  # float4
            self.shadow_paths = cl.Buffer(context, rw, pixels * 4)
            self.next_rays = cl.Buffer(context, rw, pixels * layout.RAY.itemsize)
            self.numbers = [cl.Buffer(context, rw, pixels * 4) for _ in range(2)]
            self.live = cl.Buffer(context, rw, 4 * (UNLIMITED_BOUNCES + 1))
            self.shadows = cl.Buffer(context, rw, 4 * UNLIMITED_BOUNCES)  # per pass
            self._pixels = pixels
        tables = light_tables(look, tree.scale, tree.bounds_lo, tree.bounds_hi)
        meshes, shading = self._shading
        if len(meshes) != len(look.meshes) or any(a is not b for a, b in zip(meshes, look.meshes)):
            # Meshes are immutable: their normals go to the device once
            found = shading_tables(look.meshes)
            shading = {name: upload_table(rt, found[name]) for name in ("faces", "normals")}
            shading["bases"] = found["bases"]
            self._shading = (look.meshes, shading)
        # the spheres after the meshes take their geometric normal (-1), as Mitsuba's
        tables["materials"]["shading_base"] = -1
        tables["materials"]["shading_base"][:len(shading["bases"])] = shading["bases"]
        maps = np.zeros((0, 9)) if look.instance_maps is None else \
            steadied(np.asarray(look.instance_maps).reshape(-1, 9), axis=1)
        tables["instance_maps"] = maps.astype(np.float32)
        tables["materials"], tables["instance_materials"] = instance_materials(
            tables["materials"], look)
        for name in ("materials", "vertices", "normals", "cdf", "owners", "deltas",
                     "instance_maps", "instance_materials", "envmap_image", "envmap_cdf"):
            self._tables[name] = upload_table(rt, tables[name])
        self._tables["shading_faces"] = shading["faces"]
        self._tables["shading_normals"] = shading["normals"]
        params = light_params(look, tables)
        params["ray_offset"] = spawn_floor(tree)
        warn_far_from_origin(tree)
        params["max_depth"] = settings.max_depth
        params["rr_depth"] = settings.rr_depth
        params["instance_maps"] = len(maps)
        self._params = params
        self._aovs = False
        self._length_scale = np.float32(1.0 / tree.scale)
        self._live = np.zeros(UNLIMITED_BOUNCES, np.uint32)
        self._shadow_counts = np.zeros(UNLIMITED_BOUNCES, np.uint32)
        self.last_bounces = []
        self.last_shadow_rays = []
        self._reset_depths()

    @classmethod
    def aov_sizes(cls, pixels: int, image_pixels: int) -> dict[str, int]:
        """Bytes of the AOV buffers for passes of ``pixels`` and an image of
        ``image_pixels`` (for the allocation check; 0: none, as prepare_aovs)."""
        sizes = {"AOV sums": cls.AOV_SUMS * pixels}
        if image_pixels:
            sizes["AOV image"] = cls.AOV_IMAGE * image_pixels
        return sizes

    def prepare_aovs(self, pixels: int, image_pixels: int) -> cl.Event | None:
        """After prepare: this render also sums each pixel's first-hit AOVs
        (path_aovs), added to the whole image's zeroed sums by add_aovs and
        read by read_aovs.  ``image_pixels`` 0: a splatting film takes the
        sums instead (aovs_of_groups), and no AOV image is kept."""
        context, rw = self.rt.context, cl.mem_flags.READ_WRITE
        if pixels > self._aov_pixels:
            self.aov_sums = cl.Buffer(context, rw, self.AOV_SUMS * pixels)
            self._aov_pixels = pixels
        if image_pixels > self._aov_image_pixels:
            self.aov_image = cl.Buffer(context, rw, self.AOV_IMAGE * image_pixels)
            self._aov_image_pixels = image_pixels
        self._aov_kernels = {name: path_kernel(self.rt, name)
                             for name in ("path_aovs", "path_aov_add")}
        self._aovs = True
        if image_pixels == 0:
            return None
        return cl.enqueue_fill_buffer(self.rt.queue, self.aov_image, np.float32(0), 0,
                                      self.AOV_IMAGE * image_pixels)

    def add_aovs(self, band, width: int) -> cl.Event:
        """The band's AOV sums added to the whole image's."""
        return self.rt.run(self._aov_kernels["path_aov_add"], band.tile_range, self.aov_sums,
                           np.uint32(width), band.first_row, band.rows, self.aov_image)

    def read_aovs(self, height: int, width: int, rows) -> dict[str, np.ndarray]:
        """The AOV image: "albedo" and "normal" (height, width, 3) and "depth"
        (height, width), float32 means over each pixel's samples; ``rows``:
        (first row, rows, samples) of each run of rows alike (renderer.row_runs)."""
        out = np.empty((height, width, 7), np.float32)
        self.rt.wait([cl.enqueue_copy(self.rt.queue, out, self.aov_image, is_blocking=False)])
        for first, count, samples in rows:
            out[first:first + count] /= samples
        return {"albedo": out[..., 0:3].copy(), "normal": out[..., 3:6].copy(),
                "depth": out[..., 6].copy()}

    @staticmethod
    def aovs_of_groups(means: np.ndarray) -> dict[str, np.ndarray]:
        """The AOV image from each pixel's means of its AOV_GROUPS float4
        (height, width, AOV_GROUPS, 4), as a splatting film gives them."""
        return {"albedo": means[..., 0, 0:3].copy(), "normal": means[..., 1, 0:3].copy(),
                "depth": means[..., 0, 3].copy()}

    def shade(self, step: Step) -> None:
        """The bounces of one sample of a band.  Pass d traces the
        live[d] paths that went on from pass d - 1, compacted on the device
        (path_surface), and their shadows[d] shadow rays; the host does not
        wait for those counts but launches over the last count it has read,
        LOOKAHEAD passes behind (never fewer, since paths only end), and the
        kernels read the counts on the device."""
        rt, band, kernels, events = step.rt, step.band, self._kernels, step.events
        # the samples before this one's, as the renderer's fold_times
        fold_events(self._depth_events, self._depth_ms)
        # the band's camera rays' closest hits, the renderer's last (Step)
        tagged = [("closest", 0, events["closest"][-1])]
        count, sample = np.uint32(band.count), np.uint32(step.sample)
        stream, first_pixel = np.uint32(step.stream), np.uint32(int(band.first_row) * band.width)
        tables = self._tables
        bounces = self.settings.max_depth if self.settings.max_depth > 0 else UNLIMITED_BOUNCES
        events["shade"].append(cl.enqueue_fill_buffer(rt.queue, self.live, np.uint32(0), 0,
                                                      4 * (bounces + 1)))
        events["shade"].append(cl.enqueue_fill_buffer(rt.queue, self.shadows, np.uint32(0), 0,
                                                      4 * bounces))
        events["shade"].append(cl.enqueue_copy(rt.queue, self.live, np.array([count]),
                                               is_blocking=False))
        if self._aovs:
            events["shade"].append(rt.run(
                self._aov_kernels["path_aovs"], band.count, step.rays, step.hits,
                tables["materials"], tables["shading_faces"], tables["shading_normals"],
                step.instances, tables["instance_maps"], tables["instance_materials"],
                self._params, self._length_scale,
                count, sample, self.aov_sums))
        rays, next_rays = step.rays, self.next_rays
        numbers, next_numbers = self.numbers
        bound = band.count  # paths in this pass at most
        reads = []
        for depth in range(bounces):
            at = np.int32(depth)
            if depth > 0:
                events["closest"].append(step.query.enqueue_intersect(
                    step.tree, rays, step.hits, bound, step.overflow,
                    instances=step.instances, counted=(self.live, depth)))
                tagged.append(("closest", depth, events["closest"][-1]))
            events["shade"].append(rt.run(
                kernels["path_surface"], bound, rays, step.hits, numbers, self.states,
                tables["materials"], tables["vertices"], tables["normals"], tables["cdf"],
                tables["owners"], tables["deltas"], tables["shading_faces"],
                tables["shading_normals"], step.instances, tables["instance_maps"],
                tables["instance_materials"], tables["envmap_image"], tables["envmap_cdf"],
                self._params, np.uint32(bound), first_pixel,
                salts8(int(stream), FIRST_BOUNCE_DIMENSION + DIMENSIONS_PER_BOUNCE * depth), at,
                self.live, next_rays, next_numbers, self.shadows, self.shadow, self.pending,
                self.shadow_paths,
                local_size=SURFACE_GROUP_GPU if rt.profile.gpu else SURFACE_GROUP))
            events["occluded"].append(step.query.enqueue_occluded(
                step.tree, self.shadow, self.occluded, bound, step.overflow,
                counted=(self.shadows, depth)))
            events["resolve"].append(rt.run(
                kernels["path_unoccluded"], bound, self.occluded, self.pending,
                self.shadow_paths, self.shadows, at, np.uint32(bound), self.states))
            tagged += [(stage, depth, events[stage][-1]) for stage in DEPTH_STAGES[1:]]
            reads.append(cl.enqueue_copy(rt.queue, self._live[depth:depth + 1], self.live,
                                         src_offset=4 * (depth + 1), is_blocking=False))
            rays, next_rays = next_rays, rays
            numbers, next_numbers = next_numbers, numbers
            if depth >= LOOKAHEAD:
                rt.wait([reads[depth - LOOKAHEAD]])
                bound = int(self._live[depth - LOOKAHEAD])
                if bound == 0:
                    break  # every path ended: what is enqueued after it finds none
        # and the shadow rays each pass cast, as its shadow-ray launch read them
        passes = len(reads)
        rt.wait(reads + [cl.enqueue_copy(rt.queue, self._shadow_counts[:passes], self.shadows,
                                         is_blocking=False)])
        self.last_bounces.append(int(self._live[:passes].sum()))
        self.last_shadow_rays.append(int(self._shadow_counts[:passes].sum()))
        for stage, depth, event in tagged:
            self._depth_events.setdefault((stage, depth), []).append(event)
        # the paths each depth shaded: the band's, then those that went on
        shaded = [band.count] + [int(n) for n in self._live[:passes - 1]]
        self._depth_paths.extend([0] * (len(shaded) - len(self._depth_paths)))
        self._depth_shadow_rays.extend([0] * (len(shaded) - len(self._depth_shadow_rays)))
        for depth, paths in enumerate(shaded):
            self._depth_paths[depth] += paths
            self._depth_shadow_rays[depth] += int(self._shadow_counts[depth])
        events["resolve"].append(rt.run(kernels["path_finish"], band.count, self.states, count,
                                        sample, step.accum))
        step.done(events["resolve"][-1])


def path_kernel(rt: Runtime, name: str) -> cl.Kernel:
    """Kernel ``name`` of path.cl, built once per runtime for all of them:
    on CPUs with PREFETCH (its stages ask for their scattered lines ahead)."""
    return rt.kernel(KERNEL, name, **rt.prefetch_defines)


def upload_table(rt: Runtime, array: np.ndarray) -> cl.Buffer:
    """A read-only device copy of ``array``, of one element at least (OpenCL
    has no empty buffers)."""
    data = np.ascontiguousarray(array)
    return cl.Buffer(rt.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                     hostbuf=data if data.nbytes else np.zeros(4, np.uint8))
