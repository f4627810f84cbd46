/* Mitsuba 3's `conductor`: a smooth metal, mirror reflection weighted by
 * Fresnel's conductor equations (eta + i k) times `specular_reflectance`;
 * eta = 0, k = 1 (material "none") is a perfect mirror.  A delta BSDF: no
 * light sample, and no density. */
#ifndef BSDFS_CONDUCTOR_H
#define BSDFS_CONDUCTOR_H

#include "render/bsdfs/fresnel.h"
#include "render/bsdfs/sample.h"
#include "render/surface.h"

inline BsdfSample conductor_sample(__global const PathMaterial* m, float3 n, float3 wo)
{
    BsdfSample out = no_sample();
    float cosine = dot3(n, wo);
    if (!(cosine > 0.0f))
        return out;
    out.direction = 2.0f * cosine * n - wo;
    out.weight = LOAD_XYZ(m->reflectance)
                 * fresnel_conductor(cosine, LOAD_XYZ(m->eta), LOAD_XYZ(m->k));
    out.delta = true;
    return out;
}

#endif /* BSDFS_CONDUCTOR_H */
