/* The isotropic GGX microfacet distribution (Walter et al. 2007) with
 * Smith's shadowing, and sampling of its visible normals (Heitz 2018,
 * "Sampling the GGX Distribution of Visible Normals", JCGT 7(4)), in a
 * local frame whose z is the surface normal: Mitsuba 3's
 * MicrofacetDistribution with distribution "ggx" and sample_visible. */
#ifndef BSDFS_MICROFACET_H
#define BSDFS_MICROFACET_H

#include "render/bsdfs/sample.h"

/* D(m) = alpha^2 / (pi (cos^2 (alpha^2 - 1) + 1)^2) */
inline float ggx_d(float alpha, float3 m)
{
    if (!(m.z > 0.0f))
        return 0.0f;
    float a2 = alpha * alpha;
    float denominator = m.z * m.z * (a2 - 1.0f) + 1.0f;
    return a2 * INV_PI / (denominator * denominator);
}

/* Smith's G1 of direction v (unit, local) over microfacet m. */
inline float ggx_g1(float alpha, float3 v, float3 m)
{
    if (!(dot(v, m) * v.z > 0.0f))
        return 0.0f;
    float cos2 = v.z * v.z;
    float tan2 = (1.0f - cos2) / cos2;
    return 2.0f / (1.0f + sqrt(1.0f + alpha * alpha * tan2));
}

/* A visible normal for wo (local, wo.z > 0) from u1, u2 in [0, 1). */
inline float3 ggx_sample_visible(float alpha, float3 wo, float u1, float u2)
{
    float3 stretched = normalize((float3)(alpha * wo.x, alpha * wo.y, wo.z));
    float length2 = stretched.x * stretched.x + stretched.y * stretched.y;
    float3 t1 = length2 > 0.0f ? (float3)(-stretched.y, stretched.x, 0.0f) / sqrt(length2)
                               : (float3)(1.0f, 0.0f, 0.0f);
    float3 t2 = cross(stretched, t1);
    float r = sqrt(u1);
    float cosine, sine = sincos(2.0f * M_PI_F * u2, &cosine);
    float p1 = r * cosine, p2 = r * sine;
    float s = 0.5f * (1.0f + stretched.z);
    p2 = (1.0f - s) * sqrt(1.0f - p1 * p1) + s * p2;
    float lift = 1.0f - p1 * p1 - p2 * p2;
    float3 h = p1 * t1 + p2 * t2 + sqrt(lift > 0.0f ? lift : 0.0f) * stretched;
    return normalize((float3)(alpha * h.x, alpha * h.y, h.z > 0.0f ? h.z : 0.0f));
}

/* The density of ggx_sample_visible's m for wo: G1(wo, m) (wo . m) D(m) / wo.z. */
inline float ggx_pdf_visible(float alpha, float3 wo, float3 m)
{
    float cosine = dot(wo, m);
    if (!(cosine > 0.0f) || !(wo.z > 0.0f))
        return 0.0f;
    return ggx_g1(alpha, wo, m) * cosine * ggx_d(alpha, m) / wo.z;
}

#endif /* BSDFS_MICROFACET_H */
