"""The winding number's far field (kernels/build/dipoles.cl): per wide node,
the order-1 dipole of each child's triangles (Barill et al. 2018, "Fast
Winding Numbers for Soups and Clouds"), made on the device bottom-up, one
launch per level.  A tree's dipoles are made by the first query that needs
them (hlbvh_cl.query.points) and dropped by a refit or a rebuild."""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from ..core import layout
from ..core.paths import kernel_of
from ..core.tree import leaf_defines
from ..device.runtime import Runtime
from .instances import InstancedTree

KERNEL = kernel_of(__name__)


def dipoles(rt: Runtime, tree) -> cl.Buffer:
    """The tree's dipoles (WideDipoles per node), made on first use after a
    build or refit.  An instanced scene's are its meshes' trees'
    (MeshTrees.dipoles, one buffer in the nodes' places, made once for
    every top tree over them)."""
    owner = tree.meshes if isinstance(tree, InstancedTree) else tree
    # under the build lock from the check to the store: views of one scene
    # (hlbvh_cl.travel) share the tree, and a buffer taken during a build
    # would go back with its scratch
    with rt.build_lock:
        if owner.dipoles is None:
            made = rt.pool.take(owner.node_count * layout.WIDE_DIPOLES.itemsize)
            kernel = rt.kernel(KERNEL, "dipoles_level", **leaf_defines(owner.indexed))
            if isinstance(tree, InstancedTree):
                parts = zip(owner.levels, owner.node_base, owner.triangle_base)
            else:
                parts = [(tree.levels, 0, 0)]
            events = []
            for levels, node_base, triangle_base in parts:
                for first, count in reversed(levels):
                    events.append(rt.run(kernel, count, first, count, np.int32(node_base),
                                         np.int32(triangle_base), owner.nodes, owner.triangles,
                                         made, wait_for=events[-1:] or None))
            owner.dipoles = made
        return owner.dipoles
