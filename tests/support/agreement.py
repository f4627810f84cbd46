"""Two renderers' images of one scene compared as RENDERING.md says to:
block means over independent seeds, within their combined standard errors."""
from __future__ import annotations

import numpy as np


def assert_blocks_agree(theirs, ours, block: int, sigmas: float = 5.0, slack: float = 0.02):
    """(seeds, height, width, 3) images: every block x block block's mean
    within ``sigmas`` combined standard errors (over the seeds) plus
    ``slack`` of its level (``theirs`` is the reference)."""
    seeds, height, width, _ = theirs.shape
    for y in range(0, height, block):
        for x in range(0, width, block):
            a = theirs[:, y:y + block, x:x + block].reshape(seeds, -1, 3).astype(np.float64)
            b = ours[:, y:y + block, x:x + block].reshape(seeds, -1, 3).astype(np.float64)
            n = a.shape[1]
            stderr = np.sqrt((a.var(0, ddof=1).sum(0) + b.var(0, ddof=1).sum(0)) / seeds) / n
            difference = np.abs(a.mean((0, 1)) - b.mean((0, 1)))
            bound = sigmas * stderr + slack * a.mean((0, 1)) + 1e-6
            assert (difference <= bound).all(), (
                f"block ({y}, {x}): reference {a.mean((0, 1))}, ours {b.mean((0, 1))}, "
                f"allowed {bound}")
