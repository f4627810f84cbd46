/* Point queries: the closest point of the scene, the generalized winding
 * number (Jacobson, Kavan & Sorkine-Hornung 2013), and from both the signed
 * distance.  Two visitors of the one walk of the wide tree (walk.h) on the
 * point path (point.h), one query point per work-item.
 *
 * Kernels
 *   closest_points    nearest surface point within max_distance -> its
 *                     distance, ids, u, v, unit normal and point
 *   winding_numbers   w = (sum of solid angles) / 4 pi, with Barill et al.
 *                     2018's far field (dipoles from dipoles.cl)
 *   signed_distances  the distance to the closest point, negative where
 *                     |w| >= 0.5 (inside, whichever way the faces turn)
 *
 * Compile-time parameters (-D): STACK_SIZE and PREFETCH as traverse.cl's.
 */
#include "point.h"
#include "stack.h"

/* Closest point: the reach is the best squared distance so far, so the
 * walk visits the nearer boxes first and drops those beyond it. */
#define QUERY closest
#define QUERY_PATH _point
#define QUERY_HIT(s, i, hit, t, u, v) false
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_LEAF(s, r, first, count) closest_leaf(s, r, triangles, first, count)
#define QUERY_PARAMS
#define QUERY_ARGS
#include "walk.h"

/* Winding number: children far enough count by their dipole, the rest are
 * descended (reach +inf), and leaves add their exact solid angles. */
#define QUERY winding
#define QUERY_PATH _point
#define QUERY_HIT(s, i, hit, t, u, v) false
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_CHILDREN(r, n, s, entry) children_winding(r, n, dipoles + (n - nodes), s, entry)
#define QUERY_LEAF(s, r, first, count) winding_leaf(s, r, triangles, first, count)
#define QUERY_PARAMS , __global const WideDipoles* dipoles
#define QUERY_ARGS , dipoles
#include "walk.h"

#define POINT_KERNEL __kernel __attribute__((LANES_HINT))

/* Point i of points[0, count); false past the last. */
TRAVERSAL_INLINE bool load_point(__global const float* points, uint i, uint count, PointData* q)
{
    if (i >= count)
        return false;
    q->x = points[3 * i];
    q->y = points[3 * i + 1];
    q->z = points[3 * i + 2];
    return true;
}

/* The closest point's walk from the start: nothing found, reach `reach`. */
TRAVERSAL_INLINE bool closest_walk(const PointData* q, __global const WideNode* nodes,
                                   __global const Triangle* triangles, float reach,
                                   Found_point* s)
{
    Found_point start = {-1, reach, 0.0f, 0.0f, 0.0f};
    *s = start;
    return walk_closest_point(q, nodes, triangles, s);
}

/* The winding number's walk: 4 pi w in s->solid_angle. */
TRAVERSAL_INLINE bool winding_walk(const PointData* q, __global const WideNode* nodes,
                                   __global const Triangle* triangles,
                                   __global const WideDipoles* dipoles, Found_point* s)
{
    Found_point start = {-1, INFINITY, 0.0f, 0.0f, 0.0f};
    *s = start;
    return walk_winding_point(q, nodes, triangles, s, dipoles);
}

#define WINDING(s) ((s).solid_angle * (float)(0.25 / M_PI))

/* Closest point of points[0, count) within sqrt(max_d2): distance (inf if
 * none), ids (-1), u, v, unit normal (0) and the point (NaN). */
POINT_KERNEL void closest_points(__global const WideNode* nodes,
        __global const Triangle* triangles, __global const TriangleRef* refs,
        __global const float* points, const float max_d2, __global float* distance_out,
        __global int* geom_out, __global int* prim_out, __global float* u_out,
        __global float* v_out, __global float* normal_out, __global float* points_out,
        __global int* overflow, const uint count)
{
    uint i = get_global_id(0);
    PointData q;
    if (!load_point(points, i, count, &q))
        return;
    Found_point s;
    if (closest_walk(&q, nodes, triangles, max_d2, &s))
        overflow[0] = 1;
    bool found = s.index >= 0;
    float3 normal = (float3)(0.0f), at = (float3)(NAN);
    if (found) {
        __global const Triangle* t = triangles + s.index;
        normal = unit_normal(t);
        float3 a = LOAD_XYZ(t->v0);
        at = a + s.u * (LOAD_XYZ(t->v1) - a) + s.v * (LOAD_XYZ(t->v2) - a);
    }
    distance_out[i] = found ? SQUARE_ROOT(s.reach) : INFINITY;
    geom_out[i] = found ? refs[s.index].geom_id : -1;
    prim_out[i] = found ? refs[s.index].prim_id : -1;
    u_out[i] = found ? s.u : 0.0f;
    v_out[i] = found ? s.v : 0.0f;
    float n[3] = {normal.x, normal.y, normal.z}, p[3] = {at.x, at.y, at.z};
    for (uint k = 0; k < 3; ++k) {
        normal_out[3 * i + k] = n[k];
        points_out[3 * i + k] = p[k];
    }
}

/* The winding number of points[0, count). */
POINT_KERNEL void winding_numbers(__global const WideNode* nodes,
        __global const Triangle* triangles, __global const WideDipoles* dipoles,
        __global const float* points, __global float* winding_out, __global int* overflow,
        const uint count)
{
    uint i = get_global_id(0);
    PointData q;
    if (!load_point(points, i, count, &q))
        return;
    Found_point s;
    if (winding_walk(&q, nodes, triangles, dipoles, &s))
        overflow[0] = 1;
    winding_out[i] = WINDING(s);
}

/* The signed distance of points[0, count) (in the frame's units; negative
 * where |w| >= 0.5), and
 * their winding numbers. */
POINT_KERNEL void signed_distances(__global const WideNode* nodes,
        __global const Triangle* triangles, __global const WideDipoles* dipoles,
        __global const float* points, __global float* distance_out,
        __global float* winding_out, __global int* overflow, const uint count)
{
    uint i = get_global_id(0);
    PointData q;
    if (!load_point(points, i, count, &q))
        return;
    Found_point s;
    bool out_of_stack = closest_walk(&q, nodes, triangles, INFINITY, &s);
    float distance = s.index >= 0 ? SQUARE_ROOT(s.reach) : INFINITY;
    out_of_stack |= winding_walk(&q, nodes, triangles, dipoles, &s);
    float w = WINDING(s);
    if (out_of_stack)
        overflow[0] = 1;
    distance_out[i] = fabs(w) >= 0.5f ? -distance : distance;
    winding_out[i] = w;
}
