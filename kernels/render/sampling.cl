/* The path integrator's BSDFs (render/bsdfs/) on their own, for tests and
 * users checking a material: draw samples, and evaluate f cos and the
 * density at given directions (hlbvh_cl/render/sampling.py), as Mitsuba's
 * chi2 tests drive its plugins.
 *
 * Kernels (one work-item per direction)
 *   bsdf_samples  sample k of the BSDF of materials[0] at a point with unit
 *                 normal n seen from unit wo: direction, weight f cos / pdf,
 *                 density (0 for a delta lobe); random_unit(k, seed, 0..2)
 *   bsdf_values   f cos and the density towards each of `wi`
 *   envmap_samples  sample k of an environment map's directions
 *                   (render/envmap.h): direction, radiance, density;
 *                   random_unit(k, seed, 0..2)
 *   envmap_values   its radiance and density towards each of `wi`
 *   light_samples   sample k of next-event estimation at a point x
 *                   (render/lights.h): direction, radiance, density (0:
 *                   none), reach; random_unit(k, seed, 0..3)
 *   turn_angles     sin and cos of 2 pi u as the samplers take them
 *                   (render/angles.h), for each u given
 * The normal given is used as the integrator uses it: turned towards wo for
 * a BSDF with sides, as it is for a dielectric. */
#include "core/portable.h"
#include "core/spelled.h"
#include "render/bsdfs/bsdf.h"
#include "render/random.h"
#include "render/envmap.h"
#include "render/lights.h"

/* The BSDF's normal as path_surface computes it; false where the back of
 * a one-sided BSDF is seen (black). */
inline bool facing(__global const PathMaterial* m, float3 n, float3 wo, float3* out)
{
    *out = n;
    if (bsdf_has_sides(m) && !(dot3(n, wo) > 0.0f)) {
        *out = -n;
        return m->twosided != 0;
    }
    return true;
}

__kernel void bsdf_samples(__global const PathMaterial* materials, const float nx,
                           const float ny, const float nz, const float ox, const float oy,
                           const float oz, const uint count, const uint seed,
                           __global float* directions, __global float* weights,
                           __global float* pdfs)
{
    uint k = get_global_id(0);
    if (k >= count)
        return;
    float3 wo = (float3)(ox, oy, oz), n;
    BsdfSample s = no_sample();
    if (facing(materials, (float3)(nx, ny, nz), wo, &n))
        s = bsdf_sample(materials, n, wo, random_unit(k, seed, 0), random_unit(k, seed, 1),
                        random_unit(k, seed, 2));
    store3(directions + 3 * (size_t)k, s.direction);
    store3(weights + 3 * (size_t)k, s.weight);
    pdfs[k] = s.pdf;
}

__kernel void bsdf_values(__global const PathMaterial* materials, const float nx,
                          const float ny, const float nz, const float ox, const float oy,
                          const float oz, const uint count, __global const float* wi,
                          __global float* values, __global float* pdfs)
{
    uint k = get_global_id(0);
    if (k >= count)
        return;
    float3 wo = (float3)(ox, oy, oz), n;
    float pdf = 0.0f;
    float3 value = (float3)(0.0f);
    if (facing(materials, (float3)(nx, ny, nz), wo, &n))
        value = bsdf_eval(materials, n, wo, LOAD_XYZ(wi + 3 * (size_t)k), &pdf);
    store3(values + 3 * (size_t)k, value);
    pdfs[k] = pdf;
}

__kernel void envmap_samples(const PathParams params, __global const float* image,
                             __global const float* cdf, const uint count, const uint seed,
                             __global float* directions, __global float* radiance,
                             __global float* pdfs)
{
    uint k = get_global_id(0);
    float pdf;
    if (k >= count)
        return;
    float3 d = envmap_sample(&params, cdf, random_unit(k, seed, 0), random_unit(k, seed, 1),
                             random_unit(k, seed, 2), &pdf);
    store3(directions + 3 * (size_t)k, d);
    store3(radiance + 3 * (size_t)k, envmap_radiance(&params, image, d));
    pdfs[k] = pdf;
}

__kernel void envmap_values(const PathParams params, __global const float* image,
                            __global const float* cdf, const uint count,
                            __global const float* wi, __global float* radiance,
                            __global float* pdfs)
{
    uint k = get_global_id(0);
    if (k >= count)
        return;
    float3 d = LOAD_XYZ(wi + 3 * (size_t)k);
    store3(radiance + 3 * (size_t)k, envmap_radiance(&params, image, d));
    pdfs[k] = envmap_pdf(&params, cdf, d);
}

__kernel void light_samples(const PathParams params, __global const PathMaterial* materials,
                            __global const float* light_vertices,
                            __global const float* light_normals,
                            __global const float* light_cdf, __global const int* light_geom,
                            __global const DeltaLight* delta_lights,
                            __global const float* envmap_image, __global const float* envmap_cdf,
                            const float x, const float y, const float z, const uint count,
                            const uint seed, __global float* directions,
                            __global float* radiance, __global float* pdfs,
                            __global float* reaches)
{
    uint k = get_global_id(0);
    if (k >= count)
        return;
    const LightTables tables = {materials, light_vertices, light_normals, light_cdf,
                                light_geom, delta_lights, envmap_image, envmap_cdf};
    bool delta;
    uint4 salts = (uint4)(random_salt(seed, 0), random_salt(seed, 1), random_salt(seed, 2),
                          random_salt(seed, 3));
    LightSample s = sample_light((float3)(x, y, z), &params, &tables, k, salts, &delta);
    store3(directions + 3 * (size_t)k, s.direction);
    store3(radiance + 3 * (size_t)k, s.radiance);
    pdfs[k] = s.pdf;
    reaches[k] = s.reach;
}

__kernel void turn_angles(const uint count, __global const float* turns, __global float* sines,
                          __global float* cosines)
{
    uint k = get_global_id(0);
    if (k >= count)
        return;
    float cosine;
    sines[k] = sincos_turn(turns[k], &cosine);
    cosines[k] = cosine;
}
