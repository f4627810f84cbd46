/* How a launch sized for a bound hands out work that the device counted
 * after the host sized it (the path integrator's later bounces: the host
 * launches each over the count it read a bounce behind, LOOKAHEAD in
 * hlbvh_cl/render/integrators/path.py, and the kernels read the live count
 * on the device).  The work-groups that have work are spread evenly over
 * the launch rather than being its first ones: a CPU runtime that deals
 * its threads work-groups in large runs (PoCL: hundreds at a time) would
 * otherwise give them to one thread while the others find only empty ones
 * and wait.  Whole groups move, so a GPU's groups keep their work-items
 * together, and each piece of work is done as before. */
#ifndef CORE_LAUNCH_H
#define CORE_LAUNCH_H

#include "core/portable.h"

/* The group of work that this work-group takes when `live` groups of
 * work (live <= the launch's groups G) are spread over the launch: group
 * w takes group q - 1 where q = floor((w + 1) live / G) exceeds
 * floor(w live / G), so each of 0..live-1 once, in order.  False where w
 * takes none: the same answer for all of its work-items, which may then
 * return together before a barrier. */
FORCE_INLINE bool spread_group(ulong live, uint* taken)
{
    ulong groups = (ulong)get_num_groups(0), w = (ulong)get_group_id(0);
    ulong q = (w + 1u) * live / groups;
    *taken = (uint)q - 1u;
    return q != w * live / groups;
}

#endif /* CORE_LAUNCH_H */
