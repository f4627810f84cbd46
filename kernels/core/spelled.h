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

#endif /* SPELLED_H */
