/* Fresnel reflectance of smooth interfaces, unpolarised (Mitsuba 3's
 * fresnel.h; pbrt-v4's FrDielectric and FrComplex). */
#ifndef BSDFS_FRESNEL_H
#define BSDFS_FRESNEL_H

#include "core/spelled.h"

/* A dielectric interface of relative index eta (inside over outside), seen
 * at cos_i (> 0 from outside): the reflectance, and the cosine of the
 * transmitted direction (0 under total internal reflection), whose sign is
 * the opposite of cos_i's.  *eta_it is the index ratio the light crosses. */
inline float fresnel_dielectric(float cos_i, float eta, float* cos_t, float* eta_it)
{
    float ratio = cos_i >= 0.0f ? eta : 1.0f / eta;
    *eta_it = ratio;
    float abs_i = abs_float(cos_i);
    float sin2_t = (1.0f - abs_i * abs_i) / (ratio * ratio);
    if (sin2_t >= 1.0f) {  /* total internal reflection */
        *cos_t = 0.0f;
        return 1.0f;
    }
    float abs_t = SQRT(1.0f - sin2_t);
    if (eta == 1.0f) {
        *cos_t = cos_i >= 0.0f ? -abs_t : abs_t;
        return 0.0f;
    }
    float a_s = (abs_i - ratio * abs_t) / (abs_i + ratio * abs_t);
    float a_p = (abs_t - ratio * abs_i) / (abs_t + ratio * abs_i);
    *cos_t = cos_i >= 0.0f ? -abs_t : abs_t;
    return 0.5f * (a_s * a_s + a_p * a_p);
}

/* A conductor of complex index eta + i k, per channel, seen at cos_i in
 * (0, 1] (Mitsuba 3's fresnel_conductor).  eta = 0, k = 1 reflects all. */
inline float3 fresnel_conductor(float cos_i, float3 eta, float3 k)
{
    float cos2 = cos_i * cos_i, sin2 = 1.0f - cos2;
    float3 eta2 = eta * eta, k2 = k * k;
    float3 t0 = eta2 - k2 - sin2;
    float3 a2pb2 = sqrt(t0 * t0 + 4.0f * eta2 * k2);
    float3 a = sqrt(fmax(0.5f * (a2pb2 + t0), 0.0f));
    float3 t1 = a2pb2 + cos2;
    float3 t2 = 2.0f * cos_i * a;
    float3 rs = (t1 - t2) / (t1 + t2);
    float3 t3 = cos2 * a2pb2 + sin2 * sin2;
    float3 t4 = t2 * sin2;
    float3 rp = rs * (t3 - t4) / (t3 + t4);
    return 0.5f * (rp + rs);
}

#endif /* BSDFS_FRESNEL_H */
