/* Analytic spheres beside the tree (a flat scene's, -D SPHERES): each a
 * float4 (centre, radius) in the tree's frame, geom_id sphere_geom + its
 * index, tested by every ray after its walk (query/rays.cl's closest_hits
 * and any_hits).  A scene holds few of them (Mitsuba's sphere shapes), so
 * they are not in the tree: a ray tests them all.
 *
 * The roots are Haines et al.'s ("Precision Improvements for Ray/Sphere
 * Intersection", Ray Tracing Gems, 2019, ch. 7): the discriminant from the
 * distance of the ray's nearest point to the centre, which keeps its
 * precision where b^2 - ac cancels (a small sphere far away), and the
 * second root from the first by Vieta's product c / a, which keeps the near
 * root of a ray leaving the surface (a path's next segment, c near 0). */
#ifndef SPHERE_H
#define SPHERE_H

#include "core/spelled.h"
#include "query/records.h"
#include "query/rays/ray.h"

#ifdef INSTANCES
#error "spheres are for flat scenes (hlbvh_cl.Scene refuses them with instances)"
#endif

TRAVERSAL_INLINE float sphere_dot(float3 a, float3 b)
{
    return a.x * b.x + a.y * b.y + a.z * b.z;
}

/* Where origin + t direction meets the sphere: near <= far, false if it
 * does not (or the ray is not finite: no comparison of NaN holds).  The
 * roots are taken along the direction over its largest component, whose
 * squares cannot leave float32's range as a direction 1e20 or 1e-25 long
 * would: t comes back in the direction's own units (inf past float32). */
TRAVERSAL_INLINE bool sphere_roots(float3 origin, float3 given, float4 sphere,
                                   float* near, float* far)
{
    float gx = given.x < 0.0f ? -given.x : given.x, gy = given.y < 0.0f ? -given.y : given.y;
    float gz = given.z < 0.0f ? -given.z : given.z;
    float scale = 1.0f / (gx > gy ? (gx > gz ? gx : gz) : (gy > gz ? gy : gz));
    if (!(scale < INFINITY))
        return false;
    float3 direction = given * scale;
    float3 f = origin - sphere.xyz;
    float a = sphere_dot(direction, direction);
    float b = -sphere_dot(f, direction);  /* the roots are (b +- sqrt(disc)) / a */
    float3 nearest = f + (b / a) * direction;  /* from the centre */
    float r2 = sphere.w * sphere.w;
    float disc = a * (r2 - sphere_dot(nearest, nearest));
    if (!(disc >= 0.0f) || !(a > 0.0f))
        return false;
    float root = SQRT(disc);
    float q = b < 0.0f ? b - root : b + root;
    float c = sphere_dot(f, f) - r2;
    float t0 = q / a;
    float t1 = q != 0.0f ? c / q : t0;  /* q = 0: b = disc = 0, one root at 0 */
    *near = (t0 < t1 ? t0 : t1) * scale + 0.0f;  /* + 0: -0 (on the surface) as 0 */
    *far = (t0 < t1 ? t1 : t0) * scale + 0.0f;
    return true;
}

#if PACKET_SIZE > 1
/* sphere_roots for every lane of a work-item at once: the same operations
 * lane by lane (IEEE division and square root, FP_CONTRACT off), so the
 * same bits, with one vector division where each lane took its own (the
 * lane-by-lane tests, their scalar divisions and dot products, showed in a
 * profile of the Cornell box's rays: figures in the commit that brought
 * this).  Gives the lanes (-1) whose ray meets the sphere. */
TRAVERSAL_INLINE int_packet sphere_roots_packet(const float_packet* origin,
                                                const float_packet* given, float4 sphere,
                                                float_packet* near, float_packet* far)
{
    float_packet g[3], direction[3], f[3];
    for (int k = 0; k < 3; ++k)
        g[k] = given[k] < 0.0f ? -given[k] : given[k];
    float_packet scale = (float_packet)(1.0f)
                         / (g[0] > g[1] ? (g[0] > g[2] ? g[0] : g[2]) : (g[1] > g[2] ? g[1] : g[2]));
    float centre[3] = {sphere.x, sphere.y, sphere.z};
    for (int k = 0; k < 3; ++k) {
        direction[k] = given[k] * scale;
        f[k] = origin[k] - centre[k];
    }
    float_packet a = direction[0] * direction[0] + direction[1] * direction[1]
                     + direction[2] * direction[2];
    float_packet b = -(f[0] * direction[0] + f[1] * direction[1] + f[2] * direction[2]);
    float_packet along = b / a, nearest_squared = (float_packet)(0.0f);
    for (int k = 0; k < 3; ++k) {
        float_packet nearest = f[k] + along * direction[k];
        nearest_squared = k == 0 ? nearest * nearest : nearest_squared + nearest * nearest;
    }
    float r2 = sphere.w * sphere.w;
    float_packet disc = a * (r2 - nearest_squared);
    int_packet meets = (scale < INFINITY) & (disc >= 0.0f) & (a > 0.0f);
    float_packet root = packet_root(disc);
    float_packet q = b < 0.0f ? b - root : b + root;
    float_packet c = (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]) - r2;
    float_packet t0 = q / a;
    float_packet t1 = q != 0.0f ? c / q : t0;
    *near = (t0 < t1 ? t0 : t1) * scale + 0.0f;
    *far = (t0 < t1 ? t1 : t0) * scale + 0.0f;
    return meets;
}

/* nearest_sphere for every lane (strict per lane): each lane's sphere
 * index (-1: none), with *limit lowered to its t where it has one. */
TRAVERSAL_INLINE int_packet nearest_sphere_packet(const RayLanes* lanes,
                                                  __global const float4* spheres,
                                                  uint sphere_count, float_packet* limit,
                                                  int_packet strict)
{
    float_packet o[3], d[3];
    for (int k = 0; k < 3; ++k) {
        o[k] = vload_packet(0, lanes->origin[k]);
        d[k] = vload_packet(0, lanes->direction[k]);
    }
    float_packet tmin = vload_packet(0, lanes->tmin);
    int_packet found = (int_packet)(-1);
    for (uint s = 0; s < sphere_count; ++s) {
        float_packet near, far;
        int_packet meets = sphere_roots_packet(o, d, spheres[s], &near, &far);
        float_packet t = near >= tmin ? near : far;
        int_packet take = meets & (t >= tmin) & (t < INFINITY)
                          & (strict ? t < *limit : t <= *limit);
        *limit = take ? t : *limit;
        found = take ? (int_packet)((int)s) : found;
        strict |= take;  /* a later sphere at the same t leaves this one */
    }
    return found;
}
#endif

/* Lane l's nearest sphere hit within [tmin, *limit] (within [tmin, *limit)
 * when `strict`: a triangle found at *limit keeps it), as the sphere's index
 * with *limit lowered to its t; -1 if none. */
TRAVERSAL_INLINE int nearest_sphere(const RayLanes* lanes, uint l,
                                    __global const float4* spheres, uint sphere_count,
                                    float* limit, bool strict)
{
    float3 o = (float3)(lanes->origin[0][l], lanes->origin[1][l], lanes->origin[2][l]);
    float3 d = (float3)(lanes->direction[0][l], lanes->direction[1][l],
                        lanes->direction[2][l]);
    float tmin = lanes->tmin[l];
    int found = -1;
    for (uint s = 0; s < sphere_count; ++s) {
        float near, far;
        if (!sphere_roots(o, d, spheres[s], &near, &far))
            continue;
        float t = near >= tmin ? near : far;
        if (t >= tmin && t < INFINITY && (strict ? t < *limit : t <= *limit)) {
            *limit = t;
            found = (int)s;
            strict = true;  /* a later sphere at the same t leaves this one */
        }
    }
    return found;
}

/* Whether lane l meets any sphere within [tmin, tmax]. */
TRAVERSAL_INLINE bool any_sphere(const RayLanes* lanes, uint l, __global const float4* spheres,
                                 uint sphere_count)
{
    float limit = lanes->tmax[l];
    return nearest_sphere(lanes, l, spheres, sphere_count, &limit, false) >= 0;
}

/* The Hit of lane l on sphere s at t: the outward unit normal, and u, v
 * its spherical coordinates about the frame's axes, u = atan2(y, x) / 2 pi
 * in [0, 1) and v = acos(z) / pi, as Mitsuba's sphere gives them in its
 * own frame (prim_id 0: the sphere is one primitive). */
TRAVERSAL_INLINE void sphere_hit(Hit* out, const RayLanes* lanes, uint l,
                                 __global const float4* spheres, int sphere_geom, int s, float t)
{
    float4 sphere = spheres[s];
    float3 o = (float3)(lanes->origin[0][l], lanes->origin[1][l], lanes->origin[2][l]);
    float3 d = (float3)(lanes->direction[0][l], lanes->direction[1][l],
                        lanes->direction[2][l]);
    /* o - c first: the hit point o + t d rounded to the world's coordinates
     * lost a small sphere's normal far from the origin (29 degrees at 1e4) */
    float3 n = (o - sphere.xyz) + t * d;
    float squared = sphere_dot(n, n);
    n = squared > 0.0f ? n * (1.0f / SQRT(squared)) : (float3)(0.0f, 0.0f, 1.0f);
    float u = atan2(n.y, n.x) * (0.5f * M_1_PI_F);
    Hit hit;
    hit.t = t;
    hit.geom_id = sphere_geom + s;
    hit.prim_id = 0;
    u = u < 0.0f ? u + 1.0f : u;
    hit.u = u < 1.0f ? u : 0.0f;  /* -0x1p-30 + 1 rounds to 1 */
    hit.v = acos(n.z < 1.0f ? (n.z > -1.0f ? n.z : -1.0f) : 1.0f) * M_1_PI_F;
    hit.normal[0] = n.x;
    hit.normal[1] = n.y;
    hit.normal[2] = n.z;
    *out = hit;
}

#endif /* SPHERE_H */
