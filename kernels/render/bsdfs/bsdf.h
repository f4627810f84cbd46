/* A mesh's BSDF, by PathMaterial.bsdf: sampling and evaluation dispatched
 * to the one header per BSDF in this folder. */
#ifndef BSDFS_BSDF_H
#define BSDFS_BSDF_H

#include "render/bsdfs/conductor.h"
#include "render/bsdfs/dielectric.h"
#include "render/bsdfs/diffuse.h"
#include "render/bsdfs/roughconductor.h"

#define BSDF_DIFFUSE 0
#define BSDF_CONDUCTOR 1
#define BSDF_DIELECTRIC 2
#define BSDF_ROUGHCONDUCTOR 3

/* Whether the BSDF has a back side: one-sided ones (diffuse, conductor)
 * are black seen from behind unless twosided; a dielectric is seen from
 * both sides by nature. */
inline bool bsdf_has_sides(__global const PathMaterial* m)
{
    return m->bsdf != BSDF_DIELECTRIC;
}

/* n: the facing normal for a BSDF with sides, else the geometric one. */
inline BsdfSample bsdf_sample(__global const PathMaterial* m, float3 n, float3 wo, float u0,
                              float u1, float u2)
{
    if (m->bsdf == BSDF_CONDUCTOR)
        return conductor_sample(m, n, wo);
    if (m->bsdf == BSDF_DIELECTRIC)
        return dielectric_sample(m, n, wo, u0);
    if (m->bsdf == BSDF_ROUGHCONDUCTOR)
        return roughconductor_sample(m, n, wo, u1, u2);
    return diffuse_sample(m, n, u1, u2);
}

/* f * cos towards wi and its density; 0 for delta BSDFs (nothing to
 * evaluate: a light sample cannot meet a delta lobe). */
inline float3 bsdf_eval(__global const PathMaterial* m, float3 n, float3 wo, float3 wi,
                        float* pdf)
{
    if (m->bsdf == BSDF_DIFFUSE)
        return diffuse_eval(m, n, wi, pdf);
    if (m->bsdf == BSDF_ROUGHCONDUCTOR)
        return roughconductor_eval(m, n, wo, wi, pdf);
    *pdf = 0.0f;
    return (float3)(0.0f);
}

/* Whether the BSDF has a density (bsdf_eval can be nonzero): a light
 * sample is worth taking. */
inline bool bsdf_has_density(__global const PathMaterial* m)
{
    return m->bsdf == BSDF_DIFFUSE || m->bsdf == BSDF_ROUGHCONDUCTOR;
}

#endif /* BSDFS_BSDF_H */
