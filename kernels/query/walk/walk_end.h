/* The end of a query's walks: its hooks (walk.h) undefined, so that the
 * next query defines its own.  walk.h includes it after a one-path walk,
 * query/rays/trace.h after the ray paths and their trace. */
#undef QUERY
#undef QUERY_PATH
#undef QUERY_HIT
#undef QUERY_NODE
#undef QUERY_PARAMS
#undef QUERY_ARGS
#undef QUERY_STATE
#undef QUERY_CHILDREN
#undef QUERY_LEAF
#undef QUERY_INSTANCE
#undef QUERY_UNORDERED
#undef WALK_STATE_PARAM
#undef WALK_STATE_ARG
