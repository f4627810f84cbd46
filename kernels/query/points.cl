/* Point queries: the closest point of the scene, the generalized winding
 * number (Jacobson, Kavan & Sorkine-Hornung 2013), and from both the signed
 * distance.  Two visitors of the one walk of the wide tree
 * (query/walk/walk.h) on the point path (query/points/point.h), one query
 * point per work-item; on flat scenes with PACKET_SIZE > 1 a packet of
 * points per work-item (query/points/point_packet.h).  A launch's points
 * and results are the arrays' first `count` slots, or the slots the host
 * lists (QUERY_POINTS).
 *
 * Kernels
 *   closest_points    nearest surface point within max_distance -> its
 *                     distance, ids, u, v, unit normal and point
 *   winding_numbers   w = (sum of solid angles) / 4 pi, with Barill et al.
 *                     2018's far field (dipoles from build/dipoles.cl)
 *   signed_distances  the distance to the closest point, negative where
 *                     |w| >= 0.5 (inside, whichever way the faces turn)
 *
 * Two-level scenes (INSTANCES): the top tree's leaves
 * (query/walk/instance_leaf.h) walk each instance's mesh tree with the
 * point mapped into its frame (closest_instance, winding_instance, with
 * query/points/instance.h).  Point queries take no mask: they see every
 * instance.
 *
 * Compile-time parameters (-D): STACK_SIZE, PACKET_SIZE, PREFETCH and
 * INSTANCES as rays.cl's (instanced scenes walk one point per work-item
 * whatever PACKET_SIZE).
 */
#include "core/portable.h"
#include "query/normals.h"
#include "query/points/point.h"
#include "query/points/instance.h"

/* Closest point: the reach is the best squared distance so far, so the
 * walk visits the nearer boxes first and drops those beyond it. */
#define QUERY closest
#define QUERY_PATH _point
#define QUERY_LEAF(s, r, first, count) closest_leaf(s, r, triangles, first, count)
#include "query/walk/walk.h"

/* The same walk for a packet of points (point_packet.h, which also has the
 * packet's winding walk): flat scenes, where the kernel variant has packets
 * (PACKET_SIZE > 1). */
#if PACKET_SIZE > 1 && !defined(INSTANCES)
#define POINT_PACKETS
#include "query/points/point_packet.h"
#define QUERY closest
#define QUERY_PATH _points
#define QUERY_CHILDREN(r, n, s, entry) children_points(r, n, s, entry)
#define QUERY_LEAF(s, r, first, count) closest_leaf_points(s, r, triangles, first, count)
#include "query/walk/walk.h"
#endif

/* Winding number: children far enough count by their dipole, the rest are
 * descended (reach +inf), and leaves add their exact solid angles. */
#define QUERY winding
#define QUERY_PATH _point
#define QUERY_UNORDERED
#define QUERY_CHILDREN(r, n, s, entry) children_winding(r, n, dipoles + (n - nodes), s, entry)
#define QUERY_LEAF(s, r, first, count) winding_leaf(s, r, triangles, first, count)
#define QUERY_PARAMS , __global const WideDipoles* dipoles
#define QUERY_ARGS , dipoles
#include "query/walk/walk.h"

/* The winding number's walk of one tree: 4 pi w in s->solid_angle. */
TRAVERSAL_INLINE bool winding_walk(const PointData* q, __global const WideNode* nodes,
                                   __global const Leaf* triangles,
                                   __global const WideDipoles* dipoles, Found_point* s)
{
    start_point(s, INFINITY);
    return walk_winding_point(q, nodes, triangles, s, dipoles);
}

#ifndef INSTANCES
/* The scene a point kernel reads, as its first parameters: a flat scene's
 * one tree.  (Winding kernels also take its dipoles.)  Macros: parameter
 * lists (a kernel cannot take a struct of pointers). */
#define POINT_SCENE_PARAMS                                                              \
    __global const WideNode *nodes, __global const Leaf *triangles,                      \
        __global const TriangleRef *refs
#define POINT_SCENE_ARGS nodes, triangles, refs

/* The closest point's walk from the start: nothing found, reach `reach`;
 * true if the stack ran out. */
TRAVERSAL_INLINE bool closest_search(const PointData* q, float reach, Found_point* s,
                                     POINT_SCENE_PARAMS)
{
    start_point(s, reach);
    return walk_closest_point(q, nodes, triangles, s);
}

TRAVERSAL_INLINE bool winding_search(const PointData* q, Found_point* s, POINT_SCENE_PARAMS,
                                     __global const WideDipoles* dipoles)
{
    return winding_walk(q, nodes, triangles, dipoles, s);
}

/* The closest triangle's corners and ids (no instance: -1). */
TRAVERSAL_INLINE void closest_triangle(const Found_point* s, POINT_SCENE_PARAMS, float3* a,
                                       float3* b, float3* c, int* geom, int* prim,
                                       int* instance)
{
    LEAF_CORNERS(t, triangles, s->index);
    *a = LOAD_XYZ(t->v0);
    *b = LOAD_XYZ(t->v1);
    *c = LOAD_XYZ(t->v2);
    *geom = refs[s->index].geom_id;
    *prim = refs[s->index].prim_id;
    *instance = -1;
}

#else /* INSTANCES */

/* An instance's mesh, walked for the closest point in the top frame
 * (query/points/instance.h). */
#define QUERY closest_mesh
#define QUERY_PATH _point
#define QUERY_CHILDREN(r, n, s, entry) children_mapped(r, n, s, entry, frame)
#define QUERY_LEAF(s, r, first, count) \
    closest_mapped_leaf(s, triangles, first, count, in, frame, owner)
#define QUERY_PARAMS , __global const Instance* in, const MeshFrame* frame, int owner
#define QUERY_ARGS , in, frame, owner
#include "query/walk/walk.h"

/* Closest point, instance `in` (number id) of a top tree's leaf: its mesh
 * walked with the point in its frame and the reach the best so far allows
 * there; the top walk then goes on with the top frame's reach. */
TRAVERSAL_INLINE bool closest_instance(Found_point* s, const PointData* q,
                                       __global const Instance* in, int id INSTANCE_PARAMS)
{
    PointData mapped;
    mesh_point(&mapped, in, q);
    MeshFrame frame;
    mesh_frame(&frame, in, q);
    s->reach = mesh_reach(s->best, &frame);
    *mesh_overflow |= walk_closest_mesh_point(&mapped, MESH_TREE(in), s, in, &frame, id);
    s->reach = s->best;
    return false;
}

#define QUERY closest
#define QUERY_PATH _point
#define QUERY_INSTANCE closest_instance
#include "query/walk/walk.h"

/* Winding number: the sum over the instances of sign(det) times the mesh's
 * own winding number at the mapped point.  A closed surface's winding
 * number is a degree, kept by an orientation-preserving homeomorphism and
 * negated by a reversing one, so for closed meshes this is the flattened
 * scene's w (up to the far field's approximation); on an open mesh the
 * solid angles of its parts are not kept by a non-similarity map, and each
 * instance contributes its mesh's own w (docs/queries.md).  The mesh walks
 * use their own frame's dipoles; every instance is visited (reach +inf at
 * the top). */
TRAVERSAL_INLINE bool winding_instance(Found_point* s, const PointData* q,
                                       __global const Instance* in, int id INSTANCE_PARAMS,
                                       __global const WideDipoles* dipoles)
{
    PointData mapped;
    mesh_point(&mapped, in, q);
    Found_point mesh;
    *mesh_overflow |= winding_walk(&mapped, MESH_TREE(in), dipoles + in->node_base, &mesh);
    s->solid_angle += in->normal_sign * mesh.solid_angle;
    return false;
}

#define QUERY winding
#define QUERY_PATH _point
#define QUERY_UNORDERED
#define QUERY_INSTANCE winding_instance
#define QUERY_PARAMS , __global const WideDipoles* dipoles
#define QUERY_ARGS , dipoles
#include "query/walk/walk.h"

/* A two-level scene: the top tree over the instances, the instances and
 * the meshes' trees one after another (rays/instance.h's SCENE_PARAMS
 * without the rays' masks). */
#define POINT_SCENE_PARAMS                                                              \
    __global const WideNode *top_nodes, __global const Leaf *top_triangles,              \
        __global const TriangleRef *top_refs, __global const Instance *instances,        \
        __global const WideNode *nodes, __global const Leaf *triangles,                  \
        __global const TriangleRef *refs
#define POINT_SCENE_ARGS top_nodes, top_triangles, top_refs, instances, nodes, triangles, refs

TRAVERSAL_INLINE bool closest_search(const PointData* q, float reach, Found_point* s,
                                     POINT_SCENE_PARAMS)
{
    start_point(s, reach);
    bool nested = false;
    bool out_of_stack = walk_closest_top_point(q, top_nodes, top_triangles, s,
                                               TOP_ARGS(&nested));
    return out_of_stack || nested;
}

TRAVERSAL_INLINE bool winding_search(const PointData* q, Found_point* s, POINT_SCENE_PARAMS,
                                     __global const WideDipoles* dipoles)
{
    start_point(s, INFINITY);
    bool nested = false;
    bool out_of_stack = walk_winding_top_point(q, top_nodes, top_triangles, s,
                                               TOP_ARGS(&nested), dipoles);
    return out_of_stack || nested;
}

/* The closest triangle's corners in the top frame, and its ids. */
TRAVERSAL_INLINE void closest_triangle(const Found_point* s, POINT_SCENE_PARAMS, float3* a,
                                       float3* b, float3* c, int* geom, int* prim,
                                       int* instance)
{
    __global const Instance* in = instances + s->instance;
    int j = in->triangle_base + s->index;
    LEAF_CORNERS(t, triangles, j);
    mapped_corners(in, t, a, b, c);
    *geom = in->mesh;
    *prim = refs[j].prim_id;
    *instance = s->instance;
}
#endif /* INSTANCES */

/* The closest-point results at slot i from a walk's state s. */
#define CLOSEST_OUTPUTS                                                                 \
    __global float *distance_out, __global int *geom_out, __global int *prim_out,         \
        __global int *instance_out, __global float *u_out, __global float *v_out,         \
        __global float *normal_out, __global float *points_out
TRAVERSAL_INLINE void store_closest(const Found_point* s, uint i, POINT_SCENE_PARAMS,
                                    CLOSEST_OUTPUTS)
{
    bool found = s->index >= 0;
    float3 normal = (float3)(0.0f), at = (float3)(NAN);
    int geom = -1, prim = -1, instance = -1;
    if (found) {
        float3 a, b, c;
        closest_triangle(s, POINT_SCENE_ARGS, &a, &b, &c, &geom, &prim, &instance);
        normal = corners_normal(a, b, c);
        at = a + s->u * (b - a) + s->v * (c - a);
    }
    distance_out[i] = found ? SQRT(s->reach) : INFINITY;
    geom_out[i] = geom;
    prim_out[i] = prim;
    instance_out[i] = instance;
    u_out[i] = found ? s->u : 0.0f;
    v_out[i] = found ? s->v : 0.0f;
    float n[3] = {normal.x, normal.y, normal.z}, p[3] = {at.x, at.y, at.z};
    for (uint k = 0; k < 3; ++k) {
        normal_out[3 * (size_t)i + k] = n[k];
        points_out[3 * (size_t)i + k] = p[k];
    }
}

/* The winding number from a walk's sum: a macro, for a point's and a
 * packet's lanes' alike. */
#define WINDING(s) ((s).solid_angle * (0.25f * M_1_PI_F))

/* The points a work-item takes: one, or (POINT_PACKETS) a packet. */
#ifdef POINT_PACKETS
#define POINTS_PER_ITEM PACKET_SIZE
typedef PointPacket ItemQuery;
#else
#define POINTS_PER_ITEM 1
typedef PointData ItemQuery;
#endif

/* The arguments that say which points a launch queries: `count` of them,
 * query i's point at slot i of points and its results at slot i of each
 * output; or, where `indexed` (the host hands whole arrays, points in any
 * order), at slot slots[i]. */
#define QUERY_POINTS                                                                    \
    __global const float *points, __global const uint *slots, const uint indexed,        \
        const uint count

/* The work-item's points (q) and their slots (at; lanes past the last
 * repeat it); how many exist (0 past the end: then nothing is loaded). */
TRAVERSAL_INLINE uint load_points(QUERY_POINTS, uint* at, ItemQuery* q)
{
    uint first = get_global_id(0) * POINTS_PER_ITEM;
    if (first >= count)
        return 0;
    uint used = LESSER((uint)POINTS_PER_ITEM, count - first);
    for (uint l = 0; l < POINTS_PER_ITEM; ++l) {
        uint i = first + LESSER(l, used - 1u);
        at[l] = indexed ? slots[i] : i;
    }
#ifdef POINT_PACKETS
    load_point_packet(points, at, q);
#else
    q->x = points[3 * (size_t)at[0]];
    q->y = points[3 * (size_t)at[0] + 1];
    q->z = points[3 * (size_t)at[0] + 2];
#endif
    return used;
}

/* The closest walks of points q from the squared reach `reach`: their
 * states in lanes (a packet's as Found_point each); overflow[0] set if the
 * stack ran out. */
TRAVERSAL_INLINE void closest_walks(const ItemQuery* q, float reach, POINT_SCENE_PARAMS,
                                    Found_point* lanes, __global int* overflow)
{
#ifdef POINT_PACKETS
    Found_points s;
    start_points(&s, reach);
    bool out_of_stack = walk_closest_points(q, nodes, triangles, &s);
    int index[PACKET_SIZE];
    float best[PACKET_SIZE], u[PACKET_SIZE], v[PACKET_SIZE];
    vstore_packet(s.index, 0, index);
    vstore_packet(s.best, 0, best);
    vstore_packet(s.u, 0, u);
    vstore_packet(s.v, 0, v);
    for (uint l = 0; l < PACKET_SIZE; ++l) {
        Found_point one;
        start_point(&one, best[l]);
        one.index = index[l];
        one.u = u[l];
        one.v = v[l];
        lanes[l] = one;
    }
#else
    bool out_of_stack = closest_search(q, reach, lanes, POINT_SCENE_ARGS);
#endif
    if (out_of_stack)
        overflow[0] = 1;
}

/* The winding walks of points q: their winding numbers in w; overflow[0]
 * set if the stack ran out. */
TRAVERSAL_INLINE void winding_walks(const ItemQuery* q, POINT_SCENE_PARAMS,
                                    __global const WideDipoles* dipoles, float* w,
                                    __global int* overflow)
{
#ifdef POINT_PACKETS
    Found_points s;
    start_points(&s, INFINITY);
    bool out_of_stack = walk_winding_points(q, nodes, triangles, &s, dipoles);
    vstore_packet(WINDING(s), 0, w);
#else
    Found_point s;
    bool out_of_stack = winding_search(q, &s, POINT_SCENE_ARGS, dipoles);
    w[0] = WINDING(s);
#endif
    if (out_of_stack)
        overflow[0] = 1;
}

/* The work-item's points (load_points) and their closest walks
 * (closest_walks); how many exist (0: none, nothing walked). */
TRAVERSAL_INLINE uint closest_item(QUERY_POINTS, float reach, POINT_SCENE_PARAMS,
                                   __global int* overflow, uint* at, ItemQuery* q,
                                   Found_point* lanes)
{
    uint used = load_points(points, slots, indexed, count, at, q);
    if (used != 0)
        closest_walks(q, reach, POINT_SCENE_ARGS, lanes, overflow);
    return used;
}

/* Closest point of each query within sqrt(max_d2): distance (inf if
 * none), ids (-1), u, v, unit normal (0) and the point (NaN). */
TRAVERSAL_KERNEL void closest_points(POINT_SCENE_PARAMS, QUERY_POINTS, const float max_d2,
                                     CLOSEST_OUTPUTS, __global int* overflow)
{
    uint at[POINTS_PER_ITEM];
    ItemQuery q;
    Found_point lanes[POINTS_PER_ITEM];
    uint used = closest_item(points, slots, indexed, count, max_d2, POINT_SCENE_ARGS, overflow,
                             at, &q, lanes);
    for (uint l = 0; l < used; ++l)
        store_closest(lanes + l, at[l], POINT_SCENE_ARGS, distance_out, geom_out, prim_out,
                      instance_out, u_out, v_out, normal_out, points_out);
}

/* The winding number of each query. */
TRAVERSAL_KERNEL void winding_numbers(POINT_SCENE_PARAMS, __global const WideDipoles* dipoles,
                                      QUERY_POINTS, __global float* winding_out,
                                      __global int* overflow)
{
    uint at[POINTS_PER_ITEM];
    ItemQuery q;
    uint used = load_points(points, slots, indexed, count, at, &q);
    if (used == 0)
        return;
    float w[POINTS_PER_ITEM];
    winding_walks(&q, POINT_SCENE_ARGS, dipoles, w, overflow);
    for (uint l = 0; l < used; ++l)
        winding_out[at[l]] = w[l];
}

/* The signed distance of each query (in the frame's units; negative where
 * |w| >= 0.5), and its winding number. */
TRAVERSAL_KERNEL void signed_distances(POINT_SCENE_PARAMS, __global const WideDipoles* dipoles,
                                       QUERY_POINTS, __global float* distance_out,
                                       __global float* winding_out, __global int* overflow)
{
    uint at[POINTS_PER_ITEM];
    ItemQuery q;
    Found_point lanes[POINTS_PER_ITEM];
    uint used = closest_item(points, slots, indexed, count, INFINITY, POINT_SCENE_ARGS, overflow,
                             at, &q, lanes);
    if (used == 0)
        return;
    float w[POINTS_PER_ITEM];
    winding_walks(&q, POINT_SCENE_ARGS, dipoles, w, overflow);
    for (uint l = 0; l < used; ++l) {
        float distance = lanes[l].index >= 0 ? SQRT(lanes[l].reach) : INFINITY;
        distance_out[at[l]] = fabs(w[l]) >= 0.5f ? -distance : distance;
        winding_out[at[l]] = w[l];
    }
}
