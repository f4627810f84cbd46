/* Isotropic microfacet distributions with Smith's shadowing (Walter et al.
 * 2007, "Microfacet Models for Refraction through Rough Surfaces"), in a
 * local frame whose z is the surface normal, as Mitsuba 3's
 * MicrofacetDistribution.  Both are sampled by their visible normals, with
 * density G1(wo, m) (wo . m) D(m) / wo.z (Heitz & d'Eon 2014, eq. 2): GGX by
 * Heitz 2018 ("Sampling the GGX Distribution of Visible Normals", JCGT
 * 7(4)), Beckmann by the slopes of Heitz & d'Eon 2014 ("Importance Sampling
 * Microfacet-Based BSDFs using the Distribution of Visible Normals", EGSR),
 * which at grazing wo leave far less noise than sampling D(m) cos(m). */
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

/* The squared sine of unit v's angle to the normal, from its tangent
 * components: 1 - cos^2 cancels to nothing or to 0 near the normal in
 * float32, where a smooth lobe's D peaks (at alpha 1e-4, GGX's D went to
 * inf and its samples' weights to NaN).  Mitsuba forms its D from them
 * too. */
inline float sin2_of(float3 v) { return v.x * v.x + v.y * v.y; }

/* D(m) = alpha^2 / (pi (cos^2 (alpha^2 - 1) + 1)^2), with the
 * denominator's 1 - cos^2 as sin^2 (sin2_of). */
inline float ggx_d(float alpha, float3 m)
{
    if (!(m.z > 0.0f))
        return 0.0f;
    float a2 = alpha * alpha;
    float denominator = sin2_of(m) + m.z * m.z * a2;
    return a2 * INV_PI / (denominator * denominator);
}

/* Smith's G1 of direction v (unit, local) over microfacet m. */
inline float ggx_g1(float alpha, float3 v, float3 m)
{
    if (!(dot(v, m) * v.z > 0.0f))
        return 0.0f;
    float tan2 = sin2_of(v) / (v.z * v.z);
    return 2.0f / (1.0f + SQRT(1.0f + alpha * alpha * tan2));
}

/* A visible normal for wo (local, wo.z > 0) from u1, u2 in [0, 1). */
inline float3 ggx_sample_visible(float alpha, float3 wo, float u1, float u2)
{
    float3 stretched = normalize3((float3)(alpha * wo.x, alpha * wo.y, wo.z));
    float length2 = stretched.x * stretched.x + stretched.y * stretched.y;
    float3 t1 = length2 > 0.0f ? (float3)(-stretched.y, stretched.x, 0.0f) / SQRT(length2)
                               : (float3)(1.0f, 0.0f, 0.0f);
    float3 t2 = cross3(stretched, t1);
    float r = SQRT(u1);
    float cosine, sine = sincos_turn(u2, &cosine);
    float p1 = r * cosine, p2 = r * sine;
    float s = 0.5f * (1.0f + stretched.z);
    p2 = (1.0f - s) * SQRT(1.0f - p1 * p1) + s * p2;
    float lift = 1.0f - p1 * p1 - p2 * p2;
    float3 h = p1 * t1 + p2 * t2 + SQRT(lift > 0.0f ? lift : 0.0f) * stretched;
    return normalize3((float3)(alpha * h.x, alpha * h.y, h.z > 0.0f ? h.z : 0.0f));
}

/* Beckmann: D(m) = exp(-tan^2 / alpha^2) / (pi alpha^2 cos^4) */
inline float beckmann_d(float alpha, float3 m)
{
    if (!(m.z > 0.0f))
        return 0.0f;
    float cos2 = m.z * m.z, a2 = alpha * alpha;
    float d = exp(-sin2_of(m) / (cos2 * a2)) * INV_PI / (a2 * cos2 * cos2);
    return d * m.z > 1e-20f ? d : 0.0f;  /* as Mitsuba: no denormal tails */
}

/* Smith's G1 for Beckmann by Walter et al.'s rational fit (eq. 27, under
 * 0.35% off), a = 1 / (alpha tan). */
inline float beckmann_g1(float alpha, float3 v, float3 m)
{
    if (!(dot(v, m) * v.z > 0.0f))
        return 0.0f;
    float tan2 = sin2_of(v) / (v.z * v.z);
    if (!(tan2 > 0.0f))
        return 1.0f;
    float a = 1.0f / (alpha * SQRT(tan2));
    if (a >= 1.6f)
        return 1.0f;
    return (3.535f * a + 2.181f * a * a) / (1.0f + 2.276f * a + 2.577f * a * a);
}

/* erf^-1 (OpenCL C has erf but no inverse), |x| < 1: Winitzki's closed
 * form (2008, "A handy approximation for the error function and its
 * inverse", a = 0.147) polished by one Newton step on erf.  Compact rather
 * than Giles' polynomials (2010): Intel's CPU compiler returned wrong
 * normals from every sampler here, GGX's too, once this header grew. */
inline float erfinv_approx(float x)
{
    float l = log((1.0f - x) * (1.0f + x));
    float t = 4.3307467f + 0.5f * l;
    float y = copysign(SQRT(SQRT(t * t - l * 6.802721f) - t), x);
    return y - (erf(y) - x) * 0.88622693f * exp(y * y);
}

/* The slope x along the view of a visible normal of the alpha-1 Beckmann
 * surface, seen at (cos_theta, sin_theta), from u in (0, 1).  The visible
 * slopes have density (cos - x sin) exp(-x^2) / sqrt(pi) for x < cot
 * (Heitz & d'Eon 2014, appendix), whose cdf, over cos / 2, is
 * C(x) = 1 + erf(x) + tan exp(-x^2) / sqrt(pi).  C is smooth and concave in
 * e = erf(x), with dC/de = 1 - x tan, so Newton's method in e solves
 * C = u C(cot) (Jakob's inversion, continuous in u where the paper's fit
 * is not), kept inside its bracket by bisection, from the exact solution
 * at grazing incidence, e = -erf(sqrt(-log u)), scaled to [-1, erf(cot)]. */
inline float beckmann_visible_slope(float cos_theta, float sin_theta, float u)
{
    const float inv_sqrt_pi = 0.5641895835477563f;
    float tan_theta = sin_theta / cos_theta;
    float cot_theta = sin_theta > 0.0f ? cos_theta / sin_theta : MAXFLOAT;
    float high = erf(cot_theta), low = -1.0f;
    u = clamp(u, 1e-6f, 1.0f - 1e-6f);
    float target = u * (1.0f + high + inv_sqrt_pi * tan_theta * exp(-cot_theta * cot_theta));
    float e = -1.0f + (1.0f + high) * erfc(SQRT(-log(u)));
    for (int step = 0; step < 4; step++) {
        float x = erfinv_approx(clamp(e, -1.0f + 1e-7f, 1.0f - 1e-7f));
        float excess = 1.0f + e + inv_sqrt_pi * tan_theta * exp(-x * x) - target;
        if (excess > 0.0f)
            high = e;
        else
            low = e;
        float slope = 1.0f - x * tan_theta;
        float next = e - excess / slope;
        e = slope > 0.0f && next >= low && next <= high ? next : 0.5f * (low + high);
    }
    return erfinv_approx(clamp(e, -1.0f + 1e-7f, 1.0f - 1e-7f));
}

/* A visible Beckmann normal for wo (local, wo.z > 0) from u1, u2 in [0, 1)
 * (Heitz & d'Eon 2014, sec. 4): stretch wo to the alpha-1 surface, draw the
 * slope along its azimuth (above) and the one across it (a Gaussian, which
 * visibility does not weigh), rotate them to wo's azimuth, unstretch them
 * by alpha, and m = (-x, -y, 1) normalised. */
inline float3 beckmann_sample_visible(float alpha, float3 wo, float u1, float u2)
{
    float3 stretched = normalize3((float3)(alpha * wo.x, alpha * wo.y, wo.z));
    float sin_theta = SQRT(stretched.x * stretched.x + stretched.y * stretched.y);
    float cos_phi = sin_theta > 0.0f ? stretched.x / sin_theta : 1.0f;
    float sin_phi = sin_theta > 0.0f ? stretched.y / sin_theta : 0.0f;
    float along = beckmann_visible_slope(stretched.z, sin_theta, u1);
    float across = erfinv_approx(clamp(2.0f * u2 - 1.0f, -1.0f + 1e-6f, 1.0f - 1e-6f));
    float x = alpha * (cos_phi * along - sin_phi * across);
    float y = alpha * (sin_phi * along + cos_phi * across);
    return normalize3((float3)(-x, -y, 1.0f));
}

/* By distribution (MICROFACET_*): D, G1, a visible normal m for wo (local,
 * wo.z > 0), and the density of that m. */
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
    return type == MICROFACET_BECKMANN ? beckmann_sample_visible(alpha, wo, u1, u2)
                                       : ggx_sample_visible(alpha, wo, u1, u2);
}

/* G1(wo, m) (wo . m) D(m) / wo.z (Heitz & d'Eon 2014, eq. 2). */
inline float microfacet_pdf(uint type, float alpha, float3 wo, float3 m)
{
    float cosine = dot(wo, m);
    if (!(cosine > 0.0f) || !(wo.z > 0.0f))
        return 0.0f;
    return microfacet_g1(type, alpha, wo, m) * cosine * microfacet_d(type, alpha, m) / wo.z;
}

/* D G1(wo) G1(wi) (wo . m) / (wo.z pdf(m)): what a sampled m leaves of the
 * microfacet BSDF's f cos / pdf besides Fresnel and the tints, for a
 * reflection or a refraction alike (the Jacobians cancel): G1(wi) (Heitz
 * 2018, eq. 19). */
inline float microfacet_weight(uint type, float alpha, float3 wi, float3 m)
{
    return microfacet_g1(type, alpha, wi, m);
}

#endif /* BSDFS_MICROFACET_H */
