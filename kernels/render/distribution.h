/* Sampling a discrete distribution by its CDF: the path integrator's
 * emissive triangles and the environment map's cells (render/envmap.h). */
#ifndef RENDER_DISTRIBUTION_H
#define RENDER_DISTRIBUTION_H

/* The first index whose cumulative weight exceeds u (cdf ascending, the
 * last entry 1): a binary search.  An entry of no weight is never picked. */
inline uint pick(__global const float* cdf, uint count, float u)
{
    uint lo = 0, hi = count - 1;
    while (lo < hi) {
        uint mid = (lo + hi) / 2;
        if (cdf[mid] > u)
            hi = mid;
        else
            lo = mid + 1;
    }
    return lo;
}

/* The weight of entry k: its step of the CDF (what pick gives it). */
inline float picked_weight(__global const float* cdf, uint k)
{
    return cdf[k] - (k > 0 ? cdf[k - 1] : 0.0f);
}

#endif /* RENDER_DISTRIBUTION_H */
