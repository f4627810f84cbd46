/* A ray's class: the axis along which its direction is largest, along which
 * the watertight test of Woop, Benthin & Wald 2013 projects (kz; ties go to
 * the lower axis), and the signs of its direction's components, which pick
 * a slab test's near planes (Williams et al. 2005).  Rays of one class make
 * the same choices in both tests, so only they trace together as a packet
 * (packet.h), and ray batches run ordered by class first (query/order.cl). */
#ifndef RAY_CLASS_H
#define RAY_CLASS_H

#include "query/walk/node.h"

/* kz from the direction's absolute components. */
TRAVERSAL_INLINE int shear_axis(float ax, float ay, float az)
{
    return (ax >= ay && ax >= az) ? 0 : (ay >= az ? 1 : 2);
}

#endif /* RAY_CLASS_H */
