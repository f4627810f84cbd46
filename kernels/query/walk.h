/* The one traversal of the wide tree, for every query and both paths (a
 * single ray, RayData; a packet, Packet): a stack walk that visits the
 * nearer children first (Embree's BVH8 single-ray order) and runs interior
 * nodes until it holds a leaf, then the leaf's triangles (Aila & Laine
 * 2009's "while-while"), as madmann91's bvh v2 traverse_top_down does.  A
 * query is a visitor, given as macros before including this header:
 *   QUERY                       its name: the walks are walk_QUERY_ray and
 *                               walk_QUERY_packet, run by trace_QUERY
 *   QUERY_HIT(s, i, hit, t, u, v)  triangle i is hit in the lanes `hit`: record
 *                               it in s (take_hit, which sets the limit) and
 *                               say whether the walk ends
 *   QUERY_NODE(s, r, n, mask)   before the walk orders node n's met children
 *                               (*mask): may visit some first (with
 *                               WALK_NAME(leaves_first)) and say whether the
 *                               walk ends; or false
 *   QUERY_PARAMS, QUERY_ARGS    extra walk parameters the hooks use (or empty)
 *   QUERY_CHILDREN(r, n, s, entry)  optional: the node test, giving the child
 *                               mask and entry distances (default: the path's
 *                               slab test; point queries measure box
 *                               distances instead, point.h)
 *   QUERY_LEAF(s, r, first, count)  optional: the leaf's triangles [first,
 *                               first + count) for queries that are not ray
 *                               hits (point queries); says whether the walk
 *                               ends.  Default: the path's hit_triangle on
 *                               each, then QUERY_HIT
 *   QUERY_UNORDERED             optional, defined: the query visits every
 *                               met child (its limit never shrinks), so
 *                               the walk neither orders children nor keeps
 *                               their entries (next_item_any)
 *   QUERY_PATH                  optional: the one path to instantiate (e.g.
 *                               _point, point.h); without it, _ray and
 *                               _packet and the ray wrapper trace_QUERY
 * Hooks may use the walk's `nodes` and `triangles`.  The header instantiates
 * itself for each path (PATH_SUFFIX), then undefines the hooks.  Hooks are
 * macros so that the walk compiles as if written for the query: no flag is
 * tested at run time. */
#ifndef PATH_SUFFIX

#include "query/stack.h"

#ifdef QUERY_PATH
#define PATH_SUFFIX QUERY_PATH
#include "query/walk.h"
#undef PATH_SUFFIX
#else /* the ray paths */

#define PATH_SUFFIX _ray
#include "query/walk.h"
#undef PATH_SUFFIX
#if PACKET_SIZE > 1
#define PATH_SUFFIX _packet
#include "query/walk.h"
#undef PATH_SUFFIX
#endif

/* The query for the rays lanes[0, used) of a work-item: as one packet when
 * prepare_packet accepts them (overflow[1] counts those under
 * COUNT_PACKETS), else one by one.  Per lane: the hit's tree-order index
 * (-1: none), and t, u, v unless t is 0 (a constant 0 compiles their stores
 * away: PoCL calls vstore out of line, which would keep them).  overflow[0]
 * is set to 1 if a walk ran out of stack. */
#define QUERY_WALK(path) CONCAT(CONCAT(walk_, QUERY), path)
/* Instanced scenes also give each lane's instance (instance.h). */
#ifdef INSTANCES
#define WALK_INSTANCE , int* instance
#else
#define WALK_INSTANCE
#endif
TRAVERSAL_INLINE void CONCAT(trace_, QUERY)(const RayLanes* lanes, uint used,
                                            __global const WideNode* nodes,
                                            __global const Triangle* triangles,
                                            __global int* overflow, int* index, float* t,
                                            float* u, float* v WALK_INSTANCE QUERY_PARAMS)
{
    bool out_of_stack = false;
#if PACKET_SIZE > 1
    Packet p;
    if (prepare_packet(lanes, &p)) {
#ifdef COUNT_PACKETS
        atomic_inc(overflow + 1);
#endif
        Found_packet s = {(int_packet)(-1), (float_packet)(INFINITY), (float_packet)(0.0f),
                          (float_packet)(0.0f), p.tmax, packet_max(p.tmax)};
#ifdef INSTANCES
        s.instance = (int_packet)(-1);
#endif
        out_of_stack = QUERY_WALK(_packet)(&p, nodes, triangles, &s QUERY_ARGS);
        vstore_packet(s.index, 0, index);
#ifdef INSTANCES
        vstore_packet(s.instance, 0, instance);
#endif
        if (t) {
            vstore_packet(s.t, 0, t);
            vstore_packet(s.u, 0, u);
            vstore_packet(s.v, 0, v);
        }
    } else
#endif
    {
        for (uint l = 0; l < used; ++l) {
            RayData r;
            prepare_lane(&r, lanes, l);
            Found_ray s = {-1, INFINITY, 0.0f, 0.0f, r.tmax};
#ifdef INSTANCES
            s.instance = -1;
#endif
            out_of_stack |= QUERY_WALK(_ray)(&r, nodes, triangles, &s QUERY_ARGS);
            index[l] = s.index;
#ifdef INSTANCES
            instance[l] = s.instance;
#endif
            if (t) {
                t[l] = s.t;
                u[l] = s.u;
                v[l] = s.v;
            }
        }
    }
    if (out_of_stack)
        overflow[0] = 1;
}
#undef QUERY_WALK
#undef WALK_INSTANCE
#endif /* QUERY_PATH */

#undef QUERY
#undef QUERY_HIT
#undef QUERY_NODE
#undef QUERY_PARAMS
#undef QUERY_ARGS
#undef QUERY_CHILDREN
#undef QUERY_LEAF
#undef QUERY_PATH
#undef QUERY_UNORDERED

#else /* one path */

#define WALK_NAME(name) CONCAT(CONCAT(name, CONCAT(_, QUERY)), PATH_SUFFIX)
#ifdef QUERY_CHILDREN
#define WALK_CHILDREN QUERY_CHILDREN
#else
#define WALK_CHILDREN PATH(children)
#endif

/* The leaf's triangles [first, first + count) against every lane: each hit
 * goes to QUERY_HIT; true when it ends the walk.  A lane takes a hit at
 * t == limit only while it has none (hit_triangle's `strict`).  Or the
 * query's own QUERY_LEAF. */
TRAVERSAL_INLINE bool WALK_NAME(leaf)(const PATH(Rays)* r, __global const Triangle* triangles,
                                      int first, uint count, PATH(Found)* s QUERY_PARAMS)
{
#ifdef QUERY_LEAF
    return QUERY_LEAF(s, r, first, count);
#else
    for (uint i = (uint)first; i < (uint)first + count; ++i) {
        PATH(real) t, u, v;
        PATH(flags) hit = PATH(hit_triangle)(r, triangles + i, s->limit, s->index >= 0, &t, &u,
                                             &v);
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
                                              __global const Triangle* triangles QUERY_PARAMS)
{
    uint leaves = *mask & lane_mask(LOAD_ROW(int_lanes, n->count) != (int_lanes)(0));
    *mask ^= leaves;
    for (; leaves != 0; leaves &= leaves - 1u) {
        int slot = lowest_slot(leaves);
        if (WALK_NAME(leaf)(r, triangles, n->child[slot], n->count[slot], s QUERY_ARGS))
            return true;
    }
    return false;
}

/* Walks the tree from the root (always an interior node) for the query, with
 * s holding its start (no hit, limit tmax) and ending with its result.
 * Returns true when the stack was too small (the host then raises). */
TRAVERSAL_INLINE bool WALK_NAME(walk)(const PATH(Rays)* r, __global const WideNode* nodes,
                                      __global const Triangle* triangles,
                                      PATH(Found)* s QUERY_PARAMS)
{
    StackItem stack[STACK_SIZE + 1];  /* + 1: see next_item */
    int sp = 0;
    int index = 0;
    uint count = 0;
    bool done = false;

    while (!done) {
        while (!done && count == 0) {
            __global const WideNode* n = nodes + index;
            ChildEntries entry;
            uint mask = WALK_CHILDREN(r, n, s, &entry);
            if (QUERY_NODE(s, r, n, &mask))
                return false;
#ifdef QUERY_UNORDERED
            int next = next_item_any(n, mask, nodes, triangles, stack, &sp, PATH(reach)(s),
                                     &index, &count);
#else
            int next = next_item(n, mask, &entry, nodes, triangles, stack, &sp,
                                 PATH(reach)(s), &index, &count);
#endif
            if (next == STACK_FULL)
                return true;
            done = next == NO_ITEM;
        }
        if (done)
            break;
        if (WALK_NAME(leaf)(r, triangles, index, count, s QUERY_ARGS))
            return false;
        done = !pop(stack, &sp, PATH(reach)(s), &index, &count);
    }
    return false;
}

#undef WALK_NAME
#undef WALK_CHILDREN

#endif /* PATH_SUFFIX */
