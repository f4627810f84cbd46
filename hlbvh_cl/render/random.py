"""kernels/render/random.h on the host: the salts of random_unit's dimensions
(random_salt), which a wavefront stage takes as an argument instead of hashing
them in every work-item, with the same bits as the kernels'."""
from __future__ import annotations

import numpy as np
import pyopencl.cltypes as cltypes


def hash_pcg(value) -> np.ndarray:
    """random.h's hash_pcg (Jarzynski & Olano 2020) over uint32 values,
    wrapping as the kernel's uint arithmetic does."""
    v = np.atleast_1d(np.asarray(value, np.uint32))
    state = v * np.uint32(747796405) + np.uint32(2891336453)
    word = ((state >> ((state >> np.uint32(28)) + np.uint32(4))) ^ state) * np.uint32(277803737)
    return (word >> np.uint32(22)) ^ word


def salts8(sample: int, first: int) -> np.void:
    """random_salt(sample, first + k) for k = 0..7, as a uint8 kernel argument."""
    dimensions = np.arange(first, first + 8, dtype=np.uint32)
    salts = hash_pcg(np.uint32(sample) + hash_pcg(dimensions))
    # a view, not cltypes.make_uint8, which builds its value through eval:
    # this runs once per bounce on the host, which a GPU's render waits on
    return np.ascontiguousarray(salts, np.uint32).view(cltypes.uint8)[0]
