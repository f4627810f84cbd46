/* One pass of a stable LSD radix sort of (key, value) pairs (stage: sort).
 *
 * A pass sorts by the digit (key >> shift) & digit_mask, RADIX_BITS bits wide
 * at most.  Per pass (Satish, Harris & Garland 2009, "Designing Efficient
 * Sorting Algorithms for Manycore GPUs", the digit-major histogram layout):
 *   1. radix_histogram: every work-group counts the digits of its tile;
 *   2. an exclusive scan (parallel/scan.cl) of the digit-major histogram matrix
 *      [digit][group] makes entry (d, g) the number of keys with a
 *      smaller digit plus those with digit d in earlier groups: the first
 *      output slot of digit d for group g;
 *   3. radix_scatter recounts, adds the per-work-item offsets and moves every
 *      pair to its slot.
 * Each work-group owns a contiguous tile and each work-item a contiguous
 * sub-tile of `per_item` pairs, counted into its own column of
 * counts[RADIX][SORT_GROUP_SIZE] and scattered serially in input order, so the
 * sort is stable by construction and needs no atomics.  The barriers sit
 * outside every loop (PoCL's CPU device has hung on barriers inside loops in
 * local-memory code).
 *
 * Defines: KEY_TYPE (uint or ulong), RADIX_BITS, SORT_GROUP_SIZE (required).
 * Local memory: 4 << RADIX_BITS bytes per work-item.
 */

#if !defined(KEY_TYPE) || !defined(RADIX_BITS) || !defined(SORT_GROUP_SIZE)
#error "KEY_TYPE, RADIX_BITS and SORT_GROUP_SIZE must be defined"
#endif

#define RADIX (1u << RADIX_BITS)

/* Sub-tile [*begin, *end) of global work-item `item`, clipped to n. */
inline void sub_tile(uint item, uint per_item, uint n, uint *begin, uint *end)
{
    *begin = min(item * per_item, n);
    *end = min(*begin + per_item, n);
}

inline uint digit_of(KEY_TYPE key, uint shift, uint digit_mask)
{
    return (uint)(key >> shift) & digit_mask;
}

/* counts[d * SORT_GROUP_SIZE + lid] = how many keys of this work-item's
 * sub-tile [*begin, *end) have digit d, for the whole group once it returns
 * (it holds a barrier: every work-item of the group must call it).
 * Digit-major with the work-item fastest keeps a GPU's work-items on
 * distinct banks. */
inline void count_digits(const __global KEY_TYPE *keys, uint n, uint per_item, uint shift,
                         uint digit_mask, __local uint *counts, uint *begin, uint *end)
{
    const uint lid = get_local_id(0);
    sub_tile(get_global_id(0), per_item, n, begin, end);
    for (uint d = 0; d < RADIX; ++d)
        counts[d * SORT_GROUP_SIZE + lid] = 0;
    for (uint i = *begin; i < *end; ++i)
        ++counts[digit_of(keys[i], shift, digit_mask) * SORT_GROUP_SIZE + lid];
    barrier(CLK_LOCAL_MEM_FENCE);
}

/* histogram[d * groups + g] = how many keys of group g's tile have digit d. */
__kernel __attribute__((reqd_work_group_size(SORT_GROUP_SIZE, 1, 1)))
void radix_histogram(const __global KEY_TYPE *keys, uint n, uint per_item, uint shift,
                     uint digit_mask, __global uint *histogram)
{
    __local uint counts[RADIX * SORT_GROUP_SIZE];
    uint begin, end;
    count_digits(keys, n, per_item, shift, digit_mask, counts, &begin, &end);

    const uint group = get_group_id(0), groups = get_num_groups(0);
    for (uint d = get_local_id(0); d < RADIX; d += SORT_GROUP_SIZE) {
        uint sum = 0;
        for (uint w = 0; w < SORT_GROUP_SIZE; ++w)
            sum += counts[d * SORT_GROUP_SIZE + w];
        histogram[d * groups + group] = sum;
    }
}

/* Moves every pair of the group's tile to its place in the output of this
 * pass.  digit_offsets is the histogram after an exclusive scan. */
__kernel __attribute__((reqd_work_group_size(SORT_GROUP_SIZE, 1, 1)))
void radix_scatter(const __global KEY_TYPE *keys_in, const __global uint *values_in,
                   uint n, uint per_item, uint shift, uint digit_mask,
                   const __global uint *digit_offsets,
                   __global KEY_TYPE *keys_out, __global uint *values_out)
{
    __local uint counts[RADIX * SORT_GROUP_SIZE];
    uint begin, end;
    count_digits(keys_in, n, per_item, shift, digit_mask, counts, &begin, &end);

    const uint lid = get_local_id(0);
    const uint group = get_group_id(0), groups = get_num_groups(0);
    /* Turn each digit's row of counts into output slots: the group's offset
     * for the digit plus an exclusive scan over the earlier work-items. */
    for (uint d = lid; d < RADIX; d += SORT_GROUP_SIZE) {
        uint slot = digit_offsets[d * groups + group];
        for (uint w = 0; w < SORT_GROUP_SIZE; ++w) {
            const uint count = counts[d * SORT_GROUP_SIZE + w];
            counts[d * SORT_GROUP_SIZE + w] = slot;
            slot += count;
        }
    }
    barrier(CLK_LOCAL_MEM_FENCE);

    for (uint i = begin; i < end; ++i) {
        const KEY_TYPE key = keys_in[i];
        const uint slot = counts[digit_of(key, shift, digit_mask) * SORT_GROUP_SIZE + lid]++;
        keys_out[slot] = key;
        values_out[slot] = values_in[i];
    }
}
