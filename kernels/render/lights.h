/* The path integrator's lights as next-event estimation samples them, and
 * the environment as an escaping path sees it (render/integrators/path.cl;
 * hlbvh_cl/render/emitters.py picks lights by power): written once for the
 * integrator and for sampling.cl's light_samples, which tests check
 * against their densities. */
#ifndef RENDER_LIGHTS_H
#define RENDER_LIGHTS_H

#include "core/portable.h"
#include "core/spelled.h"
#include "render/integrators/path.h"
#include "render/random.h"
#include "render/envmap.h"
#include "render/surface.h"

/* The lights' tables, as path_surface takes them. */
typedef struct {
    __global const PathMaterial* materials;  /* per geom_id: an emitter's radiance, emitter_pdf */
    __global const float* light_vertices;    /* 9 floats per emissive triangle; per
                                              * sphere after them, its centre, radius */
    __global const float* light_normals;     /* 9 floats per emissive triangle (sphere) */
    __global const float* light_cdf;         /* the triangles' CDF by power */
    __global const int* light_geom;          /* the mesh of each */
    __global const DeltaLight* delta_lights;
    __global const float* envmap_image;      /* H x W RGB (envmap.h) */
    __global const float* envmap_cdf;        /* its marginal, conditionals */
} LightTables;

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
 * direction (0 when it cannot): the map's (render/envmap.h); a constant
 * environment takes no light samples (hlbvh_cl/render/integrators/path.py:
 * BSDF sampling alone reaches it, as pbrt-v4's uniform infinite light). */
inline float3 environment_light(const PathParams* params, __global const float* envmap_image,
                                __global const float* envmap_cdf, float3 direction, float* pdf)
{
    if (params->envmap_width == 0) {
        *pdf = 0.0f;
        return LOAD_XYZ(params->environment);
    }
    *pdf = params->environment_probability > 0.0f
        ? params->environment_probability * envmap_pdf(params, envmap_cdf, direction) : 0.0f;
    return envmap_radiance(params, envmap_image, direction);
}

/* Seen from `from`, whether the analytic sphere (centre, radius) lies
 * outside it, and then the solid angle of the cone it subtends over 2 pi:
 * 1 - cos theta_max, as sin^2 / (1 + cos), which keeps a far sphere's tiny
 * cone.  A point within twice the spawn offset of the surface (path.cl's
 * spawn_offset, without its rounding term) counts as on it: a vertex on
 * the sphere, rounded outside, would see it fill a hemisphere and sample
 * itself at t near 0, and a ray it spawns must be judged as it was. */
inline bool sphere_cone(const PathParams* params, float3 centre, float radius, float3 from,
                        float* one_minus_cos)
{
    float3 axis = centre - from;
    float ax = abs_float(centre.x), ay = abs_float(centre.y), az = abs_float(centre.z);
    float largest = (ax > ay ? (ax > az ? ax : az) : (ay > az ? ay : az)) + radius;
    float shell = radius + 2.0f * (params->ray_offset + RAY_EPSILON * largest);
    float d2 = dot3(axis, axis), r2 = radius * radius;
    if (!(d2 > shell * shell))
        return false;
    float sin2 = r2 / d2;
    *one_minus_cos = sin2 / (1.0f + SQRT(1.0f - sin2));
    return true;
}

/* The solid-angle density with which a light sample from `from` picks a
 * point at `distance` with cosine `cosine` on the emitter of material m (P
 * of that emitter times 1 / its area in emitter_pdf): uniform in its area,
 * emitter_pdf d^2 / cos, but for an analytic sphere seen from outside,
 * uniform in the cone it subtends (Mitsuba's and pbrt's spheres):
 * emitter_pdf 4 pi r^2 / (2 pi (1 - cos theta_max)). */
inline float emitter_density(const PathParams* params, __global const PathMaterial* m,
                             float3 from, float distance, float cosine)
{
    float radius = m->light_sphere[3];
    float one_minus_cos;
    if (radius > 0.0f && sphere_cone(params, LOAD_XYZ(m->light_sphere), radius, from,
                                     &one_minus_cos))
        return m->emitter_pdf * (2.0f * radius * radius) / one_minus_cos;
    return m->emitter_pdf * distance * distance / cosine;
}

/* One light sample: by the map's density for an environment map
 * (render/envmap.h; a constant environment takes none), a point or directional light (a delta:
 * its pdf is the chance of picking it, and MIS leaves it alone), or uniform
 * in area on an emissive triangle or analytic sphere (in the cone a sphere
 * subtends, seen from outside: emitter_density) picked by power (its area
 * times its radiance's luminance); the lights themselves are picked by power
 * (hlbvh_cl/render/emitters.py).  Its four numbers are random_salted(pixel,
 * salts.s0..s3): the choice of light, then three for the point or direction. */
FORCE_INLINE LightSample sample_light(float3 x, const PathParams* params,
                                      const LightTables* tables, uint pixel, uint4 salts,
                                      bool* delta)
{
    LightSample out = {(float3)(0.0f), 0.0f, (float3)(0.0f), 0.0f};
    float choice = random_salted(pixel, salts.s0);
    *delta = false;
    float u1 = random_salted(pixel, salts.s2);
    float u2 = random_salted(pixel, salts.s3);
    if (choice < params->environment_probability) {  /* the map's (0 without one) */
        out.reach = INFINITY;
        out.direction = envmap_sample(params, tables->envmap_cdf,
                                      random_salted(pixel, salts.s1), u1, u2, &out.pdf);
        out.radiance = envmap_radiance(params, tables->envmap_image, out.direction);
        out.pdf *= params->environment_probability;
        return out;
    }
    choice -= params->environment_probability;
    if (choice < params->delta_probability) {
        *delta = true;
        for (uint i = 0; i < params->delta_lights; ++i) {
            __global const DeltaLight* light = tables->delta_lights + i;
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
                out.reach = SQRT(squared);
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
    uint entries = params->light_triangles + params->light_spheres;
    if (entries == 0)
        return out;
    uint k = pick(tables->light_cdf, entries, random_salted(pixel, salts.s1));
    __global const float* v = tables->light_vertices + 9 * (size_t)k;
    float3 p, normal;
    float one_minus_cos;
    float3 centre = LOAD_XYZ(v);  /* a sphere's, in its row */
    float radius = v[3];
    bool cone = k >= params->light_triangles
                && sphere_cone(params, centre, radius, x, &one_minus_cos);
    if (cone) {
        /* an analytic sphere (centre, radius in its row) seen from outside:
         * a direction uniform in the cone it subtends, cos theta uniform in
         * [cos theta_max, 1] about the axis to its centre, and the point
         * where it meets the near side (at the rim, where it grazes it) */
        /* In scalars: Intel's CPU compiler (2026.22) vectorized this
         * branch's float3 arithmetic, and its calls of orthonormal_basis,
         * length3 and normalize3, into other lanes' values. */
        float cos_phi, sin_phi = sincos_turn(u2, &cos_phi);  /* the azimuth */
        float ax = centre.x - x.x, ay = centre.y - x.y, az = centre.z - x.z;
        float d = SQRT(ax * ax + ay * ay + az * az);
        ax /= d;
        ay /= d;
        az /= d;
        /* an orthonormal basis about the axis (Duff et al. 2017), in scalars */
        float sign = sign_of(az);
        float a = -1.0f / (sign + az);
        float b = ax * ay * a;
        float b1x = 1.0f + sign * ax * ax * a, b1y = sign * b, b1z = -sign * ax;
        float b2x = b, b2y = sign + ay * ay * a, b2z = -ay;
        float drop = u1 * one_minus_cos;  /* 1 - cos theta */
        float sin2 = drop * (2.0f - drop);
        float sin_theta = SQRT(sin2);
        float c1 = sin_theta * cos_phi, c2 = sin_theta * sin_phi, c3 = 1.0f - drop;
        float wx = c1 * b1x + c2 * b2x + c3 * ax, wy = c1 * b1y + c2 * b2y + c3 * ay;
        float wz = c1 * b1z + c2 * b2z + c3 * az;
        float across = radius * radius - d * d * sin2;
        float t = d * (1.0f - drop) - SQRT(across > 0.0f ? across : 0.0f);
        float px = x.x + t * wx, py = x.y + t * wy, pz = x.z + t * wz;
        float nx = px - centre.x, ny = py - centre.y, nz = pz - centre.z;
        float n = SQRT(nx * nx + ny * ny + nz * nz);
        p = (float3)(px, py, pz);
        normal = (float3)(nx / n, ny / n, nz / n);
    } else if (k >= params->light_triangles) {
        /* one seen from inside or on it: a point uniform on it (pbrt-v4's
         * SampleUniformSphere), its outward normal; the half turned away
         * from x gives no sample, as a triangle's back */
        float cos_phi, sin_phi = sincos_turn(u2, &cos_phi);  /* the azimuth */
        float z = 1.0f - 2.0f * u1;
        float r = SQRT(1.0f - z * z > 0.0f ? 1.0f - z * z : 0.0f);
        normal = (float3)(r * cos_phi, r * sin_phi, z);
        p = centre + radius * normal;
    } else {
        float3 v0 = LOAD_XYZ(v), v1 = LOAD_XYZ(v + 3), v2 = LOAD_XYZ(v + 6);
        float root = SQRT(u1);  /* uniform in the triangle: pbrt-v4 SampleUniformTriangle's map */
        float b0 = 1.0f - root, b1 = u2 * root;
        p = b0 * v0 + b1 * v1 + (1.0f - b0 - b1) * v2;
        /* the shading normal there (Mitsuba's Mesh::sample_position), unless
         * the mesh has face normals (zeros in the table) */
        __global const float* ln = tables->light_normals + 9 * (size_t)k;
        float3 smooth = b0 * LOAD_XYZ(ln) + b1 * LOAD_XYZ(ln + 3)
                        + (1.0f - b0 - b1) * LOAD_XYZ(ln + 6);
        normal = normalize3(dot3(smooth, smooth) > 0.0f ? smooth : cross3(v1 - v0, v2 - v0));
    }
    float3 to_light = p - x;
    float squared = dot3(to_light, to_light);
    float distance = SQRT(squared);
    if (!(distance > 0.0f))
        return out;
    out.direction = to_light / distance;
    float cosine = -dot3(normal, out.direction);
    if (!(cosine > 0.0f))  /* its back side: area lights emit on the front only */
        return out;
    __global const PathMaterial* light = tables->materials + tables->light_geom[k];
    out.reach = distance;
    out.radiance = LOAD_XYZ(light->radiance);
    /* emitter_density's, spelled out: Intel's CPU compiler (2026.22)
     * vectorized a second sphere_cone here into other lanes' values */
    out.pdf = cone ? light->emitter_pdf * (2.0f * radius * radius) / one_minus_cos
                   : light->emitter_pdf * squared / cosine;
    return out;
}

#endif /* RENDER_LIGHTS_H */
