"""Split-sum DFG lookup table for GGX image-based lighting (Karis 2013).

The split-sum approximation (Karis, "Real Shading in Unreal Engine 4", SIGGRAPH 2013 course)
writes the specular image-based lighting integral as::

    integral L(l) f(l, v) (n . l) dl  ~=  prefiltered(R, roughness) * (F0 * A + B)

with the two environment-independent factors::

    A(n.v, r) = integral f(l, v) / F * (1 - Fc(v.h)) (n . l) dl
    B(n.v, r) = integral f(l, v) / F * Fc(v.h) (n . l) dl,     Fc(x) = (1 - x)^5

for the Cook-Torrance GGX BRDF ``f = D G F / (4 (n.l) (n.v))`` with Schlick's Fresnel
``F = F0 + (1 - F0) Fc`` (so ``F0 A + B`` is its directional albedo).

Conventions
-----------
* ``D`` is GGX / Trowbridge-Reitz (:func:`probegrid.core.lobes.ggx_ndf`), ``alpha = r^2`` with ``r`` the
  perceptual roughness.
* Geometry term: **height-correlated Smith GGX** (Heitz 2014, "Understanding the
  Masking-Shadowing Function in Microfacet-Based BRDFs", eq. 99), as Filament uses, written as the
  visibility ``V = G / (4 (n.l)(n.v)) = 0.5 / (n.v sqrt((n.l)^2 (1 - a^2) + a^2)
  + n.l sqrt((n.v)^2 (1 - a^2) + a^2))``.
* The table is ``lut[row, col, channel]`` of shape ``(size, size, 2)``: ``col`` indexes
  ``n.v = (col + 0.5) / size`` and ``row`` indexes the perceptual roughness
  ``r = (row + 0.5) / size`` -- **row 0 is the smoothest row** (r = 0.5 / size). Uploaded with row 0
  first (the OpenGL / Vulkan convention, ``t = 0`` at the first row), a shader reads it with
  ``texture(dfg, vec2(n_dot_v, roughness)).rg``. Channels are ``(A, B)``.

Quadrature
----------
Both integrals are written over the half vector ``h`` and importance-sampled by the GGX
distribution of normals: with ``dl = 4 (v.h) dh`` and the GGX cdf ``u = tan^2(theta_h) /
(alpha^2 + tan^2(theta_h))`` (uniform in the measure ``D(h) (n.h) dh``)::

    A = integral_0^1 du integral_0^{2 pi} dphi / (2 pi)  4 V (n.l) (v.h) / (n.h) (1 - Fc(v.h))

evaluated with a *deterministic* Gauss-Legendre product rule rather than random samples. With
``v = (sin theta_v, 0, cos theta_v)``, ``n.l = 2 (v.h)(n.h) - n.v > 0`` holds for every ``phi`` when
``theta_h < (pi/2 - theta_v)/2`` and for no ``phi`` when ``theta_h > (pi/2 + theta_v)/2``; in between
only for ``|phi| < phi_max(theta_h)``. So ``u`` is split at those two angles (``samples``
Gauss-Legendre nodes on each part, the second graded by a smoothstep to flatten the square-root
behaviour of ``phi_max`` at its ends) and ``phi`` is integrated over ``[0, phi_max]`` only
(``max(8, samples // 4)`` nodes; the integrand is even in ``phi``), so no node straddles the
``n.l = 0`` kink. Nodes per entry: ``2 * samples * max(8, samples // 4)``. At the default
``samples = 64`` the table is converged to < 1e-4 absolute (the worst entries are the grazing
column ``n.v = 0.5 / size``; elsewhere < 4e-5), measured against 160 x 160 nodes in
``tests/test_dfg.py``; five entries match an independent double integral over the light
direction to < 1e-6. Filament's ``cmgen --ibl-dfg`` (1024 Hammersley samples per entry) differs
from this table by 8e-4 on average and up to 1.2e-2 (its error; ``benchmarks/bench_filter.py``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["dfg_lookup", "dfg_lut", "smith_ggx_correlated_visibility"]


def smith_ggx_correlated_visibility(
    n_dot_v: ArrayLike, n_dot_l: ArrayLike, alpha: ArrayLike
) -> NDArray[np.float64]:
    """Height-correlated Smith GGX visibility ``G2 / (4 (n.l) (n.v))`` (Heitz 2014).

    Parameters
    ----------
    n_dot_v, n_dot_l : (...) float
        Cosines in ``[0, 1]``; they broadcast together with ``alpha``.
    alpha : (...) float
        GGX alpha (``perceptual roughness ** 2``).

    Returns
    -------
    (...) float64, units 1 (the BRDF is ``D V F``).
    """
    nv = np.asarray(n_dot_v, dtype=np.float64)
    nl = np.asarray(n_dot_l, dtype=np.float64)
    a2 = np.asarray(alpha, dtype=np.float64) ** 2
    gv = nl * np.sqrt(nv * nv * (1.0 - a2) + a2)
    gl = nv * np.sqrt(nl * nl * (1.0 - a2) + a2)
    den = gv + gl
    return np.where(den > 0, 0.5 / np.where(den > 0, den, 1.0), 0.0)


def _ggx_cdf(theta: NDArray[np.float64], alpha: NDArray[np.float64]) -> NDArray[np.float64]:
    """GGX cdf of the half-vector angle: ``tan^2 t / (alpha^2 + tan^2 t)``."""
    s2, c2 = np.sin(theta) ** 2, np.cos(theta) ** 2
    return s2 / (alpha * alpha * c2 + s2)


def _dfg_rows(n_dot_v: NDArray[np.float64], alpha: NDArray[np.float64], samples: int
              ) -> NDArray[np.float64]:
    """(A, B) for every (alpha row, n.v column): ``(len(alpha), len(n_dot_v), 2)`` float64."""
    x, w = np.polynomial.legendre.leggauss(samples)
    t = 0.5 * (x + 1.0)
    wt = 0.5 * w
    a = alpha[:, None, None, None]                           # (R, 1, 1, 1)
    nv = n_dot_v[None, :, None, None]                        # (1, X, 1, 1)
    sv = np.sqrt(np.maximum(1.0 - nv * nv, 0.0))
    theta_v = np.arccos(np.clip(nv, -1.0, 1.0))
    # n.l > 0 for every phi when theta_h < (pi/2 - theta_v)/2 and for none when
    # theta_h > (pi/2 + theta_v)/2: split u there (phi_max has sqrt-type kinks at both).
    u1 = _ggx_cdf(0.5 * (0.5 * np.pi - theta_v), a)
    u2 = _ggx_cdf(0.5 * (0.5 * np.pi + theta_v), a)
    # segment 1, u in [0, u1]: plain Gauss-Legendre; segment 2, u in [u1, u2]: smoothstep
    # grading u = u1 + (u2 - u1)(3 t^2 - 2 t^3) flattens the sqrt behaviour at both ends.
    tt = t[None, None, :, None]
    ww = wt[None, None, :, None]
    u = np.concatenate([u1 * tt, u1 + (u2 - u1) * (3 * tt**2 - 2 * tt**3)], axis=2)
    wu = np.concatenate([u1 * ww, (u2 - u1) * 6 * tt * (1 - tt) * ww], axis=2)
    # cos^2(theta_h) from the GGX cdf (Walter et al. 2007, eq. 35 inverted).
    c2 = (1.0 - u) / (1.0 + (a * a - 1.0) * u)
    nh = np.sqrt(c2)
    sh = np.sqrt(np.maximum(1.0 - c2, 0.0))
    # v = (sv, 0, nv), h = (sh cos phi, sh sin phi, nh); n.l = 2 (v.h)(n.h) - n.v > 0 exactly
    # when cos(phi) > c_min = n.v (1 - 2 (n.h)^2) / (2 (n.h) sv sh): integrate phi over
    # [0, phi_max] only, so the integrand has no kink inside the domain.
    den = 2.0 * nh * sv * sh
    c_min = np.where(den > 0, nv * (1.0 - 2.0 * c2) / np.where(den > 0, den, 1.0),
                     np.where(2.0 * c2 > 1.0, -np.inf, np.inf))
    phi_max = np.arccos(np.clip(c_min, -1.0, 1.0))           # (R, X, U, 1)
    xp, wp = np.polynomial.legendre.leggauss(max(8, samples // 4))
    phi = phi_max * (0.5 * (xp + 1.0))[None, None, None, :]  # (R, X, U, P)
    wphi = phi_max * (0.5 * wp / np.pi)                      # phi average over [0, pi]
    vh = sv * sh * np.cos(phi) + nv * nh
    nl = np.maximum(2.0 * vh * nh - nv, 0.0)
    vis = smith_ggx_correlated_visibility(nv, nl, a)
    g = 4.0 * vis * nl * vh / nh * (wu * wphi)
    fc = (1.0 - np.clip(vh, 0.0, 1.0)) ** 5
    a_ch = np.sum(g * (1.0 - fc), axis=(2, 3))
    b_ch = np.sum(g * fc, axis=(2, 3))
    return np.stack([a_ch, b_ch], axis=-1)


def dfg_lut(size: int = 128, *, samples: int = 64) -> NDArray[np.float32]:
    """The split-sum DFG table ``(A, B)`` for GGX with height-correlated Smith visibility.

    Parameters
    ----------
    size : int
        Table width and height (``n.v`` columns and roughness rows).
    samples : int
        Gauss-Legendre nodes per segment of the ``u`` integral; see the module docstring.

    Returns
    -------
    (size, size, 2) float32
        ``lut[row, col] = (A, B)`` at ``r = (row + 0.5) / size``, ``n.v = (col + 0.5) / size``;
        specular = prefiltered radiance ``* (F0 * A + B)``. Memory is bounded by processing
        a few rows at a time (about 100 MB of float64 temporaries at most).
    """
    if not isinstance(size, (int, np.integer)) or isinstance(size, bool) or size < 1:
        raise ValueError(f"size must be a positive integer, got {size!r}.")
    if not isinstance(samples, (int, np.integer)) or isinstance(samples, bool) or samples < 4:
        raise ValueError(f"samples must be an integer >= 4, got {samples!r}.")
    centres = (np.arange(size) + 0.5) / size
    alpha = centres**2
    out = np.empty((size, size, 2), dtype=np.float64)
    rows = max(1, int(1_000_000 // (size * 2 * samples * max(8, samples // 4))))
    for r0 in range(0, size, rows):
        out[r0:r0 + rows] = _dfg_rows(centres, alpha[r0:r0 + rows], int(samples))
    return out.astype(np.float32)


def dfg_lookup(lut: ArrayLike, n_dot_v: ArrayLike, roughness: ArrayLike) -> NDArray[np.float32]:
    """Bilinear lookup of a :func:`dfg_lut` table (clamp-to-edge, texel centres as in the table).

    Parameters
    ----------
    lut : (S, S, 2) float
    n_dot_v, roughness : (...) float
        Broadcast together; values outside ``[0, 1]`` are clamped.

    Returns
    -------
    (..., 2) float32
        ``(A, B)``.
    """
    t = np.asarray(lut, dtype=np.float32)
    if t.ndim != 3 or t.shape[0] != t.shape[1] or t.shape[2] != 2:
        raise ValueError(f"lut must have shape (S, S, 2), got {t.shape}.")
    s = t.shape[0]
    nv, r = np.broadcast_arrays(np.asarray(n_dot_v, dtype=np.float64),
                                np.asarray(roughness, dtype=np.float64))
    if not (np.all(np.isfinite(nv)) and np.all(np.isfinite(r))):
        raise ValueError("n_dot_v and roughness must be finite.")
    x = np.clip(np.clip(nv, 0.0, 1.0) * s - 0.5, 0.0, s - 1.0)
    y = np.clip(np.clip(r, 0.0, 1.0) * s - 0.5, 0.0, s - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.intp), s - 1)
    y0 = np.minimum(np.floor(y).astype(np.intp), s - 1)
    x1 = np.minimum(x0 + 1, s - 1)
    y1 = np.minimum(y0 + 1, s - 1)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    top = t[y0, x0] * (1.0 - fx) + t[y0, x1] * fx
    bot = t[y1, x0] * (1.0 - fx) + t[y1, x1] * fx
    return (top * (1.0 - fy) + bot * fy).astype(np.float32)
