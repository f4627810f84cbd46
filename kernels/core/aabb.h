/* Axis-aligned boxes, as the build's stages pass them between each other
 * (mirrored by hlbvh_cl/core/layout.py, AABB). */
#ifndef AABB_H
#define AABB_H

#include "core/spelled.h"

typedef struct {
    float lo[3];
    float hi[3];
} Aabb;

inline Aabb aabb_empty(void)
{
    Aabb box = {{INFINITY, INFINITY, INFINITY}, {-INFINITY, -INFINITY, -INFINITY}};
    return box;
}

inline Aabb aabb_of_points(float3 a, float3 b, float3 c)
{
    float3 lo = GROW_LO(GROW_LO(a, b), c);
    float3 hi = GROW_HI(GROW_HI(a, b), c);
    Aabb box = {{lo.x, lo.y, lo.z}, {hi.x, hi.y, hi.z}};
    return box;
}

inline Aabb aabb_union(Aabb a, Aabb b)
{
    Aabb box;
    for (int k = 0; k < 3; ++k) {
        box.lo[k] = GROW_LO(a.lo[k], b.lo[k]);
        box.hi[k] = GROW_HI(a.hi[k], b.hi[k]);
    }
    return box;
}

/* Surface area; 0 for an empty (inverted) box. */
inline float aabb_area(Aabb a)
{
    float dx = a.hi[0] - a.lo[0], dy = a.hi[1] - a.lo[1], dz = a.hi[2] - a.lo[2];
    if (!(dx >= 0.0f && dy >= 0.0f && dz >= 0.0f))
        return 0.0f;
    return 2.0f * (dx * dy + dy * dz + dz * dx);
}

inline float3 aabb_center(Aabb a)
{
    return (float3)(0.5f * (a.lo[0] + a.hi[0]), 0.5f * (a.lo[1] + a.hi[1]), 0.5f * (a.lo[2] + a.hi[2]));
}

#endif /* AABB_H */
