/* Every hit along a ray: two visitors of the one walk of the wide tree
 * (walk.h), one that counts the hits and one that stores them sorted by t,
 * into the ray's own segment of the output (hlbvh_cl/all_hits.py runs the
 * count pass, sizes the segments by a prefix sum, then runs the fill pass).
 * The triangle test is traverse.cl's (triangle.h) with OWN_EDGES, so that a
 * ray through a shared edge or vertex counts its crossing once.
 *
 * Kernels
 *   count_hits_arrays  counts[i] = number of hits of ray i in [tmin, tmax],
 *                      and its first KEEP_HITS hit triangles
 *   fill_hits_arrays   ray i's min(count, k) nearest hits, sorted by t (ties
 *                      by tree-order triangle index), in its segment
 *                      [first[i], first[i + 1]) of the output arrays: the
 *                      known triangles tested again where they are all its
 *                      hits, else found by a walk; and its index
 *
 * Conventions are traverse.cl's (tmin <= t <= tmax, no culling, degenerate
 * triangles never hit, hit = (1-u-v)*v0 + u*v1 + v*v2).
 *
 * A launch's rays are its arrays' first ray_count slots, or the slots the
 * host lists (whole arrays in the host's Morton order), and each ray's
 * results go to its own slot (counts) or its own segment (hits).
 *
 * Compile-time parameters (-D): STACK_SIZE, PREFETCH and INSTANCES as
 * traverse.cl.  PACKET_SIZE: both kernels trace packets of that many rays
 * on flat scenes (walk.h's packet path with the counting or the filling
 * visitor, each lane into its own segment); instanced scenes take one ray
 * per work-item (PACKET_SIZE 1).
 */
#if PACKET_SIZE != 1 && defined(INSTANCES)
#error "all_hits.cl traces one ray per work-item on instanced scenes (PACKET_SIZE 1)"
#endif
#define OWN_EDGES
#include "query/ray.h"
#include "query/work_item.h"
#include "query/instance.h"

/* Counting: every hit adds one to each lane it hits (a ray's hit flag is
 * 1, a packet lane's -1); the limit stays tmax and the walk never ends
 * early.  s->index stays -1, so hit_triangle takes t == tmax too.
 *
 * The count also keeps the first KEEP_HITS triangles it hits (in walk
 * order): a ray with no more hits than that needs no second walk, as the
 * fill pass tests those triangles again instead (keep_known).  A count
 * alone is built with KEEP_HITS 0.
 *
 * At each node it visits, the walk asks for one ray of a later work-item
 * (work_item.h's prefetch_ahead). */
#define KEPT_SLOTS (KEEP_HITS > 0 ? KEEP_HITS : 1) /* arrays of no element are not C */
typedef struct {
    uint count;
    uint kept[KEPT_SLOTS];
    RaysAhead* ahead;
} Hits_ray;
TRAVERSAL_INLINE void add_hits_ray(Hits_ray* found, uint i)
{
    if (found->count < KEEP_HITS)
        found->kept[found->count] = i;
    ++found->count;
}
#if PACKET_SIZE > 1
#include "query/packet.h"
typedef struct {
    int_packet count;
    int_packet kept[KEPT_SLOTS];
    RaysAhead* ahead;
} Hits_packet;
TRAVERSAL_INLINE void add_hits_packet(Hits_packet* found, uint i, int_packet hit)
{
    for (int j = 0; j < KEEP_HITS; ++j)
        found->kept[j] = (hit & (found->count == (int_packet)(j))) ? (int_packet)((int)i)
                                                                  : found->kept[j];
    found->count -= hit;
}
#endif
#define QUERY count
#define QUERY_PATH _ray
#define QUERY_HIT(s, i, hit, t, u, v) (add_hits_ray(found, i), false)
#define QUERY_NODE(s, r, n, mask) (prefetch_ahead(found->ahead), false)
#define QUERY_UNORDERED
#define QUERY_PARAMS , Hits_ray* found
#define QUERY_ARGS , found
#include "query/walk.h"
#if PACKET_SIZE > 1
#define QUERY count
#define QUERY_PATH _packet
#define QUERY_HIT(s, i, hit, t, u, v) (add_hits_packet(found, i, hit), false)
#define QUERY_NODE(s, r, n, mask) (prefetch_ahead(found->ahead), false)
#define QUERY_UNORDERED
#define QUERY_PARAMS , Hits_packet* found
#define QUERY_ARGS , found
#include "query/walk.h"
#endif

/* Whether hit (t, i, k) comes before the stored hit j: by t, ties by
 * triangle index, then by instance. */
#define BEFORE(t, i, k, out_t, index, instance, j)                                      \
    ((t) < (out_t)[j]                                                                  \
     || ((t) == (out_t)[j] && ((i) < (index)[j] || ((i) == (index)[j] && (k) < (instance)[j]))))

/* Inserts the hit of triangle i (of instance k, -1 in a flat scene) into
 * the ray's sorted segment of `capacity` slots, of which *kept are used
 * (insertion sort: a ray's hits are few).
 * When the segment is full a later hit goes in only if it comes before the
 * last, which it shifts out; the ray's *limit then drops to the last one's
 * t, so the walk skips what could not get in (a tie at that t still can). */
TRAVERSAL_INLINE void keep_hit(float* limit, int i, int k, float t, float u, float v,
                               __global float* out_t, __global float* out_u,
                               __global float* out_v, __global int* index,
                               __global int* instance, uint* kept, uint capacity)
{
    uint j = *kept;
    if (j == capacity) {
        if (!BEFORE(t, i, k, out_t, index, instance, j - 1u))
            return;
        --j;
    } else {
        ++*kept;
    }
    for (; j > 0 && BEFORE(t, i, k, out_t, index, instance, j - 1u); --j) {
        out_t[j] = out_t[j - 1u];
        out_u[j] = out_u[j - 1u];
        out_v[j] = out_v[j - 1u];
        index[j] = index[j - 1u];
        instance[j] = instance[j - 1u];
    }
    out_t[j] = t;
    out_u[j] = u;
    out_v[j] = v;
    index[j] = i;
    instance[j] = k;
    if (*kept == capacity)
        *limit = out_t[capacity - 1u];
}

/* Filling: each hit goes into the ray's segment (keep_hit); the triangle's
 * index among the meshes' triangles (its tree-order index plus `base`, the
 * first of its mesh's tree) waits in the prim_id slot until the walk ends,
 * its instance `owner` (-1: none) in the instance_id slot. */
#define FILL_PARAMS                                                                     \
    , __global float *out_t, __global float *out_u, __global float *out_v,               \
        __global int *out_index, __global int *out_instance, uint *kept, uint capacity
#define FILL_ARGS , out_t, out_u, out_v, out_index, out_instance, kept, capacity
#define QUERY fill
#define QUERY_PATH _ray
#define QUERY_HIT(s, i, hit, t, u, v)                                                    \
    (keep_hit(&(s)->limit, (int)(i) + base, owner, t, u, v, out_t, out_u, out_v,          \
              out_index, out_instance, kept, capacity),                                 \
     false)
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_PARAMS FILL_PARAMS, int base, int owner
#define QUERY_ARGS FILL_ARGS, base, owner
#include "query/walk.h"

#if PACKET_SIZE > 1
/* A packet's segments: each lane's first output slot, its capacity (0 for
 * lanes that repeat the last ray or have no hit: they keep nothing) and
 * how many it holds. */
typedef struct {
    size_t start[PACKET_SIZE];
    uint capacity[PACKET_SIZE];
    uint kept[PACKET_SIZE];
} Segments;

/* keep_hit for each lane that hits triangle i, into its own segment; the
 * lanes whose segment fills take their new limits. */
TRAVERSAL_INLINE void keep_hits(Found_packet* s, int i, int_packet hit, float_packet t,
                                float_packet u, float_packet v, __global float* out_t,
                                __global float* out_u, __global float* out_v,
                                __global int* out_index, __global int* out_instance,
                                Segments* g)
{
    int flags[PACKET_SIZE];
    float ts[PACKET_SIZE], us[PACKET_SIZE], vs[PACKET_SIZE], limit[PACKET_SIZE];
    vstore_packet(hit, 0, flags);
    vstore_packet(t, 0, ts);
    vstore_packet(u, 0, us);
    vstore_packet(v, 0, vs);
    vstore_packet(s->limit, 0, limit);
    for (uint l = 0; l < PACKET_SIZE; ++l) {
        if (flags[l] == 0 || g->capacity[l] == 0)
            continue;
        size_t at = g->start[l];
        keep_hit(limit + l, i, -1, ts[l], us[l], vs[l], out_t + at, out_u + at, out_v + at,
                 out_index + at, out_instance + at, g->kept + l, g->capacity[l]);
    }
    s->limit = vload_packet(0, limit);
    update_reach_packet(s);
}

#define QUERY fill
#define QUERY_PATH _packet
#define QUERY_HIT(s, i, hit, t, u, v)                                                    \
    (keep_hits(s, (int)(i), hit, t, u, v, out_t, out_u, out_v, out_index, out_instance,   \
               segments),                                                               \
     false)
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_PARAMS                                                                    \
    , __global float *out_t, __global float *out_u, __global float *out_v,               \
        __global int *out_index, __global int *out_instance, Segments *segments
#define QUERY_ARGS , out_t, out_u, out_v, out_index, out_instance, segments
#include "query/walk.h"
#endif

#ifdef INSTANCES
/* The top tree's leaves: each visible instance's mesh walked by the flat
 * visitor with the walk's state (a full segment's limit prunes the next
 * instances too). */
TRAVERSAL_INLINE bool instances_count(Found_ray* s, const RayData* r, int first,
                                      uint count INSTANCE_PARAMS, Hits_ray* found)
{
    for (uint i = (uint)first; i < (uint)first + count; ++i) {
        INSTANCE_AT(i);
        RayData mapped;
        if (instance_ray(&mapped, in, r))
            *mesh_overflow |= walk_count_ray(&mapped, MESH_TREE(in), s, found);
    }
    return false;
}

TRAVERSAL_INLINE bool instances_fill(Found_ray* s, const RayData* r, int first,
                                     uint count INSTANCE_PARAMS FILL_PARAMS)
{
    for (uint i = (uint)first; i < (uint)first + count; ++i) {
        INSTANCE_AT(i);
        RayData mapped;
        if (instance_ray(&mapped, in, r))
            *mesh_overflow |= walk_fill_ray(&mapped, MESH_TREE(in), s FILL_ARGS,
                                            in->triangle_base, top_refs[i].prim_id);
    }
    return false;
}

#define QUERY count_top
#define QUERY_PATH _ray
#define QUERY_UNORDERED
#define QUERY_LEAF(s, r, first, count) instances_count(s, r, first, count INSTANCE_ARGS, found)
#define QUERY_NODE(s, r, n, mask) (prefetch_ahead(found->ahead), false)
#define QUERY_PARAMS INSTANCE_PARAMS, Hits_ray* found
#define QUERY_ARGS INSTANCE_ARGS, found
#include "query/walk.h"

#define QUERY fill_top
#define QUERY_PATH _ray
#define QUERY_LEAF(s, r, first, count) instances_fill(s, r, first, count INSTANCE_ARGS FILL_ARGS)
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_PARAMS INSTANCE_PARAMS FILL_PARAMS
#define QUERY_ARGS INSTANCE_ARGS FILL_ARGS
#include "query/walk.h"
#endif

/* See traverse.cl's TRAVERSAL_KERNEL. */
#define TRAVERSAL_KERNEL __kernel __attribute__((LANES_HINT))

/* The rays as numpy arrays (work_item.h's load_arrays), and which slots a
 * launch's rays take: ray i of the launch slot i, or where `indexed` slot
 * slots[i] (whole arrays, in the host's order).  A ray's results go to its
 * slot. */
#define RAY_ARRAYS origins, directions, tmin, tmin_step, tmax, tmax_step
#define RAY_PARAMS                                                                      \
    __global const float *origins, __global const float *directions,                     \
        __global const float *tmin, const uint tmin_step, __global const float *tmax,    \
        const uint tmax_step, __global const uint *slots, const uint indexed

/* The work-item's rays into lanes and their slots into at (lanes past the
 * last repeat it); how many exist (0 past the end). */
TRAVERSAL_INLINE uint load_rays(uint ray_count, RAY_PARAMS, RayLanes* lanes, uint* at)
{
    uint first, used = packet_rays(ray_count, &first);
    if (used == 0)
        return 0;
    for (uint l = 0; l < PACKET_SIZE; ++l) {
        uint i = first + LESSER(l, used - 1u);
        at[l] = indexed ? slots[i] : i;
    }
    load_arrays_at(at, RAY_ARRAYS, lanes);
    return used;
}

/* Walks one ray (lane `lane` of lanes, at slot `at`) with `query`'s walk of the
 * flat tree, or of the top tree of an instanced scene, with the walk's
 * extra arguments `args` (one expression, or a macro naming several: OpenCL C
 * has no variadic macros, 6.9); sets overflow[0] if a stack ran out. */
#ifndef INSTANCES
#define WALK_RAY(query, lanes, lane, at, args)                                           \
    do {                                                                                 \
        RayData r_;                                                                      \
        prepare_lane(&r_, lanes, lane);                                                   \
        Found_ray s_ = {-1, INFINITY, 0.0f, 0.0f, r_.tmax};                              \
        if (CONCAT(CONCAT(walk_, query), _ray)(&r_, nodes, triangles, &s_, args))        \
            overflow[0] = 1;                                                             \
    } while (0)
#else
#define WALK_RAY(query, lanes, lane, at, args)                                           \
    do {                                                                                 \
        load_masks(lanes, at, 1, ray_masks, mask_step);                                  \
        RayData r_;                                                                      \
        prepare_lane(&r_, lanes, lane);                                                   \
        Found_ray s_ = {-1, INFINITY, 0.0f, 0.0f, r_.tmax};                              \
        bool nested_ = false;                                                            \
        if (CONCAT(CONCAT(walk_, query), _top_ray)(&r_, top_nodes, top_triangles, &s_,    \
                                                   TOP_ARGS(&nested_), args)              \
            || nested_)                                                                  \
            overflow[0] = 1;                                                             \
    } while (0)
#endif

/* counts[slot] = the number of hits of each ray in [tmin, tmax], and with
 * `keeping` its first min(count, KEEP_HITS) hit triangles (tree order, in
 * walk order) in kept[slot * KEEP_HITS ...]: a packet of rays per
 * work-item where they share their direction signs and axis
 * (prepare_packet), else one by one. */
TRAVERSAL_KERNEL void count_hits_arrays(SCENE_PARAMS, RAY_PARAMS, __global int* counts,
                                        __global uint* kept, const uint keeping,
                                        __global int* overflow, const uint ray_count)
{
    RayLanes lanes;
    uint at[PACKET_SIZE];
    uint used = load_rays(ray_count, RAY_ARRAYS, slots, indexed, &lanes, at);
    if (used == 0)
        return;
    /* two work-items ahead (CPUs run a group's items in order): the last
     * rays asked for during this walk still have the next item's walk to
     * arrive in; only read by slots (else the rays lie in order) */
    RaysAhead ahead;
    rays_ahead(&ahead, slots, get_global_id(0) * PACKET_SIZE + 2 * PACKET_SIZE,
               indexed ? ray_count : 0u, origins, directions, counts);
    int lane_counts[PACKET_SIZE];
    uint lane_kept[KEPT_SLOTS][PACKET_SIZE];
#if PACKET_SIZE > 1
    Packet p;
    if (prepare_packet(&lanes, &p)) {
        Found_packet s = {(int_packet)(-1), (float_packet)(INFINITY), (float_packet)(0.0f),
                          (float_packet)(0.0f), p.tmax, packet_max(p.tmax)};
        Hits_packet found;
        found.count = (int_packet)(0);
        for (int j = 0; j < KEEP_HITS; ++j)
            found.kept[j] = (int_packet)(0);
        found.ahead = &ahead;
        if (walk_count_packet(&p, nodes, triangles, &s, &found))
            overflow[0] = 1;
        vstore_packet(found.count, 0, lane_counts);
        for (int j = 0; j < KEEP_HITS; ++j)
            vstore_packet(found.kept[j], 0, (int*)lane_kept[j]);
    } else
#endif
    {
        for (uint l = 0; l < used; ++l) {
            Hits_ray found;
            found.count = 0;
            found.ahead = &ahead;
            WALK_RAY(count, &lanes, l, at[l], &found);
            lane_counts[l] = (int)found.count;
            for (uint j = 0; j < LESSER(found.count, (uint)KEEP_HITS); ++j)
                lane_kept[j][l] = found.kept[j];
        }
    }
    prefetch_rest(&ahead);
    for (uint l = 0; l < used; ++l) {
        counts[at[l]] = lane_counts[l];
        if (keeping)
            for (int j = 0; j < LESSER(lane_counts[l], KEEP_HITS); ++j)
                kept[(size_t)at[l] * KEEP_HITS + j] = lane_kept[j][l];
    }
}

#ifndef INSTANCES
/* A flat scene's ray (lane l) whose count pass kept all its hits: those
 * triangles tested again, as the walk would test them (the same arithmetic
 * on one ray as on a packet lane), into its segment (keep_hit); the kept
 * hits as *kept_hits. */
TRAVERSAL_INLINE void keep_known(const RayLanes* lanes, uint l, __global const Triangle* triangles,
                                 __global const uint* known, uint count, __global float* out_t,
                                 __global float* out_u, __global float* out_v,
                                 __global int* out_index, __global int* out_instance,
                                 uint* kept_hits, uint capacity)
{
    RayData r;
    prepare_lane(&r, lanes, l);
    float limit = r.tmax;  /* not lowered: each triangle is hit within tmax */
    for (uint j = 0; j < count; ++j) {
        float t, u, v;
        if (hit_triangle_ray(&r, triangles + known[j], r.tmax, false, &t, &u, &v))
            keep_hit(&limit, (int)known[j], -1, t, u, v, out_t, out_u, out_v, out_index,
                     out_instance, kept_hits, capacity);
    }
}
#endif

/* Each ray's hits go to its segment [offsets[slot] - base, offsets[slot +
 * 1] - base) of the output arrays (the host's prefix sum of the counts, or
 * of the first k), as many as that holds, and its number (first_ray +
 * slot) to ray_out there.  With `keeping`, a ray whose count pass kept all
 * its hits (counts[slot] <= KEEP_HITS, known) has them tested again
 * (keep_known); the others walk, a packet of rays per work-item where they
 * share their direction signs and axis, else one by one.
 * overflow[1] is set if a ray found fewer (the passes disagree: the host
 * raises rather than return unwritten slots). */
TRAVERSAL_KERNEL void fill_hits_arrays(SCENE_PARAMS, RAY_PARAMS, __global const long* offsets,
        const long base, const long first_ray, __global const int* counts,
        __global const uint* known, const uint keeping, __global float* t_out,
        __global float* u_out, __global float* v_out, __global int* prim_out,
        __global int* geom_out, __global int* instance_out, __global long* ray_out,
        __global int* overflow, const uint ray_count)
{
    RayLanes lanes;
    uint at[PACKET_SIZE];
    uint used = load_rays(ray_count, RAY_ARRAYS, slots, indexed, &lanes, at);
    if (used == 0)
        return;
    size_t start[PACKET_SIZE];
    uint capacity[PACKET_SIZE], kept[PACKET_SIZE];
    bool walk = false;
    for (uint l = 0; l < PACKET_SIZE; ++l) {
        uint i = at[l];
        start[l] = (size_t)(offsets[i] - base);
        capacity[l] = l < used ? (uint)(offsets[i + 1] - offsets[i]) : 0u;
        kept[l] = 0;
#ifndef INSTANCES
        if (keeping && capacity[l] != 0 && counts[i] <= KEEP_HITS) {
            size_t j = start[l];
            keep_known(&lanes, l, triangles, known + (size_t)i * KEEP_HITS, (uint)counts[i],
                       t_out + j, u_out + j, v_out + j, prim_out + j,
                       instance_out + j, kept + l, capacity[l]);
            continue;
        }
#endif
        walk |= capacity[l] != 0;
    }
#if PACKET_SIZE > 1
    Packet p;
    if (!walk) {
    } else if (prepare_packet(&lanes, &p)) {
        Segments g;
        for (uint l = 0; l < PACKET_SIZE; ++l) {
            /* lanes filled already, or with nothing to find: out of reach */
            bool walks = capacity[l] != 0 && kept[l] == 0;
            g.start[l] = start[l];
            g.capacity[l] = walks ? capacity[l] : 0u;
            g.kept[l] = kept[l];
            if (!walks)
                lanes.tmax[l] = -INFINITY;
        }
        Found_packet s = {(int_packet)(-1), (float_packet)(INFINITY), (float_packet)(0.0f),
                          (float_packet)(0.0f), vload_packet(0, lanes.tmax), 0.0f};
        update_reach_packet(&s);
        if (walk_fill_packet(&p, nodes, triangles, &s, t_out, u_out, v_out, prim_out,
                             instance_out, &g))
            overflow[0] = 1;
        for (uint l = 0; l < PACKET_SIZE; ++l)
            kept[l] = g.kept[l];
    } else
#endif
    {
        for (uint l = 0; l < used; ++l) {
            if (capacity[l] == 0 || kept[l] != 0)  /* nothing to find, or filled */
                continue;
            size_t j = start[l];
#ifndef INSTANCES
#define SEGMENT t_out + j, u_out + j, v_out + j, prim_out + j, instance_out + j, kept + l, \
                capacity[l], 0, -1
#else
#define SEGMENT t_out + j, u_out + j, v_out + j, prim_out + j, instance_out + j, kept + l, \
                capacity[l]
#endif
            WALK_RAY(fill, &lanes, l, at[l], SEGMENT);
#undef SEGMENT
        }
    }
    for (uint l = 0; l < used; ++l) {
        if (kept[l] != capacity[l])
            overflow[1] = 1;
        for (size_t j = start[l]; j < start[l] + kept[l]; ++j) {
            ray_out[j] = first_ray + at[l];
            TriangleRef ref = refs[prim_out[j]];
            prim_out[j] = ref.prim_id;
#ifdef INSTANCES
            geom_out[j] = instances[instance_out[j]].mesh;
#else
            geom_out[j] = ref.geom_id;
#endif
        }
    }
}
