"""Per-probe SH deringing: the gentlest band window that makes each probe's irradiance >= 0.

Band-2 SH of a small bright source rings: the irradiance it describes goes negative on the far
side (down to -4 % of the peak for one directional light, :mod:`probegrid.core.sh`), and a
shader reading it shows dark halos or, clamped, light where there is none. This module chooses,
for every probe of a grid at once (pure numpy, vectorised over probes), a window of band factors
``h = (1, h_1, h_2)`` applied to the radiance coefficients ``L_lm <- h_l L_lm``, such that the
irradiance ``E(n) = sum A_l h_l L_lm Y_lm(n)`` of every colour channel is non-negative over the
whole sphere, and the window is the gentlest one on a fixed path (below). One window serves the
three channels of a probe, so its colour is consistent; a probe whose irradiance is already
non-negative keeps ``h = (1, 1, 1)``, i.e. its coefficients unchanged, bit for bit.

The window path
---------------
On the unit sphere the irradiance is the quadratic ``E(d) = c + h_1 b . d + h_2 d^T S d``
(``c = pi K0 L_00``, ``b`` from band 1, ``S`` traceless symmetric from band 2; see
:func:`probegrid.core.sh.quadratic.quadratic_form`). With band 2 removed,
``min E = c - h_1 |b|``, so ``a = min(1, (1 - margin) c / |b|)`` (smallest over the channels)
is the most band 1 any non-negative window can keep. The window runs along the straight segment

    h(t) = (1, 1 - t (1 - a), 1 - t),   t in [0, 1]

from no window (``t = 0``) to ``(1, a, 0)`` (``t = 1``, feasible by construction). For each
direction and channel ``E`` is affine in ``t``, so ``m(t) = min_{d, channel} E - margin c`` is
*concave*: its feasible set ``{m >= 0}`` is an interval ``[t*, 1]``, and a bracketing root
finder (Illinois regula falsi) finds ``t*`` to ``1e-10`` (no grid scan, none of the
non-monotone windows of ``sh.auto_window``); the window returned is the feasible end. ``h_2 <= h_1``
along the whole path: the window is a low-pass, band 2 damped first.

Exact minimum over the sphere
-----------------------------
The feasibility test needs ``min_d E(d)``, a quadratic on the sphere (the trust-region
subproblem). In the eigenbasis of ``S`` (eigenvalues ``s_1 <= s_2 <= s_3``, ``beta = V^T b``),
Lagrangian duality gives, for any ``mu < s_1``, the *lower bound*

    min E >= D(mu) = c + mu - sum_i beta_i^2 / (4 (s_i - mu)),

which is tight at the maximiser of the concave ``D`` (strong duality holds for this problem;
Moré & Sorensen 1983). ``D'(mu) >= 0`` at ``mu = s_1 - |beta| / 2``, so bisection on the sign of
``D'`` over ``[s_1 - |beta| / 2, s_1)`` converges to the maximiser from the left, every iterate
giving a certified lower bound. A window is accepted only when this certified minimum, minus the
margin ``margin * c`` (default ``1e-4``: room for the float32 rounding of stored coefficients),
is ``>= 0``. The eigen-decomposition is done once per channel: a window only scales ``b`` by
``h_1`` and the eigenvalues by ``h_2``.

References
----------
* P.-P. Sloan, "Deringing Spherical Harmonics", SIGGRAPH Asia 2017 technical brief (windows that
  keep a reconstruction non-negative) and "Stupid SH Tricks", GDC 2008 (band windows).
* J. J. Moré, D. C. Sorensen, "Computing a Trust Region Step", SIAM J. Sci. Stat. Comput. 4(3),
  1983 (the minimum of a quadratic on the sphere, the secular equation).
* R. Ramamoorthi, P. Hanrahan, "An Efficient Representation for Irradiance Environment Maps",
  SIGGRAPH 2001 (``A_l``).
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core.sh.basis import BAND_OF
from probegrid.core.sh.clampedcosine import A_HAT
from probegrid.core.sh.quadratic import dual_maximiser, eigen_form, quadratic_form

__all__ = ["DEFAULT_MARGIN", "dering", "irradiance_minimum", "window_path"]

#: Relative margin ``min E >= margin * c`` a deringed probe keeps (float32 storage headroom).
DEFAULT_MARGIN: Final = 1e-4

#: Root-finder iterations (at most) and tolerance on the window parameter t, and bisection
#: steps of the dual variable.
_T_STEPS: Final = 60
_T_TOL: Final = 1e-10


def _irradiance_forms(coeffs: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
    """``c (K,)``, ``beta (K, 3)``, ``s (K, 3)``: the irradiance of ``coeffs (K, 9)`` in the
    eigenbasis of its band-2 matrix (eigenvalues ascending)."""
    irr = coeffs * A_HAT  # radiance -> irradiance coefficients
    c, b, s = quadratic_form(np.ascontiguousarray(irr.T))
    beta, evals, _ = eigen_form(b, s)
    return c, beta, evals


def _dual_minimum(c: NDArray, beta: NDArray, s: NDArray) -> NDArray[np.float64]:
    """Certified lower bound of ``min_d c + beta . d + sum s_i d_i^2`` on the unit sphere
    (eigenbasis form; see the module docstring), ``(K,)``; tight to rounding."""
    b2 = beta * beta
    lo = dual_maximiser(beta, s)
    gap = s - lo[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        terms = np.where(b2 > 0, b2 / (4.0 * gap), 0.0)
    return c + lo - terms.sum(axis=1)


def irradiance_minimum(coeffs: ArrayLike) -> NDArray[np.float64]:
    """Certified minimum over the sphere of the irradiance of radiance SH ``coeffs (..., 9)``
    (one function per leading index, e.g. ``(P, 3, 9)`` for RGB probes); a lower bound tight
    to rounding (module docstring)."""
    a = np.asarray(coeffs, dtype=np.float64)
    if a.shape[-1:] != (9,):
        raise ValueError(f"coeffs must have shape (..., 9), got {a.shape}.")
    flat = a.reshape(-1, 9)
    c, beta, s = _irradiance_forms(flat)
    return _dual_minimum(c, beta, s).reshape(a.shape[:-1])


def window_path(t: ArrayLike, a: ArrayLike) -> NDArray[np.float64]:
    """Band factors ``(..., 3)`` of the window path ``(1, 1 - t (1 - a), 1 - t)``."""
    tt, aa = np.broadcast_arrays(np.asarray(t, np.float64), np.asarray(a, np.float64))
    return np.stack([np.ones_like(tt), 1.0 - tt * (1.0 - aa), 1.0 - tt], axis=-1)


def dering(
    sh: ArrayLike, *, margin: float = DEFAULT_MARGIN
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Window every probe's radiance SH so that its irradiance is non-negative everywhere.

    Parameters
    ----------
    sh : (P, 9, C) float
        Radiance coefficients ``L_lm`` of ``P`` probes (the store's ``sh`` layout), finite.
    margin : float
        A windowed probe's certified minimum irradiance is at least ``margin * pi K0 L_00``
        per channel (module docstring); in [0, 0.5).

    Returns
    -------
    deringed : (P, 9, C) float64
        ``h_l L_lm``; exactly ``sh`` (as float64) where the irradiance was already >= 0.
    window : (P, 3) float64
        The band factors ``(1, h_1, h_2)`` of each probe (``(1, 1, 1)``: not windowed).
    minimum : (P, C) float64
        Certified minimum over the sphere of each channel's deringed irradiance.

    Raises
    ------
    ValueError
        For a wrong shape, nan / inf coefficients, or a bad margin.

    A channel with ``L_00 < 0`` (no window can make it non-negative; radiance never gives one)
    gets the strongest window ``(1, 0, 0)`` and keeps its negative minimum.
    """
    x = np.asarray(sh, dtype=np.float64)
    if x.ndim != 3 or x.shape[1] != 9:
        raise ValueError(f"sh must have shape (P, 9, C), got {x.shape}.")
    if not np.all(np.isfinite(x)):
        raise ValueError("sh contains nan or inf; cannot dering it.")
    if not (isinstance(margin, (int, float)) and 0.0 <= margin < 0.5):
        raise ValueError(f"margin must be in [0, 0.5), got {margin!r}.")
    p, _, ch = x.shape
    flat = np.moveaxis(x, 1, 2).reshape(-1, 9)  # (P C, 9), probe-major
    c, beta, s = _irradiance_forms(flat)
    need = c * margin
    raw_min = _dual_minimum(c, beta, s).reshape(p, ch)
    window = np.ones((p, 3))
    out = x.copy()
    todo = np.flatnonzero(np.any(raw_min < 0.0, axis=1))
    minimum = raw_min.copy()
    if todo.size:
        rows = (todo[:, None] * ch + np.arange(ch)).reshape(-1)  # channels of the probes to fix
        c_t, beta_t, s_t, need_t = c[rows], beta[rows], s[rows], need[rows]
        bnorm = np.linalg.norm(beta_t, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            a_ch = np.where(bnorm > 0, (1.0 - 2.0 * margin) * c_t / bnorm, 1.0)
        a = np.clip(a_ch.reshape(-1, ch).min(axis=1), 0.0, 1.0)  # (T,) per probe

        def slack(t: NDArray[np.float64], rows: NDArray[np.intp]) -> NDArray[np.float64]:
            """m(t): certified minimum minus the margin, over the channels of probes ``rows``
            (indices into ``todo``) at path parameters ``t``."""
            r = (rows[:, None] * ch + np.arange(ch)).reshape(-1)
            h1 = np.repeat(1.0 - t * (1.0 - a[rows]), ch)
            h2 = np.repeat(1.0 - t, ch)
            m = _dual_minimum(c_t[r], beta_t[r] * h1[:, None], s_t[r] * h2[:, None]) - need_t[r]
            return m.reshape(-1, ch).min(axis=1)

        # The root t* of the concave m on [0, 1] (m(0) < 0 <= m(1)) by the Illinois variant of
        # regula falsi, which keeps the bracket [lo (infeasible), hi (feasible)] and converges
        # superlinearly; a probe stops once its bracket is below T_TOL.
        every = np.arange(todo.size)
        lo, hi = np.zeros(todo.size), np.ones(todo.size)
        f_lo, f_hi = slack(lo, every), slack(hi, every)
        side = np.zeros(todo.size, dtype=np.int8)
        for _ in range(_T_STEPS):  # iterations of the root finder, all probes at once
            act = np.flatnonzero((hi - lo > _T_TOL) & (f_hi > 0))
            if act.size == 0:
                break
            l, u, fl, fu = lo[act], hi[act], f_lo[act], f_hi[act]
            t = (l * fu - u * fl) / (fu - fl)
            t = np.where((t > l) & (t < u), t, 0.5 * (l + u))
            f = slack(t, act)
            ok = f >= 0.0
            fl = np.where(ok & (side[act] == 1), 0.5 * fl, fl)  # Illinois: the same end twice
            fu = np.where(~ok & (side[act] == -1), 0.5 * fu, fu)
            hi[act], f_hi[act] = np.where(ok, t, u), np.where(ok, f, fu)
            lo[act], f_lo[act] = np.where(ok, l, t), np.where(ok, fl, f)
            side[act] = np.where(ok, 1, -1)
        h = window_path(hi, a)  # (T, 3)
        window[todo] = h
        out[todo] = x[todo] * h[:, BAND_OF][:, :, None]
        h1, h2 = np.repeat(h[:, 1], ch), np.repeat(h[:, 2], ch)
        minimum[todo] = _dual_minimum(c_t, beta_t * h1[:, None],
                                      s_t * h2[:, None]).reshape(-1, ch)
    return out, window, minimum

