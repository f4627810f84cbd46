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
 * Compile-time parameters (-D): STACK_SIZE and PREFETCH as traverse.cl;
 * PACKET_SIZE must be 1 (each ray's hits are its own: nothing for a packet
 * to share).
 */
#if PACKET_SIZE != 1
#error "all_hits.cl traces one ray per work-item (PACKET_SIZE 1)"
#endif
#define OWN_EDGES
#include "ray.h"
#include "work_item.h"

/* Counting: every hit adds one; the limit stays tmax and the walk never
 * ends early.  s->index stays -1, so hit_triangle takes t == tmax too. */
#define QUERY count
#define QUERY_HIT(s, i, hit, t, u, v) (*found += (uint)(hit), false)
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_PARAMS , uint* found
#define QUERY_ARGS , found
#include "walk.h"

/* Whether hit (t, i) comes before the stored hit j: by t, ties by index. */
#define BEFORE(t, i, out_t, index, j) ((t) < (out_t)[j] || ((t) == (out_t)[j] && (int)(i) < (index)[j]))

/* Inserts triangle i's hit into the ray's sorted segment of `capacity`
 * slots, of which *kept are used (insertion sort: a ray's hits are few).
 * When the segment is full a later hit goes in only if it comes before the
 * last, which it shifts out; the limit then drops to the last one's t, so
 * the walk skips what could not get in (a tie at that t still can). */
TRAVERSAL_INLINE void keep_hit(Found_ray* s, uint i, float t, float u, float v,
                               __global float* out_t, __global float* out_u,
                               __global float* out_v, __global int* index, uint* kept,
                               uint capacity)
{
    uint j = *kept;
    if (j == capacity) {
        if (!BEFORE(t, i, out_t, index, j - 1u))
            return;
        --j;
    } else {
        ++*kept;
    }
    for (; j > 0 && BEFORE(t, i, out_t, index, j - 1u); --j) {
        out_t[j] = out_t[j - 1u];
        out_u[j] = out_u[j - 1u];
        out_v[j] = out_v[j - 1u];
        index[j] = index[j - 1u];
    }
    out_t[j] = t;
    out_u[j] = u;
    out_v[j] = v;
    index[j] = (int)i;
    if (*kept == capacity)
        s->limit = out_t[capacity - 1u];
}

/* Filling: each hit goes into the ray's segment (keep_hit); the tree-order
 * index waits in the prim_id slot until the walk ends. */
#define QUERY fill
#define QUERY_HIT(s, i, hit, t, u, v) \
    (keep_hit(s, i, t, u, v, out_t, out_u, out_v, out_index, kept, capacity), false)
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_PARAMS                                                                   \
    , __global float *out_t, __global float *out_u, __global float *out_v,               \
        __global int *out_index, uint *kept, uint capacity
#define QUERY_ARGS , out_t, out_u, out_v, out_index, kept, capacity
#include "walk.h"

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

TRAVERSAL_KERNEL void count_hits_arrays(__global const WideNode* nodes,
        __global const Triangle* triangles, __global const float* origins,
        __global const float* directions, __global const float* tmin, const uint tmin_step,
        __global const float* tmax, const uint tmax_step, __global int* counts,
        __global int* overflow, const uint ray_count)
{
    RayLanes lanes;
    uint first;
    if (!load_ray(ray_count, RAY_ARRAYS, &lanes, &first))
        return;
    int index[1];
    uint found = 0;
    trace_count(&lanes, 1, nodes, triangles, overflow, index, 0, 0, 0, &found);
    counts[first] = (int)found;
}

/* Ray i's hits go to [segment[i], segment[i + 1]) of the output arrays, as
 * many as that holds (the count pass sized it: all of them, or the first
 * k).  overflow[1] is set if a ray found fewer (the passes disagree: the
 * host raises rather than return unwritten slots). */
TRAVERSAL_KERNEL void fill_hits_arrays(__global const WideNode* nodes,
        __global const Triangle* triangles, __global const TriangleRef* refs,
        __global const float* origins, __global const float* directions,
        __global const float* tmin, const uint tmin_step, __global const float* tmax,
        const uint tmax_step, __global const uint* segment, __global float* t_out,
        __global float* u_out, __global float* v_out, __global int* prim_out,
        __global int* geom_out, __global int* overflow, const uint ray_count)
{
    uint first = get_global_id(0);  /* one ray per work-item */
    if (first >= ray_count || segment[first + 1] == segment[first])
        return;
    uint start = segment[first], capacity = segment[first + 1] - start;
    RayLanes lanes;
    load_ray(ray_count, RAY_ARRAYS, &lanes, &first);
    int index[1];
    uint kept = 0;
    trace_fill(&lanes, 1, nodes, triangles, overflow, index, 0, 0, 0, t_out + start,
               u_out + start, v_out + start, prim_out + start, &kept, capacity);
    if (kept != capacity)
        overflow[1] = 1;
    for (uint j = start; j < start + kept; ++j) {
        TriangleRef ref = refs[prim_out[j]];
        prim_out[j] = ref.prim_id;
        geom_out[j] = ref.geom_id;
    }
}
