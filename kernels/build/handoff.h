/* Handing results from one bottom-up walker to another (Karras 2012, sec. 4;
 * Apetrei 2014): at a node where two subtrees meet, each walker stores its
 * subtree's results and counts itself in; the first stops, the second reads
 * the other's results and goes on.  The stores must happen before the
 * second walker's loads, across work-groups.
 *
 * ACQUIRE_RELEASE=1 (the host sets it where the device compiles OpenCL C 2.0,
 * or 3.0 with acquire-release order at device scope, and builds the program
 * for that version): the count is a release fetch-add, and the second
 * arrival follows it with an acquire fence, so by the 2.0 memory model
 * (sec. 3.3.6, release operation and acquire fence) plain stores before the
 * first arrival's count happen before plain loads after the second's.
 *
 * ACQUIRE_RELEASE=0 (OpenCL C 1.2): 1.2 orders nothing between work-groups
 * but atomics (sec. 3.3.1: plain memory is consistent only at a barrier,
 * within a work-group), so every word handed on is itself stored and loaded
 * by an atomic, with the 1.2 fences around the count for the order of this
 * work-item's accesses.  Oclgrind, a 1.2 device, checks this path. */
#ifndef HANDOFF_H
#define HANDOFF_H

#include "core/aabb.h"

#if ACQUIRE_RELEASE

/* The number of walkers that arrived at this node before this one. */
inline int handoff_arrive(__global int *count)
{
    int before = atomic_fetch_add_explicit((volatile __global atomic_int *)count, 1,
                                           memory_order_release, memory_scope_device);
    if (before != 0)
        atomic_work_item_fence(CLK_GLOBAL_MEM_FENCE, memory_order_acquire, memory_scope_device);
    return before;
}

inline void handoff_store(__global int *word, int value)
{
    *word = value;
}

inline int handoff_load(__global int *word)
{
    return *word;
}

#else

inline int handoff_arrive(__global int *count)
{
    write_mem_fence(CLK_GLOBAL_MEM_FENCE);
    int before = atomic_inc(count);
    read_mem_fence(CLK_GLOBAL_MEM_FENCE);
    return before;
}

inline void handoff_store(__global int *word, int value)
{
    atomic_xchg(word, value);
}

inline int handoff_load(__global int *word)
{
    return atomic_or(word, 0);
}

#endif

inline void handoff_store_float(__global float *word, float value)
{
    handoff_store((__global int *)word, as_int(value));
}

inline float handoff_load_float(__global float *word)
{
    return as_float(handoff_load((__global int *)word));
}

/* A box given as its two corners' arrays, each of three floats (never one
 * pointer indexed past lo[2] into hi: that reads beyond a declared array). */
inline void handoff_store_box(__global float *lo, __global float *hi, Aabb box)
{
    for (int k = 0; k < 3; ++k) {
        handoff_store_float(lo + k, box.lo[k]);
        handoff_store_float(hi + k, box.hi[k]);
    }
}

inline Aabb handoff_load_box(__global float *lo, __global float *hi)
{
    Aabb box = {{handoff_load_float(lo), handoff_load_float(lo + 1), handoff_load_float(lo + 2)},
                {handoff_load_float(hi), handoff_load_float(hi + 1), handoff_load_float(hi + 2)}};
    return box;
}

#endif
