/* Ray queries: closest hit and any hit, two visitors of the one walk of the
 * wide tree (walk.h) with the watertight ray/triangle test of Woop, Benthin
 * & Wald 2013 (triangle.h).  A work-item traces PACKET_SIZE consecutive
 * rays: on CPUs as one packet when they are coherent (packet.h), else one by
 * one.
 *
 * Kernels
 *   intersect_closest  nearest hit in [tmin, tmax] -> Hit
 *   intersect_any      1 if any hit in [tmin, tmax] (stops at the first one)
 *   intersect_closest_arrays, intersect_any_arrays
 *                      the same on numpy-shaped arrays (one per field)
 *
 * Conventions (tests/oracle.py follows the same ones)
 *   - a hit at distance t counts when tmin <= t <= tmax (both ends closed,
 *     as Embree's tnear <= t <= tfar); t is in units of |direction|;
 *   - no culling: both sides of a triangle are hit;
 *   - degenerate triangles (zero edge cross product) are never hit;
 *   - u, v: hit = (1-u-v)*v0 + u*v1 + v*v2.
 *
 * Compile-time parameters (-D)
 *   STACK_SIZE  entries of the private traversal stack; the host passes a
 *               bound that cannot overflow for the tree (query.py), and if
 *               it ever did, the ray is flagged and the host raises.
 *   PACKET_SIZE rays per work-item: 1 (one ray each, for GPUs, whose SIMT
 *               lanes already run neighbouring rays together), or 8 or 16
 *               (ray packets, for CPUs).
 *   PREFETCH    defined on CPUs: traversal prefetches what it visits next
 *               (__builtin_prefetch, which the CPUs' Clang-based OpenCL
 *               compilers know).
 *   PLAIN_OPENCL  no spelling that LLVM turns into what Oclgrind cannot run.
 *   COUNT_PACKETS  defined by tests: overflow[1] counts the work-items whose
 *               rays were traced as one packet.
 */
#if PACKET_SIZE > 1
#include "packet.h"
#else
#include "ray.h"
#endif
#include "work_item.h"

/* A closest hit's ids (refs[i]) are read when the traversal ends, a cache
 * miss of their own: start loading them when the hit is found. */
TRAVERSAL_INLINE void prefetch_hit_ids(__global const TriangleRef* refs, uint i)
{
#ifdef PREFETCH
    __builtin_prefetch(refs + i);
#endif
}

/* Closest hit: a hit lowers the lane's limit to its t, and the walk goes on
 * in case a nearer one follows; nearer children first. */
#define QUERY intersect
#define QUERY_HIT(s, i, hit, t, u, v) \
    (prefetch_hit_ids(refs, i), PATH(take_hit)(s, i, hit, t, u, v, t), false)
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_PARAMS , __global const TriangleRef* refs
#define QUERY_ARGS , refs
#include "walk.h"

/* Any hit (shadow rays): a lane that hits is done (its limit becomes
 * -INFINITY, below every box and triangle) and the walk ends when all are;
 * a node's leaves in reach are tested before its children are descended
 * into, and the rest go nearer first, as the nearer boxes hold an occluder
 * sooner (measured faster on incoherent rays). */
#define QUERY occluded
#define QUERY_HIT(s, i, hit, t, u, v) \
    (PATH(take_hit)(s, i, hit, t, u, v, -INFINITY), PATH(every)((s)->index >= 0))
#define QUERY_NODE(s, r, n, mask) WALK_NAME(leaves_first)(s, r, n, mask, triangles)
#define QUERY_PARAMS
#define QUERY_ARGS
#include "walk.h"

/* The kernels already compute in vectors (a node's children); the hint
 * keeps Intel's CPU compiler from also packing work-items into SIMD lanes,
 * which measured slower (its default is to vectorise whenever the group
 * size allows). */
#define TRAVERSAL_KERNEL __kernel __attribute__((LANES_HINT))

/* Closest hits of the rays lanes[0, used) of a work-item as Hit records
 * (trace_intersect, in walk.h).  The hits' ids and normals are read once
 * every lane is traced: their cache misses then overlap instead of ending
 * each ray (measured faster). */
TRAVERSAL_INLINE void closest_hits(const RayLanes* lanes, uint used,
                                   __global const WideNode* nodes,
                                   __global const Triangle* triangles,
                                   __global const TriangleRef* refs, __global int* overflow,
                                   Hit* hits)
{
    int index[PACKET_SIZE];
    float t[PACKET_SIZE], u[PACKET_SIZE], v[PACKET_SIZE];
    trace_intersect(lanes, used, nodes, triangles, overflow, index, t, u, v, refs);
    for (uint l = 0; l < used; ++l)
        make_hit(hits + l, index[l], t[l], u[l], v[l], triangles, refs);
}

/* Occlusion of the rays lanes[0, used): occluded[l] = 1 if anything is hit. */
TRAVERSAL_INLINE void any_hits(const RayLanes* lanes, uint used, __global const WideNode* nodes,
                               __global const Triangle* triangles, __global int* overflow,
                               __global uchar* occluded)
{
    int index[PACKET_SIZE];
    trace_occluded(lanes, used, nodes, triangles, overflow, index, 0, 0, 0);
    for (uint l = 0; l < used; ++l)
        occluded[l] = index[l] >= 0 ? 1 : 0;
}

/* Closest hit of rays[0, ray_count) -> hits. */
TRAVERSAL_KERNEL void intersect_closest(__global const WideNode* nodes,
        __global const Triangle* triangles, __global const TriangleRef* refs,
        __global const Ray* rays, __global Hit* hits, __global int* overflow, const uint ray_count)
{
    RayLanes lanes;
    Hit found[PACKET_SIZE];
    uint first, used = packet_rays(ray_count, &first);
    if (used == 0)
        return;
    load_records(rays, first, used, &lanes);
    closest_hits(&lanes, used, nodes, triangles, refs, overflow, found);
    for (uint l = 0; l < used; ++l)
        hits[first + l] = found[l];
}

/* Occlusion of rays[0, ray_count): occluded[i] = 1 if anything is hit. */
TRAVERSAL_KERNEL void intersect_any(__global const WideNode* nodes,
        __global const Triangle* triangles, __global const Ray* rays, __global uchar* occluded,
        __global int* overflow, const uint ray_count)
{
    uint first, used = packet_rays(ray_count, &first);
    RayLanes lanes;
    if (used != 0) {
        load_records(rays, first, used, &lanes);
        any_hits(&lanes, used, nodes, triangles, overflow, occluded + first);
    }
}

TRAVERSAL_KERNEL void intersect_closest_arrays(__global const WideNode* nodes,
        __global const Triangle* triangles, __global const TriangleRef* refs,
        __global const float* origins, __global const float* directions,
        __global const float* tmin, const uint tmin_step, __global const float* tmax,
        const uint tmax_step, __global float* t_out, __global int* geom_out,
        __global int* prim_out, __global float* u_out, __global float* v_out,
        __global float* normal_out, __global float* points_out, __global int* overflow,
        const uint ray_count)
{
    uint first, used = packet_rays(ray_count, &first);
    if (used == 0)
        return;
    RayLanes lanes;
    load_arrays(first, used, origins, directions, tmin, tmin_step, tmax, tmax_step, &lanes);
    Hit found[PACKET_SIZE];
    closest_hits(&lanes, used, nodes, triangles, refs, overflow, found);
    for (uint l = 0; l < used; ++l) {
        uint i = first + l;
        t_out[i] = found[l].t;
        geom_out[i] = found[l].geom_id;
        prim_out[i] = found[l].prim_id;
        u_out[i] = found[l].u;
        v_out[i] = found[l].v;
        /* The hit point origin + t * direction, rounded as numpy would
         * (FP_CONTRACT is off), NaN on a miss: written here, where the ray
         * is at hand, rather than kept for the host to compute later. */
        for (uint k = 0; k < 3; ++k) {
            normal_out[3 * i + k] = found[l].normal[k];
            points_out[3 * i + k] = found[l].geom_id >= 0
                ? lanes.origin[k][l] + found[l].t * lanes.direction[k][l] : NAN;
        }
    }
}

TRAVERSAL_KERNEL void intersect_any_arrays(__global const WideNode* nodes,
        __global const Triangle* triangles, __global const float* origins,
        __global const float* directions, __global const float* tmin, const uint tmin_step,
        __global const float* tmax, const uint tmax_step, __global uchar* occluded,
        __global int* overflow, const uint ray_count)
{
    uint first, used = packet_rays(ray_count, &first);
    RayLanes lanes;
    if (used != 0) {
        load_arrays(first, used, origins, directions, tmin, tmin_step, tmax, tmax_step, &lanes);
        any_hits(&lanes, used, nodes, triangles, overflow, occluded + first);
    }
}
