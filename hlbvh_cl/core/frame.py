"""The frame a scene is built and traced in: its coordinates times a power of two.

The kernels compute in float32 with products of two and three coordinates
(box areas, the SAH, Woop's edge functions and their double refinement):
coordinates near 1e-20 underflow there and near 1e20 overflow, so hits go
missing or come back with t = inf.  A scene whose largest coordinate lies
outside [2^-24, 2^24] is therefore built in a frame scaled by 2^k, which
brings it to [0.5, 1); ray origins take the same 2^k on their way in, and
each direction a power of two of its own (hlbvh_cl/query/rays.py, into_frame), by
which t is divided back.  Multiplying by a power of two is exact (barring
subnormal results), and every float operation commutes with it, so the hits
are the user's own: t, u, v and the unit normal.  Other scenes keep a scale
of 1 and nothing is copied.
"""
from __future__ import annotations

import inspect
import math
import os
import warnings

import numpy as np

#: Largest coordinate magnitudes traced as given; others are rescaled.
SAFE_RANGE = (2.0**-24, 2.0**24)


def scale_for(largest: float) -> float:
    """The power of two by which a scene whose largest coordinate magnitude
    is ``largest`` is built: 1 inside SAFE_RANGE (or for an all-zero scene),
    else the one that brings ``largest`` to [0.5, 1)."""
    if largest == 0.0 or SAFE_RANGE[0] <= largest <= SAFE_RANGE[1]:
        return 1.0
    return 2.0 ** -math.frexp(largest)[1]


def largest_magnitude(points: np.ndarray) -> float:
    return float(np.abs(points).max()) if points.size else 0.0


def used_vertices(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The vertices some face references (the array itself when all are):
    one that no face uses must not set a frame or a box, where a far one
    would scale every triangle into float32's underflow."""
    used = np.zeros(len(vertices), bool)
    used[np.asarray(faces).ravel()] = True
    return vertices if used.all() else vertices[used]


def largest_used(vertices: np.ndarray, faces: np.ndarray) -> float:
    """largest_magnitude of used_vertices."""
    return largest_magnitude(used_vertices(vertices, faces))


def to_frame(points: np.ndarray, scale: float) -> np.ndarray:
    """float32 ``points`` times ``scale`` (exact; through float64, where a
    scale like 2^140 is representable).  The array itself when scale is 1."""
    if scale == 1.0:
        return points
    with np.errstate(over="ignore"):  # an overflow becomes inf, which callers report
        return (points.astype(np.float64) * scale).astype(np.float32)


def describe(scale: float) -> str:
    return f"2^{round(math.log2(scale))}"


def vanishing(vertices: np.ndarray, faces: np.ndarray, scale: float, chunk: int = 1 << 20) -> int:
    """How many faces the frame makes degenerate: their float32 edge cross
    product (as the kernels' triangle test takes it, kernels/query/rays/
    triangle.h's geometric_normal) has a nonzero component with the given
    vertices and none with the vertices times ``scale``: rays never hit them
    there.  0 for a scale of 1 or more (the frame then holds coordinates
    below 1, whose products do not overflow, and no product shrinks)."""
    if scale >= 1.0:
        return 0
    given, framed = np.asarray(vertices, np.float32), to_frame(vertices, scale)
    lost = 0
    for start in range(0, len(faces), chunk):
        part = np.asarray(faces[start:start + chunk])
        lost += int(np.count_nonzero(_zero_normals(framed, part)
                                     & ~_zero_normals(given, part)))
    return lost


def warn_vanishing(mesh, geom_id: int, scale: float, largest: float, frame_of: str) -> None:
    """A RuntimeWarning if the frame of ``scale`` (``frame_of``: whose, set
    by a largest coordinate of ``largest``) makes some of ``mesh``'s
    triangles degenerate (vanishing): float32 cannot hold them there.  It
    names the user's line that built or changed the scene, however deep in
    the package the build was."""
    lost = vanishing(mesh.vertices, mesh.faces, scale)
    if lost:
        warn_user(f"hlbvh_cl: {lost} of mesh {geom_id}'s {mesh.triangle_count} triangles are "
                   f"too small for {frame_of} frame (its coordinates times {describe(scale)}, "
                   f"set by its largest, {largest:.3g}): their normals underflow float32 there, "
                   "so no ray hits them")


#: The smallest radius a sphere keeps in a frame: the ray test squares it
#: and its distances (kernels/query/rays/sphere.h), which float32 must hold
#: as normal numbers (2^-126 and up) with room to spare.
SMALLEST_SPHERE = 2.0**-60


def warn_vanishing_spheres(radii: np.ndarray, first_geom: int, scale: float,
                           largest: float, frame_of: str) -> None:
    """A RuntimeWarning if the frame of ``scale`` shrinks some spheres (of
    ``radii``, geom_ids from ``first_geom``) below SMALLEST_SPHERE: float32
    cannot hold their ray test there."""
    small = np.flatnonzero(np.asarray(radii, np.float64) * scale < SMALLEST_SPHERE)
    if len(small):
        warn_user(f"hlbvh_cl: {len(small)} sphere(s) (geom_id {first_geom + small[0]} first) "
                   f"are too small for {frame_of} frame (its coordinates times "
                   f"{describe(scale)}, set by its largest, {largest:.3g}): their squared "
                   "radius underflows float32 there, so rays miss them")


def warn_user(message: str) -> None:
    """A RuntimeWarning that names the user's line that built or changed
    the scene, however deep in the package the build was."""
    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__))) + os.sep
    level, caller = 1, inspect.currentframe()
    while caller is not None and caller.f_code.co_filename.startswith(package):
        caller, level = caller.f_back, level + 1
    warnings.warn(message, RuntimeWarning, stacklevel=level)


def _zero_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    a, b, c = points[faces[:, 0]], points[faces[:, 1]], points[faces[:, 2]]
    with np.errstate(all="ignore"):  # edges of a mesh spanning float32's range overflow
        e1, e2 = b - a, c - a
        return ((e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1] == 0)
                & (e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2] == 0)
                & (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] == 0))
