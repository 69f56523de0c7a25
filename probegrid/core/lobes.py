"""Reflection lobes shared by the environment filters and the analytic light maps.

Every specular map this project makes is the *normalised* average of incoming radiance under a
lobe centred on the reflection direction ``R``::

    Specular[R] = integral L(w) K(R . w) dw / integral K(R . w) dw

so a constant environment of radiance ``L`` gives ``L`` at every level, and a delta light of
irradiance ``E`` (at normal incidence, ``integral L dw = E``) gives ``E K(R . l) / integral K``.

Lobes
-----
* Phong / cosine power (the seeds' ``(R . L)^P``): ``K(c) = max(0, c)^P``, with
  ``integral K dw = 2 pi / (P + 1)``.
* GGX split-sum prefilter (Karis 2013, "Real Shading in Unreal Engine 4"; the n = v = r
  assumption): with ``h = normalize(R + w)``, ``K(w) = D(n . h) max(0, R . w) / 4`` where ``D`` is
  the GGX / Trowbridge-Reitz NDF ``D(c) = alpha^2 / (pi (c^2 (alpha^2 - 1) + 1)^2)``. This is
  exactly the weight that importance sampling ``D(h)(n . h)`` and weighting by ``n . l`` converges
  to, since with n = v the pdf of ``l`` is ``D (n . h) / (4 (v . h)) = D / 4``. ``n . h`` equals
  ``cos(theta / 2) = sqrt((1 + cos theta) / 2)`` for the angle theta between ``R`` and ``w``.
  Its integral, with ``dw_l = 4 (n . h) dw_h`` and ``R . w = 2 (n . h)^2 - 1``, is the 1-D integral
  ``2 pi int_0^{pi/4} D(cos p) cos p (2 cos^2 p - 1) sin p dp``, evaluated by Gauss-Legendre
  quadrature in :func:`ggx_kernel_integral`.

Roughness
---------
Perceptual roughness ``r`` (glTF ``roughnessFactor``), ``alpha = r^2``. A specular mip chain of
``levels`` levels holds ``r = level / (levels - 1)``; level 0 (r = 0) is the unblurred image.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "ggx_kernel",
    "ggx_kernel_inplace",
    "ggx_kernel_integral",
    "ggx_ndf",
    "level_roughness",
    "phong_kernel",
    "phong_kernel_integral",
    "roughness_to_alpha",
    "roughness_to_lod",
]

#: Below this alpha the GGX lobe is treated as a delta (level 0 is a copy).
ALPHA_DELTA = 1e-4


def roughness_to_alpha(roughness: ArrayLike) -> NDArray[np.float64]:
    """GGX alpha of perceptual roughness: ``alpha = r^2``."""
    r = np.asarray(roughness, dtype=np.float64)
    return r * r


def level_roughness(level: ArrayLike, levels: int) -> NDArray[np.float64]:
    """Perceptual roughness of a mip level: ``level / (levels - 1)`` (0 for a single level)."""
    if levels < 1:
        raise ValueError(f"levels must be >= 1, got {levels}")
    lv = np.asarray(level, dtype=np.float64)
    return lv / (levels - 1) if levels > 1 else np.zeros_like(lv)


def roughness_to_lod(roughness: ArrayLike, levels: int) -> NDArray[np.float64]:
    """Fractional mip level to sample for a perceptual roughness: ``r (levels - 1)``."""
    r = np.clip(np.asarray(roughness, dtype=np.float64), 0.0, 1.0)
    return r * (levels - 1)


def ggx_ndf(n_dot_h: ArrayLike, alpha: ArrayLike) -> NDArray[np.float64]:
    """GGX (Trowbridge-Reitz) normal distribution ``D``, normalised so that
    ``integral D(n.h) (n.h) dw_h = 1``. Units 1/sr."""
    c = np.clip(np.asarray(n_dot_h, dtype=np.float64), 0.0, 1.0)
    a2 = np.asarray(alpha, dtype=np.float64) ** 2
    t = c * c * (a2 - 1.0) + 1.0
    return a2 / (np.pi * t * t)


def ggx_kernel(cos_theta: ArrayLike, alpha: ArrayLike) -> NDArray[np.float64]:
    """Un-normalised GGX prefilter kernel ``D(cos(theta / 2)) max(0, cos theta) / 4``.

    ``cos_theta`` is ``R . w``, the cosine between the lobe axis and the incoming direction.
    """
    c = np.clip(np.asarray(cos_theta, dtype=np.float64), -1.0, 1.0)
    n_dot_h = np.sqrt(0.5 * (1.0 + c))
    return ggx_ndf(n_dot_h, alpha) * np.maximum(c, 0.0) * 0.25


def ggx_kernel_inplace(cos_theta: NDArray[np.float64], alpha: float) -> NDArray[np.float64]:
    """:func:`ggx_kernel` of a float64 array of cosines, computed in place (the array is
    overwritten and returned): the same values with no temporaries, for the dense sums.

    With ``(n.h)^2 = (1 + c) / 2``: ``K = alpha^2 / (pi t^2) max(c, 0) / 4`` and
    ``t = (1 + c) / 2 (alpha^2 - 1) + 1`` (``c`` clipped to ``[0, 1]``: ``K = 0`` for ``c <= 0``).
    """
    a2 = float(alpha) ** 2
    slope = 0.5 * (a2 - 1.0)
    c = cos_theta
    np.clip(c, 0.0, 1.0, out=c)
    t = c * slope
    t += slope + 1.0
    t *= t
    np.divide(c, t, out=c)
    c *= a2 / (4.0 * np.pi)
    return c


@lru_cache(maxsize=1)
def _gauss_legendre(n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    x, w = np.polynomial.legendre.leggauss(n)
    x.setflags(write=False)
    w.setflags(write=False)
    return x, w


@lru_cache(maxsize=256)
def _ggx_integral(alpha: float) -> float:
    # Integrate in t = atan(tan(p) / alpha), which maps the lobe's width to O(1) for any alpha.
    x, w = _gauss_legendre(512)
    t_max = np.arctan(np.tan(np.pi / 4) / alpha)
    t = 0.5 * t_max * (x + 1.0)
    wt = 0.5 * t_max * w
    p = np.arctan(alpha * np.tan(t))
    dp_dt = alpha * (1.0 + np.tan(t) ** 2) / (1.0 + (alpha * np.tan(t)) ** 2)
    cp = np.cos(p)
    f = ggx_ndf(cp, alpha) * cp * (2.0 * cp * cp - 1.0) * np.sin(p) * dp_dt
    return float(2.0 * np.pi * np.sum(f * wt))


def ggx_kernel_integral(alpha: float) -> float:
    """``integral ggx_kernel(R . w, alpha) dw`` over the sphere (steradian-weighted), for
    ``alpha > 0``. Tends to 1 as alpha -> 0 (the kernel becomes a unit delta)."""
    a = float(alpha)
    if not a > 0:
        raise ValueError(f"alpha must be > 0, got {alpha}")
    return _ggx_integral(a)


def phong_kernel(cos_theta: ArrayLike, exponent: float) -> NDArray[np.float64]:
    """Cosine-power lobe ``max(0, R . w)^P``."""
    c = np.asarray(cos_theta, dtype=np.float64)
    return np.where(c > 0.0, np.maximum(c, 0.0) ** float(exponent), 0.0)


def phong_kernel_integral(exponent: float) -> float:
    """``integral max(0, R . w)^P dw = 2 pi / (P + 1)``."""
    if not exponent >= 0:
        raise ValueError(f"Phong exponent must be >= 0, got {exponent}")
    return 2.0 * np.pi / (float(exponent) + 1.0)
