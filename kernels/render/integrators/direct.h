/* What the direct integrator's kernels (render/integrators/direct.cl) read
 * besides the hits; hlbvh_cl/render/integrators/direct.py documents the
 * formulas that use them.  Mirrored by hlbvh_cl/core/layout.py. */
#ifndef INTEGRATORS_DIRECT_H
#define INTEGRATORS_DIRECT_H

typedef struct {
    float light_direction[3];  /* unit, from the surface towards the light */
    float light_intensity;
    float ambient;
    float sky_up[3];           /* unit; the background goes from horizon to zenith along it */
    float sky_horizon[3];
    float sky_zenith[3];
    float ray_offset;          /* shadow and AO rays start this far off the surface */
    float depth_near;          /* "depth" shading: distances near..far -> 1..0 */
    float depth_far;
    float ao_distance;         /* AO rays reach this far */
    float ao_weight;           /* 1 / number of AO rays per sample */
} ShadeParams;

#endif /* INTEGRATORS_DIRECT_H */
