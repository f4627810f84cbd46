/* Stage 5: bottom-up refit with atomic visit counters (Karras 2012, sec. 4;
 * Apetrei 2014).  One work-item starts at each leaf and walks up; at every
 * node the first arrival stops and the second, which sees both children
 * finished, computes the node and goes on.  One pass, no level sync.
 *
 * refit_radix_tree runs during a build.  Besides the boxes it evaluates the
 * SAH bottom-up (cost = C_t * A(node) + cost(left) + cost(right), or
 * C_i * N * A(node) as a leaf) so that, with COLLAPSE_LEAVES, subtrees of at
 * most MAX_LEAF_SIZE triangles become leaves where the SAH says a leaf costs
 * at most COLLAPSE_COST_RATIO times as much (hlbvh.h).  refit_flat_tree
 * refits the flat tree after vertices move.
 */
#include "hlbvh.h"

/* Loads that must see another work-item's writes made before its atomic. */
inline Aabb load_box_volatile(__global const Aabb *boxes, int index)
{
    volatile __global const float *p = (volatile __global const float *)(boxes + index);
    Aabb box = {{p[0], p[1], p[2]}, {p[3], p[4], p[5]}};
    return box;
}

inline float load_float_volatile(__global const float *values, int index)
{
    return ((volatile __global const float *)values)[index];
}

inline int load_int_volatile(__global const int *values, int index)
{
    return ((volatile __global const int *)values)[index];
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

inline void store_triangle(__global Triangle *triangles, int j, float3 a, float3 b, float3 c)
{
    Triangle t;
    vstore3(a, 0, t.v0);
    vstore3(b, 0, t.v1);
    vstore3(c, 0, t.v2);
    triangles[j] = t;
}

/* Each leaf's walker first lays its triangle out in leaf (sorted) order, with
 * its (mesh, face) ref: the refit has to gather the triangle anyway. */
__kernel void refit_radix_tree(__global const float *vertices, __global const int *faces,
                               __global const uint *primitive_ids, int n,
                               __global const int *mesh_first_face, int mesh_count,
                               __global Triangle *triangles, __global TriangleRef *refs,
                               __global int *vertex_ids, __global const int *left_child, __global const int *right_child,
                               __global const int *parent, __global const int *range_first,
                               __global const int *range_last, __global volatile int *visits,
                               __global Aabb *boxes, __global float *sah_cost,
                               __global int *height, __global int *collapsed)
{
    int j = get_global_id(0);
    if (j >= n)
        return;
    int node = (n - 1) + j;
    int face = (int)primitive_ids[j];
    float3 a, b, c;
    load_triangle(vertices, faces, face, &a, &b, &c);
    store_triangle(triangles, j, a, b, c);
    refs[j] = triangle_ref(mesh_first_face, mesh_count, face);
    vstore3(vload3(face, faces), j, vertex_ids);
    Aabb box = aabb_of_points(a, b, c);
    boxes[node] = box;
    sah_cost[node] = SAH_INTERSECT_COST * aabb_area(box);
    height[node] = 0;

    node = parent[node];
    while (node >= 0) {
        /* Release, then acquire: the boxes written below this node happen
         * before the count, which happens before the sibling's are read.
         * Store-only and load-only fences suffice; full mem_fences measured
         * 3.6x slower on Intel's CPU runtime (366 vs 102 ms), PoCL the same. */
        write_mem_fence(CLK_GLOBAL_MEM_FENCE);
        if (atomic_inc(&visits[node]) == 0)
            return; /* the sibling subtree is not done; its walker goes on */
        read_mem_fence(CLK_GLOBAL_MEM_FENCE);

        int left = left_child[node], right = right_child[node];
        box = aabb_union(load_box_volatile(boxes, left), load_box_volatile(boxes, right));
        float area = aabb_area(box);
        int count = range_last[node] - range_first[node] + 1;
        float as_interior = SAH_TRAVERSAL_COST * area + load_float_volatile(sah_cost, left) +
                            load_float_volatile(sah_cost, right);
        float as_leaf = SAH_INTERSECT_COST * (float)count * area;
        int make_leaf = COLLAPSE_LEAVES && count <= MAX_LEAF_SIZE &&
                        as_leaf <= COLLAPSE_COST_RATIO * as_interior;

        boxes[node] = box;
        sah_cost[node] = make_leaf ? as_leaf : as_interior;
        height[node] = make_leaf ? 0 : 1 + max(load_int_volatile(height, left),
                                               load_int_volatile(height, right));
        collapsed[node] = make_leaf;
        node = parent[node];
    }
}

/* Re-read the triangles [first, first + count) of a leaf from the (moved)
 * vertices through their vertex ids (stored in leaf order by the build, so
 * that a refit reads them in sequence rather than chasing the faces), store
 * them, and return their box. */
inline Aabb regather_leaf(__global const float *vertices, __global const int *vertex_ids,
                          __global Triangle *triangles, int first, uint count)
{
    Aabb box = aabb_empty();
    for (int j = first; j < first + (int)count; ++j) {
        float3 a, b, c;
        load_triangle(vertices, vertex_ids, j, &a, &b, &c);
        store_triangle(triangles, j, a, b, c);
        box = aabb_union(box, aabb_of_points(a, b, c));
    }
    return box;
}

inline int is_interior_slot(int index, uint count)
{
    return count == 0 && index != EMPTY_CHILD;
}

/* Store the box of child slot `right_slot` of flat node i, and into the wide
 * child that copies that slot if there is one (widen.cl's map_wide_lanes), so
 * that the wide tree needs no pass of its own. */
inline void store_slot(__global FlatNode *nodes, int i, int right_slot, Aabb box,
                       __global WideNode *wide, __global const int *lane_of_slot)
{
    __global FlatNode *node = nodes + i;
    __global float *lo = right_slot ? node->right_lo : node->left_lo;
    __global float *hi = right_slot ? node->right_hi : node->left_hi;
    for (int k = 0; k < 3; ++k) {
        lo[k] = box.lo[k];
        hi[k] = box.hi[k];
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

inline Aabb load_slot_volatile(__global const FlatNode *node, int right_slot)
{
    volatile __global const float *lo = right_slot ? node->right_lo : node->left_lo;
    volatile __global const float *hi = right_slot ? node->right_hi : node->left_hi;
    Aabb box = {{lo[0], lo[1], lo[2]}, {hi[0], hi[1], hi[2]}};
    return box;
}

/* Refit of the flat tree (and of its wide copy) after vertices moved: a walk
 * starts at every node whose children are all leaves; a node with k interior children waits for k
 * arrivals.  Each leaf's triangles are re-read on the way (one pass over the
 * triangle data, not a gather pass and then a refit pass). */
__kernel void refit_flat_tree(__global FlatNode *nodes, __global const int *parents,
                              __global const float *vertices, __global const int *vertex_ids,
                              __global Triangle *triangles,
                              __global volatile int *visits, int node_count,
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
        Aabb left_box = left_count > 0 ? regather_leaf(vertices, vertex_ids, triangles, left,
                                                       left_count)
                                       : load_slot_volatile(node, 0);
        Aabb right_box = right_count > 0 ? regather_leaf(vertices, vertex_ids, triangles, right,
                                                         right_count)
                                         : load_slot_volatile(node, 1);
        if (left_count > 0)
            store_slot(nodes, i, 0, left_box, wide, lane_of_slot);
        if (right_count > 0)
            store_slot(nodes, i, 1, right_box, wide, lane_of_slot);

        int p = parents[i];
        if (p < 0)
            return;
        __global FlatNode *up = nodes + p;
        store_slot(nodes, p, up->left_count == 0 && up->left == i ? 0 : 1,
                   aabb_union(left_box, right_box), wide, lane_of_slot);
        /* A parent with one interior child (this one) needs no counter. */
        if (is_interior_slot(up->left, up->left_count) &&
            is_interior_slot(up->right, up->right_count)) {
            write_mem_fence(CLK_GLOBAL_MEM_FENCE); /* release, as in refit_radix_tree */
            if (atomic_inc(&visits[p]) == 0)
                return; /* the sibling subtree is not done; its walker goes on */
            read_mem_fence(CLK_GLOBAL_MEM_FENCE); /* acquire */
        }
        i = p;
    }
}

