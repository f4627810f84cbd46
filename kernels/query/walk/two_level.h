/* What every query of a two-level scene shares, rays or points: an
 * instance's affine maps (core/tree.h's Instance), and the parameters by
 * which a top tree's leaves (instance_leaf.h) reach the instances and their
 * meshes' trees.  query/rays/instance.h adds the rays' side,
 * query/points/instance.h the points'. */
#ifndef TWO_LEVEL_H
#define TWO_LEVEL_H

#include "query/walk/node.h"

#ifdef INSTANCES
#ifdef cl_khr_fp64
typedef double map_real;
#else
typedef float map_real;
#endif

/* Component `row` of a 3x4 map (m: that row's four floats) applied to a
 * point (with the offset) or a direction (without): in a fixed order
 * (contraction is off, core/portable.h), so every device maps alike, and in
 * double where the device has it, so only the final rounding to float stands
 * between the mapped value and the exact one.  Macros: they map scalars and
 * packets' lanes alike. */
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

/* What a top tree's leaves reach the instances and their meshes by, as a
 * walk's parameters: top_refs[i].prim_id is the instance in leaf slot i,
 * and the meshes' trees lie one after another (MESHES_PARAMS); and
 * *mesh_overflow, set when a mesh's walk runs out of stack.  Macros, as
 * kernels and their helpers pass several pointers on (OpenCL C has no
 * variadic macros, 6.9). */
#define MESHES_PARAMS                                                                   \
    , __global const TriangleRef *top_refs, __global const Instance *instances,          \
        __global const WideNode *mesh_nodes, __global const Leaf *mesh_triangles
#define MESHES_ARGS , top_refs, instances, mesh_nodes, mesh_triangles
#define INSTANCE_PARAMS MESHES_PARAMS, bool *mesh_overflow
#define INSTANCE_ARGS MESHES_ARGS, mesh_overflow
/* The top walk's INSTANCE_ARGS from a kernel's scene parameters (top_refs,
 * instances, and the meshes' nodes and triangles). */
#define TOP_ARGS(overflow_flag) top_refs, instances, nodes, triangles, overflow_flag

/* Instance in's mesh tree (nodes, triangles), as a walk's arguments. */
#define MESH_TREE(in) mesh_nodes + (in)->node_base, mesh_triangles + (in)->triangle_base
#endif /* INSTANCES */

#endif /* TWO_LEVEL_H */
