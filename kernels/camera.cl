/* Primary ray generation: one pinhole-camera ray per pixel and sample.
 *
 * Kernel
 *   primary_rays  rays[i] for pixel first_pixel + i of a width x height image,
 *                 pixels in row-major order from the top-left one
 *
 * Pixel (x, y), y counting down from the top row, is the square
 * [x, x + 1] x [y, y + 1]; a sample at (x + jx, y + jy) maps to the image
 * plane as sx = 2 (x + jx) / width - 1, sy = 1 - 2 (y + jy) / height
 * (scenefile.py's convention, which takes the pixel centre, jx = jy = 0.5).
 * With `jitter` set, (jx, jy) = (random_unit(pixel, sample, 0),
 * random_unit(pixel, sample, 1)) (hlbvh.h), so a render with several samples
 * per pixel is the same every time.
 *
 * Row-major order keeps a work-group's rays next to each other on the image,
 * hence coherent; measured on PoCL, 4x4 to 32x32 pixel tiles were no faster.
 */
#include "hlbvh.h"

__kernel void primary_rays(const PinholeCamera camera,
                           const uint width,
                           const uint height,
                           const uint first_pixel,
                           const uint ray_count,
                           const uint sample,
                           const int jitter,
                           __global Ray* rays)
{
    uint gid = get_global_id(0);
    if (gid >= ray_count)
        return;
    uint pixel = first_pixel + gid;
    uint x = pixel % width;
    uint y = pixel / width;
    float jx = jitter ? random_unit(pixel, sample, 0) : 0.5f;
    float jy = jitter ? random_unit(pixel, sample, 1) : 0.5f;
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
