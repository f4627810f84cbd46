/* The watertight ray/triangle test of Woop, Benthin & Wald 2013
 * ("Watertight Ray/Triangle Intersection", JCGT 2(1)), without back-face
 * culling, with t refined in double (below), and what a walk records of a
 * hit.  Written once for both paths: included with PATH_SUFFIX defined
 * (ray.h, packet.h), it defines hit_triangle and take_hit for that path's
 * types, so single rays and packet lanes run the same arithmetic. */
#ifndef TRIANGLE_H
#define TRIANGLE_H

#include "query/walk/node.h"

/* Watertightness needs each edge function to be computed the same way by the
 * two triangles that share the edge; a fused multiply-add would round the two
 * products of U = Cx*By - Cy*Bx differently and could open cracks. */
#pragma OPENCL FP_CONTRACT OFF

/* cross(v1 - v0, v2 - v0): unnormalised, following the winding. */
TRAVERSAL_INLINE void geometric_normal(TRIANGLE_AT tri, float* nx, float* ny,
                                       float* nz)
{
    float e1x = tri->v1[0] - tri->v0[0], e1y = tri->v1[1] - tri->v0[1], e1z = tri->v1[2] - tri->v0[2];
    float e2x = tri->v2[0] - tri->v0[0], e2y = tri->v2[1] - tri->v0[1], e2z = tri->v2[2] - tri->v0[2];
    *nx = e1y * e2z - e1z * e2y;
    *ny = e1z * e2x - e1x * e2z;
    *nz = e1x * e2y - e1y * e2x;
}

#ifdef cl_khr_fp64
/* Woop's t = (e_u*Az + e_v*Bz + e_w*Cz)/det is float arithmetic on the
 * sheared vertices: when the triangle is large compared with the hit
 * distance, Az, Bz, Cz are large and nearly cancel, and t loses most of its
 * relative precision (a triangle 1e5 across hit at distance 1).  So once
 * the edge test says inside, t is recomputed as dot(v0 - o, n) / dot(d, n)
 * in double: with float inputs v1 - v0, v2 - v0 and v0 - o are exact and
 * only the plane's own rounding (~1e-16 relative) is left.  The edge test
 * still decides inside/outside (watertightness).  Both paths evaluate these
 * expressions in the same order (no contraction, FP_CONTRACT OFF above), so
 * single rays and packets give identical t: macros, for both paths' types. */
#define REFINE_NUM(vx, vy, vz, ox, oy, oz, nx, ny, nz) \
    ((((vx) - (ox)) * (nx) + ((vy) - (oy)) * (ny)) + ((vz) - (oz)) * (nz))
#define REFINE_DEN(dx, dy, dz, nx, ny, nz) (((dx) * (nx) + (dy) * (ny)) + (dz) * (nz))

/* The triangle's first vertex and its plane's normal cross(v1 - v0, v2 - v0)
 * in double. */
TRAVERSAL_INLINE void plane_double(TRIANGLE_AT tri, double* v0, double* n)
{
    v0[0] = tri->v0[0];
    v0[1] = tri->v0[1];
    v0[2] = tri->v0[2];
    double e1x = (double)tri->v1[0] - v0[0], e1y = (double)tri->v1[1] - v0[1],
           e1z = (double)tri->v1[2] - v0[2];
    double e2x = (double)tri->v2[0] - v0[0], e2y = (double)tri->v2[1] - v0[1],
           e2z = (double)tri->v2[2] - v0[2];
    n[0] = e1y * e2z - e1z * e2y;
    n[1] = e1z * e2x - e1x * e2z;
    n[2] = e1x * e2y - e1y * e2x;
}
#endif

#ifdef OWN_EDGES
/* Whether the edge with edge function e and 2-D direction (dx, dy) holds the
 * ray: e != 0 (the inside test decides), or an exact 0 on an edge that owns
 * the ray (see hit_triangle).  A triangle with det < 0 has its interior on
 * the left of its edges; one with det > 0 on their right, where the
 * direction is negated.  Scalars and vectors alike: the negation picks
 * floats, as ?: between two flag tests became logic on the compares' i1
 * vectors with a negation, which Oclgrind runs wrong (see inside_packet). */
#define OWNS_EDGE(e, dx, dy, det)                                                       \
    (((e) != 0.0f) | OWNS_DIRECTION((det) < 0.0f ? (dx) : -(dx), (det) < 0.0f ? (dy) : -(dy)))
#define OWNS_DIRECTION(dx, dy) (((dy) > 0.0f) | (((dy) == 0.0f) & ((dx) < 0.0f)))
#endif

#endif /* TRIANGLE_H */

#ifdef PATH_SUFFIX
/* What the triangle test's first stage leaves for its second: the scaled
 * barycentrics (Woop et al.'s U, V, W) and, without fp64, the sheared
 * vertices' z for t. */
typedef struct {
    PATH(real) e_u, e_v, e_w;
#ifndef cl_khr_fp64
    PATH(real) az, bz, cz;
#endif
} PATH(Edges);

/* The path's triangles: one (TRIANGLE_AT), or one per lane where a path
 * tests several at once (quad.h defines PATH_TRIANGLE). */
#ifndef PATH_TRIANGLE
#define PATH_TRIANGLE TRIANGLE_AT
#define PATH_TRIANGLE_DEFAULT
#endif

/* The test's first stage: whether the ray meets `tri` inside its edges, in
 * each lane, with the edge functions in *out. */
TRAVERSAL_INLINE PATH(flags) PATH(triangle_edges)(const PATH(Rays)* r, PATH_TRIANGLE tri,
                                                  PATH(Edges)* out)
{
    /* Vertices relative to the origin, permuted (kx, ky, kz): corner picks
     * each lane's component (per path: ray.h, packet.h, mixed.h, quad.h). */
    PATH(real) ax = PATH(corner)(tri->v0, r, kx) - r->okx,
               ay = PATH(corner)(tri->v0, r, ky) - r->oky,
               az = PATH(corner)(tri->v0, r, kz) - r->okz;
    PATH(real) bx = PATH(corner)(tri->v1, r, kx) - r->okx,
               by = PATH(corner)(tri->v1, r, ky) - r->oky,
               bz = PATH(corner)(tri->v1, r, kz) - r->okz;
    PATH(real) cx = PATH(corner)(tri->v2, r, kx) - r->okx,
               cy = PATH(corner)(tri->v2, r, ky) - r->oky,
               cz = PATH(corner)(tri->v2, r, kz) - r->okz;
    /* Shear so that the ray runs along +z. */
    ax = ax - r->sx * az;  ay = ay - r->sy * az;
    bx = bx - r->sx * bz;  by = by - r->sy * bz;
    cx = cx - r->sx * cz;  cy = cy - r->sy * cz;
    /* Scaled barycentrics: 2D edge functions at the ray (0, 0). */
    PATH(real) e_u = cx * by - cy * bx;
    PATH(real) e_v = ax * cy - ay * cx;
    PATH(real) e_w = bx * ay - by * ax;
#ifdef cl_khr_fp64
    /* An edge function of exactly 0 may be rounding: redo the three in double,
     * where the products of floats are exact (as the paper does).  Without
     * fp64 a 0 stays 0, i.e. "on the edge", and the ray hits both triangles
     * that share it: never a crack, at worst a tie. */
    PATH(flags) on_edge = (e_u == 0.0f) | (e_v == 0.0f) | (e_w == 0.0f);
    if (PATH(some)(on_edge)) {
        PATH(wide) dax = PATH(to_double)(ax), day = PATH(to_double)(ay);
        PATH(wide) dbx = PATH(to_double)(bx), dby = PATH(to_double)(by);
        PATH(wide) dcx = PATH(to_double)(cx), dcy = PATH(to_double)(cy);
        e_u = on_edge ? PATH(to_float)(dcx * dby - dcy * dbx) : e_u;
        e_v = on_edge ? PATH(to_float)(dax * dcy - day * dcx) : e_v;
        e_w = on_edge ? PATH(to_float)(dbx * day - dby * dax) : e_w;
    }
#else
    out->az = az;
    out->bz = bz;
    out->cz = cz;
#endif
    out->e_u = e_u;
    out->e_v = e_v;
    out->e_w = e_w;
    /* No culling: inside when the three have the same sign (0 on an edge). */
    PATH(real) det = e_u + e_v + e_w;
    PATH(flags) hit = PATH(inside)(e_u, e_v, e_w) & (det != 0.0f);
#ifdef OWN_EDGES
    /* A ray through an edge or a vertex hits exactly one of the triangles
     * that meet there from opposite sides (all-hits queries count each
     * crossing once).  The edge functions of a shared edge are exactly
     * negated between its two triangles (same products, opposite
     * subtraction), so an exact 0 here is the same 0 for both.  It counts as
     * inside only for an edge that owns it, by the rasterisation top-left
     * rule: the edge's 2-D direction, oriented with the interior on its left
     * (sign of det), points up, or left when horizontal.  This is the
     * symbolic perturbation of the ray by (-eps, -eps^2) in the sheared frame
     * (Edelsbrunner & Muecke 1990, "Simulation of Simplicity"): every ray
     * then counts as a nearby generic one, so a vertex's fan has one owner
     * and a silhouette edge two or none.  Edges pair as e_u: v1->v2,
     * e_v: v2->v0, e_w: v0->v1. */
    if (PATH(some)(hit & ((e_u == 0.0f) | (e_v == 0.0f) | (e_w == 0.0f))))
        hit &= OWNS_EDGE(e_u, cx - bx, cy - by, det) & OWNS_EDGE(e_v, ax - cx, ay - cy, det)
               & OWNS_EDGE(e_w, bx - ax, by - ay, det);
#endif
    return hit;
}

#ifndef EDGES_ONLY
/* The test's second stage, in the lanes `hit` that the first passed: t
 * within tmin <= t <= limit (t < limit where `strict`), with t, u, v in
 * *t_out, *u_out, *v_out (hit = (1-u-v)*v0 + u*v1 + v*v2).  Degenerate
 * triangles are never hit. */
TRAVERSAL_INLINE PATH(flags) PATH(triangle_depth)(const PATH(Rays)* r, TRIANGLE_AT tri,
                                                  const PATH(Edges)* e, PATH(flags) hit,
                                                  PATH(real) limit, PATH(flags) strict,
                                                  PATH(real)* t_out, PATH(real)* u_out,
                                                  PATH(real)* v_out)
{
    PATH(real) det = e->e_u + e->e_v + e->e_w;
    PATH(real) inv_det = 1.0f / det;
#ifdef cl_khr_fp64
    PATH(real) t;
    {
        double v0[3], n[3];
        plane_double(tri, v0, n);
        PATH(wide) num = REFINE_NUM(v0[0], v0[1], v0[2], PATH(to_double)(r->ox),
                                    PATH(to_double)(r->oy), PATH(to_double)(r->oz),
                                    n[0], n[1], n[2]);
        PATH(wide) den = REFINE_DEN(PATH(to_double)(r->dx), PATH(to_double)(r->dy),
                                    PATH(to_double)(r->dz), n[0], n[1], n[2]);
        /* den == 0 (zero area, or parallel in double) gives inf or NaN,
         * which the test below rejects. */
        t = PATH(to_float)(num / den);
    }
#else
    PATH(real) t = (e->e_u * (r->sz * e->az) + e->e_v * (r->sz * e->bz)
                    + e->e_w * (r->sz * e->cz)) * inv_det;
#endif
    /* Written so that a NaN t fails; an infinite t (tmax = inf) too. */
    hit &= (t >= r->tmin) & ((PATH(bits)(t) & 0x7fffffff) < 0x7f800000)
           & (strict ? t < limit : t <= limit);
    if (!PATH(some)(hit))
        return hit;
    /* A zero-area triangle can still give det != 0 after rounding the shear;
     * never report it (its normal is undefined).  Only accepted hits pay. */
    float nx, ny, nz;
    geometric_normal(tri, &nx, &ny, &nz);
    if (nx == 0.0f && ny == 0.0f && nz == 0.0f)
        return (PATH(flags))(0);
    *t_out = t;
    /* e_v / det rounds to at most 1 + ulp, and to NaN when det overflows or
     * underflows: clamp (fmax maps NaN to 0) so u, v stay in [0, 1]. */
    *u_out = fmin(fmax(e->e_v * inv_det, (PATH(real))(0.0f)), (PATH(real))(1.0f));
    *v_out = fmin(fmax(e->e_w * inv_det, (PATH(real))(0.0f)), (PATH(real))(1.0f));
    return hit;
}

/* Every lane's hit of `tri` with tmin <= t <= limit (t < limit where
 * `strict`): the lanes that hit (flags), with their t, u, v in *t_out,
 * *u_out, *v_out: both stages. */
TRAVERSAL_INLINE PATH(flags) PATH(hit_triangle)(const PATH(Rays)* r,
                                                TRIANGLE_AT tri,
                                                PATH(real) limit, PATH(flags) strict,
                                                PATH(real)* t_out, PATH(real)* u_out,
                                                PATH(real)* v_out)
{
    PATH(Edges) e;
    PATH(flags) hit = PATH(triangle_edges)(r, tri, &e);
    if (!PATH(some)(hit))
        return hit;
    return PATH(triangle_depth)(r, tri, &e, hit, limit, strict, t_out, u_out, v_out);
}

/* Records triangle i's hit in the lanes `hit`: its t, u, v, and the limit
 * the query sets (`limit`: t for the closest hit, -INFINITY for a lane that
 * is done). */
TRAVERSAL_INLINE void PATH(take_hit)(PATH(Found)* s, uint i, PATH(flags) hit, PATH(real) t,
                                     PATH(real) u, PATH(real) v, PATH(real) limit)
{
    s->index = hit ? (PATH(flags))((int)i) : s->index;
    s->limit = hit ? limit : s->limit;
    s->t = hit ? t : s->t;
    s->u = hit ? u : s->u;
    s->v = hit ? v : s->v;
    PATH(update_reach)(s);
}
#endif /* EDGES_ONLY */
#ifdef PATH_TRIANGLE_DEFAULT
#undef PATH_TRIANGLE
#undef PATH_TRIANGLE_DEFAULT
#endif
#endif /* PATH_SUFFIX */
