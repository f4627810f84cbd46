"""Two renderers' images of one scene, compared as pbrt's and Mitsuba's
test suites do: by the means of blocks of pixels over independent seeds,
within their combined standard errors (RENDERING.md)."""
import numpy as np


def assert_blocks_agree(theirs, ours, block=8, sigmas=5.0, relative=0.02):
    """``theirs`` and ``ours``, (seeds, height, width, 3) each: every block x
    block block's mean within ``sigmas`` combined standard errors (of the
    seeds' block means) plus ``relative`` of its level (silhouettes'
    sub-pixel footing)."""
    assert theirs.shape == ours.shape
    seeds, height, width = theirs.shape[:3]
    for y in range(0, height, block):
        for x in range(0, width, block):
            a = theirs[:, y:y + block, x:x + block].reshape(seeds, -1, 3).astype(np.float64)
            b = ours[:, y:y + block, x:x + block].reshape(seeds, -1, 3).astype(np.float64)
            pixels = a.shape[1]
            stderr = np.sqrt((a.var(0, ddof=1).sum(0) + b.var(0, ddof=1).sum(0)) / seeds) / pixels
            difference = np.abs(a.mean((0, 1)) - b.mean((0, 1)))
            bound = sigmas * stderr + relative * a.mean((0, 1)) + 1e-6
            assert (difference <= bound).all(), (
                f"block ({y}, {x}): Mitsuba {a.mean((0, 1))}, ours {b.mean((0, 1))}")
