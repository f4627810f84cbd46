/* Refit of the wide tree after its vertices moved (Scene.update_vertices):
 * the topology is kept and every box is recomputed bottom-up, one launch per
 * level of wide nodes from the deepest up.  widen.cl emits the nodes level
 * by level (breadth-first), so when a level runs every child it reads is
 * final: no atomics and no handoff between walkers (Karras 2012, sec. 4,
 * refits a binary tree with visit counters instead).  A leaf lane re-reads
 * its triangles from the moved vertices; an interior lane is the union of
 * its child's lanes.  Boxes are min/max of the same floats as a build's, so
 * a refit of unmoved vertices gives back the built tree bit for bit.
 */
#include "core/portable.h"
#include "core/aabb.h"
#include "core/tree.h"
#include "build/mesh.h"

/* The boxes below come back through a pointer, not as a return value: a
 * returned struct is written through a noalias (sret) pointer, and inlining
 * such a function leaves calls to llvm.experimental.noalias.scope.decl,
 * which Oclgrind cannot run. */

/* Re-read the triangles [first, first + count) of a leaf from the (moved)
 * vertices through their vertex ids (stored in leaf order by the build, so
 * that a refit reads them in sequence rather than chasing the faces), store
 * them, and set *box to their box.  Indexed leaves name their vertices
 * themselves, and refit.py has copied the moved ones in: their corners are
 * read through them (vertices and vertex_ids may be null). */
inline void regather_leaf(__global const float *vertices, __global const int *vertex_ids,
                          __global Leaf *triangles, int first, uint count, Aabb *box)
{
    Aabb leaf = aabb_empty();
    for (int j = first; j < first + (int)count; ++j) {
        float3 a, b, c;
#ifdef INDEXED_LEAVES
        LEAF_CORNERS(t, triangles, j);
        a = LOAD_XYZ(t->v0);
        b = LOAD_XYZ(t->v1);
        c = LOAD_XYZ(t->v2);
#else
        load_triangle(vertices, vertex_ids, j, &a, &b, &c);
        store_leaf(triangles, j, 0, a, b, c, vertex_ids + 3 * (size_t)j);
#endif
        leaf = aabb_union(leaf, aabb_of_points(a, b, c));
    }
    *box = leaf;
}

/* One of a WideNode's six planes (WIDE_ARITY floats each): the lower
 * (high = 0) or upper bound of every lane along `axis`. */
inline __global float *plane(__global WideNode *node, int axis, int high)
{
    switch (2 * axis + high) {
    case 0: return node->lo_x;
    case 1: return node->hi_x;
    case 2: return node->lo_y;
    case 3: return node->hi_y;
    case 4: return node->lo_z;
    default: return node->hi_z;
    }
}

/* The union of a wide node's lanes (unused lanes hold an empty box). */
inline void node_box(__global WideNode *node, Aabb *box)
{
    Aabb out = aabb_empty();
    for (int k = 0; k < WIDE_ARITY; ++k) {
        Aabb lane;
        for (int axis = 0; axis < 3; ++axis) {
            lane.lo[axis] = plane(node, axis, 0)[k];
            lane.hi[axis] = plane(node, axis, 1)[k];
        }
        out = aabb_union(out, lane);
    }
    *box = out;
}

/* Every lane of the wide nodes [level_first, level_first + level_count),
 * whose children (the next level down) are already refit. */
NARROW_KERNEL
void refit_wide_level(int level_first, int level_count, __global WideNode *nodes,
                      __global const float *vertices, __global const int *vertex_ids,
                      __global Leaf *triangles)
{
    int i = get_global_id(0);
    if (i >= level_count)
        return;
    __global WideNode *node = nodes + level_first + i;
    for (int k = 0; k < WIDE_ARITY; ++k) {
        int child = node->child[k];
        uint count = node->count[k];
        Aabb box;
        if (count > 0)
            regather_leaf(vertices, vertex_ids, triangles, child, count, &box);
        else if (child != EMPTY_CHILD)
            node_box(nodes + child, &box);
        else
            continue;
        for (int axis = 0; axis < 3; ++axis) {
            plane(node, axis, 0)[k] = box.lo[axis];
            plane(node, axis, 1)[k] = box.hi[axis];
        }
    }
}
