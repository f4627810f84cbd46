/* Isotropic microfacet distributions with Smith's shadowing (Walter et al.
 * 2007, "Microfacet Models for Refraction through Rough Surfaces"), in a
 * local frame whose z is the surface normal, as Mitsuba 3's
 * MicrofacetDistribution: GGX, sampled by its visible normals (Heitz 2018,
 * "Sampling the GGX Distribution of Visible Normals", JCGT 7(4)), and
 * Beckmann, sampled by D(m) cos(m) (Walter et al. eq. 28), which needs no
 * inverse error function; its pdf says so, so the estimate is the same. */
#ifndef BSDFS_MICROFACET_H
#define BSDFS_MICROFACET_H

#include "render/bsdfs/sample.h"
#include "render/surface.h"

#define MICROFACET_GGX 0
#define MICROFACET_BECKMANN 1

/* The local frame around n: (b1, b2, n). */
inline float3 to_local(float3 v, float3 b1, float3 b2, float3 n)
{
    return (float3)(dot3(v, b1), dot3(v, b2), dot3(v, n));
}

/* wo in a local frame around n, whose tangents it writes to b1 and b2. */
inline float3 local_frame(float3 n, float3 wo, float3* b1, float3* b2)
{
    orthonormal_basis(n, b1, b2);
    return to_local(wo, *b1, *b2, n);
}

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

/* Beckmann: D(m) = exp(-tan^2 / alpha^2) / (pi alpha^2 cos^4) */
inline float beckmann_d(float alpha, float3 m)
{
    if (!(m.z > 0.0f))
        return 0.0f;
    float cos2 = m.z * m.z, a2 = alpha * alpha;
    float d = exp(-(1.0f - cos2) / (cos2 * a2)) * INV_PI / (a2 * cos2 * cos2);
    return d * m.z > 1e-20f ? d : 0.0f;  /* as Mitsuba: no denormal tails */
}

/* Smith's G1 for Beckmann by Walter et al.'s rational fit (eq. 27, under
 * 0.35% off), a = 1 / (alpha tan). */
inline float beckmann_g1(float alpha, float3 v, float3 m)
{
    if (!(dot(v, m) * v.z > 0.0f))
        return 0.0f;
    float tan2 = (1.0f - v.z * v.z) / (v.z * v.z);
    if (!(tan2 > 0.0f))
        return 1.0f;
    float a = 1.0f / (alpha * sqrt(tan2));
    if (a >= 1.6f)
        return 1.0f;
    return (3.535f * a + 2.181f * a * a) / (1.0f + 2.276f * a + 2.577f * a * a);
}

/* m with density D(m) cos(m): tan^2 = -alpha^2 log(1 - u1), phi = 2 pi u2. */
inline float3 beckmann_sample(float alpha, float u1, float u2)
{
    float cos_theta = rsqrt(1.0f - alpha * alpha * log(1.0f - u1));
    float sin2 = 1.0f - cos_theta * cos_theta;
    float sin_theta = sqrt(sin2 > 0.0f ? sin2 : 0.0f);
    float cosine, sine = sincos(2.0f * M_PI_F * u2, &cosine);
    return (float3)(sin_theta * cosine, sin_theta * sine, cos_theta);
}

/* By distribution (MICROFACET_*): D, G1, a normal m for wo (local, wo.z >
 * 0), and the density of that m. */
inline float microfacet_d(uint type, float alpha, float3 m)
{
    return type == MICROFACET_BECKMANN ? beckmann_d(alpha, m) : ggx_d(alpha, m);
}

inline float microfacet_g1(uint type, float alpha, float3 v, float3 m)
{
    return type == MICROFACET_BECKMANN ? beckmann_g1(alpha, v, m) : ggx_g1(alpha, v, m);
}

inline float3 microfacet_sample(uint type, float alpha, float3 wo, float u1, float u2)
{
    return type == MICROFACET_BECKMANN ? beckmann_sample(alpha, u1, u2)
                                       : ggx_sample_visible(alpha, wo, u1, u2);
}

inline float microfacet_pdf(uint type, float alpha, float3 wo, float3 m)
{
    if (type == MICROFACET_BECKMANN)
        return beckmann_d(alpha, m) * m.z;
    return ggx_pdf_visible(alpha, wo, m);
}

/* D G1(wo) G1(wi) (wo . m) / (wo.z pdf(m)): what a sampled m leaves of the
 * microfacet BSDF's f cos / pdf besides Fresnel and the tints, for a
 * reflection or a refraction alike (the Jacobians cancel): G1(wi) for
 * visible normals (Heitz 2018, eq. 19), G1 G1 (wo . m) / (wo.z m.z) else. */
inline float microfacet_weight(uint type, float alpha, float3 wo, float3 wi, float3 m)
{
    float g1_in = microfacet_g1(type, alpha, wi, m);
    if (type != MICROFACET_BECKMANN)
        return g1_in;
    return g1_in * beckmann_g1(alpha, wo, m) * dot(wo, m) / (wo.z * m.z);
}

#endif /* BSDFS_MICROFACET_H */
