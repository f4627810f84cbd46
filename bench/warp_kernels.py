"""Warp's closest-point query as a @wp.kernel for the CPU, the peer of
bench/queries.py (WarpPeer).  A module of its own because Warp compiles the
kernels of a Python module together, at their first launch."""
from __future__ import annotations

import warp as wp

wp.config.quiet = True  # no banner on import, no "module loaded" lines
# (a parameter may not be named like a C++ keyword: Warp writes C++ with the same names)


@wp.kernel
def closest_points(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), max_distance: float,
                   with_sign: int, distance: wp.array(dtype=float),
                   closest: wp.array(dtype=wp.vec3), face: wp.array(dtype=wp.int32)):
    i = wp.tid()
    if with_sign:  # wp.mesh_query_point signs the distance by casting rays from the point
        found = wp.mesh_query_point(mesh, points[i], max_distance)
    else:
        found = wp.mesh_query_point_no_sign(mesh, points[i], max_distance)
    if found.result:
        closest[i] = wp.mesh_eval_position(mesh, found.face, found.u, found.v)
        distance[i] = wp.length(closest[i] - points[i])
        if with_sign:  # found.sign is left unset without it
            distance[i] = distance[i] * found.sign
        face[i] = found.face
    else:
        distance[i] = wp.inf
        face[i] = -1
