/* Stage 6 (HLBVH): the top of the tree, built with the SAH over Morton
 * clusters (Pantaleoni & Luebke 2010; Garanzha et al. 2011; pbrt-v3's
 * HLBVHBuild + buildUpperSAH).
 *
 * A cluster is a run of sorted primitives sharing the top CLUSTER_BITS bits
 * of their Morton code.  Each cluster is exactly one subtree of the radix
 * tree, so the LBVH below it is kept and only the nodes above the clusters
 * are replaced by a binned-SAH tree over the (at most 2^CLUSTER_BITS)
 * cluster boxes.  That top build is a single work-item task: a few thousand
 * clusters cost microseconds to bin, and a serial loop needs no barriers.
 */
#include "hlbvh.h"

#if MORTON_BITS == 30
typedef uint morton_t;
#elif MORTON_BITS == 63
typedef ulong morton_t;
#else
#error "MORTON_BITS must be 30 or 63"
#endif
#define CLUSTER_SHIFT (MORTON_BITS - CLUSTER_BITS)

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

inline int bin_of(float center, float lo, float inv_extent)
{
    return clamp((int)((center - lo) * inv_extent), 0, TOP_SAH_BINS - 1);
}

inline float center_of(Aabb box, int axis)
{
    return 0.5f * (box.lo[axis] + box.hi[axis]);
}

/* Binned SAH top-down over the clusters, as a breadth-first work list (no
 * stack to overflow); then a reverse sweep (children are created after their
 * parent) folds boxes, costs and heights bottom-up.
 *
 * A split's cost is N_L A(L) + N_R A(R), N counting triangles (Wald 2007).
 * Besides the bins it tries isolating the largest cluster: centroid bins
 * cannot separate a huge primitive (a ground plane) whose centre lies among
 * the others, and leaving it inside inflates every box below.
 *
 * top_left/right[t]: >= 0 a top node, < 0 the cluster ~ref.
 * info[0] = depth of the whole tree; sah_cost_out[0] = SAH cost of the root.
 */
__kernel void build_top_sah(int cluster_count, __global const Aabb *cluster_box,
                            __global const float *cluster_size,
                            __global const float *cluster_cost,
                            __global const int *cluster_height, __global int *order,
                            __global int *top_begin, __global int *top_end, __global int *top_left,
                            __global int *top_right, __global Aabb *top_boxes,
                            __global float *top_cost, __global int *top_height, __global int *info,
                            __global float *sah_cost_out)
{
    if (get_global_id(0) != 0)
        return;
    for (int c = 0; c < cluster_count; ++c)
        order[c] = c;

    int created = 1;
    top_begin[0] = 0;
    top_end[0] = cluster_count;
    for (int t = 0; t < created; ++t) {
        int begin = top_begin[t], end = top_end[t];

        /* Pass 1: centroid bounds, total size, the largest cluster. */
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
        float lo[3], inv_extent[3];
        for (int axis = 0; axis < 3; ++axis) {
            float extent = centroid_box.hi[axis] - centroid_box.lo[axis];
            lo[axis] = centroid_box.lo[axis];
            inv_extent[axis] = extent > 0.0f ? TOP_SAH_BINS / extent : 0.0f;
        }

        /* Pass 2: all three axes' bins at once, and the box of all but the largest. */
        Aabb bin_box[3][TOP_SAH_BINS];
        float bin_size[3][TOP_SAH_BINS];
        for (int axis = 0; axis < 3; ++axis)
            for (int b = 0; b < TOP_SAH_BINS; ++b) {
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
                int b = bin_of(center_of(box, axis), lo[axis], inv_extent[axis]);
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
            for (int b = TOP_SAH_BINS - 1; b > 0; --b) {
                acc = aabb_union(acc, bin_box[axis][b]);
                size += bin_size[axis][b];
                right_area[b] = aabb_area(acc);
                right_size[b] = size;
            }
            acc = aabb_empty();
            size = 0.0f;
            for (int b = 0; b < TOP_SAH_BINS - 1; ++b) {
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

        /* Partition in place; with no usable split, halve the range. */
        int middle = begin + (end - begin) / 2;
        if (end - begin > 2 && isolate_cost < best_cost) {
            int swap = order[largest];
            order[largest] = order[end - 1];
            order[end - 1] = swap;
            middle = end - 1;
        } else if (best_axis >= 0) {
            int i = begin, j = end - 1;
            while (i <= j) {
                Aabb box = cluster_box[order[i]];
                if (bin_of(center_of(box, best_axis), lo[best_axis], inv_extent[best_axis]) <= best_bin) {
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

        int ranges[2][2] = {{begin, middle}, {middle, end}};
        for (int side = 0; side < 2; ++side) {
            int child;
            if (ranges[side][1] - ranges[side][0] == 1) {
                child = ~order[ranges[side][0]];
            } else {
                child = created++;
                top_begin[child] = ranges[side][0];
                top_end[child] = ranges[side][1];
            }
            if (side == 0)
                top_left[t] = child;
            else
                top_right[t] = child;
        }
    }

    for (int t = created - 1; t >= 0; --t) {
        int children[2] = {top_left[t], top_right[t]};
        Aabb box = aabb_empty();
        float cost = 0.0f;
        int h = 0;
        for (int side = 0; side < 2; ++side) {
            int ref = children[side];
            if (ref >= 0) {
                box = aabb_union(box, top_boxes[ref]);
                cost += top_cost[ref];
                h = max(h, top_height[ref]);
            } else {
                box = aabb_union(box, cluster_box[~ref]);
                cost += cluster_cost[~ref];
                h = max(h, cluster_height[~ref]);
            }
        }
        top_boxes[t] = box;
        top_cost[t] = SAH_TRAVERSAL_COST * aabb_area(box) + cost;
        top_height[t] = 1 + h;
    }
    info[0] = top_height[0];
    sah_cost_out[0] = top_cost[0];
}
