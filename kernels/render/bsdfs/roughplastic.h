/* Mitsuba 3's `roughplastic`: plastic.h's diffuse base under a rough
 * dielectric coating (GGX or Beckmann, microfacet.h).  Two smooth lobes:
 * the coating's microfacet reflection, F(wo . m) D G / (4 cos_o) times
 * `specular`, and the base seen through it,
 *   f cos = R / (1 - internal) / eta^2 T(cos_o) T(cos_i) cos_i / pi,
 * with T the coating's transmittance, a table by cos theta that the host
 * integrates (materials.py) and `internal` its diffuse reflectance from
 * inside.  Sampling picks the coating with probability (1 - T(cos_o))
 * steered by specular_weight, else the base by cos_i / pi; the density is
 * the mixture of both, as Mitsuba's.  One-sided. */
#ifndef BSDFS_ROUGHPLASTIC_H
#define BSDFS_ROUGHPLASTIC_H

#include "render/bsdfs/fresnel.h"
#include "render/bsdfs/microfacet.h"
#include "render/bsdfs/sample.h"
#include "render/surface.h"

/* T(cos), linear between the table's entries. */
inline float roughplastic_transmission(__global const PathMaterial* m, float cosine)
{
    float x = cosine * (float)(TRANSMISSION_TABLE - 1);
    uint index = x < (float)(TRANSMISSION_TABLE - 2) ? (uint)x : TRANSMISSION_TABLE - 2;
    float t = x - (float)index;
    return (1.0f - t) * m->transmission[index] + t * m->transmission[index + 1];
}

/* The chance of sampling the coating's lobe, seen at cos_o. */
inline float roughplastic_specular_probability(__global const PathMaterial* m, float t_o)
{
    float specular = (1.0f - t_o) * m->specular_weight;
    float diffuse = t_o * (1.0f - m->specular_weight);
    return specular / (specular + diffuse);
}

/* f cos towards i and the mixture's density, in the local frame (o.z > 0). */
inline float3 roughplastic_local(__global const PathMaterial* m, float3 o, float3 i, float* pdf)
{
    *pdf = 0.0f;
    if (!(o.z > 0.0f) || !(i.z > 0.0f))
        return (float3)(0.0f);
    uint type = m->distribution;
    float alpha = m->alpha, eta = m->eta[0];
    float3 h = normalize3(o + i);
    float t_o = roughplastic_transmission(m, o.z), t_i = roughplastic_transmission(m, i.z);
    float specular = roughplastic_specular_probability(m, t_o);
    float d = microfacet_d(type, alpha, h);
    *pdf = specular * microfacet_pdf(type, alpha, o, h) / (4.0f * dot(o, h))
           + (1.0f - specular) * i.z * INV_PI;
    float cos_t, eta_it;
    float f = fresnel_dielectric(dot(o, h), eta, &cos_t, &eta_it);
    float3 coating = LOAD_XYZ(m->specular)
                     * (f * d * microfacet_g1(type, alpha, o, h)
                        * microfacet_g1(type, alpha, i, h) / (4.0f * o.z));
    float3 albedo = LOAD_XYZ(m->reflectance);
    float3 internal = m->nonlinear ? albedo * m->internal : (float3)(m->internal);
    return coating + albedo / (1.0f - internal) * (INV_PI / (eta * eta) * i.z * t_o * t_i);
}

inline BsdfSample roughplastic_sample(__global const PathMaterial* m, float3 n, float3 wo,
                                      float u0, float u1, float u2)
{
    BsdfSample out = no_sample();
    float3 b1, b2, o = local_frame(n, wo, &b1, &b2), i;
    if (!(o.z > 0.0f))
        return out;
    float specular = roughplastic_specular_probability(m, roughplastic_transmission(m, o.z));
    if (u0 < specular) {
        float3 h = microfacet_sample(m->distribution, m->alpha, o, u1, u2);
        i = 2.0f * dot(o, h) * h - o;
    } else {
        i = cosine_local(u1, u2);
    }
    float3 value = roughplastic_local(m, o, i, &out.pdf);
    if (!(out.pdf > 0.0f))
        return out;
    out.direction = normalize3(i.x * b1 + i.y * b2 + i.z * n);
    out.weight = value / out.pdf;
    return out;
}

inline float3 roughplastic_eval(__global const PathMaterial* m, float3 n, float3 wo, float3 wi,
                                float* pdf)
{
    float3 b1, b2, o = local_frame(n, wo, &b1, &b2);
    return roughplastic_local(m, o, to_local(wi, b1, b2, n), pdf);
}

#endif /* BSDFS_ROUGHPLASTIC_H */
