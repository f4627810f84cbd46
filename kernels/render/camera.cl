/* Primary ray generation: one pinhole-camera ray per pixel and sample.
 *
 * Kernel
 *   primary_rays  one ray per pixel of the pass of `rows` rows from row
 *                 first_row of a width x height image (pixels row-major from
 *                 the top-left one), in tile order: over the 2D range of
 *                 pixel_in_pass (render/tiles.h)
 *
 * Pixel (x, y), y counting down from the top row, is the square
 * [x, x + 1] x [y, y + 1]; a sample at (x + jx, y + jy) maps to the image
 * plane as sx = 2 (x + jx) / width - 1, sy = 1 - 2 (y + jy) / height
 * (hlbvh_cl/io/scenefile.py's convention, which takes the pixel centre,
 * jx = jy = 0.5).  With `jitter` 1 (a box filter), (jx, jy) =
 * (random_unit(pixel, sample, 0), random_unit(pixel, sample, 1))
 * (render/random.h), so a render with several samples per pixel is the same
 * every time; with 2 (Mitsuba's Gaussian filter: standard deviation 0.5
 * pixel, cut at 2) each is 0.5 plus an offset drawn from that filter (filter
 * importance sampling, pbrt-v4 sec. 8.8: every sample then weighs the same,
 * and a pixel's mean is the filter's weighted mean).
 *
 * Tile order (render/tiles.h) keeps a CPU ray packet's rays next to each
 * other on the image, hence coherent.  (Before packets, 4x4 to 32x32 pixel
 * tiles were no faster than row-major order on PoCL.)
 */
#include "core/portable.h"
#include "query/records.h"
#include "render/camera.h"
#include "render/tiles.h"
#include "render/random.h"

#define FILTER_SIGMA 0.5f
#define FILTER_RADIUS 2.0f

/* The Gaussian filter's integral from -FILTER_RADIUS to x, unnormalised:
 * f(t) = exp(-t^2 / (2 sigma^2)) - exp(-r^2 / (2 sigma^2)), Mitsuba's shape. */
inline float gaussian_integral(float x)
{
    const float scale = FILTER_SIGMA * 1.2533141373155f;  /* sigma sqrt(pi / 2) */
    const float to_erf = 1.0f / (FILTER_SIGMA * 1.4142135623731f);
    float floor = exp(-FILTER_RADIUS * FILTER_RADIUS / (2.0f * FILTER_SIGMA * FILTER_SIGMA));
    return scale * (erf(x * to_erf) + erf(FILTER_RADIUS * to_erf)) - floor * (x + FILTER_RADIUS);
}

/* An offset drawn from the Gaussian filter by inverting its integral at
 * u in [0, 1): bisection, to float precision over [-r, r]. */
inline float gaussian_offset(float u)
{
    float target = u * gaussian_integral(FILTER_RADIUS);
    float lo = -FILTER_RADIUS, hi = FILTER_RADIUS;
    for (int i = 0; i < 24; ++i) {
        float mid = 0.5f * (lo + hi);
        if (gaussian_integral(mid) < target)
            lo = mid;
        else
            hi = mid;
    }
    return 0.5f * (lo + hi);
}

__kernel void primary_rays(const PinholeCamera camera, const uint width, const uint height,
                           const uint first_row, const uint rows, const uint sample,
                           const int jitter, __global Ray* rays)
{
    uint gid;
    uint2 at;
    if (!pixel_in_pass(get_global_id(0), get_global_id(1), width, rows, &gid, &at))
        return;
    uint x = at.x, y = first_row + at.y;
    uint pixel = y * width + x;
    float jx = 0.5f, jy = 0.5f;
    if (jitter == 1) {
        jx = random_unit(pixel, sample, 0);
        jy = random_unit(pixel, sample, 1);
    } else if (jitter == 2) {
        jx += gaussian_offset(random_unit(pixel, sample, 0));
        jy += gaussian_offset(random_unit(pixel, sample, 1));
    }
    float sx = 2.0f * ((float)x + jx) / (float)width - 1.0f;
    float sy = 1.0f - 2.0f * ((float)y + jy) / (float)height;

    __global Ray* ray = rays + gid;
    for (int k = 0; k < 3; ++k) {
        ray->origin[k] = camera.eye[k];
        ray->direction[k] = camera.forward[k] + sx * camera.right[k] + sy * camera.up[k];
    }
    ray->tmin = 0.0f;
    ray->tmax = INFINITY;
}
