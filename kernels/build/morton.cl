/* Stage 2: Morton codes of the triangle centroids (Karras 2012, sec. 4).
 *
 * MORTON_BITS = 30 (10 bits per axis, uint keys) or 63 (21 bits per axis,
 * ulong keys).  63 bits avoid the long runs of equal codes that scenes of
 * uneven scale give with 30 bits.  Equal codes are left equal: the radix sort
 * is stable over primitive indices and emission breaks ties on the index.
 */
#include "core/portable.h"
#include "core/aabb.h"
#include "build/config.h"

/* The kernel works on the three axes at once in vector lanes (x, y, z, and
 * an unused w): PoCL runs it as written, so this is fewer instructions
 * than a loop over the axes. */
#if MORTON_BITS == 30
#define AXIS_CELLS 1024.0f
typedef uint4 spread_t;

/* Spread the low 10 bits of each lane so two zero bits separate each. */
inline uint4 spread_bits(uint4 v)
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
typedef ulong4 spread_t;

/* Spread the low 21 bits of each lane so two zero bits separate each. */
inline ulong4 spread_bits(uint4 x)
{
    ulong4 v = convert_ulong4(x & 0x1fffffu);
    v = (v | (v << 32)) & 0x1f00000000ffffUL;
    v = (v | (v << 16)) & 0x1f0000ff0000ffUL;
    v = (v | (v << 8)) & 0x100f00f00f00f00fUL;
    v = (v | (v << 4)) & 0x10c30c30c30c30c3UL;
    v = (v | (v << 2)) & 0x1249249249249249UL;
    return v;
}
#endif

/* centroids: the triangles' box centres, stored by the bounds stage, with
 * inverse_extent: 1 / the centroid box's extent per axis, correctly rounded
 * (0 on a flat axis), so that the scale AXIS_CELLS * inverse_extent is
 * AXIS_CELLS / extent correctly rounded, as on a host (bounds.cl). */
NARROW_KERNEL
void morton_codes(__global const float4 *centroids, int triangle_count,
                  __global const Aabb *bounds, __global const float4 *inverse_extent,
                  __global morton_t *keys, __global uint *primitive_ids)
{
    int face = get_global_id(0);
    if (face >= triangle_count)
        return;
    Aabb box = bounds[1];
    float4 lo = (float4)(box.lo[0], box.lo[1], box.lo[2], 0.0f);
    /* A flat axis (all centroids equal) quantises to cell 0.  select and
     * clamp spelled with ?: (PoCL calls them out of line: see GROW_LO in
     * core/spelled.h); a NaN still goes to 0, as clamp's fmax sends it. */
    float4 scale = AXIS_CELLS * inverse_extent[0];
    float4 cell = (centroids[face] - lo) * scale;
    cell = cell > 0.0f ? cell : (float4)(0.0f);
    cell = cell < AXIS_CELLS - 1.0f ? cell : (float4)(AXIS_CELLS - 1.0f);
    spread_t s = spread_bits(convert_uint4(cell));
    keys[face] = (morton_t)((s.x << 2) | (s.y << 1) | s.z);
    primitive_ids[face] = (uint)face;
}
