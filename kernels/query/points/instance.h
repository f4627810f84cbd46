/* Two-level scenes, the points' side: what a point query's walk of an
 * instance's mesh uses (query/walk/two_level.h has the maps themselves;
 * points.cl's instance visitors walk the meshes with it).
 *
 * Closest point.  An affine map keeps no distance unless it is a
 * similarity, so the distance is measured in the top (world) frame: a leaf
 * maps its triangles there (to_world) and measures Ericson's exact
 * point-triangle distance to the query point as given.  The mesh's tree is
 * walked with the point mapped into its frame (to_mesh), and a child box is
 * dropped by the larger of two lower bounds on its world distance (either
 * alone can be far from tight):
 *   - the mesh frame's box distance d times s, the least singular value of
 *     the map's linear part A: |A x - A y| >= s |x - y|.  Exact for a
 *     similarity, but a stretched map's s makes the ball it leaves to
 *     search larger than the nearest distance by the map's condition
 *     number, whatever the box's size;
 *   - the world distance to the box's world box (Arvo 1990, "Transforming
 *     Axis-Aligned Bounding Boxes", as hlbvh_cl/build/instances.py's
 *     world_boxes), loose by at most the box's own size, which shrinks down
 *     the tree.
 * Both are compared in the mesh frame's units (times reach_scale = 1 / s^2)
 * with the reach the best so far gives there, padded by REACH_PAD (the
 * rounding of distances and of reach_scale) and by the slack of the mapped
 * point (MeshFrame), and the world boxes by ARVO_PAD: rounding never
 * drops a nearer triangle.  The walks share one state, whose reach is in
 * the frame of the tree being walked and whose `best` is always the top
 * frame's. */
#ifndef POINTS_INSTANCE_H
#define POINTS_INSTANCE_H

#include "query/points/point.h"
#include "query/walk/two_level.h"

#ifdef INSTANCES
#define REACH_PAD (1.0f + 0x1p-20f)
#define MAP_SLACK 0x1p-20f
#define ARVO_PAD 0x1p-20f

/* An instance as its mesh's closest-point walk uses it: the query point in
 * the top frame, to_world (linear part A, offset b, and their magnitudes),
 * reach_scale and the mapped point's slack (a bound on its distance from
 * the exact image: the mapped coordinates' rounding, in double the final
 * one, in float a few, each within 2^-24 of the sum of its terms'
 * magnitudes, stays below MAP_SLACK times that sum). */
typedef struct {
    PointData world;
    float a[9], abs_a[9], b[3], abs_b[3];
    float reach_scale, slack;
} MeshFrame;

/* The point q in the instance's mesh frame. */
TRAVERSAL_INLINE void mesh_point(PointData* out, __global const Instance* in, const PointData* q)
{
    float3 m = map_point(in->to_mesh, (float3)(q->x, q->y, q->z));
    out->x = m.x;
    out->y = m.y;
    out->z = m.z;
}

/* The instance's MeshFrame for the query point q. */
TRAVERSAL_INLINE void mesh_frame(MeshFrame* f, __global const Instance* in, const PointData* q)
{
    __global const float* t = in->to_mesh;
    float size = 0.0f;
    for (int row = 0; row < 12; row += 4)
        size += ((abs_float(t[row] * q->x) + abs_float(t[row + 1] * q->y))
                 + abs_float(t[row + 2] * q->z)) + abs_float(t[row + 3]);
    f->slack = size * MAP_SLACK;
    f->world = *q;
    f->reach_scale = in->reach_scale;
    for (int row = 0; row < 3; ++row) {
        for (int k = 0; k < 3; ++k) {
            f->a[3 * row + k] = in->to_world[4 * row + k];
            f->abs_a[3 * row + k] = abs_float(in->to_world[4 * row + k]);
        }
        f->b[row] = in->to_world[4 * row + 3];
        f->abs_b[row] = abs_float(in->to_world[4 * row + 3]);
    }
}

/* The squared mesh-frame reach for the top frame's squared distance `best`. */
TRAVERSAL_INLINE float mesh_reach(float best, const MeshFrame* f)
{
    /* best 0 stays 0 where reach_scale is inf (an instance scaled below
     * about 1e-19), not 0 * inf = NaN, which would skip the instance */
    float r = SQRT(best > 0.0f ? best * f->reach_scale : 0.0f) * REACH_PAD + f->slack;
    return r * r;
}

/* The mesh walk's node test: per child, the larger of the two bounds (in
 * the mesh frame's units) as its entry, and the children within the reach.
 * The world box of a child is its centre c mapped and its half extent e
 * under |A|; ARVO_PAD times the magnitudes the mapping summed covers its
 * rounding.  An unused slot's empty box gives NaN there, which GROW_HI
 * ignores, and is left out by its lo <= hi test. */
#define NODE_ROW(row) LOAD_ROW(float_lanes, node->row) /* names a node's field */
TRAVERSAL_INLINE uint children_mapped(const PointData* q, __global const WideNode* node,
                                      const Found_point* s, ChildEntries* entry,
                                      const MeshFrame* f)
{
    float_lanes near = box_distance2(q, node);
    float_lanes c[3] = {(NODE_ROW(lo_x) + NODE_ROW(hi_x)) * 0.5f,
                        (NODE_ROW(lo_y) + NODE_ROW(hi_y)) * 0.5f,
                        (NODE_ROW(lo_z) + NODE_ROW(hi_z)) * 0.5f};
    float_lanes e[3] = {(NODE_ROW(hi_x) - NODE_ROW(lo_x)) * 0.5f,
                        (NODE_ROW(hi_y) - NODE_ROW(lo_y)) * 0.5f,
                        (NODE_ROW(hi_z) - NODE_ROW(lo_z)) * 0.5f};
    float p[3] = {f->world.x, f->world.y, f->world.z};
    float_lanes world = (float_lanes)(0.0f);
    for (int row = 0; row < 3; ++row) {
        const float* a = f->a + 3 * row;
        const float* m = f->abs_a + 3 * row;
        float_lanes centre = ((a[0] * c[0] + a[1] * c[1]) + a[2] * c[2]) + f->b[row];
        float_lanes extent = (m[0] * e[0] + m[1] * e[1]) + m[2] * e[2];
        float_lanes size = ((m[0] * abs_lanes(c[0]) + m[1] * abs_lanes(c[1]))
                            + m[2] * abs_lanes(c[2])) + f->abs_b[row] + extent;
        float_lanes gap = GROW_HI((float_lanes)(0.0f),
                                  abs_lanes(p[row] - centre) - extent - size * ARVO_PAD);
        world += gap * gap;
    }
    entry->lanes = GROW_HI(near, world * f->reach_scale);
    return lane_mask((entry->lanes <= (float_lanes)(s->reach))
                     & (NODE_ROW(lo_x) <= NODE_ROW(hi_x)));
}
#undef NODE_ROW

/* Triangle t of the instance's mesh, in the top frame. */
TRAVERSAL_INLINE void mapped_corners(__global const Instance* in, TRIANGLE_AT t,
                                     float3* a, float3* b, float3* c)
{
    *a = map_point(in->to_world, LOAD_XYZ(t->v0));
    *b = map_point(in->to_world, LOAD_XYZ(t->v1));
    *c = map_point(in->to_world, LOAD_XYZ(t->v2));
}

/* A mesh walk's leaf: each triangle's top-frame distance to the query
 * point; a nearer one (at the reach only while there is none, as
 * closest_leaf) becomes the best, of instance `owner`, and shrinks the
 * mesh-frame reach. */
TRAVERSAL_INLINE bool closest_mapped_leaf(Found_point* s, __global const Leaf* triangles,
                                          int first, uint count, __global const Instance* in,
                                          const MeshFrame* f, int owner)
{
    float3 p = (float3)(f->world.x, f->world.y, f->world.z);
    for (int i = first; i < first + (int)count; ++i) {
        float3 a, b, c;
        LEAF_CORNERS(t, triangles, i);
        mapped_corners(in, t, &a, &b, &c);
        float u, v;
        float d2 = closest_on_corners(a, b, c, p, &u, &v);
        if (d2 < s->best || (s->index < 0 && d2 <= s->best)) {
            s->index = i;
            s->best = d2;
            s->u = u;
            s->v = v;
            s->instance = owner;
            s->reach = mesh_reach(d2, f);
        }
    }
    return false;
}

#endif /* INSTANCES */

#endif /* POINTS_INSTANCE_H */
