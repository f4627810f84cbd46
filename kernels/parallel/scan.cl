/* Exclusive prefix sum of uint32, in place (stage: scan).
 *
 * Reduce-then-scan (Merrill & Grimshaw 2009, "Parallel Scan for Stream
 * Architectures"): scan_reduce_tiles sums each work-group's tile,
 * scan_tile_sums scans those few sums in one work-group, and scan_tiles
 * rescans every tile starting from its scanned sum.  Data is read twice and
 * written once.
 *
 * Each work-group owns a contiguous tile and each work-item a contiguous
 * sub-tile of `per_item` elements that it walks serially, so the only
 * barriers sit outside loops (PoCL's CPU device has hung on barriers inside
 * loops in local-memory code).
 *
 * The _counted kernels scan a length that only the device knows (counts[at],
 * written by an earlier kernel), so the host need not read it back (issue
 * 57): the host launches as many tiles as the largest length needs, and each
 * work-item's share, ceil(n / work-items), is worked out on the device as the
 * host works it out for the others.
 *
 * Defines: SCAN_GROUP_SIZE, the work-group size (required).
 */

#ifndef SCAN_GROUP_SIZE
#error "SCAN_GROUP_SIZE must be defined"
#endif

/* Sub-tile [*begin, *end) of global work-item `item`, clipped to n. */
inline void sub_tile(uint item, uint per_item, uint n, uint *begin, uint *end)
{
    *begin = min(item * per_item, n);
    *end = min(*begin + per_item, n);
}

/* The sum of this work-item's sub-tile of data, which it sets. */
inline uint item_sum(const __global uint *data, uint n, uint per_item, uint *begin, uint *end)
{
    sub_tile(get_global_id(0), per_item, n, begin, end);
    uint sum = 0;
    for (uint i = *begin; i < *end; ++i)
        sum += data[i];
    return sum;
}

/* Scans the sub-tiles of one work-group starting from tile_offset, and lets
 * the work-item whose sub-tile ends the input write the total to data[n].
 * Every work-item of the group must call it (it holds two barriers). */
inline void scan_tile(__global uint *data, uint n, uint per_item, uint tile_offset,
                      __local uint *item_offsets)
{
    const uint lid = get_local_id(0);
    const uint item = get_global_id(0);
    uint begin, end;
    item_offsets[lid] = item_sum(data, n, per_item, &begin, &end);
    barrier(CLK_LOCAL_MEM_FENCE);

    /* The group is small, so one work-item scans its sums serially. */
    if (lid == 0) {
        uint running = tile_offset;
        for (uint w = 0; w < SCAN_GROUP_SIZE; ++w) {
            const uint count = item_offsets[w];
            item_offsets[w] = running;
            running += count;
        }
    }
    barrier(CLK_LOCAL_MEM_FENCE);

    uint running = item_offsets[lid];
    for (uint i = begin; i < end; ++i) {
        const uint value = data[i];
        data[i] = running;
        running += value;
    }
    /* Unclipped sub-tiles partition [0, per_item * items); exactly one holds
     * the end n (the first one when n == 0). */
    const bool owns_end = (n == 0) ? (item == 0)
                                   : (item * per_item < n && n <= item * per_item + per_item);
    if (owns_end)
        data[n] = running;
}

/* tile_sums[group] = sum of the group's tile.  Every work-item of the
 * group must call it (it holds a barrier). */
inline void reduce_tile(const __global uint *data, uint n, uint per_item,
                        __global uint *tile_sums, __local uint *item_sums)
{
    const uint lid = get_local_id(0);
    uint begin, end;
    item_sums[lid] = item_sum(data, n, per_item, &begin, &end);
    barrier(CLK_LOCAL_MEM_FENCE);

    if (lid == 0) {
        uint total = 0;
        for (uint w = 0; w < SCAN_GROUP_SIZE; ++w)
            total += item_sums[w];
        tile_sums[get_group_id(0)] = total;
    }
}

/* The elements per work-item that cover n over the whole launch (the host's
 * per_item for a launch of that size). */
inline uint share_of(uint n)
{
    const uint items = (uint)get_global_size(0);
    return (n + items - 1) / items;
}

__kernel __attribute__((reqd_work_group_size(SCAN_GROUP_SIZE, 1, 1)))
void scan_reduce_tiles(const __global uint *data, uint n, uint per_item,
                       __global uint *tile_sums)
{
    __local uint item_sums[SCAN_GROUP_SIZE];
    reduce_tile(data, n, per_item, tile_sums, item_sums);
}

__kernel __attribute__((reqd_work_group_size(SCAN_GROUP_SIZE, 1, 1)))
void scan_reduce_tiles_counted(const __global uint *data, const __global uint *counts, uint at,
                               __global uint *tile_sums)
{
    __local uint item_sums[SCAN_GROUP_SIZE];
    const uint n = counts[at];
    reduce_tile(data, n, share_of(n), tile_sums, item_sums);
}

/* Exclusive scan of data[0, n) by a single work-group; data[n] = total.
 * Scans the tile sums, and whole inputs small enough for one group. */
__kernel __attribute__((reqd_work_group_size(SCAN_GROUP_SIZE, 1, 1)))
void scan_tile_sums(__global uint *data, uint n, uint per_item)
{
    __local uint item_offsets[SCAN_GROUP_SIZE];
    scan_tile(data, n, per_item, 0u, item_offsets);
}

/* Exclusive scan of every tile, offset by the scanned tile sums. */
__kernel __attribute__((reqd_work_group_size(SCAN_GROUP_SIZE, 1, 1)))
void scan_tiles(__global uint *data, uint n, uint per_item,
                const __global uint *tile_offsets)
{
    __local uint item_offsets[SCAN_GROUP_SIZE];
    scan_tile(data, n, per_item, tile_offsets[get_group_id(0)], item_offsets);
}

/* scan_tile_sums over counts[at] elements: a whole short input. */
__kernel __attribute__((reqd_work_group_size(SCAN_GROUP_SIZE, 1, 1)))
void scan_tile_sums_counted(__global uint *data, const __global uint *counts, uint at)
{
    __local uint item_offsets[SCAN_GROUP_SIZE];
    const uint n = counts[at];
    scan_tile(data, n, share_of(n), 0u, item_offsets);
}

/* scan_tiles over counts[at] elements. */
__kernel __attribute__((reqd_work_group_size(SCAN_GROUP_SIZE, 1, 1)))
void scan_tiles_counted(__global uint *data, const __global uint *counts, uint at,
                        const __global uint *tile_offsets)
{
    __local uint item_offsets[SCAN_GROUP_SIZE];
    const uint n = counts[at];
    scan_tile(data, n, share_of(n), tile_offsets[get_group_id(0)], item_offsets);
}
