/* The rays of one work-item, of any classes (query/rays/ray_class.h), one
 * vector lane each: what the root phase (query/rays/trace.h) tests the root's
 * leaves with, in SIMD across the rays, where rays of a packet still agree
 * on their path, as Embree's hybrid traversal does before it goes on one ray
 * at a time (Benthin, Wald, Woop, Ernst & Mark 2012, "Combining Single and
 * Packet-Ray Tracing for Arbitrary Ray Distributions on the Intel MIC
 * Architecture").  The watertight test's permutation and the
 * slab test's near planes are picked per lane, so each lane computes what
 * prepare_ray and the single-ray tests compute for its ray, the same bits:
 * its hits are the one-by-one walk's.  This header is the root phase's
 * vocabulary (suffix _mixed) for the generic triangle test; its other
 * types are the packet's (packet.h).
 * Only the root: the lanes walking together below it, through every node
 * that at least T of the 16 meet, each handing the other children to its
 * own walk (Embree's hybrid switch), gave the same hits but no speed on
 * CPU runtimes (diffuse bounces within noise, incoherent rays slower, for
 * T from 3 to 16; figures in the commit that says so). */
#ifndef MIXED_H
#define MIXED_H

#include "query/rays/packet.h"

/* RayData of PACKET_SIZE rays, one lane each, as prepare_ray makes it. */
typedef struct {
    float_packet ox, oy, oz;
#ifdef RAY_DIRECTION
    float_packet dx, dy, dz;
#endif
    float_packet inv_x, inv_y, inv_z;
    float_packet tmin, tmax;
    float_packet sx, sy, sz;
    float_packet okx, oky, okz;
    int_packet kz0, kz1;              /* kz == 0, kz == 1 */
    int_packet neg_x, neg_y, neg_z;   /* the direction's sign bits */
} Mixed;

/* Component kx, ky or kz of (x, y, z) in each lane: prepare_ray's
 * permutation, (kx, ky, kz) = (1, 2, 0), (2, 0, 1) or (0, 1, 2) as kz is 0,
 * 1 or 2. */
#define PICK_kx(m, x, y, z) ((m)->kz0 ? (y) : ((m)->kz1 ? (z) : (x)))
#define PICK_ky(m, x, y, z) ((m)->kz0 ? (z) : ((m)->kz1 ? (x) : (y)))
#define PICK_kz(m, x, y, z) ((m)->kz0 ? (x) : ((m)->kz1 ? (y) : (z)))

/* prepare_ray for every lane. */
TRAVERSAL_INLINE void prepare_mixed(const RayLanes* in, Mixed* m)
{
    float_packet o[3], d[3], a[3];
    lane_vectors(in, o, d, a);
    m->kz0 = (a[0] >= a[1]) & (a[0] >= a[2]);
    m->kz1 = ~m->kz0 & (a[1] >= a[2]);
    m->ox = o[0];
    m->oy = o[1];
    m->oz = o[2];
#ifdef RAY_DIRECTION
    m->dx = d[0];
    m->dy = d[1];
    m->dz = d[2];
#endif
    m->inv_x = 1.0f / d[0];
    m->inv_y = 1.0f / d[1];
    m->inv_z = 1.0f / d[2];
    m->tmin = vload_packet(0, in->tmin);
    m->tmax = vload_packet(0, in->tmax);
    float_packet dkz = PICK_kz(m, d[0], d[1], d[2]);
    m->sx = PICK_kx(m, d[0], d[1], d[2]) / dkz;
    m->sy = PICK_ky(m, d[0], d[1], d[2]) / dkz;
    m->sz = 1.0f / dkz;
    m->okx = PICK_kx(m, o[0], o[1], o[2]);
    m->oky = PICK_ky(m, o[0], o[1], o[2]);
    m->okz = PICK_kz(m, o[0], o[1], o[2]);
    m->neg_x = as_int_packet(d[0]) < 0;
    m->neg_y = as_int_packet(d[1]) < 0;
    m->neg_z = as_int_packet(d[2]) < 0;
}

/* The lanes that meet child c of node n within their limits (SLABS_MEET
 * per lane). */
TRAVERSAL_INLINE int_packet mixed_meet(const Mixed* m, __global const WideNode* n, int c,
                                       float_packet limit)
{
    float_packet lx = (float_packet)(n->lo_x[c]), hx = (float_packet)(n->hi_x[c]);
    float_packet ly = (float_packet)(n->lo_y[c]), hy = (float_packet)(n->hi_y[c]);
    float_packet lz = (float_packet)(n->lo_z[c]), hz = (float_packet)(n->hi_z[c]);
    float_packet entry;
    return SLABS_MEET(float_packet, ((m->neg_x ? hx : lx) - m->ox) * m->inv_x,
                      ((m->neg_y ? hy : ly) - m->oy) * m->inv_y,
                      ((m->neg_z ? hz : lz) - m->oz) * m->inv_z,
                      ((m->neg_x ? lx : hx) - m->ox) * m->inv_x,
                      ((m->neg_y ? ly : hy) - m->oy) * m->inv_y,
                      ((m->neg_z ? lz : hz) - m->oz) * m->inv_z, m->tmin, limit, entry);
}

/* ---- the root phase's vocabulary (see walk.h): the packet's types, with
 * each lane's own permutation */
typedef Mixed Rays_mixed;
typedef float_packet real_mixed;
typedef int_packet flags_mixed;
typedef Found_packet Found_mixed;
#define bits_mixed as_int_packet
#define some_mixed some_packet
#define every_mixed every_packet
#define inside_mixed inside_packet
#define update_reach_mixed update_reach_packet
#ifdef cl_khr_fp64
typedef wide_packet wide_mixed;
#define to_double_mixed to_double_packet
#define to_float_mixed to_float_packet
#endif
#define corner_mixed(v, r, k) \
    CONCAT(PICK_, k)(r, (float_packet)((v)[0]), (float_packet)((v)[1]), (float_packet)((v)[2]))

#define PATH_SUFFIX _mixed
#include "query/rays/triangle.h"
#undef PATH_SUFFIX

#endif /* MIXED_H */
