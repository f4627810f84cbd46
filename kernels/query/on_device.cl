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
 * A ray is accepted when its origin is finite, its direction finite with a
 * component of magnitude >= FLT_MIN (else its inverse overflows: the slab
 * test), tmin finite and >= 0, and tmax not NaN and >= tmin.
 */
#include "core/portable.h"

__kernel void check_rays(__global const float* origins, __global const float* directions,
                         __global const float* tmin, const uint tmin_step,
                         __global const float* tmax, const uint tmax_step,
                         const float safe_range, const float safe_t,
                         __global int* counters, const uint ray_count)
{
    uint i = get_global_id(0);
    if (i >= ray_count)
        return;
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
