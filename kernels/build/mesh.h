/* The build's reads of the indexed meshes (vertices, three vertex indices
 * per face) and its writes of the tree-ordered triangles (core/tree.h). */
#ifndef BUILD_MESH_H
#define BUILD_MESH_H

#include "core/spelled.h"
#include "core/tree.h"

/* Vertex `index` (an initializer, not vload3: PoCL calls vload3 and vstore3
 * out of line, core/spelled.h; perf showed much of the bounds pass's and
 * lay_out_leaves' time in them). */
inline float3 load_vertex(__global const float *vertices, int index)
{
    return LOAD_XYZ(vertices + 3 * (size_t)index);
}

/* The triangle `face` of an indexed mesh. */
inline void load_triangle(__global const float *vertices, __global const int *faces, int face,
                          float3 *a, float3 *b, float3 *c)
{
    *a = load_vertex(vertices, faces[3 * (size_t)face + 0]);
    *b = load_vertex(vertices, faces[3 * (size_t)face + 1]);
    *c = load_vertex(vertices, faces[3 * (size_t)face + 2]);
}

/* Triangle j of the tree-ordered triangle array (an initializer, not
 * vstore3: see load_vertex). */
inline void store_triangle(__global Triangle *triangles, int j, float3 a, float3 b, float3 c)
{
    Triangle t = {{a.x, a.y, a.z}, {b.x, b.y, b.z}, {c.x, c.y, c.z}};
    triangles[j] = t;
}

#endif /* BUILD_MESH_H */
