/* Stage 6 (HLBVH): the top of the tree, built with the SAH over Morton
 * clusters (Pantaleoni & Luebke 2010; Garanzha et al. 2011; pbrt-v3's
 * HLBVHBuild + buildUpperSAH).
 *
 * A cluster is a run of sorted primitives sharing the top CLUSTER_BITS bits
 * of their Morton code.  Each cluster is exactly one subtree of the radix
 * tree, so the LBVH below it is kept and only the nodes above the clusters
 * are replaced by a binned-SAH tree over the cluster boxes, built level by
 * level in parallel (split_top_level) and folded bottom-up (fold_top_nodes).
 */
#include "hlbvh.h"


/* Isolating one huge cluster is tried only this near the root. */
#define TOP_ISOLATE_DEPTH 8

/* flags[i] = 1 where sorted primitive i starts a cluster (scanned afterwards). */
__kernel void mark_cluster_starts(__global const morton_t *keys, int n, __global uint *flags)
{
    int i = get_global_id(0);
    if (i >= n)
        return;
    flags[i] = i == 0 || (keys[i] >> CLUSTER_SHIFT) != (keys[i - 1] >> CLUSTER_SHIFT);
}

/* After the exclusive scan, scan[i] != scan[i + 1] marks a start. */
__kernel void gather_cluster_starts(__global const uint *scan, int n, __global int *cluster_first)
{
    int i = get_global_id(0);
    if (i >= n)
        return;
    if (scan[i] != scan[i + 1])
        cluster_first[scan[i]] = i;
}

/* One work-item per cluster: its radix-tree root and the compact records the
 * top build reads (a few MB at most, instead of scattered radix-tree nodes). */
__kernel void gather_clusters(__global const uint *scan, int n, __global const int *cluster_first,
                              __global const int *range_first, __global const int *range_last,
                              __global const Aabb *boxes, __global const float *sah_cost,
                              __global const int *height, __global int *cluster_root,
                              __global Aabb *cluster_box, __global float *cluster_size,
                              __global float *cluster_cost, __global int *cluster_height)
{
    int c = get_global_id(0);
    int cluster_count = (int)scan[n];
    if (c >= cluster_count)
        return;
    int first = cluster_first[c];
    int last = (c + 1 < cluster_count ? cluster_first[c + 1] : n) - 1;
    int root;
    if (first == last)
        root = (n - 1) + first; /* a one-primitive cluster is a leaf node */
    else /* Karras: an internal node's range starts or ends at its own index */
        root = range_first[first] == first && range_last[first] == last ? first : last;
    cluster_root[c] = root;
    cluster_box[c] = boxes[root];
    cluster_size[c] = (float)(last - first + 1);
    cluster_cost[c] = sah_cost[root];
    cluster_height[c] = height[root];
}

inline int bin_of(float center, float lo, float inv_extent, int bins)
{
    return clamp((int)((center - lo) * inv_extent), 0, bins - 1);
}

inline float center_of(Aabb box, int axis)
{
    return 0.5f * (box.lo[axis] + box.hi[axis]);
}

/* A pending top node: the clusters order[begin..end) and where to hang it. */
typedef struct {
    int begin;
    int end;
    int parent; /* top node, or -1 for the root */
    int side_and_depth; /* bit 0: right child of parent; the rest: depth */
} TopTask;

inline void attach(int ref, int parent, int side, __global int *top_left,
                   __global int *top_right, __global int *top_parent, __global int *info)
{
    if (parent < 0)
        info[1] = ref; /* the root */
    else if (side)
        top_right[parent] = ref;
    else
        top_left[parent] = ref;
    if (ref >= 0)
        top_parent[ref] = parent;
}

/* Split order[begin..end) with the binned SAH; partition it in place and
 * return the split point.  A split's cost is N_L A(L) + N_R A(R), N counting
 * triangles (Wald 2007).  Besides the bins it tries isolating the largest
 * cluster: centroid bins cannot separate a huge primitive (a ground plane)
 * whose centre lies among the others, and leaving it inside inflates every
 * box below.  (Only near the top, so isolation chains stay short.) */
inline int split_clusters(__global int *order, int begin, int end, int depth,
                          __global const Aabb *cluster_box, __global const float *cluster_size)
{
    Aabb centroid_box = aabb_empty();
    float total = 0.0f, largest_area = -1.0f;
    int largest = begin;
    for (int k = begin; k < end; ++k) {
        Aabb box = cluster_box[order[k]];
        centroid_box = aabb_grow(centroid_box, aabb_center(box));
        total += cluster_size[order[k]];
        float area = aabb_area(box);
        if (area > largest_area) {
            largest_area = area;
            largest = k;
        }
    }
    /* As many bins as clusters, up to TOP_SAH_BINS: a node's cost stays
     * proportional to its clusters (3 x 32 bins per node measured ~3 us,
     * which dominated the deep levels' many small nodes). */
    int bins = min(end - begin, TOP_SAH_BINS);
    float lo[3], inv_extent[3];
    for (int axis = 0; axis < 3; ++axis) {
        float extent = centroid_box.hi[axis] - centroid_box.lo[axis];
        lo[axis] = centroid_box.lo[axis];
        inv_extent[axis] = extent > 0.0f ? bins / extent : 0.0f;
    }

    Aabb bin_box[3][TOP_SAH_BINS];
    float bin_size[3][TOP_SAH_BINS];
    for (int axis = 0; axis < 3; ++axis)
        for (int b = 0; b < bins; ++b) {
            bin_box[axis][b] = aabb_empty();
            bin_size[axis][b] = 0.0f;
        }
    Aabb rest = aabb_empty();
    for (int k = begin; k < end; ++k) {
        int c = order[k];
        Aabb box = cluster_box[c];
        if (k != largest)
            rest = aabb_union(rest, box);
        for (int axis = 0; axis < 3; ++axis) {
            int b = bin_of(center_of(box, axis), lo[axis], inv_extent[axis], bins);
            bin_box[axis][b] = aabb_union(bin_box[axis][b], box);
            bin_size[axis][b] += cluster_size[c];
        }
    }

    float best_cost = INFINITY;
    int best_axis = -1, best_bin = 0;
    for (int axis = 0; axis < 3; ++axis) {
        if (inv_extent[axis] == 0.0f)
            continue;
        float right_area[TOP_SAH_BINS], right_size[TOP_SAH_BINS];
        Aabb acc = aabb_empty();
        float size = 0.0f;
        for (int b = bins - 1; b > 0; --b) {
            acc = aabb_union(acc, bin_box[axis][b]);
            size += bin_size[axis][b];
            right_area[b] = aabb_area(acc);
            right_size[b] = size;
        }
        acc = aabb_empty();
        size = 0.0f;
        for (int b = 0; b < bins - 1; ++b) {
            acc = aabb_union(acc, bin_box[axis][b]);
            size += bin_size[axis][b];
            if (size == 0.0f || right_size[b + 1] == 0.0f)
                continue;
            float cost = size * aabb_area(acc) + right_size[b + 1] * right_area[b + 1];
            if (cost < best_cost) {
                best_cost = cost;
                best_axis = axis;
                best_bin = b;
            }
        }
    }
    float largest_size = cluster_size[order[largest]];
    float isolate_cost = largest_size * largest_area + (total - largest_size) * aabb_area(rest);

    int middle = begin + (end - begin) / 2; /* no usable split: halve */
    if (depth < TOP_ISOLATE_DEPTH && end - begin > 2 && isolate_cost < best_cost) {
        int swap = order[largest];
        order[largest] = order[end - 1];
        order[end - 1] = swap;
        middle = end - 1;
    } else if (best_axis >= 0) {
        int i = begin, j = end - 1;
        while (i <= j) {
            Aabb box = cluster_box[order[i]];
            if (bin_of(center_of(box, best_axis), lo[best_axis], inv_extent[best_axis], bins) <=
                best_bin) {
                ++i;
            } else {
                int swap = order[i];
                order[i] = order[j];
                order[j] = swap;
                --j;
            }
        }
        middle = i;
    }
    if (middle == begin || middle == end)
        middle = begin + (end - begin) / 2;
    return middle;
}

/* One level of the top build: each task splits its range and hands its
 * children on.  The node splitting at m is top node m - 1: every split point
 * belongs to exactly one node, so nodes need no allocation.  Tasks at depth
 * serial_depth finish their whole subtree here, with order's own slice
 * [begin, end) of `stack` as a private work stack; so the host loop runs at
 * most serial_depth + 1 levels whatever the input. */
__kernel void split_top_level(__global const TopTask *tasks, int task_count, int serial_depth,
                              __global TopTask *next_tasks, __global volatile int *next_count,
                              __global TopTask *stack, __global int *order,
                              __global const Aabb *cluster_box,
                              __global const float *cluster_size, __global int *top_left,
                              __global int *top_right, __global int *top_parent,
                              __global int *info)
{
    int i = get_global_id(0);
    if (i >= task_count)
        return;
    TopTask task = tasks[i];
    int serial = (task.side_and_depth >> 1) >= serial_depth;
    int base = task.begin, top = base;
    while (1) {
        int depth = task.side_and_depth >> 1;
        int middle = split_clusters(order, task.begin, task.end, depth, cluster_box, cluster_size);
        int node = middle - 1;
        attach(node, task.parent, task.side_and_depth & 1, top_left, top_right, top_parent, info);
        int ranges[2][2] = {{task.begin, middle}, {middle, task.end}};
        for (int side = 0; side < 2; ++side) {
            if (ranges[side][1] - ranges[side][0] == 1) {
                attach(~order[ranges[side][0]], node, side, top_left, top_right, top_parent,
                       info);
                continue;
            }
            TopTask child = {ranges[side][0], ranges[side][1], node, ((depth + 1) << 1) | side};
            if (serial)
                stack[top++] = child;
            else
                next_tasks[atomic_inc(next_count)] = child;
        }
        if (top == base)
            return;
        task = stack[--top];
    }
}

/* Bottom-up over the top nodes with visit counters, as in refit.cl: a node
 * starts when both children are clusters, else waits for its top children. */
__kernel void fold_top_nodes(int top_count, __global const int *top_left,
                             __global const int *top_right, __global const int *top_parent,
                             __global const Aabb *cluster_box, __global const float *cluster_cost,
                             __global const int *cluster_height, __global volatile int *visits,
                             __global Aabb *top_boxes, __global float *top_cost,
                             __global int *top_height, __global int *info,
                             __global float *sah_cost_out)
{
    int t = get_global_id(0);
    if (t >= top_count || top_left[t] >= 0 || top_right[t] >= 0)
        return;
    while (1) {
        int children[2] = {top_left[t], top_right[t]};
        Aabb box = aabb_empty();
        float cost = 0.0f;
        int h = 0;
        for (int side = 0; side < 2; ++side) {
            int ref = children[side];
            if (ref >= 0) {
                volatile __global const float *b = (volatile __global const float *)(top_boxes + ref);
                Aabb child = {{b[0], b[1], b[2]}, {b[3], b[4], b[5]}};
                box = aabb_union(box, child);
                cost += ((volatile __global const float *)top_cost)[ref];
                h = max(h, ((volatile __global const int *)top_height)[ref]);
            } else {
                box = aabb_union(box, cluster_box[~ref]);
                cost += cluster_cost[~ref];
                h = max(h, cluster_height[~ref]);
            }
        }
        top_boxes[t] = box;
        top_cost[t] = SAH_TRAVERSAL_COST * aabb_area(box) + cost;
        top_height[t] = 1 + h;
        int p = top_parent[t];
        if (p < 0) {
            info[0] = 1 + h;
            sah_cost_out[0] = top_cost[t];
            return;
        }
        int waits_for = (top_left[p] >= 0) + (top_right[p] >= 0);
        mem_fence(CLK_GLOBAL_MEM_FENCE);
        if (atomic_inc(&visits[p]) + 1 < waits_for)
            return;
        mem_fence(CLK_GLOBAL_MEM_FENCE);
        t = p;
    }
}

__kernel void init_top_build(int cluster_count, __global int *order, __global TopTask *tasks)
{
    int c = get_global_id(0);
    if (c >= cluster_count)
        return;
    order[c] = c;
    if (c == 0) {
        TopTask root = {0, cluster_count, -1, 0};
        tasks[0] = root;
    }
}
