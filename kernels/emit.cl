/* Stage 4: emit the n-1 internal nodes of the binary radix tree in parallel
 * (Karras 2012, "Maximizing Parallelism in the Construction of BVHs, Octrees,
 * and k-d Trees", Algorithm 4).
 *
 * Node numbering: internal node i is i (0 = root); the leaf of sorted
 * primitive j is node (n - 1 + j).  Equal keys are made distinct by their
 * index (Karras sec. 4: delta = KEY_BITS + clz(i ^ j) when k_i == k_j).
 */
#include "hlbvh.h"


/* Length of the common prefix of keys i and j; -1 outside [0, n). */
inline int common_prefix(__global const morton_t *keys, int n, int i, int j)
{
    if (j < 0 || j >= n)
        return -1;
    morton_t ki = keys[i], kj = keys[j];
    if (ki == kj)
        return KEY_BITS + (int)clz((uint)(i ^ j));
    return (int)clz(ki ^ kj);
}

__kernel void emit_internal_nodes(__global const morton_t *keys, int n,
                                  __global int *left_child, __global int *right_child,
                                  __global int *parent, __global int *range_first,
                                  __global int *range_last)
{
    int i = get_global_id(0);
    if (i >= n - 1)
        return;

    /* Direction of the range: towards the neighbour sharing the longer prefix. */
    int d = common_prefix(keys, n, i, i + 1) - common_prefix(keys, n, i, i - 1) > 0 ? 1 : -1;

    /* Exponential then binary search for the far end j of the range. */
    int delta_min = common_prefix(keys, n, i, i - d);
    int l_max = 2;
    while (common_prefix(keys, n, i, i + l_max * d) > delta_min)
        l_max <<= 1;
    int l = 0;
    for (int t = l_max >> 1; t >= 1; t >>= 1)
        if (common_prefix(keys, n, i, i + (l + t) * d) > delta_min)
            l += t;
    int j = i + l * d;

    /* Binary search for the split: the last index sharing more than the
     * node's own prefix with i. */
    int delta_node = common_prefix(keys, n, i, j);
    int s = 0;
    int t = l;
    do {
        t = (t + 1) >> 1;
        if (common_prefix(keys, n, i, i + (s + t) * d) > delta_node)
            s += t;
    } while (t > 1);
    int split = i + s * d + min(d, 0);

    int first = min(i, j), last = max(i, j);
    int left = first == split ? (n - 1) + split : split;
    int right = last == split + 1 ? (n - 1) + split + 1 : split + 1;

    left_child[i] = left;
    right_child[i] = right;
    parent[left] = i;
    parent[right] = i;
    range_first[i] = first;
    range_last[i] = last;
    if (i == 0)
        parent[0] = -1;
}
