/* Mitsuba 3's `diffuse`: Lambert's BSDF, albedo `reflectance`, on the side
 * of n (the caller has turned n to the viewer's side, or given up). */
#ifndef BSDFS_DIFFUSE_H
#define BSDFS_DIFFUSE_H

#include "render/bsdfs/sample.h"
#include "render/surface.h"

inline BsdfSample diffuse_sample(__global const PathMaterial* m, float3 n, float u1, float u2)
{
    BsdfSample out = no_sample();
    out.direction = cosine_sample(n, u1, u2);
    float cosine = dot3(n, out.direction);
    if (!(cosine > 0.0f))
        return out;
    out.weight = LOAD_XYZ(m->reflectance);  /* f cos / pdf = (a / pi) cos / (cos / pi) */
    out.pdf = cosine * INV_PI;
    return out;
}

/* f * cos towards wi, and the density with which diffuse_sample picks it. */
inline float3 diffuse_eval(__global const PathMaterial* m, float3 n, float3 wi, float* pdf)
{
    float cosine = dot3(n, wi);
    if (!(cosine > 0.0f)) {
        *pdf = 0.0f;
        return (float3)(0.0f);
    }
    *pdf = cosine * INV_PI;
    return LOAD_XYZ(m->reflectance) * (cosine * INV_PI);
}

#endif /* BSDFS_DIFFUSE_H */
