/* PACKET_SIZE queries per work-item, one vector lane each: the vector
 * types and the folds over lanes that ray packets (query/rays/packet.h) and
 * point packets (query/points/point_packet.h) share. */
#ifndef LANES_H
#define LANES_H

#include "query/walk/node.h"

/* A 16-lane float or 8-lane double is wider than an AVX2 target's
 * registers, and clang notes, at every helper taking or returning one,
 * that such an argument would change the ABI (-Wpsabi): hundreds of notes,
 * which PoCL prints on the process's stderr, about helpers that are inlined
 * and have no ABI to keep.  (__has_warning: clang's, absent elsewhere.) */
#if defined(__has_warning)
#if __has_warning("-Wpsabi")
#pragma clang diagnostic ignored "-Wpsabi"
#endif
#endif

#if PACKET_SIZE == 16
typedef float16 float_packet;
typedef int16 int_packet;
#define vload_packet vload16
#define vstore_packet vstore16
#define as_int_packet as_int16
#define as_float_packet as_float16
#ifdef cl_khr_fp64
#define to_double_packet convert_double16
#define to_float_packet convert_float16
typedef double16 wide_packet;
#endif
#elif PACKET_SIZE == 8
typedef float8 float_packet;
typedef int8 int_packet;
#define vload_packet vload8
#define vstore_packet vstore8
#define as_int_packet as_int8
#define as_float_packet as_float8
#ifdef cl_khr_fp64
#define to_double_packet convert_double8
#define to_float_packet convert_float8
typedef double8 wide_packet;
#endif
#else
#error "PACKET_SIZE must be 1, 8 or 16"
#endif

/* |v| of every lane, by its bits (PoCL: see LOAD_ROW). */
TRAVERSAL_INLINE float_packet abs_packet(float_packet v)
{
    return as_float_packet(as_int_packet(v) & (int_packet)(0x7fffffff));
}

/* Folds a packet's lanes to one with f: the halves first, then theirs.
 * GROW_LO / GROW_HI give the least / greatest lane of lanes that are never
 * NaN (entry distances, limits), without fmin / fmax's NaN tests; OR / AND
 * fold lane flags (-1 or 0) with one test, where PoCL's any() tests lane by
 * lane, a branch each, which mispredicted in the child loop of camera-ray
 * packets. */
#if PACKET_SIZE == 16
#define HALVES(v, f) f((v).lo, (v).hi)
#else
#define HALVES(v, f) (v)
#endif
#define OR(a, b) ((a) | (b))
#define AND(a, b) ((a) & (b))
/* Macros: they name their types by token pasting and take the fold, itself
 * a macro.  FOLD_EIGHT folds 8 lanes (a node's row, or a packet's halves). */
#define FOLD_EIGHT(type, a, f)       \
    type##4 b = f((a).lo, (a).hi);   \
    type##2 c = f(b.lo, b.hi);       \
    return f(c.x, c.y)
#define FOLD_LANES(type, v, f)   \
    type##8 a = HALVES(v, f);    \
    FOLD_EIGHT(type, a, f)

TRAVERSAL_INLINE float packet_min(float_packet v) { FOLD_LANES(float, v, GROW_LO); }
TRAVERSAL_INLINE float packet_max(float_packet v) { FOLD_LANES(float, v, GROW_HI); }
TRAVERSAL_INLINE int packet_or(int_packet v) { FOLD_LANES(int, v, OR); }
TRAVERSAL_INLINE int packet_and(int_packet v) { FOLD_LANES(int, v, AND); }

/* The least / greatest of a node row's 8 planes (empty slots: +inf in lo
 * rows, -inf in hi rows). */
TRAVERSAL_INLINE float row_least(float_lanes row) { FOLD_EIGHT(float, row, GROW_LO); }
TRAVERSAL_INLINE float row_most(float_lanes row) { FOLD_EIGHT(float, row, GROW_HI); }

/* sqrt of every lane (lanes_root, a half at a time for 16 lanes). */
TRAVERSAL_INLINE float_packet packet_root(float_packet v)
{
#if PACKET_SIZE == 16
    return (float16)(lanes_root(v.lo), lanes_root(v.hi));
#else
    return lanes_root(v);
#endif
}

/* Whether some / every lane flag is set: after the halves, one movmskps
 * where there is one (measured faster). */
TRAVERSAL_INLINE bool some_packet(int_packet v)
{
#ifdef HAVE_MOVMSKPS256
    return __builtin_ia32_movmskps256(as_float8(HALVES(v, OR))) != 0;
#else
    return packet_or(v) < 0;
#endif
}

TRAVERSAL_INLINE bool every_packet(int_packet v)
{
#ifdef HAVE_MOVMSKPS256
    return __builtin_ia32_movmskps256(as_float8(HALVES(v, AND))) == 0xff;
#else
    return packet_and(v) < 0;
#endif
}

#endif /* LANES_H */
