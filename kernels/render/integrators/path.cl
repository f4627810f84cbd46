/* The path integrator's stages (hlbvh_cl/render/integrators/path.py, which
 * documents the estimator): unidirectional path tracing with next-event
 * estimation and BSDF sampling combined by the power heuristic (Veach 1997,
 * ch. 9; pbrt-v4's PathIntegrator, Mitsuba 3's path), and Russian roulette,
 * run as a wavefront (Laine, Karras & Aila 2013): one kernel per stage over
 * the pass's paths, whose states live in a device buffer.  Closest-hit and
 * shadow rays are traced between the stages by query/rays.cl.
 *
 * Kernels (one work-item per path, in ray order)
 *   path_start      a fresh path behind each camera ray
 *   path_surface    at the path's hit (or miss): the light it sees there,
 *                   a light sample (its shadow ray, and what it carries to
 *                   `pending`), and the next ray, sampled from the BSDF
 *   path_unoccluded a path's radiance += pending where its shadow ray was free
 *   path_finish     the film's sum += each path's radiance
 *
 * Random numbers: random_unit(pixel, sample, dimension) (render/random.h),
 * the camera's dimensions 0 and 1, then DIMENSIONS_PER_BOUNCE per bounce.
 */
#include "core/portable.h"
#include "core/spelled.h"
#include "query/records.h"
#include "render/integrators/path.h"
#include "render/bsdfs/bsdf.h"
#include "render/surface.h"
#include "render/random.h"
#include "render/envmap.h"

#define DIMENSIONS_PER_BOUNCE 8
#define INV_FOUR_PI 0.07957747154594767f

/* The power heuristic with beta = 2 (Veach 1997, eq. 9.13) for a sample
 * drawn with density `chosen` where the other strategy has `other`. */
inline float power_heuristic(float chosen, float other)
{
    float a = chosen * chosen, b = other * other;
    return a > 0.0f ? a / (a + b) : 0.0f;
}

inline float luminance_max(float3 v)
{
    return v.x > v.y ? (v.x > v.z ? v.x : v.z) : (v.y > v.z ? v.y : v.z);
}

/* A light sample seen from x: the direction to it (unit), how far it
 * reaches, its radiance and its solid-angle density (0: none). */
typedef struct {
    float3 direction;
    float reach;
    float3 radiance;
    float pdf;
} LightSample;

/* The environment's radiance along -direction (direction: unit, the way
 * a ray escapes) and the density with which a light sample picks that
 * direction (0 when it cannot): the constant environment's, uniform on the
 * sphere, or the map's (render/envmap.h). */
inline float3 environment_light(const PathParams* params, __global const float* envmap_image,
                                __global const float* envmap_cdf, float3 direction, float* pdf)
{
    if (params->envmap_width == 0) {
        *pdf = params->environment_probability * INV_FOUR_PI;
        return LOAD_XYZ(params->environment);
    }
    *pdf = params->environment_probability > 0.0f
        ? params->environment_probability * envmap_pdf(params, envmap_cdf, direction) : 0.0f;
    return envmap_radiance(params, envmap_image, direction);
}

/* One light sample: uniform on the sphere for the constant environment
 * (as Mitsuba's constant emitter), by the map's density for an environment
 * map (render/envmap.h), a point or directional light (a delta:
 * its pdf is the chance of picking it, and MIS leaves it alone), or uniform
 * in area on an emissive triangle picked by power (its area times its
 * radiance's luminance); the lights themselves are picked by power
 * (hlbvh_cl/render/emitters.py). */
inline LightSample sample_light(float3 x, const PathParams* params,
                                __global const PathMaterial* materials,
                                __global const float* light_vertices,
                                __global const float* light_cdf,
                                __global const int* light_geom,
                                __global const DeltaLight* delta_lights,
                                __global const float* envmap_image,
                                __global const float* envmap_cdf,
                                uint pixel, uint sample, uint base, bool* delta)
{
    LightSample out = {(float3)(0.0f), 0.0f, (float3)(0.0f), 0.0f};
    float choice = random_unit(pixel, sample, base);
    *delta = false;
    float u1 = random_unit(pixel, sample, base + 2);
    float u2 = random_unit(pixel, sample, base + 3);
    if (choice < params->environment_probability) {
        out.reach = INFINITY;
        if (params->envmap_width > 0) {
            out.direction = envmap_sample(params, envmap_cdf, random_unit(pixel, sample, base + 1),
                                          u1, u2, &out.pdf);
            out.radiance = envmap_radiance(params, envmap_image, out.direction);
            out.pdf *= params->environment_probability;
            return out;
        }
        float z = 1.0f - 2.0f * u1;
        float r = sqrt(1.0f - z * z > 0.0f ? 1.0f - z * z : 0.0f);
        float cosine, sine = sincos(2.0f * M_PI_F * u2, &cosine);
        out.direction = (float3)(r * cosine, r * sine, z);
        out.radiance = LOAD_XYZ(params->environment);
        out.pdf = params->environment_probability * INV_FOUR_PI;
        return out;
    }
    choice -= params->environment_probability;
    if (choice < params->delta_probability) {
        *delta = true;
        for (uint i = 0; i < params->delta_lights; ++i) {
            __global const DeltaLight* light = delta_lights + i;
            if (choice >= light->probability && i + 1 < params->delta_lights) {
                choice -= light->probability;
                continue;
            }
            float3 value = LOAD_XYZ(light->value);
            if (light->type == LIGHT_DIRECTIONAL) {
                out.direction = -LOAD_XYZ(light->position);
                out.reach = INFINITY;
                out.radiance = value;  /* irradiance: a delta in direction */
            } else {
                float3 to_light = LOAD_XYZ(light->position) - x;
                float squared = dot3(to_light, to_light);
                out.reach = sqrt(squared);
                if (!(out.reach > 0.0f))
                    return out;
                out.direction = to_light / out.reach;
                out.radiance = value / squared;  /* intensity over distance squared */
            }
            out.pdf = light->probability;
            return out;
        }
        return out;
    }
    if (params->light_triangles == 0)
        return out;
    uint k = pick(light_cdf, params->light_triangles, random_unit(pixel, sample, base + 1));
    __global const float* v = light_vertices + 9 * (size_t)k;
    float3 v0 = LOAD_XYZ(v), v1 = LOAD_XYZ(v + 3), v2 = LOAD_XYZ(v + 6);
    float root = sqrt(u1);  /* uniform in the triangle: pbrt-v4 SampleUniformTriangle's map */
    float b0 = 1.0f - root, b1 = u2 * root;
    float3 p = b0 * v0 + b1 * v1 + (1.0f - b0 - b1) * v2;
    float3 normal = normalize(cross(v1 - v0, v2 - v0));
    float3 to_light = p - x;
    float squared = dot3(to_light, to_light);
    float distance = sqrt(squared);
    if (!(distance > 0.0f))
        return out;
    out.direction = to_light / distance;
    float cosine = -dot3(normal, out.direction);
    if (!(cosine > 0.0f))  /* its back side: area lights emit on the front only */
        return out;
    __global const PathMaterial* light = materials + light_geom[k];
    out.reach = distance;
    out.radiance = LOAD_XYZ(light->radiance);
    out.pdf = light->emitter_pdf * squared / cosine;
    return out;
}

__kernel void path_start(const uint count, __global PathState* states)
{
    uint gid = get_global_id(0);
    if (gid >= count)
        return;
    __global PathState* s = states + gid;
    store3(s->throughput, (float3)(1.0f));
    s->bsdf_pdf = 0.0f;
    store3(s->radiance, (float3)(0.0f));
    s->alive = 1;
    s->eta = 1.0f;
}

/* The path ends here, with what it gathered at this vertex: its next ray
 * is an empty one. */
inline void end_path(__global PathState* s, __global Ray* next, float3 direction,
                     float3 gathered)
{
    store3(s->radiance, LOAD_XYZ(s->radiance) + gathered);
    s->alive = 0;
    write_empty_ray(next, direction);
}

/* No light sample at this vertex. */
inline void no_shadow_ray(__global Ray* shadow, __global float4* pending, float3 direction)
{
    write_empty_ray(shadow, direction);
    *pending = (float4)(0.0f);
}

__kernel void path_surface(__global Ray* rays,               /* read, then the next rays */
                           __global const Hit* hits,
                           __global PathState* states,
                           __global const PathMaterial* materials,  /* per geom_id */
                           __global const float* light_vertices,    /* 9 floats per triangle */
                           __global const float* light_cdf,
                           __global const int* light_geom,
                           __global const DeltaLight* delta_lights,
                           __global const float* envmap_image,  /* H x W RGB (envmap.h) */
                           __global const float* envmap_cdf,    /* its marginal, conditionals */
                           const PathParams params,
                           const uint count,
                           const uint first_pixel,    /* the pass's first pixel: random streams */
                           const uint sample,
                           const int depth,           /* segments the paths have so far, - 1 */
                           __global Ray* shadow,
                           __global float4* pending,
                           __global uint* live)       /* live[depth] += paths that go on */
{
    uint gid = get_global_id(0);
    if (gid >= count)
        return;
    __global PathState* s = states + gid;
    __global Ray* ray = rays + gid;
    float3 d = LOAD_XYZ(ray->direction);
    if (!s->alive) {
        no_shadow_ray(shadow + gid, pending + gid, d);
        return;
    }
    __global const Hit* hit = hits + gid;
    float length_d = length(d);
    float3 wo = -d / length_d;  /* unit, towards where the path came from */
    float3 throughput = LOAD_XYZ(s->throughput);
    float3 gathered = (float3)(0.0f);

    if (hit->geom_id < 0) {  /* the environment */
        float light_pdf;
        float3 escaped = environment_light(&params, envmap_image, envmap_cdf, -wo, &light_pdf);
        float weight = s->bsdf_pdf > 0.0f ? power_heuristic(s->bsdf_pdf, light_pdf) : 1.0f;
        no_shadow_ray(shadow + gid, pending + gid, d);
        end_path(s, ray, d, throughput * escaped * weight);
        return;
    }
    __global const PathMaterial* m = materials + hit->geom_id;
    float3 geometric = LOAD_XYZ(hit->normal);
    float cos_out = dot3(geometric, wo);
    float3 emitted = LOAD_XYZ(m->radiance);
    if (cos_out > 0.0f && luminance_max(emitted) > 0.0f) {
        float distance = hit->t * length_d;
        float weight = s->bsdf_pdf > 0.0f
            ? power_heuristic(s->bsdf_pdf, m->emitter_pdf * distance * distance / cos_out)
            : 1.0f;
        gathered += throughput * emitted * weight;
    }
    bool last = params.max_depth > 0 && depth + 1 >= params.max_depth;
    /* n: the BSDF's normal, turned to the viewer for one with sides */
    float3 n = geometric;
    if (bsdf_has_sides(m) && !(cos_out > 0.0f)) {
        if (!m->twosided)
            last = true;  /* the back of a one-sided BSDF is black */
        n = -n;
    }
    if (last || cos_out == 0.0f) {
        no_shadow_ray(shadow + gid, pending + gid, d);
        end_path(s, ray, d, gathered);
        return;
    }
    float3 x = LOAD_XYZ(ray->origin) + hit->t * d;
    /* secondary rays start off the surface on their own side of it */
    float3 lift = params.ray_offset * (cos_out > 0.0f ? geometric : -geometric);
    uint pixel = first_pixel + gid, base = 2 + DIMENSIONS_PER_BOUNCE * (uint)depth;

    /* next-event estimation, for a BSDF with a density: one light sample,
     * weighed against the BSDF's density of its direction (delta lights: no MIS) */
    bool delta_light = false;
    LightSample light = {(float3)(0.0f), 0.0f, (float3)(0.0f), 0.0f};
    if (bsdf_has_density(m))
        light = sample_light(x + lift, &params, materials, light_vertices, light_cdf, light_geom,
                             delta_lights, envmap_image, envmap_cdf, pixel, sample, base,
                             &delta_light);
    float bsdf_pdf_of_light;
    float3 f_cos = light.pdf > 0.0f ? bsdf_eval(m, n, wo, light.direction, &bsdf_pdf_of_light)
                                    : (float3)(0.0f);
    if (light.pdf > 0.0f && luminance_max(f_cos * light.radiance) > 0.0f) {
        float weight = delta_light ? 1.0f : power_heuristic(light.pdf, bsdf_pdf_of_light);
        float3 carried = throughput * f_cos * light.radiance * (weight / light.pdf);
        /* stop short of the light itself: by the offset, or 0.1% of a short reach */
        float margin = params.ray_offset < 1e-3f * light.reach ? params.ray_offset
                                                               : 1e-3f * light.reach;
        write_ray(shadow + gid, x + lift, light.direction, light.reach - margin);
        pending[gid] = (float4)(carried, 0.0f);
    } else {
        no_shadow_ray(shadow + gid, pending + gid, d);
    }

    /* the BSDF sample: the throughput takes its weight f cos / pdf */
    BsdfSample next = bsdf_sample(m, n, wo, random_unit(pixel, sample, base + 4),
                                  random_unit(pixel, sample, base + 5),
                                  random_unit(pixel, sample, base + 6));
    throughput *= next.weight;
    float eta = s->eta * next.eta;
    if (!(luminance_max(throughput) > 0.0f)) {
        end_path(s, ray, d, gathered);
        return;
    }
    /* Russian roulette (Mitsuba's rule): from rr_depth on, a path goes on
     * with probability q = min(max channel of its throughput * eta^2, 0.95) */
    if (depth + 1 >= params.rr_depth) {
        float q = luminance_max(throughput) * eta * eta;
        q = q < 0.95f ? q : 0.95f;
        if (!(random_unit(pixel, sample, base + 7) < q)) {
            end_path(s, ray, next.direction, gathered);  /* its light sample above still counts */
            return;
        }
        throughput /= q;
    }
    store3(s->throughput, throughput);
    s->bsdf_pdf = next.delta ? 0.0f : next.pdf;  /* 0: the next emitter hit takes no MIS */
    s->eta = eta;
    store3(s->radiance, LOAD_XYZ(s->radiance) + gathered);
    float3 side = dot3(geometric, next.direction) > 0.0f ? geometric : -geometric;
    write_ray(ray, x + params.ray_offset * side, next.direction, INFINITY);
    atomic_inc(live + depth);
}

__kernel void path_unoccluded(__global const uchar* occluded,
                              __global const float4* pending,
                              const uint count,
                              __global PathState* states)
{
    uint gid = get_global_id(0);
    if (gid >= count || occluded[gid])
        return;
    __global PathState* s = states + gid;
    store3(s->radiance, LOAD_XYZ(s->radiance) + pending[gid].xyz);
}

__kernel void path_finish(__global const PathState* states,
                          const uint count,
                          const uint sample,          /* 0 starts the sum */
                          __global float4* accum)
{
    uint gid = get_global_id(0);
    if (gid >= count)
        return;
    float4 before = sample == 0 ? (float4)(0.0f) : accum[gid];
    accum[gid] = before + (float4)(LOAD_XYZ(states[gid].radiance), 0.0f);
}
