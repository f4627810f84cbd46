/* Ray queries: stackful traversal of the wide tree (WideNode, made from the
 * flat BVH2 by widen.cl) with a watertight ray/triangle test.  A work-item
 * traces PACKET_SIZE consecutive rays: on CPUs as one packet when they are
 * coherent (see "packets" below), else one by one.
 *
 * Kernels
 *   intersect_closest  nearest hit in [tmin, tmax] -> Hit
 *   intersect_any      1 if any hit in [tmin, tmax] (stops at the first one)
 *   intersect_closest_arrays, intersect_any_arrays
 *                      the same on numpy-shaped arrays (one per field)
 *
 * Conventions (tests/oracle.py follows the same ones)
 *   - a hit at distance t counts when tmin <= t <= tmax (both ends closed,
 *     as Embree's tnear <= t <= tfar); t is in units of |direction|;
 *   - no culling: both sides of a triangle are hit;
 *   - degenerate triangles (zero edge cross product) are never hit;
 *   - u, v: hit = (1-u-v)*v0 + u*v1 + v*v2.
 *
 * Compile-time parameters (-D)
 *   STACK_SIZE  entries of the private traversal stack; the host passes a
 *               bound that cannot overflow for the tree (query.py), and if
 *               it ever did, the ray is flagged and the host raises.
 *   PACKET_SIZE rays per work-item: 1 (one ray each, for GPUs, whose SIMT
 *               lanes already run neighbouring rays together), or 8 or 16
 *               (ray packets, for CPUs; see "packets" below).
 *   PREFETCH    defined on CPUs: traversal prefetches what it visits next
 *               (__builtin_prefetch, which the CPUs' Clang-based OpenCL
 *               compilers know).
 *   COUNT_PACKETS  defined by tests: overflow[1] counts the work-items whose
 *               rays were traced as one packet.
 */
#include "hlbvh.h"

/* Watertightness needs each edge function to be computed the same way by the
 * two triangles that share the edge; a fused multiply-add would round the two
 * products of U = Cx*By - Cy*Bx differently and could open cracks. */
#pragma OPENCL FP_CONTRACT OFF

#ifdef cl_khr_fp64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif

#ifndef STACK_SIZE
#error "STACK_SIZE must be defined (-D STACK_SIZE=...)"
#endif
#ifndef PACKET_SIZE
#error "PACKET_SIZE must be defined (-D PACKET_SIZE=...)"
#endif

/* One vector lane per child of a wide node. */
#if WIDE_ARITY == 8
typedef float8 float_lanes;
typedef int8 int_lanes;
#define LANES_HINT vec_type_hint(float8)
#elif WIDE_ARITY == 4
typedef float4 float_lanes;
typedef int4 int_lanes;
#define LANES_HINT vec_type_hint(float4)
#else
#error "WIDE_ARITY must be 4 or 8"
#endif

/* PoCL's inliner stops just short of the traversal loop and the triangle
 * test (measured: about 10% slower on camera rays); every helper here is
 * small or called in one place, so inline them all. */
#define TRAVERSAL_INLINE inline __attribute__((always_inline))

/* A WideNode's plane or count row as one vector load.  A row starts at a
 * multiple of 4 * WIDE_ARITY bytes within the node, and nodes and buffers
 * at multiples of its size (buffers are aligned to at least the largest
 * built-in type, 128 bytes), so the load is aligned.  A plain load rather
 * than vload8, which PoCL 3.0 calls out of line (see GROW_LO in hlbvh.h). */
#define LOAD_ROW(type, row) (*(__global const type*)(row))

/* The plane row (lo_x, hi_x, lo_y, hi_y, lo_z or hi_z) that starts `offset`
 * bytes into a node: the row's own array, addressed from the node's first
 * byte as offsetof would, so that a read stays within it (an offset in
 * floats from lo_x would index lo_x past its end). */
TRAVERSAL_INLINE __global const float* plane_row(__global const WideNode* node, int offset)
{
    return (__global const float*)((__global const uchar*)node + offset);
}

/* The byte offsets of a node's lo rows on each axis (WideNode's rows are
 * lo_x, hi_x, lo_y, hi_y, lo_z, hi_z, ...); an axis's other row is at
 * offset ^ ROW_BYTES. */
#define ROW_BYTES (WIDE_ARITY * 4)
#define LO_X_ROW (0 * ROW_BYTES)
#define LO_Y_ROW (2 * ROW_BYTES)
#define LO_Z_ROW (4 * ROW_BYTES)

/* Sign bit and absolute value by their bits, for the same reason. */
#define SIGN_BIT(x) (as_uint(x) >> 31)
#define ABS_FLOAT(x) as_float(as_uint(x) & 0x7fffffffu)

/* sqrt as one instruction where the compiler is a Clang (PoCL calls sqrt). */
#if HAS_BUILTIN(__builtin_sqrtf)
#define SQUARE_ROOT __builtin_sqrtf
#endif
#ifndef SQUARE_ROOT
#define SQUARE_ROOT sqrt
#endif

/* Ize 2013, "Robust BVH Ray Traversal" (JCGT 2(2)): scaling the exit distance
 * by 1 + 2*gamma(3) makes the slab test conservative under float rounding.  We
 * use gamma(5) (gamma(n) = n*eps / (1 - n*eps), eps = 2^-24) because OpenCL
 * allows 2.5 ulp for the division that gives the inverse direction. */
#define EXIT_SCALE (1.0f + 2.0f * (5.0f * 0x1p-24f) / (1.0f - 5.0f * 0x1p-24f))

/* Everything about a ray that traversal reuses at each node and triangle. */
typedef struct {
    float ox, oy, oz;           /* origin */
#ifdef cl_khr_fp64
    float dx, dy, dz;           /* direction, for refine_t */
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
#ifdef cl_khr_fp64
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

    float ax = ABS_FLOAT(d[0]), ay = ABS_FLOAT(d[1]), az = ABS_FLOAT(d[2]);
    r.kz = (ax >= ay && ax >= az) ? 0 : (ay >= az ? 1 : 2);
    r.kx = r.kz == 2 ? 0 : r.kz + 1;
    r.ky = r.kx == 2 ? 0 : r.kx + 1;
    /* Components picked by indexing (a load from the private array) rather
     * than by ?: chains, which x86 compiled into branches that mispredict
     * on incoherent rays, where kz is random (A/B on PoCL, incoherent rays:
     * teapot 1.06-1.07x, bunny 1.04-1.14x, reference scene 1.02-1.04x;
     * camera rays, which packets prepare in vector lanes, unchanged). */
    float dkz = d[r.kz];
    r.sx = d[r.kx] / dkz;
    r.sy = d[r.ky] / dkz;
    r.sz = 1.0f / dkz;
    float o[3] = {r.ox, r.oy, r.oz};
    r.okx = o[r.kx];
    r.oky = o[r.ky];
    r.okz = o[r.kz];
    r.near_x = LO_X_ROW + (SIGN_BIT(r.inv_x) ? ROW_BYTES : 0);
    r.near_y = LO_Y_ROW + (SIGN_BIT(r.inv_y) ? ROW_BYTES : 0);
    r.near_z = LO_Z_ROW + (SIGN_BIT(r.inv_z) ? ROW_BYTES : 0);
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
} RayLanes;

TRAVERSAL_INLINE void set_lane(RayLanes* lanes, uint l, float3 origin, float3 direction,
                               float tmin, float tmax)
{
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
}

/* The closing step of a slab test, one lane per child: the entry is the
 * latest of tmin and the near planes' distances, the exit the earliest far
 * plane's (NaNs ignored: see hit_children), scaled by EXIT_SCALE; whether
 * they meet within limit (-1 or 0), and the entry. */
TRAVERSAL_INLINE int_lanes slabs_meet(float_lanes near_x, float_lanes near_y,
                                      float_lanes near_z, float_lanes far_x, float_lanes far_y,
                                      float_lanes far_z, float tmin, float limit,
                                      float_lanes* entry)
{
    float_lanes t_entry = GROW_HI(GROW_HI(GROW_HI((float_lanes)(tmin), near_x), near_y), near_z);
    float_lanes t_exit = GROW_LO(GROW_LO(GROW_LO((float_lanes)(INFINITY), far_x), far_y), far_z)
                         * EXIT_SCALE;
    *entry = t_entry;
    return t_entry <= GROW_LO(t_exit, (float_lanes)(limit));
}

/* Slab test (Kay & Kajiya 1986) of a wide node's WIDE_ARITY child boxes
 * at once, one vector lane per child.  Per axis the entry plane is
 * chosen by the sign bit of the inverse direction (Williams et al. 2005), so a
 * 0 * inf = NaN (origin on a slab plane, direction component 0) can only be
 * the entry or exit of that axis, which the GROW_HI / GROW_LO chains then
 * ignore (they start from tmin and +inf, never NaN): a ray lying in a face
 * plane counts as inside, as the closed box demands.  (fmax / fmin would do
 * the same but cost x86 a NaN test and a blend each: 1.03-1.14x on both ray
 * kinds, A/B.)  Returns, per lane, whether [entry, exit] meets [tmin, limit]
 * (-1 or 0), and the entry distances.  An unused slot's empty box
 * (lo = +inf, hi = -inf) is missed by every ray: its entry is +inf and its
 * exit -inf, whatever the direction's signs; so no lane checks for
 * EMPTY_CHILD (which measured 1.04-1.10x slower on camera rays). */
TRAVERSAL_INLINE int_lanes hit_children(const RayData* r, __global const WideNode* node,
                                        float limit, float_lanes* entry)
{
    float_lanes near_x = (LOAD_ROW(float_lanes, plane_row(node, r->near_x)) - r->ox) * r->inv_x;
    float_lanes near_y = (LOAD_ROW(float_lanes, plane_row(node, r->near_y)) - r->oy) * r->inv_y;
    float_lanes near_z = (LOAD_ROW(float_lanes, plane_row(node, r->near_z)) - r->oz) * r->inv_z;
    float_lanes far_x = (LOAD_ROW(float_lanes, plane_row(node, r->near_x ^ ROW_BYTES)) - r->ox)
                          * r->inv_x;
    float_lanes far_y = (LOAD_ROW(float_lanes, plane_row(node, r->near_y ^ ROW_BYTES)) - r->oy)
                          * r->inv_y;
    float_lanes far_z = (LOAD_ROW(float_lanes, plane_row(node, r->near_z ^ ROW_BYTES)) - r->oz)
                          * r->inv_z;
    return slabs_meet(near_x, near_y, near_z, far_x, far_y, far_z, r->tmin, limit, entry);
}

/* x86's sign-bit mask of 8 floats (vmovmskps), where the OpenCL compiler is
 * a Clang that exposes it (PoCL's CPU device; Intel's CPU runtime does not). */
#if HAS_BUILTIN(__builtin_ia32_movmskps256)
#define HAVE_MOVMSKPS256
#endif

/* The lanes set in `hit` (-1) as a bit mask: bit c for child c.  One
 * movmskps where the compiler offers it: the portable fold below is a chain
 * of six dependent instructions on every node step (A/B on PoCL: incoherent
 * rays 1.03-1.08x, camera rays 1.02-1.03x). */
TRAVERSAL_INLINE uint lane_mask(int_lanes hit)
{
#if defined(HAVE_MOVMSKPS256) && WIDE_ARITY == 8
    return (uint)__builtin_ia32_movmskps256(as_float8(hit));
#else
#if WIDE_ARITY == 8
    int8 bits = hit & (int8)(1, 2, 4, 8, 16, 32, 64, 128);
    int4 folded = bits.lo | bits.hi;
#else
    int4 folded = hit & (int4)(1, 2, 4, 8);
#endif
    int2 quarter = folded.lo | folded.hi;
    return (uint)(quarter.x | quarter.y);
#endif
}

/* The lowest set bit's position (mask != 0) and the number of set bits of a
 * child mask: one tzcnt / popcnt where the compiler is a Clang, else plain
 * arithmetic (ctz is OpenCL 2.0, and Oclgrind cannot run popcount()). */
#if HAS_BUILTIN(__builtin_ctz) && HAS_BUILTIN(__builtin_popcount)
#define HAVE_BIT_BUILTINS
#endif

/* Whether a non-zero mask has one bit set.  LLVM turns the classic test
 * into llvm.ctpop, which Oclgrind cannot run, hence the plain spelling. */
#ifdef PLAIN_OPENCL
#define ONE_BIT(mask) (bit_count(mask) == 1)
#else
#define ONE_BIT(mask) (((mask) & ((mask) - 1u)) == 0)
#endif

TRAVERSAL_INLINE int lowest_slot(uint mask)
{
#ifdef HAVE_BIT_BUILTINS
    return __builtin_ctz(mask);
#else
    return 31 - (int)clz(mask & (0u - mask));
#endif
}

TRAVERSAL_INLINE int bit_count(uint mask)
{
#ifdef HAVE_BIT_BUILTINS
    return __builtin_popcount(mask);
#else
    /* Masks hold WIDE_ARITY <= 8 bits: two nibbles, each counted by a
     * lookup in a 64-bit constant (a form LLVM does not turn back into
     * llvm.ctpop, which Oclgrind cannot run). */
    const ulong nibble_bits = 0x4332322132212110ul;
    return (int)(((nibble_bits >> (4u * (mask & 15u))) & 15u)
                 + ((nibble_bits >> (4u * ((mask >> 4) & 15u))) & 15u));
#endif
}

/* cross(v1 - v0, v2 - v0): unnormalised, following the winding. */
TRAVERSAL_INLINE void geometric_normal(__global const Triangle* tri, float* nx, float* ny,
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
 * still decides inside/outside (watertightness).  refine_t and the packet
 * path evaluate the same expressions in the same order (no contraction,
 * FP_CONTRACT OFF above), so single rays and packets give identical t. */
#define REFINE_NUM(vx, vy, vz, ox, oy, oz, nx, ny, nz) \
    ((((vx) - (ox)) * (nx) + ((vy) - (oy)) * (ny)) + ((vz) - (oz)) * (nz))
#define REFINE_DEN(dx, dy, dz, nx, ny, nz) (((dx) * (nx) + (dy) * (ny)) + (dz) * (nz))

/* The triangle's first vertex and its plane's normal cross(v1 - v0, v2 - v0)
 * in double, for refine_t and its packet form. */
TRAVERSAL_INLINE void plane_double(__global const Triangle* tri, double* v0, double* n)
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

TRAVERSAL_INLINE float refine_t(const RayData* r, __global const Triangle* tri)
{
    double v0[3], n[3];
    plane_double(tri, v0, n);
    double num = REFINE_NUM(v0[0], v0[1], v0[2], (double)r->ox, (double)r->oy, (double)r->oz,
                            n[0], n[1], n[2]);
    double den = REFINE_DEN((double)r->dx, (double)r->dy, (double)r->dz, n[0], n[1], n[2]);
    /* den == 0 (zero area, or parallel in double) gives inf or NaN, which
     * the caller rejects. */
    return (float)(num / den);
}
#endif

/* Watertight ray/triangle test: Woop, Benthin & Wald 2013, "Watertight
 * Ray/Triangle Intersection" (JCGT 2(1)), without back-face culling.
 * On a hit with tmin <= t <= limit (t < limit when `strict`), writes t, u, v. */
TRAVERSAL_INLINE bool hit_triangle(const RayData* r, __global const Triangle* tri, float limit,
                                   bool strict, float* t_out, float* u_out, float* v_out)
{
    /* Vertices relative to the origin, permuted (kx, ky, kz). */
    float ax = tri->v0[r->kx] - r->okx, ay = tri->v0[r->ky] - r->oky, az = tri->v0[r->kz] - r->okz;
    float bx = tri->v1[r->kx] - r->okx, by = tri->v1[r->ky] - r->oky, bz = tri->v1[r->kz] - r->okz;
    float cx = tri->v2[r->kx] - r->okx, cy = tri->v2[r->ky] - r->oky, cz = tri->v2[r->kz] - r->okz;
    /* Shear so that the ray runs along +z. */
    ax = ax - r->sx * az;  ay = ay - r->sy * az;
    bx = bx - r->sx * bz;  by = by - r->sy * bz;
    cx = cx - r->sx * cz;  cy = cy - r->sy * cz;
    /* Scaled barycentrics: 2D edge functions at the ray (0, 0). */
    float e_u = cx * by - cy * bx;
    float e_v = ax * cy - ay * cx;
    float e_w = bx * ay - by * ax;
#ifdef cl_khr_fp64
    /* An edge function of exactly 0 may be rounding: redo the three in double,
     * where the products of floats are exact (as the paper does).  Without
     * fp64 a 0 stays 0, i.e. "on the edge", and the ray hits both triangles
     * that share it: never a crack, at worst a tie. */
    if (e_u == 0.0f || e_v == 0.0f || e_w == 0.0f) {
        e_u = (float)((double)cx * (double)by - (double)cy * (double)bx);
        e_v = (float)((double)ax * (double)cy - (double)ay * (double)cx);
        e_w = (float)((double)bx * (double)ay - (double)by * (double)ax);
    }
#endif
    /* No culling: inside when the three have the same sign (0 on an edge).
     * Bitwise | and & rather than || and &&: one branch instead of up to
     * six, which the sign pattern of rejected triangles mispredicts
     * (measured 1.1x on camera rays, PoCL). */
    if (((e_u < 0.0f) | (e_v < 0.0f) | (e_w < 0.0f)) & ((e_u > 0.0f) | (e_v > 0.0f) | (e_w > 0.0f)))
        return false;
    float det = e_u + e_v + e_w;
    if (det == 0.0f)
        return false;
    float inv_det = 1.0f / det;
#ifdef cl_khr_fp64
    float t = refine_t(r, tri);
#else
    float t = (e_u * (r->sz * az) + e_v * (r->sz * bz) + e_w * (r->sz * cz)) * inv_det;
#endif
    /* Written so that a NaN t fails; an infinite t (tmax = inf) too. */
    if (!(t >= r->tmin && ABS_FLOAT(t) < INFINITY && (strict ? t < limit : t <= limit)))
        return false;
    /* A zero-area triangle can still give det != 0 after rounding the shear;
     * never report it (its normal is undefined).  Only accepted hits pay. */
    float nx, ny, nz;
    geometric_normal(tri, &nx, &ny, &nz);
    if (nx == 0.0f && ny == 0.0f && nz == 0.0f)
        return false;
    *t_out = t;
    /* e_v / det rounds to at most 1 + ulp, and to NaN when det overflows or
     * underflows: clamp (fmax maps NaN to 0) so u, v stay in [0, 1]. */
    *u_out = fmin(fmax(e_v * inv_det, 0.0f), 1.0f);
    *v_out = fmin(fmax(e_w * inv_det, 0.0f), 1.0f);
    return true;
}

/* A stacked child slot: (index, count) as in WideNode, and the distance at
 * which the ray enters its box.  One array of these rather than one per
 * field: one base address for the compiler to keep (A/B on PoCL, bunny
 * incoherent rays 1.06x, elsewhere 0.99-1.02x). */
typedef struct {
    int index;
    uint count;
    float entry;
} StackItem;

/* The distances at which a ray or packet enters a node's children, one lane
 * per child: as a vector for the compares, as floats for single children.  A
 * union rather than vstore8 (PoCL: see LOAD_ROW). */
typedef union {
    float_lanes lanes;
    float slot[WIDE_ARITY];
} ChildEntries;

/* Pops the next stacked item that can still hold a hit within limit (items
 * whose box is entered beyond it are dropped); false when none is left. */
TRAVERSAL_INLINE bool pop(const StackItem* stack, int* sp, float limit, int* index, uint* count)
{
    while (*sp > 0) {
        --*sp;
        if (stack[*sp].entry <= limit) {
            *index = stack[*sp].index;
            *count = stack[*sp].count;
            return true;
        }
    }
    return false;
}

/* Asks the CPU to start loading the node or the leaf's triangles behind
 * child `slot` of n, which the ray or packet visits now or after a pop:
 * traversal waits on such loads (sampled: about half the time of incoherent
 * rays).  Measured: packets of 1280x720 camera rays on 3.6M triangles 62 ->
 * 56 ms (prefetching only the nodes or only the triangles gained less), 2K
 * triangles unchanged; single incoherent rays 1.01-1.08x.  Four lines, at
 * the first byte, 64 and 128 bytes on and the last byte (a node's four
 * lines; every line of a leaf of up to 5 triangles, 180 bytes, as no two
 * points lie more than a line apart; of bigger leaves most), without a
 * loop: its exit branch mispredicted (bunny, incoherent rays 1.04x, A/B).
 * Without PREFETCH (GPUs) it does nothing. */
TRAVERSAL_INLINE void prefetch_child(__global const WideNode* n, int slot,
                                     __global const WideNode* nodes,
                                     __global const Triangle* triangles)
{
#ifdef PREFETCH
    uint count = n->count[slot];
    __global const char* first = count == 0 ? (__global const char*)(nodes + n->child[slot])
                                            : (__global const char*)(triangles + n->child[slot]);
    uint last = (count == 0 ? (uint)sizeof(WideNode) : count * (uint)sizeof(Triangle)) - 1u;
    __builtin_prefetch(first);
    __builtin_prefetch(first + LESSER(64u, last));
    __builtin_prefetch(first + LESSER(128u, last));
    __builtin_prefetch(first + last);
#endif
}

/* A closest hit's ids (refs[i]) are read when the traversal ends, a cache
 * miss of their own: start loading them when the hit is found. */
TRAVERSAL_INLINE void prefetch_hit_ids(__global const TriangleRef* refs, uint i, bool any_hit)
{
#ifdef PREFETCH
    if (!any_hit)
        __builtin_prefetch(refs + i);
#endif
}

/* Pushes the children in `mask` (three or more) in order of decreasing
 * entry, ties in reverse slot order, so that pops take them nearest first
 * and ties in slot order; prefetches each.  The stack may hold one item
 * more than STACK_SIZE until the caller pops the nearest.
 *
 * Where a lane mask is one instruction (movmskps, see lane_mask), each child
 * goes straight to its place, counted from the first pushed: the number of
 * met children that are farther, or as far in a later slot, from one
 * vector compare pair and a popcount.  The insertion sort (the other branch)
 * mispredicts its data-dependent loop exits: A/B on PoCL, incoherent rays
 * teapot 1.07-1.10x, bunny 1.04x, reference scene 1.03x, camera rays
 * 1.02-1.03x.  Intel's CPU runtime, whose lane mask is a chain of six
 * instructions, ran camera rays 0.93-0.97x that way, so it keeps the sort. */
TRAVERSAL_INLINE void push_sorted(__global const WideNode* n, uint mask,
                                  const ChildEntries* entries, __global const WideNode* nodes,
                                  __global const Triangle* triangles, StackItem* stack, int* sp)
{
    int first = *sp;
#if defined(HAVE_MOVMSKPS256) && WIDE_ARITY == 8
    *sp += bit_count(mask);
    for (uint rest = mask; rest != 0; rest &= rest - 1u) {
        int slot = lowest_slot(rest);
        prefetch_child(n, slot, nodes, triangles);
        float e = entries->slot[slot];
        uint deeper = lane_mask(entries->lanes > (float_lanes)(e))
                      | (lane_mask(entries->lanes == (float_lanes)(e)) & (0u - (2u << slot)));
        stack[first + bit_count(deeper & mask)] = (StackItem){n->child[slot], n->count[slot], e};
    }
#else
    for (uint rest = mask; rest != 0; rest &= rest - 1u) {
        int slot = lowest_slot(rest);
        prefetch_child(n, slot, nodes, triangles);
        float e = entries->slot[slot];
        int at = *sp;
        for (; at > first && stack[at - 1].entry <= e; --at)
            stack[at] = stack[at - 1];
        stack[at] = (StackItem){n->child[slot], n->count[slot], e};
        ++*sp;
    }
#endif
}

/* What follows a node whose children in `mask` the ray or packet meets, at
 * the distances in `entries`: the nearest child, the others pushed and all
 * of them prefetched, or when none is met the next stacked item in reach of
 * `limit`.  Returns NEXT_ITEM (in *index, *count), NO_ITEM (the stack ran
 * out) or STACK_FULL.
 *
 * One child met is the common case and touches no stack, two need one
 * comparison, more are pushed sorted (push_sorted; Embree's BVH8 single-ray
 * traversal pushes them and sorts them in place).  The children are taken
 * from the mask's set bits: a branch per child slot instead mispredicted on
 * incoherent rays (perf: a third of their time).  The order is the order
 * of increasing entry, ties in slot order. */
#define NEXT_ITEM 0
#define NO_ITEM 1
#define STACK_FULL 2
TRAVERSAL_INLINE int next_item(__global const WideNode* n, uint mask,
                               const ChildEntries* entries,
                               __global const WideNode* nodes,
                               __global const Triangle* triangles, StackItem* stack, int* sp,
                               float limit, int* index, uint* count)
{
    if (mask == 0)
        return pop(stack, sp, limit, index, count) ? NEXT_ITEM : NO_ITEM;
    const float* entry = entries->slot;
    int near = lowest_slot(mask);
    mask &= mask - 1u;
    if (*sp + bit_count(mask) > STACK_SIZE)
        return STACK_FULL;
    if (mask == 0) {
        prefetch_child(n, near, nodes, triangles);
    } else if (ONE_BIT(mask)) {
        /* two: push the farther */
        int far = lowest_slot(mask);
        prefetch_child(n, near, nodes, triangles);
        prefetch_child(n, far, nodes, triangles);
        if (entry[far] < entry[near]) {
            int nearer = far;
            far = near;
            near = nearer;
        }
        stack[*sp] = (StackItem){n->child[far], n->count[far], entry[far]};
        ++*sp;
    } else {
        /* three or more: all pushed, sorted so that the nearest is on top */
        mask |= 1u << near;
        push_sorted(n, mask, entries, nodes, triangles, stack, sp);
        --*sp;
        *index = stack[*sp].index;
        *count = stack[*sp].count;
        return NEXT_ITEM;
    }
    *index = n->child[near];
    *count = n->count[near];
    return NEXT_ITEM;
}

/* Traverses the wide tree, nearer children first (closest hit) or until the
 * first hit (any hit).  Returns the tree-order index of the hit triangle or
 * -1; sets *overflow when the stack was too small (the host then raises).
 *
 * A stack item is a child slot: (index, count) with count 0 for an interior
 * node and count > 0 for a leaf, and the distance at which the ray enters its
 * box.  At a wide node the children whose boxes the ray meets are sorted by
 * that distance; the nearest is visited next and the others are pushed, the
 * farthest first (Embree's single-ray BVH4/BVH8 traversal); any-hit rays
 * too, as the nearer boxes hold an occluder sooner (measured faster on
 * incoherent rays).  The loop runs interior nodes until it holds a leaf, then
 * the leaf's triangles (Aila & Laine 2009's "while-while"). */
TRAVERSAL_INLINE int traverse(const RayData* r, __global const WideNode* nodes,
                              __global const Triangle* triangles,
                              __global const TriangleRef* refs, bool any_hit,
                              float* t_hit, float* u_hit, float* v_hit, bool* overflow)
{
    StackItem stack[STACK_SIZE + 1];  /* + 1: see next_item */
    int sp = 0;
    int hit_index = -1;
    float limit = r->tmax;     /* shrinks to the nearest hit so far */
    int index = 0;             /* the root is always an interior node */
    uint count = 0;
    bool done = false;
    *overflow = false;

    while (!done) {
        while (!done && count == 0) {
            __global const WideNode* n = nodes + index;
            ChildEntries entry;
            uint mask = lane_mask(hit_children(r, n, limit, &entry.lanes));
            if (any_hit) {
                /* Shadow rays: any hit ends the ray, so test the leaves in
                 * reach before descending (a large occluder such as a
                 * ground quad often sits in a leaf near the root). */
                int_lanes counts = LOAD_ROW(int_lanes, n->count);
                uint leaves = mask & lane_mask(counts != (int_lanes)(0));
                mask ^= leaves;
                for (; leaves != 0; leaves &= leaves - 1u) {
                    int slot = lowest_slot(leaves);
                    int first = n->child[slot];
                    for (int i = first; i < first + (int)n->count[slot]; ++i) {
                        float t, u, v;
                        if (hit_triangle(r, triangles + i, limit, false, &t, &u, &v)) {
                            *t_hit = t;
                            *u_hit = u;
                            *v_hit = v;
                            return i;
                        }
                    }
                }
            }
            int next = next_item(n, mask, &entry, nodes, triangles, stack, &sp, limit, &index,
                                 &count);
            if (next == STACK_FULL) {
                *overflow = true;
                return hit_index;
            }
            done = next == NO_ITEM;
        }
        if (done)
            break;
        for (uint i = (uint)index; i < (uint)index + count; ++i) {
            float t, u, v;
            if (hit_triangle(r, triangles + i, limit, hit_index >= 0, &t, &u, &v)) {
                prefetch_hit_ids(refs, i, any_hit);
                hit_index = (int)i;
                limit = t;
                *t_hit = t;
                *u_hit = u;
                *v_hit = v;
                if (any_hit)
                    return hit_index;
            }
        }
        done = !pop(stack, &sp, limit, &index, &count);
    }
    return hit_index;
}


/* ---------------------------------------------------------------- packets
 * Coherent rays (camera rays, shadow rays towards one light) visit nearly the
 * same nodes, so one work-item traces PACKET_SIZE consecutive rays together,
 * one vector lane per ray: the node walk, the stack and the child sort are
 * paid once per packet instead of once per ray, and each box and triangle is
 * tested against all the rays at once (Wald, Slusallek, Benthin & Wagner 2001,
 * "Interactive Rendering with Coherent Ray Tracing"; on BVHs Wald, Boulos &
 * Shirley 2007).  A packet is traced this way only when its rays share the
 * signs of their direction components and the axis the watertight test
 * projects along (kz): then every plane offset and vertex permutation is the
 * same for all lanes and stays scalar.  Other packets (incoherent rays)
 * trace their rays one by one with the single-ray traversal above; the lanes
 * of a packet computed either way give the same hits (ties aside), as each
 * lane runs the single-ray arithmetic. */
#if PACKET_SIZE > 1
#if PACKET_SIZE == 16
typedef float16 float_packet;
typedef int16 int_packet;
#define vload_packet vload16
#define vstore_packet vstore16
#define as_int_packet as_int16
#define as_float_packet as_float16
#ifdef cl_khr_fp64
#define convert_double_packet convert_double16
#define convert_float_packet convert_float16
typedef double16 double_packet;
#endif
#elif PACKET_SIZE == 8
typedef float8 float_packet;
typedef int8 int_packet;
#define vload_packet vload8
#define vstore_packet vstore8
#define as_int_packet as_int8
#define as_float_packet as_float8
#ifdef cl_khr_fp64
#define convert_double_packet convert_double8
#define convert_float_packet convert_float8
typedef double8 double_packet;
#endif
#else
#error "PACKET_SIZE must be 8 or 16"
#endif

/* RayData of PACKET_SIZE rays, one lane each, with the fields the packet
 * shares kept scalar. */
typedef struct {
    float_packet ox, oy, oz;
#ifdef cl_khr_fp64
    float_packet dx, dy, dz;  /* direction, for refine_t */
#endif
    float_packet inv_x, inv_y, inv_z;
    float_packet tmin, tmax;
    float_packet sx, sy, sz;
    float_packet okx, oky, okz;
    int kx, ky, kz;
    int near_x, near_y, near_z;
    /* The packet as one interval ray, for culling a node's children with
     * interval arithmetic before the per-lane tests (hit_children_interval):
     * per axis the lanes' least and greatest inverse direction, and the
     * origin component that bounds the entry (near_o) and the exit (far_o)
     * distances from below and above; the least tmin. */
    float inv_lo_x, inv_lo_y, inv_lo_z, inv_hi_x, inv_hi_y, inv_hi_z;
    float near_ox, near_oy, near_oz, far_ox, far_oy, far_oz;
    float tmin_lo;
} Packet;

/* The least / greatest lane of a packet whose lanes are never NaN (entry
 * distances, limits): GROW_LO / GROW_HI, without fmin / fmax's NaN tests. */
TRAVERSAL_INLINE float packet_min(float_packet v)
{
#if PACKET_SIZE == 16
    float8 a = GROW_LO(v.lo, v.hi);
#else
    float8 a = v;
#endif
    float4 b = GROW_LO(a.lo, a.hi);
    float2 c = GROW_LO(b.lo, b.hi);
    return GROW_LO(c.x, c.y);
}

TRAVERSAL_INLINE float packet_max(float_packet v)
{
#if PACKET_SIZE == 16
    float8 a = GROW_HI(v.lo, v.hi);
#else
    float8 a = v;
#endif
    float4 b = GROW_HI(a.lo, a.hi);
    float2 c = GROW_HI(b.lo, b.hi);
    return GROW_HI(c.x, c.y);
}

/* any() of a packet's lane flags (-1 or 0) as one test: the halves are
 * folded with | first, then one movmskps where there is one (A/B on PoCL,
 * camera rays 1.01-1.05x with packet_all's), else | down to one lane.
 * (PoCL's any() tests lane by lane, a branch each, which mispredicted in
 * the child loop of camera-ray packets.) */
TRAVERSAL_INLINE bool packet_any(int_packet v)
{
#if PACKET_SIZE == 16
    int8 a = v.lo | v.hi;
#else
    int8 a = v;
#endif
#ifdef HAVE_MOVMSKPS256
    return __builtin_ia32_movmskps256(as_float8(a)) != 0;
#else
    int4 b = a.lo | a.hi;
    int2 c = b.lo | b.hi;
    return (c.x | c.y) < 0;
#endif
}

/* all() of a packet's lane flags, folded the same way. */
TRAVERSAL_INLINE bool packet_all(int_packet v)
{
#if PACKET_SIZE == 16
    int8 a = v.lo & v.hi;
#else
    int8 a = v;
#endif
#ifdef HAVE_MOVMSKPS256
    return __builtin_ia32_movmskps256(as_float8(a)) == 0xff;
#else
    int4 b = a.lo & a.hi;
    int2 c = b.lo & b.hi;
    return (c.x & c.y) < 0;
#endif
}

/* prepare_ray for every lane, in vector arithmetic; false when the lanes do
 * not share direction signs and kz (then they are traced one by one). */
TRAVERSAL_INLINE bool prepare_packet(const RayLanes* in, Packet* p)
{
    float_packet o[3], d[3];
    for (int k = 0; k < 3; ++k) {
        o[k] = vload_packet(0, in->origin[k]);
        d[k] = vload_packet(0, in->direction[k]);
    }
    /* fabs, signbit and select by bits and ?: (PoCL: see LOAD_ROW) */
    int_packet magnitude = (int_packet)(0x7fffffff);
    float_packet ax = as_float_packet(as_int_packet(d[0]) & magnitude),
                 ay = as_float_packet(as_int_packet(d[1]) & magnitude),
                 az = as_float_packet(as_int_packet(d[2]) & magnitude);
    /* Each lane's kz, as prepare_ray picks it, held in floats: LLVM makes
     * ?: between integer constants a zext of the compare lanes, which
     * Oclgrind gets wrong (its vector compares give -1 per true lane). */
    float_packet kz = ((ax >= ay) & (ax >= az)) ? (float_packet)(0.0f)
                      : (ay >= az ? (float_packet)(1.0f) : (float_packet)(2.0f));
    int_packet neg_x = as_int_packet(d[0]) < 0, neg_y = as_int_packet(d[1]) < 0,
               neg_z = as_int_packet(d[2]) < 0;
    if (packet_any((kz != (float_packet)(kz.s0)) | (neg_x != (int_packet)(neg_x.s0))
            | (neg_y != (int_packet)(neg_y.s0)) | (neg_z != (int_packet)(neg_z.s0))))
        return false;
    p->kz = (int)kz.s0;
    p->kx = p->kz == 2 ? 0 : p->kz + 1;
    p->ky = p->kx == 2 ? 0 : p->kx + 1;
    p->ox = o[0];
    p->oy = o[1];
    p->oz = o[2];
#ifdef cl_khr_fp64
    p->dx = d[0];
    p->dy = d[1];
    p->dz = d[2];
#endif
    p->inv_x = 1.0f / d[0];
    p->inv_y = 1.0f / d[1];
    p->inv_z = 1.0f / d[2];
    p->tmin = vload_packet(0, in->tmin);
    p->tmax = vload_packet(0, in->tmax);
    float_packet dkz = d[p->kz];
    p->sx = d[p->kx] / dkz;
    p->sy = d[p->ky] / dkz;
    p->sz = 1.0f / dkz;
    p->okx = o[p->kx];
    p->oky = o[p->ky];
    p->okz = o[p->kz];
    p->near_x = LO_X_ROW + (neg_x.s0 ? ROW_BYTES : 0);
    p->near_y = LO_Y_ROW + (neg_y.s0 ? ROW_BYTES : 0);
    p->near_z = LO_Z_ROW + (neg_z.s0 ? ROW_BYTES : 0);
    p->inv_lo_x = packet_min(p->inv_x);
    p->inv_lo_y = packet_min(p->inv_y);
    p->inv_lo_z = packet_min(p->inv_z);
    p->inv_hi_x = packet_max(p->inv_x);
    p->inv_hi_y = packet_max(p->inv_y);
    p->inv_hi_z = packet_max(p->inv_z);
    /* (plane - o) * inv over the lanes: the least entry comes from the
     * greatest origin when the direction is positive, the least when it is
     * negative; the greatest exit the other way round. */
    float o_lo_x = packet_min(o[0]), o_lo_y = packet_min(o[1]), o_lo_z = packet_min(o[2]);
    float o_hi_x = packet_max(o[0]), o_hi_y = packet_max(o[1]), o_hi_z = packet_max(o[2]);
    p->near_ox = neg_x.s0 ? o_lo_x : o_hi_x;
    p->near_oy = neg_y.s0 ? o_lo_y : o_hi_y;
    p->near_oz = neg_z.s0 ? o_lo_z : o_hi_z;
    p->far_ox = neg_x.s0 ? o_hi_x : o_lo_x;
    p->far_oy = neg_y.s0 ? o_hi_y : o_lo_y;
    p->far_oz = neg_z.s0 ? o_hi_z : o_lo_z;
    p->tmin_lo = packet_min(p->tmin);
    return true;
}

/* A bound, from below (entry) or above (exit), of (plane - o) * inv over
 * the packet's lanes for each child: `offset` (plane - o) is the bounding
 * origin's, and the factor is the end of [inv_lo, inv_hi] that makes the
 * product least (entry: inv_lo where the offset is >= 0, else inv_hi) or
 * greatest (exit: the other end).  Both signs of the direction follow the
 * same rule (prepare_packet picks the origin). */
TRAVERSAL_INLINE float_lanes entry_bound(float_lanes offset, float inv_lo, float inv_hi)
{
    return offset * (offset >= 0.0f ? (float_lanes)(inv_lo) : (float_lanes)(inv_hi));
}

TRAVERSAL_INLINE float_lanes exit_bound(float_lanes offset, float inv_lo, float inv_hi)
{
    return offset * (offset >= 0.0f ? (float_lanes)(inv_hi) : (float_lanes)(inv_lo));
}

/* The children of a node that some lane of the packet may meet within
 * `reach`, as a bit mask, from one slab test of the interval ray (interval
 * arithmetic over the lanes: Boulos et al. 2007, "Geometric and Arithmetic
 * Culling Methods for Entire Ray Packets").  Float rounding is monotone, so
 * each bound is as far out as the per-lane results computed the same way:
 * a child left out here fails hit_child_packet for every lane, and the
 * culling changes no result.  A NaN (0 * inf) bound is ignored, as in
 * hit_children, which only widens the interval. */
TRAVERSAL_INLINE uint hit_children_interval(const Packet* p, __global const WideNode* node,
                                            float reach)
{
    float_lanes near_x = entry_bound(LOAD_ROW(float_lanes, plane_row(node, p->near_x))
                                     - p->near_ox, p->inv_lo_x, p->inv_hi_x);
    float_lanes near_y = entry_bound(LOAD_ROW(float_lanes, plane_row(node, p->near_y))
                                     - p->near_oy, p->inv_lo_y, p->inv_hi_y);
    float_lanes near_z = entry_bound(LOAD_ROW(float_lanes, plane_row(node, p->near_z))
                                     - p->near_oz, p->inv_lo_z, p->inv_hi_z);
    float_lanes far_x = exit_bound(LOAD_ROW(float_lanes, plane_row(node, p->near_x ^ ROW_BYTES))
                                   - p->far_ox, p->inv_lo_x, p->inv_hi_x);
    float_lanes far_y = exit_bound(LOAD_ROW(float_lanes, plane_row(node, p->near_y ^ ROW_BYTES))
                                   - p->far_oy, p->inv_lo_y, p->inv_hi_y);
    float_lanes far_z = exit_bound(LOAD_ROW(float_lanes, plane_row(node, p->near_z ^ ROW_BYTES))
                                   - p->far_oz, p->inv_lo_z, p->inv_hi_z);
    float_lanes entry;
    return lane_mask(slabs_meet(near_x, near_y, near_z, far_x, far_y, far_z, p->tmin_lo, reach,
                                &entry));
}

/* hit_children's slab test of child c of a node for every lane: which lanes
 * meet its box within their limit, and where they enter it. */
TRAVERSAL_INLINE int_packet hit_child_packet(const Packet* p, __global const WideNode* node, int c,
                                             float_packet limit, float_packet* t_entry)
{
    float_packet near_x = (plane_row(node, p->near_x)[c] - p->ox) * p->inv_x;
    float_packet near_y = (plane_row(node, p->near_y)[c] - p->oy) * p->inv_y;
    float_packet near_z = (plane_row(node, p->near_z)[c] - p->oz) * p->inv_z;
    float_packet far_x = (plane_row(node, p->near_x ^ ROW_BYTES)[c] - p->ox) * p->inv_x;
    float_packet far_y = (plane_row(node, p->near_y ^ ROW_BYTES)[c] - p->oy) * p->inv_y;
    float_packet far_z = (plane_row(node, p->near_z ^ ROW_BYTES)[c] - p->oz) * p->inv_z;
    *t_entry = GROW_HI(GROW_HI(GROW_HI(p->tmin, near_x), near_y), near_z);
    float_packet t_exit = GROW_LO(GROW_LO(GROW_LO((float_packet)(INFINITY), far_x), far_y), far_z)
                          * EXIT_SCALE;
    return *t_entry <= GROW_LO(t_exit, limit);
}

/* hit_triangle for every lane: the same arithmetic per lane.  Returns the
 * lanes that hit (-1), with their t, u, v in *t_out, *u_out, *v_out. */
TRAVERSAL_INLINE int_packet hit_triangle_packet(const Packet* p, __global const Triangle* tri,
                                                float_packet limit, int_packet strict,
                                                float_packet* t_out, float_packet* u_out,
                                                float_packet* v_out)
{
    float_packet ax = tri->v0[p->kx] - p->okx, ay = tri->v0[p->ky] - p->oky,
                 az = tri->v0[p->kz] - p->okz;
    float_packet bx = tri->v1[p->kx] - p->okx, by = tri->v1[p->ky] - p->oky,
                 bz = tri->v1[p->kz] - p->okz;
    float_packet cx = tri->v2[p->kx] - p->okx, cy = tri->v2[p->ky] - p->oky,
                 cz = tri->v2[p->kz] - p->okz;
    ax = ax - p->sx * az;  ay = ay - p->sy * az;
    bx = bx - p->sx * bz;  by = by - p->sy * bz;
    cx = cx - p->sx * cz;  cy = cy - p->sy * cz;
    float_packet e_u = cx * by - cy * bx;
    float_packet e_v = ax * cy - ay * cx;
    float_packet e_w = bx * ay - by * ax;
#ifdef cl_khr_fp64
    int_packet on_edge = (e_u == 0.0f) | (e_v == 0.0f) | (e_w == 0.0f);
    if (packet_any(on_edge)) {
        double_packet dax = convert_double_packet(ax), day = convert_double_packet(ay);
        double_packet dbx = convert_double_packet(bx), dby = convert_double_packet(by);
        double_packet dcx = convert_double_packet(cx), dcy = convert_double_packet(cy);
        e_u = on_edge ? convert_float_packet(dcx * dby - dcy * dbx) : e_u;
        e_v = on_edge ? convert_float_packet(dax * dcy - day * dcx) : e_v;
        e_w = on_edge ? convert_float_packet(dbx * day - dby * dax) : e_w;
    }
#endif
    /* hit_triangle's test that the three do not straddle 0, written as the
     * lanes where all three are >= 0 or all are <= 0.  It differs from
     * ~outside only in a lane with a NaN, whose t is then NaN and fails the
     * test of t below.  (~outside became an xor of the compare lanes with an i1
     * true vector, which Oclgrind gets wrong: its vector compares give -1
     * per true lane.) */
    int_packet inside = ((e_u >= 0.0f) & (e_v >= 0.0f) & (e_w >= 0.0f))
                        | ((e_u <= 0.0f) & (e_v <= 0.0f) & (e_w <= 0.0f));
    float_packet det = e_u + e_v + e_w;
    float_packet inv_det = 1.0f / det;
#ifdef cl_khr_fp64
    /* refine_t per lane (see there), only when some lane is inside. */
    int_packet hit = inside & (det != 0.0f);
    if (!packet_any(hit))
        return hit;
    float_packet t;
    {
        double v0[3], n[3];
        plane_double(tri, v0, n);
        double_packet num = REFINE_NUM((double_packet)(v0[0]), (double_packet)(v0[1]),
                                       (double_packet)(v0[2]), convert_double_packet(p->ox),
                                       convert_double_packet(p->oy),
                                       convert_double_packet(p->oz), n[0], n[1], n[2]);
        double_packet den = REFINE_DEN(convert_double_packet(p->dx), convert_double_packet(p->dy),
                                       convert_double_packet(p->dz), n[0], n[1], n[2]);
        t = convert_float_packet(num / den);
    }
#else
    int_packet hit;
    float_packet t = (e_u * (p->sz * az) + e_v * (p->sz * bz) + e_w * (p->sz * cz)) * inv_det;
#endif
    /* As hit_triangle: NaN and infinite t fail. */
    int_packet finite = as_int_packet(t) & (int_packet)(0x7fffffff);
    hit = inside & (det != 0.0f) & (t >= p->tmin) & (finite < (int_packet)(0x7f800000))
          & (strict ? t < limit : t <= limit);
    if (!packet_any(hit))
        return hit;
    float nx, ny, nz;
    geometric_normal(tri, &nx, &ny, &nz);
    if (nx == 0.0f && ny == 0.0f && nz == 0.0f)
        return (int_packet)(0);
    *t_out = t;
    *u_out = fmin(fmax(e_v * inv_det, (float_packet)(0.0f)), (float_packet)(1.0f));
    *v_out = fmin(fmax(e_w * inv_det, (float_packet)(0.0f)), (float_packet)(1.0f));
    return hit;
}

/* The triangles [first, first + count) of a leaf against every lane: a lane
 * takes a hit within its limit (limit, hit_index, t, u, v; as in traverse(),
 * at t == limit only while it has no hit yet) and `reach` follows.  For any
 * hit a lane that hits is done (its limit becomes -INFINITY, below every box
 * and triangle); returns true when every lane is. */
TRAVERSAL_INLINE bool hit_leaf_packet(const Packet* p, __global const Triangle* triangles,
                                      __global const TriangleRef* refs, int first, uint count,
                                      bool any_hit, float_packet* limit,
                                      float* reach, int_packet* hit_index, float_packet* t_hit,
                                      float_packet* u_hit, float_packet* v_hit)
{
    for (uint i = (uint)first; i < (uint)first + count; ++i) {
        float_packet t, u, v;
        int_packet hit = hit_triangle_packet(p, triangles + i, *limit, *hit_index >= 0, &t, &u,
                                             &v);
        if (!packet_any(hit))
            continue;
        prefetch_hit_ids(refs, i, any_hit);
        *hit_index = hit ? (int_packet)((int)i) : *hit_index;
        *limit = hit ? (any_hit ? (float_packet)(-INFINITY) : t) : *limit;
        *t_hit = hit ? t : *t_hit;
        *u_hit = hit ? u : *u_hit;
        *v_hit = hit ? v : *v_hit;
        *reach = packet_max(*limit);
        if (any_hit && packet_all(*hit_index >= 0))
            return true;
    }
    return false;
}

/* traverse() for a packet: returns each lane's tree-order hit triangle or -1
 * and its t, u, v.  Children are visited in the order of the nearest entry
 * over the lanes that hit them; a popped child is skipped when even that
 * entry lies beyond every lane's limit. */
TRAVERSAL_INLINE int_packet traverse_packet(const Packet* p, __global const WideNode* nodes,
                                            __global const Triangle* triangles,
                                            __global const TriangleRef* refs, bool any_hit,
                                            float_packet* t_hit, float_packet* u_hit,
                                            float_packet* v_hit, bool* overflow)
{
    StackItem stack[STACK_SIZE + 1];  /* + 1: see next_item */
    int sp = 0;
    int_packet hit_index = (int_packet)(-1);
    float_packet limit = p->tmax;
    float reach = packet_max(limit);  /* the farthest any lane still looks */
    int index = 0;
    uint count = 0;
    bool done = false;
    *overflow = false;

    while (!done) {
        while (!done && count == 0) {
            __global const WideNode* n = nodes + index;
            /* Lanes of children no lane meets stay +inf: push_sorted compares
             * whole vectors (and masks them). */
            ChildEntries entry = {(float_lanes)(INFINITY)};
            uint mask = 0;
            for (uint rest = hit_children_interval(p, n, reach); rest != 0; rest &= rest - 1u) {
                int c = lowest_slot(rest);
                float_packet t_entry;
                int_packet hit = hit_child_packet(p, n, c, limit, &t_entry);
                if (packet_any(hit)) {
                    entry.slot[c] = packet_min(hit ? t_entry : (float_packet)(INFINITY));
                    mask |= 1u << c;
                }
            }
            if (any_hit) {
                /* As traverse(): the leaves in reach first (shadow rays). */
                for (uint rest = mask; rest != 0; rest &= rest - 1u) {
                    int slot = lowest_slot(rest);
                    if (n->count[slot] == 0)
                        continue;
                    mask ^= 1u << slot;
                    if (hit_leaf_packet(p, triangles, refs, n->child[slot], n->count[slot], true,
                                        &limit, &reach, &hit_index, t_hit, u_hit, v_hit))
                        return hit_index;
                }
            }
            int next = next_item(n, mask, &entry, nodes, triangles, stack, &sp, reach, &index,
                                 &count);
            if (next == STACK_FULL) {
                *overflow = true;
                return hit_index;
            }
            done = next == NO_ITEM;
        }
        if (done)
            break;
        if (hit_leaf_packet(p, triangles, refs, index, count, any_hit, &limit, &reach, &hit_index,
                            t_hit, u_hit, v_hit))
            return hit_index;
        done = !pop(stack, &sp, reach, &index, &count);
    }
    return hit_index;
}
#endif /* PACKET_SIZE > 1 */

/* The kernels already compute in vectors (a node's children); the hint
 * keeps Intel's CPU compiler from also packing work-items into SIMD lanes,
 * which measured 3-4x slower at 16 work-items per group (its default is to
 * vectorise whenever the group size allows). */
#define TRAVERSAL_KERNEL __kernel __attribute__((LANES_HINT))

/* The unit geometric normal of a hit triangle.  Scaled by its largest
 * component first so that tiny or huge triangles neither underflow nor
 * overflow the squared length. */
TRAVERSAL_INLINE float3 unit_normal(__global const Triangle* tri)
{
    float nx, ny, nz;
    geometric_normal(tri, &nx, &ny, &nz);
    float largest = GROW_HI(GROW_HI(ABS_FLOAT(nx), ABS_FLOAT(ny)), ABS_FLOAT(nz));
    float3 n = (float3)(nx, ny, nz) * (1.0f / largest);
    return n * (1.0f / SQUARE_ROOT(n.x * n.x + n.y * n.y + n.z * n.z));
}

/* One ray's closest hit as a Hit record (a miss: t = INFINITY, ids -1, the
 * rest 0) from the tree-order index of the triangle hit (-1: none). */
TRAVERSAL_INLINE void make_hit(Hit* out, int index, float t, float u, float v,
                               __global const Triangle* triangles,
                               __global const TriangleRef* refs)
{
    bool found = index >= 0;
    Hit hit;
    hit.t = found ? t : INFINITY;
    hit.geom_id = found ? refs[index].geom_id : -1;
    hit.prim_id = found ? refs[index].prim_id : -1;
    hit.u = found ? u : 0.0f;
    hit.v = found ? v : 0.0f;
    float3 normal = found ? unit_normal(triangles + index) : (float3)(0.0f);
    hit.normal[0] = normal.x;
    hit.normal[1] = normal.y;
    hit.normal[2] = normal.z;
    *out = hit;
}

/* The two queries for the rays lanes[0, used), shared by the record kernels
 * and the array kernels: closest hits as Hit records, and any hit as 0 or 1.
 * With packets, the lanes are traced together when prepare_packet accepts them
 * and one by one otherwise; lanes[used, PACKET_SIZE) repeat lanes[used - 1]
 * (a packet pays nothing for them) and are not written.  overflow[0] is set
 * to 1 if a traversal ran out of stack. */
TRAVERSAL_INLINE void closest_hits(const RayLanes* lanes, uint used,
                                   __global const WideNode* nodes,
                                   __global const Triangle* triangles,
                                   __global const TriangleRef* refs, __global int* overflow,
                                   Hit* hits)
{
    bool out_of_stack = false;
#if PACKET_SIZE > 1
    Packet p;
    if (prepare_packet(lanes, &p)) {
#ifdef COUNT_PACKETS
        atomic_inc(overflow + 1);
#endif
        float_packet t = (float_packet)(INFINITY), u = (float_packet)(0.0f),
                     v = (float_packet)(0.0f);
        int index[PACKET_SIZE];
        float t_lanes[PACKET_SIZE], u_lanes[PACKET_SIZE], v_lanes[PACKET_SIZE];
        vstore_packet(traverse_packet(&p, nodes, triangles, refs, false, &t, &u, &v, &out_of_stack),
                      0, index);
        vstore_packet(t, 0, t_lanes);
        vstore_packet(u, 0, u_lanes);
        vstore_packet(v, 0, v_lanes);
        for (uint l = 0; l < used; ++l)
            make_hit(hits + l, index[l], t_lanes[l], u_lanes[l], v_lanes[l], triangles, refs);
        if (out_of_stack)
            overflow[0] = 1;
        return;
    }
#endif
    /* The hits' ids and normals are read once every lane is traced: their
     * cache misses then overlap instead of ending each ray (perf: the read
     * of refs took ~6% of the incoherent kernel; A/B 1.00-1.04x). */
    int index[PACKET_SIZE];
    float t[PACKET_SIZE], u[PACKET_SIZE], v[PACKET_SIZE];
    for (uint l = 0; l < used; ++l) {
        bool lane_out_of_stack;
        RayData r;
        prepare_lane(&r, lanes, l);
        t[l] = INFINITY;
        u[l] = v[l] = 0.0f;
        index[l] = traverse(&r, nodes, triangles, refs, false, t + l, u + l, v + l,
                            &lane_out_of_stack);
        out_of_stack |= lane_out_of_stack;
    }
    for (uint l = 0; l < used; ++l)
        make_hit(hits + l, index[l], t[l], u[l], v[l], triangles, refs);
    if (out_of_stack)
        overflow[0] = 1;
}

TRAVERSAL_INLINE void any_hits(const RayLanes* lanes, uint used, __global const WideNode* nodes,
                               __global const Triangle* triangles, __global int* overflow,
                               uchar* occluded)
{
    bool out_of_stack = false;
#if PACKET_SIZE > 1
    Packet p;
    if (prepare_packet(lanes, &p)) {
#ifdef COUNT_PACKETS
        atomic_inc(overflow + 1);
#endif
        float_packet t = (float_packet)(0.0f), u = t, v = t;  /* unused: any hit */
        int index[PACKET_SIZE];
        vstore_packet(traverse_packet(&p, nodes, triangles, 0, true, &t, &u, &v, &out_of_stack),
                      0, index);
        for (uint l = 0; l < used; ++l)
            occluded[l] = index[l] >= 0 ? 1 : 0;
        if (out_of_stack)
            overflow[0] = 1;
        return;
    }
#endif
    for (uint l = 0; l < used; ++l) {
        float t, u, v;
        bool lane_out_of_stack;
        RayData r;
        prepare_lane(&r, lanes, l);
        int index = traverse(&r, nodes, triangles, 0, true, &t, &u, &v, &lane_out_of_stack);
        occluded[l] = index >= 0 ? 1 : 0;
        out_of_stack |= lane_out_of_stack;
    }
    if (out_of_stack)
        overflow[0] = 1;
}

/* Work-item i traces rays [i * PACKET_SIZE, ...) : how many of them exist
 * (0 for the items past the end), and the first one. */
TRAVERSAL_INLINE uint packet_rays(uint ray_count, uint* first)
{
    *first = get_global_id(0) * PACKET_SIZE;
    return *first < ray_count ? LESSER((uint)PACKET_SIZE, ray_count - *first) : 0;
}

TRAVERSAL_INLINE void load_lanes_records(__global const Ray* rays, uint first, uint used,
                                         RayLanes* lanes)
{
    for (uint l = 0; l < PACKET_SIZE; ++l) {
        __global const Ray* ray = rays + first + LESSER(l, used - 1);
        set_lane(lanes, l, LOAD_XYZ(ray->origin), LOAD_XYZ(ray->direction), ray->tmin,
                 ray->tmax);
    }
}

/* Closest hit of rays[0, ray_count) -> hits (the renderer's records). */
TRAVERSAL_KERNEL void intersect_closest(__global const WideNode* nodes,
                                        __global const Triangle* triangles,
                                        __global const TriangleRef* refs,
                                        __global const Ray* rays,
                                        __global Hit* hits,
                                        __global int* overflow,
                                        const uint ray_count)
{
    uint first, used = packet_rays(ray_count, &first);
    if (used == 0)
        return;
    RayLanes lanes;
    load_lanes_records(rays, first, used, &lanes);
    Hit found[PACKET_SIZE];
    closest_hits(&lanes, used, nodes, triangles, refs, overflow, found);
    for (uint l = 0; l < used; ++l)
        hits[first + l] = found[l];
}

/* Occlusion of rays[0, ray_count): occluded[i] = 1 if anything is hit. */
TRAVERSAL_KERNEL void intersect_any(__global const WideNode* nodes,
                                    __global const Triangle* triangles,
                                    __global const Ray* rays,
                                    __global uchar* occluded,
                                    __global int* overflow,
                                    const uint ray_count)
{
    uint first, used = packet_rays(ray_count, &first);
    if (used == 0)
        return;
    RayLanes lanes;
    load_lanes_records(rays, first, used, &lanes);
    uchar found[PACKET_SIZE];
    any_hits(&lanes, used, nodes, triangles, overflow, found);
    for (uint l = 0; l < used; ++l)
        occluded[first + l] = found[l];
}

/* The same two queries on the arrays numpy users hand in and get back
 * (query.py): origins and directions packed (x, y, z) per ray, and one
 * array per result field, so that the host neither packs records nor picks
 * fields out of them (measured: that repacking took as long as tracing
 * camera rays).  tmin[i * tmin_step], tmax[i * tmax_step]: step 0 gives
 * every ray the same limit.  Lanes past `used` repeat the last ray. */
TRAVERSAL_INLINE void load_lanes_arrays(uint first, uint used, __global const float* origins,
                                        __global const float* directions,
                                        __global const float* tmin, uint tmin_step,
                                        __global const float* tmax, uint tmax_step,
                                        RayLanes* lanes)
{
#ifdef PREFETCH
    /* The next work-item's rays (CPUs run a group's items in order): between
     * two work-items' loads lie thousands of random reads, and the hardware
     * prefetcher loses the stream (A/B on PoCL, incoherent rays 1.01-1.02x).
     * Past the last ray this asks for memory the kernel never reads, which
     * a prefetch may: it never faults. */
    for (uint offset = 0; offset < 3 * PACKET_SIZE * sizeof(float); offset += 64) {
        __builtin_prefetch((__global const char*)(origins + 3 * (first + PACKET_SIZE)) + offset);
        __builtin_prefetch((__global const char*)(directions + 3 * (first + PACKET_SIZE)) + offset);
    }
#endif
    for (uint l = 0; l < PACKET_SIZE; ++l) {
        uint i = first + LESSER(l, used - 1);
        set_lane(lanes, l, LOAD_XYZ(origins + 3 * i), LOAD_XYZ(directions + 3 * i),
                 tmin[i * tmin_step], tmax[i * tmax_step]);
    }
}

TRAVERSAL_KERNEL void intersect_closest_arrays(__global const WideNode* nodes,
                                               __global const Triangle* triangles,
                                               __global const TriangleRef* refs,
                                               __global const float* origins,
                                               __global const float* directions,
                                               __global const float* tmin, const uint tmin_step,
                                               __global const float* tmax, const uint tmax_step,
                                               __global float* t_out, __global int* geom_out,
                                               __global int* prim_out, __global float* u_out,
                                               __global float* v_out, __global float* normal_out,
                                               __global int* overflow, const uint ray_count)
{
    uint first, used = packet_rays(ray_count, &first);
    if (used == 0)
        return;
    RayLanes lanes;
    load_lanes_arrays(first, used, origins, directions, tmin, tmin_step, tmax, tmax_step,
                      &lanes);
    Hit found[PACKET_SIZE];
    closest_hits(&lanes, used, nodes, triangles, refs, overflow, found);
    for (uint l = 0; l < used; ++l) {
        uint i = first + l;
        t_out[i] = found[l].t;
        geom_out[i] = found[l].geom_id;
        prim_out[i] = found[l].prim_id;
        u_out[i] = found[l].u;
        v_out[i] = found[l].v;
        for (uint k = 0; k < 3; ++k)
            normal_out[3 * i + k] = found[l].normal[k];
    }
}

TRAVERSAL_KERNEL void intersect_any_arrays(__global const WideNode* nodes,
                                           __global const Triangle* triangles,
                                           __global const float* origins,
                                           __global const float* directions,
                                           __global const float* tmin, const uint tmin_step,
                                           __global const float* tmax, const uint tmax_step,
                                           __global uchar* occluded, __global int* overflow,
                                           const uint ray_count)
{
    uint first, used = packet_rays(ray_count, &first);
    if (used == 0)
        return;
    RayLanes lanes;
    load_lanes_arrays(first, used, origins, directions, tmin, tmin_step, tmax, tmax_step,
                      &lanes);
    uchar found[PACKET_SIZE];
    any_hits(&lanes, used, nodes, triangles, overflow, found);
    for (uint l = 0; l < used; ++l)
        occluded[first + l] = found[l];
}
