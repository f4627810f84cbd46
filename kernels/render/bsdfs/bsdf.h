/* A mesh's BSDF, by PathMaterial.bsdf: sampling and evaluation dispatched
 * to the one header per BSDF in this folder. */
#ifndef BSDFS_BSDF_H
#define BSDFS_BSDF_H

#include "render/bsdfs/conductor.h"
#include "render/bsdfs/dielectric.h"
#include "render/bsdfs/diffuse.h"
#include "render/bsdfs/plastic.h"
#include "render/bsdfs/roughconductor.h"
#include "render/bsdfs/roughdielectric.h"
#include "render/bsdfs/roughplastic.h"

#define BSDF_DIFFUSE 0
#define BSDF_CONDUCTOR 1
#define BSDF_DIELECTRIC 2
#define BSDF_ROUGHCONDUCTOR 3
#define BSDF_PLASTIC 4
#define BSDF_ROUGHPLASTIC 5
#define BSDF_ROUGHDIELECTRIC 6

/* Whether the BSDF has a back side: one-sided ones (diffuse, conductor,
 * plastic) are black seen from behind unless twosided; a dielectric, smooth
 * or rough, is seen from both sides by nature. */
inline bool bsdf_has_sides(__global const PathMaterial* m)
{
    return m->bsdf != BSDF_DIELECTRIC && m->bsdf != BSDF_ROUGHDIELECTRIC;
}

/* n: the facing normal for a BSDF with sides, else the geometric one. */
FORCE_INLINE BsdfSample bsdf_sample(__global const PathMaterial* m, float3 n, float3 wo, float u0,
                              float u1, float u2)
{
    if (m->bsdf == BSDF_CONDUCTOR)
        return conductor_sample(m, n, wo);
    if (m->bsdf == BSDF_DIELECTRIC)
        return dielectric_sample(m, n, wo, u0);
    if (m->bsdf == BSDF_ROUGHCONDUCTOR)
        return roughconductor_sample(m, n, wo, u1, u2);
    if (m->bsdf == BSDF_PLASTIC)
        return plastic_sample(m, n, wo, u0, u1, u2);
    if (m->bsdf == BSDF_ROUGHPLASTIC)
        return roughplastic_sample(m, n, wo, u0, u1, u2);
    if (m->bsdf == BSDF_ROUGHDIELECTRIC)
        return roughdielectric_sample(m, n, wo, u0, u1, u2);
    return diffuse_sample(m, n, u1, u2);
}

/* f * cos towards wi and its density, of the smooth lobes only: 0 for
 * delta BSDFs and lobes (nothing to evaluate: a light sample cannot meet a
 * delta lobe).  For a BSDF of both (plastic) the density is the one with
 * which bsdf_sample draws wi, its smooth lobe's share included, so that
 * MIS weighs a light sample against it; a delta sample is marked delta,
 * and an emitter it meets takes no MIS (path.cl). */
FORCE_INLINE float3 bsdf_eval(__global const PathMaterial* m, float3 n, float3 wo, float3 wi,
                        float* pdf)
{
    if (m->bsdf == BSDF_DIFFUSE)
        return diffuse_eval(m, n, wi, pdf);
    if (m->bsdf == BSDF_ROUGHCONDUCTOR)
        return roughconductor_eval(m, n, wo, wi, pdf);
    if (m->bsdf == BSDF_PLASTIC)
        return plastic_eval(m, n, wo, wi, pdf);
    if (m->bsdf == BSDF_ROUGHPLASTIC)
        return roughplastic_eval(m, n, wo, wi, pdf);
    if (m->bsdf == BSDF_ROUGHDIELECTRIC)
        return roughdielectric_eval(m, n, wo, wi, pdf);
    *pdf = 0.0f;
    return (float3)(0.0f);
}

/* Whether the BSDF has a density (bsdf_eval can be nonzero): a light
 * sample is worth taking. */
inline bool bsdf_has_density(__global const PathMaterial* m)
{
    return m->bsdf != BSDF_CONDUCTOR && m->bsdf != BSDF_DIELECTRIC;
}

#endif /* BSDFS_BSDF_H */
