/* Stage 4: the binary radix tree over the sorted primitives, with each
 * node's box, SAH cost and collapse decision, in one bottom-up pass
 * (Apetrei 2014, "Fast and Simple Agglomerative LBVH Construction").
 *
 * The tree is Karras's (2012, "Maximizing Parallelism in the Construction of
 * BVHs, Octrees, and k-d Trees"), numbered as he numbers it: internal node i
 * is i (0 = the root), the leaf of sorted primitive j is node n - 1 + j, and
 * equal keys are told apart by their index (Karras sec. 4).  Instead of a
 * binary search per node followed by a refit walk, one work-item starts at
 * each leaf and walks up.  A node covering the primitives [first, last] has
 * as parent the split at `last` (it is the left child) when the keys across
 * that end differ less than the keys across `first - 1 | first`, else the
 * split at first - 1 (it is the right child).  At a split where two
 * subtrees meet, both arrivals leave their far end and count themselves in;
 * the first stops, the second learns the parent's whole range, emits it and
 * computes it from both children, and goes on.  A leaf child needs no
 * meeting: its data is laid out before the walk.
 *
 * Karras's number of a node is its parent's split if it is a left child, and
 * that split + 1 if it is a right child: its range ends at, or starts at, its
 * own number.  So the walker names each node as soon as it knows the node's
 * range (tests/build/test_radix_tree.py checks the arrays against a top-down
 * build from Karras's definition).
 *
 * On the way the walker evaluates the SAH bottom-up (cost = C_t A(node) +
 * cost(left) + cost(right), or C_i N A(node) as a leaf) so that, with
 * COLLAPSE_LEAVES, subtrees of at most MAX_LEAF_SIZE triangles become leaves
 * where the SAH says a leaf costs at most COLLAPSE_COST_RATIO times as much
 * (build/config.h).  A kernel before the walk (lay_out_leaves) lays the triangles
 * out in leaf (sorted) order, with their (mesh, face) refs and vertex ids,
 * and sets up the leaves the walkers start from.
 */
#include "core/portable.h"
#include "core/aabb.h"
#include "core/tree.h"
#include "build/config.h"
#include "build/mesh.h"
#include "build/handoff.h"

/* Intel's CPU compiler runs these kernels 16 work-items to a vector, and a
 * vector of walkers climbs as long as its longest walk: one work-item at a
 * time measured much faster, and the leaves' gathers too ran faster one at
 * a time.  (PoCL does not vectorize them.) */
#ifdef cl_intel_vec_len_hint
#define ONE_WORK_ITEM_AT_A_TIME __attribute__((intel_vec_len_hint(1)))
#else
#define ONE_WORK_ITEM_AT_A_TIME
#endif


/* Whether the node over [first, last] is its parent's left child: the keys
 * across its right end differ less than those across its left end (the
 * highest differing bit decides; the two can never tie).  Equal keys on both
 * sides compare the indices instead, as Karras's tie-break does. */
inline int is_left_child(__global const morton_t *keys, int n, int first, int last)
{
    if (first == 0)
        return 1;
    if (last == n - 1)
        return 0;
    morton_t left_gap = keys[first - 1] ^ keys[first];
    morton_t right_gap = keys[last] ^ keys[last + 1];
    if (left_gap != right_gap)
        return right_gap < left_gap;
    return (uint)(last ^ (last + 1)) < (uint)((first - 1) ^ first);
}

/* The mesh a concatenated face belongs to: the last whose first face is <= face. */
inline TriangleRef triangle_ref(__global const int *mesh_first_face, int mesh_count, int face)
{
    int lo = 0, hi = mesh_count - 1;
    while (lo < hi) {
        int mid = (lo + hi + 1) >> 1;
        if (mesh_first_face[mid] <= face)
            lo = mid;
        else
            hi = mid - 1;
    }
    TriangleRef ref = {lo, face - mesh_first_face[lo]};
    return ref;
}

/* The leaves, one work-item per sorted primitive j: the triangle laid out
 * in leaf (sorted) order with its (mesh, face) ref and vertex ids (none for
 * indexed leaves, whose records name the vertices: vertex_ids may be null),
 * and the leaf's box, SAH cost and height.  Apart from the walk because the walk's
 * atomic waits for every store before it to reach the cache: after these
 * (a missing cache line each) it took a quarter of the walk's time. */
__kernel ONE_WORK_ITEM_AT_A_TIME
void lay_out_leaves(int n, __global const float *vertices, __global const int *faces,
                    __global const uint *primitive_ids,
                    __global const int *mesh_first_face, int mesh_count,
                    __global Leaf *triangles, __global TriangleRef *refs,
                    __global int *vertex_ids, __global Aabb *boxes,
                    __global float *sah_cost, __global int *height)
{
    int j = get_global_id(0);
    if (j >= n)
        return;
    int face = (int)primitive_ids[j];
    float3 a, b, c;
    load_triangle(vertices, faces, face, &a, &b, &c);
    store_leaf(triangles, j, n, a, b, c, faces + 3 * (size_t)face);
    refs[j] = triangle_ref(mesh_first_face, mesh_count, face);
#ifndef INDEXED_LEAVES
    for (int k = 0; k < 3; ++k) /* not vstore3(vload3()): see load_vertex */
        vertex_ids[3 * (size_t)j + k] = faces[3 * (size_t)face + k];
#endif
    Aabb box = aabb_of_points(a, b, c);
    int node = (n - 1) + j;
    boxes[node] = box;
    sah_cost[node] = SAH_INTERSECT_COST * aabb_area(box);
    height[node] = 0;
}

/* far_end[2s + side]: the far end of split s's child on that side (left 0);
 * visits[s] (zeroed): how many of its children have arrived.  The walker
 * carries its own subtree's box, cost and height, and reads only the
 * sibling's. */
__kernel ONE_WORK_ITEM_AT_A_TIME
void build_radix_tree(__global const morton_t *keys, int n, __global int *far_end,
                      __global int *visits, __global int *left_child,
                      __global int *right_child, __global int *parent,
                      __global int *range_first, __global int *range_last,
                      __global Aabb *boxes, __global float *sah_cost, __global int *height,
                      __global int *collapsed)
{
    int j = get_global_id(0);
    if (j >= n)
        return;
    int node = (n - 1) + j;
    Aabb box = boxes[node];
    float cost = sah_cost[node];
    int subtree_height = 0;

    int first = j, last = j;
    int left_side = is_left_child(keys, n, first, last);
    while (!(first == 0 && last == n - 1)) {
        int split = left_side ? last : first - 1;
        int other;
        int meeting = 0;
        /* A sibling that is a leaf is ready (lay_out_leaves wrote it), so
         * there is nothing to wait for: a subtree's walker goes on alone, and
         * of two leaves the left one; a leaf beside a subtree stops.  Only
         * two subtrees meet, through the handoff (handoff.h), at about a
         * third of the splits.  The right child of `split` is the leaf
         * split + 1 when that leaf is a right child; the left one the leaf
         * split when it is a left child.  This walker's own node (unless a
         * leaf) is stored here, once it is known whether a sibling's walker
         * may read it. */
        int sibling_is_leaf = left_side ? !is_left_child(keys, n, split + 1, split + 1)
                                        : is_left_child(keys, n, split, split);
        if (sibling_is_leaf) {
            if (first == last && !left_side)
                return;
            if (first != last) {
                boxes[node] = box;
                sah_cost[node] = cost;
                height[node] = subtree_height;
            }
            other = left_side ? split + 1 : split;
        } else if (first == last) {
            return;
        } else {
            handoff_store(far_end + 2 * split + !left_side, left_side ? first : last);
            handoff_store_box(boxes[node].lo, boxes[node].hi, box);
            handoff_store_float(sah_cost + node, cost);
            handoff_store(height + node, subtree_height);
            if (handoff_arrive(visits + split) == 0)
                return; /* the sibling subtree is not done; its walker goes on */
            other = handoff_load(far_end + 2 * split + left_side);
            meeting = 1;
        }
        if (left_side)
            last = other;
        else
            first = other;

        int left = first == split ? (n - 1) + split : split;
        int right = last == split + 1 ? (n - 1) + split + 1 : split + 1;
        int sibling = left_side ? right : left;
        Aabb sibling_box = meeting ? handoff_load_box(boxes[sibling].lo, boxes[sibling].hi)
                                   : boxes[sibling];
        float sibling_cost = meeting ? handoff_load_float(sah_cost + sibling) : sah_cost[sibling];
        int sibling_height = meeting ? handoff_load(height + sibling) : height[sibling];
        left_side = is_left_child(keys, n, first, last);
        /* Karras's number: the root 0, else the end it shares with its parent's split */
        node = first == 0 && last == n - 1 ? 0 : left_side ? last : first;
        left_child[node] = left;
        right_child[node] = right;
        parent[left] = node;
        parent[right] = node;
        range_first[node] = first;
        range_last[node] = last;

        box = aabb_union(box, sibling_box);
        float area = aabb_area(box);
        int count = last - first + 1;
        /* The children's costs added first, as one commutative sum: which
         * walker arrives second (and adds the other's cost) varies from run
         * to run, and (a + b) + c need not equal (a + c) + b in float. */
        float as_interior = SAH_TRAVERSAL_COST * area + (cost + sibling_cost);
        float as_leaf = SAH_INTERSECT_COST * (float)count * area;
        int make_leaf = COLLAPSE_LEAVES && count <= MAX_LEAF_SIZE &&
                        as_leaf <= COLLAPSE_COST_RATIO * as_interior;
        cost = make_leaf ? as_leaf : as_interior;
        subtree_height = make_leaf ? 0 : 1 + max(subtree_height, sibling_height);
        collapsed[node] = make_leaf;
    }
    boxes[node] = box; /* the root's walker */
    sah_cost[node] = cost;
    height[node] = subtree_height;
    parent[node] = -1;
}
