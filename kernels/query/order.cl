/* The order a batch of queries runs in (hlbvh_cl/query/order.py): the
 * Morton code of each point's cell in a 2^ORDER_BITS grid over the batch's
 * box, whose sort on the device (parallel/radix_sort.cl) gives the order.  A
 * ray's key has its class (query/rays/ray_class.h) above its origin's code,
 * or above its direction's (rays whose lines nearly meet at a point:
 * order.py's concurrent_rays), so that the rays of a class run together, as
 * packets need.  The cells are computed as order.py's numpy reference
 * computes them, in float32 without contraction, so both give the same keys
 * (but for a direction whose face coordinate rounds across a cell's edge:
 * OpenCL's division may round differently from numpy's).
 */
#include "core/portable.h" /* contraction off, as the numpy reference */

#if ORDER_BITS < 1 || ORDER_BITS > 10
#error "ORDER_BITS must be 1..10"
#endif
#if DIRECTION_BITS < 1 || DIRECTION_BITS > 13
#error "DIRECTION_BITS must be 1..13 (order.py's; 2 * 13 + 5 class bits fill a 32-bit key)"
#endif

/* Each work-item keys ROWS_PER_ITEM (the host's KEY_ROWS) consecutive rows
 * at once, as vectors: the CPU runtimes' own vectorizers, across
 * work-items, leave much of this integer code scalar, while explicit
 * vectors are plain OpenCL C that a GPU compiler splits into scalars
 * again. */
#if ROWS_PER_ITEM != 8
#error "ROWS_PER_ITEM must be 8 (the vector types below)"
#endif
typedef float8 rows_f;
typedef int8 rows_i;
typedef uint8 rows_u;
#define convert_rows_i convert_int8
#define as_rows_u as_uint8

/* The x, y, z columns of rows first .. first + 7 of a float32 (count, 3)
 * array; a row past the last repeats the last (its key is not stored). */
inline void load_rows(__global const float* rows, uint first, uint count, rows_f* x, rows_f* y,
                      rows_f* z)
{
    if (first + ROWS_PER_ITEM <= count) {
        __global const float* p = rows + 3 * (size_t)first;
        float8 a = vload8(0, p), b = vload8(1, p), c = vload8(2, p);
        *x = (float8)(a.s0, a.s3, a.s6, b.s1, b.s4, b.s7, c.s2, c.s5);
        *y = (float8)(a.s1, a.s4, a.s7, b.s2, b.s5, c.s0, c.s3, c.s6);
        *z = (float8)(a.s2, a.s5, b.s0, b.s3, b.s6, c.s1, c.s4, c.s7);
        return;
    }
    float column[3][ROWS_PER_ITEM];
    for (uint j = 0; j < ROWS_PER_ITEM; ++j) {
        size_t row = 3 * (size_t)min(first + j, count - 1u);
        for (int axis = 0; axis < 3; ++axis)
            column[axis][j] = rows[row + axis];
    }
    *x = vload8(0, column[0]);
    *y = vload8(0, column[1]);
    *z = vload8(0, column[2]);
}

/* Stores rows first .. first + 7 of keys (those before `count`) and their
 * ids. */
inline void store_keys(rows_u key, uint first, uint count, __global uint* keys,
                       __global uint* ids)
{
    rows_u id = (rows_u)(first) + (rows_u)(0, 1, 2, 3, 4, 5, 6, 7);
    if (first + ROWS_PER_ITEM <= count) {
        vstore8(key, 0, keys + first);
        vstore8(id, 0, ids + first);
        return;
    }
    uint lanes[ROWS_PER_ITEM];
    vstore8(key, 0, lanes);
    for (uint j = 0; first + j < count; ++j) {
        keys[first + j] = lanes[j];
        ids[first + j] = first + j;
    }
}

/* The cell, 0 .. top, of v >= 0 (truncated, as numpy's astype; clamped
 * before the conversion, which is undefined out of int's range). */
inline rows_u cell_of(rows_f v, int top)
{
    return as_rows_u(convert_rows_i(fmin(v, (float)top)));
}

/* The low 10 bits of v with two zero bits after each (build/morton.cl's). */
inline rows_u spread_cell(rows_u v)
{
    v = (v | (v << 16)) & 0x030000ffu;
    v = (v | (v << 8)) & 0x0300f00fu;
    v = (v | (v << 4)) & 0x030c30c3u;
    return (v | (v << 2)) & 0x09249249u;
}

/* The low 16 bits of v with one zero bit after each. */
inline rows_u spread_cell_2d(rows_u v)
{
    v = (v | (v << 8)) & 0x00ff00ffu;
    v = (v | (v << 4)) & 0x0f0f0f0fu;
    v = (v | (v << 2)) & 0x33333333u;
    return (v | (v << 1)) & 0x55555555u;
}

/* The Morton code of points' cells (lo and scale: per axis, the box's low
 * corner and (2^ORDER_BITS - 1) / extent, 0 on a flat axis). */
inline rows_u cell_key(rows_f x, rows_f y, rows_f z, float3 lo, float3 scale)
{
    const int top = (1 << ORDER_BITS) - 1;
    /* >= 0 by the box */
    return spread_cell(cell_of((x - lo.x) * scale.x, top))
           | spread_cell(cell_of((y - lo.y) * scale.y, top)) << 1
           | spread_cell(cell_of((z - lo.z) * scale.z, top)) << 2;
}

/* The cell, 0 .. 2^DIRECTION_BITS - 1, of face coordinates in [-1, 1]. */
inline rows_u face_cell(rows_f face)
{
    const int top = (1 << DIRECTION_BITS) - 1;
    return cell_of((face + 1.0f) * (0.5f * (float)top), top);
}

/* Rays' classes (ray_class.h: kz * 8, plus 1, 2, 4 for a sign bit set in
 * x, y, z; -0 counts as negative, as its inverse is -inf) and, where
 * *face_key is asked for, the 2-D Morton code of each direction's cell on
 * its cube face: the face coordinates are its components after kz
 * (cyclically) over its component along kz, the largest in magnitude, in
 * [-1, 1]. */
inline rows_u ray_class(rows_f x, rows_f y, rows_f z, rows_u* face_key)
{
    rows_f ax = fabs(x), ay = fabs(y), az = fabs(z);
    /* ray_class.h's shear_axis, per lane (ties to the lower axis): -1
     * where kz is 0, resp. 1, else 0 */
    rows_i k0 = ax >= ay & ax >= az;
    rows_i k1 = ~k0 & (ay >= az);
    rows_u kz = as_rows_u(k1 & 1) | as_rows_u(~k0 & ~k1 & 2);
    if (face_key) {
        rows_f major = select(select(az, ay, k1), ax, k0);
        rows_f u = select(select(x, z, k1), y, k0);
        rows_f w = select(select(y, x, k1), z, k0);
        *face_key = spread_cell_2d(face_cell(u / major))
                    | spread_cell_2d(face_cell(w / major)) << 1;
    }
    return kz * 8u + (as_rows_u(x) >> 31) + ((as_rows_u(y) >> 31) << 1)
           + ((as_rows_u(z) >> 31) << 2);
}

/* points: float32 (count, 3) rows; lo and scale as cell_key's, from the
 * host.  keys[i] <- the Morton code of point i's cell, ids[i] <- i, for
 * ROWS_PER_ITEM rows per work-item. */
__kernel void point_keys(__global const float* points, const uint count, const float lo_x,
                         const float lo_y, const float lo_z, const float scale_x,
                         const float scale_y, const float scale_z, __global uint* keys,
                         __global uint* ids)
{
    uint first = ROWS_PER_ITEM * get_global_id(0);
    if (first >= count)
        return;
    rows_f x, y, z;
    load_rows(points, first, count, &x, &y, &z);
    store_keys(cell_key(x, y, z, (float3)(lo_x, lo_y, lo_z), (float3)(scale_x, scale_y, scale_z)),
               first, count, keys, ids);
}

/* As point_keys for rays' origins, with the class of each ray's direction
 * (directions: float32 (count, 3) rows) above the cell's code.  With
 * by_direction, the direction's cell on its face takes the place of the
 * origin's. */
__kernel void ray_keys(__global const float* origins, __global const float* directions,
                       const uint count, const float lo_x, const float lo_y, const float lo_z,
                       const float scale_x, const float scale_y, const float scale_z,
                       const uint by_direction, __global uint* keys, __global uint* ids)
{
    uint first = ROWS_PER_ITEM * get_global_id(0);
    if (first >= count)
        return;
    rows_f x, y, z;
    load_rows(directions, first, count, &x, &y, &z);
    rows_u key, cls;
    if (by_direction) {
        cls = ray_class(x, y, z, &key) << (2 * DIRECTION_BITS);
    } else {
        cls = ray_class(x, y, z, 0) << (3 * ORDER_BITS);
        load_rows(origins, first, count, &x, &y, &z);
        key = cell_key(x, y, z, (float3)(lo_x, lo_y, lo_z), (float3)(scale_x, scale_y, scale_z));
    }
    store_keys(key | cls, first, count, keys, ids);
}
