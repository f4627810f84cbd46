/* The winding-number walk's dipoles (WideDipoles, core/tree.h; Barill et al.
 * 2018, sec. 3.2, order 1), one per child of every wide node, computed
 * bottom-up one launch per level of wide nodes from the deepest up, as
 * refit.cl computes boxes: when a level runs, every child node it reads is
 * final.  A leaf lane sums its triangles; an interior lane merges its child
 * node's lanes: p the area-weighted mean of theirs, a their sum, and a
 * radius that holds each lane's ball, max(|p - p_i| + r_i).
 */
#include "core/portable.h"
#include "core/spelled.h"
#include "core/leaf.h"
#include "core/tree.h"

#pragma OPENCL FP_CONTRACT OFF

/* Running sums of one lane. */
typedef struct {
    float3 weighted;  /* sum of area * centre */
    float3 centres;   /* sum of centres, for a lane of zero area */
    float3 a;
    float area;
    int parts;
} DipoleSum;

inline void add_part(DipoleSum* sum, float3 centre, float3 a, float area)
{
    sum->weighted += area * centre;
    sum->centres += centre;
    sum->a += a;
    sum->area += area;
    sum->parts += 1;
}

/* The weighted centre; the plain mean when the parts have no area. */
inline float3 sum_centre(const DipoleSum* sum)
{
    return sum->area > 0.0f ? sum->weighted / sum->area : sum->centres / (float)sum->parts;
}

inline void store_lane(__global WideDipoles* d, int k, float3 p, float3 a, float area,
                       float radius)
{
    d->p_x[k] = p.x;
    d->p_y[k] = p.y;
    d->p_z[k] = p.z;
    d->a_x[k] = a.x;
    d->a_y[k] = a.y;
    d->a_z[k] = a.z;
    d->area[k] = area;
    d->radius[k] = radius;
}

inline float distance3(float3 a, float3 b)
{
    float3 d = a - b;
    return sqrt(d.x * d.x + d.y * d.y + d.z * d.z);
}

/* A leaf lane: the triangles [first, first + count). */
inline void leaf_dipole(__global const Leaf* triangles, int first, uint count,
                        __global WideDipoles* d, int k)
{
    DipoleSum sum = {(float3)(0.0f), (float3)(0.0f), (float3)(0.0f), 0.0f, 0};
    for (int j = first; j < first + (int)count; ++j) {
        LEAF_CORNERS(t, triangles, j);
        float3 v0 = LOAD_XYZ(t->v0), v1 = LOAD_XYZ(t->v1), v2 = LOAD_XYZ(t->v2);
        float3 a = 0.5f * cross(v1 - v0, v2 - v0);
        add_part(&sum, (v0 + v1 + v2) / 3.0f, a, length(a));
    }
    float3 p = sum_centre(&sum);
    float radius = 0.0f;
    for (int j = first; j < first + (int)count; ++j) {
        LEAF_CORNERS(t, triangles, j);
        radius = GROW_HI(radius, distance3(LOAD_XYZ(t->v0), p));
        radius = GROW_HI(radius, distance3(LOAD_XYZ(t->v1), p));
        radius = GROW_HI(radius, distance3(LOAD_XYZ(t->v2), p));
    }
    store_lane(d, k, p, sum.a, sum.area, radius);
}

/* An interior lane: the used lanes of its child node `c`. */
inline void node_dipole(__global const WideNode* nodes, __global const WideDipoles* dipoles,
                        int c, __global WideDipoles* d, int k)
{
    __global const WideNode* child = nodes + c;
    __global const WideDipoles* below = dipoles + c;
    DipoleSum sum = {(float3)(0.0f), (float3)(0.0f), (float3)(0.0f), 0.0f, 0};
    for (int i = 0; i < WIDE_ARITY; ++i)
        if (child->count[i] > 0 || child->child[i] != EMPTY_CHILD)
            add_part(&sum, (float3)(below->p_x[i], below->p_y[i], below->p_z[i]),
                     (float3)(below->a_x[i], below->a_y[i], below->a_z[i]), below->area[i]);
    float3 p = sum_centre(&sum);
    float radius = 0.0f;
    for (int i = 0; i < WIDE_ARITY; ++i)
        if (child->count[i] > 0 || child->child[i] != EMPTY_CHILD)
            radius = GROW_HI(radius, distance3((float3)(below->p_x[i], below->p_y[i],
                                                        below->p_z[i]), p) + below->radius[i]);
    store_lane(d, k, p, sum.a, sum.area, radius);
}

/* Every lane of the wide nodes [level_first, level_first + level_count),
 * whose child nodes (deeper levels) already have their dipoles.  The tree
 * starts at nodes[node_base] and triangles[triangle_base], its dipoles at
 * dipoles[node_base]: one tree among the meshes' trees of a two-level scene
 * (hlbvh_cl/build/instances.py's MeshTrees), its indices its own; 0 and 0 for a
 * flat scene's one tree. */
NARROW_KERNEL
void dipoles_level(int level_first, int level_count, int node_base, int triangle_base,
                   __global const WideNode* nodes, __global const Leaf* triangles,
                   __global WideDipoles* dipoles)
{
    int i = get_global_id(0);
    if (i >= level_count)
        return;
    nodes += node_base;
    triangles += triangle_base;
    dipoles += node_base;
    int n = level_first + i;
    __global const WideNode* node = nodes + n;
    for (int k = 0; k < WIDE_ARITY; ++k) {
        if (node->count[k] > 0)
            leaf_dipole(triangles, node->child[k], node->count[k], dipoles + n, k);
        else if (node->child[k] != EMPTY_CHILD)
            node_dipole(nodes, dipoles, node->child[k], dipoles + n, k);
        else
            store_lane(dipoles + n, k, (float3)(0.0f), (float3)(0.0f), 0.0f, 0.0f);
    }
}
