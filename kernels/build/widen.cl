/* Stage 7, the build's last: the 8-wide tree that traversal reads, collapsed
 * from the binary tree (the build's scratch, freed when it ends).
 *
 * Each wide node stands for one interior node b of the BVH2 (Dammertz et al.
 * 2008, "Shallow Bounding Volume Hierarchies"; Wald, Benthin & Boulos 2008,
 * "Getting Rid of Packets").  Its children are a cut through b's subtree of
 * at most WIDE_ARITY slots, each a BVH2 leaf, a subtree merged into one leaf,
 * or an interior node, which becomes a wide node of the next level; the cut
 * is the one of least SAH cost, found bottom-up first (wide_costs, below).
 *
 * Before the levels, over the whole BVH2:
 *   link_wide_parents   each node's parent
 *   wide_costs          the optimal cuts' costs and choices, bottom-up
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
 * left, 1 right), with MERGED_SLOT set where its subtree is one leaf, or
 * NO_SLOT.
 */
#include "core/portable.h"
#include "core/aabb.h"
#include "core/tree.h"
#include "build/config.h"
#include "build/flat_node.h"
#include "build/handoff.h"

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

/* Which slots a wide node takes is decided by the SAH, not greedily: the
 * collapse that minimises the wide tree's SAH cost over every way to cut
 * the BVH2 into wide nodes and leaves (Ylitie, Karras & Laine 2017,
 * "Efficient Incoherent Ray Traversal on GPUs Through Compressed Wide BVHs",
 * sec. 4.1).  Opening the largest slot first (Wald et al. 2008) fills the
 * nodes high in the tree and leaves small subtrees, often two leaves, as
 * whole nodes of their own; the optimal cut opens those into their parent's
 * slots instead, and merges small subtrees whose triangles are contiguous
 * into one leaf (at most MAX_LEAF_SIZE triangles).
 *
 * C(n, i), for i = 1..WIDE_ARITY, is the least cost of subtree n as at
 * most i slots of its parent, with one slot (i = 1) a leaf or a wide node:
 *   C(n, 1) = min(WIDE_TRIANGLE_COST * A(n) * triangles(n),
 *                 WIDE_NODE_COST * A(n) + D(n, WIDE_ARITY)),
 *   C(n, i) = min(C(n, i - 1), D(n, i)),
 *   D(n, i) = min over k of C(left, k) + C(right, i - k),
 * a BVH2 leaf slot costing its triangles whatever i, an empty slot 0 with
 * no slot.  wide_costs finds it bottom-up (one walker per BVH2 node whose
 * children are leaves, the second arrival at a node going on, as in
 * radix_tree.cl), choose_slots reads its choices top-down. */

/* A slot whose BVH2 subtree is merged into one leaf of the wide tree. */
#define MERGED_SLOT 0x80000000u
/* choice[WIDE_ARITY * n + i - 1] for i >= 2: the slots k given to the left
 * child for D(n, i), or KEEP_FEWER where C(n, i) = C(n, i - 1).  For i = 1:
 * the split of D(n, WIDE_ARITY) in the low bits, LEAF_CHOICE set where the
 * subtree is best one leaf. */
#define KEEP_FEWER 0xffu
#define LEAF_CHOICE 0x80u
#define SPLIT_BITS 0x0fu

inline int interior_children(__global const FlatNode *nodes, int node)
{
    return (int)slot_is_interior(nodes, 2u * (uint)node) +
           (int)slot_is_interior(nodes, 2u * (uint)node + 1u);
}

/* parent[m] of every BVH2 node m (-1 for the root, node 0), for the walk up. */
NARROW_KERNEL
void link_wide_parents(__global const int *bvh2_count, __global const FlatNode *nodes,
                       __global int *parent)
{
    int node = get_global_id(0);
    if (node >= *bvh2_count)
        return;
    if (node == 0)
        parent[0] = -1;
    for (uint side = 0; side < 2; ++side) {
        uint slot = 2u * (uint)node + side;
        if (slot_is_interior(nodes, slot))
            parent[slot_child(nodes, slot)] = node;
    }
}

#if WIDE_ARITY != 8
#error "wide_costs holds a node's costs in one 8-lane vector"
#endif

/* The costs C(m, k), k = 1..8, as a vector (lane k - 1): WIDE_ARITY is 8,
 * and vectors of fixed lanes, not arrays indexed in loops, are what the CPU
 * compilers that vectorise across work-items keep in registers. */
inline float8 load_costs(__global float *costs, size_t m)
{
#if ACQUIRE_RELEASE
    return vload8(m, costs);
#else
    __global float *c = costs + 8 * m;
    return (float8)(handoff_load_float(c), handoff_load_float(c + 1), handoff_load_float(c + 2),
                    handoff_load_float(c + 3), handoff_load_float(c + 4),
                    handoff_load_float(c + 5), handoff_load_float(c + 6),
                    handoff_load_float(c + 7));
#endif
}

inline void store_costs(__global float *costs, size_t m, float8 v)
{
#if ACQUIRE_RELEASE
    vstore8(v, m, costs);
#else
    __global float *c = costs + 8 * m;
    handoff_store_float(c, v.s0);
    handoff_store_float(c + 1, v.s1);
    handoff_store_float(c + 2, v.s2);
    handoff_store_float(c + 3, v.s3);
    handoff_store_float(c + 4, v.s4);
    handoff_store_float(c + 5, v.s5);
    handoff_store_float(c + 6, v.s6);
    handoff_store_float(c + 7, v.s7);
#endif
}

/* A non-empty child slot's costs with k = 1..8 slots (an empty slot costs
 * 0 with any), and its triangles as a run: (first, count), count 0 for an
 * empty slot, -1 where they are not one run of at most MAX_LEAF_SIZE. */
inline float8 slot_costs(__global const FlatNode *nodes, uint slot, __global float *costs,
                         __global int *spans, int *first, int *count)
{
    if (slot_is_empty(nodes, slot)) {
        *first = 0;
        *count = 0;
        return (float8)(0.0f);
    }
    if (slot_is_interior(nodes, slot)) {
        size_t m = (size_t)slot_child(nodes, slot);
        *first = handoff_load(spans + 2 * m);
        *count = handoff_load(spans + 2 * m + 1);
        return load_costs(costs, m);
    }
    uint triangles = slot_count(nodes, slot);
    *first = slot_child(nodes, slot);
    *count = triangles <= MAX_LEAF_SIZE ? (int)triangles : -1;
    return (float8)(WIDE_TRIANGLE_COST * aabb_area(slot_box(nodes, slot)) * (float)triangles);
}

/* The run of two children's runs, if they join into one of at most
 * MAX_LEAF_SIZE triangles; count -1 otherwise. */
inline void join_spans(int first_a, int count_a, int first_b, int count_b, int *first,
                       int *count)
{
    *first = count_a == 0 ? first_b : (count_b == 0 ? first_a : min(first_a, first_b));
    int total = count_a + count_b;
    bool adjacent = count_a == 0 || count_b == 0 || first_a + count_a == first_b ||
                    first_b + count_b == first_a;
    *count = count_a < 0 || count_b < 0 || !adjacent || total > MAX_LEAF_SIZE ? -1 : total;
}

/* D(n, i) of the splits that give the left child k slots, lane i - 1: the
 * left's C(., k) plus the right's C(., i - k), the right's costs moved up
 * k lanes (shuffle2 index 8 takes the infinity: no such split).  Where it
 * is less than the best so far, it and k replace them: the least k wins
 * ties. */
#define TRY_SPLIT(k, left_cost, mask)                                                   \
    {                                                                                   \
        float8 v = (float8)(left_cost) + shuffle2(cr, none, (uint8)mask);               \
        int8 better = isless(v, d);                                                     \
        d = select(d, v, better);                                                       \
        split = select(split, (int8)(k), better);                                       \
    }

/* C(node, i) for every i, its choices and its triangles' run, from its
 * children's (handed on by their walkers). */
inline void node_costs(__global const FlatNode *nodes, int node, __global float *costs,
                       __global int *spans, __global uchar *choice)
{
    uint left = 2u * (uint)node, right = left + 1u;
    int first_l, count_l, first_r, count_r, first, count;
    float8 cl = slot_costs(nodes, left, costs, spans, &first_l, &count_l);
    float8 cr = slot_costs(nodes, right, costs, spans, &first_r, &count_r);
    join_spans(first_l, count_l, first_r, count_r, &first, &count);
    bool left_empty = slot_is_empty(nodes, left), right_empty = slot_is_empty(nodes, right);
    float area = aabb_area(aabb_union(slot_box(nodes, left), slot_box(nodes, right)));

    /* D(node, i) and its split, lane i - 1; an empty child takes no slot */
    float8 d, none = (float8)(INFINITY);
    int8 split;
    if (left_empty || right_empty) {
        d = left_empty ? cr : cl;
        split = left_empty ? (int8)(0) : (int8)(1, 2, 3, 4, 5, 6, 7, 8);
    } else {
        d = (float8)(cl.s0) + shuffle2(cr, none, (uint8)(8, 0, 1, 2, 3, 4, 5, 6));
        split = (int8)(1);
        TRY_SPLIT(2, cl.s1, (8, 8, 0, 1, 2, 3, 4, 5))
        TRY_SPLIT(3, cl.s2, (8, 8, 8, 0, 1, 2, 3, 4))
        TRY_SPLIT(4, cl.s3, (8, 8, 8, 8, 0, 1, 2, 3))
        TRY_SPLIT(5, cl.s4, (8, 8, 8, 8, 8, 0, 1, 2))
        TRY_SPLIT(6, cl.s5, (8, 8, 8, 8, 8, 8, 0, 1))
        TRY_SPLIT(7, cl.s6, (8, 8, 8, 8, 8, 8, 8, 0))
    }
    float as_node = WIDE_NODE_COST * area + d.s7;
    float as_leaf = count > 0 ? WIDE_TRIANGLE_COST * area * (float)count : INFINITY;
    bool leaf = as_leaf <= as_node;

    /* C(node, i) = min(C(node, i - 1), D(node, i)), lane by lane */
    float dd[8], c[8];
    int ss[8];
    vstore8(d, 0, dd);
    vstore8(split, 0, ss);
    __global uchar *chosen = choice + (size_t)WIDE_ARITY * node;
    c[0] = leaf ? as_leaf : as_node;
    chosen[0] = (uchar)((leaf ? LEAF_CHOICE : 0u) | (uint)ss[7]);
    for (int i = 1; i < 8; ++i) {
        bool fewer = !(dd[i] < c[i - 1]);
        c[i] = fewer ? c[i - 1] : dd[i];
        chosen[i] = fewer ? (uchar)KEEP_FEWER : (uchar)ss[i];
    }
    store_costs(costs, (size_t)node, vload8(0, c));
    handoff_store(spans + 2 * (size_t)node, first);
    handoff_store(spans + 2 * (size_t)node + 1, count);
}

/* The DP bottom-up: a walker from each BVH2 node with no interior child;
 * at a node with two, the first arrival stops and the second goes on. */
NARROW_KERNEL
void wide_costs(__global const int *bvh2_count, __global const FlatNode *nodes,
                __global const int *parent, __global int *visits,
                __global float *costs, __global int *spans, __global uchar *choice)
{
    int node = get_global_id(0);
    if (node >= *bvh2_count || interior_children(nodes, node) > 0)
        return;
    for (;;) {
        node_costs(nodes, node, costs, spans, choice);
        int up = parent[node];
        if (up < 0)
            return;
        if (interior_children(nodes, up) == 2 && handoff_arrive(visits + up) == 0)
            return; /* the sibling subtree is not done; its walker goes on */
        node = up;
    }
}

/* The child slots of the wide node made from BVH2 node `node`: the cut
 * D(node, WIDE_ARITY) chose, left to right.  A choice table that is not
 * the DP's (a BVH2 that is not a tree leaves it zero) still gives at most
 * WIDE_ARITY slots. */
inline int choose_slots(__global const FlatNode *nodes, __global const uchar *choice, int node,
                        uint *slots)
{
    uint stack_slot[2 * WIDE_ARITY];
    int stack_budget[2 * WIDE_ARITY];
    int k = min((int)(choice[(size_t)WIDE_ARITY * node] & SPLIT_BITS), WIDE_ARITY);
    stack_slot[0] = 2u * (uint)node + 1u;
    stack_budget[0] = WIDE_ARITY - k;
    stack_slot[1] = 2u * (uint)node;
    stack_budget[1] = k;
    int depth = 2, used = 0;
    while (depth > 0 && used < WIDE_ARITY) {
        --depth;
        uint slot = stack_slot[depth];
        int budget = stack_budget[depth];
        if (slot_is_empty(nodes, slot))
            continue;
        if (!slot_is_interior(nodes, slot)) {
            slots[used++] = slot;
            continue;
        }
        __global const uchar *chosen = choice + (size_t)WIDE_ARITY * slot_child(nodes, slot);
        while (budget > 1 && chosen[budget - 1] == KEEP_FEWER)
            --budget;
        if (budget <= 1 || depth + 2 > 2 * WIDE_ARITY) {
            slots[used++] = (chosen[0] & LEAF_CHOICE) ? slot | MERGED_SLOT : slot;
            continue;
        }
        k = min((int)chosen[budget - 1], budget);
        uint left = 2u * (uint)slot_child(nodes, slot);
        stack_slot[depth] = left + 1u;
        stack_budget[depth++] = budget - k;
        stack_slot[depth] = left;
        stack_budget[depth++] = k;
    }
    return used;
}

/* A chosen slot (not NO_SLOT) that becomes a wide node of the next level. */
inline bool chosen_is_interior(__global const FlatNode *nodes, uint slot)
{
    return !(slot & MERGED_SLOT) && slot_is_interior(nodes, slot);
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
NARROW_KERNEL
void choose_wide_slots(int at, __global const int *levels, __global const int *source,
                       __global const FlatNode *nodes, __global const uchar *choice,
                       __global uint *slots,
                       __global uint *interior_count)
{
    int first = levels[2 * at], begin, end;
    group_block(levels[2 * at + 1], &begin, &end);
    for (int i = begin + (int)get_local_id(0); i < end; i += (int)get_local_size(0)) {
        int w = first + i;
        uint chosen[WIDE_ARITY];
        int used = choose_slots(nodes, choice, source[w], chosen);
        uint interior = 0;
        for (int k = 0; k < WIDE_ARITY; ++k) {
            uint slot = k < used ? chosen[k] : NO_SLOT;
            slots[(size_t)WIDE_ARITY * w + k] = slot;
            if (slot != NO_SLOT && chosen_is_interior(nodes, slot))
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
NARROW_KERNEL
void link_wide_children(int at, __global int *levels, int overflow_at,
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
            if (slot != NO_SLOT && chosen_is_interior(nodes, slot))
                source[next++] = slot_child(nodes, slot);
        }
    }
}

/* Every wide node from its chosen slots, the BVH2's boxes and, for a
 * merged slot, its subtree's run of triangles. */
NARROW_KERNEL
void write_wide_nodes(int wide_count, __global const uint *slots,
                      __global const int *first_child, __global const FlatNode *nodes,
                      __global const int *spans, __global WideNode *wide)
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
        if (slot != NO_SLOT && (slot & MERGED_SLOT)) {
            slot &= ~MERGED_SLOT;
            box = slot_box(nodes, slot);
            size_t m = (size_t)slot_child(nodes, slot);
            child = spans[2 * m];
            count = (uint)spans[2 * m + 1];
        } else if (slot != NO_SLOT) {
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
