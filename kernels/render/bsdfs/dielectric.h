/* Mitsuba 3's `dielectric`: a smooth interface of relative index eta =
 * int_ior / ext_ior, which reflects with Fresnel's probability and else
 * refracts; refraction scales radiance by 1 / eta_it^2 (the solid angle's
 * compression, Veach 1997 sec. 5.2), as Mitsuba does for radiance.  It has
 * no back side: n is the geometric normal, and whether the light comes from
 * inside is the sign of n . wo.  A delta BSDF. */
#ifndef BSDFS_DIELECTRIC_H
#define BSDFS_DIELECTRIC_H

#include "render/bsdfs/fresnel.h"
#include "render/bsdfs/sample.h"
#include "render/surface.h"

inline BsdfSample dielectric_sample(__global const PathMaterial* m, float3 n, float3 wo, float u)
{
    BsdfSample out = no_sample();
    float cos_i = dot3(n, wo), cos_t, eta_it;
    float reflectance = fresnel_dielectric(cos_i, m->eta[0], &cos_t, &eta_it);
    out.delta = true;
    if (u <= reflectance) {
        out.direction = 2.0f * cos_i * n - wo;
        out.weight = LOAD_XYZ(m->reflectance);
        return out;
    }
    /* Snell: wt = -wo / eta_it + n (cos_i / eta_it + cos_t), cos_t signed */
    out.direction = normalize3(-wo / eta_it + n * (cos_i / eta_it + cos_t));
    out.weight = LOAD_XYZ(m->transmittance) / (eta_it * eta_it);
    out.eta = eta_it;
    return out;
}

#endif /* BSDFS_DIELECTRIC_H */
