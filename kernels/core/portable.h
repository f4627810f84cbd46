/* What every kernel needs to compile to the same arithmetic, and to run, on
 * every OpenCL C compiler we test (PoCL's and Intel's CPU runtimes, Oclgrind,
 * NVIDIA's): contraction off, and compiler builtins asked for by name.
 * Every kernel file includes it first. */
#ifndef PORTABLE_H
#define PORTABLE_H

/* Arithmetic as written, never fused into multiply-adds, in every kernel:
 * OpenCL C lets a compiler contract by default, and one that does (for the
 * SAH's box areas, say) would build another tree, and draw other pixels, than
 * one that does not.  Traversal needs it besides (query/rays/triangle.h). */
#pragma OPENCL FP_CONTRACT OFF

/* Compiler builtins are only ever a faster spelling of plain OpenCL C: each
 * use asks HAS_BUILTIN(name) and keeps a portable fallback.  The host defines
 * PLAIN_OPENCL for compilers that claim a builtin they cannot lower (Oclgrind
 * accepts __builtin_ctz, then fails on llvm.cttz), and for its safest kernel
 * variant (hlbvh_cl/device/probe.py). */
#if defined(__has_builtin) && !defined(PLAIN_OPENCL)
#define HAS_BUILTIN(name) __has_builtin(name)
#else
#define HAS_BUILTIN(name) 0
#endif

/* A kernel whose work-items Intel's CPU compiler is not to pack into
 * vector registers, as it does by default (16 to a register with AVX-512).
 * Given this float4 hint, its compiler (2026.22 here) does not vectorize
 * the kernel across work-items at all: its build log says "Kernel can't be
 * vectorized due to unsupported vec type hint" and "was not vectorized".
 * Packed work-items' loads and stores at scattered addresses (a path's
 * state, a pixel's film entries, a triangle's vertices, a node's children)
 * become gathers and scatters, which cost more than the lanes save: the camera,
 * the preview shading, the path tracer's film and resolve kernels, the
 * build's bounds, Morton, flatten and widen stages, refit and the dipoles
 * measured faster with it, the same bits (figures in the commits that
 * marked them).  Standard OpenCL C that other compilers (PoCL's) may
 * ignore.  (Traversal kernels carry their own hint: query/walk/node.h's
 * TRAVERSAL_KERNEL.) */
#define NARROW_KERNEL __kernel __attribute__((vec_type_hint(float4)))

/* PREFETCH (set by the host for CPU devices) asks for __builtin_prefetch. */
#if defined(PREFETCH) && !HAS_BUILTIN(__builtin_prefetch)
#undef PREFETCH
#endif

/* Asks for the cache line at p, to be written (rw 1) or read (0), under
 * PREFETCH; elsewhere nothing, and p is not evaluated. */
#ifdef PREFETCH
#define PREFETCH_AT(p, rw) __builtin_prefetch((p), (rw))
#else
#define PREFETCH_AT(p, rw) do {} while (0)
#endif

/* Inlined whatever the compiler's inliner thinks: PoCL's stops short of
 * the path integrator's light and BSDF samplers, and each call it leaves
 * spills every live vector register (all are caller-saved on x86-64).
 * Not under PLAIN_OPENCL: Oclgrind cannot run the
 * llvm.experimental.noalias.scope.decl that LLVM leaves where it forces
 * them inline. */
#ifdef PLAIN_OPENCL
#define FORCE_INLINE inline
#else
#define FORCE_INLINE inline __attribute__((always_inline))
#endif

#endif /* PORTABLE_H */
