/* The film's encoding: each pixel's summed samples -> 8-bit RGB.
 *
 * Kernel
 *   encode_image  over pixel_in_pass's 2D range (render/tiles.h): the RGB of
 *                 the pixel of ray i = round(255 * encode(clamp(accum[i] *
 *                 scale, 0, 1))), scale = 1 / samples per pixel
 *
 *   radiance_image  the same range: each pixel's mean, float32 RGB, as it is
 *
 *   add_to_image  the same range: each pixel's sums added to the float32
 *                 image's (a progressive render's running sums; the host
 *                 divides by the samples each band has taken)
 *
 * Compile-time parameter (-D)
 *   RADIANCE  1: the sums are radiance, encoded with display gamma 2 (sqrt,
 *             which looks as 2.2 does; pow measured far slower on PoCL);
 *             0: they are data (normals, depth), encoded as they are
 */
#include "core/portable.h"
#include "render/tiles.h"

#ifndef RADIANCE
#error "RADIANCE must be defined (-D RADIANCE=1 for radiance, 0 for data)"
#endif

__kernel void encode_image(__global const float4* accum,
                           const uint width,
                           const uint first_row,
                           const uint rows,
                           const float scale,          /* 1 / samples per pixel */
                           __global uchar* image)      /* the whole image */
{
    uint gid;
    uint2 at;
    if (!pixel_in_pass(get_global_id(0), get_global_id(1), width, rows, &gid, &at))
        return;
    /* fmin(fmax(value, 0), 1), which turns a NaN into 0 too, spelled with
     * ?: (PoCL 3.0 calls fmin and fmax out of line: core/spelled.h) */
    float3 value = accum[gid].xyz * scale;
    value = value > 0.0f ? value : (float3)(0.0f);
    value = value < 1.0f ? value : (float3)(1.0f);
#if RADIANCE
    value = sqrt(value);
#endif
    uchar3 rgb = convert_uchar3(value * 255.0f + 0.5f);
    __global uchar* pixel = image + 3 * (size_t)((first_row + at.y) * width + at.x);
    pixel[0] = rgb.x;
    pixel[1] = rgb.y;
    pixel[2] = rgb.z;
}

__kernel void radiance_image(__global const float4* accum,
                             const uint width,
                             const uint first_row,
                             const uint rows,
                             const float scale,        /* 1 / samples per pixel */
                             __global float* image)    /* the whole image, RGB */
{
    uint gid;
    uint2 at;
    if (!pixel_in_pass(get_global_id(0), get_global_id(1), width, rows, &gid, &at))
        return;
    float4 mean = accum[gid] * scale;
    __global float* pixel = image + 3 * (size_t)((first_row + at.y) * width + at.x);
    pixel[0] = mean.x;
    pixel[1] = mean.y;
    pixel[2] = mean.z;
}

__kernel void add_to_image(__global const float4* accum,
                           const uint width,
                           const uint first_row,
                           const uint rows,
                           __global float* image)      /* the whole image's sums, RGB */
{
    uint gid;
    uint2 at;
    if (!pixel_in_pass(get_global_id(0), get_global_id(1), width, rows, &gid, &at))
        return;
    float4 sums = accum[gid];
    __global float* pixel = image + 3 * (size_t)((first_row + at.y) * width + at.x);
    pixel[0] += sums.x;
    pixel[1] += sums.y;
    pixel[2] += sums.z;
}
