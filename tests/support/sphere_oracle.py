"""A float64 oracle of closest hits over a square ground and analytic
spheres (Scene(spheres=...)), for tests/query/test_spheres.py and the
Oclgrind tier."""
from __future__ import annotations

import numpy as np


def oracle(origins, directions, spheres, tmin=0.0, tmax=np.inf, scale=1.0):
    """float64 closest hits over the ground (y = 0, |x|, |z| <= 4 times
    ``scale``) and the spheres ((S, 4) centres and radii), of the rays as
    float32 holds them: t, geom_id (-1: none), and the gap to the
    runner-up's t (relative), where float32 may swap them."""
    o = np.asarray(origins, np.float32).astype(np.float64)
    d = np.asarray(directions, np.float32).astype(np.float64)
    n = len(o)
    tmin = np.broadcast_to(np.asarray(tmin, np.float64), (n,))
    tmax = np.broadcast_to(np.asarray(tmax, np.float64), (n,))
    candidates = np.full((n, 1 + len(spheres)), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[:, 1] / d[:, 1]
        p = o + t[:, None] * d
        on = (np.abs(p[:, 0]) <= 4 * scale) & (np.abs(p[:, 2]) <= 4 * scale)
        candidates[:, 0] = np.where(on & (t >= tmin) & (t <= tmax), t, np.inf)
        for k, (cx, cy, cz, r) in enumerate(spheres):
            f = o - [cx, cy, cz]
            a, b, c = (d * d).sum(1), -(f * d).sum(1), (f * f).sum(1) - r * r
            root = np.sqrt(b * b - a * c)
            for t in ((b - root) / a, (b + root) / a):  # the nearer first
                take = (t >= tmin) & (t <= tmax) & np.isinf(candidates[:, k + 1])
                candidates[take, k + 1] = t[take]
    order = np.sort(candidates, axis=1)
    geom = np.where(np.isfinite(order[:, 0]), np.argmin(candidates, axis=1), -1)
    with np.errstate(invalid="ignore"):
        gap = (order[:, 1] - order[:, 0]) / order[:, 0]
    return order[:, 0], geom, np.where(np.isnan(gap), np.inf, gap)
