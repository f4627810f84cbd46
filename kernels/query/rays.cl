/* Ray queries: closest hit and any hit, two visitors of the one walk of the
 * wide tree (query/walk/walk.h) with the watertight ray/triangle test of
 * Woop, Benthin & Wald 2013 (query/rays/triangle.h), traced by
 * query/rays/trace.h.  A work-item traces PACKET_SIZE consecutive rays: on
 * CPUs as one packet when they are coherent (query/rays/packet.h), else one
 * by one.
 *
 * Kernels
 *   intersect_closest  nearest hit in [tmin, tmax] -> Hit
 *   intersect_any      1 if any hit in [tmin, tmax] (stops at the first one)
 *   intersect_closest_arrays, intersect_any_arrays
 *                      the same on numpy-shaped arrays (one per field)
 *
 * Conventions (tests/support/oracle.py follows the same ones)
 *   - a hit at distance t counts when tmin <= t <= tmax (both ends closed,
 *     as Embree's tnear <= t <= tfar); t is in units of |direction|;
 *   - no culling: both sides of a triangle are hit;
 *   - degenerate triangles (zero edge cross product) are never hit;
 *   - u, v: hit = (1-u-v)*v0 + u*v1 + v*v2.
 *
 * Compile-time parameters (-D)
 *   STACK_SIZE  entries of the private traversal stack; the host passes a
 *               bound that cannot overflow for the tree (hlbvh_cl/query/), and if
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
#include "core/portable.h"
#include "query/rays/work_item.h"
#include "query/rays/instance.h"
#ifdef ROOT_PHASE
#include "query/rays/mixed.h"
#endif

/* A closest hit's ids (refs[i]) are read when the traversal ends, a cache
 * miss of their own: start loading them when the hit is found. */
TRAVERSAL_INLINE void prefetch_hit_ids(__global const TriangleRef* refs, uint i)
{
#ifdef PREFETCH
    __builtin_prefetch(refs + i);
#endif
}

/* Closest hit: a hit lowers the lane's limit to its t, and the walk goes on
 * in case a nearer one follows; nearer children first.  An instance's mesh
 * prefetches from its own refs.  Rays traced one by one on a CPU have the
 * root's leaves that any of the work-item's rays meets tested first, for all
 * of them at once (trace.h's root phase), and their walks skip those. */
#define QUERY intersect
#define QUERY_OUT HitLanes
#define QUERY_HIT(s, i, hit, t, u, v) \
    (prefetch_hit_ids(refs, i), PATH(take_hit)(s, i, hit, t, u, v, t), false)
#define QUERY_END(s, out, l) PATH(store_hit)(s, out, l)
#define QUERY_PARAMS , __global const TriangleRef* refs
#define QUERY_ARGS , refs
#define QUERY_MESH_ARGS(in, id) , refs + (in)->triangle_base
#define QUERY_ROOT_PHASE
#define QUERY_NODE(s, r, n, mask) ((n) == nodes && (*(mask) &= ~PATH(root_done)(s), false))
#include "query/rays/trace.h"

/* Any hit (shadow rays): a lane that hits is done (its limit becomes
 * -INFINITY, below every box and triangle) and the walk ends when all are.
 * The root's leaves in reach are tested before its children are descended
 * into: the SAH top isolates the largest triangles (a ground, a wall) at
 * the top of the tree, where they end most shadow rays at once.  Rays
 * traced one by one on a CPU have those leaves tested for all of them at
 * once, as the closest hit does (trace.h's root phase: which hit a lane
 * takes does not change whether it has one); a lane the phase occludes, or
 * that meets no interior child of the root, takes no walk.  Deeper, the
 * children go nearer first, leaves too, as the nearer boxes hold an occluder
 * sooner: leaves tested first there are the far ones as often as not
 * (measured slower on rays leaving a surface). */
#define QUERY occluded
#define QUERY_OUT HitLanes
#define QUERY_ENDS(s) PATH(every)((s)->index >= 0)
#define QUERY_HIT(s, i, hit, t, u, v) \
    (PATH(take_hit)(s, i, hit, t, u, v, -INFINITY), QUERY_ENDS(s))
#define QUERY_ROOT_PHASE
#define QUERY_NODE(s, r, n, mask)                                    \
    ((n) == nodes && (*(mask) &= ~PATH(root_done)(s),                \
                      WALK_NAME(leaves_first)(s, r, n, mask, triangles WALK_ARGS)))
#define QUERY_END(s, out, l) PATH(store_index)(s, out, l)
#include "query/rays/trace.h"

/* Lane l's closest hit as a Hit record: a flat scene's (make_hit), or on a
 * two-level scene the hit of the instance's mesh, whose mesh-frame normal
 * goes to the world by the instance (instance_normal). */
TRAVERSAL_INLINE void lane_hit(Hit* out, const HitLanes* found, uint l, SCENE_PARAMS)
{
#ifdef INSTANCES
    if (found->index[l] >= 0) {
        __global const Instance* in = instances + found->instance[l];
        int i = in->triangle_base + found->index[l];
        Hit hit;
        hit.t = found->t[l];
        hit.geom_id = in->mesh;
        hit.prim_id = refs[i].prim_id;
        hit.u = found->u[l];
        hit.v = found->v[l];
        float3 n = instance_normal(in, unit_normal(triangles + i));
        hit.normal[0] = n.x;
        hit.normal[1] = n.y;
        hit.normal[2] = n.z;
        *out = hit;
        return;
    }
#endif
    make_hit(out, found->index[l], found->t[l], found->u[l], found->v[l], triangles, refs);
}

/* Closest hits of the rays lanes[0, used) of a work-item as Hit records, and
 * their instances (-1: none).  The hits' ids and normals are read once every
 * lane is traced: their cache misses then overlap instead of ending each ray
 * (measured faster).  `first` is the first ray's index (its mask's). */
TRAVERSAL_INLINE void closest_hits(RayLanes* lanes, uint used, uint first, SCENE_PARAMS,
                                   __global int* overflow, Hit* hits, int* instance)
{
#ifdef INSTANCES
    load_masks(lanes, first, used, ray_masks, mask_step);
#endif
    HitLanes found;
    trace_intersect(lanes, used, SCENE_TREES, overflow, &found, refs);
    for (uint l = 0; l < used; ++l) {
        lane_hit(hits + l, &found, l, SCENE_ARGS);
#ifdef INSTANCES
        instance[l] = found.instance[l];
#else
        instance[l] = -1;
#endif
    }
}

/* Occlusion of the rays lanes[0, used): occluded[l] = 1 if anything is hit. */
TRAVERSAL_INLINE void any_hits(RayLanes* lanes, uint used, uint first, SCENE_PARAMS,
                               __global int* overflow, __global uchar* occluded)
{
#ifdef INSTANCES
    load_masks(lanes, first, used, ray_masks, mask_step);
#endif
    HitLanes found;
    trace_occluded(lanes, used, SCENE_TREES, overflow, &found);
    for (uint l = 0; l < used; ++l)
        occluded[l] = found.index[l] >= 0 ? 1 : 0;
}

/* The rays a launch over Ray records traces: ray_count, or where `counts`
 * is not null at most counts[count_at], a count the device wrote after the
 * host sized the launch (the path integrator's live paths and shadow rays:
 * the work-items past it return at once rather than trace empty rays). */
TRAVERSAL_INLINE uint rays_to_trace(uint ray_count, __global const uint* counts, uint count_at)
{
    return counts != 0 ? LESSER(ray_count, counts[count_at]) : ray_count;
}

/* Closest hit of rays[0, rays_to_trace) -> hits, and where instance_out is
 * not null, the instance each hit (-1: none, or a flat scene): the path
 * integrator maps a mesh's shading normals to the world by it. */
TRAVERSAL_KERNEL void intersect_closest(SCENE_PARAMS, __global const Ray* rays, __global Hit* hits,
        __global int* instance_out, __global int* overflow, const uint ray_count,
        __global const uint* counts, const uint count_at)
{
    RayLanes lanes;
    Hit found[PACKET_SIZE];
    uint first, used = packet_rays(rays_to_trace(ray_count, counts, count_at), &first);
    if (used == 0)
        return;
    load_records(rays, first, used, &lanes);
    /* The lines this work-item's hits go to, asked for while it walks. */
    PREFETCH_LINES(hits + first, PACKET_SIZE * sizeof(Hit), 1);
    if (instance_out != 0)
        PREFETCH_LINES(instance_out + first, PACKET_SIZE * sizeof(int), 1);
    int instance[PACKET_SIZE];
    closest_hits(&lanes, used, first, SCENE_ARGS, overflow, found, instance);
    for (uint l = 0; l < used; ++l)
        hits[first + l] = found[l];
    if (instance_out != 0)
        for (uint l = 0; l < used; ++l)
            instance_out[first + l] = instance[l];
}

/* Occlusion of rays[0, rays_to_trace): occluded[i] = 1 if anything is hit. */
TRAVERSAL_KERNEL void intersect_any(SCENE_PARAMS, __global const Ray* rays,
        __global uchar* occluded,
        __global int* overflow, const uint ray_count,
        __global const uint* counts, const uint count_at)
{
    uint first, used = packet_rays(rays_to_trace(ray_count, counts, count_at), &first);
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
