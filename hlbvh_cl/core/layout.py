"""numpy mirror of the kernels' structs (HEADERS): the one place Python
restates them.

The constants are parsed from the headers themselves, so they exist once.
tests/device/test_devices.py compiles a probe kernel that includes each header
and reports sizeof/offsetof on the device, and checks them against these
dtypes.
"""
from __future__ import annotations

import re

import numpy as np

from .paths import kernel_dir

#: The headers this module mirrors, named from the kernels' root.
HEADERS = ("core/aabb.h", "core/tree.h", "build/config.h", "build/flat_node.h",
           "query/records.h", "render/camera.h", "render/tiles.h", "render/integrators/direct.h",
           "render/integrators/path.h")


def header_text() -> str:
    """The mirrored headers' text, one after another."""
    return "\n".join((kernel_dir() / name).read_text() for name in HEADERS)


def _read_constants(text: str) -> dict[str, float | int]:
    constants: dict[str, float | int] = {}
    for name, value in re.findall(r"^#define\s+([A-Z_][A-Z0-9_]*)\s+\(?(-?[0-9.]+)f?\)?\s*$",
                                  text, flags=re.M):
        constants[name] = float(value) if "." in value else int(value)
    return constants


CONSTANTS = _read_constants(header_text())
CLUSTER_BITS: int = CONSTANTS["CLUSTER_BITS"]
MAX_LEAF_SIZE: int = CONSTANTS["MAX_LEAF_SIZE"]
EMPTY_CHILD: int = CONSTANTS["EMPTY_CHILD"]
WIDE_ARITY: int = CONSTANTS["WIDE_ARITY"]
TILE_ROWS: int = CONSTANTS["TILE_ROWS"]
TILE_COLUMNS: int = CONSTANTS["TILE_COLUMNS"]
TRANSMISSION_TABLE: int = CONSTANTS["TRANSMISSION_TABLE"]

_f3 = (np.float32, 3)

AABB = np.dtype([("lo", *_f3), ("hi", *_f3)])

FLAT_NODE = np.dtype([
    ("left_lo", *_f3), ("left_hi", *_f3),
    ("right_lo", *_f3), ("right_hi", *_f3),
    ("left", np.int32), ("right", np.int32),
    ("left_count", np.uint32), ("right_count", np.uint32),
])

FLAT_SUMMARY = np.dtype([
    ("node_count", np.int32), ("leaf_count", np.int32), ("depth", np.int32),
    ("clusters", np.int32), ("root_is_leaf", np.int32), ("sah_cost", np.float32),
    ("lo", *_f3), ("hi", *_f3),
])

_wide = (np.float32, WIDE_ARITY)
WIDE_NODE = np.dtype([
    ("lo_x", *_wide), ("hi_x", *_wide), ("lo_y", *_wide), ("hi_y", *_wide),
    ("lo_z", *_wide), ("hi_z", *_wide),
    ("child", np.int32, WIDE_ARITY), ("count", np.uint32, WIDE_ARITY),
])

WIDE_DIPOLES = np.dtype([(name, *_wide) for name in
                         ("p_x", "p_y", "p_z", "a_x", "a_y", "a_z", "area", "radius")])

TRIANGLE = np.dtype([("v0", *_f3), ("v1", *_f3), ("v2", *_f3)])

#: a compact tree's leaf record: its corners, in 12-byte cells from the record (core/leaf.h)
INDEXED_TRIANGLE = np.dtype([("corner", np.int32, 3)])

TRIANGLE_REF = np.dtype([("geom_id", np.int32), ("prim_id", np.int32)])

INSTANCE = np.dtype([("to_mesh", np.float32, 12), ("to_world", np.float32, 12),
                     ("normal_sign", np.float32), ("reach_scale", np.float32),
                     ("mask", np.uint32), ("mesh", np.int32), ("node_base", np.int32),
                     ("triangle_base", np.int32)])

RAY = np.dtype([("origin", *_f3), ("tmin", np.float32), ("direction", *_f3), ("tmax", np.float32)])

HIT = np.dtype([("t", np.float32), ("geom_id", np.int32), ("prim_id", np.int32),
                ("u", np.float32), ("v", np.float32), ("normal", *_f3)])

PINHOLE_CAMERA = np.dtype([("eye", *_f3), ("forward", *_f3), ("right", *_f3), ("up", *_f3)])

SHADE_PARAMS = np.dtype([
    ("light_direction", *_f3), ("light_intensity", np.float32), ("ambient", np.float32),
    ("sky_up", *_f3), ("sky_horizon", *_f3), ("sky_zenith", *_f3),
    ("ray_offset", np.float32), ("depth_near", np.float32), ("depth_far", np.float32),
    ("ao_distance", np.float32), ("ao_weight", np.float32),
])

PATH_MATERIAL = np.dtype([
    ("reflectance", *_f3), ("twosided", np.uint32), ("radiance", *_f3),
    ("emitter_pdf", np.float32), ("eta", *_f3), ("bsdf", np.uint32), ("k", *_f3),
    ("alpha", np.float32), ("transmittance", *_f3), ("distribution", np.uint32),
    ("specular", *_f3), ("specular_weight", np.float32), ("internal", np.float32),
    ("nonlinear", np.uint32), ("shading_base", np.int32), ("reserved", np.float32),
    ("transmission", np.float32, (TRANSMISSION_TABLE,)), ("light_sphere", np.float32, 4),
])

DELTA_LIGHT = np.dtype([("position", *_f3), ("type", np.uint32), ("value", *_f3),
                        ("probability", np.float32)])

PATH_PARAMS = np.dtype([
    ("environment", *_f3), ("environment_probability", np.float32), ("ray_offset", np.float32),
    ("light_triangles", np.uint32), ("delta_lights", np.uint32), ("max_depth", np.int32),
    ("rr_depth", np.int32), ("delta_probability", np.float32), ("instance_maps", np.uint32),
    ("envmap_to_world", np.float32, 9), ("envmap_width", np.uint32), ("envmap_height", np.uint32),
    ("light_spheres", np.uint32),
])

PATH_STATE = np.dtype([("throughput", *_f3), ("bsdf_pdf", np.float32), ("radiance", *_f3),
                       ("eta", np.float32)])

#: name in HEADERS -> dtype, for the layout test
STRUCTS = {"Aabb": AABB, "FlatNode": FLAT_NODE, "FlatSummary": FLAT_SUMMARY, "WideNode": WIDE_NODE,
           "WideDipoles": WIDE_DIPOLES, "Triangle": TRIANGLE,
           "IndexedTriangle": INDEXED_TRIANGLE,
           "TriangleRef": TRIANGLE_REF, "Instance": INSTANCE, "Ray": RAY, "Hit": HIT, "PinholeCamera": PINHOLE_CAMERA,
           "ShadeParams": SHADE_PARAMS, "PathMaterial": PATH_MATERIAL, "PathParams": PATH_PARAMS,
           "DeltaLight": DELTA_LIGHT,
           "PathState": PATH_STATE}
