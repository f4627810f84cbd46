/* Two-level scenes' compact trees (Scene(..., instances=..., compact=True);
 * hlbvh_cl/build/instances.py): every mesh's tree is built alone, its
 * IndexedTriangle records followed by its vertices (core/tree.h), and the
 * trees are joined as all the records, in the meshes' order, then all the
 * vertices.  A record names its corners relative to itself, so each mesh's
 * records, once copied, point `delta` cells from where their vertices now
 * lie: the same shift for all of a mesh's records.  Then mesh m's triangle
 * i is still cell triangle_base[m] + i, the index its refs and the
 * instance records use, as in the default layout. */
#include "core/portable.h"
#include "core/tree.h"

NARROW_KERNEL
void shift_corners(__global IndexedTriangle* records,
                   const uint first,  /* the mesh's records: [first, first + count) */
                   const uint count,
                   const int delta)
{
    uint i = get_global_id(0);
    if (i >= count)
        return;
    __global IndexedTriangle* r = records + first + i;
    r->corner[0] += delta;
    r->corner[1] += delta;
    r->corner[2] += delta;
}
