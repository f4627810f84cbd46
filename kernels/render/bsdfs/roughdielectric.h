/* Mitsuba 3's `roughdielectric`: a rough interface of relative index
 * eta[0] (Walter et al. 2007, "Microfacet Models for Refraction through
 * Rough Surfaces"), GGX or Beckmann (microfacet.h).  In the frame turned
 * to the viewer (o.z > 0, e the index ratio the light meets there):
 *   reflection  f cos = F D G / (4 o.z) times `reflectance` (eq. 20),
 *   refraction  f cos = (1 - F) D G |o.m| |i.m| / (o.z (o.m + e i.m)^2)
 *               times `transmittance` (eq. 21 with the radiance's 1 / e^2,
 *               Veach 1997 sec. 5.2, as Mitsuba's radiance mode),
 * with m = normalize(o + e i) (eq. 16).  Sampling draws m, then reflects
 * with Fresnel's probability F(o . m) or refracts; the density carries the
 * half vector's Jacobian, 1 / (4 |i.m|) or e^2 |i.m| / (o.m + e i.m)^2
 * (eqs. 14, 17); a sample's weight is its f cos over that density.  No back side: n is the geometric normal. */
#ifndef BSDFS_ROUGHDIELECTRIC_H
#define BSDFS_ROUGHDIELECTRIC_H

#include "render/bsdfs/fresnel.h"
#include "render/bsdfs/microfacet.h"
#include "render/bsdfs/sample.h"
#include "render/surface.h"

/* The frame turned to wo: n flipped where wo is behind it, and the index
 * ratio the light meets on that side. */
inline float roughdielectric_side(__global const PathMaterial* m, float3* n, float3 wo)
{
    if (dot3(*n, wo) >= 0.0f)
        return m->eta[0];
    *n = -*n;
    return 1.0f / m->eta[0];
}

/* f cos towards i and its density, in the turned frame (o.z > 0). */
inline float3 roughdielectric_local(__global const PathMaterial* m, float e, float3 o, float3 i,
                                    float* pdf)
{
    *pdf = 0.0f;
    if (!(o.z > 0.0f) || i.z == 0.0f)
        return (float3)(0.0f);
    bool reflect = i.z > 0.0f;
    float3 h = normalize3(reflect ? o + i : o + e * i);
    h = h.z < 0.0f ? -h : h;
    float oh = dot(o, h), ih = dot(i, h);
    /* the micro- and macrosurface agree on each direction's side (Mitsuba's rule) */
    if (!(oh > 0.0f) || !(ih * i.z > 0.0f))
        return (float3)(0.0f);
    uint type = m->distribution;
    float alpha = m->alpha;
    float cos_t, eta_it;
    float f = fresnel_dielectric(oh, e, &cos_t, &eta_it);
    float d = microfacet_d(type, alpha, h);
    float g = microfacet_g1(type, alpha, o, h) * microfacet_g1(type, alpha, i, h);
    float density = microfacet_pdf(type, alpha, o, h);
    if (reflect) {
        *pdf = density * f / (4.0f * ih);
        return LOAD_XYZ(m->reflectance) * (f * d * g / (4.0f * o.z));
    }
    float denominator = oh + e * ih;
    denominator *= denominator;
    *pdf = density * (1.0f - f) * e * e * fabs(ih) / denominator;
    return LOAD_XYZ(m->transmittance) * ((1.0f - f) * d * g * oh * abs_float(ih) / (o.z * denominator));
}

inline BsdfSample roughdielectric_sample(__global const PathMaterial* m, float3 n, float3 wo,
                                         float u0, float u1, float u2)
{
    BsdfSample out = no_sample();
    float e = roughdielectric_side(m, &n, wo);
    float3 b1, b2, o = local_frame(n, wo, &b1, &b2);
    if (!(o.z > 0.0f))
        return out;
    uint type = m->distribution;
    float alpha = m->alpha;
    float3 h = microfacet_sample(type, alpha, o, u1, u2);
    float oh = dot(o, h);
    if (!(oh > 0.0f))
        return out;
    float cos_t, eta_it;
    float f = fresnel_dielectric(oh, e, &cos_t, &eta_it);
    /* reflect with Fresnel's probability, else refract about m by Snell:
     * i = -o / e + m (o.m / e + cos_t), cos_t < 0 */
    bool reflect = u0 <= f;
    float3 i = normalize3(reflect ? 2.0f * oh * h - o : -o / e + h * (oh / e + cos_t));
    if (reflect != (i.z > 0.0f))  /* off the macrosurface's side: no sample */
        return out;
    float3 value = roughdielectric_local(m, e, o, i, &out.pdf);
    if (!(out.pdf > 0.0f))
        return out;
    out.direction = normalize3(i.x * b1 + i.y * b2 + i.z * n);
    out.weight = value / out.pdf;
    out.eta = i.z < 0.0f ? e : 1.0f;
    return out;
}

inline float3 roughdielectric_eval(__global const PathMaterial* m, float3 n, float3 wo,
                                   float3 wi, float* pdf)
{
    float e = roughdielectric_side(m, &n, wo);
    float3 b1, b2, o = local_frame(n, wo, &b1, &b2);
    return roughdielectric_local(m, e, o, to_local(wi, b1, b2, n), pdf);
}

#endif /* BSDFS_ROUGHDIELECTRIC_H */
