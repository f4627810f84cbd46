/* The checks of rays that are already on the device (pyopencl arrays given
 * to a query, hlbvh_cl/query/on_device.py): the checks hlbvh_cl/core/inputs.py
 * makes of numpy rays, run where the rays are, so that the call reads back
 * no more than its counters.
 *
 * Kernel
 *   check_rays  one work-item per ray; sets counters[2] where a ray is not
 *               what inputs.rays accepts (the host then names the first
 *               such ray as inputs.rays would), and counters[3] where a hit
 *               of the ray in a scene at scale 1 could lie past float32's
 *               range (the host then traces it in the scaled frame instead,
 *               query/rays.py's into_frame).
 *
 *   check_points  one work-item per point; sets counters[2] where a point is
 *               not finite or lies beyond `limit` in a coordinate (the point
 *               queries' range, query/points.py's POINT_RANGE)
 *
 *   unpack_rays  Open3D's packed rays (R, 6), origin then direction, into
 *               the (R, 3) arrays the queries read
 *
 *   kept_hits, hit_offsets  intersect_all's segments from its counts, on
 *               the device (query/all_hits.py): each ray's hits kept,
 *               min(count, max_hits), which parallel/scan.cl's uint32
 *               exclusive scan sums, then those sums as the int64 offsets
 *               the numpy query returns
 *
 * A ray is accepted when its origin is finite, its direction finite with a
 * component of magnitude >= FLT_MIN (else its inverse overflows: the slab
 * test), tmin finite and >= 0, and tmax not NaN and >= tmin.
 */
#include "core/portable.h"

__kernel void check_rays(__global const float* origins, __global const float* directions,
                         __global const float* tmin, const uint tmin_step,
                         __global const float* tmax, const uint tmax_step,
                         __global const uint* masks, const uint mask_step,
                         __global float* walked_tmax, const uint blind,
                         const float safe_range, const float safe_t,
                         __global int* counters, const uint ray_count)
{
    uint i = get_global_id(0);
    if (i >= ray_count)
        return;
    if (blind)
        walked_tmax[i] = masks[i * mask_step] == 0u ? -INFINITY : tmax[i * tmax_step];
    float far = 0.0f, longest = 0.0f;
    int finite = 1;
    for (uint k = 0; k < 3; ++k) {
        float o = origins[3 * (size_t)i + k], d = directions[3 * (size_t)i + k];
        finite &= isfinite(o) && isfinite(d);
        far = fmax(far, fabs(o));
        longest = fmax(longest, fabs(d));
    }
    float low = tmin[i * tmin_step], high = tmax[i * tmax_step];
    int valid = finite && longest >= FLT_MIN && isfinite(low) && low >= 0.0f
                && !isnan(high) && high >= low;
    if (!valid) {
        atomic_or(counters + 2, 1);
        return;
    }
    /* The farthest a hit can lie, sqrt(3) (|origin|_inf + the scene's
     * extent), over the direction's largest component: past safe_t the box
     * and triangle tests overflow and would miss it. */
    if (1.7320508f * (far + safe_range) > safe_t * longest)
        atomic_or(counters + 3, 1);
}

__kernel void check_points(__global const float* points, const float limit,
                           __global int* counters, const uint count)
{
    uint i = get_global_id(0);
    if (i >= count)
        return;
    int valid = 1;
    for (uint k = 0; k < 3; ++k)
        valid &= fabs(points[3 * (size_t)i + k]) <= limit;  /* false for NaN */
    if (!valid)
        atomic_or(counters + 2, 1);
}

__kernel void unpack_rays(__global const float* rays, __global float* origins,
                          __global float* directions, const uint count)
{
    uint i = get_global_id(0);
    if (i >= count)
        return;
    for (uint k = 0; k < 3; ++k) {
        origins[3 * (size_t)i + k] = rays[6 * (size_t)i + k];
        directions[3 * (size_t)i + k] = rays[6 * (size_t)i + 3 + k];
    }
}

__kernel void kept_hits(__global const int* counts, const uint max_hits, __global uint* kept,
                        const uint count)
{
    uint i = get_global_id(0);
    if (i < count)
        kept[i] = min((uint)counts[i], max_hits);
}

/* offsets[i] = scanned[i] for i <= count.  The uint32 scan wraps where the
 * hits pass 2^32 - 1 in all: then scanned[i] + kept[i] passes it for some
 * ray i, which sets counters[1] (the host refuses the call). */
__kernel void hit_offsets(__global const uint* scanned, __global const int* counts,
                          const uint max_hits, __global long* offsets, __global int* counters,
                          const uint count)
{
    uint i = get_global_id(0);
    if (i > count)
        return;
    offsets[i] = (long)scanned[i];
    if (i < count && (ulong)scanned[i] + min((uint)counts[i], max_hits) > (ulong)UINT_MAX)
        atomic_or(counters + 1, 1);
}
