/* The wide tree that every query walks, as the build leaves it on the device
 * (mirrored by hlbvh_cl/core/layout.py): its nodes, their dipoles for the
 * winding number, its triangles in tree order and their ids, and the
 * instances of a two-level scene.  Every struct is made of 4-byte scalars,
 * so that the OpenCL and numpy layouts agree without padding rules
 * (tests/device/test_devices.py checks sizeof/offsetof on each device). */
#ifndef TREE_H
#define TREE_H

/* Children per node of the wide tree that traversal reads (build/widen.cl).
 * 8 measured faster than 4 on both CPU devices (PoCL and Intel), on camera
 * and incoherent rays; traversal (query/walk/node.h) reads 8-wide nodes only. */
#define WIDE_ARITY 8

/* A child slot with count 0 is an interior node (index = node), with count
 * > 0 a leaf (index = first triangle), and EMPTY_CHILD marks a missing
 * child: the second child of a one-triangle scene, an unused slot. */
#define EMPTY_CHILD (-1)

/* One node of the wide tree (build/widen.cl collapses the flat BVH2 into
 * it; Wald et al. 2008, "Getting Rid of Packets", and Embree's BVH4/BVH8):
 * the boxes of up to WIDE_ARITY children stored per axis and bound (SoA), so
 * that one vector operation per plane tests every child.  A slot's child and
 * count mean what they mean in FlatNode; an unused slot has child EMPTY_CHILD,
 * count 0 and an empty box (lo = +inf, hi = -inf).  32 * WIDE_ARITY bytes.
 * Planes as floats: quantized to bytes against the node's own frame (Ylitie
 * et al. 2017; Embree's compressed BVH8), in 128-byte nodes, the hits were
 * the same but CPU runtimes traced slower, decoding costing more than the
 * smaller node saved (figures in the commit that says so). */
typedef struct {
    float lo_x[WIDE_ARITY];
    float hi_x[WIDE_ARITY];
    float lo_y[WIDE_ARITY];
    float hi_y[WIDE_ARITY];
    float lo_z[WIDE_ARITY];
    float hi_z[WIDE_ARITY];
    int child[WIDE_ARITY];
    uint count[WIDE_ARITY];
} WideNode;

/* The order-1 dipole of each child of a wide node (WideNode's lanes; Barill
 * et al. 2018, "Fast Winding Numbers for Soups and Clouds", sec. 3.2),
 * which the winding-number walk takes in place of the child when the query
 * point is far from it: the area-weighted centroid p, the sum a of the
 * triangles' area vectors 0.5 * cross(v1 - v0, v2 - v0), their total area
 * (to merge lanes up the tree) and the radius around p that holds every
 * vertex.  One row of WIDE_ARITY floats per field, as WideNode's, so the
 * far-field test is one vector operation; an unused slot holds zeros.
 * Computed on the device by build/dipoles.cl.  32 * WIDE_ARITY bytes. */
typedef struct {
    float p_x[WIDE_ARITY];
    float p_y[WIDE_ARITY];
    float p_z[WIDE_ARITY];
    float a_x[WIDE_ARITY];
    float a_y[WIDE_ARITY];
    float a_z[WIDE_ARITY];
    float area[WIDE_ARITY];
    float radius[WIDE_ARITY];
} WideDipoles;

/* A triangle's vertices in tree order, as the ray-triangle test reads them:
 * one triangle at a time, or on CPUs four of a leaf's at a time, gathered
 * from these records into vector lanes (query/rays/quad.h).  Stored as SoA
 * blocks of four instead (Embree's Triangle4), with the same arithmetic lane
 * by lane and so the same hits, they traced slower on CPU runtimes, on
 * single meshes whose leaves hold about two triangles (figures in the commit
 * that says so).  Three vertex indices into shared vertices
 * instead (Embree's compact Triangle4i) halve the leaves' memory, the hits
 * the same bits, but incoherent rays trace slower on CPU runtimes: a leaf's
 * vertices wait on its indices, which the push-time prefetch cannot cover.
 * So they are the opt-in compact layout (IndexedTriangle, below), not the
 * default (figures in the commit that says so).  Indices into the leaf's own
 * distinct vertices, stored in the leaf (two fifths less leaf memory on the
 * reference scene), gave the same bits again for nearly the same
 * instructions, and traced slower too, most on PoCL (figures in the commit
 * that says so). */
typedef struct {
    float v0[3];
    float v1[3];
    float v2[3];
} Triangle;

/* The compact leaves' triangle (Scene(..., compact=True); core/leaf.h reads
 * it): where each of its corners lies, in 12-byte cells counted from this
 * record, among the vertices that follow the records in the same buffer
 * (the scene's vertices in the tree's frame, each stored once).  Relative,
 * so a record keeps its meaning wherever the block it is in is copied to;
 * 12 bytes a triangle plus 12 a vertex instead of 36 a triangle, at the
 * price of a load that waits on another (Embree's Triangle4i and
 * RTC_SCENE_FLAG_COMPACT make the same trade).  On CPUs a ray tests these
 * four at a time too, each lane's corners found through its record
 * (query/rays/quad.h). */
typedef struct {
    int corner[3];
} IndexedTriangle;

/* Which mesh and which of its faces a tree-ordered triangle came from. */
typedef struct {
    int geom_id;
    int prim_id;
} TriangleRef;

/* One instance of a two-level scene (hlbvh_cl/build/instances.py): where its
 * mesh's tree lies among the meshes' trees, the maps between the top tree's
 * frame and that mesh's frame, and its mask.  Rays are mapped, not
 * renormalised, so t is the same in both frames; point queries measure
 * distances in the top frame (query/points/instance.h), where a
 * non-similarity map does not keep them. */
typedef struct {
    float to_mesh[12];  /* 3x4 row-major affine map: top frame -> mesh frame */
    float to_world[12]; /* its inverse: mesh frame -> top frame */
    float normal_sign;  /* sign of the map's determinant (mirroring flips normals) */
    float reach_scale;  /* 1 / s^2, s the least singular value of to_world's linear
                           part: a mesh-frame distance d is at least s d in the top frame */
    uint mask;          /* a ray skips the instance when (ray mask & mask) == 0 */
    int mesh;           /* index of its mesh (the hits' geom_id) */
    int node_base;      /* its mesh tree's root among the meshes' wide nodes */
    int triangle_base;  /* its mesh tree's first triangle among the meshes' triangles */
} Instance;

#endif /* TREE_H */
