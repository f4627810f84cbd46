"""Refit host side (kernels/build/refit.cl): new boxes for a finished Tree after
its vertices moved, the topology kept.  One launch per level of wide nodes,
from the deepest up, so that no node waits on another (a build computes its
boxes as it makes the radix tree instead: Karras 2012, radix_tree.py)."""
from __future__ import annotations

import pyopencl as cl

from ..device.runtime import Runtime
from ..core.tree import Tree, leaf_defines
from .pipeline import copy_vertices


def refit(rt: Runtime, tree: Tree, vertices: cl.Buffer | None,
          wait_for=None) -> list[cl.Event]:
    """Re-read ``tree``'s triangles from ``vertices`` (the scene's, moved;
    None for an indexed tree whose own vertices were moved in place) and
    recompute every box of its wide nodes; returns the launches' events."""
    if tree.vertex_ids is None and not tree.indexed:
        raise ValueError("this tree has no vertex ids (it was not made by a build): "
                         "it cannot be refit")
    tree.drop_dipoles(rt.pool)  # made anew from the moved triangles when next asked for
    kernel = rt.kernel("build/refit.cl", "refit_wide_level", **leaf_defines(tree.indexed))
    events: list[cl.Event] = []
    if tree.indexed and vertices is not None:  # the leaves' own copy, which their records name
        events.append(copy_vertices(rt, vertices, tree.vertex_count, tree.triangle_count,
                                    tree.triangles, wait_for=wait_for))
    for first, count in reversed(tree.levels):
        # an indexed tree's leaves read the vertices they hold (refit.cl)
        events.append(rt.run(kernel, count, first, count, tree.nodes,
                             None if tree.indexed else vertices, tree.vertex_ids,
                             tree.triangles, wait_for=events[-1:] or wait_for))
    return events
