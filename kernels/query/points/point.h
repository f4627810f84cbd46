/* Point queries' vocabulary (path suffix _point, see walk.h): a query point
 * walks the wide tree as a ray does, with box distances instead of slab
 * entries.  The closest point on a triangle follows Ericson, "Real-Time
 * Collision Detection" (2005), sec. 5.1.5; the winding number's far field
 * is Barill et al. 2018 ("Fast Winding Numbers for Soups and Clouds"),
 * order 1, and its near field the exact solid angle of Van Oosterom &
 * Strackee 1983. */
#ifndef POINT_H
#define POINT_H

#include "query/walk/node.h"
#include "query/normals.h"

/* The query point, in the tree's frame. */
typedef struct {
    float x, y, z;
} PointData;
typedef PointData Rays_point;

/* Dot product spelled out (PoCL calls dot out of line, see GROW_LO). */
#define DOT3(a, b) ((a).x * (b).x + (a).y * (b).y + (a).z * (b).z)

/* A power of two s that brings m, a squared length (m >= 0), into [1, 4)
 * as m * s * s, by m's exponent bits: a vector scaled by s keeps its
 * direction and its ratios to the others exactly.  The solid angle and the
 * dipole term are ratios of products of three lengths, which underflow
 * float for a feature under about 1e-13 of the frame (a small mesh in a big
 * scene): where a squared length is under SCALE_BELOW, they are taken
 * scaled, which keeps them exact down to the frame's own limit
 * (docs/queries.md, Range); above it, where scaling would change nothing,
 * it is not paid for (on every term it slowed the winding walk).  m's exponent is
 * clamped so that s * s stays finite (m = 0 or subnormal).  The int and
 * float conversions name the width (as_int and as_float for one, as_int8
 * and as_float8 for lanes). */
#define SCALE_BELOW 0x1p-64f
#define UNIT_SCALE(int_t, AS_INT, AS_FLOAT, m)                                     \
    AS_FLOAT(((int_t)(127) - ((GROW_HI(AS_INT(m) >> 23, (int_t)(2)) - (int_t)(127)) >> 1)) << 23)

/* What a point walk keeps: the closest triangle so far (tree order, -1:
 * none), its squared distance `reach` (the walk drops boxes farther than
 * it), the closest point on it and its barycentrics (point = (1-u-v)*v0 +
 * u*v1 + v*v2); or the winding walk's sum of solid angles (4 pi times the
 * winding number).  In a two-level scene (instance.h) the squared distance
 * is `best`, in the top frame, with the instance that holds the triangle
 * (its index then counts from its mesh's first triangle), and `reach` is
 * the bound in the frame of the tree being walked. */
typedef struct {
    int index;
    float reach;
    float u, v;
    float solid_angle;
#ifdef INSTANCES
    float best;
    int instance;
#endif
} Found_point;
TRAVERSAL_INLINE float reach_point(const Found_point* s) { return s->reach; }

/* A walk's start: nothing found, squared reach `reach`. */
TRAVERSAL_INLINE void start_point(Found_point* s, float reach)
{
#ifdef INSTANCES
    Found_point start = {-1, reach, 0.0f, 0.0f, 0.0f, reach, -1};
#else
    Found_point start = {-1, reach, 0.0f, 0.0f, 0.0f};
#endif
    *s = start;
}

/* Squared distance from the point to each child's box, one lane each
 * (0 inside).  (Row macros: they name a node's field.) */
#define NODE_ROW(row) LOAD_ROW(float_lanes, node->row)
#define BOX_GAP(lo, hi, q) GROW_HI(GROW_HI((float_lanes)(0.0f), NODE_ROW(lo) - (q)), (q) - NODE_ROW(hi))
TRAVERSAL_INLINE float_lanes box_distance2(const PointData* q, __global const WideNode* node)
{
    float_lanes dx = BOX_GAP(lo_x, hi_x, q->x);
    float_lanes dy = BOX_GAP(lo_y, hi_y, q->y);
    float_lanes dz = BOX_GAP(lo_z, hi_z, q->z);
    return (dx * dx + dy * dy) + dz * dz;
}
#undef BOX_GAP

/* The children within the reach (box_distance2) as a mask.  An unused
 * slot's empty box (lo = +inf > hi = -inf) is left out by its lo <= hi
 * test, as its distance (+inf) does not exceed an infinite reach. */
TRAVERSAL_INLINE uint children_point(const PointData* q, __global const WideNode* node,
                                     const Found_point* s, ChildEntries* entry)
{
    entry->lanes = box_distance2(q, node);
    return lane_mask((entry->lanes <= (float_lanes)(s->reach))
                     & (NODE_ROW(lo_x) <= NODE_ROW(hi_x)));
}

/* Barill et al. 2018, sec. 3: a cluster whose centre lies farther than
 * BETA times its radius from the point counts by its dipole alone. */
#define WINDING_BETA 2.0f

#define DIPOLE_ROW(row) LOAD_ROW(float_lanes, dipole->row)

/* The children's dipole fluxes a.d, one lane each. */
TRAVERSAL_INLINE float_lanes dipole_flux(__global const WideDipoles* dipole, float_lanes dx,
                                         float_lanes dy, float_lanes dz)
{
    return (DIPOLE_ROW(a_x) * dx + DIPOLE_ROW(a_y) * dy) + DIPOLE_ROW(a_z) * dz;
}

/* The winding walk's node test: the children far enough from the point
 * (Barill's |q - p| > beta r) add their dipole's solid angle a.(p - q) /
 * |p - q|^3 to the sum and are not descended; the others (used slots) are,
 * in any order: the walk is unordered (QUERY_UNORDERED), so no entry is set. */
TRAVERSAL_INLINE uint children_winding(const PointData* q, __global const WideNode* node,
                                       __global const WideDipoles* dipole, Found_point* s,
                                       ChildEntries* entry)
{
    float_lanes dx = DIPOLE_ROW(p_x) - q->x, dy = DIPOLE_ROW(p_y) - q->y,
                dz = DIPOLE_ROW(p_z) - q->z;
    float_lanes d2 = (dx * dx + dy * dy) + dz * dz;
    float_lanes near = DIPOLE_ROW(radius) * WINDING_BETA;
    int_lanes far = d2 > near * near;
    /* far lanes have d2 > 0; an unused slot's dipole is 0 (far unless the
     * point sits at its centre 0, and never descended) */
    float_lanes term;
    if (lane_mask(d2 < (float_lanes)(SCALE_BELOW)) == 0) {
        term = dipole_flux(dipole, dx, dy, dz) / (d2 * lanes_root(d2));
    } else {  /* a.(s d) / |s d|^3 = a.d / (s^2 |d|^3): see UNIT_SCALE */
        float_lanes unit = UNIT_SCALE(int_lanes, as_int8, as_float8, d2), unit2 = unit * unit;
        float_lanes scaled = d2 * unit2;
        term = dipole_flux(dipole, dx * unit, dy * unit, dz * unit) / (scaled * lanes_root(scaled))
               * unit2;
    }
    term = as_float8(as_int8(term) & far);
    float4 halves = term.lo + term.hi;
    float2 quarter = halves.lo + halves.hi;
    s->solid_angle += quarter.x + quarter.y;
    int_lanes used = (LOAD_ROW(int_lanes, node->count) != (int_lanes)(0))
                     | (LOAD_ROW(int_lanes, node->child) != (int_lanes)(EMPTY_CHILD));
    /* the near lanes by a compare of their own, not as far == 0: Clang
     * makes that an xor of the compare's <8 x i1> with true (1), which
     * Oclgrind runs wrong (its vector compares set i1 lanes to all ones,
     * and 0xff ^ 1 is nonzero: every lane stays true), so there every used
     * child was counted by its dipole and descended too.  d2 is never NaN
     * (finite points and dipoles): <= is exactly not-far. */
    return lane_mask((d2 <= near * near) & used);
}
#undef DIPOLE_ROW
#undef NODE_ROW

/* Below this fraction of |a| |b| |c|, the triple product and the
 * denominator of solid_angle are both lost in float's rounding of their
 * terms (a few eps of |a| |b| |c|): the point lies near the line of an edge
 * (a sliver is all edge), and the angle may be off by up to pi. */
#define DOUBTFUL_ANGLE 0x1p-10f

/* The solid angle the triangle (a, b, c), given relative to the point,
 * subtends (Van Oosterom & Strackee 1983): positive when the point lies
 * behind it (on the side its normal cross(b - a, c - a) points away from);
 * a tiny one scaled to about unit size first (UNIT_SCALE).  *doubtful: its
 * float terms cannot be trusted (DOUBTFUL_ANGLE). */
TRAVERSAL_INLINE float solid_angle(float3 a, float3 b, float3 c, bool* doubtful)
{
    float aa = DOT3(a, a), bb = DOT3(b, b), cc = DOT3(c, c);
    float m = GROW_HI(GROW_HI(aa, bb), cc);
    if (m < SCALE_BELOW) {
        float unit = UNIT_SCALE(int, as_int, as_float, m), unit2 = unit * unit;
        a *= unit;
        b *= unit;
        c *= unit;
        aa *= unit2;
        bb *= unit2;
        cc *= unit2;
    }
    float la = SQRT(aa), lb = SQRT(bb), lc = SQRT(cc);
    float det = a.x * (b.y * c.z - b.z * c.y) + a.y * (b.z * c.x - b.x * c.z)
                + a.z * (b.x * c.y - b.y * c.x);
    float ab = DOT3(a, b), bc = DOT3(b, c), ca = DOT3(c, a);
    float product = la * lb * lc, denominator = product + ab * lc + bc * la + ca * lb;
    *doubtful = !(GROW_HI(abs_float(det), abs_float(denominator)) >= DOUBTFUL_ANGLE * product);
    return 2.0f * atan2(det, denominator);
}

/* Whether the float face formula may not be trusted (a sliver): twice the
 * area squared, |ab x ac|^2, below THIN_RATIO times the longest edge's
 * length L to the fourth (the height over that edge under 10% of it), or
 * NaN.  Ericson's face denominator va + vb + vc is |ab x ac|^2 summed from
 * products of the point's dot products, whose rounding is that of L to the
 * fourth, so the face point's error grows as the ratio shrinks: below
 * THIN_RATIO it is no longer within a few float ulps of the coordinates.
 * A triangle whose L^4 is under THIN_SMALLEST is taken as thin too: those
 * products then near float's underflow (a tiny triangle in a big scene's
 * frame), where the ratio test itself reads 0 >= 0. */
#define THIN_RATIO 1e-2f
#define THIN_SMALLEST 0x1p-100f
TRAVERSAL_INLINE bool thin_triangle(float3 ab, float3 ac)
{
    /* |ab x ac|^2 by Lagrange's identity, and |bc|^2 from the same dots:
     * their rounding, eps |ab|^2 |ac|^2, is far below THIN_RATIO's scale */
    float aa = DOT3(ab, ab), cc = DOT3(ac, ac), ac_dot = DOT3(ab, ac);
    float area2 = aa * cc - ac_dot * ac_dot;
    float longest = GROW_HI(GROW_HI(aa, cc), (aa + cc) - 2.0f * ac_dot);
    return !(area2 >= THIN_RATIO * longest * longest && longest * longest >= THIN_SMALLEST);
}

#ifdef cl_khr_fp64
/* solid_angle of the triangle (v0, v1, v2) seen from p, in double, where
 * float's is doubtful: a sliver's triple product and denominator are both
 * nearly 0 from a point near it, and float's rounding of them turned its
 * angle around by up to pi, half a winding, 1e-6 from the surface. */
TRAVERSAL_INLINE float solid_angle_double(float3 v0, float3 v1, float3 v2, float3 p)
{
    double3 q = convert_double3(p);
    double3 a = convert_double3(v0) - q, b = convert_double3(v1) - q, c = convert_double3(v2) - q;
    double la = sqrt(DOT3(a, a)), lb = sqrt(DOT3(b, b)), lc = sqrt(DOT3(c, c));
    double det = a.x * (b.y * c.z - b.z * c.y) + a.y * (b.z * c.x - b.x * c.z)
                 + a.z * (b.x * c.y - b.y * c.x);
    double ab = DOT3(a, b), bc = DOT3(b, c), ca = DOT3(c, a);
    return (float)(2.0 * atan2(det, la * lb * lc + ab * lc + bc * la + ca * lb));
}
#endif

/* The winding walk's leaf: every triangle's exact solid angle.  A
 * zero-area triangle subtends none, but its formula does not say so: its
 * corners lie on a line, the triple product is 0 up to rounding, and the
 * denominator, negative where the point sees the line's ends on either
 * side of it, took atan2 to +-pi, a whole 0.5 of winding (zero_area).
 * Doubtful angles (a sliver's, near an edge's line) go in double where
 * the device has it (solid_angle_double). */
TRAVERSAL_INLINE bool winding_leaf(Found_point* s, const PointData* q,
                                   __global const Leaf* triangles, int first, uint count)
{
    float3 p = (float3)(q->x, q->y, q->z);
    for (int i = first; i < first + (int)count; ++i) {
        LEAF_CORNERS(t, triangles, i);
        if (zero_area(t))
            continue;
        float3 v0 = LOAD_XYZ(t->v0), v1 = LOAD_XYZ(t->v1), v2 = LOAD_XYZ(t->v2);
        bool doubtful;
        float angle = solid_angle(v0 - p, v1 - p, v2 - p, &doubtful);
#ifdef cl_khr_fp64
        if (doubtful)
            angle = solid_angle_double(v0, v1, v2, p);
#endif
        s->solid_angle += angle;
    }
    return false;
}

/* The closest point on a triangle in float, and in double where the device
 * has it (closest_corners.h).  A sliver's face formula cancels badly in
 * float (its point could lie a hundred times farther from p than the true
 * one), so slivers take the double version, whose error is far below
 * float's; a device without doubles takes the nearer of the face point and
 * the edges'. */
#define REAL float
#define REAL3 float3
#define CORNERS(name) CONCAT(name, _float)
#ifdef cl_khr_fp64
#define THIN(ab, ac) false
#else
#define THIN(ab, ac) thin_triangle(ab, ac)
#endif
#include "query/points/closest_corners.h"
#undef REAL
#undef REAL3
#undef CORNERS
#undef THIN
#ifdef cl_khr_fp64
#define REAL double
#define REAL3 double3
#define CORNERS(name) CONCAT(name, _double)
#define THIN(ab, ac) false
#include "query/points/closest_corners.h"
#undef REAL
#undef REAL3
#undef CORNERS
#undef THIN
#endif

#ifdef cl_khr_fp64
TRAVERSAL_INLINE float closest_on_sliver(float3 a, float3 b, float3 c, float3 p, float* u_out,
                                         float* v_out)
{
    double u, v;
    double d2 = closest_on_corners_double(convert_double3(a), convert_double3(b),
                                          convert_double3(c), convert_double3(p), &u, &v);
    *u_out = (float)u;
    *v_out = (float)v;
    return (float)d2;
}
#endif

TRAVERSAL_INLINE float closest_on_corners(float3 a, float3 b, float3 c, float3 p, float* u_out,
                                          float* v_out)
{
#ifdef cl_khr_fp64
    if (thin_triangle(b - a, c - a))
        return closest_on_sliver(a, b, c, p, u_out, v_out);
#endif
    return closest_on_corners_float(a, b, c, p, u_out, v_out);
}

TRAVERSAL_INLINE float closest_on_triangle(TRIANGLE_AT t, float3 p, float* u_out,
                                           float* v_out)
{
    return closest_on_corners(LOAD_XYZ(t->v0), LOAD_XYZ(t->v1), LOAD_XYZ(t->v2), p, u_out,
                              v_out);
}

/* The closest-point walk's leaf: a triangle nearer than the reach becomes
 * the best (at the reach itself while there is none, so that a point
 * exactly max_distance away is found, or when it comes first in tree
 * order: equidistant triangles resolve the same whichever order the walk
 * meets them in, alone or in any packet). */
TRAVERSAL_INLINE bool closest_leaf(Found_point* s, const PointData* q,
                                   __global const Leaf* triangles, int first, uint count)
{
    float3 p = (float3)(q->x, q->y, q->z);
    for (int i = first; i < first + (int)count; ++i) {
        float u, v;
        LEAF_CORNERS(t, triangles, i);
        float d2 = closest_on_triangle(t, p, &u, &v);
        if (d2 < s->reach || (d2 <= s->reach && (s->index < 0 || i < s->index))) {
            s->index = i;
            s->reach = d2;
            s->u = u;
            s->v = v;
        }
    }
    return false;
}

#endif /* POINT_H */
