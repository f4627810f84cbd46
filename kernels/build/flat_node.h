/* The flat binary tree: the build's scratch, which build/widen.cl collapses
 * into the wide tree (core/tree.h).  Mirrored by hlbvh_cl/core/layout.py. */
#ifndef FLAT_NODE_H
#define FLAT_NODE_H

/* One node: both children's boxes live in the parent, so one read gives
 * both (Aila & Laine 2009).  A child with count 0 is a node, with count > 0
 * a leaf (index = first triangle), EMPTY_CHILD (core/tree.h) none. 64 bytes. */
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

#endif /* FLAT_NODE_H */
