/* Stage 1: scene bounds and centroid bounds by a two-level parallel reduction.
 *
 * Each work-item folds a slice of the triangles into partial boxes; one
 * work-item then folds the partials.  No local memory and no barriers:
 * simple to run correctly on PoCL's CPU device, and the second level touches
 * only a few thousand boxes.  Slices are contiguous on CPUs (a grid-stride
 * loop measured ~50x slower on PoCL) and interleaved on GPUs (coalescing):
 * STRIDED_SLICES selects.
 */
#include "hlbvh.h"

__kernel void reduce_triangle_bounds(__global const float *vertices, __global const int *faces,
                                     int triangle_count, __global Aabb *partial_geometry,
                                     __global Aabb *partial_centroids)
{
    int gid = get_global_id(0);
#if STRIDED_SLICES
    int begin = gid, end = triangle_count, step = get_global_size(0);
#else
    int per_item = (triangle_count + get_global_size(0) - 1) / get_global_size(0);
    int begin = gid * per_item, end = min(triangle_count, begin + per_item), step = 1;
#endif
    Aabb geometry = aabb_empty();
    Aabb centroids = aabb_empty();
    for (int face = begin; face < end; face += step) {
        float3 a, b, c;
        load_triangle(vertices, faces, face, &a, &b, &c);
        Aabb box = aabb_of_points(a, b, c);
        geometry = aabb_union(geometry, box);
        centroids = aabb_grow(centroids, aabb_center(box));
    }
    partial_geometry[gid] = geometry;
    partial_centroids[gid] = centroids;
}

/* bounds[0] = scene box, bounds[1] = box of the triangle centroids. */
__kernel void fold_partial_bounds(__global const Aabb *partial_geometry,
                                  __global const Aabb *partial_centroids, int partial_count,
                                  __global Aabb *bounds)
{
    if (get_global_id(0) != 0)
        return;
    Aabb geometry = aabb_empty();
    Aabb centroids = aabb_empty();
    for (int i = 0; i < partial_count; ++i) {
        geometry = aabb_union(geometry, partial_geometry[i]);
        centroids = aabb_union(centroids, partial_centroids[i]);
    }
    bounds[0] = geometry;
    bounds[1] = centroids;
}
