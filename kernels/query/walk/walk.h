/* The one traversal of the wide tree, for every query and path: a stack
 * walk that visits the nearer children first (Embree's BVH8 single-ray
 * order) and runs interior nodes until it holds a leaf, then the leaf's
 * triangles (Aila & Laine 2009's "while-while"), as madmann91's bvh v2
 * traverse_top_down does.  A query is a visitor, given as macros before
 * including this header:
 *   QUERY                       its name: the walk is walk_QUERY_PATH
 *   QUERY_PATH                  the path: the vocabulary (PATH(...), node.h)
 *                               of what walks and what it keeps, e.g. _ray
 *                               or _packet (query/rays/), _point or _points
 *                               (query/points/)
 *   QUERY_HIT(s, i, hit, t, u, v)  for the default leaf: triangle i is hit
 *                               in the lanes `hit`: record it in s
 *                               (take_hit, which sets the limit) and say
 *                               whether the walk ends
 *   QUERY_NODE(s, r, n, mask)   optional: before the walk orders node n's
 *                               met children (*mask): may visit some first
 *                               (with WALK_NAME(leaves_first)) and say
 *                               whether the walk ends.  Default: false
 *   QUERY_PARAMS, QUERY_ARGS    optional: extra walk parameters the hooks use
 *   QUERY_STATE                 optional: what the query keeps besides the
 *                               path's Found, a type per path
 *                               (PATH(QUERY_STATE)); the walk takes a pointer
 *                               to it, `state`, last
 *   QUERY_CHILDREN(r, n, s, entry)  optional: the node test, giving the child
 *                               mask and entry distances (default: the path's
 *                               PATH(children); point queries measure box
 *                               distances instead)
 *   QUERY_LEAF(s, r, first, count)  optional: the leaf's triangles [first,
 *                               first + count) for queries that are not ray
 *                               hits (point queries); says whether the walk
 *                               ends.  Default: the path's hit_triangle on
 *                               each, then QUERY_HIT
 *   QUERY_INSTANCE              optional: the walk is a top tree's, whose
 *                               leaves hold instances: the function that
 *                               visits one (instance_leaf.h).  The walk is
 *                               walk_QUERY_top_PATH, and takes the
 *                               instances' INSTANCE_PARAMS (two_level.h)
 *                               before QUERY_PARAMS
 *   QUERY_UNORDERED             optional, defined: the query visits every
 *                               met child (its limit never shrinks), or
 *                               ends at its first hit (any hit), so the
 *                               walk neither orders children nor keeps
 *                               their entries (next_item_any)
 * Hooks may use the walk's `nodes` and `triangles`, `state`, and WALK_ARGS,
 * which passes its extra parameters on.  Hooks are macros so that the walk
 * compiles as if written for the query: no flag is tested at run time.
 *
 * With QUERY_PATH the header instantiates that path, then undefines the
 * hooks (walk_end.h).  A header that instantiates several paths of one
 * query (query/rays/trace.h) defines PATH_SUFFIX itself for each and
 * includes walk_end.h when done. */
#include "query/walk/stack.h"

#ifndef PATH_SUFFIX

#ifndef QUERY_PATH
#error "walk.h: define QUERY_PATH (or PATH_SUFFIX, see above)"
#endif
#define PATH_SUFFIX QUERY_PATH
#include "query/walk/walk.h"
#undef PATH_SUFFIX
#include "query/walk/walk_end.h"

#else /* one path */

#ifndef WALK_STATE_PARAM /* the query's first path: its defaults, until walk_end.h */
#ifndef QUERY_NODE
#define QUERY_NODE(s, r, n, mask) false
#endif
#ifndef QUERY_PARAMS
#define QUERY_PARAMS
#define QUERY_ARGS
#endif
#ifdef QUERY_STATE
#define WALK_STATE_PARAM , PATH(QUERY_STATE)* state
#define WALK_STATE_ARG , state
#else
#define WALK_STATE_PARAM
#define WALK_STATE_ARG
#endif
#endif
#ifdef QUERY_INSTANCE
#define WALK_QUERY CONCAT(QUERY, _top)
#define WALK_PARAMS INSTANCE_PARAMS QUERY_PARAMS WALK_STATE_PARAM
#define WALK_ARGS INSTANCE_ARGS QUERY_ARGS WALK_STATE_ARG
#else
#define WALK_QUERY QUERY
#define WALK_PARAMS QUERY_PARAMS WALK_STATE_PARAM
#define WALK_ARGS QUERY_ARGS WALK_STATE_ARG
#endif
#define WALK_NAME(name) CONCAT(CONCAT(name, CONCAT(_, WALK_QUERY)), PATH_SUFFIX)
#ifdef QUERY_CHILDREN
#define WALK_CHILDREN QUERY_CHILDREN
#else
#define WALK_CHILDREN PATH(children)
#endif

#ifdef QUERY_INSTANCE
#include "query/walk/instance_leaf.h"
#endif

#if PATH(QUAD_LEAVES) && !defined(QUERY_LEAF) && !defined(QUERY_INSTANCE)
/* The default leaf of a single ray, four triangles at a time
 * (query/rays/quad.h): the lanes whose edge test passes take the second
 * stage in index order against the limit as it stands then, as the loop
 * below would, so the hits are the same. */
TRAVERSAL_INLINE bool WALK_NAME(quads)(const PATH(Rays)* r, __global const Leaf* triangles,
                                       int first, uint count, PATH(Found)* s WALK_PARAMS)
{
    uint last = (uint)first + count - 1u;
    for (uint i = (uint)first; i <= last; i += 4u) {
        QuadTriangles quad;
        quad_triangles(&quad, triangles, i, last);
        Edges_quad edges;
        uint lanes = quad_mask(triangle_edges_quad(r, &quad, &edges)) & quad_lanes(i, last);
        for (; lanes != 0u; lanes &= lanes - 1u) {
            uint l = (uint)lowest_slot(lanes), k = i + l;
            PATH(Edges) e;
            quad_lane(&edges, l, &e);
            PATH(real) t, u, v;
            LEAF_CORNERS(tri, triangles, k);
            PATH(flags) hit = PATH(triangle_depth)(r, tri, &e, 1, s->limit,
                                                   (s->index >= 0) & (s->index < (int)k),
                                                   &t, &u, &v);
            if (PATH(some)(hit) && QUERY_HIT(s, k, hit, t, u, v))
                return true;
        }
    }
    return false;
}
#endif

/* The leaf's triangles [first, first + count) against every lane: each hit
 * goes to QUERY_HIT; true when it ends the walk.  A lane takes a hit at
 * t == limit only while it has none or its hit's triangle comes later in
 * the tree (hit_triangle's `strict`): of hits at one t, the closest hit is
 * the first triangle, whatever order the walk met them in (a packet's and
 * one ray's walks differ), so every packet size and walk gives the same
 * hit.  Or the query's own QUERY_LEAF, or a top tree's instances. */
TRAVERSAL_INLINE bool WALK_NAME(leaf)(const PATH(Rays)* r, __global const Leaf* triangles,
                                      int first, uint count, PATH(Found)* s WALK_PARAMS)
{
#if defined(QUERY_LEAF)
    return QUERY_LEAF(s, r, first, count);
#elif defined(QUERY_INSTANCE)
    return WALK_NAME(instances)(s, r, first, count WALK_ARGS);
#else
#if PATH(QUAD_LEAVES)
    if (count >= QUAD_LEAF_MIN)
        return WALK_NAME(quads)(r, triangles, first, count, s WALK_ARGS);
#endif
    for (uint i = (uint)first; i < (uint)first + count; ++i) {
        PATH(real) t, u, v;
        LEAF_CORNERS(tri, triangles, i);
        PATH(flags) hit = PATH(hit_triangle)(r, tri, s->limit,
                                             (s->index >= 0) & (s->index < (int)i), &t, &u, &v);
        if (PATH(some)(hit) && QUERY_HIT(s, i, hit, t, u, v))
            return true;
    }
    return false;
#endif
}

/* A node visitor for queries that end at a hit (shadow rays): the leaves
 * among node n's met children (*mask) are tested at once, in slot order,
 * and taken out of *mask; true when that ends the walk.  A large occluder
 * such as a ground quad often sits in a leaf near the root. */
TRAVERSAL_INLINE bool WALK_NAME(leaves_first)(PATH(Found)* s, const PATH(Rays)* r,
                                              __global const WideNode* n, uint* mask,
                                              __global const Leaf* triangles WALK_PARAMS)
{
    uint leaves = *mask & lane_mask(LOAD_ROW(int_lanes, n->count) != (int_lanes)(0));
    *mask ^= leaves;
    for (; leaves != 0; leaves &= leaves - 1u) {
        int slot = lowest_slot(leaves);
        if (WALK_NAME(leaf)(r, triangles, n->child[slot], n->count[slot], s WALK_ARGS))
            return true;
    }
    return false;
}

/* Node *index's visit: its children met, the query's node hook, and the
 * walk's next item (*index, *count): NEXT_ITEM, NO_ITEM, STACK_FULL, or
 * WALK_ENDED where the hook ended the walk. */
TRAVERSAL_INLINE int WALK_NAME(node)(const PATH(Rays)* r, __global const WideNode* nodes,
                                     __global const Leaf* triangles, PATH(Found)* s,
                                     StackItem* stack, int* sp, int* index,
                                     uint* count WALK_PARAMS)
{
    __global const WideNode* n = nodes + *index;
    ChildEntries entry;
    uint mask = WALK_CHILDREN(r, n, s, &entry);
    if (QUERY_NODE(s, r, n, &mask))
        return WALK_ENDED;
#ifdef QUERY_UNORDERED
    return next_item_any(n, mask, nodes, triangles, stack, sp, PATH(reach)(s), index, count);
#else
    return next_item(n, mask, &entry, nodes, triangles, stack, sp, PATH(reach)(s), index,
                     count);
#endif
}

/* Walks the tree from the root (always an interior node) for the query, with
 * s holding its start (no hit, limit tmax) and ending with its result.
 * Returns true when the stack was too small (the host then raises). */
TRAVERSAL_INLINE bool WALK_NAME(walk)(const PATH(Rays)* r, __global const WideNode* nodes,
                                      __global const Leaf* triangles,
                                      PATH(Found)* s WALK_PARAMS)
{
    StackItem stack[STACK_SIZE + 1];  /* + 1: see next_item */
    int sp = 0;
    int index = 0;
    uint count = 0;
    bool done = false;

    while (!done) {
        while (!done && count == 0) {
            int next = WALK_NAME(node)(r, nodes, triangles, s, stack, &sp, &index, &count
                                       WALK_ARGS);
            if (next == WALK_ENDED)
                return false;
            if (next == STACK_FULL)
                return true;
            done = next == NO_ITEM;
        }
        if (done)
            break;
        if (WALK_NAME(leaf)(r, triangles, index, count, s WALK_ARGS))
            return false;
        done = !pop(stack, &sp, PATH(reach)(s), &index, &count);
    }
    return false;
}

#if defined(INTERLEAVED_WALKS) && !defined(QUERY_INSTANCE)
/* The most walks that `walks` takes at once: a work-item's queries
 * (PACKET_SIZE), or more where its includer says (query/rays.cl). */
#ifndef WALK_LANES
#define WALK_LANES PACKET_SIZE
#endif
/* The most walks that `walks` takes at once on each path: WALK_LANES
 * rays or points, and a work-item's LANE_GROUPS packets
 * (query/rays/trace.h). */
#ifndef WALKS_MAX_ray
#define WALKS_MAX_ray WALK_LANES
#define WALKS_MAX_packet LANE_GROUPS
#define WALKS_MAX_point WALK_LANES
#define WALKS_MAX_points WALK_LANES
#endif

/* One step of walk r: a node, or a leaf and then the next stacked item;
 * NEXT_ITEM while the walk goes on, else how it ended (NO_ITEM,
 * STACK_FULL, WALK_ENDED: stack.h). */
TRAVERSAL_INLINE int WALK_NAME(step)(const PATH(Rays)* r, __global const WideNode* nodes,
                                     __global const Leaf* triangles, PATH(Found)* s,
                                     StackItem* stack, int* sp, int* index,
                                     uint* count WALK_PARAMS)
{
    if (*count == 0)
        return WALK_NAME(node)(r, nodes, triangles, s, stack, sp, index, count WALK_ARGS);
    if (WALK_NAME(leaf)(r, triangles, *index, *count, s WALK_ARGS))
        return WALK_ENDED;
    return pop(stack, sp, PATH(reach)(s), index, count) ? NEXT_ITEM : NO_ITEM;
}

/* The walks of rays r[0, n) (n <= PATH(WALKS_MAX)), each as WALK_NAME(walk)
 * walks it, taken a step each in turn: one ray's walk is a chain of
 * dependent loads (a node, then the child it chose), which stalls a CPU
 * core on every cache miss; the steps of other rays, independent, fill
 * those stalls (the core runs them out of order).  Each walk visits the
 * same nodes and leaves in the same order as alone, so the results are
 * the same bits.  With QUERY_STATE, `state` is an array: walk k's is
 * state[k].  True when a stack ran out.  Every walk in turn, rather than a
 * few slots (4 or 8 walks in flight, each in registers through a loop
 * unrolled over its slots and refilled with the next ray when its walk
 * ends): 4 slots traced no faster than this, 8 slower (figures in the
 * commit that says so). */
TRAVERSAL_INLINE bool WALK_NAME(walks)(const PATH(Rays)* r, __global const WideNode* nodes,
                                       __global const Leaf* triangles, PATH(Found)* s,
                                       uint n WALK_PARAMS)
{
    StackItem stack[PATH(WALKS_MAX)][STACK_SIZE + 1];
    int sp[PATH(WALKS_MAX)], index[PATH(WALKS_MAX)];
    uint count[PATH(WALKS_MAX)];
    for (uint k = 0; k < PATH(WALKS_MAX); ++k) {
        sp[k] = 0;
        index[k] = 0;
        count[k] = 0;
    }
#ifdef QUERY_STATE
    PATH(QUERY_STATE)* states = state;
#endif
    uint live = (2u << (n - 1u)) - 1u;  /* n >= 1 */
    bool full = false;
    while (live != 0)
        for (uint rest = live; rest != 0; rest &= rest - 1u) {
            uint k = (uint)lowest_slot(rest);
#ifdef QUERY_STATE
            PATH(QUERY_STATE)* state = states + k;  /* the hooks' (WALK_ARGS) */
#endif
            int next = WALK_NAME(step)(r + k, nodes, triangles, s + k, stack[k], sp + k,
                                       index + k, count + k WALK_ARGS);
            /* A branch taken once a walk, not selects on every step: the
             * live mask and the stack flag stay out of the step's work. */
            if (next != NEXT_ITEM) {
                live ^= 1u << k;
                full |= next == STACK_FULL;
            }
        }
    return full;
}
#endif

#undef WALK_QUERY
#undef WALK_PARAMS
#undef WALK_ARGS
#undef WALK_NAME
#undef WALK_CHILDREN

#endif /* PATH_SUFFIX */
