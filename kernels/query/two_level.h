/* What every query of a two-level scene shares, rays or points: an
 * instance's affine maps (hlbvh.h's Instance), and the parameters by which a
 * top tree's leaf visitor reaches the instances and their meshes' trees.
 * instance.h adds the rays' side, points.cl the points'. */
#ifndef TWO_LEVEL_H
#define TWO_LEVEL_H

#include "query/node.h"

#ifdef INSTANCES
#ifdef cl_khr_fp64
typedef double map_real;
#else
typedef float map_real;
#endif

/* Component `row` of a 3x4 map (m: that row's four floats) applied to a
 * point (with the offset) or a direction (without): in a fixed order
 * (FP_CONTRACT is off in node.h), so every device maps alike, and in double
 * where the device has it, so only the final rounding to float stands
 * between the mapped value and the exact one. */
#define MAP_POINT(m, x, y, z) \
    (((map_real)(m)[0] * (x) + (map_real)(m)[1] * (y)) + (map_real)(m)[2] * (z) + (map_real)(m)[3])
#define MAP_DIRECTION(m, x, y, z) \
    (((map_real)(m)[0] * (x) + (map_real)(m)[1] * (y)) + (map_real)(m)[2] * (z))

/* The point p under the 3x4 row-major map m (to_mesh or to_world). */
TRAVERSAL_INLINE float3 map_point(__global const float* m, float3 p)
{
    return (float3)((float)MAP_POINT(m, p.x, p.y, p.z), (float)MAP_POINT(m + 4, p.x, p.y, p.z),
                    (float)MAP_POINT(m + 8, p.x, p.y, p.z));
}

/* What the top tree's leaf visitors use besides the walk's own: top_refs[i]
 * .prim_id is the instance in leaf slot i; *mesh_overflow is set when a
 * mesh's walk runs out of stack. */
#define INSTANCE_PARAMS                                                                 \
    , __global const TriangleRef *top_refs, __global const Instance *instances,          \
        __global const WideNode *mesh_nodes, __global const Triangle *mesh_triangles,    \
        __global const TriangleRef *mesh_refs, bool *mesh_overflow
#define INSTANCE_ARGS , top_refs, instances, mesh_nodes, mesh_triangles, mesh_refs, mesh_overflow
/* The top walk's arguments from a kernel's scene parameters (top_refs,
 * instances, and the meshes' nodes, triangles and refs). */
#define TOP_ARGS(overflow_flag) top_refs, instances, nodes, triangles, refs, overflow_flag

/* Leaf slot i's instance, and its mesh's tree (nodes, triangles). */
#define INSTANCE_AT(i) __global const Instance* in = instances + top_refs[i].prim_id
#define MESH_TREE(in) mesh_nodes + (in)->node_base, mesh_triangles + (in)->triangle_base
/* ... and its triangle refs, for closest-hit walks. */
#define MESH_TREE_REFS(in) MESH_TREE(in), mesh_refs + (in)->triangle_base
#endif /* INSTANCES */

#endif /* TWO_LEVEL_H */
