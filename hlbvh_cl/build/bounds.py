"""Stage 1 host side: scene and centroid bounds, and the centroids (kernels/build/bounds.cl)."""
from __future__ import annotations

import pyopencl as cl

from ..core import layout

#: Work-items of the fold's one work-group at most (FOLD_GROUP in
#: kernels/build/bounds.cl, whose local arrays it sizes).
FOLD_GROUP = 256


def partial_count(rt, triangle_count: int) -> int:
    """Work-items of the first reduction level: enough to fill the device,
    about one per 64 triangles at most, in whole work-groups."""
    per_unit = 2048 if rt.profile.gpu else 256
    wanted = per_unit * rt.device.compute_units
    group = rt.group_size
    return max(group, min(wanted, -(-triangle_count // 64) * 64) // group * group)


def scene_bounds(rt, vertices: cl.Buffer, faces: cl.Buffer, triangle_count: int,
                 bounds: cl.Buffer, centroids: cl.Buffer, inverse_extent: cl.Buffer,
                 wait_for=None) -> list[cl.Event]:
    """bounds[0] <- box of all triangles, bounds[1] <- box of their centroids;
    centroids[i] <- triangle i's box centre (float4, w = 0); inverse_extent
    (float4) <- 1 / the centroid box's extent per axis, correctly rounded."""
    partials = partial_count(rt, triangle_count)
    geometry = rt.pool.take(partials * layout.AABB.itemsize)
    centroid_boxes = rt.pool.take(partials * layout.AABB.itemsize)
    kernel = rt.kernel("build/bounds.cl", "reduce_triangle_bounds",
                       STRIDED_SLICES=int(rt.profile.gpu), FOLD_GROUP=FOLD_GROUP)
    reduce = rt.run(kernel, partials,
                    vertices, faces, triangle_count, geometry, centroid_boxes, centroids,
                    wait_for=wait_for)
    fold_kernel = rt.kernel("build/bounds.cl", "fold_partial_bounds", STRIDED_SLICES=0,
                            FOLD_GROUP=FOLD_GROUP)
    group = min(FOLD_GROUP, rt.largest_group(fold_kernel))  # one work-group
    fold = rt.run(fold_kernel, group, geometry, centroid_boxes, partials, bounds,
                  inverse_extent, wait_for=[reduce], local_size=group)
    return [reduce, fold]
