"""A band-0-2 SH function as a quadratic form on the unit sphere, and its exact minimum.

On the unit sphere a function of bands 0-2 is the quadratic ``f(d) = c + b . d + d^T S d``
(:func:`quadratic_form`): ``c`` from band 0, ``b`` from band 1 and ``S`` symmetric and traceless
from band 2 (``3 z^2 - 1 = 2 z^2 - x^2 - y^2`` on the sphere; R&H 2001 eq. 13). Band 1 is then
the vector ``b`` and band 2 the matrix ``S`` (:func:`band2_from_matrix` is the inverse), which is
what makes rotation exact (:mod:`probegrid.core.sh.rotation`).

Its minimum over the sphere is the trust-region subproblem. In the eigenbasis of ``S``
(eigenvalues ``s_1 <= s_2 <= s_3``, ``beta = V^T b``, :func:`eigen_form`), Lagrangian duality
gives, for any ``mu < s_1``, the lower bound ``D(mu) = c + mu - sum_i beta_i^2 / (4 (s_i - mu))``,
tight at the maximiser of the concave ``D`` (strong duality: Moré & Sorensen 1983), which
:func:`dual_maximiser` finds by bisection; :func:`dual_direction` is the minimiser it points to.
:mod:`probegrid.core.sh.minimum` starts its search there, :mod:`probegrid.core.sh.dering` uses the
certified bound.

References
----------
* R. Ramamoorthi, P. Hanrahan, "An Efficient Representation for Irradiance Environment Maps",
  SIGGRAPH 2001 (eq. 13 quadratic form).
* J. J. Moré, D. C. Sorensen, "Computing a Trust Region Step", SIAM J. Sci. Stat. Comput. 4(3),
  1983 (the minimum of a quadratic on the sphere, the secular equation).
* J. M. Martinez, "Local minimizers of quadratic functions on Euclidean balls and spheres",
  SIAM J. Optim. 4(1), 1994: a quadratic on the sphere has at most one local minimum besides the
  global one.
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import NDArray

from probegrid.core.sh.basis import K0, K1, K2, K3, K4

__all__ = ["band2_from_matrix", "dual_direction", "dual_maximiser", "eigen_form",
           "quadratic_form"]


def quadratic_form(
    coeffs: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The band-0-2 function as ``f(d) = c + b . d + d^T S d`` on the unit sphere.

    Parameters
    ----------
    coeffs : (9, K) float64

    Returns
    -------
    c : (K,), b : (K, 3), S : (K, 3, 3) float64, ``S`` symmetric and traceless
        (``3 z^2 - 1 = 2 z^2 - x^2 - y^2`` on the sphere).
    """
    a = coeffs
    k = a.shape[1]
    c = K0 * a[0]
    b = np.stack([K1 * a[3], K1 * a[1], K1 * a[2]], axis=-1)
    s = np.zeros((k, 3, 3))
    s[:, 0, 0] = -K3 * a[6] + K4 * a[8]
    s[:, 1, 1] = -K3 * a[6] - K4 * a[8]
    s[:, 2, 2] = 2.0 * K3 * a[6]
    s[:, 0, 1] = s[:, 1, 0] = 0.5 * K2 * a[4]
    s[:, 1, 2] = s[:, 2, 1] = 0.5 * K2 * a[5]
    s[:, 0, 2] = s[:, 2, 0] = 0.5 * K2 * a[7]
    return c, b, s


#: Bisection steps of :func:`dual_maximiser` (the interval halves each step: 64 reach float64).
_MU_STEPS: Final = 64


def dual_maximiser(beta: NDArray[np.float64], s: NDArray[np.float64]) -> NDArray[np.float64]:
    """The maximiser ``mu`` of the Lagrangian dual ``D(mu) = c + mu - sum_i beta_i^2 /
    (4 (s_i - mu))`` of ``min c + beta . d + sum_i s_i d_i^2`` over unit ``d`` (the quadratic
    form in the eigenbasis of its matrix, eigenvalues ``s (K, 3)`` ascending, ``beta (K, 3)``):
    bisection on the sign of ``D'`` over ``[s_1 - |beta| / 2, s_1)``, from the left, so ``D``
    at the result is a certified lower bound of the minimum, tight to rounding (strong duality:
    Moré & Sorensen 1983; :mod:`probegrid.core.sh.dering`). ``(K,)``."""
    b2 = beta * beta
    s1 = s[:, 0]
    lo = s1 - 0.5 * np.sqrt(b2.sum(axis=1))  # D'(lo) >= 0
    hi = s1.copy()
    for _ in range(_MU_STEPS):  # bisection on the sign of D'(mu); D'(lo) >= 0 throughout
        mid = 0.5 * (lo + hi)
        gap = s - mid[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            terms = np.where(b2 > 0, b2 / (4.0 * gap * gap), 0.0)
        up = terms.sum(axis=1) <= 1.0  # D'(mid) >= 0: the maximiser lies above
        lo = np.where(up, mid, lo)
        hi = np.where(up, hi, mid)
    return lo


def eigen_form(b: NDArray[np.float64], s: NDArray[np.float64]
               ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """``b . d + d^T S d`` (``b (K, 3)``, symmetric ``S (K, 3, 3)``) in the eigenbasis of ``S``:
    ``beta = V^T b (K, 3)``, the eigenvalues ``(K, 3)`` ascending and the eigenvectors ``V``
    ``(K, 3, 3)`` (columns), the form :func:`dual_maximiser` takes."""
    evals, evecs = np.linalg.eigh(s)  # ascending
    return np.einsum("kij,ki->kj", evecs, b), evals, evecs


def dual_direction(b: NDArray[np.float64], s: NDArray[np.float64]) -> NDArray[np.float64]:
    """A unit direction near the global minimiser of ``b . d + d^T S d`` (``b (K, 3)``,
    ``S (K, 3, 3)``) from the dual: ``d_i = -beta_i / (2 (s_i - mu))`` in the eigenbasis at
    :func:`dual_maximiser`'s ``mu``, completed along the first eigenvector where it is shorter
    than 1 (the "hard case"), normalised. ``(K, 3)``."""
    beta, evals, evecs = eigen_form(b, s)
    mu = dual_maximiser(beta, evals)
    gap = evals - mu[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(gap > 0, -beta / (2.0 * gap), 0.0)
    short = np.maximum(0.0, 1.0 - np.sum(x * x, axis=1))
    x[:, 0] += np.where(x[:, 0] < 0, -1.0, 1.0) * np.sqrt(short)
    d = np.einsum("kij,kj->ki", evecs, x)
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    return np.where(norm > 0, d / np.where(norm > 0, norm, 1.0), evecs[:, :, 0])


def band2_from_matrix(s: NDArray[np.float64]) -> NDArray[np.float64]:
    """Band-2 coefficients (5, K) of traceless symmetric matrices ``s`` (K, 3, 3)."""
    return np.stack(
        [
            2.0 * s[:, 0, 1] / K2,
            2.0 * s[:, 1, 2] / K2,
            (2.0 * s[:, 2, 2] - s[:, 0, 0] - s[:, 1, 1]) / (6.0 * K3),
            2.0 * s[:, 0, 2] / K2,
            (s[:, 0, 0] - s[:, 1, 1]) / (2.0 * K4),
        ]
    )
