/* One ray as traversal uses it: its origin, inverse direction and limits
 * for the slab test (Kay & Kajiya 1986, near planes by the direction's signs
 * as Williams et al. 2005), and the shear of Woop, Benthin & Wald 2013
 * ("Watertight Ray/Triangle Intersection", JCGT 2(1)) for the triangle
 * test, computed once per ray.  Also the single-ray path's vocabulary
 * (suffix _ray) that the generic triangle test and walk are written in. */
#ifndef RAY_H
#define RAY_H

#include "query/walk/node.h"
#include "query/rays/ray_class.h"

#ifndef PACKET_SIZE
#error "PACKET_SIZE must be defined (-D PACKET_SIZE=...)"
#endif

/* A flat scene's rays traced one by one on a CPU (PACKET_SIZE > 1) begin
 * with the root phase (query/rays/trace.h, mixed.h): the root's leaves
 * tested in SIMD across the work-item's rays. */
#if PACKET_SIZE > 1 && !defined(INSTANCES)
#define ROOT_PHASE
#endif

/* Instanced scenes (instance.h) map rays by their direction, and test
 * instances against their masks. */
#if defined(cl_khr_fp64) || defined(INSTANCES)
#define RAY_DIRECTION
#endif

/* Everything about a ray that traversal reuses at each node and triangle. */
typedef struct {
    float ox, oy, oz;           /* origin */
#ifdef RAY_DIRECTION
    float dx, dy, dz;           /* direction, for the refined t (triangle.h), mapping */
#endif
#ifdef INSTANCES
    uint mask;                  /* the ray's mask (instance.h) */
#endif
    float inv_x, inv_y, inv_z;  /* 1/direction; +-INFINITY for a +-0 component */
    float tmin, tmax;
    /* Woop et al. 2013: the axis of largest |direction| becomes z
     * (kz), the other two (kx, ky) follow cyclically; the shear
     * (sx, sy, sz) maps the ray onto the +z axis through the origin. */
    int kx, ky, kz;
    float sx, sy, sz;
    float okx, oky, okz;        /* origin, permuted */
    /* Byte offsets (plane_row) of the rows of planes through which the ray
     * enters the children's boxes on each axis: the lo planes where the
     * inverse direction is positive, the hi planes where its sign bit is set
     * (Williams et al. 2005).  The exit planes are at offset ^ ROW_BYTES. */
    int near_x, near_y, near_z;
} RayData;

/* The helpers that fill a RayData or a Hit write it through a pointer rather
 * than return it: a returned struct goes through a noalias (sret) pointer,
 * and inlining that leaves llvm.experimental.noalias.scope.decl calls,
 * which Oclgrind cannot run. */
TRAVERSAL_INLINE void prepare_ray(RayData* ray, float3 origin, float3 direction, float tmin,
                                  float tmax)
{
    RayData r;
    float d[3] = {direction.x, direction.y, direction.z};
    r.ox = origin.x;
    r.oy = origin.y;
    r.oz = origin.z;
#ifdef RAY_DIRECTION
    r.dx = d[0];
    r.dy = d[1];
    r.dz = d[2];
#endif
    /* IEEE division: 1/+0 = +inf, 1/-0 = -inf, which the slab test relies on. */
    r.inv_x = 1.0f / d[0];
    r.inv_y = 1.0f / d[1];
    r.inv_z = 1.0f / d[2];
    r.tmin = tmin;
    r.tmax = tmax;

    float ax = abs_float(d[0]), ay = abs_float(d[1]), az = abs_float(d[2]);
    r.kz = shear_axis(ax, ay, az);
    r.kx = r.kz == 2 ? 0 : r.kz + 1;
    r.ky = r.kx == 2 ? 0 : r.kx + 1;
    /* Components picked by indexing (a load from the private array) rather
     * than by ?: chains, which x86 compiled into branches that mispredict
     * on incoherent rays, where kz is random (measured faster). */
    float dkz = d[r.kz];
    r.sx = d[r.kx] / dkz;
    r.sy = d[r.ky] / dkz;
    r.sz = 1.0f / dkz;
    float o[3] = {r.ox, r.oy, r.oz};
    r.okx = o[r.kx];
    r.oky = o[r.ky];
    r.okz = o[r.kz];
    r.near_x = LO_X_ROW + (sign_bit(r.inv_x) ? ROW_BYTES : 0);
    r.near_y = LO_Y_ROW + (sign_bit(r.inv_y) ? ROW_BYTES : 0);
    r.near_z = LO_Z_ROW + (sign_bit(r.inv_z) ? ROW_BYTES : 0);
    *ray = r;
}

/* The rays one work-item traces, one lane each (PACKET_SIZE of them), as
 * loaded: lanes past the last ray repeat it (a packet pays nothing for them
 * and they are not written back). */
typedef struct {
    float origin[3][PACKET_SIZE];
    float direction[3][PACKET_SIZE];
    float tmin[PACKET_SIZE];
    float tmax[PACKET_SIZE];
#ifdef INSTANCES
    uint mask[PACKET_SIZE];  /* set by the instanced kernels (instance.h's load_masks) */
#endif
} RayLanes;

/* Whether x is NaN or infinite, by its exponent bits (packet.h's not_finite, one lane). */
TRAVERSAL_INLINE int float_not_finite(float x)
{
    return (as_uint(x) & 0x7f800000u) == 0x7f800000u;
}

/* Lane l's ray.  One whose origin or direction is not finite meets nothing
 * (tmax -inf): its slab distances would be NaN, which SLABS_MEET's min and
 * max pass over, so that it would enter every lane of a node, the unused
 * ones (an empty box, child EMPTY_CHILD) too, and read outside the tree.
 * The host checks the rays it is given; rays made on the device (the
 * renderer's bounces) get here unchecked. */
TRAVERSAL_INLINE void set_lane(RayLanes* lanes, uint l, float3 origin, float3 direction,
                               float tmin, float tmax)
{
    if (float_not_finite(origin.x) | float_not_finite(origin.y) | float_not_finite(origin.z)
        | float_not_finite(direction.x) | float_not_finite(direction.y)
        | float_not_finite(direction.z))
        tmax = -INFINITY;
    lanes->origin[0][l] = origin.x;
    lanes->origin[1][l] = origin.y;
    lanes->origin[2][l] = origin.z;
    lanes->direction[0][l] = direction.x;
    lanes->direction[1][l] = direction.y;
    lanes->direction[2][l] = direction.z;
    lanes->tmin[l] = tmin;
    lanes->tmax[l] = tmax;
}

TRAVERSAL_INLINE void prepare_lane(RayData* ray, const RayLanes* lanes, uint l)
{
    prepare_ray(ray, (float3)(lanes->origin[0][l], lanes->origin[1][l], lanes->origin[2][l]),
                (float3)(lanes->direction[0][l], lanes->direction[1][l], lanes->direction[2][l]),
                lanes->tmin[l], lanes->tmax[l]);
#ifdef INSTANCES
    ray->mask = lanes->mask[l];
#endif
}

/* ---- the single-ray path's vocabulary (see walk.h): one lane, scalars */
typedef RayData Rays_ray;
typedef float real_ray;
typedef int flags_ray;       /* a scalar compare: 1 or 0 */
TRAVERSAL_INLINE bool some_ray(int flags) { return flags != 0; }
TRAVERSAL_INLINE bool every_ray(int flags) { return flags != 0; }
TRAVERSAL_INLINE int bits_ray(float x) { return as_int(x); }
#ifdef cl_khr_fp64
typedef double wide_ray;
TRAVERSAL_INLINE double to_double_ray(float x) { return (double)x; }
TRAVERSAL_INLINE float to_float_ray(double x) { return (float)x; }
#endif

/* What a walk keeps for its query: the triangle hit (tree order, -1: none),
 * its t, u, v, and the limit beyond which nothing counts. */
typedef struct {
    int index;
    float t, u, v, limit;
#ifdef INSTANCES
    int instance;  /* whose mesh holds triangle `index` (instance.h) */
#endif
#ifdef ROOT_PHASE
    uint root_done;  /* the root's leaves the work-item's root phase tested (trace.h) */
#endif
} Found_ray;

/* A walk's start: no hit, the limit the ray's tmax. */
TRAVERSAL_INLINE void start_ray(Found_ray* s, const RayData* r)
{
    Found_ray start = {-1, INFINITY, 0.0f, 0.0f, r->tmax};
#ifdef INSTANCES
    start.instance = -1;
#endif
#ifdef ROOT_PHASE
    start.root_done = 0;
#endif
    *s = start;
}

/* The root's leaves that the walk has had tested already (root_done). */
#ifdef ROOT_PHASE
#define root_done_ray(s) ((s)->root_done)
#else
#define root_done_ray(s) 0u
#endif

/* float_below (core/spelled.h), the single-ray path's spelling. */
#define below_ray float_below

/* The farthest the walk still looks: the limit. */
TRAVERSAL_INLINE float reach_ray(const Found_ray* s) { return s->limit; }
TRAVERSAL_INLINE void update_reach_ray(Found_ray* s) {}

/* Woop et al.'s inside test: the three edge functions have one sign (0
 * counts as either), for every path's lanes (inside_packet, inside_quad).
 * Written so that a NaN edge function (the products overflow, inf - inf,
 * for a ray from ~1e30 away) fails it: "do not straddle 0" took NaN as
 * inside, and such a ray hit every triangle it was tested against.  Bitwise
 * | and & rather than || and &&: one branch instead of up to six, which the
 * sign pattern of rejected triangles mispredicts (measured faster). */
#define ONE_SIGN(e_u, e_v, e_w)                                  \
    ((((e_u) >= 0.0f) & ((e_v) >= 0.0f) & ((e_w) >= 0.0f))      \
     | (((e_u) <= 0.0f) & ((e_v) <= 0.0f) & ((e_w) <= 0.0f)))

TRAVERSAL_INLINE int inside_ray(float e_u, float e_v, float e_w)
{
    return ONE_SIGN(e_u, e_v, e_w);
}

/* The slab test of a wide node's WIDE_ARITY child boxes at once, one vector
 * lane per child, within the walk's limit: the children met as a bit mask,
 * and where the ray enters each. */
#define NODE_ROW(offset) LOAD_ROW(float_lanes, plane_row(node, offset)) /* SLAB_TEST's PLANE */
TRAVERSAL_INLINE uint children_ray(const RayData* r, __global const WideNode* node,
                                   const Found_ray* s, ChildEntries* entry)
{
    return lane_mask(SLAB_TEST(float_lanes, NODE_ROW, r, (float_lanes)(r->tmin),
                               (float_lanes)(s->limit), entry->lanes));
}
#undef NODE_ROW

/* A vertex's component k (kx, ky or kz) of the ray's permutation. */
#define corner_ray(v, r, k) ((v)[(r)->k])

#define PATH_SUFFIX _ray
#include "query/rays/triangle.h"
#undef PATH_SUFFIX

#include "query/rays/quad.h"

#endif /* RAY_H */
