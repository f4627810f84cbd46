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
 *   - u, v: hit = (1-u-v)*v0 + u*v1 + v*v2;
 *   - a flat scene's analytic spheres (-D SPHERES, query/rays/sphere.h)
 *     are tested after the walk; of a triangle and a sphere hit at one t,
 *     the triangle.
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
#include "core/launch.h"
#include "query/rays/work_item.h"
#include "query/rays/instance.h"
#ifdef ROOT_PHASE
#include "query/rays/mixed.h"
#endif
#ifdef SPHERES
#include "query/rays/sphere.h"
#endif

/* A work-item traces LANE_GROUPS groups of PACKET_SIZE rays (a -D define of
 * the host's, hlbvh_cl/query/rays.py's lane_groups, which sizes the
 * launches so; default 1).  Two on a flat scene on a CPU whose walks go
 * interleaved: the root phase ends many of a group's rays (on a ground, a
 * wall), and the walks left from both groups then go in turn together, more
 * of them to hide one another's cache misses (measured faster on incoherent
 * rays, and on bounces). */
#ifndef LANE_GROUPS
#define LANE_GROUPS 1
#endif
#if LANE_GROUPS > 1
#if !defined(ROOT_PHASE) || !defined(INTERLEAVED_WALKS)
#error "LANE_GROUPS > 1 is for flat scenes on CPUs whose walks go interleaved"
#endif
#define WALK_LANES (LANE_GROUPS * PACKET_SIZE)
#endif

/* The rays of work-item `item`: LANE_GROUPS groups of PACKET_SIZE from
 * *first, of which group g has used[g] (0 past ray_count: only the last
 * group that has any may have fewer than PACKET_SIZE); returns how many in
 * all. */
TRAVERSAL_INLINE uint item_rays(uint ray_count, uint item, uint* first, uint* used)
{
    *first = item * (LANE_GROUPS * PACKET_SIZE);
    uint total = 0;
    for (uint g = 0; g < LANE_GROUPS; ++g) {
        used[g] = rays_from(ray_count, *first + g * PACKET_SIZE);
        total += used[g];
    }
    return total;
}

/* This work-item's rays (item_rays) of a launch over ray_count rays. */
TRAVERSAL_INLINE uint group_rays(uint ray_count, uint* first, uint* used)
{
    return item_rays(ray_count, (uint)get_global_id(0), first, used);
}

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
 * met children go in slot order, unsorted (QUERY_UNORDERED): a shadow ray
 * wants any occluder, not the nearest, and sorting the children by entry
 * cost more than the earlier occluders it found saved (figures in the
 * commit that says so).  Leaves tested first at every node, the far ones
 * as often as not, had measured slower than that order on rays leaving a
 * surface. */
#define QUERY occluded
#define QUERY_UNORDERED
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

/* Lane l's closest hit as a Hit record: a flat scene's (make_hit, with
 * `normal`, the unit normal of the triangle hit), or on a two-level scene
 * the hit of the instance's mesh, whose mesh-frame normal goes to the world
 * by the instance (instance_normal). */
TRAVERSAL_INLINE void lane_hit(Hit* out, const HitLanes* found, uint l, float3 normal,
                               SCENE_PARAMS)
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
        LEAF_CORNERS(tri, triangles, i);
        float3 n = instance_normal(in, unit_normal(tri));
        hit.normal[0] = n.x;
        hit.normal[1] = n.y;
        hit.normal[2] = n.z;
        *out = hit;
        return;
    }
#endif
    make_hit(out, found->index[l], found->t[l], found->u[l], found->v[l], normal, refs);
}

/* Closest hits of a work-item's rays (group g: lanes[g], its first used[g]
 * lanes) as Hit records, group by group from hits[0], and their instances
 * (-1: none).  The hits' ids and normals are read once every lane is
 * traced: their cache misses then overlap instead of ending each ray
 * (measured faster).  `first` is the first ray's index (its mask's). */
TRAVERSAL_INLINE void closest_hits(RayLanes* lanes, const uint* used, uint first, SCENE_PARAMS,
                                   __global int* overflow, Hit* hits, int* instance)
{
#ifdef INSTANCES
    load_masks(lanes, first, used[0], ray_masks, mask_step);  /* one group (LANE_GROUPS) */
#endif
    HitLanes found[LANE_GROUPS];
    trace_intersect(lanes, used, SCENE_TREES, overflow, found, refs);
    for (uint g = 0; g < LANE_GROUPS; ++g) {
        if (used[g] == 0)
            break;  /* groups fill in order; an empty one's lanes were never loaded */
#if PACKET_SIZE > 1 && !defined(INSTANCES)
        PacketFloats normals[3];
        hit_normals(found + g, used[g], triangles, normals);
#endif
#if defined(SPHERES) && PACKET_SIZE > 1
        /* each lane's sphere nearer than its walk's hit (at its t, the
         * triangle), every lane at once */
        PacketInts sphere;
        PacketFloats sphere_t;
        int_packet walked = as_int_packet(vload_packet(0, (const float*)found[g].index)) >= 0;
        sphere_t.lanes = walked ? vload_packet(0, found[g].t) : vload_packet(0, lanes[g].tmax);
        sphere.lanes = nearest_sphere_packet(lanes + g, spheres, sphere_count, &sphere_t.lanes,
                                             walked);
#endif
        for (uint l = 0; l < used[g]; ++l) {
            uint i = g * PACKET_SIZE + l;
#ifdef SPHERES
#if PACKET_SIZE > 1
            int s = sphere.lane[l];
            float t = sphere_t.lane[l];
#else
            /* a sphere nearer than the walk's hit (at its t, the triangle) */
            bool walked = found[g].index[l] >= 0;
            float t = walked ? found[g].t[l] : lanes[g].tmax[l];
            int s = nearest_sphere(lanes + g, l, spheres, sphere_count, &t, walked);
#endif
            if (s >= 0) {
                sphere_hit(hits + i, lanes + g, l, spheres, sphere_geom, s, t);
                instance[i] = -1;
                continue;
            }
#endif
#if defined(INSTANCES)
            float3 normal = (float3)(0.0f);  /* lane_hit maps the mesh's own */
#elif PACKET_SIZE > 1
            float3 normal = (float3)(normals[0].lane[l], normals[1].lane[l], normals[2].lane[l]);
#else
            float3 normal = hit_normal(found[g].index[l], triangles);
#endif
            lane_hit(hits + i, found + g, l, normal, SCENE_ARGS);
#ifdef INSTANCES
            instance[i] = found[g].instance[l];
#else
            instance[i] = -1;
#endif
        }
    }
}

/* Occlusion of a work-item's rays, as closest_hits takes them: occluded[i]
 * = 1 if anything is hit. */
TRAVERSAL_INLINE void any_hits(RayLanes* lanes, const uint* used, uint first, SCENE_PARAMS,
                               __global int* overflow, __global uchar* occluded)
{
#ifdef INSTANCES
    load_masks(lanes, first, used[0], ray_masks, mask_step);
#endif
    HitLanes found[LANE_GROUPS];
    trace_occluded(lanes, used, SCENE_TREES, overflow, found);
    for (uint g = 0; g < LANE_GROUPS; ++g) {
        if (used[g] == 0)
            break;  /* as in closest_hits */
#if defined(SPHERES) && PACKET_SIZE > 1
        PacketInts sphere;  /* any_sphere of every lane at once */
        float_packet limit = vload_packet(0, lanes[g].tmax);
        sphere.lanes = nearest_sphere_packet(lanes + g, spheres, sphere_count, &limit,
                                             (int_packet)(0));
#endif
        for (uint l = 0; l < used[g]; ++l) {
            bool hit = found[g].index[l] >= 0;
#if defined(SPHERES) && PACKET_SIZE > 1
            hit = hit || sphere.lane[l] >= 0;
#elif defined(SPHERES)
            hit = hit || any_sphere(lanes + g, l, spheres, sphere_count);
#endif
            occluded[g * PACKET_SIZE + l] = hit ? 1 : 0;
        }
    }
}

/* The rays a launch over Ray records traces: ray_count, or where `counts`
 * is not null at most counts[count_at], a count the device wrote after the
 * host sized the launch (the path integrator's live paths and shadow rays:
 * the work-items past it return at once rather than trace empty rays). */
TRAVERSAL_INLINE uint rays_to_trace(uint ray_count, __global const uint* counts, uint count_at)
{
    return counts != 0 ? LESSER(ray_count, counts[count_at]) : ray_count;
}

/* This work-item's rays (item_rays) of a launch over Ray records.  Where
 * the device wrote a count (rays_to_trace), the work-groups that have rays
 * to trace are spread over the launch (core/launch.h's spread_group: the
 * launch is sized for the host's bound, of which the count may be a small
 * part; sampled before the spread, one PoCL thread of two was busy for
 * much of such launches); each ray is traced as before, so the results
 * are the same. */
TRAVERSAL_INLINE uint counted_rays(uint ray_count, __global const uint* counts, uint count_at,
                                   uint* first, uint* used)
{
    uint rays = rays_to_trace(ray_count, counts, count_at);
    if (counts == 0)
        return group_rays(rays, first, used);
    uint per_group = (uint)get_local_size(0) * (LANE_GROUPS * PACKET_SIZE);
    uint taken;
    if (!spread_group(((ulong)rays + per_group - 1u) / per_group, &taken)) {
        *first = 0;
        for (uint g = 0; g < LANE_GROUPS; ++g)
            used[g] = 0;
        return 0;
    }
    return item_rays(rays, taken * (uint)get_local_size(0) + (uint)get_local_id(0), first, used);
}

/* Closest hit of rays[0, rays_to_trace) -> hits, and where instance_out is
 * not null, the instance each hit (-1: none, or a flat scene): the path
 * integrator maps a mesh's shading normals to the world by it. */
TRAVERSAL_KERNEL void intersect_closest(SCENE_PARAMS, __global const Ray* rays, __global Hit* hits,
        __global int* instance_out, __global int* overflow, const uint ray_count,
        __global const uint* counts, const uint count_at)
{
    RayLanes lanes[LANE_GROUPS];
    Hit found[LANE_GROUPS * PACKET_SIZE];
    uint first, used[LANE_GROUPS];
    uint count = counted_rays(ray_count, counts, count_at, &first, used);
    if (count == 0)
        return;
    for (uint g = 0; g < LANE_GROUPS && used[g] != 0; ++g)
        load_records(rays, first + g * PACKET_SIZE, used[g], lanes + g);
    /* The lines this work-item's hits go to, asked for while it walks. */
    PREFETCH_LINES(hits + first, count * sizeof(Hit), 1);
    if (instance_out != 0)
        PREFETCH_LINES(instance_out + first, count * sizeof(int), 1);
    int instance[LANE_GROUPS * PACKET_SIZE];
    closest_hits(lanes, used, first, SCENE_ARGS, overflow, found, instance);
    for (uint i = 0; i < count; ++i)
        hits[first + i] = found[i];
    if (instance_out != 0)
        for (uint i = 0; i < count; ++i)
            instance_out[first + i] = instance[i];
}

/* Occlusion of rays[0, rays_to_trace): occluded[i] = 1 if anything is hit. */
TRAVERSAL_KERNEL void intersect_any(SCENE_PARAMS, __global const Ray* rays,
        __global uchar* occluded,
        __global int* overflow, const uint ray_count,
        __global const uint* counts, const uint count_at)
{
    RayLanes lanes[LANE_GROUPS];
    uint first, used[LANE_GROUPS];
    if (counted_rays(ray_count, counts, count_at, &first, used) == 0)
        return;
    for (uint g = 0; g < LANE_GROUPS && used[g] != 0; ++g)
        load_records(rays, first + g * PACKET_SIZE, used[g], lanes + g);
    any_hits(lanes, used, first, SCENE_ARGS, overflow, occluded + first);
}

TRAVERSAL_KERNEL void intersect_closest_arrays(SCENE_PARAMS, __global const float* origins, __global const float* directions,
        __global const float* tmin, const uint tmin_step, __global const float* tmax,
        const uint tmax_step, __global float* t_out, __global int* geom_out,
        __global int* prim_out, __global float* u_out, __global float* v_out,
        __global float* normal_out, __global float* points_out, __global int* instance_out,
        __global int* overflow,
        const uint ray_count)
{
    RayLanes lanes[LANE_GROUPS];
    uint first, used[LANE_GROUPS];
    uint count = group_rays(ray_count, &first, used);
    if (count == 0)
        return;
    for (uint g = 0; g < LANE_GROUPS && used[g] != 0; ++g)
        load_arrays(first + g * PACKET_SIZE, used[g], origins, directions, tmin, tmin_step,
                    tmax, tmax_step, lanes + g);
    Hit found[LANE_GROUPS * PACKET_SIZE];
    int instance[LANE_GROUPS * PACKET_SIZE];
    closest_hits(lanes, used, first, SCENE_ARGS, overflow, found, instance);
    for (uint j = 0; j < count; ++j) {
        uint i = first + j, l = j % PACKET_SIZE;
        const RayLanes* group = lanes + j / PACKET_SIZE;
        instance_out[i] = instance[j];
        t_out[i] = found[j].t;
        geom_out[i] = found[j].geom_id;
        prim_out[i] = found[j].prim_id;
        u_out[i] = found[j].u;
        v_out[i] = found[j].v;
        /* The hit point origin + t * direction, rounded as numpy would
         * (FP_CONTRACT is off), NaN on a miss: written here, where the ray
         * is at hand, rather than kept for the host to compute later. */
        for (uint k = 0; k < 3; ++k) {
            normal_out[3 * (size_t)i + k] = found[j].normal[k];
            points_out[3 * (size_t)i + k] = found[j].geom_id >= 0
                ? group->origin[k][l] + found[j].t * group->direction[k][l] : NAN;
        }
    }
}

TRAVERSAL_KERNEL void intersect_any_arrays(SCENE_PARAMS, __global const float* origins,
        __global const float* directions, __global const float* tmin, const uint tmin_step,
        __global const float* tmax, const uint tmax_step, __global uchar* occluded,
        __global int* overflow, const uint ray_count)
{
    RayLanes lanes[LANE_GROUPS];
    uint first, used[LANE_GROUPS];
    if (group_rays(ray_count, &first, used) == 0)
        return;
    for (uint g = 0; g < LANE_GROUPS && used[g] != 0; ++g)
        load_arrays(first + g * PACKET_SIZE, used[g], origins, directions, tmin, tmin_step,
                    tmax, tmax_step, lanes + g);
    any_hits(lanes, used, first, SCENE_ARGS, overflow, occluded + first);
}
