/* Point queries: the closest point of the scene, the generalized winding
 * number (Jacobson, Kavan & Sorkine-Hornung 2013), and from both the signed
 * distance.  Two visitors of the one walk of the wide tree (walk.h) on the
 * point path (point.h), one query point per work-item; on flat scenes with
 * PACKET_SIZE > 1 a packet of points per work-item (point_packet.h).  A
 * launch's points and results are the arrays' first `count` slots, or the
 * slots the host lists (QUERY_POINTS).
 *
 * Kernels
 *   closest_points    nearest surface point within max_distance -> its
 *                     distance, ids, u, v, unit normal and point
 *   winding_numbers   w = (sum of solid angles) / 4 pi, with Barill et al.
 *                     2018's far field (dipoles from dipoles.cl)
 *   signed_distances  the distance to the closest point, negative where
 *                     |w| >= 0.5 (inside, whichever way the faces turn)
 *
 * Two-level scenes (INSTANCES): the top tree's leaf visitors walk each
 * instance's mesh tree with the point mapped into its frame (below).  Point
 * queries take no mask: they see every instance.
 *
 * Compile-time parameters (-D): STACK_SIZE, PACKET_SIZE, PREFETCH and
 * INSTANCES as traverse.cl's (instanced scenes walk one point per
 * work-item whatever PACKET_SIZE).
 */
#include "query/point.h"
#include "query/stack.h"
#include "query/two_level.h"

/* Closest point: the reach is the best squared distance so far, so the
 * walk visits the nearer boxes first and drops those beyond it. */
#define QUERY closest
#define QUERY_PATH _point
#define QUERY_HIT(s, i, hit, t, u, v) false
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_LEAF(s, r, first, count) closest_leaf(s, r, triangles, first, count)
#define QUERY_PARAMS
#define QUERY_ARGS
#include "query/walk.h"

/* The same walk for a packet of points (point_packet.h, which also has the
 * packet's winding walk): flat scenes, where the kernel variant has packets
 * (PACKET_SIZE > 1). */
#if PACKET_SIZE > 1 && !defined(INSTANCES)
#define POINT_PACKETS
#include "query/point_packet.h"
#define QUERY closest
#define QUERY_PATH _points
#define QUERY_HIT(s, i, hit, t, u, v) false
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_CHILDREN(r, n, s, entry) children_points(r, n, s, entry)
#define QUERY_LEAF(s, r, first, count) closest_leaf_points(s, r, triangles, first, count)
#define QUERY_PARAMS
#define QUERY_ARGS
#include "query/walk.h"
#endif

/* Winding number: children far enough count by their dipole, the rest are
 * descended (reach +inf), and leaves add their exact solid angles. */
#define QUERY winding
#define QUERY_PATH _point
#define QUERY_UNORDERED
#define QUERY_HIT(s, i, hit, t, u, v) false
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_CHILDREN(r, n, s, entry) children_winding(r, n, dipoles + (n - nodes), s, entry)
#define QUERY_LEAF(s, r, first, count) winding_leaf(s, r, triangles, first, count)
#define QUERY_PARAMS , __global const WideDipoles* dipoles
#define QUERY_ARGS , dipoles
#include "query/walk.h"

#define POINT_KERNEL __kernel __attribute__((LANES_HINT))

/* The point at slot `at` of points. */
TRAVERSAL_INLINE void load_point(__global const float* points, uint at, PointData* q)
{
    q->x = points[3 * (size_t)at];
    q->y = points[3 * (size_t)at + 1];
    q->z = points[3 * (size_t)at + 2];
}

/* The winding number's walk of one tree: 4 pi w in s->solid_angle. */
TRAVERSAL_INLINE bool winding_walk(const PointData* q, __global const WideNode* nodes,
                                   __global const Triangle* triangles,
                                   __global const WideDipoles* dipoles, Found_point* s)
{
    Found_point start = POINT_START(INFINITY);
    *s = start;
    return walk_winding_point(q, nodes, triangles, s, dipoles);
}

#ifndef INSTANCES
/* The scene a point kernel reads, as its first parameters: a flat scene's
 * one tree.  (Winding kernels also take its dipoles.) */
#define POINT_SCENE_PARAMS                                                              \
    __global const WideNode *nodes, __global const Triangle *triangles,                  \
        __global const TriangleRef *refs
#define POINT_SCENE_ARGS nodes, triangles, refs

/* The closest point's walk from the start: nothing found, reach `reach`;
 * true if the stack ran out. */
TRAVERSAL_INLINE bool closest_search(const PointData* q, float reach, Found_point* s,
                                     POINT_SCENE_PARAMS)
{
    Found_point start = POINT_START(reach);
    *s = start;
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
    __global const Triangle* t = triangles + s->index;
    *a = LOAD_XYZ(t->v0);
    *b = LOAD_XYZ(t->v1);
    *c = LOAD_XYZ(t->v2);
    *geom = refs[s->index].geom_id;
    *prim = refs[s->index].prim_id;
    *instance = -1;
}

#else /* INSTANCES */

/* Closest point.  An affine map keeps no distance unless it is a
 * similarity, so the distance is measured in the top (world) frame: a leaf
 * maps its triangles there (to_world) and measures Ericson's exact
 * point-triangle distance to the query point as given.  The mesh's tree is
 * walked with the point mapped into its frame (to_mesh), and a child box is
 * dropped by the larger of two lower bounds on its world distance (either
 * alone can be far from tight):
 *   - the mesh frame's box distance d times s, the least singular value of
 *     the map's linear part A: |A x - A y| >= s |x - y|.  Exact for a
 *     similarity, but a stretched map's s makes the ball it leaves to
 *     search larger than the nearest distance by the map's condition
 *     number, whatever the box's size;
 *   - the world distance to the box's world box (Arvo 1990, "Transforming
 *     Axis-Aligned Bounding Boxes", as instances.py's world_boxes), loose
 *     by at most the box's own size, which shrinks down the tree.
 * Both are compared in the mesh frame's units (times reach_scale = 1 / s^2)
 * with the reach the best so far gives there, padded by REACH_PAD (the
 * rounding of distances and of reach_scale) and by the slack of the mapped
 * point (MeshFrame), and the world boxes by ARVO_PAD: rounding never
 * drops a nearer triangle.  The walks share one state, whose reach is in
 * the frame of the tree being walked and whose `best` is always the top
 * frame's. */
#define REACH_PAD (1.0f + 0x1p-20f)
#define MAP_SLACK 0x1p-20f
#define ARVO_PAD 0x1p-20f

/* An instance as its mesh's closest-point walk uses it: the query point in
 * the top frame, to_world (linear part A, offset b, and their magnitudes),
 * reach_scale and the mapped point's slack (a bound on its distance from
 * the exact image: the mapped coordinates' rounding, in double the final
 * one, in float a few, each within 2^-24 of the sum of its terms'
 * magnitudes, stays below MAP_SLACK times that sum). */
typedef struct {
    PointData world;
    float a[9], abs_a[9], b[3], abs_b[3];
    float reach_scale, slack;
} MeshFrame;

/* The point q in the instance's mesh frame. */
TRAVERSAL_INLINE void mesh_point(PointData* out, __global const Instance* in, const PointData* q)
{
    float3 m = map_point(in->to_mesh, (float3)(q->x, q->y, q->z));
    out->x = m.x;
    out->y = m.y;
    out->z = m.z;
}

/* The instance's MeshFrame for the query point q. */
TRAVERSAL_INLINE void mesh_frame(MeshFrame* f, __global const Instance* in, const PointData* q)
{
    __global const float* t = in->to_mesh;
    float size = 0.0f;
    for (int row = 0; row < 12; row += 4)
        size += ((ABS_FLOAT(t[row] * q->x) + ABS_FLOAT(t[row + 1] * q->y))
                 + ABS_FLOAT(t[row + 2] * q->z)) + ABS_FLOAT(t[row + 3]);
    f->slack = size * MAP_SLACK;
    f->world = *q;
    f->reach_scale = in->reach_scale;
    for (int row = 0; row < 3; ++row) {
        for (int k = 0; k < 3; ++k) {
            f->a[3 * row + k] = in->to_world[4 * row + k];
            f->abs_a[3 * row + k] = ABS_FLOAT(in->to_world[4 * row + k]);
        }
        f->b[row] = in->to_world[4 * row + 3];
        f->abs_b[row] = ABS_FLOAT(in->to_world[4 * row + 3]);
    }
}

/* The squared mesh-frame reach for the top frame's squared distance `best`. */
TRAVERSAL_INLINE float mesh_reach(float best, const MeshFrame* f)
{
    /* best 0 stays 0 where reach_scale is inf (an instance scaled below
     * about 1e-19), not 0 * inf = NaN, which would skip the instance */
    float r = SQUARE_ROOT(best > 0.0f ? best * f->reach_scale : 0.0f) * REACH_PAD + f->slack;
    return r * r;
}

/* The mesh walk's node test: per child, the larger of the two bounds (in
 * the mesh frame's units) as its entry, and the children within the reach.
 * The world box of a child is its centre c mapped and its half extent e
 * under |A|; ARVO_PAD times the magnitudes the mapping summed covers its
 * rounding.  An unused slot's empty box gives NaN there, which GROW_HI
 * ignores, and is left out by its lo <= hi test. */
#define NODE_ROW(row) LOAD_ROW(float_lanes, node->row)
#define BOX_GAP(lo, hi, q) GROW_HI(GROW_HI((float_lanes)(0.0f), NODE_ROW(lo) - (q)), (q) - NODE_ROW(hi))
TRAVERSAL_INLINE uint children_mapped(const PointData* q, __global const WideNode* node,
                                      const Found_point* s, ChildEntries* entry,
                                      const MeshFrame* f)
{
    float_lanes dx = BOX_GAP(lo_x, hi_x, q->x);
    float_lanes dy = BOX_GAP(lo_y, hi_y, q->y);
    float_lanes dz = BOX_GAP(lo_z, hi_z, q->z);
    float_lanes near = (dx * dx + dy * dy) + dz * dz;
    float_lanes c[3] = {(NODE_ROW(lo_x) + NODE_ROW(hi_x)) * 0.5f,
                        (NODE_ROW(lo_y) + NODE_ROW(hi_y)) * 0.5f,
                        (NODE_ROW(lo_z) + NODE_ROW(hi_z)) * 0.5f};
    float_lanes e[3] = {(NODE_ROW(hi_x) - NODE_ROW(lo_x)) * 0.5f,
                        (NODE_ROW(hi_y) - NODE_ROW(lo_y)) * 0.5f,
                        (NODE_ROW(hi_z) - NODE_ROW(lo_z)) * 0.5f};
    float p[3] = {f->world.x, f->world.y, f->world.z};
    float_lanes world = (float_lanes)(0.0f);
    for (int row = 0; row < 3; ++row) {
        const float* a = f->a + 3 * row;
        const float* m = f->abs_a + 3 * row;
        float_lanes centre = ((a[0] * c[0] + a[1] * c[1]) + a[2] * c[2]) + f->b[row];
        float_lanes extent = (m[0] * e[0] + m[1] * e[1]) + m[2] * e[2];
        float_lanes size = ((m[0] * ABS_LANES(c[0]) + m[1] * ABS_LANES(c[1]))
                            + m[2] * ABS_LANES(c[2])) + f->abs_b[row] + extent;
        float_lanes gap = GROW_HI((float_lanes)(0.0f),
                                  ABS_LANES(p[row] - centre) - extent - size * ARVO_PAD);
        world += gap * gap;
    }
    entry->lanes = GROW_HI(near, world * f->reach_scale);
    return lane_mask((entry->lanes <= (float_lanes)(s->reach))
                     & (NODE_ROW(lo_x) <= NODE_ROW(hi_x)));
}
#undef BOX_GAP
#undef NODE_ROW

/* Triangle t of the instance's mesh, in the top frame. */
TRAVERSAL_INLINE void mapped_corners(__global const Instance* in, __global const Triangle* t,
                                     float3* a, float3* b, float3* c)
{
    *a = map_point(in->to_world, LOAD_XYZ(t->v0));
    *b = map_point(in->to_world, LOAD_XYZ(t->v1));
    *c = map_point(in->to_world, LOAD_XYZ(t->v2));
}

/* A mesh walk's leaf: each triangle's top-frame distance to the query
 * point; a nearer one (at the reach only while there is none, as
 * closest_leaf) becomes the best, of instance `owner`, and shrinks the
 * mesh-frame reach. */
TRAVERSAL_INLINE bool closest_mapped_leaf(Found_point* s, __global const Triangle* triangles,
                                          int first, uint count, __global const Instance* in,
                                          const MeshFrame* f, int owner)
{
    float3 p = (float3)(f->world.x, f->world.y, f->world.z);
    for (int i = first; i < first + (int)count; ++i) {
        float3 a, b, c;
        mapped_corners(in, triangles + i, &a, &b, &c);
        float u, v;
        float d2 = closest_on_corners(a, b, c, p, &u, &v);
        if (d2 < s->best || (s->index < 0 && d2 <= s->best)) {
            s->index = i;
            s->best = d2;
            s->u = u;
            s->v = v;
            s->instance = owner;
            s->reach = mesh_reach(d2, f);
        }
    }
    return false;
}

#define QUERY closest_mesh
#define QUERY_PATH _point
#define QUERY_HIT(s, i, hit, t, u, v) false
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_CHILDREN(r, n, s, entry) children_mapped(r, n, s, entry, frame)
#define QUERY_LEAF(s, r, first, count) \
    closest_mapped_leaf(s, triangles, first, count, in, frame, owner)
#define QUERY_PARAMS , __global const Instance* in, const MeshFrame* frame, int owner
#define QUERY_ARGS , in, frame, owner
#include "query/walk.h"

/* The top tree's leaves: each instance's mesh walked with the point in its
 * frame and the reach the best so far allows there; the top walk then goes
 * on with the top frame's reach. */
TRAVERSAL_INLINE bool instances_closest(Found_point* s, const PointData* q, int first,
                                        uint count INSTANCE_PARAMS)
{
    for (uint i = (uint)first; i < (uint)first + count; ++i) {
        INSTANCE_AT(i);
        PointData mapped;
        mesh_point(&mapped, in, q);
        MeshFrame frame;
        mesh_frame(&frame, in, q);
        s->reach = mesh_reach(s->best, &frame);
        *mesh_overflow |= walk_closest_mesh_point(&mapped, MESH_TREE(in), s, in, &frame,
                                                  top_refs[i].prim_id);
        s->reach = s->best;
    }
    return false;
}

#define QUERY closest_top
#define QUERY_PATH _point
#define QUERY_HIT(s, i, hit, t, u, v) false
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_LEAF(s, r, first, count) instances_closest(s, r, first, count INSTANCE_ARGS)
#define QUERY_PARAMS INSTANCE_PARAMS
#define QUERY_ARGS INSTANCE_ARGS
#include "query/walk.h"

/* Winding number: the sum over the instances of sign(det) times the mesh's
 * own winding number at the mapped point.  A closed surface's winding
 * number is a degree, kept by an orientation-preserving homeomorphism and
 * negated by a reversing one, so for closed meshes this is the flattened
 * scene's w (up to the far field's approximation); on an open mesh the
 * solid angles of its parts are not kept by a non-similarity map, and each
 * instance contributes its mesh's own w (docs/queries.md).  The mesh walks
 * use their own frame's dipoles; every instance is visited (reach +inf at
 * the top). */
TRAVERSAL_INLINE bool instances_winding(Found_point* s, const PointData* q, int first,
                                        uint count INSTANCE_PARAMS,
                                        __global const WideDipoles* dipoles)
{
    for (uint i = (uint)first; i < (uint)first + count; ++i) {
        INSTANCE_AT(i);
        PointData mapped;
        mesh_point(&mapped, in, q);
        Found_point mesh;
        *mesh_overflow |= winding_walk(&mapped, MESH_TREE(in), dipoles + in->node_base, &mesh);
        s->solid_angle += in->normal_sign * mesh.solid_angle;
    }
    return false;
}

#define QUERY winding_top
#define QUERY_PATH _point
#define QUERY_UNORDERED
#define QUERY_HIT(s, i, hit, t, u, v) false
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_LEAF(s, r, first, count) \
    instances_winding(s, r, first, count INSTANCE_ARGS, dipoles)
#define QUERY_PARAMS INSTANCE_PARAMS, __global const WideDipoles* dipoles
#define QUERY_ARGS INSTANCE_ARGS, dipoles
#include "query/walk.h"

/* A two-level scene: the top tree over the instances, the instances and
 * the meshes' trees one after another (instance.h's SCENE_PARAMS without
 * the rays' masks). */
#define POINT_SCENE_PARAMS                                                              \
    __global const WideNode *top_nodes, __global const Triangle *top_triangles,          \
        __global const TriangleRef *top_refs, __global const Instance *instances,        \
        __global const WideNode *nodes, __global const Triangle *triangles,              \
        __global const TriangleRef *refs
#define POINT_SCENE_ARGS top_nodes, top_triangles, top_refs, instances, nodes, triangles, refs

TRAVERSAL_INLINE bool closest_search(const PointData* q, float reach, Found_point* s,
                                     POINT_SCENE_PARAMS)
{
    Found_point start = POINT_START(reach);
    *s = start;
    bool nested = false;
    bool out_of_stack = walk_closest_top_point(q, top_nodes, top_triangles, s,
                                               TOP_ARGS(&nested));
    return out_of_stack || nested;
}

TRAVERSAL_INLINE bool winding_search(const PointData* q, Found_point* s, POINT_SCENE_PARAMS,
                                     __global const WideDipoles* dipoles)
{
    Found_point start = POINT_START(INFINITY);
    *s = start;
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
    mapped_corners(in, triangles + j, a, b, c);
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
    distance_out[i] = found ? SQUARE_ROOT(s->reach) : INFINITY;
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

#define WINDING(s) ((s).solid_angle * (0.25f * M_1_PI_F))

/* The points a work-item takes: one, or (POINT_PACKETS) a packet. */
#ifdef POINT_PACKETS
#define POINTS_PER_ITEM PACKET_SIZE
#else
#define POINTS_PER_ITEM 1
#endif

/* The arguments that say which points a launch queries: `count` of them,
 * query i's point at slot i of points and its results at slot i of each
 * output; or, where `indexed` (the host hands whole arrays, points in any
 * order), at slot slots[i]. */
#define QUERY_POINTS                                                                    \
    __global const float *points, __global const uint *slots, const uint indexed,        \
        const uint count

/* The work-item's queries and their slots (lanes past the last repeat it);
 * how many exist (0 past the end). */
TRAVERSAL_INLINE uint query_slots(__global const uint* slots, uint indexed, uint count,
                                  uint* at)
{
    uint first = get_global_id(0) * POINTS_PER_ITEM;
    if (first >= count)
        return 0;
    uint used = LESSER((uint)POINTS_PER_ITEM, count - first);
    for (uint l = 0; l < POINTS_PER_ITEM; ++l) {
        uint i = first + LESSER(l, used - 1u);
        at[l] = indexed ? slots[i] : i;
    }
    return used;
}

#ifdef POINT_PACKETS
/* The packet's closest walk from the squared reach `reach`, its lanes'
 * states as Found_point each; true if the stack ran out. */
TRAVERSAL_INLINE bool closest_packet(const PointPacket* q, float reach, POINT_SCENE_PARAMS,
                                     Found_point* lanes)
{
    Found_points s = {(int_packet)(-1), (float_packet)(reach), (float_packet)(0.0f),
                      (float_packet)(0.0f), (float_packet)(0.0f), reach};
    bool out_of_stack = walk_closest_points(q, nodes, triangles, &s);
    int index[PACKET_SIZE];
    float best[PACKET_SIZE], u[PACKET_SIZE], v[PACKET_SIZE];
    vstore_packet(s.index, 0, index);
    vstore_packet(s.best, 0, best);
    vstore_packet(s.u, 0, u);
    vstore_packet(s.v, 0, v);
    for (uint l = 0; l < PACKET_SIZE; ++l) {
        Found_point one = POINT_START(best[l]);
        one.index = index[l];
        one.u = u[l];
        one.v = v[l];
        lanes[l] = one;
    }
    return out_of_stack;
}

/* The packet's winding walk: each lane's winding number in w; true if the
 * stack ran out. */
TRAVERSAL_INLINE bool winding_packet(const PointPacket* q, POINT_SCENE_PARAMS,
                                     __global const WideDipoles* dipoles, float* w)
{
    Found_points s = {(int_packet)(-1), (float_packet)(INFINITY), (float_packet)(0.0f),
                      (float_packet)(0.0f), (float_packet)(0.0f), INFINITY};
    bool out_of_stack = walk_winding_points(q, nodes, triangles, &s, dipoles);
    vstore_packet(WINDING(s), 0, w);
    return out_of_stack;
}
#endif

/* The work-item's closest walks from the squared reach `reach`: its
 * points' states in lanes. */
TRAVERSAL_INLINE bool closest_walks(__global const float* points, const uint* at, float reach,
                                    POINT_SCENE_PARAMS, Found_point* lanes)
{
#ifdef POINT_PACKETS
    PointPacket q;
    load_point_packet(points, at, &q);
    return closest_packet(&q, reach, POINT_SCENE_ARGS, lanes);
#else
    PointData q;
    load_point(points, at[0], &q);
    return closest_search(&q, reach, lanes, POINT_SCENE_ARGS);
#endif
}

/* The work-item's winding walks: its points' winding numbers in w. */
TRAVERSAL_INLINE bool winding_walks(__global const float* points, const uint* at,
                                    POINT_SCENE_PARAMS, __global const WideDipoles* dipoles,
                                    float* w)
{
#ifdef POINT_PACKETS
    PointPacket q;
    load_point_packet(points, at, &q);
    return winding_packet(&q, POINT_SCENE_ARGS, dipoles, w);
#else
    PointData q;
    load_point(points, at[0], &q);
    Found_point s;
    bool out_of_stack = winding_search(&q, &s, POINT_SCENE_ARGS, dipoles);
    w[0] = WINDING(s);
    return out_of_stack;
#endif
}

/* Closest point of each query within sqrt(max_d2): distance (inf if
 * none), ids (-1), u, v, unit normal (0) and the point (NaN). */
POINT_KERNEL void closest_points(POINT_SCENE_PARAMS, QUERY_POINTS, const float max_d2,
                                 CLOSEST_OUTPUTS, __global int* overflow)
{
    uint at[POINTS_PER_ITEM];
    uint used = query_slots(slots, indexed, count, at);
    if (used == 0)
        return;
    Found_point lanes[POINTS_PER_ITEM];
    if (closest_walks(points, at, max_d2, POINT_SCENE_ARGS, lanes))
        overflow[0] = 1;
    for (uint l = 0; l < used; ++l)
        store_closest(lanes + l, at[l], POINT_SCENE_ARGS, distance_out, geom_out, prim_out,
                      instance_out, u_out, v_out, normal_out, points_out);
}

/* The winding number of each query. */
POINT_KERNEL void winding_numbers(POINT_SCENE_PARAMS, __global const WideDipoles* dipoles,
                                  QUERY_POINTS, __global float* winding_out,
                                  __global int* overflow)
{
    uint at[POINTS_PER_ITEM];
    uint used = query_slots(slots, indexed, count, at);
    if (used == 0)
        return;
    float w[POINTS_PER_ITEM];
    if (winding_walks(points, at, POINT_SCENE_ARGS, dipoles, w))
        overflow[0] = 1;
    for (uint l = 0; l < used; ++l)
        winding_out[at[l]] = w[l];
}

/* The signed distance of each query (in the frame's units; negative where
 * |w| >= 0.5), and its winding number. */
POINT_KERNEL void signed_distances(POINT_SCENE_PARAMS, __global const WideDipoles* dipoles,
                                   QUERY_POINTS, __global float* distance_out,
                                   __global float* winding_out, __global int* overflow)
{
    uint at[POINTS_PER_ITEM];
    uint used = query_slots(slots, indexed, count, at);
    if (used == 0)
        return;
    Found_point lanes[POINTS_PER_ITEM];
    float w[POINTS_PER_ITEM];
    if (closest_walks(points, at, INFINITY, POINT_SCENE_ARGS, lanes)
        | winding_walks(points, at, POINT_SCENE_ARGS, dipoles, w))
        overflow[0] = 1;
    for (uint l = 0; l < used; ++l) {
        float distance = lanes[l].index >= 0 ? SQUARE_ROOT(lanes[l].reach) : INFINITY;
        distance_out[at[l]] = fabs(w[l]) >= 0.5f ? -distance : distance;
        winding_out[at[l]] = w[l];
    }
}
