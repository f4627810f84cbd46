/* The wide node as traversal reads it: its plane rows as vectors with one
 * lane per child, the closing step of the slab test (Kay & Kajiya 1986),
 * made conservative under rounding as Ize 2013 ("Robust BVH Ray
 * Traversal", JCGT 2(2)) shows, and the bit helpers that turn a lane
 * compare into a child mask and walk its set bits. */
#ifndef NODE_H
#define NODE_H

#include "core/portable.h"
#include "core/spelled.h"
#include "core/leaf.h"
#include "core/tree.h"

#ifdef cl_khr_fp64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif

#if WIDE_ARITY != 8
#error "traversal reads 8-wide nodes (WIDE_ARITY 8)"
#endif

/* One vector lane per child of a wide node. */
typedef float8 float_lanes;
typedef int8 int_lanes;
#define LANES_HINT vec_type_hint(float8)

/* A query kernel.  The kernels already compute in vectors (a node's
 * children); the hint keeps Intel's CPU compiler from also packing
 * work-items into SIMD lanes, which measured slower (its default is to
 * vectorise whenever the group size allows). */
#define TRAVERSAL_KERNEL __kernel __attribute__((LANES_HINT))

/* PoCL's inliner stops just short of the traversal loop and the triangle
 * test (measured slower on camera rays); every helper here is small or
 * called in one place, so inline them all. */
#define TRAVERSAL_INLINE inline __attribute__((always_inline))

/* A WideNode's plane or count row as one vector load.  A row starts at a
 * multiple of 4 * WIDE_ARITY bytes within the node, and nodes and buffers
 * at multiples of its size (buffers are aligned to at least the largest
 * built-in type, 128 bytes), so the load is aligned.  A plain load rather
 * than vload8, which PoCL 3.0 calls out of line (core/spelled.h).  A macro:
 * it names the row's type. */
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

/* sqrt of 8 lanes at once (core/spelled.h's SQRT: one), as x86's one vsqrtps where the compiler
 * exposes it: PoCL calls sqrt on vectors out of line, and the winding
 * walk's dipole and solid-angle terms took a call each (measured slower).
 * Both round correctly, as sqrtf does, so the results are the same. */
TRAVERSAL_INLINE float8 lanes_root(float8 v)
{
#if HAS_BUILTIN(__builtin_ia32_sqrtps256)
    return __builtin_ia32_sqrtps256(v);
#else
    return sqrt(v);
#endif
}

/* Sign bit and absolute values by their bits (PoCL: see LOAD_ROW;
 * core/spelled.h's abs_float for one). */
TRAVERSAL_INLINE uint sign_bit(float x) { return as_uint(x) >> 31; }
TRAVERSAL_INLINE float8 abs_lanes(float8 x) { return as_float8(as_int8(x) & (int8)(0x7fffffff)); }

/* Ize 2013: scaling the exit distance by 1 + 2*gamma(3) makes the slab test
 * conservative under float rounding.  We use gamma(5) (gamma(n) = n*eps /
 * (1 - n*eps), eps = 2^-24) because OpenCL allows 2.5 ulp for the division
 * that gives the inverse direction. */
#define EXIT_SCALE (1.0f + 2.0f * (5.0f * 0x1p-24f) / (1.0f - 5.0f * 0x1p-24f))

/* The closing step of a slab test (Kay & Kajiya 1986), one lane each, from
 * the distances to the near planes (nx, ny, nz) and far planes (fx, fy, fz):
 * the entry is the latest of tmin and the near ones, the exit the earliest
 * far one.  Sets `entry` and gives whether [entry, exit] meets [tmin, limit]
 * (-1 or 0) per lane, with the lesser of exit and limit scaled by
 * EXIT_SCALE: the limit too, as the entry may round up past a hit exactly
 * at the limit (a ray's tmax is inclusive).  The GROW_HI / GROW_LO chains start
 * from tmin and +inf, never NaN, so they ignore a 0 * inf = NaN distance
 * (origin on a slab plane, direction component 0): a ray lying in a face
 * plane counts as inside, as the closed box demands.  (fmax / fmin would do
 * the same but cost x86 a NaN test and a blend each: measured slower.)  An
 * unused slot's empty box (lo = +inf, hi = -inf) is missed by every ray: its
 * entry is +inf and its exit -inf, whatever the direction's signs, so no
 * lane checks for EMPTY_CHILD (measured slower).  A macro, as the lanes are
 * children (one ray, float_lanes) or rays (a packet at one child). */
#define SLABS_MEET(type, nx, ny, nz, fx, fy, fz, tmin, limit, entry)                     \
    ((entry) = CONCAT(HI_, type)(CONCAT(HI_, type)(CONCAT(HI_, type)(tmin, nx), ny), nz),   \
     (entry) <= CONCAT(LO_, type)(CONCAT(LO_, type)(CONCAT(LO_, type)(CONCAT(LO_, type)(    \
                    (type)(INFINITY), fx), fy), fz), limit) * EXIT_SCALE)

/* SLABS_MEET's GROW_LO / GROW_HI for its lane types.  A node's 8 children
 * (float_lanes) as x86's vminps / vmaxps where the compiler exposes them:
 * minps(a, b) is a < b ? a : b, and maxps(a, b) a > b ? a : b, NaN and
 * signed zeros alike, the very selects GROW_LO(b, a) and GROW_HI(b, a)
 * spell, so the lanes are the same bits.  Spelled as selects, the exit's
 * chain became a compare, a blend and a min per plane on PoCL (the selects
 * kept beside the mins they equal).  Packets keep the selects. */
#if HAS_BUILTIN(__builtin_ia32_minps256) && HAS_BUILTIN(__builtin_ia32_maxps256)
#define LO_float_lanes(acc, value) __builtin_ia32_minps256(value, acc)
#define HI_float_lanes(acc, value) __builtin_ia32_maxps256(value, acc)
#else
#define LO_float_lanes GROW_LO
#define HI_float_lanes GROW_HI
#endif
#define LO_float_packet GROW_LO
#define HI_float_packet GROW_HI

/* The slab test of ray or packet r, whose near_* offsets pick the entry
 * plane rows by the sign of the inverse direction (Williams et al. 2005; the
 * exit rows are at offset ^ ROW_BYTES), against the planes that
 * PLANE(offset) reads. */
#define PLANE_DISTANCE(PLANE, offset, o, inv) ((PLANE(offset) - (o)) * (inv))
#define SLAB_TEST(type, PLANE, r, tmin, limit, entry)                                      \
    SLABS_MEET(type, PLANE_DISTANCE(PLANE, (r)->near_x, (r)->ox, (r)->inv_x),               \
               PLANE_DISTANCE(PLANE, (r)->near_y, (r)->oy, (r)->inv_y),                     \
               PLANE_DISTANCE(PLANE, (r)->near_z, (r)->oz, (r)->inv_z),                     \
               PLANE_DISTANCE(PLANE, (r)->near_x ^ ROW_BYTES, (r)->ox, (r)->inv_x),         \
               PLANE_DISTANCE(PLANE, (r)->near_y ^ ROW_BYTES, (r)->oy, (r)->inv_y),         \
               PLANE_DISTANCE(PLANE, (r)->near_z ^ ROW_BYTES, (r)->oz, (r)->inv_z), tmin, limit, \
               entry)

/* x86's sign-bit mask of 8 floats (vmovmskps), where the OpenCL compiler is
 * a Clang that exposes it (PoCL's CPU device; Intel's CPU runtime does not). */
#if HAS_BUILTIN(__builtin_ia32_movmskps256)
#define HAVE_MOVMSKPS256
#endif

/* The lanes set in `hit` (-1) as a bit mask: bit c for child c.  One
 * movmskps where the compiler offers it: the portable fold below is a chain
 * of six dependent instructions on every node step (measured slower).  A
 * Clang's __builtin_reduce_or of the weighted lanes, which Intel's CPU
 * compiler has, ran there within noise of the fold, and Oclgrind cannot
 * lower it (figures in the commit that says so). */
TRAVERSAL_INLINE uint lane_mask(int_lanes hit)
{
#ifdef HAVE_MOVMSKPS256
    return (uint)__builtin_ia32_movmskps256(as_float8(hit));
#else
    int8 bits = hit & (int8)(1, 2, 4, 8, 16, 32, 64, 128);
    int4 folded = bits.lo | bits.hi;
    int2 quarter = folded.lo | folded.hi;
    return (uint)(quarter.x | quarter.y);
#endif
}

/* The lowest and highest set bits' positions (mask != 0) and the number of
 * set bits of a child mask: one tzcnt / lzcnt / popcnt where the compiler is
 * a Clang, else plain arithmetic (ctz is OpenCL 2.0, PoCL calls clz out of
 * line, and Oclgrind cannot run popcount()). */
#if HAS_BUILTIN(__builtin_ctz) && HAS_BUILTIN(__builtin_clz) && HAS_BUILTIN(__builtin_popcount)
#define HAVE_BIT_BUILTINS
#endif

TRAVERSAL_INLINE int lowest_slot(uint mask)
{
#ifdef HAVE_BIT_BUILTINS
    return __builtin_ctz(mask);
#else
    return 31 - (int)clz(mask & (0u - mask));
#endif
}

TRAVERSAL_INLINE int highest_slot(uint mask)
{
#ifdef HAVE_BIT_BUILTINS
    return 31 - __builtin_clz(mask);
#else
    return 31 - (int)clz(mask);
#endif
}

TRAVERSAL_INLINE int bit_count(uint mask)
{
#ifdef HAVE_BIT_BUILTINS
    return __builtin_popcount(mask);
#else
    /* Masks hold WIDE_ARITY = 8 bits: two nibbles, each counted by a lookup
     * in a 64-bit constant (a form LLVM does not turn back into llvm.ctpop,
     * which Oclgrind cannot run). */
    const ulong nibble_bits = 0x4332322132212110ul;
    return (int)(((nibble_bits >> (4u * (mask & 15u))) & 15u)
                 + ((nibble_bits >> (4u * ((mask >> 4) & 15u))) & 15u));
#endif
}

/* Whether a non-zero mask has one bit set.  LLVM turns the classic test
 * into llvm.ctpop, which Oclgrind cannot run, hence the plain spelling. */
TRAVERSAL_INLINE bool one_bit(uint mask)
{
#ifdef PLAIN_OPENCL
    return bit_count(mask) == 1;
#else
    return (mask & (mask - 1u)) == 0;
#endif
}

/* PATH(name): the name in the path being instantiated (PATH_SUFFIX: _ray,
 * _packet, _point or _points), for the headers written once for every path
 * (walk.h, query/rays/triangle.h).  Token pasting: macros. */
#define CONCAT_(a, b) a##b
#define CONCAT(a, b) CONCAT_(a, b)
#define PATH(name) CONCAT(name, PATH_SUFFIX)

/* The distances at which a ray or packet enters a node's children, one lane
 * per child: as a vector for the compares, as floats for single children.  A
 * union rather than vstore8 (PoCL: see LOAD_ROW). */
typedef union {
    float_lanes lanes;
    float slot[WIDE_ARITY];
} ChildEntries;

#endif /* NODE_H */
