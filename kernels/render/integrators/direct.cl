/* The direct integrator (hlbvh_cl/render/integrators/direct.py, which
 * documents the formulas): closest hits -> colours, plus the shadow or
 * ambient-occlusion rays that decide the rest of each colour, and the
 * resolve that adds it.  In short, with n the hit's geometric normal turned
 * towards the viewer and a the mesh's colour:
 *   diffuse  a * (ambient + intensity * max(n.l, 0) * visible(l)), sky on a miss
 *   normals  (n + 1) / 2, black on a miss
 *   depth    (far - distance) / (far - near) clamped to [0, 1], black on a miss
 *   ao       a * (fraction of ao rays that meet nothing), sky on a miss
 * The modes share one kernel body, specialised at compile time by SHADING:
 * written as one function per mode instead, shade_hits measured slower on
 * PoCL 3.0 (the A/B is in the commit message that chose this).  The path
 * integrator (path.cl) is the place for new light transport; these are the
 * fast previews.
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
#include "render/surface.h"
#include "render/tiles.h"
#include "render/random.h"

#define SHADING_DIFFUSE 1
#define SHADING_NORMALS 2
#define SHADING_DEPTH 3
#define SHADING_AO 4

#if !defined(SHADING) || !defined(SHADOWS)
#error "SHADING and SHADOWS must be defined (-D SHADING=SHADING_DIFFUSE -D SHADOWS=1)"
#endif

#if SHADING != SHADING_DIFFUSE && SHADING != SHADING_NORMALS && SHADING != SHADING_DEPTH \
    && SHADING != SHADING_AO
#error "SHADING must be SHADING_DIFFUSE, SHADING_NORMALS, SHADING_DEPTH or SHADING_AO"
#endif

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

NARROW_KERNEL
void shade_hits(__global const Ray* rays,
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
    __global const Ray* ray = rays + gid;
    __global const Hit* hit = hits + gid;
    float3 direction = LOAD_XYZ(ray->direction);
    float3 colour = (float3)(0.0f);
    float3 deferred = (float3)(0.0f);  /* added later if the secondary ray is free */

    if (hit->geom_id < 0) {
#if SHADING == SHADING_DIFFUSE || SHADING == SHADING_AO
        colour = sky(&params, direction);
#endif
#if SHADING == SHADING_DIFFUSE && SHADOWS
        write_empty_ray(secondary + gid, LOAD_XYZ(params.light_direction));
#endif
    } else {
        float3 n = facing_normal(hit, direction);
#if SHADING == SHADING_DIFFUSE
        float3 base = LOAD_XYZ(albedo + 3 * hit->geom_id);
        float3 light = LOAD_XYZ(params.light_direction);
        float cosine = dot3(n, light);
        cosine = cosine > 0.0f ? cosine : 0.0f; /* fmax(cosine, 0), a NaN to 0 too */
        float3 direct = base * (params.light_intensity * cosine);
        colour = base * params.ambient;
#if SHADOWS
        if (cosine > 0.0f && params.light_intensity > 0.0f) {
            deferred = direct;
            write_ray(secondary + gid, secondary_origin(ray, hit, n, &params), light, INFINITY);
        } else {
            write_empty_ray(secondary + gid, light);
        }
#else
        colour += direct;
#endif
#elif SHADING == SHADING_NORMALS
        colour = 0.5f * (n + 1.0f);
#elif SHADING == SHADING_DEPTH
        float distance = hit->t * length(direction);
        colour = (float3)(clamp((params.depth_far - distance)
                                / (params.depth_far - params.depth_near), 0.0f, 1.0f));
#elif SHADING == SHADING_AO
        deferred = LOAD_XYZ(albedo + 3 * hit->geom_id) * params.ao_weight;
#endif
    }
#if (SHADING == SHADING_DIFFUSE && SHADOWS) || SHADING == SHADING_AO
    pending[gid] = (float4)(deferred, 0.0f);
#endif
    float4 before = sample == 0 ? (float4)(0.0f) : accum[gid];
    accum[gid] = before + (float4)(colour, 0.0f);
}

/* The k-th AO ray of each pixel: cosine_direction about n from
 * random_unit(pixel, sample, 2 + 2k) and (..., 3 + 2k), reaching
 * ao_distance.  Misses get an empty ray. */
NARROW_KERNEL
void ao_rays(__global const Ray* rays, __global const Hit* hits,
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
    float3 direction = cosine_direction(n, random_unit(pixel, sample, 2 + 2 * ao_index),
                                        random_unit(pixel, sample, 3 + 2 * ao_index));
    write_ray(secondary + gid, secondary_origin(ray, hit, n, &params), direction,
              params.ao_distance);
}

NARROW_KERNEL
void add_unoccluded(__global const uchar* occluded,
                    __global const float4* pending,
                    const uint ray_count,
                    __global float4* accum)
{
    uint gid = get_global_id(0);
    if (gid >= ray_count || occluded[gid])
        return;
    accum[gid] += pending[gid];
}
