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
#include "query/packet.h"
#else
#include "query/ray.h"
#endif
#include "query/work_item.h"
#include "query/instance.h"

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
#include "query/walk.h"

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
#include "query/walk.h"

/* The kernels already compute in vectors (a node's children); the hint
 * keeps Intel's CPU compiler from also packing work-items into SIMD lanes,
 * which measured slower (its default is to vectorise whenever the group
 * size allows). */
#define TRAVERSAL_KERNEL __kernel __attribute__((LANES_HINT))

#ifndef INSTANCES
/* Closest hits of the rays lanes[0, used) of a work-item as Hit records
 * (trace_intersect, in walk.h), and their instances (none: -1).  The hits'
 * ids and normals are read once every lane is traced: their cache misses
 * then overlap instead of ending each ray (measured faster).  `first` (the
 * first ray's index) is the instanced version's. */
TRAVERSAL_INLINE void closest_hits(RayLanes* lanes, uint used, uint first, SCENE_PARAMS,
                                   __global int* overflow, Hit* hits, int* instance)
{
    int index[PACKET_SIZE];
    float t[PACKET_SIZE], u[PACKET_SIZE], v[PACKET_SIZE];
    trace_intersect(lanes, used, nodes, triangles, overflow, index, t, u, v, refs);
    for (uint l = 0; l < used; ++l) {
        make_hit(hits + l, index[l], t[l], u[l], v[l], triangles, refs);
        instance[l] = -1;
    }
}

/* Occlusion of the rays lanes[0, used): occluded[l] = 1 if anything is hit. */
TRAVERSAL_INLINE void any_hits(RayLanes* lanes, uint used, uint first, SCENE_PARAMS,
                               __global int* overflow, __global uchar* occluded)
{
    int index[PACKET_SIZE];
    trace_occluded(lanes, used, nodes, triangles, overflow, index, 0, 0, 0);
    for (uint l = 0; l < used; ++l)
        occluded[l] = index[l] >= 0 ? 1 : 0;
}

#else /* INSTANCES */

/* Closest hit, one ray: each visible instance of the leaf in turn, its mesh
 * walked by the flat visitor with the walk's state, so the limit found so
 * far prunes it; the instance whose walk lowered t holds the hit. */
TRAVERSAL_INLINE bool instances_intersect_ray(Found_ray* s, const RayData* r, int first,
                                              uint count INSTANCE_PARAMS)
{
    for (uint i = (uint)first; i < (uint)first + count; ++i) {
        INSTANCE_AT(i);
        RayData mapped;
        if (!instance_ray(&mapped, in, r))
            continue;
        float before = s->t;
        *mesh_overflow |= walk_intersect_ray(&mapped, MESH_TREE(in), s,
                                            mesh_refs + in->triangle_base);
        if (s->t != before)
            s->instance = top_refs[i].prim_id;
    }
    return false;
}

/* Any hit, one ray: the first instance with a hit ends the walk. */
TRAVERSAL_INLINE bool instances_occluded_ray(Found_ray* s, const RayData* r, int first,
                                             uint count INSTANCE_PARAMS)
{
    for (uint i = (uint)first; i < (uint)first + count; ++i) {
        INSTANCE_AT(i);
        RayData mapped;
        if (!instance_ray(&mapped, in, r))
            continue;
        *mesh_overflow |= walk_occluded_ray(&mapped, MESH_TREE(in), s);
        if (s->index >= 0) {
            s->instance = top_refs[i].prim_id;
            return true;
        }
    }
    return false;
}

#if PACKET_SIZE > 1
/* The lanes of a mapped packet that prepare_packet turned down (their
 * mapped directions disagree in sign), each walked as one ray with its
 * lane's state: `walk` and its extra arguments.  Lanes the instance is
 * hidden from (tmin inf) and lanes done (limit -inf) are skipped.  `tree`
 * is the walk's arguments before its state: one macro naming several (OpenCL
 * C has no variadic macros, 6.9). */
#define WALK_LANES(s, lanes, walk, tree)                                                 \
    do {                                                                                 \
        int index_[PACKET_SIZE];                                                         \
        float t_[PACKET_SIZE], u_[PACKET_SIZE], v_[PACKET_SIZE], limit_[PACKET_SIZE];    \
        vstore_packet((s)->index, 0, index_);                                            \
        vstore_packet((s)->t, 0, t_);                                                    \
        vstore_packet((s)->u, 0, u_);                                                    \
        vstore_packet((s)->v, 0, v_);                                                    \
        vstore_packet((s)->limit, 0, limit_);                                            \
        for (uint l = 0; l < PACKET_SIZE; ++l) {                                         \
            if (!((lanes)->tmin[l] <= limit_[l]))                                        \
                continue;                                                                \
            RayData one;                                                                 \
            prepare_lane(&one, lanes, l);                                                \
            Found_ray f = {index_[l], t_[l], u_[l], v_[l], limit_[l]};                   \
            *mesh_overflow |= walk(&one, tree, &f);                                       \
            index_[l] = f.index;                                                         \
            t_[l] = f.t;                                                                 \
            u_[l] = f.u;                                                                 \
            v_[l] = f.v;                                                                 \
            limit_[l] = f.limit;                                                         \
        }                                                                                \
        (s)->index = vload_packet(0, index_);                                            \
        (s)->t = vload_packet(0, t_);                                                    \
        (s)->u = vload_packet(0, u_);                                                    \
        (s)->v = vload_packet(0, v_);                                                    \
        (s)->limit = vload_packet(0, limit_);                                            \
        update_reach_packet(s);                                                          \
    } while (0)

/* The walks' argument orders (state last, for WALK_LANES). */
#define intersect_lane(r, n, t, refs, s) walk_intersect_ray(r, n, t, s, refs)
#define occluded_lane(r, n, t, s) walk_occluded_ray(r, n, t, s)

/* Closest hit, a packet: as instances_intersect_ray, the mesh walked as a
 * packet where the mapped rays allow it. */
TRAVERSAL_INLINE bool instances_intersect_packet(Found_packet* s, const Packet* r, int first,
                                                 uint count INSTANCE_PARAMS)
{
    for (uint i = (uint)first; i < (uint)first + count; ++i) {
        INSTANCE_AT(i);
        RayLanes lanes;
        if (!instance_lanes(&lanes, in, r))
            continue;
        float_packet before = s->t;
        Packet mapped;
        if (prepare_packet(&lanes, &mapped))
            *mesh_overflow |= walk_intersect_packet(&mapped, MESH_TREE(in), s,
                                                   mesh_refs + in->triangle_base);
        else
            WALK_LANES(s, &lanes, intersect_lane, MESH_TREE_REFS(in));
        s->instance = s->t != before ? (int_packet)(top_refs[i].prim_id) : s->instance;
    }
    return false;
}

/* Any hit, a packet: the walk ends once every lane has one. */
TRAVERSAL_INLINE bool instances_occluded_packet(Found_packet* s, const Packet* r, int first,
                                                uint count INSTANCE_PARAMS)
{
    for (uint i = (uint)first; i < (uint)first + count; ++i) {
        INSTANCE_AT(i);
        RayLanes lanes;
        if (!instance_lanes(&lanes, in, r))
            continue;
        int_packet before = s->index;
        Packet mapped;
        if (prepare_packet(&lanes, &mapped))
            *mesh_overflow |= walk_occluded_packet(&mapped, MESH_TREE(in), s);
        else
            WALK_LANES(s, &lanes, occluded_lane, MESH_TREE(in));
        s->instance = s->index != before ? (int_packet)(top_refs[i].prim_id) : s->instance;
        if (every_packet(s->index >= 0))
            return true;
    }
    return false;
}
#endif

#define QUERY intersect_top
#define QUERY_LEAF(s, r, first, count) PATH(instances_intersect)(s, r, first, count INSTANCE_ARGS)
#define QUERY_NODE(s, r, n, mask) false
#define QUERY_PARAMS INSTANCE_PARAMS
#define QUERY_ARGS INSTANCE_ARGS
#include "query/walk.h"

#define QUERY occluded_top
#define QUERY_LEAF(s, r, first, count) PATH(instances_occluded)(s, r, first, count INSTANCE_ARGS)
#define QUERY_NODE(s, r, n, mask) WALK_NAME(leaves_first)(s, r, n, mask, triangles INSTANCE_ARGS)
#define QUERY_PARAMS INSTANCE_PARAMS
#define QUERY_ARGS INSTANCE_ARGS
#include "query/walk.h"

/* Closest hits of the rays lanes[0, used) walked from the top, as Hit
 * records with their instances; the hit's mesh-frame normal goes to the
 * world by its instance (instance_normal). */
TRAVERSAL_INLINE void closest_hits(RayLanes* lanes, uint used, uint first, SCENE_PARAMS,
                                   __global int* overflow, Hit* hits, int* instance)
{
    load_masks(lanes, first, used, ray_masks, mask_step);
    int index[PACKET_SIZE];
    float t[PACKET_SIZE], u[PACKET_SIZE], v[PACKET_SIZE];
    bool out_of_stack = false;
    trace_intersect_top(lanes, used, top_nodes, top_triangles, overflow, index, t, u, v,
                        instance, TOP_ARGS(&out_of_stack));
    if (out_of_stack)
        overflow[0] = 1;
    for (uint l = 0; l < used; ++l) {
        if (index[l] < 0) {
            make_hit(hits + l, -1, 0.0f, 0.0f, 0.0f, triangles, refs);
            continue;
        }
        __global const Instance* in = instances + instance[l];
        int i = in->triangle_base + index[l];
        Hit hit;
        hit.t = t[l];
        hit.geom_id = in->mesh;
        hit.prim_id = refs[i].prim_id;
        hit.u = u[l];
        hit.v = v[l];
        float3 n = instance_normal(in, unit_normal(triangles + i));
        hit.normal[0] = n.x;
        hit.normal[1] = n.y;
        hit.normal[2] = n.z;
        hits[l] = hit;
    }
}

TRAVERSAL_INLINE void any_hits(RayLanes* lanes, uint used, uint first, SCENE_PARAMS,
                               __global int* overflow, __global uchar* occluded)
{
    load_masks(lanes, first, used, ray_masks, mask_step);
    int index[PACKET_SIZE], instance[PACKET_SIZE];
    bool out_of_stack = false;
    trace_occluded_top(lanes, used, top_nodes, top_triangles, overflow, index, 0, 0, 0,
                       instance, TOP_ARGS(&out_of_stack));
    if (out_of_stack)
        overflow[0] = 1;
    for (uint l = 0; l < used; ++l)
        occluded[l] = index[l] >= 0 ? 1 : 0;
}
#endif /* INSTANCES */

/* Closest hit of rays[0, ray_count) -> hits. */
TRAVERSAL_KERNEL void intersect_closest(SCENE_PARAMS, __global const Ray* rays, __global Hit* hits, __global int* overflow, const uint ray_count)
{
    RayLanes lanes;
    Hit found[PACKET_SIZE];
    uint first, used = packet_rays(ray_count, &first);
    if (used == 0)
        return;
    load_records(rays, first, used, &lanes);
    int instance[PACKET_SIZE];
    closest_hits(&lanes, used, first, SCENE_ARGS, overflow, found, instance);
    for (uint l = 0; l < used; ++l)
        hits[first + l] = found[l];
}

/* Occlusion of rays[0, ray_count): occluded[i] = 1 if anything is hit. */
TRAVERSAL_KERNEL void intersect_any(SCENE_PARAMS, __global const Ray* rays,
        __global uchar* occluded,
        __global int* overflow, const uint ray_count)
{
    uint first, used = packet_rays(ray_count, &first);
    RayLanes lanes;
    if (used != 0) {
        load_records(rays, first, used, &lanes);
        any_hits(&lanes, used, first, SCENE_ARGS, overflow, occluded + first);
    }
}

TRAVERSAL_KERNEL void intersect_closest_arrays(SCENE_PARAMS, __global const float* origins, __global const float* directions,
        __global const float* tmin, const uint tmin_step, __global const float* tmax,
        const uint tmax_step, __global float* t_out, __global int* geom_out,
        __global int* prim_out, __global float* u_out, __global float* v_out,
        __global float* normal_out, __global float* points_out, __global int* instance_out,
        __global int* overflow,
        const uint ray_count)
{
    uint first, used = packet_rays(ray_count, &first);
    if (used == 0)
        return;
    RayLanes lanes;
    load_arrays(first, used, origins, directions, tmin, tmin_step, tmax, tmax_step, &lanes);
    Hit found[PACKET_SIZE];
    int instance[PACKET_SIZE];
    closest_hits(&lanes, used, first, SCENE_ARGS, overflow, found, instance);
    for (uint l = 0; l < used; ++l) {
        uint i = first + l;
        instance_out[i] = instance[l];
        t_out[i] = found[l].t;
        geom_out[i] = found[l].geom_id;
        prim_out[i] = found[l].prim_id;
        u_out[i] = found[l].u;
        v_out[i] = found[l].v;
        /* The hit point origin + t * direction, rounded as numpy would
         * (FP_CONTRACT is off), NaN on a miss: written here, where the ray
         * is at hand, rather than kept for the host to compute later. */
        for (uint k = 0; k < 3; ++k) {
            normal_out[3 * (size_t)i + k] = found[l].normal[k];
            points_out[3 * (size_t)i + k] = found[l].geom_id >= 0
                ? lanes.origin[k][l] + found[l].t * lanes.direction[k][l] : NAN;
        }
    }
}

TRAVERSAL_KERNEL void intersect_any_arrays(SCENE_PARAMS, __global const float* origins,
        __global const float* directions, __global const float* tmin, const uint tmin_step,
        __global const float* tmax, const uint tmax_step, __global uchar* occluded,
        __global int* overflow, const uint ray_count)
{
    uint first, used = packet_rays(ray_count, &first);
    RayLanes lanes;
    if (used != 0) {
        load_arrays(first, used, origins, directions, tmin, tmin_step, tmax, tmax_step, &lanes);
        any_hits(&lanes, used, first, SCENE_ARGS, overflow, occluded + first);
    }
}
