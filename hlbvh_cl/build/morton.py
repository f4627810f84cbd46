"""Stage 2 host side: Morton codes of triangle centroids (kernels/build/morton.cl)."""
from __future__ import annotations

import numpy as np
import pyopencl as cl

MORTON_BITS = (30, 63)


def key_dtype(bits: int) -> np.dtype:
    # an int, not merely equal to one: 30.0 would reach the kernels as -DMORTON_BITS=30.0f
    if isinstance(bits, bool) or not isinstance(bits, (int, np.integer)) or bits not in MORTON_BITS:
        raise ValueError(f"morton_bits must be the int 30 or 63, got {bits!r}")
    return np.dtype(np.uint32 if bits == 30 else np.uint64)


def morton_codes(rt, centroids: cl.Buffer, triangle_count: int, bounds: cl.Buffer,
                 inverse_extent: cl.Buffer, keys: cl.Buffer, primitive_ids: cl.Buffer,
                 bits: int, wait_for=None) -> list[cl.Event]:
    """keys[i] <- Morton code of centroids[i] (float4, from the bounds stage)
    over the centroid box bounds[1], whose inverse extent the bounds stage
    gives too; primitive_ids[i] <- i."""
    key_dtype(bits)
    kernel = rt.kernel("build/morton.cl", "morton_codes", MORTON_BITS=bits)
    return [rt.run(kernel, triangle_count, centroids, triangle_count, bounds, inverse_extent,
                   keys, primitive_ids, wait_for=wait_for)]
