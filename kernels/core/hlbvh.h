/* Structs and constants shared by every kernel of hlbvh_cl.
 *
 * Mirrored once in Python by hlbvh_cl/layout.py (numpy dtypes); the constants
 * below are read from this file by that module, never restated.  Keep every
 * struct made of 4-byte scalars so that the OpenCL and numpy layouts agree
 * without padding rules (tests/test_devices.py checks sizeof/offsetof on the
 * device).
 */
#ifndef HLBVH_H
#define HLBVH_H

/* Arithmetic as written, never fused into multiply-adds, in every kernel:
 * OpenCL C lets a compiler contract by default, and one that does (for the
 * SAH's box areas, say) would build another tree, and draw other pixels, than
 * one that does not.  Traversal needs it besides (triangle.h). */
#pragma OPENCL FP_CONTRACT OFF

/* Compiler builtins are only ever a faster spelling of plain OpenCL C: each
 * use asks HAS_BUILTIN(name) and keeps a portable fallback.  The host defines
 * PLAIN_OPENCL for compilers that claim a builtin they cannot lower (Oclgrind
 * accepts __builtin_ctz, then fails on llvm.cttz), and for its safest kernel
 * variant (hlbvh_cl/probe.py). */
#if defined(__has_builtin) && !defined(PLAIN_OPENCL)
#define HAS_BUILTIN(name) __has_builtin(name)
#else
#define HAS_BUILTIN(name) 0
#endif

/* PREFETCH (set by the host for CPU devices) asks for __builtin_prefetch. */
#if defined(PREFETCH) && !HAS_BUILTIN(__builtin_prefetch)
#undef PREFETCH
#endif

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
#define COLLAPSE_COST_RATIO 1.5f

/* SAH cost model: traversal cost 1, intersection cost 1, normalised by the
 * surface area of the root (stats["sah_cost"]). */
#define SAH_TRAVERSAL_COST 1.0f
#define SAH_INTERSECT_COST 1.0f

/* Bins per axis of the binned SAH that builds the top of the HLBVH over the
 * clusters (Wald 2007, "On fast construction of SAH-based BVHs").  64 rather
 * than 32 lowers the bunny's SAH cost slightly for a slightly longer build. */
#define TOP_SAH_BINS 64

/* A child slot with count 0 is an interior node (index = node), with count
 * > 0 a leaf (index = first triangle), and EMPTY_CHILD marks the missing
 * second child of a one-triangle scene. */
#define EMPTY_CHILD (-1)

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

typedef struct {
    float lo[3];
    float hi[3];
} Aabb;

/* One node of the flat binary tree, the build's scratch that widen.cl
 * collapses into WideNodes: both children's boxes live in the parent, so one
 * read gives both (Aila & Laine 2009). 64 bytes. */
typedef struct {
    float left_lo[3];
    float left_hi[3];
    float right_lo[3];
    float right_hi[3];
    int left;
    int right;
    uint left_count;
    uint right_count;
} FlatNode;

/* Children per node of the wide tree that traversal reads (widen.cl).  8
 * measured faster than 4 on both CPU devices (PoCL and Intel), on camera
 * and incoherent rays; traversal (node.h) reads 8-wide nodes only. */
#define WIDE_ARITY 8

/* One node of the wide tree (hlbvh_cl/widen.py collapses the flat BVH2 into
 * it; Wald et al. 2008, "Getting Rid of Packets", and Embree's BVH4/BVH8):
 * the boxes of up to WIDE_ARITY children stored per axis and bound (SoA), so
 * that one vector operation per plane tests every child.  A slot's child and
 * count mean what they mean in FlatNode; an unused slot has child EMPTY_CHILD,
 * count 0 and an empty box (lo = +inf, hi = -inf).  32 * WIDE_ARITY bytes. */
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
 * Computed on the device by kernels/dipoles.cl.  32 * WIDE_ARITY bytes. */
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

/* A triangle's vertices in tree order, as the ray-triangle test reads them. */
typedef struct {
    float v0[3];
    float v1[3];
    float v2[3];
} Triangle;

/* Which mesh and which of its faces a tree-ordered triangle came from. */
typedef struct {
    int geom_id;
    int prim_id;
} TriangleRef;

/* One instance of a two-level scene (hlbvh_cl/instances.py): where its
 * mesh's tree lies among the meshes' trees, the maps between the top tree's
 * frame and that mesh's frame, and its mask.  Rays are mapped, not
 * renormalised, so t is the same in both frames; point queries measure
 * distances in the top frame (points.cl), where a non-similarity map does
 * not keep them. */
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

/* A ray as the traversal kernels read it (query.py fills these). */
typedef struct {
    float origin[3];
    float tmin;
    float direction[3];
    float tmax;
} Ray;

/* One closest-hit result; t = INFINITY and ids -1 on a miss. */
typedef struct {
    float t;
    int geom_id;
    int prim_id;
    float u;
    float v;
    float normal[3];
} Hit;

/* A pinhole camera as the ray generation stage reads it (render.py fills it
 * from a Camera, following scenefile.py's convention): the image-plane point
 * (sx, sy) in [-1, 1]^2, x to the right and y up, gets the ray
 * eye + t * (forward + sx * right + sy * up).  right and up are scaled by
 * tan(fov / 2), right also by the aspect ratio width / height. */
typedef struct {
    float eye[3];
    float forward[3];
    float right[3];
    float up[3];
} PinholeCamera;

/* What the shading stage reads besides the hits; render.py documents the
 * formulas that use them. */
typedef struct {
    float light_direction[3];  /* unit, from the surface towards the light */
    float light_intensity;
    float ambient;
    float sky_up[3];           /* unit; the background goes from horizon to zenith along it */
    float sky_horizon[3];
    float sky_zenith[3];
    float ray_offset;          /* shadow and AO rays start this far off the surface */
    float depth_near;          /* "depth" shading: distances near..far -> 1..0 */
    float depth_far;
    float ao_distance;         /* AO rays reach this far */
    float ao_weight;           /* 1 / number of AO rays per sample */
} ShadeParams;

/* Helpers several stages share. */

/* The three floats from p[0] on, in any address space: vload3 spelled out,
 * as PoCL 3.0 calls vload3 out of line (see GROW_LO; perf showed much of
 * the bounds pass's and lay_out_leaves' time in vload3 and vstore3). */
#define LOAD_XYZ(p) ((float3)((p)[0], (p)[1], (p)[2]))

/* min(a, b) for scalars, spelled with ?: for the same reason. */
#define LESSER(a, b) ((a) < (b) ? (a) : (b))

inline float3 load_vertex(__global const float *vertices, int index)
{
    return LOAD_XYZ(vertices + 3 * (size_t)index);
}

/* The lesser / greater of an accumulator and a value, scalars or vectors:
 * fmin/fmax without the NaN handling they pay for (a compare and a blend
 * per call on x86).  The accumulator is never NaN, and a NaN value leaves it
 * unchanged, as fmin/fmax would.  Spelled with ?: (on vectors it selects
 * per lane by the condition's sign bit, as select does) rather than
 * select(): PoCL 3.0's CPU device calls select, min, vload8 and other
 * builtins out of line instead of inlining them (perf showed much of the
 * incoherent-ray kernel's time in such calls). */
#define GROW_LO(acc, value) ((value) < (acc) ? (value) : (acc))
#define GROW_HI(acc, value) ((value) > (acc) ? (value) : (acc))

inline Aabb aabb_empty(void)
{
    Aabb box = {{INFINITY, INFINITY, INFINITY}, {-INFINITY, -INFINITY, -INFINITY}};
    return box;
}

inline Aabb aabb_of_points(float3 a, float3 b, float3 c)
{
    float3 lo = GROW_LO(GROW_LO(a, b), c);
    float3 hi = GROW_HI(GROW_HI(a, b), c);
    Aabb box = {{lo.x, lo.y, lo.z}, {hi.x, hi.y, hi.z}};
    return box;
}

inline Aabb aabb_union(Aabb a, Aabb b)
{
    Aabb box;
    for (int k = 0; k < 3; ++k) {
        box.lo[k] = GROW_LO(a.lo[k], b.lo[k]);
        box.hi[k] = GROW_HI(a.hi[k], b.hi[k]);
    }
    return box;
}

/* Surface area; 0 for an empty (inverted) box. */
inline float aabb_area(Aabb a)
{
    float dx = a.hi[0] - a.lo[0], dy = a.hi[1] - a.lo[1], dz = a.hi[2] - a.lo[2];
    if (!(dx >= 0.0f && dy >= 0.0f && dz >= 0.0f))
        return 0.0f;
    return 2.0f * (dx * dy + dy * dz + dz * dx);
}

inline float3 aabb_center(Aabb a)
{
    return (float3)(0.5f * (a.lo[0] + a.hi[0]), 0.5f * (a.lo[1] + a.hi[1]), 0.5f * (a.lo[2] + a.hi[2]));
}

/* The triangle `face` of an indexed mesh. */
inline void load_triangle(__global const float *vertices, __global const int *faces, int face,
                          float3 *a, float3 *b, float3 *c)
{
    *a = load_vertex(vertices, faces[3 * (size_t)face + 0]);
    *b = load_vertex(vertices, faces[3 * (size_t)face + 1]);
    *c = load_vertex(vertices, faces[3 * (size_t)face + 2]);
}

/* Triangle j of the tree-ordered triangle array (an initializer, not
 * vstore3: see load_vertex). */
inline void store_triangle(__global Triangle *triangles, int j, float3 a, float3 b, float3 c)
{
    Triangle t = {{a.x, a.y, a.z}, {b.x, b.y, b.z}, {c.x, c.y, c.z}};
    triangles[j] = t;
}

/* Rendering traces a pass of whole image rows in tile order.  Bands of
 * TILE_ROWS rows are cut into tiles of TILE_COLUMNS x TILE_ROWS pixels, left
 * to right, each tile row-major; a band's last width % TILE_COLUMNS columns,
 * and a last band of fewer rows, stay row-major.  A CPU ray packet
 * (traverse.cl: 16 or 8 rays, the kernel variant's packet size) then covers a
 * tile or half of one rather than a strip of a row, which measured faster
 * than row-major order for closest-hit and shadow rays, and 4x4 tiles with
 * packets of 16 faster than 4x2 with packets of 8.
 *
 * The kernels that map rays to pixels run over a 2D range
 * (TILE_ROWS * width, bands): work-item (k, band) is the pass's ray
 * band * TILE_ROWS * width + k, and its pixel takes no integer division
 * (CPU devices run those one lane at a time, measured slow on PoCL). */
#define TILE_COLUMNS 4
#define TILE_ROWS 4

/* How many of the multiples value, 2 value, ... (TILE_ROWS - 1) value are
 * <= k: k / value when that is below TILE_ROWS, without a division. */
inline uint rows_below(uint k, uint value)
{
    uint y = 0;
    for (uint r = 1; r < TILE_ROWS; ++r)
        y += k >= r * value;
    return y;
}

/* The ray and the pixel (column, row within the pass) of work-item
 * (k, band) of a pass of `rows` rows; false if it has none. */
inline bool pixel_in_pass(uint k, uint band, uint width, uint rows, uint *ray, uint2 *pixel)
{
    uint first_row = band * TILE_ROWS;
    if (first_row >= rows)
        return false;
    uint band_rows = LESSER((uint)TILE_ROWS, rows - first_row);
    if (k >= band_rows * width)
        return false;
    uint tiled = (width & ~(TILE_COLUMNS - 1u)) * TILE_ROWS;
    uint x, y;
    if (band_rows < TILE_ROWS) { /* the pass's last band, of fewer rows */
        y = rows_below(k, width);
        x = k - y * width;
    } else if (k < tiled) {
        x = k / (TILE_COLUMNS * TILE_ROWS) * TILE_COLUMNS + k % TILE_COLUMNS;
        y = k / TILE_COLUMNS % TILE_ROWS;
    } else { /* the last width % TILE_COLUMNS columns */
        uint columns = width % TILE_COLUMNS, rest = k - tiled;
        y = rows_below(rest, columns);
        x = width - columns + rest - y * columns;
    }
    *ray = first_row * width + k;
    *pixel = (uint2)(x, first_row + y);
    return true;
}

/* Deterministic random numbers for rendering: the PCG hash of Jarzynski &
 * Olano 2020 ("Hash Functions for GPU Rendering", JCGT 9(3)), an integer
 * hash good enough to be used without state. */
inline uint hash_pcg(uint value)
{
    uint state = value * 747796405u + 2891336453u;
    uint word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

/* A number in [0, 1) fixed by (pixel, sample, dimension), the same on every
 * run and device.  24 bits, so that the float is exact. */
inline float random_unit(uint pixel, uint sample, uint dimension)
{
    uint h = hash_pcg(pixel + hash_pcg(sample + hash_pcg(dimension)));
    return (float)(h >> 8) * 0x1p-24f;
}

#endif /* HLBVH_H */
