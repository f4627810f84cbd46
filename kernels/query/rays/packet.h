/* Ray packets: one work-item traces PACKET_SIZE coherent rays together, one
 * vector lane per ray, so that the node walk, the stack and the child sort
 * are paid once per packet and each box and triangle is tested against all
 * the rays at once (Wald, Slusallek, Benthin & Wagner 2001, "Interactive
 * Rendering with Coherent Ray Tracing"; on BVHs Wald, Boulos & Shirley
 * 2007).  A packet is traced so only when its rays share the signs of their
 * direction components and the axis the watertight test projects along
 * (kz): then every plane offset and vertex permutation is the same for all
 * lanes and stays scalar.  Nodes are first culled with the packet as one
 * interval ray (Boulos et al. 2007, "Geometric and Arithmetic Culling
 * Methods for Entire Ray Packets").  This header is the packet path's
 * vocabulary (suffix _packet) for the generic triangle test and walk. */
#ifndef PACKET_H
#define PACKET_H

#include "query/rays/ray.h"
#include "query/walk/lanes.h"

/* RayData of PACKET_SIZE rays, one lane each, with the fields the packet
 * shares kept scalar. */
typedef struct {
    float_packet ox, oy, oz;
#ifdef RAY_DIRECTION
    float_packet dx, dy, dz;  /* direction, for the refined t, mapping */
#endif
#ifdef INSTANCES
    int_packet mask;          /* the rays' masks (instance.h) */
#endif
    float_packet inv_x, inv_y, inv_z;
    float_packet tmin, tmax;
    float_packet sx, sy, sz;
    float_packet okx, oky, okz;
    int kx, ky, kz;
    int near_x, near_y, near_z;
    /* The packet as one interval ray, for culling a node's children with
     * interval arithmetic before the per-lane tests (children_interval):
     * per axis the lanes' least and greatest inverse direction, and the
     * origin component that bounds the entry (near_o) and the exit (far_o)
     * distances from below and above, of the origins moved onto one plane
     * (interval_origins); the least tmin from there, the least move (a
     * lane's limit L is at most L - least_move from there), and the slack
     * the test allows its exit for the largest move (children_interval). */
    float inv_lo_x, inv_lo_y, inv_lo_z, inv_hi_x, inv_hi_y, inv_hi_z;
    float near_ox, near_oy, near_oz, far_ox, far_oy, far_oz;
    float tmin_lo, least_move, slack;
} Packet;

/* The interval test's relative slack on the exit: it must keep every child
 * a lane's own test keeps, and that test lets the exit grow by Ize's
 * 2 * gamma(5) (EXIT_SCALE, about 2^-20.7) of its own distance; the moved
 * origins' tmin and limit round by a few units of 2^-24 more. */
#define INTERVAL_SLACK 0x1p-19f

/* Lanes that are infinite or NaN, from the exponent's bits. */
TRAVERSAL_INLINE int_packet not_finite(float_packet v)
{
    return (as_int_packet(v) & (int_packet)(0x7f800000)) == (int_packet)(0x7f800000);
}

/* The lanes' extent on each axis, summed. */
TRAVERSAL_INLINE float packet_spread(const float_packet* v)
{
    float sum = 0.0f;
    for (int k = 0; k < 3; ++k)
        sum += packet_max(v[k]) - packet_min(v[k]);
    return sum;
}

/* The interval ray's origins (o, directions d) into `moved`, and each
 * lane's `move`: rays along nearly one line but starting apart (rays aimed
 * at one point, ordered by direction: hlbvh_cl/query/order.py) would make an
 * interval ray as wide as their origins are apart (Boulos et al. 2007 bound
 * the origins as given); moved along their rays, by `move` times their
 * directions, onto the plane across kz through the middle of the lanes' kz
 * coordinates, they make a thin one.  A lane's distances from its moved
 * origin are its own less its move.  The origins stay where moving them
 * spreads them more (rays that part), or a move is not finite (huge
 * coordinates).  Returns, per axis, a bound on how far a moved origin may
 * be from the real point its move reaches: off kz, o + move * d rounds
 * twice, by 2^-24 (|o| + |move d|) at most each time; along kz, the move is
 * mid - o rounded, times 1 / d rounded (by up to 2.5 ulp in OpenCL), and
 * rounded again, so the point reached misses mid by at most about
 * 2^-24 * 7 |move d|. */
TRAVERSAL_INLINE float3 interval_origins(const Packet* p, const float_packet* o,
                                         const float_packet* d, float_packet* moved,
                                         float_packet* move)
{
    float mid = 0.5f * (packet_min(o[p->kz]) + packet_max(o[p->kz]));
    *move = (mid - o[p->kz]) * p->sz;
    int_packet wild = not_finite(*move);
    float error[3];
    for (int k = 0; k < 3; ++k) {
        float_packet step = *move * d[k];
        moved[k] = k == p->kz ? (float_packet)(mid) : o[k] + step;
        wild |= not_finite(moved[k]);
        error[k] = 0x1p-21f * packet_max(abs_packet(o[k]) + abs_packet(step));
    }
    if (some_packet(wild) || !(packet_spread(moved) < packet_spread(o))) {
        for (int k = 0; k < 3; ++k)
            moved[k] = o[k];
        *move = (float_packet)(0.0f);
        return (float3)(0.0f);
    }
    return (float3)(error[0], error[1], error[2]);
}

/* The lanes' origins o and directions d as vectors, and |d| in a.  (fabs,
 * signbit and select by bits and ?: here and below: PoCL, see LOAD_ROW.) */
TRAVERSAL_INLINE void lane_vectors(const RayLanes* in, float_packet* o, float_packet* d,
                                   float_packet* a)
{
    for (int k = 0; k < 3; ++k) {
        o[k] = vload_packet(0, in->origin[k]);
        d[k] = vload_packet(0, in->direction[k]);
        a[k] = abs_packet(d[k]);
    }
}

/* prepare_ray for every lane, in vector arithmetic; false when the lanes do
 * not share direction signs and kz (then they are traced one by one). */
TRAVERSAL_INLINE bool prepare_packet(const RayLanes* in, Packet* p)
{
    float_packet o[3], d[3], a[3];
    lane_vectors(in, o, d, a);
    float_packet ax = a[0], ay = a[1], az = a[2];
    /* Each lane's kz, as prepare_ray picks it, held in floats: LLVM makes
     * ?: between integer constants a zext of the compare lanes, which
     * Oclgrind gets wrong (its vector compares give -1 per true lane). */
    float_packet kz = ((ax >= ay) & (ax >= az)) ? (float_packet)(0.0f)
                      : (ay >= az ? (float_packet)(1.0f) : (float_packet)(2.0f));
    int_packet neg_x = as_int_packet(d[0]) < 0, neg_y = as_int_packet(d[1]) < 0,
               neg_z = as_int_packet(d[2]) < 0;
    if (some_packet((kz != (float_packet)(kz.s0)) | (neg_x != (int_packet)(neg_x.s0))
            | (neg_y != (int_packet)(neg_y.s0)) | (neg_z != (int_packet)(neg_z.s0))))
        return false;
    p->kz = (int)kz.s0;
    p->kx = p->kz == 2 ? 0 : p->kz + 1;
    p->ky = p->kx == 2 ? 0 : p->kx + 1;
    p->ox = o[0];
    p->oy = o[1];
    p->oz = o[2];
#ifdef RAY_DIRECTION
    p->dx = d[0];
    p->dy = d[1];
    p->dz = d[2];
#endif
#ifdef INSTANCES
    p->mask = as_int_packet(vload_packet(0, (const float*)in->mask));
#endif
    p->inv_x = 1.0f / d[0];
    p->inv_y = 1.0f / d[1];
    p->inv_z = 1.0f / d[2];
    p->tmin = vload_packet(0, in->tmin);
    p->tmax = vload_packet(0, in->tmax);
    float_packet dkz = d[p->kz];
    p->sx = d[p->kx] / dkz;
    p->sy = d[p->ky] / dkz;
    p->sz = p->kz == 0 ? p->inv_x : (p->kz == 1 ? p->inv_y : p->inv_z);  /* 1 / dkz, once */
    p->okx = o[p->kx];
    p->oky = o[p->ky];
    p->okz = o[p->kz];
    p->near_x = LO_X_ROW + (neg_x.s0 ? ROW_BYTES : 0);
    p->near_y = LO_Y_ROW + (neg_y.s0 ? ROW_BYTES : 0);
    p->near_z = LO_Z_ROW + (neg_z.s0 ? ROW_BYTES : 0);
    p->inv_lo_x = packet_min(p->inv_x);
    p->inv_lo_y = packet_min(p->inv_y);
    p->inv_lo_z = packet_min(p->inv_z);
    p->inv_hi_x = packet_max(p->inv_x);
    p->inv_hi_y = packet_max(p->inv_y);
    p->inv_hi_z = packet_max(p->inv_z);
    /* (plane - o) * inv over the lanes: the least entry comes from the
     * greatest origin when the direction is positive, the least when it is
     * negative; the greatest exit the other way round. */
    /* The moved origins' box, grown by their error and then by one ulp, so
     * that no origin lies on its faces: a lane whose origin lies on a node's
     * plane and whose direction is 0 along that axis ignores the plane (0 *
     * inf is NaN), but the box's distance to that plane would be 0 times a
     * finite inverse of another lane, a bound of 0 that drops the child. */
    float o_lo_x, o_lo_y, o_lo_z, o_hi_x, o_hi_y, o_hi_z;
    if (!some_packet((o[0] != (float_packet)(o[0].s0)) | (o[1] != (float_packet)(o[1].s0))
                     | (o[2] != (float_packet)(o[2].s0)))) {
        /* One origin (a camera's; signed zeros alike): nothing to move,
         * and the box is the point grown by an ulp, the same bits as the
         * general case below gives it, for two folds of the lanes instead
         * of some twenty-five (perf: prepare_packet was a third of the
         * time of camera rays that meet nothing) */
        o_lo_x = float_below(o[0].s0);
        o_lo_y = float_below(o[1].s0);
        o_lo_z = float_below(o[2].s0);
        o_hi_x = float_above(o[0].s0);
        o_hi_y = float_above(o[1].s0);
        o_hi_z = float_above(o[2].s0);
        p->slack = 0.0f;
        p->tmin_lo = packet_min(p->tmin);
        p->least_move = 0.0f;
    } else {
        float_packet moved[3], move;
        float3 error = interval_origins(p, o, d, moved, &move);
        o_lo_x = float_below(packet_min(moved[0]) - error.x);
        o_lo_y = float_below(packet_min(moved[1]) - error.y);
        o_lo_z = float_below(packet_min(moved[2]) - error.z);
        o_hi_x = float_above(packet_max(moved[0]) + error.x);
        o_hi_y = float_above(packet_max(moved[1]) + error.y);
        o_hi_z = float_above(packet_max(moved[2]) + error.z);
        p->slack = INTERVAL_SLACK * packet_max(abs_packet(move));
        p->tmin_lo = packet_min(p->tmin - move);
        p->least_move = packet_min(move);
    }
    p->near_ox = neg_x.s0 ? o_lo_x : o_hi_x;
    p->near_oy = neg_y.s0 ? o_lo_y : o_hi_y;
    p->near_oz = neg_z.s0 ? o_lo_z : o_hi_z;
    p->far_ox = neg_x.s0 ? o_hi_x : o_lo_x;
    p->far_oy = neg_y.s0 ? o_hi_y : o_lo_y;
    p->far_oz = neg_z.s0 ? o_hi_z : o_lo_z;
    return true;
}

/* Whether a prepared packet's rays lie close enough to walk as one: its
 * interval ray's origins (the moved origins' box, interval_origins) within
 * 1/PACKET_SPREAD of the scene's extent (the root's children's box, its
 * largest axis) on every axis.  The interval ray spans that box, so rays
 * from origins spread across the scene, such as parallel rays from random
 * points, meet most of the tree together, where one by one (interleaved on
 * CPUs) each meets its own few nodes (measured faster so; figures in the
 * commit that brought this).  Rays from one point (a camera's), sorted by
 * origin, or aimed at one point and sorted by direction (query/order.py)
 * pass.  And the rays must not turn apart: the lanes' slopes across kz
 * (sx = d[kx] / d[kz], sy = d[ky] / d[kz], at most 1 in magnitude) within
 * PACKET_TURN of each other.  Shadow rays from a patch of ground to the
 * points sampled on an area light share their origins' patch and their
 * direction signs, but spread over some 30 degrees (slopes about 0.55
 * apart, where a 4x4 camera tile's lie under 0.005 apart): as one packet
 * the interval ray widened across the tree, and they traced slower than one
 * by one (figures in the commit that brought this). */
#define PACKET_SPREAD 16.0f
#define PACKET_TURN 0.25f
/* How far apart packet_compact lets a packet's origins lie: the scene's
 * extent (the root's children's box, its largest axis) / PACKET_SPREAD;
 * the same for every packet of a launch, so a work-item takes it once. */
TRAVERSAL_INLINE float packet_allowed(__global const WideNode* root)
{
    float scene = 0.0f;
    for (int k = 0; k < 3; ++k) {
        float least = row_least(LOAD_ROW(float_lanes, plane_row(root, 2 * k * ROW_BYTES)));
        float most = row_most(LOAD_ROW(float_lanes, plane_row(root, (2 * k + 1) * ROW_BYTES)));
        scene = scene > most - least ? scene : most - least;
    }
    return scene * (1.0f / PACKET_SPREAD);
}

TRAVERSAL_INLINE bool packet_compact(const Packet* p, float allowed)
{
    /* (a lane whose ray is not finite has a NaN slope, which the folds may pass
     * over: it meets nothing either way, its tmax -inf: set_lane) */
    return packet_max(p->sx) - packet_min(p->sx) <= PACKET_TURN
           && packet_max(p->sy) - packet_min(p->sy) <= PACKET_TURN
           && fabs(p->near_ox - p->far_ox) <= allowed && fabs(p->near_oy - p->far_oy) <= allowed
           && fabs(p->near_oz - p->far_oz) <= allowed;
}

/* float_below (core/spelled.h) of every lane. */
TRAVERSAL_INLINE float_packet below_packet(float_packet x)
{
    int_packet bits = as_int_packet(x);
    int_packet next = bits >= (int_packet)(0) ? bits - 1 : bits + 1;
    next = (bits & 0x7fffffff) == (int_packet)(0) ? (int_packet)((int)0x80000001) : next;
    float_packet finite = as_float_packet(next);
    float_packet special = x == (float_packet)(INFINITY) ? (float_packet)(FLT_MAX) : x;
    return (bits & 0x7f800000) == (int_packet)(0x7f800000) ? special : finite;
}

/* ---- the packet path's vocabulary (see walk.h): one lane per ray */
typedef Packet Rays_packet;
typedef float_packet real_packet;
typedef int_packet flags_packet;  /* a vector compare: -1 or 0 per lane */
#define bits_packet as_int_packet

/* What a walk keeps for its query, per lane (see Found_ray), and the
 * farthest any lane still looks. */
typedef struct {
    int_packet index;
    float_packet t, u, v, limit;
    float reach;
#ifdef INSTANCES
    int_packet instance;  /* whose mesh holds each lane's triangle (instance.h) */
#endif
} Found_packet;

TRAVERSAL_INLINE float reach_packet(const Found_packet* s) { return s->reach; }
#define root_done_packet(s) 0u  /* packets take no root phase */
TRAVERSAL_INLINE void update_reach_packet(Found_packet* s) { s->reach = packet_max(s->limit); }

/* A walk's start: no hit in any lane, each lane's limit its tmax. */
TRAVERSAL_INLINE void start_packet(Found_packet* s, const Packet* p)
{
    Found_packet start = {(int_packet)(-1), (float_packet)(INFINITY), (float_packet)(0.0f),
                          (float_packet)(0.0f), p->tmax, packet_max(p->tmax)};
#ifdef INSTANCES
    start.instance = (int_packet)(-1);
#endif
    *s = start;
}

/* inside_ray's test, in lanes: all three >= 0 or all <= 0, so a NaN fails.
 * (Negating a straddle test became an xor of the compare lanes with an i1
 * true vector, which Oclgrind gets wrong: its vector compares give -1 per
 * true lane.) */
TRAVERSAL_INLINE int_packet inside_packet(float_packet e_u, float_packet e_v, float_packet e_w)
{
    return ONE_SIGN(e_u, e_v, e_w);
}

/* A bound, from below (entry) or above (exit), of (plane - o) * inv over
 * the packet's lanes for each child: `offset` (plane - o) is the bounding
 * origin's, and the factor is the end of [inv_lo, inv_hi] that makes the
 * product least (entry: inv_lo where the offset is >= 0, else inv_hi) or
 * greatest (exit: the other end).  Both signs of the direction follow the
 * same rule (prepare_packet picks the origin). */
TRAVERSAL_INLINE float_lanes entry_bound(float_lanes offset, float inv_lo, float inv_hi)
{
    return offset * (offset >= 0.0f ? (float_lanes)(inv_lo) : (float_lanes)(inv_hi));
}

TRAVERSAL_INLINE float_lanes exit_bound(float_lanes offset, float inv_lo, float inv_hi)
{
    return offset * (offset >= 0.0f ? (float_lanes)(inv_hi) : (float_lanes)(inv_lo));
}

/* The children of a node that some lane may meet within `reach`, as a bit
 * mask, from one slab test of the interval ray (Boulos et al. 2007), its
 * distances counted from the moved origins (interval_origins), whose box is
 * grown by their rounding.  Its bounds then hold in real arithmetic, and the
 * exit grows by INTERVAL_SLACK of its size plus the slack for the largest
 * move: a lane's own test grows its exit by EXIT_SCALE of its distance from
 * the lane's real origin, which is at most the exit's size plus the move,
 * so every child some lane's test keeps is kept.  A NaN (0 * inf) bound is
 * ignored, as in SLABS_MEET, which only widens the interval; an unused
 * slot's -inf exit grows to NaN, and no lane meets it. */
#define NODE_ROW(offset) LOAD_ROW(float_lanes, plane_row(node, offset)) /* as ray.h's */
TRAVERSAL_INLINE uint children_interval(const Packet* p, __global const WideNode* node,
                                        float reach)
{
    float_lanes entry = GROW_HI(
        GROW_HI(GROW_HI((float_lanes)(p->tmin_lo),
                        entry_bound(NODE_ROW(p->near_x) - p->near_ox, p->inv_lo_x, p->inv_hi_x)),
                entry_bound(NODE_ROW(p->near_y) - p->near_oy, p->inv_lo_y, p->inv_hi_y)),
        entry_bound(NODE_ROW(p->near_z) - p->near_oz, p->inv_lo_z, p->inv_hi_z));
    float_lanes exit = GROW_LO(
        GROW_LO(GROW_LO((float_lanes)(reach - p->least_move),
                        exit_bound(NODE_ROW(p->near_x ^ ROW_BYTES) - p->far_ox, p->inv_lo_x,
                                   p->inv_hi_x)),
                exit_bound(NODE_ROW(p->near_y ^ ROW_BYTES) - p->far_oy, p->inv_lo_y,
                           p->inv_hi_y)),
        exit_bound(NODE_ROW(p->near_z ^ ROW_BYTES) - p->far_oz, p->inv_lo_z, p->inv_hi_z));
    return lane_mask(entry <= exit + (INTERVAL_SLACK * abs_lanes(exit) + (float_lanes)(p->slack)));
}
#undef NODE_ROW

/* The children that some lane meets within its limit, as a bit mask, and
 * the nearest entry over those lanes for each (children no lane meets stay
 * +inf: the stack's sort compares whole vectors).  Each candidate's result
 * goes in without a branch: whether the interval test's candidate is kept
 * is close to a coin toss on incoherent packets, and its branch
 * mispredicted (measured slower). */
#define CHILD_PLANE(offset) (plane_row(node, offset)[c]) /* SLAB_TEST's PLANE */
TRAVERSAL_INLINE uint children_packet(const Packet* p, __global const WideNode* node,
                                      const Found_packet* s, ChildEntries* entry)
{
    entry->lanes = (float_lanes)(INFINITY);
    uint mask = 0;
    for (uint rest = children_interval(p, node, s->reach); rest != 0; rest &= rest - 1u) {
        int c = lowest_slot(rest);
        float_packet t_entry;
        int_packet hit = SLAB_TEST(float_packet, CHILD_PLANE, p, p->tmin, s->limit, t_entry);
        entry->slot[c] = packet_min(hit ? t_entry : (float_packet)(INFINITY));
        mask |= (uint)some_packet(hit) << c;
    }
    return mask;
}
#undef CHILD_PLANE

/* A vertex's component k (kx, ky or kz) of the ray's permutation. */
#define corner_packet(v, r, k) ((v)[(r)->k])

#define PATH_SUFFIX _packet
#include "query/rays/triangle.h"
#undef PATH_SUFFIX

#endif /* PACKET_H */
