/* What every integrator does at a surface: store and dot without PoCL's
 * out-of-line builtins, the rays it writes (an empty one where none is
 * needed), the normal facing the viewer, and a basis around it. */
#ifndef SURFACE_H
#define SURFACE_H

#include "core/spelled.h"
#include "query/records.h"
#include "render/angles.h"

/* PoCL 3.0 calls vload3, vstore3, dot, fmax and other builtins out of line
 * (core/spelled.h; perf showed most of shade_hits' time in such calls), so
 * most are spelled out (LOAD_XYZ, store3, dot3).  dot3 adds the
 * products in dot's order, and apart from them, which in one expression
 * could fuse into fmas. */
inline void store3(__global float* p, float3 v)
{
    p[0] = v.x;
    p[1] = v.y;
    p[2] = v.z;
}

inline float dot3(float3 a, float3 b)
{
    float3 products = a * b;
    return products.x + products.y + products.z;
}

/* |v|, v / |v| and a x b in the operations of length, normalize and cross
 * (PoCL's: for v / |v|, one division and three products), without their
 * calls.  Outside squared lengths of [1e-30, 1e30], where length and
 * normalize rescale v against underflow and overflow, they call them. */
inline float length3(float3 v)
{
    float squared = dot3(v, v);
    return squared > 1e-30f && squared < 1e30f ? SQRT(squared) : length(v);
}

inline float3 normalize3(float3 v)
{
    float squared = dot3(v, v);
    return squared > 1e-30f && squared < 1e30f ? v * (1.0f / SQRT(squared)) : normalize(v);
}

inline float3 cross3(float3 a, float3 b)
{
    return (float3)(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x);
}

/* A ray with tmin > tmax: traversal rejects the root's children at once and
 * reports no hit, so a pixel that needs no secondary ray costs one node.  It
 * takes the direction of its neighbours' rays (the light's, for shadows):
 * CPU traversal traces 8 rays as one packet only when their directions share
 * signs and dominant axis (query/rays.cl), and an odd empty ray would send its
 * whole packet down the one-ray-at-a-time path. */
inline void write_empty_ray(__global Ray* ray, float3 direction)
{
    ray->origin[0] = ray->origin[1] = ray->origin[2] = 0.0f;
    store3(ray->direction, direction);
    ray->tmin = 1.0f;
    ray->tmax = 0.0f;
}

inline void write_ray(__global Ray* ray, float3 origin, float3 direction, float tmax)
{
    store3(ray->origin, origin);
    store3(ray->direction, direction);
    ray->tmin = 0.0f;
    ray->tmax = tmax;
}

/* The unit geometric normal on the side the ray came from: meshes may be
 * open or inconsistently wound, so both sides are front sides. */
inline float3 facing_normal(__global const Hit* hit, float3 direction)
{
    float3 n = LOAD_XYZ(hit->normal);
    return dot3(n, direction) > 0.0f ? -n : n;
}

/* Orthonormal basis around a unit n: Duff et al. 2017, "Building an
 * Orthonormal Basis, Revisited" (JCGT 6(1)), branchless and exact at n.z = -1. */
inline void orthonormal_basis(float3 n, float3* b1, float3* b2)
{
    float sign = sign_of(n.z);
    float a = -1.0f / (sign + n.z);
    float b = n.x * n.y * a;
    *b1 = (float3)(1.0f + sign * n.x * n.x * a, sign * b, -sign * n.x);
    *b2 = (float3)(b, sign + n.y * n.y * a, -n.y);
}

/* A direction cosine-distributed about the unit n, of density cos / pi
 * (Malley's method: a uniform point on the unit disc, lifted to the
 * hemisphere; pbrt-v4 SampleCosineHemisphere), from u1 in [0, 1) and the
 * cosine and sine of the point's angle on the disc; not normalised beyond
 * rounding. */
inline float3 cosine_direction_at(float3 n, float u1, float cosine, float sine)
{
    float radius = SQRT(u1);
    float3 b1, b2;
    orthonormal_basis(n, &b1, &b2);
    return radius * cosine * b1 + radius * sine * b2
           + SQRT(1.0f - u1) * n;  /* u1 < 1, so never tangent */
}

/* The same at the angle 2 pi u2 (u2 in [0, 1)), as the previews draw it.
 * One call for both (PoCL: the same bits as sin and cos at every angle u2
 * can give, and measured faster). */
inline float3 cosine_direction(float3 n, float u1, float u2)
{
    float cosine, sine = sincos(2.0f * M_PI_F * u2, &cosine);
    return cosine_direction_at(n, u1, cosine, sine);
}

/* The same in a local frame whose normal is +z, at the angle sincos_turn
 * gives (render/angles.h): cosine_direction_at's terms without the basis,
 * which is the identity there. */
inline float3 cosine_local(float u1, float u2)
{
    float cos_phi, sin_phi = sincos_turn(u2, &cos_phi);
    float radius = SQRT(u1);
    return (float3)(radius * cos_phi, radius * sin_phi, SQRT(1.0f - u1));
}

/* The path integrator's cosine-distributed direction, normalised, at the
 * angle sincos_turn gives (render/angles.h). */
FORCE_INLINE float3 cosine_sample(float3 n, float u1, float u2)
{
    float cos_phi, sin_phi = sincos_turn(u2, &cos_phi);
    return normalize3(cosine_direction_at(n, u1, cos_phi, sin_phi));
}

#endif /* SURFACE_H */
