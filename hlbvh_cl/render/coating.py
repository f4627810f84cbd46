"""What plastic and roughplastic (kernels/render/bsdfs/) need of their
dielectric coating, computed once per material in float64 (Mitsuba 3
computes the same when a plastic is loaded):

- ``diffuse_fresnel(eta)``: a smooth interface's reflectance averaged over
  cosine-weighted incidence, by the fits Mitsuba uses (Egan & Hilgeman 1973
  for eta < 1; d'Eon & Irving 2011, "A quantized-diffusion model for
  rendering translucent materials", for eta >= 1);
- ``rough_transmission(kind, alpha, eta, cosines)``: a rough interface's
  transmittance from outside at each cosine, and
  ``rough_internal_reflectance(kind, alpha, eta)``: its reflectance from
  inside averaged over cosine-weighted incidence, as Mitsuba's roughplastic
  tabulates them (its 64 cosines, and its mean over them);
  ``roughplastic_tables`` both, remembered for the materials seen last.

The rough integrals run over the microfacet normals m, drawn by the map
that samples D(m) cos(m) (Walter et al. 2007, eq. 28 and 35), with
Gauss-Legendre nodes: sum over m of the visible-normal weight
G1(wi, m) (wi . m) / (wi.z m.z) times (1 - F) G1 of the refracted
direction, or F G1 of the reflected one (Walter et al. 2007, eq. 15-21).
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

#: Gauss-Legendre nodes per dimension of the microfacet integrals.
NODES = 128


def diffuse_fresnel(eta: float) -> float:
    """The cosine-weighted mean reflectance of a smooth interface of
    relative index eta, seen from the side eta is relative to."""
    if eta < 1.0:
        return 0.0636 / eta + eta * (eta * -1.4399 + 0.7099) + 0.6681
    x = 1.0 / eta
    return float(np.polyval([-1.36881, 4.98554, -7.80989, 6.75335, -3.4793, 0.919317], x))


def _fresnel(cos_i: np.ndarray, eta: float) -> tuple[np.ndarray, np.ndarray]:
    """Unpolarised reflectance at cos_i > 0 and the transmitted cosine's
    magnitude (0 under total internal reflection)."""
    sin2_t = (1.0 - cos_i**2) / eta**2
    cos_t = np.sqrt(np.clip(1.0 - sin2_t, 0.0, None))
    a_s = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    a_p = (cos_t - eta * cos_i) / (cos_t + eta * cos_i)
    return np.where(sin2_t >= 1.0, 1.0, 0.5 * (a_s**2 + a_p**2)), cos_t


def smith_g1(kind: str, alpha: float, v: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Smith's G1 as microfacet.h computes it (Beckmann: Walter et al.'s
    rational fit, eq. 27); v and m (..., 3), unit."""
    cos2 = np.clip(v[..., 2] ** 2, 1e-300, None)
    tan2 = np.clip(1.0 - cos2, 0.0, None) / cos2
    if kind == "ggx":
        g = 2.0 / (1.0 + np.sqrt(1.0 + alpha**2 * tan2))
    else:
        with np.errstate(divide="ignore", invalid="ignore"):  # a = inf at the normal: 1
            a = 1.0 / (alpha * np.sqrt(tan2))
            g = np.where(a >= 1.6, 1.0, (3.535 * a + 2.181 * a * a)
                         / (1.0 + 2.276 * a + 2.577 * a * a))
    return np.where((v * m).sum(-1) * v[..., 2] > 0, g, 0.0)


def _normals(kind: str, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """Microfacet normals (K, 3) at the Gauss-Legendre nodes of the D cos
    map, and their quadrature weights (summing to 1)."""
    x, w = np.polynomial.legendre.leggauss(NODES)
    u, w = (x + 1) / 2, w / 2
    u1, u2 = np.meshgrid(u, u, indexing="ij")
    weight = np.outer(w, w).reshape(-1)
    if kind == "ggx":
        tan2 = alpha**2 * u1 / (1.0 - u1)
    else:
        tan2 = -alpha**2 * np.log1p(-u1)
    cos = 1.0 / np.sqrt(1.0 + tan2)
    sin = np.sqrt(1.0 - cos**2)
    phi = 2 * np.pi * u2
    m = np.stack([sin * np.cos(phi), sin * np.sin(phi), cos], -1).reshape(-1, 3)
    return m, weight


def _rough(kind: str, alpha: float, eta: float, cosines, transmitted: bool) -> np.ndarray:
    mu = np.asarray(cosines, np.float64)
    wi = np.stack([np.sqrt(1 - mu**2), np.zeros_like(mu), mu], -1)[:, None, :]  # (C, 1, 3)
    m, weight = _normals(kind, alpha)
    m = m[None]
    dot = (wi * m).sum(-1)
    visible = smith_g1(kind, alpha, wi, m) * np.clip(dot, 0, None) / (wi[..., 2] * m[..., 2])
    f, cos_t = _fresnel(np.clip(dot, 1e-300, None), eta)
    if transmitted:
        wo = -wi / eta + m * (dot / eta - cos_t)[..., None]
        share = (1 - f) * np.where(wo[..., 2] < 0, smith_g1(kind, alpha, wo, m), 0.0)
    else:
        wo = 2 * dot[..., None] * m - wi
        share = f * np.where(wo[..., 2] > 0, smith_g1(kind, alpha, wo, m), 0.0)
    return (visible * share * weight).sum(-1)


def rough_transmission(kind: str, alpha: float, eta: float, cosines) -> np.ndarray:
    """The share of light from outside at each cosine that a rough
    interface (``kind`` "ggx" or "beckmann") lets in."""
    return _rough(kind, alpha, eta, cosines, transmitted=True)


def rough_internal_reflectance(kind: str, alpha: float, eta: float, count: int) -> float:
    """The interface's reflectance from inside (index ratio 1 / eta), twice
    its mean times the cosine over ``count`` cosines evenly in [0, 1]
    (Mitsuba's estimate of the cosine-weighted mean)."""
    mu = np.maximum(1e-6, np.linspace(0, 1, count))
    return float(2 * np.mean(_rough(kind, alpha, 1 / eta, mu, transmitted=False) * mu))


@lru_cache(maxsize=64)
def roughplastic_tables(kind: str, alpha: float, eta: float,
                        count: int) -> tuple[np.ndarray, float]:
    """A roughplastic's transmittance at ``count`` cosines evenly in [0, 1]
    (the first at 1e-6, as Mitsuba's) and its internal reflectance; the
    table is read-only, shared between the calls that ask alike."""
    cosines = np.maximum(1e-6, np.linspace(0.0, 1.0, count))
    table = rough_transmission(kind, alpha, eta, cosines)
    table.flags.writeable = False
    return table, rough_internal_reflectance(kind, alpha, eta, count)
