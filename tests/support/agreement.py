"""Two renderers' images of one scene compared as RENDERING.md says to:
block means over independent seeds, within their combined standard errors."""
from __future__ import annotations

import numpy as np

from bench.path import relmse  # noqa: F401  (the score bench/path.py gives renders)


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


def assert_falls_as_one_over_spp(errors, counts, reference_spp: int) -> None:
    """An unbiased estimator's relMSE against a reference of reference_spp
    is its variance over spp plus the reference's own, a / n + a /
    reference_spp (a bias would level it off): fit a, then the log-log slope
    of what is left once the reference's share is taken off is -1 within
    0.2."""
    errors, counts = np.asarray(errors, np.float64), np.asarray(counts, np.float64)
    a = float(np.mean(errors / (1.0 / counts + 1.0 / reference_spp)))
    own = errors - a / reference_spp
    assert (own > 0).all(), (errors, a)
    slope = np.polyfit(np.log(counts), np.log(own), 1)[0]
    assert -1.2 < slope < -0.8, (slope, errors)
