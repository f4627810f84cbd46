/* Mitsuba 3's `roughconductor`: a rough metal,
 * f = F(wi . m) D(m) G1(wo) G1(wi) / (4 cos_o cos_i) with m the half
 * vector, F Fresnel's conductor term times `specular_reflectance`; GGX or
 * Beckmann (microfacet.h), whose sampled m gives the weight
 * F microfacet_weight.  One-sided. */
#ifndef BSDFS_ROUGHCONDUCTOR_H
#define BSDFS_ROUGHCONDUCTOR_H

#include "render/bsdfs/fresnel.h"
#include "render/bsdfs/microfacet.h"
#include "render/bsdfs/sample.h"
#include "render/surface.h"

inline BsdfSample roughconductor_sample(__global const PathMaterial* m, float3 n, float3 wo,
                                        float u1, float u2)
{
    BsdfSample out = no_sample();
    float3 b1, b2, o = local_frame(n, wo, &b1, &b2);
    if (!(o.z > 0.0f))
        return out;
    float alpha = m->alpha;
    float3 h = microfacet_sample(m->distribution, alpha, o, u1, u2);
    float3 i = 2.0f * dot(o, h) * h - o;
    if (!(i.z > 0.0f))
        return out;
    out.direction = normalize3(i.x * b1 + i.y * b2 + i.z * n);
    out.pdf = microfacet_pdf(m->distribution, alpha, o, h) / (4.0f * dot(o, h));
    out.weight = LOAD_XYZ(m->reflectance)
                 * fresnel_conductor(dot(i, h), LOAD_XYZ(m->eta), LOAD_XYZ(m->k))
                 * microfacet_weight(m->distribution, alpha, i, h);
    return out;
}

inline float3 roughconductor_eval(__global const PathMaterial* m, float3 n, float3 wo, float3 wi,
                                  float* pdf)
{
    *pdf = 0.0f;
    float3 b1, b2, o = local_frame(n, wo, &b1, &b2), i = to_local(wi, b1, b2, n);
    if (!(o.z > 0.0f) || !(i.z > 0.0f))
        return (float3)(0.0f);
    float3 h = normalize3(o + i);
    float alpha = m->alpha;
    uint type = m->distribution;
    float d = microfacet_d(type, alpha, h);
    *pdf = microfacet_pdf(type, alpha, o, h) / (4.0f * dot(o, h));
    float3 f = LOAD_XYZ(m->reflectance)
               * fresnel_conductor(dot(i, h), LOAD_XYZ(m->eta), LOAD_XYZ(m->k));
    return f * (d * microfacet_g1(type, alpha, o, h) * microfacet_g1(type, alpha, i, h)
                / (4.0f * o.z));
}

#endif /* BSDFS_ROUGHCONDUCTOR_H */
