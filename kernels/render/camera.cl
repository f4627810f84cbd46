/* Primary ray generation: one pinhole-camera ray per pixel and sample.
 *
 * Kernels
 *   primary_rays  one ray per pixel of the pass of `rows` rows from row
 *                 first_row of a width x height image (pixels row-major from
 *                 the top-left one), in tile order: over the 2D range of
 *                 pixel_in_pass (render/tiles.h)
 *   camera_rays   one ray through each pixel's centre, row-major, as
 *                 origins and directions arrays (Camera.rays on the device,
 *                 which computes them as camera.py does in numpy)
 *
 * Pixel (x, y), y counting down from the top row, is the square
 * [x, x + 1] x [y, y + 1]; a sample at (x + jx, y + jy) maps to the image
 * plane as sx = 2 (x + jx) / width - 1, sy = 1 - 2 (y + jy) / height
 * (hlbvh_cl/io/scenefile.py's convention, which takes the pixel centre,
 * jx = jy = 0.5).  With `jitter` 1, (jx, jy) = (random_unit(pixel, sample,
 * 0), random_unit(pixel, sample, 1)) (render/camera.h's pixel_offset), so a
 * render with several samples per pixel is the same every time: a box
 * filter's samples, and the path integrator's under Mitsuba's Gaussian
 * filter, which film.cl then splats onto the pixels around, as Mitsuba does.
 * With 2 (the previews' Gaussian filter: standard deviation 0.5 pixel, cut
 * at 2) each is 0.5 plus an offset drawn from that filter (filter
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

#ifndef FILTER_INTERVALS
#error "FILTER_INTERVALS must be defined: the intervals of the filter's table (camera.py)"
#endif

/* An offset drawn from Mitsuba's Gaussian filter by its inverse CDF:
 * `table` holds the offsets at CDF values i / FILTER_INTERVALS (camera.py's
 * gaussian_filter_table, in float64), and u falls between two of them.
 * (Bisecting the CDF in the kernel, 48 erf calls an offset, was the render's
 * slowest kernel on PoCL.) */
inline float gaussian_offset(__global const float* table, float u)
{
    float at = u * (float)FILTER_INTERVALS;
    uint i = min((uint)at, (uint)FILTER_INTERVALS - 1u);
    return mix(table[i], table[i + 1], at - (float)i);
}

NARROW_KERNEL
void primary_rays(const PinholeCamera camera, const uint width, const uint height,
                  const uint first_row, const uint rows, const uint sample,
                  const int jitter,
                  const float tmin,   /* the clip planes' distances along */
                  const float tmax,   /* camera.forward, a unit vector */
                  __global const float* table,  /* the Gaussian filter's */
                  __global Ray* rays)
{
    uint gid;
    uint2 at;
    if (!pixel_in_pass(get_global_id(0), get_global_id(1), width, rows, &gid, &at))
        return;
    uint x = at.x, y = first_row + at.y;
    uint pixel = y * width + x;
    float2 offset = pixel_offset(pixel, sample, jitter);
    float jx = offset.x, jy = offset.y;
    if (jitter == 2) {
        jx += gaussian_offset(table, random_unit(pixel, sample, 0));
        jy += gaussian_offset(table, random_unit(pixel, sample, 1));
    }
    float sx = 2.0f * ((float)x + jx) / (float)width - 1.0f;
    float sy = 1.0f - 2.0f * ((float)y + jy) / (float)height;

    __global Ray* ray = rays + gid;
    for (int k = 0; k < 3; ++k) {
        ray->origin[k] = camera.eye[k];
        ray->direction[k] = camera.forward[k] + sx * camera.right[k] + sy * camera.up[k];
    }
    ray->tmin = tmin;
    ray->tmax = tmax;
}

NARROW_KERNEL
void camera_rays(const PinholeCamera camera, const uint width, const uint height,
                 __global float* origins, __global float* directions)
{
    size_t pixel = get_global_id(0);
    if (pixel >= (size_t)width * height)
        return;
    uint x = (uint)(pixel % width), y = (uint)(pixel / width);
    float sx = 2.0f * ((float)x + 0.5f) / (float)width - 1.0f;
    float sy = 1.0f - 2.0f * ((float)y + 0.5f) / (float)height;
    for (int k = 0; k < 3; ++k) {
        origins[3 * pixel + k] = camera.eye[k];
        directions[3 * pixel + k] = camera.forward[k] + sx * camera.right[k] + sy * camera.up[k];
    }
}
