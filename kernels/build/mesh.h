/* The build's reads of the indexed meshes (vertices, three vertex indices
 * per face) and its writes of the tree-ordered triangles (core/tree.h). */
#ifndef BUILD_MESH_H
#define BUILD_MESH_H

#include "core/spelled.h"
#include "core/leaf.h"
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

/* Leaf j of the tree-ordered leaves: triangle (a, b, c), whose vertex
 * indices are ids[0..2] (core/leaf.h).  Default leaves hold the corners (an
 * initializer, not vstore3: see load_vertex); indexed ones where the
 * corners lie among the n records' vertices, which follow the records. */
inline void store_leaf(__global Leaf *leaves, int j, int n, float3 a, float3 b, float3 c,
                       __global const int *ids)
{
#ifdef INDEXED_LEAVES
    IndexedTriangle t = {{n + ids[0] - j, n + ids[1] - j, n + ids[2] - j}};
#else
    Triangle t = {{a.x, a.y, a.z}, {b.x, b.y, b.z}, {c.x, c.y, c.z}};
#endif
    leaves[j] = t;
}

#endif /* BUILD_MESH_H */
