/* The build's constants (hlbvh_cl/core/layout.py reads CLUSTER_BITS and
 * MAX_LEAF_SIZE from this file, never restates them) and the Morton key
 * type of the stages that read keys. */
#ifndef BUILD_CONFIG_H
#define BUILD_CONFIG_H

/* HLBVH clusters are the runs of primitives that share the top CLUSTER_BITS
 * bits of their Morton code.  pbrt-v3's HLBVHBuild uses 12; 21 (7 per axis)
 * puts the SAH deep enough to lower the SAH cost of the Stanford meshes
 * well below the plain LBVH's, more than 12 bits do (bench/build.py). */
#define CLUSTER_BITS 21

/* A subtree of at most MAX_LEAF_SIZE triangles collapses into one leaf when
 * the leaf's SAH cost is at most COLLAPSE_COST_RATIO times the subtree's
 * (HLBVH builder only).  A ratio of 1 is the plain SAH decision; 1.5 keeps
 * more small subtrees whole, for fewer nodes to flatten and widen: on the
 * reference scene it measured far fewer nodes and a faster build for a
 * slightly higher SAH cost and render time, and the Stanford meshes keep
 * their SAH gain over the LBVH (bench/build.py). */
#define MAX_LEAF_SIZE 8
/* A compact tree (core/leaf.h's INDEXED_LEAVES: Scene(..., compact=True)) is
 * the layout that trades speed for memory, and collapses at 2: nearly every
 * subtree of at most MAX_LEAF_SIZE triangles becomes a leaf (higher ratios
 * change little), for fewer nodes to store (issue 56's memory target) and
 * slightly slower incoherent rays (figures in the commit that says so).  The
 * triangles keep their sorted order, so every hit is the same; the winding
 * number's dipoles are the tree's own. */
#ifdef INDEXED_LEAVES
#define COLLAPSE_COST_RATIO 2.0f
#else
#define COLLAPSE_COST_RATIO 1.5f
#endif

/* SAH cost model: traversal cost 1, intersection cost 1, normalised by the
 * surface area of the root (stats["sah_cost"]). */
#define SAH_TRAVERSAL_COST 1.0f
#define SAH_INTERSECT_COST 1.0f

/* The wide tree's cost model, for the collapse into 8-wide nodes (widen.cl):
 * a wide node's test of all its lanes against one triangle's test.  Ylitie
 * et al. 2017 (sec. 4.1) weigh a triangle 0.3 of a node on GPUs. */
#define WIDE_NODE_COST 1.0f
#define WIDE_TRIANGLE_COST 0.3f

/* Bins per axis of the binned SAH that builds the top of the HLBVH over the
 * clusters (Wald 2007, "On fast construction of SAH-based BVHs").  64 rather
 * than 32 lowers the bunny's SAH cost slightly for a slightly longer build. */
#define TOP_SAH_BINS 64

/* Morton keys: MORTON_BITS = 30 (10 bits per axis, uint) or 63 (21 bits per
 * axis, ulong), set by the host as a -D define for the stages that read keys. */
#ifdef MORTON_BITS
#if MORTON_BITS == 30
typedef uint morton_t;
#define KEY_BITS 32
#elif MORTON_BITS == 63
typedef ulong morton_t;
#define KEY_BITS 64
#else
#error "MORTON_BITS must be 30 or 63"
#endif
#define CLUSTER_SHIFT (MORTON_BITS - CLUSTER_BITS)
#endif

#endif /* BUILD_CONFIG_H */
