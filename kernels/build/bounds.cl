/* Stage 1: scene bounds and centroid bounds by a two-level parallel reduction.
 *
 * The pass also stores every centroid (float4, in face order) for the Morton
 * stage, which then reads 16 sequential bytes per triangle instead of
 * gathering its three vertices again.
 *
 * Each work-item folds a slice of the triangles into partial boxes; one
 * work-group then folds the partials.  Slices are contiguous on CPUs (a grid-stride
 * loop measured far slower on PoCL) and interleaved on GPUs (coalescing):
 * STRIDED_SLICES selects.
 */
#include "core/portable.h"
#include "core/aabb.h"
#include "build/mesh.h"

NARROW_KERNEL
void reduce_triangle_bounds(__global const float *vertices, __global const int *faces,
                            int triangle_count, __global Aabb *partial_geometry,
                            __global Aabb *partial_centroids, __global float4 *centroids)
{
    int gid = get_global_id(0);
#if STRIDED_SLICES
    int begin = gid, end = triangle_count, step = get_global_size(0);
#else
    int per_item = (triangle_count + get_global_size(0) - 1) / get_global_size(0);
    int begin = gid * per_item, end = min(triangle_count, begin + per_item), step = 1;
#endif
    /* float3 accumulators: PoCL runs the loop as written, so the three axes
     * share each vector min/max instead of three scalar ones. */
    float3 geometry_lo = (float3)(INFINITY), geometry_hi = (float3)(-INFINITY);
    float3 centroid_lo = (float3)(INFINITY), centroid_hi = (float3)(-INFINITY);
    for (int face = begin; face < end; face += step) {
        float3 a, b, c;
        load_triangle(vertices, faces, face, &a, &b, &c);
        float3 lo = GROW_LO(GROW_LO(a, b), c), hi = GROW_HI(GROW_HI(a, b), c);
        float3 centroid = 0.5f * (lo + hi); /* = aabb_center of the triangle's box */
        geometry_lo = GROW_LO(geometry_lo, lo);
        geometry_hi = GROW_HI(geometry_hi, hi);
        centroid_lo = GROW_LO(centroid_lo, centroid);
        centroid_hi = GROW_HI(centroid_hi, centroid);
        centroids[face] = (float4)(centroid, 0.0f);
    }
    Aabb geometry = {{geometry_lo.x, geometry_lo.y, geometry_lo.z},
                     {geometry_hi.x, geometry_hi.y, geometry_hi.z}};
    Aabb centroid_box = {{centroid_lo.x, centroid_lo.y, centroid_lo.z},
                         {centroid_hi.x, centroid_hi.y, centroid_hi.z}};
    partial_geometry[gid] = geometry;
    partial_centroids[gid] = centroid_box;
}

/* a / b rounded to nearest, as a host divides, on any device: OpenCL C lets a
 * float divide be 2.5 ulp off (sec. 7.4; NVIDIA's is) unless built with
 * -cl-fp32-correctly-rounded-divide-sqrt, which is optional, and a compiler
 * may turn a divide in double back into that one.  The nearest quotient
 * leaves the smallest residual |a - q b|, which fma rounds once (exactly,
 * near the quotient), so step to a neighbour while it leaves a smaller one
 * (Markstein 1990). */
inline float divide_nearest(float a, float b)
{
    float q = a / b;
    for (int step = 0; step < 3; ++step) {
        float up = nextafter(q, INFINITY), down = nextafter(q, -INFINITY);
        float r = fabs(fma(-q, b, a));
        float r_up = fabs(fma(-up, b, a)), r_down = fabs(fma(-down, b, a));
        if (r_up < r && r_up <= r_down)
            q = up;
        else if (r_down < r)
            q = down;
        else
            break;
    }
    return q;
}

/* FOLD_GROUP (-D, hlbvh_cl/build/bounds.py): the fold's work-items at most,
 * its local arrays' length; the host launches a power of two no larger. */
#ifndef FOLD_GROUP
#error "FOLD_GROUP must be defined (-D FOLD_GROUP=...)"
#endif

/* bounds[0] = scene box, bounds[1] = box of the triangle centroids,
 * inverse_extent[0] = 1 / that box's extent per axis, correctly rounded (0
 * on a flat axis): one ulp of the Morton codes' scale moves many centroids
 * across a cell of 2^21 per axis, so every device must agree on it.
 *
 * One work-group folds the partials: each work-item a strided share, then
 * a tree in local memory (issue 57: a GPU has hundreds of thousands of
 * partials, which one work-item folded serially).  min and max are exact,
 * so any order of folding gives the same boxes. */
NARROW_KERNEL
void fold_partial_bounds(__global const Aabb *partial_geometry,
                         __global const Aabb *partial_centroids, int partial_count,
                         __global Aabb *bounds, __global float4 *inverse_extent)
{
    __local Aabb geometry[FOLD_GROUP];
    __local Aabb centroids[FOLD_GROUP];
    int item = (int)get_local_id(0), items = (int)get_local_size(0);
    Aabb g = aabb_empty(), c = aabb_empty();
    for (int i = item; i < partial_count; i += items) {
        g = aabb_union(g, partial_geometry[i]);
        c = aabb_union(c, partial_centroids[i]);
    }
    geometry[item] = g;
    centroids[item] = c;
    for (int step = items / 2; step > 0; step /= 2) {
        barrier(CLK_LOCAL_MEM_FENCE);
        if (item < step) {
            geometry[item] = aabb_union(geometry[item], geometry[item + step]);
            centroids[item] = aabb_union(centroids[item], centroids[item + step]);
        }
    }
    if (item != 0)
        return;
    bounds[0] = geometry[0];
    bounds[1] = centroids[0];
    float inverse[3];
    for (int k = 0; k < 3; ++k) {
        float extent = centroids[0].hi[k] - centroids[0].lo[k];
        inverse[k] = extent > 0.0f ? divide_nearest(1.0f, extent) : 0.0f;
    }
    inverse_extent[0] = (float4)(inverse[0], inverse[1], inverse[2], 0.0f);
}
