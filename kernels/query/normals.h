/* Unit normals of triangles, as the queries report them: a hit's, a closest
 * point's (the geometric normal, following the winding), and a mesh-frame
 * normal mapped to the world (query/rays/instance.h). */
#ifndef NORMALS_H
#define NORMALS_H

#include "query/walk/node.h"

/* w at unit length, scaled by its largest component first so that tiny or
 * huge vectors neither underflow nor overflow the squared length; a zero
 * vector (the normal of a zero-area triangle, which a closest-point query
 * can find) stays zero. */
TRAVERSAL_INLINE float3 unit_vector(float3 w)
{
    float largest = GROW_HI(GROW_HI(abs_float(w.x), abs_float(w.y)), abs_float(w.z));
    if (largest == 0.0f)
        return w;
    w = w * (1.0f / largest);
    return w * (1.0f / SQRT(w.x * w.x + w.y * w.y + w.z * w.z));
}

/* cross(b - a, c - a), as query/rays/triangle.h's geometric_normal computes it. */
TRAVERSAL_INLINE float3 corners_cross(float3 a, float3 b, float3 c)
{
    float3 e1 = b - a, e2 = c - a;
    return (float3)(e1.y * e2.z - e1.z * e2.y, e1.z * e2.x - e1.x * e2.z,
                    e1.x * e2.y - e1.y * e2.x);
}

/* The unit geometric normal of the triangle (a, b, c) (see unit_vector). */
TRAVERSAL_INLINE float3 corners_normal(float3 a, float3 b, float3 c)
{
    return unit_vector(corners_cross(a, b, c));
}

/* The triangle's cross(v1 - v0, v2 - v0) (then its unit normal, below). */
TRAVERSAL_INLINE float3 triangle_cross(TRIANGLE_AT tri)
{
    return corners_cross(LOAD_XYZ(tri->v0), LOAD_XYZ(tri->v1), LOAD_XYZ(tri->v2));
}

TRAVERSAL_INLINE float3 unit_normal(TRIANGLE_AT tri)
{
    return unit_vector(triangle_cross(tri));
}

/* Whether the triangle has zero area: cross(v1 - v0, v2 - v0) exactly 0,
 * the geometric normal that the ray test refuses to report
 * (query/rays/triangle.h), without contraction as it computes it. */
TRAVERSAL_INLINE bool zero_area(TRIANGLE_AT tri)
{
#pragma OPENCL FP_CONTRACT OFF
    float3 e1 = LOAD_XYZ(tri->v1) - LOAD_XYZ(tri->v0), e2 = LOAD_XYZ(tri->v2) - LOAD_XYZ(tri->v0);
    return e1.y * e2.z - e1.z * e2.y == 0.0f && e1.z * e2.x - e1.x * e2.z == 0.0f
           && e1.x * e2.y - e1.y * e2.x == 0.0f;
}

#endif /* NORMALS_H */
