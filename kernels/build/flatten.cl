/* Stage 6: the flat binary tree, which widen.cl then collapses into the
 * 8-wide tree that traversal reads (the flat tree is the build's scratch).
 *
 * Interior nodes that survive (not inside a collapsed leaf, and, for the
 * HLBVH, not above the clusters) are compacted by a scan and written after
 * the top_count SAH top nodes, each holding both children's boxes.  A leaf
 * slot points at a run of triangles in sorted (Morton) order, the order in
 * which radix_tree.cl stored them.
 *
 * The SAH top's size, root and depth come from its info[] (sah_top.cl:
 * depth, root, cluster count), on the device: the host reads none of them
 * (issue 57), and summarise_flat_tree gathers what it reads at the end.
 */
#include "core/portable.h"
#include "core/aabb.h"
#include "core/tree.h"
#include "build/config.h"
#include "build/flat_node.h"


inline int spans_clusters(__global const morton_t *keys, int first, int last)
{
    return USE_CLUSTERS && (keys[first] >> CLUSTER_SHIFT) != (keys[last] >> CLUSTER_SHIFT);
}

/* live[i] = 1 if radix-tree node i is an interior node of the flat tree. */
NARROW_KERNEL
void mark_live_nodes(__global const morton_t *keys, int n, __global const int *parent,
                     __global const int *range_first, __global const int *range_last,
                     __global const int *collapsed, __global uint *live)
{
    int i = get_global_id(0);
    if (i >= n - 1)
        return;
    int is_live = !collapsed[i] && !spans_clusters(keys, range_first[i], range_last[i]);
    /* A collapsed ancestor holds at most MAX_LEAF_SIZE triangles, so only
     * the few ancestors that small need a look. */
    for (int p = parent[i]; is_live && p >= 0; p = parent[p]) {
        if (range_last[p] - range_first[p] + 1 > MAX_LEAF_SIZE ||
            spans_clusters(keys, range_first[p], range_last[p]))
            break;
        if (collapsed[p])
            is_live = 0;
    }
    live[i] = is_live;
}

/* The SAH top's node count: clusters - 1, none for one cluster or without
 * clusters (the LBVH builder; top_info is then not read). */
inline int top_node_count(__global const int *top_info)
{
    return USE_CLUSTERS ? max(top_info[2] - 1, 0) : 0;
}

/* Where radix-tree node `node` lands in a parent's child slot. */
inline void child_slot(int node, int n, int top_count, __global const uint *live_scan,
                       __global const int *range_first, __global const int *range_last,
                       __global const int *collapsed, int *index, uint *count)
{
    if (node >= n - 1) {
        *index = node - (n - 1);
        *count = 1;
    } else if (collapsed[node]) {
        *index = range_first[node];
        *count = (uint)(range_last[node] - range_first[node] + 1);
    } else {
        *index = top_count + (int)live_scan[node];
        *count = 0;
    }
}

inline void write_node(__global FlatNode *out, Aabb left_box, Aabb right_box, int left,
                       uint left_count, int right, uint right_count)
{
    FlatNode node;
    for (int k = 0; k < 3; ++k) {
        node.left_lo[k] = left_box.lo[k];
        node.left_hi[k] = left_box.hi[k];
        node.right_lo[k] = right_box.lo[k];
        node.right_hi[k] = right_box.hi[k];
    }
    node.left = left;
    node.right = right;
    node.left_count = left_count;
    node.right_count = right_count;
    *out = node;
}

NARROW_KERNEL
void write_flat_nodes(int n, __global const int *top_info,
                      __global const uint *live_scan,
                      __global const int *left_child, __global const int *right_child,
                      __global const int *range_first, __global const int *range_last,
                      __global const int *collapsed, __global const Aabb *boxes,
                      __global FlatNode *nodes)
{
    int i = get_global_id(0);
    if (i >= n - 1 || live_scan[i] == live_scan[i + 1])
        return;
    int top_count = top_node_count(top_info);
    int self = top_count + (int)live_scan[i];
    int left, right;
    uint left_count, right_count;
    child_slot(left_child[i], n, top_count, live_scan, range_first, range_last, collapsed, &left,
               &left_count);
    child_slot(right_child[i], n, top_count, live_scan, range_first, range_last, collapsed, &right,
               &right_count);
    write_node(nodes + self, boxes[left_child[i]], boxes[right_child[i]], left, left_count, right,
               right_count);
}

/* Top node t goes to flat slot t, but the root must be slot 0: swap the two. */
inline int top_slot(int t, int top_root)
{
    return t == top_root ? 0 : (t == 0 ? top_root : t);
}

/* Where child `ref` of a top node (>= 0 a top node, < 0 the cluster ~ref)
 * lands in its parent's slot, and its box. */
inline void top_child(int ref, int n, int top_count, int top_root,
                      __global const uint *live_scan, __global const Aabb *top_boxes,
                      __global const int *cluster_roots, __global const Aabb *cluster_boxes,
                      __global const int *range_first, __global const int *range_last,
                      __global const int *collapsed, int *index, uint *count, Aabb *box)
{
    if (ref >= 0) {
        *index = top_slot(ref, top_root);
        *count = 0;
        *box = top_boxes[ref];
    } else {
        /* the cluster's box from the compact copy, not boxes[root]: a
         * random read into the radix tree's boxes dominated this kernel */
        child_slot(cluster_roots[~ref], n, top_count, live_scan, range_first, range_last,
                   collapsed, index, count);
        *box = cluster_boxes[~ref];
    }
}

/* Two calls to top_child rather than a loop over the sides: PoCL keeps a
 * work-item's private arrays in memory, and copying them took half the
 * kernel's time.  Launched for as many top nodes as there can be. */
NARROW_KERNEL
void write_top_nodes(int n, __global const int *top_info,
                     __global const uint *live_scan,
                     __global const int *top_left, __global const int *top_right,
                     __global const Aabb *top_boxes, __global const int *cluster_roots,
                     __global const Aabb *cluster_boxes, __global const int *range_first,
                     __global const int *range_last, __global const int *collapsed,
                     __global FlatNode *nodes)
{
    int t = get_global_id(0), top_count = top_node_count(top_info), top_root = top_info[1];
    if (t >= top_count)
        return;
    int self = top_slot(t, top_root);
    int left, right;
    uint left_count, right_count;
    Aabb left_box, right_box;
    top_child(top_left[t], n, top_count, top_root, live_scan, top_boxes, cluster_roots,
              cluster_boxes, range_first, range_last, collapsed, &left, &left_count,
              &left_box);
    top_child(top_right[t], n, top_count, top_root, live_scan, top_boxes, cluster_roots,
              cluster_boxes, range_first, range_last, collapsed, &right, &right_count,
              &right_box);
    write_node(nodes + self, left_box, right_box, left, left_count, right, right_count);
}

/* The figures the host reads of the flat tree (FlatSummary), one work-item;
 * and a tree whose root is a leaf gets its one node here, whose left slot
 * holds all n triangles (the scan marked no node live, so no other kernel
 * wrote one).  Without the scan (n == 1) live_scan is not read. */
NARROW_KERNEL
void summarise_flat_tree(int n, __global const int *top_info,
                         __global const uint *live_scan, __global const int *collapsed,
                         __global const Aabb *boxes, __global const float *sah_cost,
                         __global const int *height, __global const Aabb *top_boxes,
                         __global const float *top_cost, __global FlatNode *nodes,
                         __global FlatSummary *out)
{
    if (get_global_id(0) != 0)
        return;
    FlatSummary s;
    int top_count = n > 1 ? top_node_count(top_info) : 0;
    Aabb box = boxes[0];
    s.clusters = USE_CLUSTERS && n > 1 ? top_info[2] : 1;
    /* one triangle, or a few that the SAH keeps together with no top above */
    s.root_is_leaf = n == 1 || (top_count == 0 && collapsed[0]);
    if (s.root_is_leaf) {
        s.node_count = s.leaf_count = s.depth = 1;
        s.sah_cost = 0.0f;
        write_node(nodes, box, aabb_empty(), 0, (uint)n, EMPTY_CHILD, 0);
    } else {
        s.node_count = top_count + (int)live_scan[n - 1];
        s.leaf_count = s.node_count + 1;
        if (top_count > 0) {
            s.depth = top_info[0];
            s.sah_cost = top_cost[0];
            box = top_boxes[top_info[1]];
        } else {
            s.depth = height[0];
            s.sah_cost = sah_cost[0];
        }
    }
    for (int k = 0; k < 3; ++k) {
        s.lo[k] = box.lo[k];
        s.hi[k] = box.hi[k];
    }
    *out = s;
}
