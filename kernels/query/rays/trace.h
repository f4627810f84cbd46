/* A ray query from its visitor: its walks (query/walk/walk.h) for one ray
 * (_ray) and, where PACKET_SIZE > 1, for a packet (_packet); on a two-level
 * scene (INSTANCES) also the top tree's walks, whose leaves walk each
 * instance's mesh with the query's own walks and state (below); and
 * trace_QUERY, which traces the rays of a work-item, each of its
 * LANE_GROUPS groups as one packet when prepare_packet accepts it and its
 * rays lie close (packet_compact), else one by one, each walk from its start
 * (start_ray, start_packet) over the scene's tree (on a two-level scene the
 * top tree).
 * Include it as walk.h, without QUERY_PATH, with walk.h's hooks and these:
 *   QUERY_OUT                the type of what the work-item's walks read and
 *                            leave, one lane each: trace_QUERY's `out`
 *   QUERY_END(s, out, l)     optional: stores a walk's results (s, and
 *                            `state`) in lane l of out (a packet's in every
 *                            lane)
 *   QUERY_BEGIN(out, l)      with QUERY_STATE: sets `state` for lane l (a
 *                            packet's for every lane) before its walk
 *   QUERY_LANE(out, l)       optional: whether lane l's ray, traced one by one,
 *                            takes a walk at all (default: every lane's)
 *   QUERY_ENDS(s)            optional: whether the top walk ends once an
 *                            instance's mesh is walked (default: false)
 *   QUERY_MESH_ARGS(in, id)  optional: the QUERY_ARGS of the walk of instance
 *                            in's mesh (id: its number; default: QUERY_ARGS)
 *   QUERY_ROOT_PHASE         optional, defined: the rays of a work-item that
 *                            go one by one on a flat scene on a CPU
 *                            (ROOT_PHASE, query/rays/ray.h) first have the
 *                            root's leaves that any of them meets tested for
 *                            all of them at once, one vector lane per ray
 *                            (the root phase, query/rays/mixed.h), with
 *                            QUERY_HIT; their walks then start from there
 *                            (those that still meet an interior child of
 *                            the root), and the query's QUERY_NODE drops
 *                            those leaves at the root (root_done).  For
 *                            queries whose result does not depend on the
 *                            order of their hits (the closest hit, ties
 *                            going to the first triangle: walk.h's leaf;
 *                            any hit, whose lanes that hit are done: their
 *                            limit, -inf, meets no child)
 * trace_QUERY(lanes, used, the scene's trees (instance.h's SCENE_TREES),
 * overflow, out, QUERY_ARGS), with lanes, used and out arrays of LANE_GROUPS,
 * sets overflow[0] if a walk ran out of stack, and counts the packets in
 * overflow[1] under COUNT_PACKETS (tests). */
#ifndef PATH_SUFFIX

#include "query/rays/instance.h"

/* The groups of PACKET_SIZE rays a work-item traces (trace_QUERY): one, or
 * more where the includer says (query/rays.cl). */
#ifndef LANE_GROUPS
#define LANE_GROUPS 1
#endif

/* QUERY_FN(name, path): the query's function `name` on a path. */
#define QUERY_FN(name, path) CONCAT(CONCAT(name, CONCAT(_, QUERY)), path)
#define TRACE_NAME(name) QUERY_FN(name, PATH_SUFFIX)
#ifndef QUERY_ENDS
#define QUERY_ENDS(s) false
#endif
#ifndef QUERY_MESH_ARGS
#define QUERY_MESH_ARGS(in, id) QUERY_ARGS
#endif
#ifndef QUERY_END
#define QUERY_END(s, out, l)
#endif

#ifdef INSTANCES
/* A trace walks the top tree, with the instances' parameters. */
#define TRACED(path) QUERY_FN(walk, CONCAT(_top, path))
#define TRACE_SCENE_PARAMS MESHES_PARAMS
#define TRACE_PARAMS INSTANCE_PARAMS QUERY_PARAMS
#define TRACE_ARGS INSTANCE_ARGS QUERY_ARGS
/* The walk of rays mapped into an instance's frame: a ray's is the query's
 * own (map_instance_ray prepared it), a packet's mapped_QUERY_packet, which
 * splits the packet where it must. */
#define MESH_WALK_ray walk
#define MESH_WALK_packet mapped
#if PACKET_SIZE > 1 && defined(QUERY_STATE)
#error "trace.h: instanced packets keep no query state (all_hits.cl walks one ray per work-item)"
#endif
#else /* a flat scene's trace walks its one tree */
#define TRACED(path) QUERY_FN(walk, path)
#define TRACE_SCENE_PARAMS
#define TRACE_PARAMS QUERY_PARAMS
#define TRACE_ARGS QUERY_ARGS
#endif

/* Each path's walks and trace, and the root phase's lanes (_mixed);
 * IS_PACKET tells which. */
#define IS_PACKET_ray 0
#define IS_PACKET_packet 1
#define IS_PACKET_mixed 2
#define PATH_SUFFIX _ray
#include "query/rays/trace.h"
#undef PATH_SUFFIX
#if PACKET_SIZE > 1
#define PATH_SUFFIX _packet
#include "query/rays/trace.h"
#undef PATH_SUFFIX
#endif
#if defined(ROOT_PHASE) && defined(QUERY_ROOT_PHASE)
#define TRACE_ROOT_PHASE
#define PATH_SUFFIX _mixed
#include "query/rays/trace.h"
#undef PATH_SUFFIX
#endif

/* The query for the rays of a work-item's LANE_GROUPS groups, group g's
 * lanes[g] (its first used[g] lanes; none past the end of the rays): each
 * group as one packet when prepare_packet accepts it and its rays lie close,
 * else one by one; group g's results in out[g].  With interleaved walks, the
 * one-by-one walks of every group go in turn together: after a root phase
 * has ended many of a group's rays, the rest would otherwise have few
 * others to hide their cache misses behind; and where every group goes as
 * a packet, so do the packets' walks. */
TRAVERSAL_INLINE void CONCAT(trace_, QUERY)(const RayLanes* lanes, const uint* used,
                                            __global const WideNode* nodes,
                                            __global const Leaf* triangles
                                            TRACE_SCENE_PARAMS, __global int* overflow,
                                            QUERY_OUT* out QUERY_PARAMS)
{
#ifdef INSTANCES
    bool mesh_out_of_stack = false;
    bool* mesh_overflow = &mesh_out_of_stack;
#endif
    bool out_of_stack = false;
#if defined(INTERLEAVED_WALKS) && !defined(INSTANCES)
    /* the walks of the lanes that take one, interleaved (walk.h's walks):
     * walk k is lane lane_of[k] % PACKET_SIZE of group lane_of[k] /
     * PACKET_SIZE, with its own state */
    RayData r[WALK_LANES];
    Found_ray s[WALK_LANES];
    uint lane_of[WALK_LANES];
    uint n = 0;
#ifdef QUERY_STATE
#define PATH_SUFFIX _ray
    PATH(QUERY_STATE) states[WALK_LANES];
#undef PATH_SUFFIX
#endif
#endif
    uint walked = 0;  /* the groups whose packets walked together (bit g) */
#if PACKET_SIZE > 1
    /* the groups that go as one packet each (bit g) */
    Packet packets[LANE_GROUPS];
    uint packed = 0;
    float allowed = -1.0f;  /* packet_allowed, once a packet asks */
    for (uint g = 0; g < LANE_GROUPS; ++g)
        if (used[g] != 0 && prepare_packet(lanes + g, packets + g)) {
            if (allowed < 0.0f)
                allowed = packet_allowed(nodes);
            if (packet_compact(packets + g, allowed))
                packed |= 1u << g;
        }
#if LANE_GROUPS > 1 && defined(INTERLEAVED_WALKS) && !defined(INSTANCES) && !defined(QUERY_STATE)
    /* Where every group goes as a packet, their walks go in turn together
     * (walk.h's walks), as one-by-one walks do: a packet's walk waits on
     * each node's and leaf's lines (perf: on a camera packet's first
     * vertex load in a leaf), and the other packet's steps fill the wait.
     * Each packet visits the same nodes in the same order as alone. */
    if (packed == (1u << LANE_GROUPS) - 1u) {
#define PATH_SUFFIX _packet
        Found_packet found[LANE_GROUPS];
        for (uint g = 0; g < LANE_GROUPS; ++g)
            start_packet(found + g, packets + g);
        out_of_stack |= QUERY_FN(walks, _packet)(packets, nodes, triangles, found, LANE_GROUPS
                                                 TRACE_ARGS);
        for (uint g = 0; g < LANE_GROUPS; ++g)
            QUERY_END(found + g, out + g, 0);
#undef PATH_SUFFIX
#ifdef COUNT_PACKETS
        atomic_add(overflow + 1, LANE_GROUPS);
#endif
        walked = packed;
    }
#endif
#endif
    for (uint g = 0; g < LANE_GROUPS; ++g) {
        if (used[g] == 0 || ((walked >> g) & 1u))
            continue;
        const RayLanes* group = lanes + g;
        QUERY_OUT* group_out = out + g;
#if PACKET_SIZE > 1
        if ((packed >> g) & 1u) {
#ifdef COUNT_PACKETS
            atomic_inc(overflow + 1);
#endif
            out_of_stack |= QUERY_FN(trace, _packet)(packets + g, nodes, triangles, group_out, 0
                                                     TRACE_ARGS);
            continue;
        }
#endif
#ifdef TRACE_ROOT_PHASE
        Found_ray starts[PACKET_SIZE];
        uint walking = QUERY_FN(root, _mixed)(group, nodes, triangles, starts QUERY_ARGS);
#define START_LANE(s, r, l) (*(s) = starts[l])
#define WALKS(l) ((walking >> (l)) & 1u)
#else
#define START_LANE(s, r, l) start_ray(s, r)
#endif
#if defined(INTERLEAVED_WALKS) && !defined(INSTANCES)
#define PATH_SUFFIX _ray
        for (uint l = 0; l < used[g]; ++l) {
#ifdef QUERY_LANE
            if (!QUERY_LANE(group_out, l))
                continue;
#endif
#ifdef TRACE_ROOT_PHASE
            if (!WALKS(l)) {  /* the root phase found all there is */
                QUERY_END(starts + l, group_out, l);
                continue;
            }
#endif
            prepare_lane(r + n, group, l);
            START_LANE(s + n, r + n, l);
#ifdef QUERY_STATE
            PATH(QUERY_STATE)* state = states + n;
            QUERY_BEGIN(group_out, l);
#endif
            lane_of[n++] = g * PACKET_SIZE + l;
        }
#undef PATH_SUFFIX
#else
        for (uint l = 0; l < used[g]; ++l) {
#ifdef QUERY_LANE
            if (!QUERY_LANE(group_out, l))
                continue;
#endif
            RayData r;
#ifdef TRACE_ROOT_PHASE
#define PATH_SUFFIX _ray
            Found_ray s = starts[l];
            if (WALKS(l)) {
                prepare_lane(&r, group, l);
                out_of_stack |= QUERY_FN(walk, _ray)(&r, nodes, triangles, &s TRACE_ARGS);
            }
            QUERY_END(&s, group_out, l);
#undef PATH_SUFFIX
#else
            prepare_lane(&r, group, l);
            out_of_stack |= QUERY_FN(trace, _ray)(&r, nodes, triangles, group_out, l
                                                  TRACE_ARGS);
#endif
        }
#endif
#undef START_LANE
#undef WALKS
    }
#if defined(INTERLEAVED_WALKS) && !defined(INSTANCES)
#define PATH_SUFFIX _ray
    if (n > 0) {
#ifdef QUERY_STATE
        PATH(QUERY_STATE)* state = states;
#endif
        out_of_stack |= QUERY_FN(walks, _ray)(r, nodes, triangles, s, n TRACE_ARGS
                                              WALK_STATE_ARG);
    }
    for (uint k = 0; k < n; ++k) {
#ifdef QUERY_STATE
        PATH(QUERY_STATE)* state = states + k;
#endif
        QUERY_END(s + k, out + lane_of[k] / PACKET_SIZE, lane_of[k] % PACKET_SIZE);
    }
#undef PATH_SUFFIX
#endif
#ifdef INSTANCES
    out_of_stack |= mesh_out_of_stack;
#endif
    if (out_of_stack)
        overflow[0] = 1;
}

#include "query/walk/walk_end.h"
#undef TRACE_ROOT_PHASE
#undef QUERY_ROOT_PHASE
#undef QUERY_OUT
#undef QUERY_BEGIN
#undef QUERY_END
#undef QUERY_LANE
#undef QUERY_ENDS
#undef QUERY_MESH_ARGS
#undef QUERY_FN
#undef TRACE_NAME
#undef TRACED
#undef TRACE_SCENE_PARAMS
#undef TRACE_PARAMS
#undef TRACE_ARGS
#undef MESH_WALK_ray
#undef MESH_WALK_packet
#undef IS_PACKET_ray
#undef IS_PACKET_packet
#undef IS_PACKET_mixed

#else /* one path */

#if CONCAT(IS_PACKET, PATH_SUFFIX) == IS_PACKET_mixed
/* The root phase of rays lanes[0, PACKET_SIZE) (QUERY_ROOT_PHASE): each leaf
 * of the root that some lane meets within its limit (SLABS_MEET per lane),
 * in slot order, tested for every lane, one vector test per triangle.  A
 * lane that does not meet the leaf's box may take a hit there too, a real
 * one, which its walk would have found below the same limit: the query's
 * result does not depend on the order, so it is the same.  Each lane's walk
 * starts from starts[l]: what the root phase found, and the leaves it
 * tested (root_done).  Returns the lanes (bit l) that meet an interior child
 * of the root within their limits then: the others have found all there is
 * (on a ground or a wall, or nothing), and take no walk.  On two-level
 * scenes (INSTANCES) there is no root phase: a leaf of the top tree holds
 * instances. */
TRAVERSAL_INLINE uint QUERY_FN(root, _mixed)(const RayLanes* lanes,
                                             __global const WideNode* nodes,
                                             __global const Leaf* triangles,
                                             Found_ray* starts QUERY_PARAMS)
{
    Mixed r;
    prepare_mixed(lanes, &r);
    Found_mixed found = {(int_packet)(-1), (float_packet)(INFINITY), (float_packet)(0.0f),
                         (float_packet)(0.0f), r.tmax, 0.0f};
    Found_mixed* s = &found;  /* QUERY_HIT's */
    uint done = 0;
    for (uint leaves = lane_mask(LOAD_ROW(int_lanes, nodes->count) != (int_lanes)(0));
         leaves != 0; leaves &= leaves - 1u) {
        int c = lowest_slot(leaves);
        if (!some_packet(mixed_meet(&r, nodes, c, s->limit)))
            continue;
        done |= 1u << c;
        uint first = (uint)nodes->child[c];
        for (uint i = first; i < first + nodes->count[c]; ++i) {
            float_packet t, u, v;
            LEAF_CORNERS(tri, triangles, i);
            int_packet hit = hit_triangle_mixed(&r, tri, s->limit,
                                                (s->index >= 0) & (s->index < (int)i), &t,
                                                &u, &v);
            if (some_packet(hit))
                QUERY_HIT(s, i, hit, t, u, v);
        }
    }
    /* the lanes that meet an interior child of the root within their
     * limits: only they may find more */
    int_packet further = (int_packet)(0);
    for (uint inner = lane_mask(LOAD_ROW(int_lanes, nodes->count) == (int_lanes)(0));
         inner != 0; inner &= inner - 1u)
        further |= mixed_meet(&r, nodes, lowest_slot(inner), s->limit);
    int index[PACKET_SIZE], walks[PACKET_SIZE];
    float t[PACKET_SIZE], u[PACKET_SIZE], v[PACKET_SIZE], limit[PACKET_SIZE];
    vstore_packet(further, 0, walks);
    vstore_packet(found.index, 0, index);
    vstore_packet(found.t, 0, t);
    vstore_packet(found.u, 0, u);
    vstore_packet(found.v, 0, v);
    vstore_packet(found.limit, 0, limit);
    uint walking = 0;
    for (uint l = 0; l < PACKET_SIZE; ++l) {
        Found_ray start = {index[l], t[l], u[l], v[l], limit[l], done};
        starts[l] = start;
        walking |= (walks[l] != 0 ? 1u : 0u) << l;
    }
    return walking;
}
#else
/* The walk of a flat scene's tree, or of an instance's mesh. */
#include "query/walk/walk.h"

#ifdef INSTANCES
#if CONCAT(IS_PACKET, PATH_SUFFIX)
/* The lanes of a mapped packet that prepare_packet turned down (their mapped
 * directions disagree in sign), each walked as one ray with its lane's
 * state.  Lanes the instance is hidden from (tmin inf) and lanes done (limit
 * -inf) are skipped. */
TRAVERSAL_INLINE bool QUERY_FN(lanes, _packet)(const RayLanes* lanes,
                                               __global const WideNode* nodes,
                                               __global const Leaf* triangles,
                                               Found_packet* s QUERY_PARAMS)
{
    int index[PACKET_SIZE];
    float t[PACKET_SIZE], u[PACKET_SIZE], v[PACKET_SIZE], limit[PACKET_SIZE];
    vstore_packet(s->index, 0, index);
    vstore_packet(s->t, 0, t);
    vstore_packet(s->u, 0, u);
    vstore_packet(s->v, 0, v);
    vstore_packet(s->limit, 0, limit);
    bool out_of_stack = false;
    for (uint l = 0; l < PACKET_SIZE; ++l) {
        if (!(lanes->tmin[l] <= limit[l]))
            continue;
        RayData one;
        prepare_lane(&one, lanes, l);
        Found_ray f = {index[l], t[l], u[l], v[l], limit[l]};
        out_of_stack |= QUERY_FN(walk, _ray)(&one, nodes, triangles, &f QUERY_ARGS);
        index[l] = f.index;
        t[l] = f.t;
        u[l] = f.u;
        v[l] = f.v;
        limit[l] = f.limit;
    }
    s->index = vload_packet(0, index);
    s->t = vload_packet(0, t);
    s->u = vload_packet(0, u);
    s->v = vload_packet(0, v);
    s->limit = vload_packet(0, limit);
    update_reach_packet(s);
    return out_of_stack;
}

/* A mapped packet's walk: as a packet where its mapped rays still share
 * their direction signs and kz, else lane by lane. */
TRAVERSAL_INLINE bool QUERY_FN(mapped, _packet)(const RayLanes* lanes,
                                                __global const WideNode* nodes,
                                                __global const Leaf* triangles,
                                                Found_packet* s QUERY_PARAMS)
{
    Packet p;
    if (prepare_packet(lanes, &p))
        return QUERY_FN(walk, _packet)(&p, nodes, triangles, s QUERY_ARGS);
    return QUERY_FN(lanes, _packet)(lanes, nodes, triangles, s QUERY_ARGS);
}
#endif /* the packet's own */

/* Instance `in` (number id) of a top tree's leaf (instance_leaf.h): the
 * rays mapped into its mesh's frame, where its mask lets them see it; the
 * mesh's tree walked by the query's walk with the same state, so that what
 * was found so far prunes it; and the instance recorded in the lanes whose
 * walk took a hit.  True when that ends the top walk.
 *
 * A hit of an instance walked before keeps its ties (docs/queries.md):
 * the walk takes only nearer hits, within a limit one float below the
 * lane's, and with the lane's hit hidden (index -1), as tree order, which
 * breaks ties within one mesh, means nothing across two: comparing one
 * mesh's triangle index with another's let a tie replace the triangle and
 * u, v but not the instance, a record of a triangle the ray never hit.  A
 * lane that took no hit gets its hit and limit back.  (The all-hits
 * queries take none this way: their index stays -1, their limits theirs.) */
TRAVERSAL_INLINE bool TRACE_NAME(instance)(PATH(Found)* s, const PATH(Rays)* r,
                                           __global const Instance* in,
                                           int id TRACE_PARAMS WALK_STATE_PARAM)
{
    PATH(Mapped) mapped;
    if (!PATH(map_instance)(&mapped, in, r))
        return false;
    PATH(flags) had = s->index >= 0;
    PATH(flags) index = s->index;
    PATH(real) limit = s->limit;
    s->index = (PATH(flags))(-1);
    s->limit = had ? PATH(below)(limit) : limit;
    PATH(update_reach)(s);
    *mesh_overflow |= TRACE_NAME(PATH(MESH_WALK))(&mapped, MESH_TREE(in),
                                                  s QUERY_MESH_ARGS(in, id) WALK_STATE_ARG);
    PATH(flags) took = s->index >= 0;
    s->index = took ? s->index : index;
    s->limit = (had & ~took) ? limit : s->limit;  /* (all hits keep their own limits) */
    s->instance = took ? (PATH(flags))(id) : s->instance;
    PATH(update_reach)(s);
    return QUERY_ENDS(s);
}

/* The top tree's walk, whose leaves hold instances. */
#define QUERY_INSTANCE TRACE_NAME(instance)
#include "query/walk/walk.h"
#undef QUERY_INSTANCE
#endif /* INSTANCES */

/* The trace's walk of rays r (a packet, or lane `lane`'s ray) from its start
 * over the scene's tree, with results in out; true if a stack ran out. */
TRAVERSAL_INLINE bool TRACE_NAME(trace)(const PATH(Rays)* r, __global const WideNode* nodes,
                                        __global const Leaf* triangles, QUERY_OUT* out,
                                        uint lane TRACE_PARAMS)
{
    PATH(Found) s;
    PATH(start)(&s, r);
#ifdef QUERY_STATE
    PATH(QUERY_STATE) walk_state;
    PATH(QUERY_STATE)* state = &walk_state;
    QUERY_BEGIN(out, lane);
#endif
    bool out_of_stack = TRACED(PATH_SUFFIX)(r, nodes, triangles, &s TRACE_ARGS WALK_STATE_ARG);
    QUERY_END(&s, out, lane);
    return out_of_stack;
}
#endif /* a walk's path */

#endif /* PATH_SUFFIX */
