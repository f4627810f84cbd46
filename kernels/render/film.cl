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
 * Splatting (a progressive render under a filter wider than a pixel: the
 * path integrator's Gaussian).  As Mitsuba 3's film does (ImageBlock::put),
 * each sample, taken uniformly in its pixel, adds its value times the
 * filter's weight f(dx) f(dy) to every pixel whose centre is within the
 * filter's radius, and the weight to that pixel's sum of weights; the image
 * is the ratio.  A sample then serves up to (2 REACH + 1)^2 pixels, where
 * filter importance sampling (camera.cl) gives it to one.  Gathered rather
 * than scattered, so that no two work-items add to one pixel and a render
 * is the same on every run (no float atomics):
 *   store_round   over pixel_in_pass's range: a band's values of this round
 *                 into the whole image's round buffer, row-major, and (group
 *                 0) the filter's weights for the columns and rows around
 *                 each sample, from where it fell in its pixel (camera.h)
 *   splat_round   over (width, rows reached), once the round's bands are
 *                 stored: each pixel's weighted sums of the samples of the
 *                 (2 REACH + 1)^2 pixels around, added to its sums.  A round
 *                 cut short by a time budget stored only its first rows:
 *                 the rows below hold no sample of it
 *
 * Compile-time parameters (-D)
 *   RADIANCE  1: the sums are radiance, encoded with display gamma 2 (sqrt,
 *             which looks as 2.2 does; pow measured far slower on PoCL);
 *             0: they are data (normals, depth), encoded as they are
 *   GROUPS, REACH, WEIGHT_INTERVALS  (the splatting kernels) float4 values
 *             per pixel, pixels a sample reaches on each side, intervals of
 *             the filter's weight table (camera.py)
 */
#include "core/portable.h"
#include "render/camera.h"
#include "render/tiles.h"

#ifndef RADIANCE
#error "RADIANCE must be defined (-D RADIANCE=1 for radiance, 0 for data)"
#endif

NARROW_KERNEL
void encode_image(__global const float4* accum,
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

NARROW_KERNEL
void radiance_image(__global const float4* accum,
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

NARROW_KERNEL
void add_to_image(__global const float4* accum,
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

#ifdef GROUPS

/* A sample's filter weights for the pixel columns (or rows) k - REACH from
 * its own, k = 0 .. TAPS - 1, of which it is the only reader's source. */
#define TAPS (2 * REACH + 1)

/* The filter's weight at offset t from a pixel centre (0 beyond its
 * radius), interpolated in `table`: f at |t| = i * radius / WEIGHT_INTERVALS
 * for i = 0 .. WEIGHT_INTERVALS (camera.py's gaussian_weight_table). */
inline float filter_weight(__global const float* table, float radius, float t)
{
    float at = (t < 0.0f ? -t : t) * ((float)WEIGHT_INTERVALS / radius);  /* fabs: spelled.h */
    if (!(at < (float)WEIGHT_INTERVALS))
        return 0.0f;
    uint i = (uint)at;
    /* mix as OpenCL defines it, spelled (PoCL calls mix out of line) */
    return table[i] + (table[i + 1] - table[i]) * (at - (float)i);
}

NARROW_KERNEL
void store_round(__global const float4* values,  /* the band's, in tile order */
                 const uint value_groups,        /* float4 per pixel in values */
                 const uint to_group,            /* where they go among GROUPS */
                 const uint width,
                 const uint first_row,
                 const uint rows,
                 const uint sample,              /* the round's random stream */
                 const int jitter,               /* the camera's (0 or 1) */
                 __global const float* table,    /* the filter's weights */
                 const float radius,             /* the filter's, in pixels */
                 __global float4* round,         /* GROUPS float4 per image pixel */
                 __global float* taps)           /* 2 TAPS per image pixel */
{
    uint gid;
    uint2 at;
    if (!pixel_in_pass(get_global_id(0), get_global_id(1), width, rows, &gid, &at))
        return;
    uint pixel = (first_row + at.y) * width + at.x;  /* as camera.cl numbers it */
    for (uint g = 0; g < value_groups; ++g)
        round[(size_t)pixel * GROUPS + to_group + g] = values[(size_t)gid * value_groups + g];
    if (to_group != 0)
        return;
    /* The weights this sample gives the pixel columns and rows around its
     * own, once here rather than at each of the pixels that read them: the
     * centre of column x + k - REACH is k - REACH + 0.5 - offset from it. */
    float2 offset = pixel_offset(pixel, sample, jitter);
    __global float* out = taps + (size_t)pixel * (2 * TAPS);
    for (int k = 0; k < TAPS; ++k) {
        float centre = (float)(k - REACH) + 0.5f;
        out[k] = filter_weight(table, radius, centre - offset.x);
        out[TAPS + k] = filter_weight(table, radius, centre - offset.y);
    }
}

NARROW_KERNEL
void splat_round(__global const float4* round,
                 __global const float* taps,
                 const uint width,
                 const uint height,
                 const uint stored,             /* rows [0, stored) hold samples */
                 __global float4* sums,         /* GROUPS float4 per pixel */
                 __global float* weights)       /* per pixel */
{
    int x = (int)get_global_id(0), y = (int)get_global_id(1);
    if (x >= (int)width || y >= (int)height || y >= (int)stored + REACH)
        return;
    float4 gathered[GROUPS];
    for (int g = 0; g < GROUPS; ++g)
        gathered[g] = (float4)(0.0f);
    float total = 0.0f;
    /* the samples of the image's pixels within REACH, rows then columns
     * (the sums' order); bounds taken once rather than tested per tap */
    int dy_first = y < REACH ? -y : -REACH;
    int dy_last = (int)stored - 1 - y < REACH ? (int)stored - 1 - y : REACH;
    int dx_first = x < REACH ? -x : -REACH;
    int dx_last = (int)width - 1 - x < REACH ? (int)width - 1 - x : REACH;
    for (int dy = dy_first; dy <= dy_last; ++dy) {
        size_t row = (size_t)(y + dy) * width;
        for (int dx = dx_first; dx <= dx_last; ++dx) {
            /* this pixel is column -dx and row -dy from the sample's */
            size_t source = row + (size_t)(x + dx);
            __global const float* tap = taps + source * (2 * TAPS);
            float w = tap[REACH - dx] * tap[TAPS + REACH - dy];
            for (int g = 0; g < GROUPS; ++g)
                gathered[g] += w * round[source * GROUPS + g];
            total += w;
        }
    }
    size_t pixel = (size_t)y * width + (size_t)x;
    for (int g = 0; g < GROUPS; ++g)
        sums[pixel * GROUPS + g] += gathered[g];
    weights[pixel] += total;
}

#endif /* GROUPS */
