/* Four triangles of a leaf against one ray at once, one vector lane each:
 * the first stage of the watertight test (triangle.h's triangle_edges),
 * whose edge functions are most of its work and reject most triangles, in
 * float4 lanes gathered from the leaf's Triangle records.  Each lane's
 * arithmetic is the scalar test's, operation for operation (FP_CONTRACT
 * off), so the lanes that pass go on to the scalar second stage
 * (triangle_depth) with the same bits, one by one in index order (walk.h's
 * quads), and every hit is the one that the one-at-a-time loop finds.  A
 * ray leaving a surface tests most of its triangles in the leaves around
 * its origin, which it enters at once (bench/trace.py's bounce rays: about
 * 8 of 13 a ray on the reference scene), and rejects nearly all. */
#ifndef QUAD_H
#define QUAD_H

#include "query/rays/ray.h"

/* Where the host asks for it (LEAF_QUADS: hlbvh_cl/query/engine.py's
 * leaf_quads, on CPUs), a single ray's walk tests the leaves of at least
 * QUAD_LEAF_MIN triangles four at a time (walk.h's quads).  From 2: leaves
 * of 2 measured faster by quads too, 1 no faster (figures in the commit that
 * says so).  Either leaf layout (core/leaf.h): the lanes take their corners
 * where leaf_corners finds them. */
#if defined(LEAF_QUADS) && LEAF_QUADS
#define QUAD_LEAVES_ray 1
#define QUAD_LEAF_MIN 2

/* The path's vocabulary (walk.h): one ray, four triangles. */
typedef RayData Rays_quad;
typedef float4 real_quad;
typedef int4 flags_quad;  /* a vector compare: -1 or 0 per lane */
TRAVERSAL_INLINE bool some_quad(int4 flags)
{
    return (flags.s0 | flags.s1 | flags.s2 | flags.s3) != 0;
}
TRAVERSAL_INLINE int4 inside_quad(float4 e_u, float4 e_v, float4 e_w)
{
    return ONE_SIGN(e_u, e_v, e_w);
}
#ifdef cl_khr_fp64
typedef double4 wide_quad;
#define to_double_quad convert_double4
#define to_float_quad convert_float4
#endif

/* Each lane's triangle, by its corners. */
typedef struct {
    __global const float* v0[4];
    __global const float* v1[4];
    __global const float* v2[4];
} QuadTriangles;

/* Component k (kx, ky or kz) of each lane's corner v. */
#define corner_quad(v, r, k) \
    ((float4)((v)[0][(r)->k], (v)[1][(r)->k], (v)[2][(r)->k], (v)[3][(r)->k]))

#define PATH_TRIANGLE const QuadTriangles*
#define EDGES_ONLY
#define PATH_SUFFIX _quad
#include "query/rays/triangle.h"
#undef PATH_SUFFIX
#undef EDGES_ONLY
#undef PATH_TRIANGLE

/* Triangles i .. i + 3 of a leaf whose last is `last`, lanes past it
 * repeating it (their results are dropped: quad_lanes), so that nothing
 * past the leaf is read. */
TRAVERSAL_INLINE void quad_triangles(QuadTriangles* q, __global const Leaf* triangles,
                                     uint i, uint last)
{
    for (uint j = 0; j < 4u; ++j) {
        LEAF_CORNERS(tri, triangles, LESSER(i + j, last));
        q->v0[j] = tri->v0;
        q->v1[j] = tri->v1;
        q->v2[j] = tri->v2;
    }
}

/* The lanes that hold triangles i .. last (at most four), as bits. */
TRAVERSAL_INLINE uint quad_lanes(uint i, uint last)
{
    return (2u << LESSER(last - i, 3u)) - 1u;
}

/* The lanes set in flags, as bits (lane l: bit l). */
TRAVERSAL_INLINE uint quad_mask(int4 flags)
{
    return (uint)((flags.s0 & 1) | (flags.s1 & 2) | (flags.s2 & 4) | (flags.s3 & 8));
}

/* Lane l's edge functions, for the scalar second stage.  A union rather
 * than a vector indexed by a variable, which OpenCL C does not have. */
typedef union {
    float4 lanes;
    float lane[4];
} QuadLanes;

TRAVERSAL_INLINE void quad_lane(const Edges_quad* e, uint l, Edges_ray* out)
{
    QuadLanes u = {e->e_u}, v = {e->e_v}, w = {e->e_w};
    out->e_u = u.lane[l];
    out->e_v = v.lane[l];
    out->e_w = w.lane[l];
#ifndef cl_khr_fp64
    QuadLanes az = {e->az}, bz = {e->bz}, cz = {e->cz};
    out->az = az.lane[l];
    out->bz = bz.lane[l];
    out->cz = cz.lane[l];
#endif
}

#endif /* LEAF_QUADS */

#endif /* QUAD_H */
