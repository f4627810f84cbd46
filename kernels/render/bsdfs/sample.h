/* What sampling a BSDF gives: the direction, the weight f cos / pdf the
 * path's throughput takes, the density (0 for a delta lobe, whose light
 * sample and MIS are skipped), and the index ratio crossed (1 for a
 * reflection), which Russian roulette follows (Mitsuba's eta^2). */
#ifndef BSDFS_SAMPLE_H
#define BSDFS_SAMPLE_H

#include "render/integrators/path.h"

#define INV_PI 0.31830988618379067f

typedef struct {
    float3 direction;
    float3 weight;     /* 0: no sample (the path ends) */
    float pdf;
    float eta;
    bool delta;
} BsdfSample;

inline BsdfSample no_sample(void)
{
    BsdfSample out = {(float3)(0.0f), (float3)(0.0f), 0.0f, 1.0f, false};
    return out;
}

#endif /* BSDFS_SAMPLE_H */
