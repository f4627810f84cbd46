/* Mitsuba 3's `plastic`: a diffuse base of albedo `reflectance` under a
 * smooth dielectric coating of relative index eta[0] (Weidlich & Wilkie
 * 2007, "Arbitrarily layered micro-facet surfaces", as Mitsuba simplifies
 * it).  Two lobes: the coating's mirror reflection, a delta of weight
 * F(cos_o) times `specular`, and the base seen through the coating,
 *   f cos = R / (1 - internal) / eta^2 (1 - F(cos_o)) (1 - F(cos_i)) cos_i / pi
 * where `internal` is the coating's diffuse reflectance from inside (times
 * R with `nonlinear`): light bouncing between base and coating.  Sampling
 * picks the coating with probability prob_specular (Fresnel's share
 * steered by specular_weight), else the base by cos_i / pi; the base's
 * density is therefore (1 - prob_specular) cos_i / pi, which is what
 * evaluation returns for MIS.  One-sided. */
#ifndef BSDFS_PLASTIC_H
#define BSDFS_PLASTIC_H

#include "render/bsdfs/fresnel.h"
#include "render/bsdfs/sample.h"
#include "render/surface.h"

/* The coating's reflectance at cos (> 0, from outside). */
inline float plastic_fresnel(__global const PathMaterial* m, float cosine)
{
    float cos_t, eta_it;
    return fresnel_dielectric(cosine, m->eta[0], &cos_t, &eta_it);
}

/* The chance of sampling the coating's mirror lobe, seen at Fresnel f_o. */
inline float plastic_specular_probability(__global const PathMaterial* m, float f_o)
{
    float specular = f_o * m->specular_weight;
    float diffuse = (1.0f - f_o) * (1.0f - m->specular_weight);
    return specular / (specular + diffuse);
}

/* The base's f cos / (cos_i / pi), seen at Fresnel f_o, towards cos_i. */
inline float3 plastic_base(__global const PathMaterial* m, float f_o, float cos_i)
{
    float3 albedo = LOAD_XYZ(m->reflectance);
    float3 internal = m->nonlinear ? albedo * m->internal : (float3)(m->internal);
    float eta = m->eta[0];
    return albedo / (1.0f - internal)
           * ((1.0f - f_o) * (1.0f - plastic_fresnel(m, cos_i)) / (eta * eta));
}

inline BsdfSample plastic_sample(__global const PathMaterial* m, float3 n, float3 wo, float u0,
                                 float u1, float u2)
{
    BsdfSample out = no_sample();
    float cos_o = dot3(n, wo);
    if (!(cos_o > 0.0f))
        return out;
    float f_o = plastic_fresnel(m, cos_o);
    float specular = plastic_specular_probability(m, f_o);
    if (u0 < specular) {
        out.direction = 2.0f * cos_o * n - wo;
        out.weight = LOAD_XYZ(m->specular) * (f_o / specular);
        out.delta = true;
        return out;
    }
    out.direction = cosine_sample(n, u1, u2);
    float cos_i = dot3(n, out.direction);
    if (!(cos_i > 0.0f))
        return out;
    out.pdf = (1.0f - specular) * cos_i * INV_PI;
    out.weight = plastic_base(m, f_o, cos_i) / (1.0f - specular);
    return out;
}

/* The base's f cos towards wi and its density; the mirror lobe, a delta,
 * has no value to evaluate. */
inline float3 plastic_eval(__global const PathMaterial* m, float3 n, float3 wo, float3 wi,
                           float* pdf)
{
    *pdf = 0.0f;
    float cos_o = dot3(n, wo), cos_i = dot3(n, wi);
    if (!(cos_o > 0.0f) || !(cos_i > 0.0f))
        return (float3)(0.0f);
    float f_o = plastic_fresnel(m, cos_o);
    *pdf = (1.0f - plastic_specular_probability(m, f_o)) * cos_i * INV_PI;
    return plastic_base(m, f_o, cos_i) * (cos_i * INV_PI);
}

#endif /* BSDFS_PLASTIC_H */
