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

inline int cluster_root(__global const int *cluster_first, int cluster_count, int n, int c,
                        __global const int *range_first, __global const int *range_last)
{
    int first = cluster_first[c];
    int last = (c + 1 < cluster_count ? cluster_first[c + 1] : n) - 1;
    if (first == last)
        return (n - 1) + first; /* a one-primitive cluster is a leaf node */
    /* Karras: an internal node's range starts or ends at its own index. */
    return range_first[first] == first && range_last[first] == last ? first : last;
}

/* Binned SAH top-down over the clusters, as a breadth-first work list so no
 * stack can overflow; then a reverse sweep (children are created after their
 * parent) folds boxes, costs and heights bottom-up.
 *
 * top_left/right[t]: >= 0 a top node, < 0 the cluster ~ref.
 * info[0] = depth of the whole tree; sah_cost_out[0] = SAH cost of the root.
 */
__kernel void build_top_sah(__global const uint *scan, int n, __global const int *cluster_first,
                            __global const int *range_first, __global const int *range_last,
                            __global const Aabb *boxes, __global const float *sah_cost,
                            __global const int *height, __global int *cluster_roots,
                            __global int *cluster_order, __global int *top_begin,
                            __global int *top_end, __global int *top_left, __global int *top_right,
                            __global Aabb *top_boxes, __global float *top_cost,
                            __global int *top_height, __global int *info,
                            __global float *sah_cost_out)
{
    if (get_global_id(0) != 0)
        return;
    int cluster_count = (int)scan[n];
    for (int c = 0; c < cluster_count; ++c) {
        cluster_roots[c] = cluster_root(cluster_first, cluster_count, n, c, range_first, range_last);
        cluster_order[c] = c;
    }

    int created = 1;
    top_begin[0] = 0;
    top_end[0] = cluster_count;
    for (int t = 0; t < created; ++t) {
        int begin = top_begin[t], end = top_end[t];
        Aabb centroid_box = aabb_empty();
        for (int k = begin; k < end; ++k)
            centroid_box = aabb_grow(centroid_box, aabb_center(boxes[cluster_roots[cluster_order[k]]]));

        /* Bin the clusters on each axis; the cost of a split is
         * N_L A(L) + N_R A(R), with N counting triangles (Wald 2007). */
        float best_cost = INFINITY;
        int best_axis = -1, best_bin = 0;
        for (int axis = 0; axis < 3; ++axis) {
            float lo = centroid_box.lo[axis], extent = centroid_box.hi[axis] - lo;
            if (!(extent > 0.0f))
                continue;
            Aabb bin_box[TOP_SAH_BINS];
            float bin_count[TOP_SAH_BINS];
            for (int b = 0; b < TOP_SAH_BINS; ++b) {
                bin_box[b] = aabb_empty();
                bin_count[b] = 0.0f;
            }
            for (int k = begin; k < end; ++k) {
                int c = cluster_order[k];
                Aabb box = boxes[cluster_roots[c]];
                float center = 0.5f * (box.lo[axis] + box.hi[axis]);
                int b = clamp((int)((center - lo) / extent * TOP_SAH_BINS), 0, TOP_SAH_BINS - 1);
                bin_box[b] = aabb_union(bin_box[b], box);
                int last = (c + 1 < cluster_count ? cluster_first[c + 1] : n) - 1;
                bin_count[b] += (float)(last - cluster_first[c] + 1);
            }
            float right_area[TOP_SAH_BINS], right_count[TOP_SAH_BINS];
            Aabb acc = aabb_empty();
            float count = 0.0f;
            for (int b = TOP_SAH_BINS - 1; b > 0; --b) {
                acc = aabb_union(acc, bin_box[b]);
                count += bin_count[b];
                right_area[b] = aabb_area(acc);
                right_count[b] = count;
            }
            acc = aabb_empty();
            count = 0.0f;
            for (int b = 0; b < TOP_SAH_BINS - 1; ++b) {
                acc = aabb_union(acc, bin_box[b]);
                count += bin_count[b];
                if (count == 0.0f || right_count[b + 1] == 0.0f)
                    continue;
                float cost = count * aabb_area(acc) + right_count[b + 1] * right_area[b + 1];
                if (cost < best_cost) {
                    best_cost = cost;
                    best_axis = axis;
                    best_bin = b;
                }
            }
        }

        /* Partition in place; with no usable split, halve the range. */
        int middle = begin + (end - begin) / 2;
        if (best_axis >= 0) {
            float lo = centroid_box.lo[best_axis];
            float extent = centroid_box.hi[best_axis] - lo;
            int i = begin, j = end - 1;
            while (i <= j) {
                Aabb box = boxes[cluster_roots[cluster_order[i]]];
                float center = 0.5f * (box.lo[best_axis] + box.hi[best_axis]);
                int b = clamp((int)((center - lo) / extent * TOP_SAH_BINS), 0, TOP_SAH_BINS - 1);
                if (b <= best_bin) {
                    ++i;
                } else {
                    int swap = cluster_order[i];
                    cluster_order[i] = cluster_order[j];
                    cluster_order[j] = swap;
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
                child = ~cluster_order[ranges[side][0]];
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
                int root = cluster_roots[~ref];
                box = aabb_union(box, boxes[root]);
                cost += sah_cost[root];
                h = max(h, height[root]);
            }
        }
        top_boxes[t] = box;
        top_cost[t] = SAH_TRAVERSAL_COST * aabb_area(box) + cost;
        top_height[t] = 1 + h;
    }
    info[0] = top_height[0];
    sah_cost_out[0] = top_cost[0];
}
