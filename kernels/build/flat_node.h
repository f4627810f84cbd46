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

/* What the host reads of the flat tree, with the rest of the build's
 * figures, in the build's one read (issue 57; flatten.cl's
 * summarise_flat_tree writes it). */
typedef struct {
    int node_count;   /* flat nodes */
    int leaf_count;
    int depth;        /* nodes on the longest root-to-leaf path */
    int clusters;     /* the SAH top's clusters (1 without it) */
    int root_is_leaf; /* one leaf holds every triangle */
    float sah_cost;   /* not normalised (0 for a leaf root: the host's) */
    float lo[3];      /* the root's box */
    float hi[3];
} FlatSummary;

#endif /* FLAT_NODE_H */
