"""The minimum over the sphere of a spherical-harmonic function, per channel.

Needed to check a reconstruction for negative lobes (ringing) and to choose windows
(:mod:`probegrid.core.sh.windowing`). Both paths start from a dense Fibonacci search and refine
the best samples by damped Newton steps on the sphere, keeping a step only where it lowers the
function (so the result is never worse than the best sample):

* 3 bands (the fast path): the function is the quadratic ``c + b . d + d^T S d`` on the unit
  sphere (:mod:`probegrid.core.sh.quadratic`). 4096 samples; the 32 lowest of each channel and
  the direction the Lagrangian dual points to (:func:`probegrid.core.sh.quadratic.dual_direction`)
  are refined by Riemannian Newton steps with the exact gradient and Hessian (converging
  quadratically). A quadratic on the sphere has at most one local minimum besides the global
  one (Martinez 1994), which is why refining the best samples finds the global minimum; without
  the dual's start the search missed it in 9 of 36 000 ringing probes, by up to 1e-4 of their
  scale (``tests/test_sh.py``).
* Any other band count: ``max(4096, 32 bands^2)`` samples (spacing a quarter of the shortest
  wavelength ``2 pi / (bands - 1)`` or better), then Newton steps in a tangent chart of the
  best 32 candidates per channel, with the gradient and Hessian from central differences
  (``h = 1e-3`` rad; the functions are polynomials of degree ``< bands`` on the sphere, so this
  converges to the critical point to ~1e-10 rad).

Non-finite coefficients raise ``ValueError``.

References
----------
* J. M. Martinez, "Local minimizers of quadratic functions on Euclidean balls and spheres",
  SIAM J. Optim. 4(1), 1994.
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core.sh.basis import (
    K0,
    NUM_BANDS,
    NUM_COEFFS,
    basis_unit,
    check_coeffs,
    fibonacci_directions,
    sh_basis,
)
from probegrid.core.sh.quadratic import dual_direction, quadratic_form

__all__ = ["min_over_sphere"]

#: Fibonacci samples of the search (at least), and how many of the best are refined.
_MIN_SAMPLES: Final = 4096
_MIN_REFINE: Final = 32
#: Newton steps of the 3-band path (quadratic convergence: 6 gave the same bits as 12 on 5000
#: random functions) and of the general path, and the general path's finite-difference step.
_NEWTON_STEPS_3: Final = 8
_NEWTON_STEPS: Final = 12
_FD_STEP: Final = 1e-3
#: Channels per block (bounded memory for many channels): 3 bands, other counts.
_MIN_CHANNEL_BLOCK_3: Final = 256
_MIN_CHANNEL_BLOCK: Final = 64


def _refine_quadratic(
    c: NDArray[np.float64],
    b: NDArray[np.float64],
    s: NDArray[np.float64],
    d: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Damped Riemannian Newton descent of ``c + b.d + d^T S d`` on the sphere.

    ``c (K,)``, ``b (K, 3)``, ``s (K, 3, 3)`` and starting unit vectors ``d (K, 3)``; returns the
    refined ``(values (K,), directions (K, 3))``. A step is kept only where it lowers ``f``, so the
    result is never worse than the start.
    """

    def f(dd: NDArray[np.float64]) -> NDArray[np.float64]:
        return c + np.sum(dd * (b + (s @ dd[..., None])[..., 0]), axis=-1)

    ex = np.array([1.0, 0.0, 0.0])
    ey = np.array([0.0, 1.0, 0.0])
    val = f(d)
    for _ in range(_NEWTON_STEPS_3):
        grad = b + 2.0 * (s @ d[..., None])[..., 0]  # Euclidean gradient
        # Orthonormal tangent frame t = (t1, t2) at d, (K, 3, 2).
        t1 = np.cross(np.where(np.abs(d[:, :1]) < 0.9, ex, ey), d)
        t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
        t = np.stack([t1, np.cross(d, t1)], axis=-1)
        g = (grad[:, None, :] @ t)[:, 0]  # (K, 2) Riemannian gradient
        # Riemannian Hessian on the sphere: T^T (2 S) T - (d . grad) I, symmetric 2 x 2.
        h = 2.0 * (t.transpose(0, 2, 1) @ s @ t)
        dg = np.sum(d * grad, axis=-1)
        h00, h01, h11 = h[:, 0, 0] - dg, h[:, 0, 1], h[:, 1, 1] - dg
        # Levenberg shift to positive definite where needed, then the closed-form 2 x 2 solve.
        lam_min = 0.5 * (h00 + h11) - np.hypot(0.5 * (h00 - h11), h01)
        scale = np.maximum(np.abs(h00), np.abs(h11)) + np.abs(h01) + np.abs(g).max(axis=1)
        shift = np.maximum(0.0, 1e-9 * scale - lam_min)
        a00, a11 = h00 + shift, h11 + shift
        det = a00 * a11 - h01 * h01
        ok = det > 0  # false only where f is constant (g = h = 0): no step
        inv = np.divide(1.0, det, out=np.zeros_like(det), where=ok)
        step0 = -(a11 * g[:, 0] - h01 * g[:, 1]) * inv
        step1 = -(a00 * g[:, 1] - h01 * g[:, 0]) * inv
        cand = d + t[..., 0] * step0[:, None] + t[..., 1] * step1[:, None]
        cand /= np.linalg.norm(cand, axis=-1, keepdims=True)
        cval = f(cand)
        better = cval < val
        d = np.where(better[:, None], cand, d)
        val = np.where(better, cval, val)
    return val, d


def _tangent_frames(d: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    ref = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(ref, d)
    t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
    return t1, np.cross(d, t1)


def _refine(coeffs: NDArray[np.float64], d: NDArray[np.float64], bands: int
            ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Damped Newton descent of ``f_k(d) = coeffs[k] . Y(d)`` from ``d (K, 3)``, in the chart
    ``normalize(d + a t1 + b t2)`` with finite-difference derivatives; a step is kept only where
    it lowers ``f``."""
    h = _FD_STEP
    # stencil (a, b): centre, +-a, +-b, and the four diagonals
    st = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [1, -1], [-1, 1], [-1, -1]],
                  dtype=np.float64) * h

    def f(points: NDArray[np.float64]) -> NDArray[np.float64]:  # points (K, S, 3)
        y = basis_unit(points, bands)
        return np.einsum("ksi,ki->ks", y, coeffs)

    val = f(d[:, None])[:, 0]
    for _ in range(_NEWTON_STEPS):
        t1, t2 = _tangent_frames(d)
        pts = d[:, None] + st[None, :, :1] * t1[:, None] + st[None, :, 1:] * t2[:, None]
        pts /= np.linalg.norm(pts, axis=-1, keepdims=True)
        fv = f(pts)
        g = np.stack([fv[:, 1] - fv[:, 2], fv[:, 3] - fv[:, 4]], axis=-1) / (2 * h)
        h00 = (fv[:, 1] - 2 * fv[:, 0] + fv[:, 2]) / (h * h)
        h11 = (fv[:, 3] - 2 * fv[:, 0] + fv[:, 4]) / (h * h)
        h01 = (fv[:, 5] - fv[:, 6] - fv[:, 7] + fv[:, 8]) / (4 * h * h)
        lam_min = 0.5 * (h00 + h11) - np.hypot(0.5 * (h00 - h11), h01)
        scale = np.maximum(np.abs(h00), np.abs(h11)) + np.abs(h01) + np.abs(g).max(axis=1)
        shift = np.maximum(0.0, 1e-9 * scale - lam_min)
        a00, a11 = h00 + shift, h11 + shift
        det = a00 * a11 - h01 * h01
        ok = det > 0
        inv = np.divide(1.0, det, out=np.zeros_like(det), where=ok)
        s0 = -(a11 * g[:, 0] - h01 * g[:, 1]) * inv
        s1 = -(a00 * g[:, 1] - h01 * g[:, 0]) * inv
        # a chart step longer than a quarter turn is not trusted: shorten it
        length = np.hypot(s0, s1)
        cut = np.minimum(1.0, 0.5 / np.maximum(length, 1e-300))
        cand = d + (s0 * cut)[:, None] * t1 + (s1 * cut)[:, None] * t2
        cand /= np.linalg.norm(cand, axis=-1, keepdims=True)
        cval = f(cand[:, None])[:, 0]
        better = cval < val
        d = np.where(better[:, None], cand, d)
        val = np.where(better, cval, val)
    return val, d


def min_over_sphere(coeffs: ArrayLike, *, bands: int = NUM_BANDS
                    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Minimum over all directions of an SH function, per channel.

    Dense Fibonacci search, then Newton refinement of the best samples (module docstring). Pass
    :func:`probegrid.core.sh.irradiance_coefficients` of ``L`` for the minimum irradiance.

    Parameters
    ----------
    coeffs : (bands^2, ...) float
        Coefficients of the function (any trailing channel shape).
    bands : int

    Returns
    -------
    values : (...) float64
        The minimum of each channel.
    directions : (..., 3) float64
        A unit direction where it is reached.

    Raises
    ------
    ValueError
        For nan / inf coefficients.
    """
    a = check_coeffs(coeffs, bands)
    if not np.all(np.isfinite(a)):
        raise ValueError("coeffs contain nan or inf; the minimum over the sphere is undefined.")
    if bands == NUM_BANDS:
        return _min_quadratic(a)
    return _min_general(a, bands)


def _min_quadratic(a: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The 3-band path of :func:`min_over_sphere` (finite ``a (9, ...)``)."""
    rest = a.shape[1:]
    flat = a.reshape(NUM_COEFFS, -1)
    dirs = fibonacci_directions(_MIN_SAMPLES)
    basis = sh_basis(dirs)  # (N, 9)
    m = _MIN_REFINE
    vmin = np.empty(flat.shape[1])
    dmin = np.empty((flat.shape[1], 3))
    for j in range(0, flat.shape[1], _MIN_CHANNEL_BLOCK_3):  # bounded memory for many channels
        blk = flat[:, j : j + _MIN_CHANNEL_BLOCK_3]
        k = blk.shape[1]
        # the samples' values summed coefficient by coefficient (not a BLAS product, whose
        # rounding may depend on how many channels share it): each channel's minimum is
        # the same bits whatever channels it is computed with
        vals = basis[:, :1] * blk[0]
        for i in range(1, NUM_COEFFS):
            vals += basis[:, i:i + 1] * blk[i]
        best = np.argpartition(vals, m - 1, axis=0)[:m]  # (m, k) sample indices
        c, b, s = quadratic_form(blk)
        # One refinement per (channel, candidate), laid out channel-major as (k * (m + 1)):
        # the m lowest samples and the dual's direction (a narrow global minimum can lie
        # between the samples, all of the lowest of them in another basin)
        start = np.concatenate([dirs[best.T], dual_direction(b, s)[:, None]], axis=1)
        val, d = _refine_quadratic(
            np.repeat(c, m + 1), np.repeat(b, m + 1, axis=0), np.repeat(s, m + 1, axis=0),
            start.reshape(-1, 3)
        )
        val, d = val.reshape(k, m + 1), d.reshape(k, m + 1, 3)
        pick = np.argmin(val, axis=1)
        vmin[j : j + k] = val[np.arange(k), pick]
        dmin[j : j + k] = d[np.arange(k), pick]
    return vmin.reshape(rest), dmin.reshape(rest + (3,))


def _min_general(a: NDArray[np.float64], b: int
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The general path of :func:`min_over_sphere` (finite ``a (b^2, ...)``)."""
    rest = a.shape[1:]
    flat = a.reshape(b * b, -1)
    if b == 1:  # a constant
        return (flat[0] * K0).reshape(rest), np.tile([0.0, 0.0, 1.0], flat.shape[1:] + (1,)
                                                     ).reshape(rest + (3,))
    dirs = fibonacci_directions(max(_MIN_SAMPLES, 32 * b * b))
    y = basis_unit(dirs, b)
    m = _MIN_REFINE
    vmin = np.empty(flat.shape[1])
    dmin = np.empty((flat.shape[1], 3))
    for j in range(0, flat.shape[1], _MIN_CHANNEL_BLOCK):
        blk = flat[:, j:j + _MIN_CHANNEL_BLOCK]
        k = blk.shape[1]
        best = np.argpartition(y @ blk, m - 1, axis=0)[:m]          # (m, k)
        start = dirs[best.T.reshape(-1)]
        val, d = _refine(np.repeat(blk.T, m, axis=0), start, b)
        val, d = val.reshape(k, m), d.reshape(k, m, 3)
        pick = np.argmin(val, axis=1)
        vmin[j:j + k] = val[np.arange(k), pick]
        dmin[j:j + k] = d[np.arange(k), pick]
    return vmin.reshape(rest), dmin.reshape(rest + (3,))
