/* Ray queries: stackful traversal of the flat BVH2 (DeviceTree) with a
 * watertight ray/triangle test.  One work-item traces one ray.
 *
 * Kernels
 *   intersect_closest  nearest hit in [tmin, tmax] -> Hit
 *   intersect_any      1 if any hit in [tmin, tmax] (stops at the first one)
 *
 * Conventions (tests/oracle.py follows the same ones)
 *   - a hit at distance t counts when tmin <= t <= tmax (both ends closed,
 *     as Embree's tnear <= t <= tfar); t is in units of |direction|;
 *   - no culling: both sides of a triangle are hit;
 *   - degenerate triangles (zero edge cross product) are never hit;
 *   - u, v: hit = (1-u-v)*v0 + u*v1 + v*v2.
 *
 * Compile-time parameters (-D)
 *   STACK_SIZE  entries of the private traversal stack; the host passes
 *               DeviceTree.depth rounded up, so it cannot overflow (if it ever
 *               did, the ray is flagged and the host raises).
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

/* Ize 2013, "Robust BVH Ray Traversal" (JCGT 2(2)): scaling the exit distance
 * by 1 + 2*gamma(3) makes the slab test conservative under float rounding.  We
 * use gamma(5) (gamma(n) = n*eps / (1 - n*eps), eps = 2^-24) because OpenCL
 * allows 2.5 ulp for the division that gives the inverse direction. */
#define EXIT_SCALE (1.0f + 2.0f * (5.0f * 0x1p-24f) / (1.0f - 5.0f * 0x1p-24f))

/* Everything about a ray that traversal reuses at each node and triangle. */
typedef struct {
    float ox, oy, oz;           /* origin */
    float inv_x, inv_y, inv_z;  /* 1/direction; +-INFINITY for a +-0 component */
    float tmin, tmax;
    /* Woop et al. 2013: the axis of largest |direction| becomes z
     * (kz), the other two (kx, ky) follow cyclically; the shear
     * (sx, sy, sz) maps the ray onto the +z axis through the origin. */
    int kx, ky, kz;
    float sx, sy, sz;
    float okx, oky, okz;        /* origin, permuted */
} RayData;

inline float component(const float v[3], int axis)
{
    return axis == 0 ? v[0] : (axis == 1 ? v[1] : v[2]);
}

inline RayData prepare_ray(__global const Ray* ray)
{
    RayData r;
    float d[3] = {ray->direction[0], ray->direction[1], ray->direction[2]};
    r.ox = ray->origin[0];
    r.oy = ray->origin[1];
    r.oz = ray->origin[2];
    /* IEEE division: 1/+0 = +inf, 1/-0 = -inf, which the slab test relies on. */
    r.inv_x = 1.0f / d[0];
    r.inv_y = 1.0f / d[1];
    r.inv_z = 1.0f / d[2];
    r.tmin = ray->tmin;
    r.tmax = ray->tmax;

    float ax = fabs(d[0]), ay = fabs(d[1]), az = fabs(d[2]);
    r.kz = (ax >= ay && ax >= az) ? 0 : (ay >= az ? 1 : 2);
    r.kx = r.kz == 2 ? 0 : r.kz + 1;
    r.ky = r.kx == 2 ? 0 : r.kx + 1;
    float dkz = component(d, r.kz);
    r.sx = component(d, r.kx) / dkz;
    r.sy = component(d, r.ky) / dkz;
    r.sz = 1.0f / dkz;
    float o[3] = {r.ox, r.oy, r.oz};
    r.okx = component(o, r.kx);
    r.oky = component(o, r.ky);
    r.okz = component(o, r.kz);
    return r;
}

/* Slab test (Kay & Kajiya 1986) of one child box.  Per axis the entry plane is
 * chosen by the sign bit of the inverse direction (Williams et al. 2005), so a
 * 0 * inf = NaN (origin on a slab plane, direction component 0) can only be
 * the entry or exit of that axis, which fmax / fmin then ignore: a ray lying
 * in a face plane counts as inside, as the closed box demands.  Returns the
 * entry distance and whether [entry, exit] meets [tmin, limit]. */
inline bool hit_box(const RayData* r, __global const float* lo, __global const float* hi,
                    float limit, float* entry)
{
    float near_x = ((signbit(r->inv_x) ? hi[0] : lo[0]) - r->ox) * r->inv_x;
    float near_y = ((signbit(r->inv_y) ? hi[1] : lo[1]) - r->oy) * r->inv_y;
    float near_z = ((signbit(r->inv_z) ? hi[2] : lo[2]) - r->oz) * r->inv_z;
    float far_x = ((signbit(r->inv_x) ? lo[0] : hi[0]) - r->ox) * r->inv_x;
    float far_y = ((signbit(r->inv_y) ? lo[1] : hi[1]) - r->oy) * r->inv_y;
    float far_z = ((signbit(r->inv_z) ? lo[2] : hi[2]) - r->oz) * r->inv_z;
    float t_entry = fmax(fmax(near_x, near_y), fmax(near_z, r->tmin));
    float t_exit = fmin(fmin(far_x, far_y), far_z) * EXIT_SCALE;
    *entry = t_entry;
    return t_entry <= fmin(t_exit, limit);
}

/* cross(v1 - v0, v2 - v0): unnormalised, following the winding. */
inline void geometric_normal(__global const Triangle* tri, float* nx, float* ny, float* nz)
{
    float e1x = tri->v1[0] - tri->v0[0], e1y = tri->v1[1] - tri->v0[1], e1z = tri->v1[2] - tri->v0[2];
    float e2x = tri->v2[0] - tri->v0[0], e2y = tri->v2[1] - tri->v0[1], e2z = tri->v2[2] - tri->v0[2];
    *nx = e1y * e2z - e1z * e2y;
    *ny = e1z * e2x - e1x * e2z;
    *nz = e1x * e2y - e1y * e2x;
}

/* Watertight ray/triangle test: Woop, Benthin & Wald 2013, "Watertight
 * Ray/Triangle Intersection" (JCGT 2(1)), without back-face culling.
 * On a hit with tmin <= t <= limit (t < limit when `strict`), writes t, u, v. */
inline bool hit_triangle(const RayData* r, __global const Triangle* tri, float limit, bool strict,
                         float* t_out, float* u_out, float* v_out)
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
    /* No culling: inside when the three have the same sign (0 on an edge). */
    if ((e_u < 0.0f || e_v < 0.0f || e_w < 0.0f) && (e_u > 0.0f || e_v > 0.0f || e_w > 0.0f))
        return false;
    float det = e_u + e_v + e_w;
    if (det == 0.0f)
        return false;
    float t_scaled = e_u * (r->sz * az) + e_v * (r->sz * bz) + e_w * (r->sz * cz);
    float inv_det = 1.0f / det;
    float t = t_scaled * inv_det;
    /* Written so that a NaN t fails. */
    if (!(t >= r->tmin && (strict ? t < limit : t <= limit)))
        return false;
    /* A zero-area triangle can still give det != 0 after rounding the shear;
     * never report it (its normal is undefined).  Only accepted hits pay. */
    float nx, ny, nz;
    geometric_normal(tri, &nx, &ny, &nz);
    if (nx == 0.0f && ny == 0.0f && nz == 0.0f)
        return false;
    *t_out = t;
    *u_out = e_v * inv_det;
    *v_out = e_w * inv_det;
    return true;
}

/* Pops the next stacked item that can still hold a hit within limit (items
 * whose box is entered beyond it are dropped); false when none is left. */
inline bool pop(const int* stack_index, const uint* stack_count, const float* stack_entry,
                int* sp, float limit, int* index, uint* count)
{
    while (*sp > 0) {
        --*sp;
        if (stack_entry[*sp] <= limit) {
            *index = stack_index[*sp];
            *count = stack_count[*sp];
            return true;
        }
    }
    return false;
}

/* Traverses the tree, nearer child first (closest hit) or until the first hit
 * (any hit).  Returns the tree-order index of the hit triangle or -1; sets
 * *overflow when the stack was too small (the host then raises).
 *
 * A stack item is a child slot: (index, count) with count 0 for an interior
 * node and count > 0 for a leaf.  The loop runs interior nodes until it holds
 * a leaf, then the leaf's triangles (Aila & Laine 2009's "while-while"), so
 * the work-items that a CPU runs in SIMD lanes stay in step. */
inline int traverse(const RayData* r, __global const FlatNode* nodes,
                    __global const Triangle* triangles, bool any_hit,
                    float* t_hit, float* u_hit, float* v_hit, bool* overflow)
{
    int stack_index[STACK_SIZE];
    uint stack_count[STACK_SIZE];
    float stack_entry[STACK_SIZE];
    int sp = 0;
    int hit_index = -1;
    float limit = r->tmax;     /* shrinks to the nearest hit so far */
    int index = 0;             /* the root is always an interior node */
    uint count = 0;
    bool done = false;
    *overflow = false;

    while (!done) {
        while (!done && count == 0) {
            __global const FlatNode* n = nodes + index;
            float entry_left, entry_right;
            /* (an EMPTY_CHILD's box is empty, so the test alone would do) */
            bool visit_left = hit_box(r, n->left_lo, n->left_hi, limit, &entry_left)
                              && n->left != EMPTY_CHILD;
            bool visit_right = hit_box(r, n->right_lo, n->right_hi, limit, &entry_right)
                               && n->right != EMPTY_CHILD;
            if (visit_left && visit_right) {
                bool left_first = entry_left <= entry_right;
                if (sp == STACK_SIZE) {
                    *overflow = true;
                    return hit_index;
                }
                stack_index[sp] = left_first ? n->right : n->left;
                stack_count[sp] = left_first ? n->right_count : n->left_count;
                stack_entry[sp] = left_first ? entry_right : entry_left;
                ++sp;
                index = left_first ? n->left : n->right;
                count = left_first ? n->left_count : n->right_count;
            } else if (visit_left || visit_right) {
                index = visit_left ? n->left : n->right;
                count = visit_left ? n->left_count : n->right_count;
            } else {
                done = !pop(stack_index, stack_count, stack_entry, &sp, limit, &index, &count);
            }
        }
        if (done)
            break;
        for (uint i = (uint)index; i < (uint)index + count; ++i) {
            float t, u, v;
            if (hit_triangle(r, triangles + i, limit, hit_index >= 0, &t, &u, &v)) {
                hit_index = (int)i;
                limit = t;
                *t_hit = t;
                *u_hit = u;
                *v_hit = v;
                if (any_hit)
                    return hit_index;
            }
        }
        done = !pop(stack_index, stack_count, stack_entry, &sp, limit, &index, &count);
    }
    return hit_index;
}

/* Closest hit of rays[0, ray_count) -> hits; overflow[0] is set to 1 if a
 * ray's traversal ran out of stack. */
__kernel void intersect_closest(__global const FlatNode* nodes,
                                __global const Triangle* triangles,
                                __global const TriangleRef* refs,
                                __global const Ray* rays,
                                __global Hit* hits,
                                __global int* overflow,
                                const uint ray_count)
{
    uint gid = get_global_id(0);
    if (gid >= ray_count)
        return;
    RayData r = prepare_ray(rays + gid);
    float t = INFINITY, u = 0.0f, v = 0.0f;
    bool out_of_stack;
    int index = traverse(&r, nodes, triangles, false, &t, &u, &v, &out_of_stack);
    if (out_of_stack)
        overflow[0] = 1;

    __global Hit* hit = hits + gid;
    if (index < 0) {
        hit->t = INFINITY;
        hit->geom_id = -1;
        hit->prim_id = -1;
        hit->u = 0.0f;
        hit->v = 0.0f;
        hit->normal[0] = hit->normal[1] = hit->normal[2] = 0.0f;
        return;
    }
    float nx, ny, nz;
    geometric_normal(triangles + index, &nx, &ny, &nz);
    /* Scale by the largest component first so tiny or huge triangles neither
     * underflow nor overflow the squared length. */
    float scale = 1.0f / fmax(fabs(nx), fmax(fabs(ny), fabs(nz)));
    nx *= scale;
    ny *= scale;
    nz *= scale;
    float inv_length = 1.0f / sqrt(nx * nx + ny * ny + nz * nz);
    hit->t = t;
    hit->geom_id = refs[index].geom_id;
    hit->prim_id = refs[index].prim_id;
    hit->u = u;
    hit->v = v;
    hit->normal[0] = nx * inv_length;
    hit->normal[1] = ny * inv_length;
    hit->normal[2] = nz * inv_length;
}

/* Occlusion of rays[0, ray_count): occluded[i] = 1 if anything is hit. */
__kernel void intersect_any(__global const FlatNode* nodes,
                            __global const Triangle* triangles,
                            __global const Ray* rays,
                            __global uchar* occluded,
                            __global int* overflow,
                            const uint ray_count)
{
    uint gid = get_global_id(0);
    if (gid >= ray_count)
        return;
    RayData r = prepare_ray(rays + gid);
    float t, u, v;
    bool out_of_stack;
    int index = traverse(&r, nodes, triangles, true, &t, &u, &v, &out_of_stack);
    if (out_of_stack)
        overflow[0] = 1;
    occluded[gid] = index >= 0 ? 1 : 0;
}
