/* The traversal stack: a stacked item is a child slot of a wide node and the
 * distance at which the ray (or packet) enters its box.  At a node the met
 * children are ordered by that distance; the nearest is visited next and the
 * others pushed, the farthest first (Embree's single-ray BVH4/BVH8
 * traversal), and a pop skips items entered beyond the current limit. */
#ifndef STACK_H
#define STACK_H

#include "query/walk/node.h"

#ifndef STACK_SIZE
#error "STACK_SIZE must be defined (-D STACK_SIZE=...)"
#endif

/* A stacked child slot: (index, count) as in WideNode (count 0: an interior
 * node), and the distance at which the ray enters its box.  One array of
 * these rather than one per field: one base address for the compiler to
 * keep (measured faster). */
typedef struct {
    int index;
    uint count;
    float entry;
} StackItem;

/* Pops the next stacked item that can still hold a hit within limit (items
 * whose box is entered beyond it are dropped, with SLABS_MEET's allowance
 * for the entry's rounding); false when none is left. */
TRAVERSAL_INLINE bool pop(const StackItem* stack, int* sp, float limit, int* index, uint* count)
{
    limit *= EXIT_SCALE;
    while (*sp > 0) {
        --*sp;
        if (stack[*sp].entry <= limit) {
            *index = stack[*sp].index;
            *count = stack[*sp].count;
            return true;
        }
    }
    return false;
}

/* Asks the CPU to start loading the node or the leaf's triangles behind
 * child `slot` of n, which the ray or packet visits now or after a pop:
 * traversal waits on such loads (sampled: about half the time of incoherent
 * rays), and prefetching both nodes and triangles measured fastest.  Four
 * lines, at the first byte, a third and two thirds of the way and the last
 * byte: a node's four lines (bytes 0, 85, 170 and 255 of a node that starts
 * on a line), and every line of a leaf of up to 5 triangles, 180 bytes, as
 * no two points lie more than a line apart (of bigger leaves, most); the
 * thirds are scaled index addresses, where clamped offsets (64 and 128
 * bytes on, at most the last) cost compares and selects.  Without a loop,
 * whose exit branch mispredicted.  Without PREFETCH (GPUs) it does
 * nothing. */
TRAVERSAL_INLINE void prefetch_child(__global const WideNode* n, int slot,
                                     __global const WideNode* nodes,
                                     __global const Leaf* triangles)
{
#ifdef PREFETCH
    uint count = n->count[slot];
    __global const char* first = count == 0 ? (__global const char*)(nodes + n->child[slot])
                                            : (__global const char*)(triangles + n->child[slot]);
    uint last = (count == 0 ? (uint)sizeof(WideNode) : count * (uint)sizeof(Leaf)) - 1u;
    uint third = last / 3u;
    __builtin_prefetch(first);
    __builtin_prefetch(first + third);
    __builtin_prefetch(first + 2u * third);
    __builtin_prefetch(first + last);
#endif
}

/* Pushes the children in `mask` (three or more) in order of decreasing
 * entry, ties in reverse slot order, so that pops take them nearest first
 * and ties in slot order; prefetches each.  The stack may hold one item
 * more than STACK_SIZE until the caller pops the nearest.
 *
 * Where a lane mask is one instruction (movmskps, see lane_mask), each child
 * goes straight to its place, counted from the first pushed: the number of
 * met children that are farther, or as far in a later slot, from one
 * vector compare pair and a popcount.  The insertion sort (the other branch)
 * mispredicts its data-dependent loop exits, which measured slower; but
 * Intel's CPU runtime, whose lane mask is a chain of six instructions, ran
 * camera rays slower without it, so it keeps the sort. */
TRAVERSAL_INLINE void push_sorted(__global const WideNode* n, uint mask,
                                  const ChildEntries* entries, __global const WideNode* nodes,
                                  __global const Leaf* triangles, StackItem* stack, int* sp)
{
    int first = *sp;
#ifdef HAVE_MOVMSKPS256
    *sp += bit_count(mask);
#endif
    for (uint rest = mask; rest != 0; rest &= rest - 1u) {
        int slot = lowest_slot(rest);
        prefetch_child(n, slot, nodes, triangles);
        float e = entries->slot[slot];
#ifdef HAVE_MOVMSKPS256
        uint deeper = lane_mask(entries->lanes > (float_lanes)(e))
                      | (lane_mask(entries->lanes == (float_lanes)(e)) & (0u - (2u << slot)));
        int at = first + bit_count(deeper & mask);
#else
        int at = *sp;
        for (; at > first && stack[at - 1].entry <= e; --at)
            stack[at] = stack[at - 1];
        ++*sp;
#endif
        stack[at] = (StackItem){n->child[slot], n->count[slot], e};
    }
}

/* What follows a node whose children in `mask` the ray or packet meets, at
 * the distances in `entries`: the nearest child, the others pushed and all
 * of them prefetched, or when none is met the next stacked item in reach of
 * `limit`.  Returns NEXT_ITEM (in *index, *count), NO_ITEM (the stack ran
 * out) or STACK_FULL.
 *
 * One child met is the common case and touches no stack, two need one
 * comparison, more are pushed sorted (push_sorted; Embree's BVH8 single-ray
 * traversal pushes them and sorts them in place).  The children are taken
 * from the mask's set bits: a branch per child slot instead mispredicted on
 * incoherent rays.  The order is the order of increasing entry, ties in
 * slot order. */
#define NEXT_ITEM 0
#define NO_ITEM 1
#define STACK_FULL 2
#define WALK_ENDED 3 /* (walk.h: a query's node hook ended the walk) */
TRAVERSAL_INLINE int next_item(__global const WideNode* n, uint mask,
                               const ChildEntries* entries,
                               __global const WideNode* nodes,
                               __global const Leaf* triangles, StackItem* stack, int* sp,
                               float limit, int* index, uint* count)
{
    if (mask == 0)
        return pop(stack, sp, limit, index, count) ? NEXT_ITEM : NO_ITEM;
    const float* entry = entries->slot;
    int near = lowest_slot(mask);
    mask &= mask - 1u;
    if (mask == 0) {  /* the common case: nothing pushed, no stack check */
        prefetch_child(n, near, nodes, triangles);
    } else if (*sp + bit_count(mask) > STACK_SIZE) {
        return STACK_FULL;
    } else if (one_bit(mask)) {
        /* two: push the farther */
        int far = lowest_slot(mask);
        prefetch_child(n, near, nodes, triangles);
        prefetch_child(n, far, nodes, triangles);
        if (entry[far] < entry[near]) {
            int nearer = far;
            far = near;
            near = nearer;
        }
        stack[*sp] = (StackItem){n->child[far], n->count[far], entry[far]};
        ++*sp;
    } else {
        /* three or more: all pushed, sorted so that the nearest is on top */
        mask |= 1u << near;
        push_sorted(n, mask, entries, nodes, triangles, stack, sp);
        --*sp;
        *index = stack[*sp].index;
        *count = stack[*sp].count;
        return NEXT_ITEM;
    }
    *index = n->child[near];
    *count = n->count[near];
    return NEXT_ITEM;
}

/* next_item for a walk that visits every met child whatever the order (a
 * count, a winding number: the limit never shrinks, so no child is ever
 * dropped by distance): the children in slot order, as the ordered walk
 * takes children whose entries tie (so a sum keeps its order), with no
 * entry compared or sorted.  Their entries are -inf, so that pop never
 * drops them. */
TRAVERSAL_INLINE int next_item_any(__global const WideNode* n, uint mask,
                                   __global const WideNode* nodes,
                                   __global const Leaf* triangles, StackItem* stack, int* sp,
                                   float limit, int* index, uint* count)
{
    if (mask == 0)
        return pop(stack, sp, limit, index, count) ? NEXT_ITEM : NO_ITEM;
    int near = lowest_slot(mask);
    mask &= mask - 1u;
    if (*sp + bit_count(mask) > STACK_SIZE)
        return STACK_FULL;
    prefetch_child(n, near, nodes, triangles);
    while (mask != 0) {
        int slot = highest_slot(mask);  /* the highest first: popped last */
        mask ^= 1u << slot;
        prefetch_child(n, slot, nodes, triangles);
        stack[*sp] = (StackItem){n->child[slot], n->count[slot], -INFINITY};
        ++*sp;
    }
    *index = n->child[near];
    *count = n->count[near];
    return NEXT_ITEM;
}

#endif /* STACK_H */
