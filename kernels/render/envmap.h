/* Mitsuba 3's envmap emitter on the device: radiance by direction from an
 * equirectangular image, and importance sampling of directions by a
 * piecewise-constant density over its bilinear cells.  The mapping, the
 * cells and the density are documented by hlbvh_cl/render/envmap.py,
 * which builds the CDFs: the marginal over the H - 1 bands of latitude,
 * then each band's conditional over its W cells.  The map's size and
 * rotation are in PathParams (render/integrators/path.h). */
#ifndef RENDER_ENVMAP_H
#define RENDER_ENVMAP_H

#include "render/integrators/path.h"
#include "render/distribution.h"
#include "render/angles.h"

/* A world direction in the map's frame: the rotation's transpose (its inverse). */
inline float3 envmap_local(const PathParams* p, float3 d)
{
    const float* m = p->envmap_to_world;
    return (float3)(m[0] * d.x + m[3] * d.y + m[6] * d.z, m[1] * d.x + m[4] * d.y + m[7] * d.z,
                    m[2] * d.x + m[5] * d.y + m[8] * d.z);
}

inline float3 envmap_world(const PathParams* p, float3 d)
{
    const float* m = p->envmap_to_world;
    return (float3)(m[0] * d.x + m[1] * d.y + m[2] * d.z, m[3] * d.x + m[4] * d.y + m[5] * d.z,
                    m[6] * d.x + m[7] * d.y + m[8] * d.z);
}

/* Mitsuba's lat-long coordinates of a unit direction in the map's frame:
 * u = atan2(x, -z) / 2 pi in [0, 1], v = acos(y) / pi (+y at the top row). */
inline float2 envmap_uv(float3 d)
{
    float u = atan2(d.x, -d.z) * (0.5f * M_1_PI_F);
    float y = d.y < -1.0f ? -1.0f : (d.y > 1.0f ? 1.0f : d.y);
    return (float2)(u - floor(u), acos(y) * M_1_PI_F);
}

/* The cell (band j, sector i) holding uv, and x = u W - 0.5 (texel-centred
 * columns: cell i spans the columns i and i + 1, wrapping) and y = v (H - 1)
 * (row j at v = j / (H - 1)), for the bilinear weights. */
inline void envmap_cell(uint width, uint height, float2 uv, uint* i, uint* j, float* x, float* y)
{
    *x = uv.x * (float)width - 0.5f;
    *y = uv.y * (float)(height - 1);
    float column = floor(*x), row = floor(*y);
    *i = column < 0.0f ? width - 1 : (column < (float)width ? (uint)column : width - 1);
    *j = row < (float)(height - 2) ? (uint)row : height - 2;
}

inline float3 envmap_texel(__global const float* image, uint width, uint row, uint column)
{
    return LOAD_XYZ(image + 3 * ((size_t)row * width + column));
}

/* The radiance arriving along -world (world: the unit direction a ray
 * escapes in): the image's bilinear interpolation, as Mitsuba's texture. */
inline float3 envmap_radiance(const PathParams* p, __global const float* image, float3 world)
{
    uint width = p->envmap_width, height = p->envmap_height, i, j;
    float x, y;
    envmap_cell(width, height, envmap_uv(envmap_local(p, world)), &i, &j, &x, &y);
    float tx = x - floor(x), ty = y - (float)j;
    ty = ty > 1.0f ? 1.0f : ty;
    uint next = i + 1 == width ? 0 : i + 1;
    float3 top = mix(envmap_texel(image, width, j, i), envmap_texel(image, width, j, next), tx);
    float3 bottom = mix(envmap_texel(image, width, j + 1, i),
                        envmap_texel(image, width, j + 1, next), tx);
    return mix(top, bottom, ty);
}

/* Half of cos(theta_j) - cos(theta_j+1), band j's share of the sphere in
 * cos theta, as sin(mid) sin(step / 2): no cancellation near the poles. */
inline float envmap_band(uint height, uint j)
{
    float step = M_PI_F / (float)(height - 1);
    return sin(((float)j + 0.5f) * step) * sin(0.5f * step);
}

/* The solid-angle density of cell (j, i): its probability over its solid
 * angle, 2 band * 2 pi / W. */
inline float envmap_cell_pdf(const PathParams* p, __global const float* cdf, uint i, uint j)
{
    uint width = p->envmap_width, bands = p->envmap_height - 1;
    float chance = picked_weight(cdf, j) * picked_weight(cdf + bands + (size_t)j * width, i);
    return chance * (float)width / (4.0f * M_PI_F * envmap_band(p->envmap_height, j));
}

/* The density envmap_sample gives the unit world direction. */
inline float envmap_pdf(const PathParams* p, __global const float* cdf, float3 world)
{
    uint i, j;
    float x, y;
    envmap_cell(p->envmap_width, p->envmap_height, envmap_uv(envmap_local(p, world)), &i, &j,
                &x, &y);
    return envmap_cell_pdf(p, cdf, i, j);
}

/* A unit world direction: a band by the marginal CDF (u_band), a cell of
 * it by its conditional CDF (u_cell, whose remainder places the longitude),
 * then uniform in cos theta across the band (u_theta), counted from the
 * nearer pole for precision; *pdf its solid-angle density. */
inline float3 envmap_sample(const PathParams* p, __global const float* cdf, float u_band,
                            float u_cell, float u_theta, float* pdf)
{
    uint width = p->envmap_width, height = p->envmap_height;
    uint j = pick(cdf, height - 1, u_band);
    __global const float* row = cdf + (height - 1) + (size_t)j * width;
    uint i = pick(row, width, u_cell);
    float below = i > 0 ? row[i - 1] : 0.0f;
    float t = (u_cell - below) / (row[i] - below);
    t = t < 0.0f ? 0.0f : (t < 0x1.fffffep-1f ? t : 0x1.fffffep-1f);
    float step = M_PI_F / (float)(height - 1), band = envmap_band(height, j);
    /* s = sin^2(theta / 2) = (1 - cos theta) / 2 grows by `band` across the
     * band; in the south, s is cos^2(theta / 2) = (1 + cos theta) / 2, which
     * shrinks by it, so that s stays small near either pole */
    bool north = 2 * j + 1 < height - 1;
    float start = sin(0.5f * step * (float)(north ? j : height - 1 - j));
    float s = north ? start * start + u_theta * band : start * start - u_theta * band;
    s = s < 0.0f ? 0.0f : (s < 1.0f ? s : 1.0f);
    float cos_theta = north ? 1.0f - 2.0f * s : 2.0f * s - 1.0f;
    float sin_theta = 2.0f * sqrt(s * (1.0f - s));
    float cos_phi, sin_phi = sincos_turn(((float)i + 0.5f + t) / (float)width, &cos_phi);
    *pdf = envmap_cell_pdf(p, cdf, i, j);
    return envmap_world(p, (float3)(sin_phi * sin_theta, cos_theta, -cos_phi * sin_theta));
}

#endif /* RENDER_ENVMAP_H */
