/* The order a batch of queries runs in (hlbvh_cl/order.py): the Morton code
 * of each point's cell in a 2^ORDER_BITS grid over the batch's box, whose
 * sort on the device (radix_sort.cl) gives the order.  A ray's key has its
 * class (ray_class.h) above its origin's code, or above its direction's
 * (rays whose lines nearly meet at a point: order.py's concurrent_rays), so
 * that the rays of a class run together, as packets need.  The cells are
 * computed as order.py's numpy reference computes them, in float32 without
 * contraction, so both give the same keys (but for a direction whose face
 * coordinate rounds across a cell's edge: OpenCL's division may round
 * differently from numpy's).
 */
#include "hlbvh.h"
#include "ray_class.h"

#pragma OPENCL FP_CONTRACT OFF

#if ORDER_BITS < 1 || ORDER_BITS > 10
#error "ORDER_BITS must be 1..10"
#endif
#if DIRECTION_BITS < 1 || DIRECTION_BITS > 13
#error "DIRECTION_BITS must be 1..13 (order.py's; 2 * 13 + 5 class bits fill a 32-bit key)"
#endif

/* The low 10 bits of v with two zero bits after each (morton.cl's). */
inline uint spread_cell(uint v)
{
    v = (v | (v << 16)) & 0x030000ffu;
    v = (v | (v << 8)) & 0x0300f00fu;
    v = (v | (v << 4)) & 0x030c30c3u;
    return (v | (v << 2)) & 0x09249249u;
}

/* The Morton code of a point's cell (lo and scale: per axis, the box's
 * low corner and (2^ORDER_BITS - 1) / extent, 0 on a flat axis). */
inline uint cell_key(__global const float* point, const float* lo, const float* scale)
{
    const uint top = (1u << ORDER_BITS) - 1u;
    uint key = 0;
    for (int axis = 0; axis < 3; ++axis) {
        /* >= 0 by the box; truncation toward zero, as numpy's astype */
        uint cell = convert_uint((point[axis] - lo[axis]) * scale[axis]);
        key |= spread_cell(cell < top ? cell : top) << axis;
    }
    return key;
}

/* The low 16 bits of v with one zero bit after each. */
inline uint spread_cell_2d(uint v)
{
    v = (v | (v << 8)) & 0x00ff00ffu;
    v = (v | (v << 4)) & 0x0f0f0f0fu;
    v = (v | (v << 2)) & 0x33333333u;
    return (v | (v << 1)) & 0x55555555u;
}

/* The cell, 0 .. 2^DIRECTION_BITS - 1, of a face coordinate in [-1, 1]. */
inline uint face_cell(float face)
{
    const uint top = (1u << DIRECTION_BITS) - 1u;
    uint cell = convert_uint((face + 1.0f) * (0.5f * (float)top));
    return cell < top ? cell : top;
}

/* The 2-D Morton code of a direction's cell on its cube face: the face
 * coordinates are its components after kz (cyclically) over its component
 * along kz, the largest in magnitude (`major`), in [-1, 1]. */
inline uint direction_key(float dx, float dy, float dz, int kz, float major)
{
    float u = kz == 0 ? dy : (kz == 1 ? dz : dx);
    float w = kz == 0 ? dz : (kz == 1 ? dx : dy);
    return spread_cell_2d(face_cell(u / major)) | spread_cell_2d(face_cell(w / major)) << 1;
}

/* points: float32 (count, 3) rows; lo and scale as cell_key's, from the
 * host.  keys[i] <- the Morton code of point i's cell, ids[i] <- i. */
__kernel void point_keys(__global const float* points, const uint count, const float lo_x,
                         const float lo_y, const float lo_z, const float scale_x,
                         const float scale_y, const float scale_z, __global uint* keys,
                         __global uint* ids)
{
    uint i = get_global_id(0);
    if (i >= count)
        return;
    const float lo[3] = {lo_x, lo_y, lo_z}, scale[3] = {scale_x, scale_y, scale_z};
    keys[i] = cell_key(points + 3 * (size_t)i, lo, scale);
    ids[i] = i;
}

/* As point_keys for rays' origins, with the class of each ray's direction
 * (directions: float32 (count, 3) rows) above the cell's code: kz * 8, plus
 * 1, 2, 4 for a sign bit set in x, y, z (-0 counts as negative, as its
 * inverse is -inf).  With by_direction, the direction's cell on its face
 * (direction_key) takes the place of the origin's. */
__kernel void ray_keys(__global const float* origins, __global const float* directions,
                       const uint count, const float lo_x, const float lo_y, const float lo_z,
                       const float scale_x, const float scale_y, const float scale_z,
                       const uint by_direction, __global uint* keys, __global uint* ids)
{
    uint i = get_global_id(0);
    if (i >= count)
        return;
    const float lo[3] = {lo_x, lo_y, lo_z}, scale[3] = {scale_x, scale_y, scale_z};
    __global const float* d = directions + 3 * (size_t)i;
    uint bits[3] = {as_uint(d[0]), as_uint(d[1]), as_uint(d[2])};
    float ax = as_float(bits[0] & 0x7fffffffu), ay = as_float(bits[1] & 0x7fffffffu),
          az = as_float(bits[2] & 0x7fffffffu);
    int kz = SHEAR_AXIS(ax, ay, az);
    uint ray_class = (uint)kz * 8u + (bits[0] >> 31) + ((bits[1] >> 31) << 1)
                     + ((bits[2] >> 31) << 2);
    if (by_direction) {
        float major = kz == 0 ? ax : (kz == 1 ? ay : az);
        keys[i] = direction_key(as_float(bits[0]), as_float(bits[1]), as_float(bits[2]), kz, major)
                  | ray_class << (2 * DIRECTION_BITS);
    } else {
        keys[i] = cell_key(origins + 3 * (size_t)i, lo, scale) | ray_class << (3 * ORDER_BITS);
    }
    ids[i] = i;
}
