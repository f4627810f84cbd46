/* Two-level scenes, the rays' side: a top tree whose leaves hold instances
 * (core/tree.h's Instance), each a mesh's own tree under an affine map, as
 * Embree's and Mitsuba's instances (and pbrt-v4's TransformedPrimitive).
 * The walk of the top tree is the one walk (query/walk/walk.h) whose leaves
 * (query/walk/instance_leaf.h) map the rays into each instance's mesh frame
 * and walk that mesh's tree with the same query state (trace.h): the ray is
 * mapped, not renormalised, so t, the limit and every hit found so far mean
 * the same in both frames.  This header maps rays (query/walk/two_level.h
 * has the maps themselves) and gives the ray kernels their scene parameters.
 * A packet of rays is mapped lane by lane and walks the mesh's tree as a
 * packet when its mapped rays still share their direction signs
 * (prepare_packet), else one ray at a time. */
#ifndef INSTANCE_H
#define INSTANCE_H

#include "query/normals.h"
#include "query/rays/ray.h"
#if PACKET_SIZE > 1
#include "query/rays/packet.h"
#endif
#include "query/walk/two_level.h"

#ifdef INSTANCES
/* What a path's rays become in an instance's frame (map_instance_ray,
 * map_instance_packet): one ray prepared for the mesh's tree, a packet's
 * lanes for prepare_packet. */
typedef RayData Mapped_ray;
typedef RayLanes Mapped_packet;

/* Whether the ray sees the instance ((ray mask & instance mask) != 0, as
 * Embree), and if so the ray in the instance's mesh frame, prepared for its
 * tree (*out). */
TRAVERSAL_INLINE bool map_instance_ray(RayData* out, __global const Instance* in, const RayData* r)
{
    if ((in->mask & r->mask) == 0)
        return false;
    float o[3], d[3];
    for (int row = 0; row < 3; ++row) {
        __global const float* m = in->to_mesh + 4 * row;
        o[row] = (float)MAP_POINT(m, r->ox, r->oy, r->oz);
        d[row] = (float)MAP_DIRECTION(m, r->dx, r->dy, r->dz);
    }
    prepare_ray(out, (float3)(o[0], o[1], o[2]), (float3)(d[0], d[1], d[2]), r->tmin, r->tmax);
    return true;
}

#if PACKET_SIZE > 1
/* A packet's rays in the instance's mesh frame, as lanes for prepare_packet
 * (or for one-by-one walks where it turns them down); the lanes whose mask
 * hides the instance get tmin = inf, which no box or triangle meets.  False
 * when the instance is hidden from every lane. */
TRAVERSAL_INLINE bool map_instance_packet(RayLanes* out, __global const Instance* in,
                                         const Packet* p)
{
    int_packet seen = (p->mask & (int_packet)((int)in->mask)) != (int_packet)(0);
    if (!some_packet(seen))
        return false;
    for (int row = 0; row < 3; ++row) {
        __global const float* m = in->to_mesh + 4 * row;
#ifdef cl_khr_fp64
        vstore_packet(to_float_packet(MAP_POINT(m, to_double_packet(p->ox),
                                                to_double_packet(p->oy),
                                                to_double_packet(p->oz))), 0, out->origin[row]);
        vstore_packet(to_float_packet(MAP_DIRECTION(m, to_double_packet(p->dx),
                                                    to_double_packet(p->dy),
                                                    to_double_packet(p->dz))), 0,
                      out->direction[row]);
#else
        vstore_packet(MAP_POINT(m, p->ox, p->oy, p->oz), 0, out->origin[row]);
        vstore_packet(MAP_DIRECTION(m, p->dx, p->dy, p->dz), 0, out->direction[row]);
#endif
    }
    vstore_packet(seen ? p->tmin : (float_packet)(INFINITY), 0, out->tmin);
    vstore_packet(p->tmax, 0, out->tmax);
    vstore_packet(as_float_packet(p->mask), 0, (float*)out->mask);
    return true;
}
#endif

/* A mesh-frame normal in the world: the inverse transpose of the
 * instance's map (the transpose of to_mesh's linear part), turned by the
 * sign of its determinant so that it stays cross(v1 - v0, v2 - v0) of the
 * mapped vertices (a mirror flips the winding); unit length. */
TRAVERSAL_INLINE float3 instance_normal(__global const Instance* in, float3 n)
{
    __global const float* m = in->to_mesh;
    return unit_vector((float3)((m[0] * n.x + m[4] * n.y) + m[8] * n.z,
                                (m[1] * n.x + m[5] * n.y) + m[9] * n.z,
                                (m[2] * n.x + m[6] * n.y) + m[10] * n.z) * in->normal_sign);
}

#endif /* INSTANCES (the map) */

/* The scene a ray kernel traces, as its first parameters (SCENE_PARAMS;
 * SCENE_ARGS passes them on; hlbvh_cl/query/rays.py's scene_args gives
 * them), and the trees its trace walks (SCENE_TREES, trace.h's trace_QUERY).
 * Macros: parameter lists (a kernel cannot take a struct of pointers). */
#ifndef INSTANCES
/* A flat scene: one tree over every mesh's triangles. */
#ifndef SPHERES
#define SCENE_PARAMS                                                                    \
    __global const WideNode *nodes, __global const Leaf *triangles,                      \
        __global const TriangleRef *refs
#define SCENE_ARGS nodes, triangles, refs
#else
/* ... and its analytic spheres (query/rays/sphere.h), after the meshes. */
#define SCENE_PARAMS                                                                    \
    __global const WideNode *nodes, __global const Leaf *triangles,                      \
        __global const TriangleRef *refs, __global const float4 *spheres,                \
        const uint sphere_count, const int sphere_geom
#define SCENE_ARGS nodes, triangles, refs, spheres, sphere_count, sphere_geom
#endif
#define SCENE_TREES nodes, triangles
#else
/* A two-level scene: the top tree over the instances, the instances, the
 * rays' masks (ray_masks[i * mask_step]: step 0, one mask for all) and the
 * meshes' trees one after another. */
#define SCENE_PARAMS                                                                    \
    __global const WideNode *top_nodes, __global const Leaf *top_triangles,              \
        __global const TriangleRef *top_refs, __global const Instance *instances,        \
        __global const uint *ray_masks, const uint mask_step,                             \
        __global const WideNode *nodes, __global const Leaf *triangles,                  \
        __global const TriangleRef *refs
#define SCENE_ARGS top_nodes, top_triangles, top_refs, instances, ray_masks, mask_step, nodes, \
                   triangles, refs
#define SCENE_TREES top_nodes, top_triangles, top_refs, instances, nodes, triangles

/* The rays' masks into the lanes (lanes past `used` repeat the last). */
TRAVERSAL_INLINE void load_masks(RayLanes* lanes, uint first, uint used,
                                 __global const uint* ray_masks, uint mask_step)
{
    for (uint l = 0; l < PACKET_SIZE; ++l)
        lanes->mask[l] = ray_masks[(first + LESSER(l, used - 1)) * mask_step];
}
#endif /* INSTANCES */

#endif /* INSTANCE_H */
