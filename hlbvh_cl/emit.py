"""Stage 4 host side: Karras (2012) emission of the radix tree (kernels/emit.cl)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl as cl


@dataclass
class RadixTree:
    """Binary radix tree over n sorted primitives: internal nodes 0..n-2,
    leaf of sorted primitive j = node n-1+j."""

    n: int
    left_child: cl.Buffer    # int32[n-1]
    right_child: cl.Buffer   # int32[n-1]
    parent: cl.Buffer        # int32[2n-1], -1 at the root
    range_first: cl.Buffer   # int32[n-1]: first sorted primitive under the node
    range_last: cl.Buffer    # int32[n-1]

    @classmethod
    def allocate(cls, rt, n: int) -> "RadixTree":
        def ints(count):
            return rt.pool.take(count * 4)
        return cls(n, ints(n - 1), ints(n - 1), ints(2 * n - 1), ints(n - 1), ints(n - 1))

    def read(self, queue) -> dict[str, np.ndarray]:
        """Host copies, for tests."""
        out = {}
        for name, count in (("left_child", self.n - 1), ("right_child", self.n - 1),
                            ("parent", 2 * self.n - 1), ("range_first", self.n - 1),
                            ("range_last", self.n - 1)):
            out[name] = np.empty(count, np.int32)
            if count:
                cl.enqueue_copy(queue, out[name], getattr(self, name))
        return out


def emit_internal_nodes(rt, keys: cl.Buffer, bits: int, tree: RadixTree,
                        wait_for=None) -> list[cl.Event]:
    if tree.n < 2:  # a lone leaf: it is the root
        return [cl.enqueue_fill_buffer(rt.queue, tree.parent, np.int32(-1), 0, 4,
                                       wait_for=wait_for)]
    kernel = rt.kernel("emit.cl", "emit_internal_nodes", MORTON_BITS=bits)
    return [rt.run(kernel, tree.n - 1, keys, tree.n, tree.left_child, tree.right_child,
                   tree.parent, tree.range_first, tree.range_last, wait_for=wait_for)]
