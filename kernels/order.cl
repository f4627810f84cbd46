/* The order a batch of queries runs in (hlbvh_cl/order.py): the Morton code
 * of each point's cell in a 2^ORDER_BITS grid over the batch's box, whose
 * sort on the device (radix_sort.cl) gives the order.  The cells are
 * computed as order.py's numpy reference computes them, in float32 without
 * contraction, so both give the same keys.
 */
#include "hlbvh.h"

#pragma OPENCL FP_CONTRACT OFF

#if ORDER_BITS < 1 || ORDER_BITS > 10
#error "ORDER_BITS must be 1..10"
#endif

/* The low 10 bits of v with two zero bits after each (morton.cl's). */
inline uint spread_cell(uint v)
{
    v = (v | (v << 16)) & 0x030000ffu;
    v = (v | (v << 8)) & 0x0300f00fu;
    v = (v | (v << 4)) & 0x030c30c3u;
    return (v | (v << 2)) & 0x09249249u;
}

/* points: float32 (count, 3) rows; lo and scale: per axis, the box's low
 * corner and (2^ORDER_BITS - 1) / extent (0 on a flat axis), from the host.
 * keys[i] <- the Morton code of point i's cell, ids[i] <- i. */
__kernel void point_keys(__global const float* points, const uint count, const float lo_x,
                         const float lo_y, const float lo_z, const float scale_x,
                         const float scale_y, const float scale_z, __global uint* keys,
                         __global uint* ids)
{
    uint i = get_global_id(0);
    if (i >= count)
        return;
    const uint top = (1u << ORDER_BITS) - 1u;
    const float lo[3] = {lo_x, lo_y, lo_z}, scale[3] = {scale_x, scale_y, scale_z};
    uint key = 0;
    for (int axis = 0; axis < 3; ++axis) {
        /* >= 0 by the box; truncation toward zero, as numpy's astype */
        uint cell = convert_uint((points[3 * (size_t)i + axis] - lo[axis]) * scale[axis]);
        key |= spread_cell(cell < top ? cell : top) << axis;
    }
    keys[i] = key;
    ids[i] = i;
}
