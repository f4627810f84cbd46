/* Stage 2: Morton codes of the triangle centroids (Karras 2012, sec. 4).
 *
 * MORTON_BITS = 30 (10 bits per axis, uint keys) or 63 (21 bits per axis,
 * ulong keys).  63 bits avoid the long runs of equal codes that scenes of
 * uneven scale give with 30 bits.  Equal codes are left equal: the radix sort
 * is stable over primitive indices and emission breaks ties on the index.
 */
#include "hlbvh.h"

#if MORTON_BITS == 30
#define AXIS_CELLS 1024.0f

/* Spread the low 10 bits of v so two zero bits separate each. */
inline uint spread_bits(uint v)
{
    v &= 0x3ffu;
    v = (v | (v << 16)) & 0x030000ffu;
    v = (v | (v << 8)) & 0x0300f00fu;
    v = (v | (v << 4)) & 0x030c30c3u;
    v = (v | (v << 2)) & 0x09249249u;
    return v;
}
#elif MORTON_BITS == 63
#define AXIS_CELLS 2097152.0f

/* Spread the low 21 bits of v so two zero bits separate each. */
inline ulong spread_bits(uint x)
{
    ulong v = x & 0x1fffffu;
    v = (v | (v << 32)) & 0x1f00000000ffffUL;
    v = (v | (v << 16)) & 0x1f0000ff0000ffUL;
    v = (v | (v << 8)) & 0x100f00f00f00f00fUL;
    v = (v | (v << 4)) & 0x10c30c30c30c30c3UL;
    v = (v | (v << 2)) & 0x1249249249249249UL;
    return v;
}
#endif

inline uint quantize(float x, float lo, float scale)
{
    float cell = (x - lo) * scale;
    return (uint)clamp(cell, 0.0f, AXIS_CELLS - 1.0f);
}

__kernel void morton_codes(__global const float *vertices, __global const int *faces,
                           int triangle_count, __global const Aabb *bounds,
                           __global morton_t *keys, __global uint *primitive_ids)
{
    int face = get_global_id(0);
    if (face >= triangle_count)
        return;
    Aabb centroid_box = bounds[1];
    float3 a, b, c;
    load_triangle(vertices, faces, face, &a, &b, &c);
    float3 centroid = aabb_center(aabb_of_points(a, b, c));
    float p[3] = {centroid.x, centroid.y, centroid.z};
    morton_t code = 0;
    for (int k = 0; k < 3; ++k) {
        float extent = centroid_box.hi[k] - centroid_box.lo[k];
        /* A flat axis (all centroids equal) quantises to cell 0. */
        float scale = extent > 0.0f ? AXIS_CELLS / extent : 0.0f;
        code |= spread_bits(quantize(p[k], centroid_box.lo[k], scale)) << (2 - k);
    }
    keys[face] = code;
    primitive_ids[face] = (uint)face;
}
