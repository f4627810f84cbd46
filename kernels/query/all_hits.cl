/* Every hit along a ray: two visitors of the one walk of the wide tree
 * (query/walk/walk.h), traced by query/rays/trace.h, one that counts the
 * hits and one that stores them sorted by t, into the ray's own segment of
 * the output (hlbvh_cl/query/all_hits.py runs the count pass, sizes the
 * segments by a prefix sum, then runs the fill pass).  The triangle test is
 * rays.cl's (query/rays/triangle.h) with OWN_EDGES, so that a ray through a
 * shared edge or vertex counts its crossing once.
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
 * Conventions are rays.cl's (tmin <= t <= tmax, no culling, degenerate
 * triangles never hit, hit = (1-u-v)*v0 + u*v1 + v*v2).
 *
 * A launch's rays are its arrays' first ray_count slots, or the slots the
 * host lists (whole arrays in the host's Morton order), and each ray's
 * results go to its own slot (counts) or its own segment (hits).
 *
 * Compile-time parameters (-D): STACK_SIZE, PREFETCH and INSTANCES as
 * rays.cl.  PACKET_SIZE: both kernels trace packets of that many rays on
 * flat scenes (the packet path with the counting or the filling visitor,
 * each lane into its own segment); instanced scenes take one ray per
 * work-item (PACKET_SIZE 1).
 */
#if PACKET_SIZE != 1 && defined(INSTANCES)
#error "all_hits.cl traces one ray per work-item on instanced scenes (PACKET_SIZE 1)"
#endif
#define OWN_EDGES
#include "core/portable.h"
#include "query/rays/work_item.h"
#include "query/rays/instance.h"

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

/* The work-item's counts and kept triangles, one lane each, and the rays it
 * asks for ahead. */
typedef struct {
    int count[PACKET_SIZE];
    uint kept[KEPT_SLOTS][PACKET_SIZE];
    RaysAhead* ahead;
} HitCounts;

/* A walk's count (the trace's state for the count): one ray's, */
typedef struct {
    uint count;
    uint kept[KEPT_SLOTS];
    RaysAhead* ahead;
} Hits_ray;

TRAVERSAL_INLINE void start_hits_ray(Hits_ray* found, const HitCounts* out)
{
    found->count = 0;
    found->ahead = out->ahead;
}

TRAVERSAL_INLINE void add_hits_ray(Hits_ray* found, uint i, int hit)
{
    if (found->count < KEEP_HITS)
        found->kept[found->count] = i;
    ++found->count;
}

TRAVERSAL_INLINE void store_hits_ray(const Hits_ray* found, HitCounts* out, uint l)
{
    out->count[l] = (int)found->count;
    for (uint j = 0; j < LESSER(found->count, (uint)KEEP_HITS); ++j)
        out->kept[j][l] = found->kept[j];
}

#if PACKET_SIZE > 1
/* ... and a packet's, one lane each. */
typedef struct {
    int_packet count;
    int_packet kept[KEPT_SLOTS];
    RaysAhead* ahead;
} Hits_packet;

TRAVERSAL_INLINE void start_hits_packet(Hits_packet* found, const HitCounts* out)
{
    found->count = (int_packet)(0);
    for (int j = 0; j < KEEP_HITS; ++j)
        found->kept[j] = (int_packet)(0);
    found->ahead = out->ahead;
}

TRAVERSAL_INLINE void add_hits_packet(Hits_packet* found, uint i, int_packet hit)
{
    for (int j = 0; j < KEEP_HITS; ++j)
        found->kept[j] = (hit & (found->count == (int_packet)(j))) ? (int_packet)((int)i)
                                                                  : found->kept[j];
    found->count -= hit;
}

TRAVERSAL_INLINE void store_hits_packet(const Hits_packet* found, HitCounts* out, uint l)
{
    vstore_packet(found->count, 0, out->count);
    for (int j = 0; j < KEEP_HITS; ++j)
        vstore_packet(found->kept[j], 0, (int*)out->kept[j]);
}
#endif

#define QUERY count
#define QUERY_STATE Hits
#define QUERY_OUT HitCounts
#define QUERY_BEGIN(out, l) PATH(start_hits)(state, out)
#define QUERY_HIT(s, i, hit, t, u, v) (PATH(add_hits)(state, i, hit), false)
#define QUERY_NODE(s, r, n, mask) (prefetch_ahead(state->ahead), false)
#define QUERY_END(s, out, l) PATH(store_hits)(state, out, l)
#define QUERY_UNORDERED
#include "query/rays/trace.h"

/* Whether hit (t, i, k) comes before the stored hit j: by t, ties by
 * triangle index, then by instance. */
TRAVERSAL_INLINE bool hit_before(float t, int i, int k, __global const float* out_t,
                                 __global const int* index, __global const int* instance,
                                 uint j)
{
    return t < out_t[j]
           || (t == out_t[j] && (i < index[j] || (i == index[j] && k < instance[j])));
}

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
        if (!hit_before(t, i, k, out_t, index, instance, j - 1u))
            return;
        --j;
    } else {
        ++*kept;
    }
    for (; j > 0 && hit_before(t, i, k, out_t, index, instance, j - 1u); --j) {
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

/* Filling: each hit goes into its ray's segment (keep_hit); the triangle's
 * index among the meshes' triangles (its tree-order index plus `base`, the
 * first of its mesh's tree: 0 on a flat scene) waits in the prim_id slot
 * until the walk ends, its instance `owner` (-1: none) in the instance_id
 * slot.  The work-item's segments: the output arrays, and per lane its
 * segment's start, its capacity (0 for lanes that repeat the last ray or
 * have nothing to find: they keep nothing) and how many hits it holds. */
typedef struct {
    __global float *t, *u, *v;
    __global int *index, *instance;
    size_t start[PACKET_SIZE];
    uint capacity[PACKET_SIZE];
    uint kept[PACKET_SIZE];
} Segments;

/* A walk's segment (the trace's state for the fill): one ray's, */
typedef struct {
    __global float *t, *u, *v;
    __global int *index, *instance;
    uint* kept;
    uint capacity;
} Fill_ray;

TRAVERSAL_INLINE void start_fill_ray(Fill_ray* f, Segments* g, uint l)
{
    size_t at = g->start[l];
    f->t = g->t + at;
    f->u = g->u + at;
    f->v = g->v + at;
    f->index = g->index + at;
    f->instance = g->instance + at;
    f->kept = g->kept + l;
    f->capacity = g->capacity[l];
}

TRAVERSAL_INLINE void keep_hits_ray(Found_ray* s, int i, int owner, int hit, float t, float u,
                                    float v, Fill_ray* f)
{
    keep_hit(&s->limit, i, owner, t, u, v, f->t, f->u, f->v, f->index, f->instance, f->kept,
             f->capacity);
}

#if PACKET_SIZE > 1
/* ... and a packet's: every lane's. */
typedef struct {
    Segments* g;
} Fill_packet;

TRAVERSAL_INLINE void start_fill_packet(Fill_packet* f, Segments* g, uint l)
{
    f->g = g;
}

/* keep_hit for each lane that hits triangle i, into its own segment; the
 * lanes whose segment fills take their new limits. */
TRAVERSAL_INLINE void keep_hits_packet(Found_packet* s, int i, int owner, int_packet hit,
                                       float_packet t, float_packet u, float_packet v,
                                       Fill_packet* f)
{
    Segments* g = f->g;
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
        keep_hit(limit + l, i, owner, ts[l], us[l], vs[l], g->t + at, g->u + at, g->v + at,
                 g->index + at, g->instance + at, g->kept + l, g->capacity[l]);
    }
    s->limit = vload_packet(0, limit);
    update_reach_packet(s);
}
#endif

#define QUERY fill
#define QUERY_STATE Fill
#define QUERY_OUT Segments
#define QUERY_BEGIN(out, l) PATH(start_fill)(state, out, l)
#define QUERY_LANE(out, l) ((out)->capacity[l] != 0)
#define QUERY_HIT(s, i, hit, t, u, v) \
    (PATH(keep_hits)(s, (int)(i) + base, owner, hit, t, u, v, state), false)
#define QUERY_PARAMS , int base, int owner
#define QUERY_ARGS , base, owner
#define QUERY_MESH_ARGS(in, id) , (in)->triangle_base, id
#include "query/rays/trace.h"

/* The rays as numpy arrays (work_item.h's load_arrays), and which slots a
 * launch's rays take: ray i of the launch slot i, or where `indexed` slot
 * slots[i] (whole arrays, in the host's order).  A ray's results go to its
 * slot. */
#define RAY_ARRAYS origins, directions, tmin, tmin_step, tmax, tmax_step
#define RAY_PARAMS                                                                      \
    __global const float *origins, __global const float *directions,                     \
        __global const float *tmin, const uint tmin_step, __global const float *tmax,    \
        const uint tmax_step, __global const uint *slots, const uint indexed

/* On a two-level scene the rays' masks too, by slot (SCENE_PARAMS' ray_masks). */
#ifdef INSTANCES
#define MASK_PARAMS , __global const uint *ray_masks, const uint mask_step
#define MASK_ARGS , ray_masks, mask_step
#else
#define MASK_PARAMS
#define MASK_ARGS
#endif

/* The rays a work-item takes (lanes past the last repeat it), and their
 * slots. */
typedef struct {
    RayLanes lanes;
    uint at[PACKET_SIZE];
} ItemRays;

/* The work-item's rays; how many exist (0 past the end). */
TRAVERSAL_INLINE uint load_rays(uint ray_count, RAY_PARAMS, ItemRays* item MASK_PARAMS)
{
    uint first, used = packet_rays(ray_count, &first);
    if (used == 0)
        return 0;
    for (uint l = 0; l < PACKET_SIZE; ++l) {
        uint i = first + LESSER(l, used - 1u);
        item->at[l] = indexed ? slots[i] : i;
    }
    load_arrays_at(item->at, RAY_ARRAYS, &item->lanes);
#ifdef INSTANCES
    for (uint l = 0; l < PACKET_SIZE; ++l)
        item->lanes.mask[l] = ray_masks[item->at[l] * mask_step];
#endif
    return used;
}

/* counts[slot] = the number of hits of each ray in [tmin, tmax], and with
 * `keeping` its first min(count, KEEP_HITS) hit triangles (tree order, in
 * walk order) in kept[slot * KEEP_HITS ...]: a packet of rays per
 * work-item where they share their direction signs and axis
 * (prepare_packet), else one by one. */
TRAVERSAL_KERNEL void count_hits_arrays(SCENE_PARAMS, RAY_PARAMS, __global int* counts,
                                        __global uint* kept, const uint keeping,
                                        __global int* overflow, const uint ray_count)
{
    ItemRays rays;
    uint used = load_rays(ray_count, RAY_ARRAYS, slots, indexed, &rays MASK_ARGS);
    if (used == 0)
        return;
    /* two work-items ahead (CPUs run a group's items in order): the last
     * rays asked for during this walk still have the next item's walk to
     * arrive in; only read by slots (else the rays lie in order) */
    RaysAhead ahead;
    rays_ahead(&ahead, slots, get_global_id(0) * PACKET_SIZE + 2 * PACKET_SIZE,
               indexed ? ray_count : 0u, origins, directions, counts);
    HitCounts found;
    found.ahead = &ahead;
    trace_count(&rays.lanes, &used, SCENE_TREES, overflow, &found);
    prefetch_rest(&ahead);
    for (uint l = 0; l < used; ++l) {
        counts[rays.at[l]] = found.count[l];
        if (keeping)
            for (int j = 0; j < LESSER(found.count[l], KEEP_HITS); ++j)
                kept[(size_t)rays.at[l] * KEEP_HITS + j] = found.kept[j][l];
    }
}

#ifndef INSTANCES
/* A flat scene's ray (lane l) whose count pass kept all its hits: those
 * triangles tested again, as the walk would test them (the same arithmetic
 * on one ray as on a packet lane), into its segment (keep_hit); the kept
 * hits as *kept_hits. */
TRAVERSAL_INLINE void keep_known(const RayLanes* lanes, uint l, __global const Leaf* triangles,
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
        LEAF_CORNERS(tri, triangles, known[j]);
        if (hit_triangle_ray(&r, tri, r.tmax, false, &t, &u, &v))
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
    ItemRays rays;
    uint used = load_rays(ray_count, RAY_ARRAYS, slots, indexed, &rays MASK_ARGS);
    if (used == 0)
        return;
    Segments g;
    g.t = t_out;
    g.u = u_out;
    g.v = v_out;
    g.index = prim_out;
    g.instance = instance_out;
    uint capacity[PACKET_SIZE];
    bool walk = false;
    for (uint l = 0; l < PACKET_SIZE; ++l) {
        uint i = rays.at[l];
        g.start[l] = (size_t)(offsets[i] - base);
        capacity[l] = l < used ? (uint)(offsets[i + 1] - offsets[i]) : 0u;
        g.kept[l] = 0;
#ifndef INSTANCES
        if (keeping && capacity[l] != 0 && counts[i] <= KEEP_HITS) {
            size_t j = g.start[l];
            keep_known(&rays.lanes, l, triangles, known + (size_t)i * KEEP_HITS, (uint)counts[i],
                       t_out + j, u_out + j, v_out + j, prim_out + j, instance_out + j,
                       g.kept + l, capacity[l]);
        }
#endif
        /* lanes filled already, or with nothing to find: none walked one by
         * one (QUERY_LANE), and out of a packet's reach */
        bool walks = capacity[l] != 0 && g.kept[l] == 0;
        g.capacity[l] = walks ? capacity[l] : 0u;
        if (!walks)
            rays.lanes.tmax[l] = -INFINITY;
        walk |= walks;
    }
    if (walk)
        trace_fill(&rays.lanes, &used, SCENE_TREES, overflow, &g, 0, -1);
    for (uint l = 0; l < used; ++l) {
        if (g.kept[l] != capacity[l])
            overflow[1] = 1;
        for (size_t j = g.start[l]; j < g.start[l] + g.kept[l]; ++j) {
            ray_out[j] = first_ray + rays.at[l];
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
