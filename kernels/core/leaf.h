/* How a walk reaches the corners of a leaf's triangle, in either leaf
 * layout (core/tree.h): a Leaf is what the tree's leaf buffer holds one of
 * per triangle, and LEAF_CORNERS(name, leaves, i) declares `name`, of type
 * TRIANGLE_AT, through which name->v0, v1 and v2 read triangle i's corners as
 * arrays of three floats.  The default leaves are the corners themselves
 * (Triangle), so TRIANGLE_AT is a pointer into the buffer and nothing changes
 * from a plain read.  With INDEXED_LEAVES (Scene(..., compact=True)) they
 * are IndexedTriangle records, and TRIANGLE_AT points at three pointers to the
 * vertices the records name: the same floats, so the same arithmetic and
 * the same hits, bit for bit. */
#ifndef LEAF_H
#define LEAF_H

#include "core/tree.h"

#ifdef INDEXED_LEAVES

typedef IndexedTriangle Leaf;

typedef struct {
    __global const float* v0;
    __global const float* v1;
    __global const float* v2;
} Corners;

#define TRIANGLE_AT const Corners*

/* A record's corner k is the cell corner[k] cells on from the record. */
inline void leaf_corners(__global const Leaf* leaf, Corners* out)
{
    out->v0 = (__global const float*)(leaf + leaf->corner[0]);
    out->v1 = (__global const float*)(leaf + leaf->corner[1]);
    out->v2 = (__global const float*)(leaf + leaf->corner[2]);
}

#define LEAF_CORNERS(name, leaves, i)      \
    Corners name##_corners;                \
    leaf_corners((leaves) + (i), &name##_corners); \
    TRIANGLE_AT name = &name##_corners

#else

typedef Triangle Leaf;

#define TRIANGLE_AT __global const Triangle*
#define LEAF_CORNERS(name, leaves, i) TRIANGLE_AT name = (leaves) + (i)

#endif

#endif /* LEAF_H */
