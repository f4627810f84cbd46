/* Builtins spelled out in plain OpenCL C: PoCL 3.0's CPU device calls vload3,
 * min, fmin, select and other builtins out of line instead of inlining them
 * (perf showed much of the bounds pass's, lay_out_leaves' and the
 * incoherent-ray kernel's time in such calls).  Macros, as each works on
 * scalars and vectors alike, and LOAD_XYZ in any address space. */
#ifndef SPELLED_H
#define SPELLED_H

#include "core/portable.h"

/* The three floats from p[0] on, in any address space: vload3 spelled out. */
#define LOAD_XYZ(p) ((float3)((p)[0], (p)[1], (p)[2]))

/* min(a, b) for scalars, spelled with ?:. */
#define LESSER(a, b) ((a) < (b) ? (a) : (b))

/* The lesser / greater of an accumulator and a value, scalars or vectors:
 * fmin/fmax without the NaN handling they pay for (a compare and a blend
 * per call on x86).  The accumulator is never NaN, and a NaN value leaves it
 * unchanged, as fmin/fmax would.  Spelled with ?: (on vectors it selects
 * per lane by the condition's sign bit, as select does) rather than
 * select(). */
#define GROW_LO(acc, value) ((value) < (acc) ? (value) : (acc))
#define GROW_HI(acc, value) ((value) > (acc) ? (value) : (acc))

/* sqrt as one instruction where the compiler is a Clang (PoCL calls sqrt
 * out of line, and each call spills every live vector register around it:
 * all are caller-saved on x86-64).  Both round correctly. */
#if HAS_BUILTIN(__builtin_sqrtf)
#define SQRT __builtin_sqrtf
#else
#define SQRT sqrt
#endif

/* |x| and copysign(1, x) by the sign bit: fabs and copysign without calls. */
inline float abs_float(float x) { return as_float(as_uint(x) & 0x7fffffffu); }
inline float sign_of(float x) { return as_float((as_uint(x) & 0x80000000u) | 0x3f800000u); }

/* nextafter(x, INFINITY) and nextafter(x, -INFINITY), by the bits: the
 * next float up is the next integer up for a positive x and the next down
 * for a negative one, from either zero the least subnormal.  (OpenCL's
 * nextafter is a library call on some CPU runtimes.) */
inline float float_above(float x)
{
    int bits = as_int(x);
    if ((bits & 0x7f800000) == 0x7f800000)  /* inf or NaN */
        return x == -INFINITY ? -FLT_MAX : x;
    if ((bits & 0x7fffffff) == 0)
        return as_float(1);
    return as_float(bits >= 0 ? bits + 1 : bits - 1);
}

inline float float_below(float x) { return -float_above(-x); }

#endif /* SPELLED_H */
