/* Stage 7, the build's last: the 8-wide tree that traversal reads, collapsed
 * from the binary tree (the build's scratch, freed when it ends).
 *
 * Each wide node stands for one interior node b of the BVH2.  Its children
 * are found by opening, starting from b's two child slots, the interior slot
 * of largest surface area until WIDE_ARITY slots are held or none is interior
 * (collapsing a binary BVH as in Dammertz et al. 2008, "Shallow Bounding
 * Volume Hierarchies", and Wald, Benthin & Boulos 2008, "Getting Rid of
 * Packets"; Embree's BVH4/BVH8 builders open the largest child the same way).
 * Every interior slot left over is a wide node of the next level.
 *
 * Levels are made top-down, one launch per kernel and level (hlbvh_cl/build/widen.py):
 *   choose_wide_slots   the slots of each node of the level, and how many are interior
 *   (exclusive scan of those counts)
 *   link_wide_children  the next level's BVH2 nodes, and where each node's children start
 * then write_wide_nodes writes every wide node at once from the chosen slots.
 * The nodes come out breadth-first, level after level, which is the order
 * the refit (refit.cl) walks back up.
 *
 * Each level's first node and count stay on the device, in `levels` (first,
 * count pairs, the level at `at`; link_wide_children writes the next): the
 * host launches the levels without reading their sizes (issue 57), over as
 * many work-items as a level can use at most, and each work-group takes its
 * share of the nodes the level has (group_block).
 *
 * A slot is named by the BVH2 child slot it copies: 2 * node + side (side 0
 * left, 1 right), or NO_SLOT.
 */
#include "core/portable.h"
#include "core/aabb.h"
#include "core/tree.h"
#include "build/flat_node.h"

#define NO_SLOT 0xffffffffu

inline int slot_node(uint slot)
{
    return (int)(slot >> 1);
}

inline int slot_child(__global const FlatNode *nodes, uint slot)
{
    __global const FlatNode *n = nodes + slot_node(slot);
    return (slot & 1u) ? n->right : n->left;
}

inline uint slot_count(__global const FlatNode *nodes, uint slot)
{
    __global const FlatNode *n = nodes + slot_node(slot);
    return (slot & 1u) ? n->right_count : n->left_count;
}

inline bool slot_is_empty(__global const FlatNode *nodes, uint slot)
{
    return slot_count(nodes, slot) == 0 && slot_child(nodes, slot) == EMPTY_CHILD;
}

inline bool slot_is_interior(__global const FlatNode *nodes, uint slot)
{
    return slot_count(nodes, slot) == 0 && slot_child(nodes, slot) != EMPTY_CHILD;
}

inline Aabb slot_box(__global const FlatNode *nodes, uint slot)
{
    __global const FlatNode *n = nodes + slot_node(slot);
    __global const float *lo = (slot & 1u) ? n->right_lo : n->left_lo;
    __global const float *hi = (slot & 1u) ? n->right_hi : n->left_hi;
    Aabb box = {{lo[0], lo[1], lo[2]}, {hi[0], hi[1], hi[2]}};
    return box;
}

/* Starts loading the BVH2 node behind an interior slot, which the greedy
 * opening will likely read: the openings of a wide node are a chain of
 * dependent loads, and prefetching every candidate overlaps them. */
inline void prefetch_slot_node(__global const FlatNode *nodes, uint slot)
{
#ifdef PREFETCH
    if (slot_is_interior(nodes, slot))
        __builtin_prefetch(nodes + slot_child(nodes, slot));
#endif
}

/* What a slot bids to be opened: its box's area if it is interior, else -1
 * (never chosen). */
inline float opening_bid(__global const FlatNode *nodes, uint slot)
{
    return slot_is_interior(nodes, slot) ? aabb_area(slot_box(nodes, slot)) : -1.0f;
}

/* Replaces slots[at] (an interior slot) by the non-empty child slots of its
 * node, in place, keeping the left-to-right order and each slot's bid;
 * returns the new count. */
inline int open_slot(__global const FlatNode *nodes, uint *slots, float *bids, int used, int at)
{
    int node = slot_child(nodes, slots[at]);
    uint left = 2u * (uint)node, right = left + 1u;
    bool keep_left = !slot_is_empty(nodes, left), keep_right = !slot_is_empty(nodes, right);
    int added = (int)keep_left + (int)keep_right;
    /* shift the slots after `at` by added - 1 (at most one place right) */
    if (added == 2) {
        for (int k = used - 1; k > at; --k) {
            slots[k + 1] = slots[k];
            bids[k + 1] = bids[k];
        }
    } else if (added == 0) {
        for (int k = at; k + 1 < used; ++k) {
            slots[k] = slots[k + 1];
            bids[k] = bids[k + 1];
        }
    }
    int k = at;
    if (keep_left) {
        prefetch_slot_node(nodes, left);
        slots[k] = left;
        bids[k++] = opening_bid(nodes, left);
    }
    if (keep_right) {
        prefetch_slot_node(nodes, right);
        slots[k] = right;
        bids[k] = opening_bid(nodes, right);
    }
    return used - 1 + added;
}

/* The child slots of the wide node made from BVH2 node `node` (greedy
 * opening, largest area first; ties go to the leftmost slot).  Each slot's
 * bid is computed once, when it enters the list (not at every round). */
inline int choose_slots(__global const FlatNode *nodes, int node, uint *slots)
{
    float bids[WIDE_ARITY];
    int used = 0;
    for (uint side = 0; side < 2; ++side) {
        uint slot = 2u * (uint)node + side;
        if (!slot_is_empty(nodes, slot)) {
            prefetch_slot_node(nodes, slot);
            slots[used] = slot;
            bids[used++] = opening_bid(nodes, slot);
        }
    }
    /* every opening descends one BVH2 level, so this ends */
    while (used < WIDE_ARITY) {
        int best = -1;
        float best_bid = -1.0f;
        for (int k = 0; k < used; ++k) {
            bool better = bids[k] > best_bid;
            best = better ? k : best;
            best_bid = better ? bids[k] : best_bid;
        }
        if (best < 0)
            break;
        used = open_slot(nodes, slots, bids, used, best);
    }
    return used;
}

/* The block [*begin, *end) of the level's nodes (as indices into it) that
 * this work-group takes, its work-items the block's nodes in turn.  Blocks
 * over all the groups, so that a level smaller than the launch still
 * spreads over every core (PoCL hands each core a run of consecutive
 * work-groups, as in sah_top.cl); neighbouring work-items on neighbouring
 * nodes, as with one node each. */
inline void group_block(int count, int *begin, int *end)
{
    long g = get_group_id(0), groups = get_num_groups(0);
    *begin = (int)(g * count / groups);
    *end = (int)((g + 1) * count / groups);
}

/* For the level's wide nodes [first, first + count) (levels[2 * at] and
 * levels[2 * at + 1]): slots[WIDE_ARITY * w + k] and interior_count[i]
 * (i = w - first).  Slot indices are size_t, as WIDE_ARITY * w passes int's
 * range from 2^28 wide nodes. */
__kernel void choose_wide_slots(int at, __global const int *levels, __global const int *source,
                                __global const FlatNode *nodes, __global uint *slots,
                                __global uint *interior_count)
{
    int first = levels[2 * at], begin, end;
    group_block(levels[2 * at + 1], &begin, &end);
    for (int i = begin + (int)get_local_id(0); i < end; i += (int)get_local_size(0)) {
        int w = first + i;
        uint chosen[WIDE_ARITY];
        int used = choose_slots(nodes, source[w], chosen);
        uint interior = 0;
        for (int k = 0; k < WIDE_ARITY; ++k) {
            uint slot = k < used ? chosen[k] : NO_SLOT;
            slots[(size_t)WIDE_ARITY * w + k] = slot;
            if (slot != NO_SLOT && slot_is_interior(nodes, slot))
                ++interior;
        }
        interior_count[i] = interior;
    }
}

/* With interior_offset the exclusive scan of interior_count: the interior
 * children of wide node w become wide nodes next_first + interior_offset[i] + j,
 * in slot order; their BVH2 nodes go to source[], the first index to
 * first_child[w].  Work-item 0 writes the next level's (first, count) at
 * at + 1.  Each wide node stands for a distinct BVH2 node, so more wide
 * nodes than *bvh2_count means the BVH2 is not a tree: then nothing is
 * linked, the next level is empty and levels[overflow_at] is set, which the
 * host reports. */
__kernel void link_wide_children(int at, __global int *levels, int overflow_at,
                                 __global const int *bvh2_count,
                                 __global const uint *interior_offset,
                                 __global const FlatNode *nodes, __global const uint *slots,
                                 __global int *source, __global int *first_child)
{
    int first = levels[2 * at], count = levels[2 * at + 1];
    int next_first = first + count;
    long next_count = (long)interior_offset[count];
    int fits = next_first + next_count <= (long)*bvh2_count;
    if (get_global_id(0) == 0) {
        levels[2 * at + 2] = next_first;
        levels[2 * at + 3] = fits ? (int)next_count : 0;
        if (!fits)
            levels[overflow_at] = 1;
    }
    if (!fits)
        return;
    int begin, end;
    group_block(count, &begin, &end);
    for (int i = begin + (int)get_local_id(0); i < end; i += (int)get_local_size(0)) {
        int w = first + i;
        int next = next_first + (int)interior_offset[i];
        first_child[w] = next;
        for (int k = 0; k < WIDE_ARITY; ++k) {
            uint slot = slots[(size_t)WIDE_ARITY * w + k];
            if (slot != NO_SLOT && slot_is_interior(nodes, slot))
                source[next++] = slot_child(nodes, slot);
        }
    }
}

/* Every wide node from its chosen slots and the BVH2's boxes. */
__kernel void write_wide_nodes(int wide_count, __global const uint *slots,
                               __global const int *first_child, __global const FlatNode *nodes,
                               __global WideNode *wide)
{
    int w = get_global_id(0);
    if (w >= wide_count)
        return;
    WideNode out;
    int next = first_child[w];
    for (int k = 0; k < WIDE_ARITY; ++k) {
        uint slot = slots[(size_t)WIDE_ARITY * w + k];
        Aabb box = aabb_empty();
        int child = EMPTY_CHILD;
        uint count = 0;
        if (slot != NO_SLOT) {
            box = slot_box(nodes, slot);
            count = slot_count(nodes, slot);
            child = count > 0 ? slot_child(nodes, slot) : next++;
        }
        out.lo_x[k] = box.lo[0];
        out.hi_x[k] = box.hi[0];
        out.lo_y[k] = box.lo[1];
        out.hi_y[k] = box.hi[1];
        out.lo_z[k] = box.lo[2];
        out.hi_z[k] = box.hi[2];
        out.child[k] = child;
        out.count[k] = count;
    }
    wide[w] = out;
}
