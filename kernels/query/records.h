/* The ray queries' records: a ray as the closest-hit and any-hit kernels
 * read it (the renderer's rays; hlbvh_cl/query/rays.py fills these) and a
 * closest hit as they write it.  Mirrored by hlbvh_cl/core/layout.py. */
#ifndef RECORDS_H
#define RECORDS_H

/* A ray: hits count for tmin <= t <= tmax (query/rays.cl). */
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

#endif /* RECORDS_H */
