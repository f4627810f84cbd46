/* The direct integrator (hlbvh_cl/render/integrators/direct.py, which
 * documents the formulas): closest hits -> colours, plus the shadow or
 * ambient-occlusion rays that decide the rest of each colour, and the
 * resolve that adds it.  In short, with n the hit's geometric normal turned
 * towards the viewer and a the mesh's colour:
 *   diffuse  a * (ambient + intensity * max(n.l, 0) * visible(l)), sky on a miss
 *   normals  (n + 1) / 2, black on a miss
 *   depth    (far - distance) / (far - near) clamped to [0, 1], black on a miss
 *   ao       a * (fraction of ao rays that meet nothing), sky on a miss
 * One function per mode (shade_diffuse ... shade_ao), chosen at compile time.
 *
 * Kernels (one work-item per pixel of the current pass; ao_rays over
 * pixel_in_pass's 2D range, render/tiles.h, the others 1D in ray order)
 *   shade_hits      adds to accum what needs no further ray; for diffuse with
 *                   SHADOWS writes each pixel's shadow ray (an empty ray
 *                   where none is needed) and the light it would let through
 *                   to `pending`; for ao writes a / ao_samples to `pending`
 *   ao_rays         the k-th ambient-occlusion ray of every pixel
 *   add_unoccluded  accum += pending where the shadow or AO ray hit nothing
 * The film (render/film.cl) encodes the sums.
 *
 * Compile-time parameters (-D)
 *   SHADING  one of the SHADING_* names below
 *   SHADOWS  1: diffuse shading traces shadow rays; 0: every light is visible
 */
#include "core/portable.h"
#include "core/spelled.h"
#include "query/records.h"
#include "render/integrators/direct.h"
#include "render/tiles.h"
#include "render/random.h"

#define SHADING_DIFFUSE 1
#define SHADING_NORMALS 2
#define SHADING_DEPTH 3
#define SHADING_AO 4

#if !defined(SHADING) || !defined(SHADOWS)
#error "SHADING and SHADOWS must be defined (-D SHADING=SHADING_DIFFUSE -D SHADOWS=1)"
#endif

/* The mode's function, and whether it defers light to a secondary ray. */
#if SHADING == SHADING_DIFFUSE
#define SHADE shade_diffuse
#define DEFERS SHADOWS
#elif SHADING == SHADING_NORMALS
#define SHADE shade_normals
#define DEFERS 0
#elif SHADING == SHADING_DEPTH
#define SHADE shade_depth
#define DEFERS 0
#elif SHADING == SHADING_AO
#define SHADE shade_ao
#define DEFERS 1
#else
#error "SHADING must be SHADING_DIFFUSE, SHADING_NORMALS, SHADING_DEPTH or SHADING_AO"
#endif

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

/* Where secondary rays start: the hit point moved ray_offset off the surface,
 * on the viewer's side, so that they cannot hit their own triangle again. */
inline float3 secondary_origin(__global const Ray* ray, __global const Hit* hit, float3 n,
                               const ShadeParams* params)
{
    float3 hit_point = LOAD_XYZ(ray->origin) + hit->t * LOAD_XYZ(ray->direction);
    return hit_point + params->ray_offset * n;
}

/* Background: from the horizon colour (directions at or below the horizon)
 * to the zenith colour (straight up), linear in the sine of the elevation. */
inline float3 sky(const ShadeParams* params, float3 direction)
{
    float elevation = dot3(normalize(direction), LOAD_XYZ(params->sky_up));
    elevation = elevation > 0.0f ? (elevation < 1.0f ? elevation : 1.0f) : 0.0f; /* clamp */
    float3 horizon = LOAD_XYZ(params->sky_horizon);
    float3 rise = (LOAD_XYZ(params->sky_zenith) - horizon) * elevation;
    return horizon + rise; /* mix, unfused (see dot3) */
}

/* What a primary ray's closest hit (or miss) gives: `colour` now, and
 * `deferred`, added later where its secondary ray proves free. */
typedef struct {
    float3 colour;
    float3 deferred;
} Shaded;

/* What each mode reads of one primary ray: the ray, its closest hit, its
 * direction, and where its secondary ray goes. */
typedef struct {
    __global const Ray* ray;
    __global const Hit* hit;
    float3 direction;
    __global const float* albedo;  /* RGB per geom_id */
    const ShadeParams* params;
    __global Ray* secondary;
} Primary;

inline Shaded shade_diffuse(const Primary* p)
{
    Shaded out = {(float3)(0.0f), (float3)(0.0f)};
    float3 light = LOAD_XYZ(p->params->light_direction);
    if (p->hit->geom_id < 0) {
        out.colour = sky(p->params, p->direction);
        if (SHADOWS)
            write_empty_ray(p->secondary, light);
        return out;
    }
    float3 n = facing_normal(p->hit, p->direction);
    float3 base = LOAD_XYZ(p->albedo + 3 * p->hit->geom_id);
    float cosine = dot3(n, light);
    cosine = cosine > 0.0f ? cosine : 0.0f; /* fmax(cosine, 0), a NaN to 0 too */
    float3 direct = base * (p->params->light_intensity * cosine);
    out.colour = base * p->params->ambient;
    if (!SHADOWS) {
        out.colour += direct;
    } else if (cosine > 0.0f && p->params->light_intensity > 0.0f) {
        out.deferred = direct;
        write_ray(p->secondary, secondary_origin(p->ray, p->hit, n, p->params), light, INFINITY);
    } else {
        write_empty_ray(p->secondary, light);
    }
    return out;
}

inline Shaded shade_normals(const Primary* p)
{
    Shaded out = {(float3)(0.0f), (float3)(0.0f)};
    if (p->hit->geom_id >= 0)
        out.colour = 0.5f * (facing_normal(p->hit, p->direction) + 1.0f);
    return out;
}

inline Shaded shade_depth(const Primary* p)
{
    Shaded out = {(float3)(0.0f), (float3)(0.0f)};
    if (p->hit->geom_id >= 0) {
        float distance = p->hit->t * length(p->direction);
        out.colour = (float3)(clamp((p->params->depth_far - distance)
                                    / (p->params->depth_far - p->params->depth_near), 0.0f, 1.0f));
    }
    return out;
}

/* The colour ao_rays' rays carry; they are written by ao_rays, per AO sample. */
inline Shaded shade_ao(const Primary* p)
{
    Shaded out = {(float3)(0.0f), (float3)(0.0f)};
    if (p->hit->geom_id < 0)
        out.colour = sky(p->params, p->direction);
    else
        out.deferred = LOAD_XYZ(p->albedo + 3 * p->hit->geom_id) * p->params->ao_weight;
    return out;
}

__kernel void shade_hits(__global const Ray* rays,
                         __global const Hit* hits,
                         __global const float* albedo,    /* RGB per geom_id */
                         const ShadeParams params,
                         const uint ray_count,
                         const uint sample,               /* 0 starts the sum */
                         __global Ray* secondary,
                         __global float4* pending,
                         __global float4* accum)
{
    uint gid = get_global_id(0);
    if (gid >= ray_count)
        return;
    Primary primary = {rays + gid, hits + gid, LOAD_XYZ(rays[gid].direction), albedo, &params,
                       secondary + gid};
    Shaded shaded = SHADE(&primary);
    if (DEFERS)
        pending[gid] = (float4)(shaded.deferred, 0.0f);
    float4 before = sample == 0 ? (float4)(0.0f) : accum[gid];
    accum[gid] = before + (float4)(shaded.colour, 0.0f);
}

/* Orthonormal basis around a unit n: Duff et al. 2017, "Building an
 * Orthonormal Basis, Revisited" (JCGT 6(1)), branchless and exact at n.z = -1. */
inline void orthonormal_basis(float3 n, float3* b1, float3* b2)
{
    float sign = copysign(1.0f, n.z);
    float a = -1.0f / (sign + n.z);
    float b = n.x * n.y * a;
    *b1 = (float3)(1.0f + sign * n.x * n.x * a, sign * b, -sign * n.x);
    *b2 = (float3)(b, sign + n.y * n.y * a, -n.y);
}

/* The k-th AO ray of each pixel: cosine-distributed about n (Malley's method:
 * a uniform point on the unit disc, lifted to the hemisphere; pbrt-v4
 * SampleCosineHemisphere) from random_unit(pixel, sample, 2 + 2k) and
 * (..., 3 + 2k), reaching ao_distance.  Misses get an empty ray. */
__kernel void ao_rays(__global const Ray* rays, __global const Hit* hits,
                      const ShadeParams params, const uint width, const uint first_row,
                      const uint rows, const uint sample, const uint ao_index,
                      __global Ray* secondary)
{
    uint gid;
    uint2 at;
    if (!pixel_in_pass(get_global_id(0), get_global_id(1), width, rows, &gid, &at))
        return;
    __global const Hit* hit = hits + gid;
    if (hit->geom_id < 0) { /* AO rays scatter: any direction will do */
        write_empty_ray(secondary + gid, LOAD_XYZ(params.sky_up));
        return;
    }
    __global const Ray* ray = rays + gid;
    float3 n = facing_normal(hit, LOAD_XYZ(ray->direction));
    uint pixel = (first_row + at.y) * width + at.x;
    float u1 = random_unit(pixel, sample, 2 + 2 * ao_index);
    float u2 = random_unit(pixel, sample, 3 + 2 * ao_index);
    float radius = sqrt(u1);
    float angle = 2.0f * M_PI_F * u2;
    float3 b1, b2;
    orthonormal_basis(n, &b1, &b2);
    /* One call for both (PoCL: the same bits as sin and cos at every angle
     * u2 can give, and measured faster) */
    float cosine, sine = sincos(angle, &cosine);
    float3 direction = radius * cosine * b1 + radius * sine * b2
                       + sqrt(1.0f - u1) * n;  /* u1 < 1, so never tangent */
    write_ray(secondary + gid, secondary_origin(ray, hit, n, &params), direction,
              params.ao_distance);
}

__kernel void add_unoccluded(__global const uchar* occluded,
                             __global const float4* pending,
                             const uint ray_count,
                             __global float4* accum)
{
    uint gid = get_global_id(0);
    if (gid >= ray_count || occluded[gid])
        return;
    accum[gid] += pending[gid];
}
