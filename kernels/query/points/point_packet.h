/* Point packets: one work-item walks PACKET_SIZE query points together, one
 * vector lane each, as ray packets do (packet.h; Wald et al. 2001).  The
 * points run in Morton order (hlbvh_cl/query/order.py), so a work-item's points
 * lie close together and look for their closest triangles among much the
 * same nodes: the walk, the stack and the child sort are paid once for
 * them, and each box and triangle is measured against every lane at once.
 * A node's children are first culled by their distance to the lanes' own
 * box, a lower bound on every lane's (as children_interval culls with the
 * packet as one interval ray).  Each lane keeps its own best distance; the
 * walk drops what lies beyond the farthest lane's.  The closest-point
 * walk is walk.h's, with this header's vocabulary (path suffix _points);
 * the winding walk is its own (below). */
#ifndef POINT_PACKET_H
#define POINT_PACKET_H

#include "query/walk/lanes.h"
#include "query/points/point.h"
#include "query/walk/stack.h"

/* The query points, one lane each, and the box around them. */
typedef struct {
    float_packet x, y, z;
    float lo_x, lo_y, lo_z, hi_x, hi_y, hi_z;
} PointPacket;
typedef PointPacket Rays_points;

/* Per lane what Found_point keeps for one point (its squared distance in
 * `best`), and the largest lane's best: how far the walk still looks. */
typedef struct {
    int_packet index;
    float_packet best, u, v, solid_angle;
    float reach;
} Found_points;
TRAVERSAL_INLINE float reach_points(const Found_points* s) { return s->reach; }

/* A walk's start: nothing found in any lane, squared reach `reach`. */
TRAVERSAL_INLINE void start_points(Found_points* s, float reach)
{
    Found_points start = {(int_packet)(-1), (float_packet)(reach), (float_packet)(0.0f),
                          (float_packet)(0.0f), (float_packet)(0.0f), reach};
    *s = start;
}

/* The packet of the points at slots at[lane] of points. */
TRAVERSAL_INLINE void load_point_packet(__global const float* points, const uint* at,
                                        PointPacket* q)
{
    float c[3][PACKET_SIZE];
    for (uint l = 0; l < PACKET_SIZE; ++l)
        for (uint k = 0; k < 3; ++k)
            c[k][l] = points[3 * (size_t)at[l] + k];
    q->x = vload_packet(0, c[0]);
    q->y = vload_packet(0, c[1]);
    q->z = vload_packet(0, c[2]);
    q->lo_x = packet_min(q->x);
    q->lo_y = packet_min(q->y);
    q->lo_z = packet_min(q->z);
    q->hi_x = packet_max(q->x);
    q->hi_y = packet_max(q->y);
    q->hi_z = packet_max(q->z);
}

/* Each lane's distance to the interval [lo, hi] (0 inside). */
TRAVERSAL_INLINE float_packet lane_gap(float lo, float hi, float_packet q)
{
    return GROW_HI(GROW_HI((float_packet)(0.0f), lo - q), q - hi);
}

/* The children some lane may find a triangle in, nearer than its best: the
 * lanes' box culls them all at once, then each left is measured per lane.
 * Entries are the least lane distance (children none reach stay +inf).
 * (Row macros: they name a node's field.) */
#define NODE_ROW(row) LOAD_ROW(float_lanes, node->row)
#define BOX_GAP(lo, hi, q_lo, q_hi)                                                       \
    GROW_HI(GROW_HI((float_lanes)(0.0f), NODE_ROW(lo) - (q_hi)), (q_lo) - NODE_ROW(hi))
TRAVERSAL_INLINE uint children_points(const PointPacket* q, __global const WideNode* node,
                                      const Found_points* s, ChildEntries* entry)
{
    float_lanes gx = BOX_GAP(lo_x, hi_x, q->lo_x, q->hi_x);
    float_lanes gy = BOX_GAP(lo_y, hi_y, q->lo_y, q->hi_y);
    float_lanes gz = BOX_GAP(lo_z, hi_z, q->lo_z, q->hi_z);
    uint rest = lane_mask((((gx * gx + gy * gy) + gz * gz) <= (float_lanes)(s->reach))
                          & (NODE_ROW(lo_x) <= NODE_ROW(hi_x)));
    entry->lanes = (float_lanes)(INFINITY);
    uint mask = 0;
    for (; rest != 0; rest &= rest - 1u) {
        int c = lowest_slot(rest);
        float_packet dx = lane_gap(node->lo_x[c], node->hi_x[c], q->x);
        float_packet dy = lane_gap(node->lo_y[c], node->hi_y[c], q->y);
        float_packet dz = lane_gap(node->lo_z[c], node->hi_z[c], q->z);
        float_packet d2 = (dx * dx + dy * dy) + dz * dz;
        int_packet near = d2 <= s->best;
        if (some_packet(near)) {
            entry->slot[c] = packet_min(near ? d2 : (float_packet)(INFINITY));
            mask |= 1u << c;
        }
    }
    return mask;
}
#undef BOX_GAP
#undef NODE_ROW

/* segment_point per lane: the point of segment a + w ab nearest to each. */
/* dot(e, p) for each lane's p. */
TRAVERSAL_INLINE float_packet dot_lanes(float3 e, float_packet px, float_packet py,
                                        float_packet pz)
{
    return (e.x * px + e.y * py) + e.z * pz;
}

TRAVERSAL_INLINE float_packet segment_points(float3 a, float3 ab, const PointPacket* q,
                                             float_packet* w)
{
    float length2 = DOT3(ab, ab);
    float_packet along = (float_packet)(0.0f);
    if (length2 > 0.0f)
        along = dot_lanes(ab, q->x - a.x, q->y - a.y, q->z - a.z) / length2;
    along = GROW_LO(GROW_HI(along, (float_packet)(0.0f)), (float_packet)(1.0f));
    *w = along;
    float_packet dx = q->x - (a.x + along * ab.x), dy = q->y - (a.y + along * ab.y),
                 dz = q->z - (a.z + along * ab.z);
    return (dx * dx + dy * dy) + dz * dz;
}

#ifdef cl_khr_fp64
/* closest_on_sliver lane by lane (point.h: a sliver is found in double). */
typedef union {
    float_packet lanes;
    float lane[PACKET_SIZE];
} PacketLanes;
TRAVERSAL_INLINE float_packet sliver_packet(float3 a, float3 b, float3 c, const PointPacket* q,
                                            float_packet* u_out, float_packet* v_out)
{
    PacketLanes x = {q->x}, y = {q->y}, z = {q->z}, u, v, d2;
    for (int l = 0; l < PACKET_SIZE; ++l)
        d2.lane[l] = closest_on_sliver(a, b, c, (float3)(x.lane[l], y.lane[l], z.lane[l]),
                                       &u.lane[l], &v.lane[l]);
    *u_out = u.lanes;
    *v_out = v.lanes;
    return d2.lanes;
}
#endif

/* closest_on_corners for every lane: the same regions and formulas (Ericson
 * 2005, sec. 5.1.5), each lane's picked by selects instead of branches.
 * The face region is the default, and each region of the scalar chain
 * overrides it, the earliest last, so that a lane in several takes the one
 * the chain tests first.  The degenerate triangle's fallback runs only when
 * a lane left in the face region has barycentrics out of range.  A sliver
 * goes lane by lane in double where the device has it (sliver_packet). */
#define PICK(cond, value, was) ((cond) ? (value) : (was)) /* ints and floats alike */
TRAVERSAL_INLINE float_packet closest_on_corners_packet(float3 a, float3 b, float3 c,
                                                        const PointPacket* q,
                                                        float_packet* u_out,
                                                        float_packet* v_out)
{
    float3 ab = b - a, ac = c - a;
#ifdef cl_khr_fp64
    if (thin_triangle(ab, ac))
        return sliver_packet(a, b, c, q, u_out, v_out);
#endif
    float_packet apx = q->x - a.x, apy = q->y - a.y, apz = q->z - a.z;
    float_packet bpx = q->x - b.x, bpy = q->y - b.y, bpz = q->z - b.z;
    float_packet cpx = q->x - c.x, cpy = q->y - c.y, cpz = q->z - c.z;
    float_packet d1 = dot_lanes(ab, apx, apy, apz), d2 = dot_lanes(ac, apx, apy, apz);
    float_packet d3 = dot_lanes(ab, bpx, bpy, bpz), d4 = dot_lanes(ac, bpx, bpy, bpz);
    float_packet d5 = dot_lanes(ab, cpx, cpy, cpz), d6 = dot_lanes(ac, cpx, cpy, cpz);
    float_packet vc = d1 * d4 - d3 * d2, vb = d5 * d2 - d1 * d6, va = d3 * d6 - d5 * d4;
    float_packet inv = 1.0f / (va + vb + vc);
    float_packet u = vb * inv, v = vc * inv;
    const float_packet zero = (float_packet)(0.0f), one = (float_packet)(1.0f);
    int_packet vertex_a = (d1 <= 0.0f) & (d2 <= 0.0f);
    int_packet vertex_b = (d3 >= 0.0f) & (d4 <= d3);
    float_packet len_ab = d1 - d3, len_ac = d2 - d6, len_bc = (d4 - d3) + (d5 - d6);
    int_packet edge_ab = (vc <= 0.0f) & (d1 >= 0.0f) & (d3 <= 0.0f) & (len_ab > 0.0f);
    int_packet vertex_c = (d6 >= 0.0f) & (d5 <= d6);
    int_packet edge_ac = (vb <= 0.0f) & (d2 >= 0.0f) & (d6 <= 0.0f) & (len_ac > 0.0f);
    int_packet edge_bc = (va <= 0.0f) & (d4 - d3 >= 0.0f) & (d5 - d6 >= 0.0f) & (len_bc > 0.0f);
    /* the lanes in the face region, as the chain reaches it (every test
     * above failed), spelled as the compares that fail rather than their
     * negation, which Clang makes an xor of the compare's i1 vector with
     * true: Oclgrind runs that wrong (see inside_packet).  A NaN fails
     * the chain's tests and these alike, so NaN lanes join explicitly. */
    int_packet face = ((d1 > 0.0f) | (d2 > 0.0f)) & ((d3 < 0.0f) | (d4 > d3))
                      & ((vc > 0.0f) | (d1 < 0.0f) | (d3 > 0.0f) | (len_ab <= 0.0f))
                      & ((d6 < 0.0f) | (d5 > d6))
                      & ((vb > 0.0f) | (d2 < 0.0f) | (d6 > 0.0f) | (len_ac <= 0.0f))
                      & ((va > 0.0f) | (d4 - d3 < 0.0f) | (d5 - d6 < 0.0f) | (len_bc <= 0.0f));
    face |= (va != va) | (vb != vb) | (vc != vc);
    /* face lanes with u, v out of range (NaN included), or all of them on a
     * sliver: closest_on_corners' fallback */
    int_packet out_of_range = (u < 0.0f) | (v < 0.0f) | (u + v > 1.0f) | (u != u) | (v != v);
    bool thin = some_packet(face) && thin_triangle(ab, ac);
    int_packet degenerate = face & (thin ? face : out_of_range);
    if (some_packet(degenerate)) {
        float_packet w, best = segment_points(a, ab, q, &w);
        float_packet fu = w, fv = zero;
        float_packet d = segment_points(a, ac, q, &w);
        int_packet nearer = d < best;
        best = PICK(nearer, d, best);
        fu = PICK(nearer, zero, fu);
        fv = PICK(nearer, w, fv);
        d = segment_points(b, c - b, q, &w);
        nearer = d < best;
        best = PICK(nearer, d, best);
        fu = PICK(nearer, one - w, fu);
        fv = PICK(nearer, w, fv);
        if (thin) {  /* the edges' point where it is nearer than the face's */
            float_packet fx = q->x - ((a.x + u * ab.x) + v * ac.x),
                         fy = q->y - ((a.y + u * ab.y) + v * ac.y),
                         fz = q->z - ((a.z + u * ab.z) + v * ac.z);
            degenerate &= out_of_range | (best < (fx * fx + fy * fy) + fz * fz);
        }
        u = PICK(degenerate, fu, u);
        v = PICK(degenerate, fv, v);
    }
    float_packet along_bc = (d4 - d3) / len_bc;
    u = PICK(edge_bc, one - along_bc, u);
    v = PICK(edge_bc, along_bc, v);
    u = PICK(edge_ac, zero, u);
    v = PICK(edge_ac, d2 / len_ac, v);
    u = PICK(vertex_c, zero, u);
    v = PICK(vertex_c, one, v);
    u = PICK(edge_ab, d1 / len_ab, u);
    v = PICK(edge_ab, zero, v);
    u = PICK(vertex_b, one, u);
    v = PICK(vertex_b, zero, v);
    u = PICK(vertex_a, zero, u);
    v = PICK(vertex_a, zero, v);
    *u_out = u;
    *v_out = v;
    float_packet dx = q->x - ((a.x + u * ab.x) + v * ac.x),
                 dy = q->y - ((a.y + u * ab.y) + v * ac.y),
                 dz = q->z - ((a.z + u * ab.z) + v * ac.z);
    return (dx * dx + dy * dy) + dz * dz;
}

/* closest_leaf for every lane: a triangle nearer than a lane's best becomes
 * that lane's (at the best itself while it has none or when it comes first
 * in tree order). */
TRAVERSAL_INLINE bool closest_leaf_points(Found_points* s, const PointPacket* q,
                                          __global const Leaf* triangles, int first,
                                          uint count)
{
    for (int i = first; i < first + (int)count; ++i) {
        LEAF_CORNERS(t, triangles, i);
        float_packet u, v;
        float_packet d2 = closest_on_corners_packet(LOAD_XYZ(t->v0), LOAD_XYZ(t->v1),
                                                    LOAD_XYZ(t->v2), q, &u, &v);
        int_packet take = (d2 < s->best)
                          | ((d2 <= s->best) & ((s->index < 0) | ((int_packet)(i) < s->index)));
        if (some_packet(take)) {
            s->index = PICK(take, (int_packet)(i), s->index);
            s->best = PICK(take, d2, s->best);
            s->u = PICK(take, u, s->u);
            s->v = PICK(take, v, s->v);
            s->reach = packet_max(s->best);
        }
    }
    return false;
}
#undef PICK

/* solid_angle for every lane: the triangle (a, b, c) seen from each point. */
TRAVERSAL_INLINE float_packet solid_angle_points(float3 a, float3 b, float3 c,
                                                 const PointPacket* q, int_packet* doubtful)
{
    float_packet ax = a.x - q->x, ay = a.y - q->y, az = a.z - q->z;
    float_packet bx = b.x - q->x, by = b.y - q->y, bz = b.z - q->z;
    float_packet cx = c.x - q->x, cy = c.y - q->y, cz = c.z - q->z;
    float_packet aa = (ax * ax + ay * ay) + az * az, bb = (bx * bx + by * by) + bz * bz,
                 cc = (cx * cx + cy * cy) + cz * cz;
    float_packet m = GROW_HI(GROW_HI(aa, bb), cc);
    if (some_packet(m < (float_packet)(SCALE_BELOW))) {
        float_packet unit = UNIT_SCALE(int_packet, as_int_packet, as_float_packet, m),
                     unit2 = unit * unit;
        ax *= unit, ay *= unit, az *= unit, bx *= unit, by *= unit, bz *= unit;
        cx *= unit, cy *= unit, cz *= unit, aa *= unit2, bb *= unit2, cc *= unit2;
    }
    float_packet la = packet_root(aa), lb = packet_root(bb), lc = packet_root(cc);
    float_packet det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz)
                       + az * (bx * cy - by * cx);
    float_packet ab = (ax * bx + ay * by) + az * bz, bc = (bx * cx + by * cy) + bz * cz,
                 ca = (cx * ax + cy * ay) + cz * az;
    float_packet product = la * lb * lc, denominator = product + ab * lc + bc * la + ca * lb;
    *doubtful = !(GROW_HI(abs_packet(det), abs_packet(denominator))
                  >= (float_packet)(DOUBTFUL_ANGLE) * product);
    return 2.0f * atan2(det, denominator);
}

#ifdef cl_khr_fp64
/* solid_angle_double (point.h) for every lane. */
TRAVERSAL_INLINE float_packet solid_angle_points_double(float3 v0, float3 v1, float3 v2,
                                                        const PointPacket* q)
{
    wide_packet qx = to_double_packet(q->x), qy = to_double_packet(q->y),
                qz = to_double_packet(q->z);
    wide_packet ax = (double)v0.x - qx, ay = (double)v0.y - qy, az = (double)v0.z - qz;
    wide_packet bx = (double)v1.x - qx, by = (double)v1.y - qy, bz = (double)v1.z - qz;
    wide_packet cx = (double)v2.x - qx, cy = (double)v2.y - qy, cz = (double)v2.z - qz;
    wide_packet la = sqrt((ax * ax + ay * ay) + az * az), lb = sqrt((bx * bx + by * by) + bz * bz),
                lc = sqrt((cx * cx + cy * cy) + cz * cz);
    wide_packet det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz)
                      + az * (bx * cy - by * cx);
    wide_packet ab = (ax * bx + ay * by) + az * bz, bc = (bx * cx + by * cy) + bz * cz,
                ca = (cx * ax + cy * ay) + cz * az;
    return to_float_packet(2.0 * atan2(det, la * lb * lc + ab * lc + bc * la + ca * lb));
}
#endif

/* Lane flags (-1 or 0) from a bit mask of lanes, and back. */
#if PACKET_SIZE == 16
#define LANE_BITS (int16)(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096, 8192, \
                          16384, 32768)
#else
#define LANE_BITS (int8)(1, 2, 4, 8, 16, 32, 64, 128)
#endif
TRAVERSAL_INLINE int_packet lanes_of(uint bits)
{
    return ((int_packet)(bits) & LANE_BITS) != (int_packet)(0);
}

TRAVERSAL_INLINE uint bits_of(int_packet flags)
{
    return (uint)packet_or(flags & LANE_BITS);
}

/* A child's dipole flux a.d for each lane's d. */
TRAVERSAL_INLINE float_packet dipole_flux_points(__global const WideDipoles* dipole, int c,
                                                 float_packet dx, float_packet dy,
                                                 float_packet dz)
{
    return (dipole->a_x[c] * dx + dipole->a_y[c] * dy) + dipole->a_z[c] * dz;
}

/* The winding walk of a packet, each lane's sum made as the one-point walk
 * makes it: at a node, a child far from a lane (Barill's |q - p| > beta r)
 * adds its dipole's solid angle to that lane, and a child near some lanes
 * is descended for those lanes only, so a lane's terms never depend on the
 * other points of its packet (nor do its sums: children go in slot order).
 * Not walk.h's ordered walk: this one carries each stacked node's lanes
 * still summing, for which that walk's items have no place.  s->solid_angle
 * gets the sums; true when the stack was too small. */
TRAVERSAL_INLINE bool walk_winding_points(const PointPacket* q, __global const WideNode* nodes,
                                          __global const Leaf* triangles,
                                          Found_points* s,
                                          __global const WideDipoles* dipoles)
{
    /* a node's children replace it on the stack: at most 7 more a level, as
     * the ordered walk's pushes, and WIDE_ARITY for the last node's */
    StackItem stack[STACK_SIZE + WIDE_ARITY];
    int sp = 0;
    int index = 0;       /* the node or leaf walked now, */
    uint count = 0;      /* its triangles (0: a node) */
    uint lanes = bits_of((int_packet)(-1));  /* and the lanes summing there */
    for (;;) {
        int_packet active = lanes_of(lanes);
        if (count == 0) {
            __global const WideNode* node = nodes + index;
            __global const WideDipoles* dipole = dipoles + index;
            for (int c = WIDE_ARITY - 1; c >= 0; --c) {  /* popped in slot order */
                if (node->count[c] == 0 && node->child[c] == EMPTY_CHILD)
                    continue;
                float_packet dx = dipole->p_x[c] - q->x, dy = dipole->p_y[c] - q->y,
                             dz = dipole->p_z[c] - q->z;
                float_packet d2 = (dx * dx + dy * dy) + dz * dz;
                float near = dipole->radius[c] * WINDING_BETA;
                float_packet term;
                /* a far lane's d2 passes near^2: a cluster this size or
                 * larger never needs the scaling (one test per child, not a
                 * lane reduction) */
                if (near * near >= SCALE_BELOW) {
                    term = dipole_flux_points(dipole, c, dx, dy, dz) / (d2 * packet_root(d2));
                } else {  /* scaled as children_winding's term */
                    float_packet unit = UNIT_SCALE(int_packet, as_int_packet, as_float_packet, d2),
                                 unit2 = unit * unit, scaled = d2 * unit2;
                    term = dipole_flux_points(dipole, c, dx * unit, dy * unit, dz * unit)
                           / (scaled * packet_root(scaled)) * unit2;
                }
                int_packet far = active & (d2 > (float_packet)(near * near));
                s->solid_angle += far ? term : (float_packet)(0.0f);
                uint descend = bits_of(active & (d2 <= (float_packet)(near * near)));
                if (descend != 0) {
                    if (sp == STACK_SIZE + WIDE_ARITY)
                        return true;
                    stack[sp++] = (StackItem){node->child[c], node->count[c],
                                              as_float(descend)};
                }
            }
        } else {
            for (int i = index; i < index + (int)count; ++i) {
                LEAF_CORNERS(t, triangles, i);
                if (zero_area(t))
                    continue;  /* none subtended (winding_leaf) */
                float3 v0 = LOAD_XYZ(t->v0), v1 = LOAD_XYZ(t->v1), v2 = LOAD_XYZ(t->v2);
                int_packet doubtful;
                float_packet angle = solid_angle_points(v0, v1, v2, q, &doubtful);
#ifdef cl_khr_fp64
                doubtful &= active;
                if (some_packet(doubtful))  /* (winding_leaf) */
                    angle = doubtful ? solid_angle_points_double(v0, v1, v2, q) : angle;
#endif
                s->solid_angle += active ? angle : (float_packet)(0.0f);
            }
        }
        if (sp == 0)
            return false;
        --sp;
        index = stack[sp].index;
        count = stack[sp].count;
        lanes = as_uint(stack[sp].entry);
    }
}
#undef LANE_BITS

#endif /* POINT_PACKET_H */
