/* Two-level scenes: a top tree whose leaves hold instances (hlbvh.h's
 * Instance), each a mesh's own tree under an affine map, as Embree's and
 * Mitsuba's instances (and pbrt-v4's TransformedPrimitive).  The walk of the
 * top tree is the one walk (walk.h) with a leaf visitor that maps the ray
 * into each instance's mesh frame and walks that mesh's tree with the same
 * query state: the ray is mapped, not renormalised, so t, the limit and
 * every hit found so far mean the same in both frames.  This header holds
 * the map; the visitors live with their queries (traverse.cl, all_hits.cl).
 * One ray per work-item (PACKET_SIZE 1): a packet's rays would need mapping
 * per instance as well. */
#ifndef INSTANCE_H
#define INSTANCE_H

#include "ray.h"
#include "triangle.h"

#if PACKET_SIZE != 1
#error "instanced scenes are traced one ray per work-item (PACKET_SIZE 1)"
#endif

/* The ray as the caller gave it (in the top tree's frame) with its mask:
 * what each instance maps. */
typedef struct {
    float origin[3];
    float direction[3];
    uint mask;
} WorldRay;

TRAVERSAL_INLINE void world_ray(WorldRay* w, const RayLanes* lanes, uint mask)
{
    for (int k = 0; k < 3; ++k) {
        w->origin[k] = lanes->origin[k][0];
        w->direction[k] = lanes->direction[k][0];
    }
    w->mask = mask;
}

/* Whether the ray sees the instance ((ray mask & instance mask) != 0, as
 * Embree), and if so the ray in the instance's mesh frame, prepared for its
 * tree (*out): origin
 * by the whole map, direction by its linear part, row by row in a fixed
 * order (FP_CONTRACT is off in triangle.h), so every device maps alike.  In
 * double where the device has it: then only the final rounding to float
 * stands between the mapped ray and the exact one. */
#ifdef cl_khr_fp64
typedef double map_real;
#else
typedef float map_real;
#endif
TRAVERSAL_INLINE bool instance_ray(RayData* out, __global const Instance* in, const WorldRay* w,
                                   float tmin, float tmax)
{
    if ((in->mask & w->mask) == 0)
        return false;
    float o[3], d[3];
    for (int row = 0; row < 3; ++row) {
        __global const float* m = in->to_mesh + 4 * row;
        map_real m0 = m[0], m1 = m[1], m2 = m[2];
        o[row] = (float)(((m0 * w->origin[0] + m1 * w->origin[1]) + m2 * w->origin[2])
                         + (map_real)m[3]);
        d[row] = (float)((m0 * w->direction[0] + m1 * w->direction[1])
                         + m2 * w->direction[2]);
    }
    prepare_ray(out, (float3)(o[0], o[1], o[2]), (float3)(d[0], d[1], d[2]), tmin, tmax);
    return true;
}

/* A mesh-frame normal in the world: the inverse transpose of the
 * instance's map (the transpose of to_mesh's linear part), turned by the
 * sign of its determinant so that it stays cross(v1 - v0, v2 - v0) of the
 * mapped vertices (a mirror flips the winding); unit length. */
TRAVERSAL_INLINE float3 instance_normal(__global const Instance* in, float3 n)
{
    __global const float* m = in->to_mesh;
    float3 w = (float3)((m[0] * n.x + m[4] * n.y) + m[8] * n.z,
                        (m[1] * n.x + m[5] * n.y) + m[9] * n.z,
                        (m[2] * n.x + m[6] * n.y) + m[10] * n.z) * in->normal_sign;
    float largest = GROW_HI(GROW_HI(ABS_FLOAT(w.x), ABS_FLOAT(w.y)), ABS_FLOAT(w.z));
    w = w * (1.0f / largest);
    return w * (1.0f / SQUARE_ROOT(w.x * w.x + w.y * w.y + w.z * w.z));
}

#endif /* INSTANCE_H */
