/* Every hit along a ray: two visitors of the one walk of the wide tree
 * (walk.h), one that counts the hits and one that stores them sorted by t,
 * into the ray's own segment of the output (hlbvh_cl/all_hits.py runs the
 * count pass, sizes the segments by a prefix sum, then runs the fill pass).
 * The triangle test is traverse.cl's (triangle.h) with OWN_EDGES, so that a
 * ray through a shared edge or vertex counts its crossing once.
 *
 * Kernels
 *   count_hits_arrays  counts[i] = number of hits of ray i in [tmin, tmax]
 *   fill_hits_arrays   ray i's min(count, k) nearest hits, sorted by t (ties
 *                      by tree-order triangle index), in its segment
 *                      [first[i], first[i + 1]) of the output arrays
 *
 * Conventions are traverse.cl's (tmin <= t <= tmax, no culling, degenerate
 * triangles never hit, hit = (1-u-v)*v0 + u*v1 + v*v2).
 *
 * Compile-time parameters (-D): STACK_SIZE, PREFETCH and INSTANCES as
 * traverse.cl; PACKET_SIZE must be 1 (each ray's hits are its own: nothing
 * for a packet to share).
 */
#if PACKET_SIZE != 1
#error "all_hits.cl traces one ray per work-item (PACKET_SIZE 1)"
#endif
#define OWN_EDGES
#include "ray.h"
#include "work_item.h"
#include "instance.h"

/* Counting: every hit adds one; the limit stays tmax and the walk never
 * ends early.  s->index stays -1, so hit_triangle takes t == tmax too. */
#define QUERY count
#define QUERY_HIT(s, i, hit, t, u, v) (*found += (uint)(hit), false)
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_PARAMS , uint* found
#define QUERY_ARGS , found
#include "walk.h"

/* Whether hit (t, i, k) comes before the stored hit j: by t, ties by
 * triangle index, then by instance. */
#define BEFORE(t, i, k, out_t, index, instance, j)                                      \
    ((t) < (out_t)[j]                                                                  \
     || ((t) == (out_t)[j] && ((i) < (index)[j] || ((i) == (index)[j] && (k) < (instance)[j]))))

/* Inserts the hit of triangle i (of instance k, -1 in a flat scene) into
 * the ray's sorted segment of `capacity` slots, of which *kept are used
 * (insertion sort: a ray's hits are few).
 * When the segment is full a later hit goes in only if it comes before the
 * last, which it shifts out; the limit then drops to the last one's t, so
 * the walk skips what could not get in (a tie at that t still can). */
TRAVERSAL_INLINE void keep_hit(Found_ray* s, int i, int k, float t, float u, float v,
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
        s->limit = out_t[capacity - 1u];
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
#define QUERY_HIT(s, i, hit, t, u, v)                                                    \
    (keep_hit(s, (int)(i) + base, owner, t, u, v, out_t, out_u, out_v, out_index,         \
              out_instance, kept, capacity),                                            \
     false)
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_PARAMS FILL_PARAMS, int base, int owner
#define QUERY_ARGS FILL_ARGS, base, owner
#include "walk.h"

#ifdef INSTANCES
/* The top tree's leaves: each visible instance's mesh walked by the flat
 * visitor with the walk's state (a full segment's limit prunes the next
 * instances too). */
TRAVERSAL_INLINE bool instances_count(Found_ray* s, const RayData* r, int first,
                                      uint count INSTANCE_PARAMS, uint* found)
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
#define QUERY_LEAF(s, r, first, count) instances_count(s, r, first, count INSTANCE_ARGS, found)
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_PARAMS INSTANCE_PARAMS, uint* found
#define QUERY_ARGS INSTANCE_ARGS, found
#include "walk.h"

#define QUERY fill_top
#define QUERY_PATH _ray
#define QUERY_LEAF(s, r, first, count) instances_fill(s, r, first, count INSTANCE_ARGS FILL_ARGS)
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_PARAMS INSTANCE_PARAMS FILL_PARAMS
#define QUERY_ARGS INSTANCE_ARGS FILL_ARGS
#include "walk.h"
#endif

/* See traverse.cl's TRAVERSAL_KERNEL. */
#define TRAVERSAL_KERNEL __kernel __attribute__((LANES_HINT))

/* The work-item's ray (load_arrays), its index in *ray; false past the last. */
#define RAY_ARRAYS origins, directions, tmin, tmin_step, tmax, tmax_step
TRAVERSAL_INLINE bool load_ray(uint ray_count, __global const float* origins,
                               __global const float* directions, __global const float* tmin,
                               uint tmin_step, __global const float* tmax, uint tmax_step,
                               RayLanes* lanes, uint* ray)
{
    uint used = packet_rays(ray_count, ray);
    if (used != 0)
        load_arrays(*ray, used, RAY_ARRAYS, lanes);
    return used != 0;
}

/* Walks the work-item's one ray (lanes) with `query`'s walk of the flat
 * tree, or of the top tree of an instanced scene, with the walk's extra
 * arguments; sets overflow[0] if a stack ran out. */
#ifndef INSTANCES
#define WALK_RAY(query, lanes, first, ...)                                               \
    do {                                                                                 \
        int index_[1];                                                                   \
        CONCAT(trace_, query)(lanes, 1, nodes, triangles, overflow, index_, 0, 0, 0,      \
                              __VA_ARGS__);                                              \
    } while (0)
#else
#define WALK_RAY(query, lanes, first, ...)                                               \
    do {                                                                                 \
        load_masks(lanes, first, 1, ray_masks, mask_step);                               \
        RayData r_;                                                                      \
        prepare_lane(&r_, lanes, 0);                                                     \
        Found_ray s_ = {-1, INFINITY, 0.0f, 0.0f, r_.tmax};                              \
        bool nested_ = false;                                                            \
        if (CONCAT(CONCAT(walk_, query), _top_ray)(&r_, top_nodes, top_triangles, &s_,    \
                                                   TOP_ARGS(&nested_), __VA_ARGS__)      \
            || nested_)                                                                  \
            overflow[0] = 1;                                                             \
    } while (0)
#endif

TRAVERSAL_KERNEL void count_hits_arrays(SCENE_PARAMS, __global const float* origins,
        __global const float* directions, __global const float* tmin, const uint tmin_step,
        __global const float* tmax, const uint tmax_step, __global int* counts,
        __global int* overflow, const uint ray_count)
{
    RayLanes lanes;
    uint first;
    if (!load_ray(ray_count, RAY_ARRAYS, &lanes, &first))
        return;
    uint found = 0;
    WALK_RAY(count, &lanes, first, &found);
    counts[first] = (int)found;
}

/* Ray i's hits go to [segment[i], segment[i + 1]) of the output arrays, as
 * many as that holds (the count pass sized it: all of them, or the first
 * k).  overflow[1] is set if a ray found fewer (the passes disagree: the
 * host raises rather than return unwritten slots). */
TRAVERSAL_KERNEL void fill_hits_arrays(SCENE_PARAMS, __global const float* origins,
        __global const float* directions, __global const float* tmin, const uint tmin_step,
        __global const float* tmax, const uint tmax_step, __global const uint* segment,
        __global float* t_out, __global float* u_out, __global float* v_out,
        __global int* prim_out, __global int* geom_out, __global int* instance_out,
        __global int* overflow, const uint ray_count)
{
    uint first = get_global_id(0);  /* one ray per work-item */
    if (first >= ray_count || segment[first + 1] == segment[first])
        return;
    uint start = segment[first], capacity = segment[first + 1] - start;
    RayLanes lanes;
    load_ray(ray_count, RAY_ARRAYS, &lanes, &first);
    uint kept = 0;
#ifndef INSTANCES
    WALK_RAY(fill, &lanes, first, t_out + start, u_out + start, v_out + start,
             prim_out + start, instance_out + start, &kept, capacity, 0, -1);
#else
    WALK_RAY(fill, &lanes, first, t_out + start, u_out + start, v_out + start,
             prim_out + start, instance_out + start, &kept, capacity);
#endif
    if (kept != capacity)
        overflow[1] = 1;
    for (uint j = start; j < start + kept; ++j) {
        TriangleRef ref = refs[prim_out[j]];
        prim_out[j] = ref.prim_id;
#ifdef INSTANCES
        geom_out[j] = instances[instance_out[j]].mesh;
#else
        geom_out[j] = ref.geom_id;
#endif
    }
}
