/* Moves CSR segments of 4-byte values (one hit field of intersect_all) from
 * the order the rays were traced in to the caller's order
 * (hlbvh_cl/all_hits.py): one work-item per caller ray, whose segment
 * [to[r], to[r + 1]) of `target` takes the values that start at from[r] in
 * `source`; with `numbering`, ray_index[to[r] ...] <- r too.  Writes go in
 * order and reads gather, which a CPU's caches take better than scattered
 * writes.
 */
__kernel void move_segments(__global const uint* source, __global uint* target,
                            __global const long* to, __global const long* from,
                            __global long* ray_index, const uint numbering,
                            const uint ray_count)
{
    uint r = get_global_id(0);
    if (r >= ray_count)
        return;
    long first = to[r], count = to[r + 1] - first, start = from[r];
    for (long j = 0; j < count; ++j)
        target[first + j] = source[start + j];
    if (numbering)
        for (long j = 0; j < count; ++j)
            ray_index[first + j] = (long)r;
}
