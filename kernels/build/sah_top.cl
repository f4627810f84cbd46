/* Stage 5 (HLBVH): the top of the tree, built with the SAH over Morton
 * clusters (Pantaleoni & Luebke 2010; Garanzha et al. 2011; pbrt-v3's
 * HLBVHBuild + buildUpperSAH).
 *
 * A cluster is a run of sorted primitives sharing the top CLUSTER_BITS bits
 * of their Morton code.  Each cluster is exactly one subtree of the radix
 * tree, so the LBVH below it is kept and only the nodes above the clusters
 * are replaced by a binned-SAH tree over the cluster boxes, built level by
 * level in parallel (split_top_level), which also writes each top node's box
 * and the tree's depth; sum_top_cost then adds up its SAH cost.
 *
 * info[] holds what the later stages need to know of the top, on the device
 * (the host reads none of it, issue 57): [0] the tree's depth, [1] the root
 * top node, [2] the cluster count.
 */
#include "core/portable.h"
#include "core/aabb.h"
#include "build/config.h"


/* Isolating one huge cluster is tried only this near the root. */
#define TOP_ISOLATE_DEPTH 8

/* Work-items of sum_top_cost's one work-group: set by the host (-D). */
#ifndef TOP_COST_GROUP
#error "TOP_COST_GROUP must be defined"
#endif

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

/* What the split loop reads of a cluster: its box corners as float4s, so a
 * union is one vector min and max and one vector expression bins all three
 * axes (the Aabb struct of float[3]s compiled to scalar code and stack
 * copies: measured much slower).  lo.w carries the cluster's triangle count, hi.w its
 * index as a float (exact: clusters <= 2^CLUSTER_BITS <= 2^24).  The
 * partition moves whole records, so every pass reads a node's clusters in
 * sequence rather than through an index array. */
#if CLUSTER_BITS > 24
#error "ClusterRecord keeps the cluster index in a float: CLUSTER_BITS must be <= 24"
#endif
typedef struct {
    float4 lo;
    float4 hi;
} ClusterRecord;

/* A pending top node: the clusters records[begin..end) and where to hang it. */
typedef struct {
    int begin;
    int end;
    int parent; /* top node, or -1 for the root */
    int side_and_depth; /* bit 0: right child of parent; the rest: depth */
} TopTask;

/* One work-item per cluster: its radix-tree root and the compact records the
 * top build reads (a few MB at most, instead of scattered radix-tree nodes).
 * The host launches as many work-items as there can be clusters and never
 * reads the count (issue 57): work-item 0 writes it to info[2] for the
 * stages after, and queues the root task over all clusters when there are
 * two or more (with one, no level finds a task and the radix tree stands). */
__kernel void gather_clusters(__global const uint *scan, int n, __global const int *cluster_first,
                              __global const int *range_first, __global const int *range_last,
                              __global const Aabb *boxes, __global const float *sah_cost,
                              __global const int *height, __global int *cluster_root,
                              __global Aabb *cluster_box, __global ClusterRecord *records,
                              __global float *cluster_cost, __global int *cluster_height,
                              __global TopTask *tasks, __global int *task_counts,
                              __global int *info)
{
    int c = get_global_id(0);
    int cluster_count = (int)scan[n];
    if (c >= cluster_count)
        return;
    if (c == 0) {
        TopTask root = {0, cluster_count, -1, 0};
        tasks[0] = root;
        task_counts[0] = cluster_count >= 2;
        info[2] = cluster_count;
    }
    int first = cluster_first[c];
    int last = (c + 1 < cluster_count ? cluster_first[c + 1] : n) - 1;
    int root;
    if (first == last)
        root = (n - 1) + first; /* a one-primitive cluster is a leaf node */
    else /* Karras: an internal node's range starts or ends at its own index */
        root = range_first[first] == first && range_last[first] == last ? first : last;
    Aabb box = boxes[root];
    cluster_root[c] = root;
    cluster_box[c] = box;
    ClusterRecord record = {(float4)(box.lo[0], box.lo[1], box.lo[2], (float)(last - first + 1)),
                            (float4)(box.hi[0], box.hi[1], box.hi[2], (float)c)};
    records[c] = record;
    cluster_cost[c] = sah_cost[root];
    cluster_height[c] = height[root];
}

/* GROW_LO / GROW_HI (core/spelled.h) on float4s. */
inline float4 grow_lo(float4 acc, float4 value)
{
    return GROW_LO(acc, value);
}

inline float4 grow_hi(float4 acc, float4 value)
{
    return GROW_HI(acc, value);
}

/* grow_lo on xyz, a sum on w: a bin's lower corner and its triangle count. */
inline float4 grow_bin(float4 acc, float4 value)
{
    float4 low = grow_lo(acc, value);
    return (float4)(low.xyz, acc.w + value.w);
}

/* aabb_area of the box lo.xyz..hi.xyz, written as the same expression so the
 * result is bit-identical (the trees must not depend on the record layout). */
inline float area_of(float4 lo, float4 hi)
{
    float4 d = hi - lo;
    if (!(d.x >= 0.0f && d.y >= 0.0f && d.z >= 0.0f))
        return 0.0f;
    return 2.0f * (d.x * d.y + d.y * d.z + d.z * d.x);
}

/* area_of of three boxes given their extents d0, d1, d2, in lanes x, y, z:
 * transposed so each lane computes exactly area_of's expression. */
inline float4 areas_of(float4 d0, float4 d1, float4 d2)
{
    float4 dx = (float4)(d0.x, d1.x, d2.x, 0.0f);
    float4 dy = (float4)(d0.y, d1.y, d2.y, 0.0f);
    float4 dz = (float4)(d0.z, d1.z, d2.z, 0.0f);
    int4 valid = dx >= 0.0f & dy >= 0.0f & dz >= 0.0f;
    return select((float4)(0.0f), 2.0f * (dx * dy + dy * dz + dz * dx), valid);
}

/* A sweep over a node's bins, the three axes side by side (lane a for axis
 * a): per axis the box of the bins swept so far, and their count. */
typedef struct {
    float4 lo0, lo1, lo2, hi0, hi1, hi2, size;
} Sweep;

inline void sweep_start(Sweep *s)
{
    s->lo0 = s->lo1 = s->lo2 = (float4)(INFINITY);
    s->hi0 = s->hi1 = s->hi2 = (float4)(-INFINITY);
    s->size = (float4)(0.0f);
}

/* Bin b added to the sweep (bin_lo, bin_hi and bin_size as
 * split_clusters'); the areas of the swept boxes, per axis. */
inline float4 sweep_bin(Sweep *s, float4 (*bin_lo)[TOP_SAH_BINS], float4 (*bin_hi)[TOP_SAH_BINS],
                        const float4 *bin_size, int b)
{
    s->lo0 = grow_lo(s->lo0, bin_lo[0][b]);
    s->hi0 = grow_hi(s->hi0, bin_hi[0][b]);
    s->lo1 = grow_lo(s->lo1, bin_lo[1][b]);
    s->hi1 = grow_hi(s->hi1, bin_hi[1][b]);
    s->lo2 = grow_lo(s->lo2, bin_lo[2][b]);
    s->hi2 = grow_hi(s->hi2, bin_hi[2][b]);
    s->size += bin_size[b];
    return areas_of(s->hi0 - s->lo0, s->hi1 - s->lo1, s->hi2 - s->lo2);
}

/* The bin of a record's centre on each axis (.xyz).  The bounds are int4s:
 * the spec's clamp(int4, int, int) means the same, but Oclgrind 19.10 fills
 * only lane x from scalar bounds and leaves lanes y..w garbage (bins out of
 * the arrays below). */
inline int4 bins_of(ClusterRecord r, float4 lo, float4 inv_extent, int bins)
{
    float4 center = 0.5f * (r.lo + r.hi);
    /* clamped as floats first: converting a float the int cannot hold is
     * undefined (OpenCL C 6.2.3.3); inverse_extents keeps it finite */
    float4 x = (center - lo) * inv_extent;
    x = x > 0.0f ? x : (float4)(0.0f);
    x = x < (float)(bins - 1) ? x : (float4)((float)(bins - 1));
    return convert_int4(x);
}

/* bins / extent per axis (0 on a flat one), capped at FLT_MAX: centres
 * closer than bins / FLT_MAX (1e-38 apart) would make it inf, and the
 * lowest centre's bin 0 * inf = NaN, which left_of_split sends right. */
inline float4 inverse_extents(float4 extent, float bins)
{
    float4 inv = (float4)(extent.x > 0.0f ? bins / extent.x : 0.0f,
                          extent.y > 0.0f ? bins / extent.y : 0.0f,
                          extent.z > 0.0f ? bins / extent.z : 0.0f, 0.0f);
    return inv < FLT_MAX ? inv : (float4)(FLT_MAX);
}

inline int lane(int4 v, int axis)
{
    return axis == 0 ? v.x : axis == 1 ? v.y : v.z;
}

inline float lane_f(float4 v, int axis)
{
    return axis == 0 ? v.x : axis == 1 ? v.y : v.z;
}

/* bins_of(r, ...) on `axis` is at most bins_after - 1: bins_of truncates
 * x = (center - lo) * inv_extent (x >= 0, as lo is the least centre), and
 * trunc(x) < B + 1 <=> x < B + 1; the clamp at bins - 1 never reaches B.
 * Same float operations on one axis, so the same answer for less work. */
inline int left_of_split(ClusterRecord r, int axis, float lo, float inv_extent, float bins_after)
{
    float center = 0.5f * (lane_f(r.lo, axis) + lane_f(r.hi, axis));
    return (center - lo) * inv_extent < bins_after;
}

/* in[begin..end) -> out[begin..end), the records left of the split first
 * (in order) and the others after them (in reverse); returns the first of
 * the others.  Every record is stored at both ends, and only the end that
 * it belongs to moves on: no branch on the side, which no predictor guesses
 * (in place, with swaps, the mispredictions took a quarter of the time). */
inline int partition_records(__global const ClusterRecord *in, __global ClusterRecord *out,
                             int begin, int end, int axis, float lo, float inv_extent,
                             float bins_after)
{
    int left_end = begin, right_begin = end - 1;
    for (int k = begin; k < end; ++k) {
        ClusterRecord r = in[k];
        int left = left_of_split(r, axis, lo, inv_extent, bins_after);
        out[left_end] = r;
        out[right_begin] = r;
        left_end += left;
        right_begin -= !left;
    }
    return left_end;
}

inline void attach(int ref, int parent, int side, __global int *top_left,
                   __global int *top_right, volatile __global int *info)
{
    if (parent < 0)
        info[1] = ref; /* the root */
    else if (side)
        top_right[parent] = ref;
    else
        top_left[parent] = ref;
}

/* split_clusters for two clusters (a third of all top nodes), without its
 * loops and bin arrays but with its arithmetic, so the tree is the same:
 * the split is always begin + 1, and the first axis of least cost whose
 * bins_of separates the two puts the one in bin 0 on the left.  Isolation
 * needs three clusters or more. */
inline int split_pair(__global const ClusterRecord *in, __global ClusterRecord *out, int begin,
                      float4 *box_lo, float4 *box_hi)
{
    ClusterRecord a = in[begin], b = in[begin + 1];
    *box_lo = grow_lo(a.lo, b.lo);
    *box_hi = grow_hi(a.hi, b.hi);
    float4 center_a = 0.5f * (a.lo + a.hi), center_b = 0.5f * (b.lo + b.hi);
    float4 lo = grow_lo(center_a, center_b), extent = grow_hi(center_a, center_b) - lo;
    lo.w = 0.0f;
    float4 inv_extent = inverse_extents(extent, 2.0f);
    int4 bin_a = bins_of(a, lo, inv_extent, 2), bin_b = bins_of(b, lo, inv_extent, 2);
    float area_a = area_of(a.lo, a.hi), area_b = area_of(b.lo, b.hi);
    float cost_a_left = a.lo.w * area_a + b.lo.w * area_b;
    float cost_b_left = b.lo.w * area_b + a.lo.w * area_a;
    float best_cost = INFINITY;
    int swap = 0;
    for (int axis = 0; axis < 3; ++axis) {
        int side_a = lane(bin_a, axis);
        if (side_a == lane(bin_b, axis)) /* also every axis with inv_extent 0 */
            continue;
        float cost = side_a == 0 ? cost_a_left : cost_b_left;
        if (cost < best_cost) {
            best_cost = cost;
            swap = side_a != 0;
        }
    }
    out[begin] = swap ? b : a;
    out[begin + 1] = swap ? a : b;
    return begin + 1;
}

/* The split of least SAH cost over a node's bins (bin_lo/hi[a][b] the box
 * of bin b on axis a, its triangle count in bin_lo's w lane): *best_axis
 * -1 where no axis has a usable split.  Shared by split_clusters and the
 * work-group split, so both choose the same split. */
inline void choose_split(float4 (*bin_lo)[TOP_SAH_BINS], float4 (*bin_hi)[TOP_SAH_BINS], int bins,
                         float4 inv_extent, float *best_cost, int *best_axis, int *best_bin)
{
    /* Lane a of bin_size[b]: bin b's count on axis a, so the sweeps read one vector. */
    float4 bin_size[TOP_SAH_BINS];
    for (int b = 0; b < bins; ++b)
        bin_size[b] = (float4)(bin_lo[0][b].w, bin_lo[1][b].w, bin_lo[2][b].w, 0.0f);

    /* Both sweeps run the three axes side by side, lane a for axis a: the
     * per-bin work is a few vector ops instead of three scalar passes. */
    float4 right_area[TOP_SAH_BINS], right_size[TOP_SAH_BINS];
    Sweep sweep;
    sweep_start(&sweep);
    for (int b = bins - 1; b > 0; --b) {
        right_area[b] = sweep_bin(&sweep, bin_lo, bin_hi, bin_size, b);
        right_size[b] = sweep.size;
    }
    /* An axis whose centroids coincide has no split (all in bin 0). */
    int4 usable_axis = inv_extent != 0.0f;
    float4 axis_cost = (float4)(INFINITY);
    int4 axis_bin = (int4)(0);
    sweep_start(&sweep);
    for (int b = 0; b < bins - 1; ++b) {
        float4 area = sweep_bin(&sweep, bin_lo, bin_hi, bin_size, b);
        float4 cost = sweep.size * area + right_size[b + 1] * right_area[b + 1];
        /* Strict <: per axis the first bin of least cost, as a scalar scan. */
        int4 better = usable_axis & (sweep.size != 0.0f) & (right_size[b + 1] != 0.0f) &
                      (cost < axis_cost);
        axis_cost = select(axis_cost, cost, better);
        axis_bin = select(axis_bin, (int4)(b), better);
    }
    /* Axes in order, strict <: the first (axis, bin) of least cost, the
     * split a scan over axis 0, 1, 2 in turn would keep. */
    *best_cost = INFINITY;
    *best_axis = -1;
    *best_bin = 0;
    for (int axis = 0; axis < 3; ++axis) {
        float cost = lane_f(axis_cost, axis);
        if (cost < *best_cost) {
            *best_cost = cost;
            *best_axis = axis;
            *best_bin = lane(axis_bin, axis);
        }
    }
}

/* A record's centre into the centroid bounds and its box into the box. */
inline void grow_bounds(ClusterRecord r, float4 *centroid_lo, float4 *centroid_hi,
                        float4 *lo_corner, float4 *hi_corner)
{
    float4 center = 0.5f * (r.lo + r.hi);
    *centroid_lo = grow_lo(*centroid_lo, center);
    *centroid_hi = grow_hi(*centroid_hi, center);
    *lo_corner = grow_lo(*lo_corner, r.lo);
    *hi_corner = grow_hi(*hi_corner, r.hi);
}

/* The SAH cost of isolating the largest cluster (largest_size triangles, box
 * area largest_area) from the rest (the box rest_lo..rest_hi). */
inline float isolation_cost(float largest_size, float largest_area, float total, float4 rest_lo,
                            float4 rest_hi)
{
    return largest_size * largest_area + (total - largest_size) * area_of(rest_lo, rest_hi);
}

/* Split records[begin..end) with the binned SAH: write the range to
 * out[begin..end), the left child's records first, and return the split
 * point, and the box of the whole range in *box_lo/hi.  A split's cost is
 * N_L A(L) + N_R A(R), N counting triangles (Wald 2007).  Besides the bins
 * it tries isolating the largest cluster: centroid bins cannot separate a
 * huge primitive (a ground plane) whose centre lies among the others, and
 * leaving it inside inflates every box below.  (Only near the top, so
 * isolation chains stay short.) */
inline int split_clusters(__global const ClusterRecord *records, __global ClusterRecord *out,
                          int begin, int end, int depth, float4 *box_lo, float4 *box_hi)
{
    if (end - begin == 2)
        return split_pair(records, out, begin, box_lo, box_hi);
    /* The isolation candidate needs the largest cluster (the first of equal
     * areas), the triangle total and the box of the rest: gathered in the
     * same pass, the rest growing by each cluster that stops being largest. */
    int try_isolate = depth < TOP_ISOLATE_DEPTH && end - begin > 2;
    float4 centroid_lo = (float4)(INFINITY), centroid_hi = (float4)(-INFINITY);
    float4 rest_lo = centroid_lo, rest_hi = centroid_hi;
    ClusterRecord big = {rest_lo, rest_hi};
    float4 lo_corner = rest_lo, hi_corner = rest_hi;
    float total = 0.0f, largest_area = -1.0f;
    int largest = begin;
    for (int k = begin; k < end; ++k) {
        ClusterRecord r = records[k];
        grow_bounds(r, &centroid_lo, &centroid_hi, &lo_corner, &hi_corner);
        if (try_isolate) {
            total += r.lo.w;
            float area = area_of(r.lo, r.hi);
            ClusterRecord other = r;
            if (area > largest_area) {
                largest_area = area;
                largest = k;
                other = big;
                big = r;
            }
            rest_lo = grow_lo(rest_lo, other.lo);
            rest_hi = grow_hi(rest_hi, other.hi);
        }
    }
    /* Half as many bins as clusters (at least 2), up to TOP_SAH_BINS: a
     * node's cost stays proportional to its clusters (a fixed 3 x 32 bins per
     * node dominated the deep levels' many small nodes), and half rather than
     * all of them measured faster on the deep levels for a barely higher SAH
     * cost. */
    *box_lo = lo_corner;
    *box_hi = hi_corner;
    int bins = min(max((end - begin) / 2, 2), TOP_SAH_BINS);
    float4 extent = centroid_hi - centroid_lo;
    float4 lo = (float4)(centroid_lo.xyz, 0.0f);
    float4 inv_extent = inverse_extents(extent, (float)bins);

    /* Per axis a: bin_lo/hi[a][b] the box of bin b, with bin b's triangle
     * count in bin_lo's w lane (grow_bin). */
    float4 bin_lo[3][TOP_SAH_BINS], bin_hi[3][TOP_SAH_BINS];
    for (int axis = 0; axis < 3; ++axis)
        for (int b = 0; b < bins; ++b) {
            bin_lo[axis][b] = (float4)(INFINITY, INFINITY, INFINITY, 0.0f);
            bin_hi[axis][b] = (float4)(-INFINITY);
        }
    for (int k = begin; k < end; ++k) {
        ClusterRecord r = records[k];
        int4 b = bins_of(r, lo, inv_extent, bins);
        bin_lo[0][b.x] = grow_bin(bin_lo[0][b.x], r.lo);
        bin_hi[0][b.x] = grow_hi(bin_hi[0][b.x], r.hi);
        bin_lo[1][b.y] = grow_bin(bin_lo[1][b.y], r.lo);
        bin_hi[1][b.y] = grow_hi(bin_hi[1][b.y], r.hi);
        bin_lo[2][b.z] = grow_bin(bin_lo[2][b.z], r.lo);
        bin_hi[2][b.z] = grow_hi(bin_hi[2][b.z], r.hi);
    }
    float best_cost;
    int best_axis, best_bin;
    choose_split(bin_lo, bin_hi, bins, inv_extent, &best_cost, &best_axis, &best_bin);

    int middle = begin + (end - begin) / 2; /* no usable split: halve */
    int isolated = 0;
    if (try_isolate) {
        float largest_size = big.lo.w;
        if (isolation_cost(largest_size, largest_area, total, rest_lo, rest_hi) < best_cost) {
            for (int k = begin; k < end; ++k) /* the largest last */
                out[k] = k == end - 1 ? big : k == largest ? records[end - 1] : records[k];
            middle = end - 1;
            isolated = 1;
        }
    }
    if (!isolated && best_axis >= 0) {
        float split_lo = lane_f(lo, best_axis), split_scale = lane_f(inv_extent, best_axis);
        float bins_after = best_bin + 1.0f;
        /* A literal axis per call, so each inlined loop reads one lane. */
        if (best_axis == 0)
            middle = partition_records(records, out, begin, end, 0, split_lo, split_scale,
                                       bins_after);
        else if (best_axis == 1)
            middle = partition_records(records, out, begin, end, 1, split_lo, split_scale,
                                       bins_after);
        else
            middle = partition_records(records, out, begin, end, 2, split_lo, split_scale,
                                       bins_after);
    }
    if (middle == begin || middle == end || (!isolated && best_axis < 0)) {
        middle = begin + (end - begin) / 2; /* no usable split: halve, in order */
        for (int k = begin; k < end; ++k)
            out[k] = records[k];
    }
    return middle;
}

/* The top node of `task`, split at middle with the box lo..hi: its box,
 * its link from its parent and its one-cluster children (out holds the
 * children's records); its other children in children[], their count
 * returned.  *tree_depth grows to the deepest path through a cluster. */
inline int finish_node(TopTask task, int middle, float4 lo, float4 hi,
                       __global const ClusterRecord *out, __global const int *cluster_height,
                       __global int *top_left, __global int *top_right, __global Aabb *top_boxes,
                       __global volatile int *info, int *tree_depth, TopTask *children)
{
    int depth = task.side_and_depth >> 1, node = middle - 1, count = 0;
    Aabb box = {{lo.x, lo.y, lo.z}, {hi.x, hi.y, hi.z}};
    top_boxes[node] = box;
    attach(node, task.parent, task.side_and_depth & 1, top_left, top_right, info);
    int ranges[2][2] = {{task.begin, middle}, {middle, task.end}};
    for (int side = 0; side < 2; ++side) {
        if (ranges[side][1] - ranges[side][0] == 1) {
            int cluster = (int)out[ranges[side][0]].hi.w;
            attach(~cluster, node, side, top_left, top_right, info);
            /* the tree's depth: top nodes on the path, then the cluster's subtree */
            *tree_depth = max(*tree_depth, depth + 1 + cluster_height[cluster]);
            continue;
        }
        TopTask child = {ranges[side][0], ranges[side][1], node, ((depth + 1) << 1) | side};
        children[count++] = child;
    }
    return count;
}

/* One task of split_top_level, and its whole subtree if it is serial. */
inline void split_task(TopTask task, int level, int serial_depth, __global TopTask *next_tasks,
                       __global volatile int *task_counts, __global TopTask *stack,
                       __global ClusterRecord *records, __global ClusterRecord *records_odd,
                       __global const int *cluster_height, __global int *top_left,
                       __global int *top_right, __global Aabb *top_boxes,
                       __global volatile int *info)
{
    int serial = (task.side_and_depth >> 1) >= serial_depth;
    int base = task.begin, top = base;
    /* The deepest path seen, published with one atomic_max at the end: one
     * per cluster made both cores fight over info[0]'s cache line (measured
     * slower on the serial level). */
    int tree_depth = 0;
    while (1) {
        int depth = task.side_and_depth >> 1;
        /* A node at an even depth reads `records` and leaves its children's
         * in `records_odd`, and the other way round at odd depths. */
        __global ClusterRecord *in = depth & 1 ? records_odd : records;
        __global ClusterRecord *out = depth & 1 ? records : records_odd;
        float4 lo, hi;
        int middle = split_clusters(in, out, task.begin, task.end, depth, &lo, &hi);
        TopTask children[2];
        int child_count = finish_node(task, middle, lo, hi, out, cluster_height, top_left,
                                      top_right, top_boxes, info, &tree_depth, children);
        for (int c = 0; c < child_count; ++c) {
            if (serial)
                stack[top++] = children[c];
            else
                next_tasks[atomic_inc(&task_counts[level + 1])] = children[c];
        }
        if (top == base)
            break;
        task = stack[--top];
    }
    if (tree_depth > 0)
        atomic_max(&info[0], tree_depth);
}

/* One level of the top build: each task splits its range and hands its
 * children on.  The node splitting at m is top node m - 1: every split point
 * belongs to exactly one node, so nodes need no allocation.  Tasks at depth
 * serial_depth finish their whole subtree here, with the slice [begin, end)
 * of `stack` that matches their clusters as a private work stack; so the
 * host runs serial_depth + 1 levels whatever the input.
 *
 * The host launches 2^level work-items, as many as the level can have
 * tasks, without reading back how many it has.  Work-item i takes the tasks
 * [i * count / items, (i + 1) * count / items), so that the tasks spread
 * over all the work-items: PoCL hands each core a block of consecutive
 * work-groups, and the first `count` work-items would all be on one core
 * (measured: the serial level took much longer). */
__kernel void split_top_level(__global const TopTask *tasks, int level, int serial_depth,
                              __global TopTask *next_tasks, __global volatile int *task_counts,
                              __global TopTask *stack, __global ClusterRecord *records,
                              __global ClusterRecord *records_odd,
                              __global const int *cluster_height, __global int *top_left,
                              __global int *top_right, __global Aabb *top_boxes,
                              __global volatile int *info)
{
    long i = get_global_id(0), items = get_global_size(0);
    long count = task_counts[level]; /* the tasks the level before queued */
    for (long t = i * count / items; t < (i + 1) * count / items; ++t)
        split_task(tasks[t], level, serial_depth, next_tasks, task_counts, stack, records,
                   records_odd, cluster_height, top_left, top_right, top_boxes, info);
}

/* TOP_GROUP (-D, hlbvh_cl/build/sah_top.py): the work-items of
 * split_top_group's groups at most, its local arrays' length; the host
 * launches a power of two no larger. */
#ifndef TOP_GROUP
#error "TOP_GROUP must be defined (-D TOP_GROUP=...)"
#endif

/* A float as an int of the same order (the negatives' magnitude bits
 * flipped), and back: so local atomic_min/max, standard on ints, take the
 * least and greatest float of a bin in any order.  -0 and +0 get different
 * ints where the serial scan keeps whichever came first; bins only feed
 * areas, whose sign of zero no comparison sees, so the split is the same. */
inline int order_key(float f)
{
    int i = as_int(f);
    return i < 0 ? i ^ 0x7fffffff : i;
}

inline float key_value(int key)
{
    return as_float(key < 0 ? key ^ 0x7fffffff : key);
}

/* The first and last+1 record of work-item `item`'s block of [begin, end):
 * blocks in order, so a fold of the blocks in order is the serial scan's. */
inline int block_start(int begin, int end, int item, int items)
{
    return begin + (int)((long)item * (end - begin) / items);
}

/* split_clusters by a whole work-group (issue 57: at the top levels a few
 * tasks hold all clusters, which one work-item each scanned serially), with
 * the same result bit for bit:
 *  - the box, centroid bounds, triangle total and largest cluster: each
 *    work-item folds its block in order, then a tree in local memory joins
 *    neighbouring blocks, earlier on the left (Blelloch 1990), so the ties
 *    of GROW_LO/HI (the first of equal values: -0 and +0 in the box) and of
 *    the largest area (the first) fall as in the serial scan;
 *  - the bins and the box of all but the largest: min/max over int keys by
 *    local atomics (order_key), the counts by atomic_add (exact, as the
 *    serial float sum is below 2^24 triangles);
 *  - the split: choose_split and isolation_cost, by work-item 0;
 *  - the partition: in tiles of one record per work-item, a local prefix
 *    sum of the left flags places each record where partition_records puts
 *    it (left ones in order, the others from the end backwards).
 * Returns the split point; *box_lo/hi the task's box (every work-item). */
inline int split_clusters_group(__global const ClusterRecord *records,
                                __global ClusterRecord *out, int begin, int end, int depth,
                                float4 *box_lo, float4 *box_hi, __local float4 *fold_lo,
                                __local float4 *fold_hi, __local float4 *fold_centre_lo,
                                __local float4 *fold_centre_hi, __local float *fold_total,
                                __local float *fold_area, __local int *fold_largest,
                                __local int *bin_min, __local int *bin_max, __local int *bin_count,
                                __local int *decision)
{
    int item = (int)get_local_id(0), items = (int)get_local_size(0);
    int try_isolate = depth < TOP_ISOLATE_DEPTH && end - begin > 2;
    /* pass 1: each work-item's block, folded in order */
    float4 centroid_lo = (float4)(INFINITY), centroid_hi = (float4)(-INFINITY);
    float4 lo_corner = centroid_lo, hi_corner = centroid_hi;
    float total = 0.0f, largest_area = -1.0f;
    int largest = begin;
    int first = block_start(begin, end, item, items), last = block_start(begin, end, item + 1, items);
    for (int k = first; k < last; ++k) {
        ClusterRecord r = records[k];
        grow_bounds(r, &centroid_lo, &centroid_hi, &lo_corner, &hi_corner);
        total += r.lo.w;
        float area = area_of(r.lo, r.hi);
        if (area > largest_area) {
            largest_area = area;
            largest = k;
        }
    }
    fold_lo[item] = lo_corner;
    fold_hi[item] = hi_corner;
    fold_centre_lo[item] = centroid_lo;
    fold_centre_hi[item] = centroid_hi;
    fold_total[item] = total;
    fold_area[item] = largest_area;
    fold_largest[item] = largest;
    /* items is a power of two: slot i joins slot i + step, its next block */
    for (int step = 1; step < items; step *= 2) {
        barrier(CLK_LOCAL_MEM_FENCE);
        if ((item & (2 * step - 1)) == 0) {
            int next = item + step;
            fold_lo[item] = grow_lo(fold_lo[item], fold_lo[next]);
            fold_hi[item] = grow_hi(fold_hi[item], fold_hi[next]);
            fold_centre_lo[item] = grow_lo(fold_centre_lo[item], fold_centre_lo[next]);
            fold_centre_hi[item] = grow_hi(fold_centre_hi[item], fold_centre_hi[next]);
            fold_total[item] += fold_total[next];
            if (fold_area[next] > fold_area[item]) { /* strict: the first largest */
                fold_area[item] = fold_area[next];
                fold_largest[item] = fold_largest[next];
            }
        }
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    *box_lo = fold_lo[0];
    *box_hi = fold_hi[0];
    centroid_lo = fold_centre_lo[0];
    largest = fold_largest[0];
    int bins = min(max((end - begin) / 2, 2), TOP_SAH_BINS);
    float4 lo = (float4)(centroid_lo.xyz, 0.0f);
    float4 inv_extent = inverse_extents(fold_centre_hi[0] - centroid_lo, (float)bins);

    /* pass 2: the bins, and (key 3 * bins of each array) the box of all
     * but the largest cluster */
    int slots = 3 * TOP_SAH_BINS + 1, rest = 3 * TOP_SAH_BINS;
    for (int s = item; s < 3 * slots; s += items) {
        bin_min[s] = order_key(INFINITY);
        bin_max[s] = order_key(-INFINITY);
    }
    for (int s = item; s < slots; s += items)
        bin_count[s] = 0;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int k = begin + item; k < end; k += items) {
        ClusterRecord r = records[k];
        int4 b = bins_of(r, lo, inv_extent, bins);
        for (int axis = 0; axis < 3; ++axis) {
            int slot = axis * TOP_SAH_BINS + lane(b, axis);
            atomic_add(&bin_count[slot], (int)r.lo.w);
            for (int c = 0; c < 3; ++c) {
                atomic_min(&bin_min[3 * slot + c], order_key(lane_f(r.lo, c)));
                atomic_max(&bin_max[3 * slot + c], order_key(lane_f(r.hi, c)));
            }
        }
        if (k != largest)
            for (int c = 0; c < 3; ++c) {
                atomic_min(&bin_min[3 * rest + c], order_key(lane_f(r.lo, c)));
                atomic_max(&bin_max[3 * rest + c], order_key(lane_f(r.hi, c)));
            }
    }
    barrier(CLK_LOCAL_MEM_FENCE);

    /* the split, as split_clusters chooses it; decision[0]: 0 partition on
     * axis decision[1] at bin decision[2], 1 isolate, 2 halve */
    if (item == 0) {
        float4 bin_lo[3][TOP_SAH_BINS], bin_hi[3][TOP_SAH_BINS];
        for (int axis = 0; axis < 3; ++axis)
            for (int b = 0; b < bins; ++b) {
                int slot = axis * TOP_SAH_BINS + b;
                bin_lo[axis][b] = (float4)(key_value(bin_min[3 * slot]),
                                           key_value(bin_min[3 * slot + 1]),
                                           key_value(bin_min[3 * slot + 2]), (float)bin_count[slot]);
                bin_hi[axis][b] = (float4)(key_value(bin_max[3 * slot]),
                                           key_value(bin_max[3 * slot + 1]),
                                           key_value(bin_max[3 * slot + 2]), 0.0f);
            }
        float best_cost;
        int best_axis, best_bin;
        choose_split(bin_lo, bin_hi, bins, inv_extent, &best_cost, &best_axis, &best_bin);
        int mode = best_axis >= 0 ? 0 : 2;
        if (try_isolate) {
            ClusterRecord big = records[largest];
            float4 rest_lo = (float4)(key_value(bin_min[3 * rest]), key_value(bin_min[3 * rest + 1]),
                                      key_value(bin_min[3 * rest + 2]), 0.0f);
            float4 rest_hi = (float4)(key_value(bin_max[3 * rest]), key_value(bin_max[3 * rest + 1]),
                                      key_value(bin_max[3 * rest + 2]), 0.0f);
            if (isolation_cost(big.lo.w, fold_area[0], fold_total[0], rest_lo, rest_hi) < best_cost)
                mode = 1;
        }
        decision[0] = mode;
        decision[1] = best_axis;
        decision[2] = best_bin;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    int mode = decision[0], middle = begin + (end - begin) / 2;
    if (mode == 1) { /* the largest last */
        ClusterRecord big = records[largest], swapped = records[end - 1];
        for (int k = begin + item; k < end; k += items)
            out[k] = k == end - 1 ? big : k == largest ? swapped : records[k];
        middle = end - 1;
    } else if (mode == 0) {
        int axis = decision[1];
        float split_lo = lane_f(lo, axis), split_scale = lane_f(inv_extent, axis);
        float bins_after = decision[2] + 1.0f;
        /* fold_largest reused as the tile's inclusive prefix sum of left flags */
        __local int *scan = fold_largest;
        int left_before = 0;
        for (int tile = begin; tile < end; tile += items) {
            int k = tile + item;
            ClusterRecord r = {(float4)(0.0f), (float4)(0.0f)};
            int left = 0;
            if (k < end) {
                r = records[k];
                left = left_of_split(r, axis, split_lo, split_scale, bins_after);
            }
            barrier(CLK_LOCAL_MEM_FENCE); /* the last tile's total has been read */
            scan[item] = left;
            for (int step = 1; step < items; step *= 2) {
                barrier(CLK_LOCAL_MEM_FENCE);
                int add = item >= step ? scan[item - step] : 0;
                barrier(CLK_LOCAL_MEM_FENCE);
                scan[item] += add;
            }
            barrier(CLK_LOCAL_MEM_FENCE);
            int lefts = left_before + scan[item] - left; /* left records before k */
            if (k < end)
                out[left ? begin + lefts : end - 1 - ((k - begin) - lefts)] = r;
            left_before += scan[items - 1];
        }
        middle = begin + left_before;
    }
    if (mode == 2 || middle == begin || middle == end) {
        middle = begin + (end - begin) / 2; /* no usable split: halve, in order */
        barrier(CLK_GLOBAL_MEM_FENCE); /* the partition's stores first */
        for (int k = begin + item; k < end; k += items)
            out[k] = records[k];
    }
    return middle;
}

/* split_top_level with one work-group per task, for the levels with few
 * tasks (the host picks them): group g takes the tasks
 * [g * count / groups, (g + 1) * count / groups), none of them serial. */
__kernel void split_top_group(__global const TopTask *tasks, int level,
                              __global TopTask *next_tasks, __global volatile int *task_counts,
                              __global ClusterRecord *records, __global ClusterRecord *records_odd,
                              __global const int *cluster_height, __global int *top_left,
                              __global int *top_right, __global Aabb *top_boxes,
                              __global volatile int *info)
{
    __local float4 fold_lo[TOP_GROUP], fold_hi[TOP_GROUP];
    __local float4 fold_centre_lo[TOP_GROUP], fold_centre_hi[TOP_GROUP];
    __local float fold_total[TOP_GROUP], fold_area[TOP_GROUP];
    __local int fold_largest[TOP_GROUP];
    __local int bin_min[3 * (3 * TOP_SAH_BINS + 1)], bin_max[3 * (3 * TOP_SAH_BINS + 1)];
    __local int bin_count[3 * TOP_SAH_BINS + 1];
    __local int decision[3];
    long g = get_group_id(0), groups = get_num_groups(0);
    long count = task_counts[level]; /* the tasks the level before queued */
    int tree_depth = 0;
    for (long t = g * count / groups; t < (g + 1) * count / groups; ++t) {
        TopTask task = tasks[t];
        int depth = task.side_and_depth >> 1;
        __global ClusterRecord *in = depth & 1 ? records_odd : records;
        __global ClusterRecord *out = depth & 1 ? records : records_odd;
        float4 lo = (float4)(0.0f), hi = lo;
        int middle = task.begin + 1;
        barrier(CLK_LOCAL_MEM_FENCE); /* the last task's local arrays are read */
        if (task.end - task.begin == 2) {
            if (get_local_id(0) == 0)
                middle = split_pair(in, out, task.begin, &lo, &hi);
        } else {
            middle = split_clusters_group(in, out, task.begin, task.end, depth, &lo, &hi, fold_lo,
                                          fold_hi, fold_centre_lo, fold_centre_hi, fold_total,
                                          fold_area, fold_largest, bin_min, bin_max, bin_count,
                                          decision);
        }
        barrier(CLK_GLOBAL_MEM_FENCE); /* work-item 0 reads the children's records */
        if (get_local_id(0) == 0) {
            TopTask children[2];
            int child_count = finish_node(task, middle, lo, hi, out, cluster_height, top_left,
                                          top_right, top_boxes, info, &tree_depth, children);
            for (int c = 0; c < child_count; ++c)
                next_tasks[atomic_inc(&task_counts[level + 1])] = children[c];
        }
    }
    if (tree_depth > 0)
        atomic_max(&info[0], tree_depth);
}

/* The SAH cost of the whole tree: cost(node) = C_t A(node) + cost(left) +
 * cost(right) unrolls into the sum of C_t A over the top nodes plus the
 * clusters' costs.  One work-group of at most TOP_COST_GROUP: each
 * work-item sums a fixed stride, work-item 0 adds the partial sums in order
 * (the same total every run on a device).  The cluster count is info[2]
 * (gather_clusters); with one cluster the total is unused. */
__kernel void sum_top_cost(__global const int *info, __global const Aabb *top_boxes,
                           __global const float *cluster_cost, __global float *sah_cost_out)
{
    __local float partial[TOP_COST_GROUP];
    int cluster_count = info[2], top_count = cluster_count - 1;
    /* the group may be smaller than asked (a device's limit for the kernel) */
    int i = get_local_id(0), items = (int)get_local_size(0);
    float sum = 0.0f;
    for (int t = i; t < top_count; t += items)
        sum += SAH_TRAVERSAL_COST * aabb_area(top_boxes[t]);
    for (int c = i; c < cluster_count; c += items)
        sum += cluster_cost[c];
    partial[i] = sum;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (i == 0) {
        float total = 0.0f;
        for (int k = 0; k < items; ++k)
            total += partial[k];
        sah_cost_out[0] = total;
    }
}
