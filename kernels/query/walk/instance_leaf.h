/* The leaf of a top tree (a two-level scene's, two_level.h), whose slots
 * hold instances: for every query family one loop, which hands each
 * instance of the leaf, in slot order, to the query's QUERY_INSTANCE
 * (s, r, in, id, the walk's arguments): it maps the query into the
 * instance's mesh frame and walks the mesh's tree, with the same state
 * (query/rays/instance.h, query/points/instance.h).  Included by walk.h
 * for each path of a walk with QUERY_INSTANCE; true when the walk ends. */
TRAVERSAL_INLINE bool WALK_NAME(instances)(PATH(Found)* s, const PATH(Rays)* r, int first,
                                           uint count WALK_PARAMS)
{
    for (uint i = (uint)first; i < (uint)first + count; ++i) {
        int id = top_refs[i].prim_id;
        if (QUERY_INSTANCE(s, r, instances + id, id WALK_ARGS))
            return true;
    }
    return false;
}
