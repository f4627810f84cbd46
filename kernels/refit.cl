/* Refit of a finished tree after its vertices moved (Scene.update_vertices):
 * the topology is kept, and every box is recomputed bottom-up with atomic
 * visit counters (Karras 2012, sec. 4): one walk starts at every node whose
 * children are all leaves; at every node the first arrival stops and the
 * last, which sees all children finished, computes the node and goes on.
 * (A build computes its boxes as it builds the radix tree: radix_tree.cl.)
 */
#include "hlbvh.h"
#include "handoff.h"

/* The boxes of the two functions below come back through a pointer, not as
 * a return value: a returned struct is written through a noalias (sret)
 * pointer, and inlining such a function leaves calls to
 * llvm.experimental.noalias.scope.decl, which Oclgrind cannot run. */

/* Re-read the triangles [first, first + count) of a leaf from the (moved)
 * vertices through their vertex ids (stored in leaf order by the build, so
 * that a refit reads them in sequence rather than chasing the faces), store
 * them, and set *box to their box. */
inline void regather_leaf(__global const float *vertices, __global const int *vertex_ids,
                          __global Triangle *triangles, int first, uint count, Aabb *box)
{
    Aabb leaf = aabb_empty();
    for (int j = first; j < first + (int)count; ++j) {
        float3 a, b, c;
        load_triangle(vertices, vertex_ids, j, &a, &b, &c);
        store_triangle(triangles, j, a, b, c);
        leaf = aabb_union(leaf, aabb_of_points(a, b, c));
    }
    *box = leaf;
}

inline int is_interior_slot(int index, uint count)
{
    return count == 0 && index != EMPTY_CHILD;
}

/* Store the box of child slot `right_slot` of flat node i (through the
 * handoff when another walker may read it), and into the wide child that
 * copies that slot if there is one (widen.cl's map_wide_lanes), so that the
 * wide tree needs no pass of its own. */
inline void store_slot(__global FlatNode *nodes, int i, int right_slot, Aabb box,
                       __global WideNode *wide, __global const int *lane_of_slot,
                       int handed_on)
{
    __global FlatNode *node = nodes + i;
    __global float *lo = right_slot ? node->right_lo : node->left_lo;
    __global float *hi = right_slot ? node->right_hi : node->left_hi;
    if (handed_on) {
        handoff_store_box(lo, hi, box);
    } else {
        for (int k = 0; k < 3; ++k) {
            lo[k] = box.lo[k];
            hi[k] = box.hi[k];
        }
    }
    int lane = lane_of_slot[2 * i + right_slot];
    if (lane >= 0) {
        __global WideNode *w = wide + lane / WIDE_ARITY;
        int k = lane % WIDE_ARITY;
        w->lo_x[k] = box.lo[0];
        w->hi_x[k] = box.hi[0];
        w->lo_y[k] = box.lo[1];
        w->hi_y[k] = box.hi[1];
        w->lo_z[k] = box.lo[2];
        w->hi_z[k] = box.hi[2];
    }
}

/* An interior child's box, which this walker or (through the handoff) its
 * sibling's stored. */
inline void load_slot(__global FlatNode *node, int right_slot, Aabb *box)
{
    *box = handoff_load_box(right_slot ? node->right_lo : node->left_lo,
                            right_slot ? node->right_hi : node->left_hi);
}

/* Refit of the flat tree (and of its wide copy) after vertices moved: a walk
 * starts at every node whose children are all leaves; a node with k interior children waits for k
 * arrivals.  Each leaf's triangles are re-read on the way (one pass over the
 * triangle data, not a gather pass and then a refit pass). */
__kernel void refit_flat_tree(__global FlatNode *nodes, __global const int *parents,
                              __global const float *vertices, __global const int *vertex_ids,
                              __global Triangle *triangles,
                              __global int *visits, int node_count,
                              __global WideNode *wide, __global const int *lane_of_slot)
{
    int i = get_global_id(0);
    if (i >= node_count)
        return;
    if (is_interior_slot(nodes[i].left, nodes[i].left_count) ||
        is_interior_slot(nodes[i].right, nodes[i].right_count))
        return;

    while (1) {
        __global FlatNode *node = nodes + i;
        int left = node->left, right = node->right;
        uint left_count = node->left_count, right_count = node->right_count;
        Aabb left_box, right_box;
        if (left_count > 0)
            regather_leaf(vertices, vertex_ids, triangles, left, left_count, &left_box);
        else
            load_slot(node, 0, &left_box);
        if (right_count > 0)
            regather_leaf(vertices, vertex_ids, triangles, right, right_count, &right_box);
        else
            load_slot(node, 1, &right_box);
        if (left_count > 0)
            store_slot(nodes, i, 0, left_box, wide, lane_of_slot, 0);
        if (right_count > 0)
            store_slot(nodes, i, 1, right_box, wide, lane_of_slot, 0);

        int p = parents[i];
        if (p < 0)
            return;
        __global FlatNode *up = nodes + p;
        /* A parent with one interior child (this one) needs no counter. */
        int meeting = is_interior_slot(up->left, up->left_count) &&
                      is_interior_slot(up->right, up->right_count);
        store_slot(nodes, p, up->left_count == 0 && up->left == i ? 0 : 1,
                   aabb_union(left_box, right_box), wide, lane_of_slot, meeting);
        if (meeting && handoff_arrive(visits + p) == 0)
            return; /* the sibling subtree is not done; its walker goes on */
        i = p;
    }
}

