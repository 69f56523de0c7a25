"""Band windows against SH ringing: hanning, lanczos, gauss, and the gentlest non-negative one.

Truncating at a band rings: a bright sun gives negative irradiance on the far side (for one
directional light the band-0-2 irradiance dips to ``-19/480 = -4 %`` of its peak). Following
Sloan (2008), "Stupid Spherical Harmonics (SH) Tricks", section "Windowing", band ``l`` is scaled
by a window factor ``h_l`` (``h_0 = 1``, so the mean is kept) of width ``w``::

    hanning   h_l = (1 + cos(pi l / w)) / 2     for l < w, else 0
    lanczos   h_l = sin(pi l / w) / (pi l / w)  for l < w, else 0
    gauss     h_l = exp(-l (l + 1) / (2 w^2))   (the spherical heat kernel; a Gaussian blur of
                                                 angular standard deviation ~ 1 / w radian)

All three tend to no windowing as ``w -> inf`` and keep only band 0 as ``w -> 0`` (``w <= 1`` for
hanning / lanczos). Windowing does not always help: for one directional light, hanning at
``w = 2.5`` and lanczos at ``w = 2`` (Sloan's "w = number of bands" region) make the negative
lobe *deeper* (-4.7 %, -6.8 % of the peak) than no window (-4.0 %), because they damp band 1 more
than band 2 helps; gauss improves monotonically. :func:`auto_window` picks the largest width (the
least smoothing) whose windowed irradiance (or radiance) is non-negative everywhere, with the
minimum of :mod:`probegrid.core.sh.minimum`. Per-probe deringing of a whole grid along a fixed
window path is :mod:`probegrid.core.sh.dering`.

:func:`window` propagates nan / inf; :func:`auto_window` raises ``ValueError`` on them.

References
----------
* P.-P. Sloan, "Stupid Spherical Harmonics (SH) Tricks", GDC 2008 (windowing).
"""

from __future__ import annotations

from typing import Final, Literal, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._types import SHWindow, WindowKind, choices
from probegrid.core.sh.basis import NUM_BANDS, band_of, check_bands, check_coeffs
from probegrid.core.sh.clampedcosine import irradiance_coefficients, per_coeff
from probegrid.core.sh.minimum import min_over_sphere

__all__ = ["WindowKind", "auto_window", "window", "window_factors"]

_WINDOW_KINDS: Final[tuple[str, ...]] = get_args(WindowKind)


def window_factors(kind: WindowKind, width: float, *, bands: int = NUM_BANDS
                   ) -> NDArray[np.float64]:
    """Per-band window factors ``h_0 .. h_(bands-1)`` (Sloan 2008; formulas in the module
    docstring).

    Parameters
    ----------
    kind : {"none", "hanning", "lanczos", "gauss"}
    width : float
        Window width ``w > 0`` (``inf`` means no windowing); ignored for "none".
    bands : int

    Returns
    -------
    (bands,) float64, ``h_0 = 1``.
    """
    if kind not in _WINDOW_KINDS:
        raise ValueError(f"window kind must be one of {_WINDOW_KINDS}, got {kind!r}.")
    bands = check_bands(bands)
    l = np.arange(bands, dtype=np.float64)
    if kind == "none":
        return np.ones(bands)
    w = float(width)
    if not w > 0:
        raise ValueError(f"window width must be > 0, got {width!r}.")
    if np.isinf(w):
        return np.ones(bands)
    if kind == "gauss":
        return np.exp(-l * (l + 1.0) / (2.0 * w * w))
    x = np.pi * l / w
    if kind == "hanning":
        h = 0.5 * (1.0 + np.cos(x))
    else:
        h = np.sinc(l / w)  # numpy's sinc is sin(pi t) / (pi t)
    return np.where(l < w, h, 0.0)


def _apply_window(c: NDArray[np.float64], kind: WindowKind, width: float, bands: int
                  ) -> NDArray[np.float64]:
    return c * per_coeff(window_factors(kind, width, bands=bands), c)


def window(L: ArrayLike, *, kind: WindowKind, width: float, bands: int = NUM_BANDS
           ) -> NDArray[np.float64]:
    """Scale each band of SH coefficients by a window to reduce ringing (Sloan 2008).

    Parameters
    ----------
    L : (bands^2, ...) float
        Coefficients of any function (radiance or irradiance: windowing commutes with ``A_l``).
    kind : {"none", "hanning", "lanczos", "gauss"}
    width : float
        Window width ``w > 0``; larger is gentler, ``inf`` is no windowing. Check the result
        (e.g. with :func:`probegrid.core.sh.min_over_sphere`) or use :func:`auto_window`: some
        hanning / lanczos widths deepen the negative lobe instead (module docstring).
    bands : int

    Returns
    -------
    (bands^2, ...) float64
    """
    return _apply_window(check_coeffs(L, bands, "L"), kind, width, bands)


def _windowed_minima(
    f: NDArray[np.float64], kind: WindowKind, widths: NDArray[np.float64], bands: int
) -> NDArray[np.float64]:
    """Minimum over the sphere and over channels of ``f`` windowed at each width, (G,)."""
    flat = f.reshape(bands * bands, -1)
    per = band_of(bands)
    h = np.stack([window_factors(kind, w, bands=bands)[per] for w in widths], axis=1)  # (k, G)
    # one vectorised call, (G, K)
    vals, _ = min_over_sphere(flat[:, None, :] * h[:, :, None], bands=bands)
    return vals.min(axis=1)


def auto_window(
    L: ArrayLike,
    *,
    kind: Literal["hanning", "lanczos", "gauss"] = "hanning",
    quantity: Literal["irradiance", "radiance"] = "irradiance",
    rtol: float = 1e-4,
    bands: int = NUM_BANDS,
) -> tuple[NDArray[np.float64], float]:
    """The gentlest window of a kind that makes an SH function non-negative everywhere.

    Useful for bright suns: band truncation of a near-delta light gives negative irradiance on
    the far side. One width serves all channels (so the colour of the result is consistent).
    Every ``h_l`` grows with the width ``w``, so the gentlest window is the *largest* feasible
    ``w``. The minimum is **not** monotone in ``w`` for hanning and lanczos (for one directional
    light, hanning at ``w = 2.5`` dips to -4.7 % of the peak, deeper than the unwindowed -4.0 %;
    lanczos at ``w = 2`` to -6.8 %), so the feasible widths need not form an interval and a plain
    bisection could stop at the wrong end. Hence: the windowed minimum (by
    :func:`probegrid.core.sh.min_over_sphere`, all candidate widths in one vectorised call) is
    scanned on 48 log-spaced widths from the band-0-only width (``w = 1`` for hanning /
    lanczos, ``0.01`` for gauss) to ``1e3``, plus ``1e6``; the bracket after the largest
    feasible grid width is then narrowed 17-fold per round to ``rtol``. The returned width is
    always feasible (minimum ``>= 0``); a feasible island narrower than the grid step (a factor
    1.15) could be missed.

    Parameters
    ----------
    L : (bands^2, ...) float
        Radiance coefficients.
    kind : {"hanning", "lanczos", "gauss"}
    quantity : {"irradiance", "radiance"}
        Which function must be non-negative: the irradiance ``A_l L_lm`` (default, what a
        diffuse map shows) or the radiance expansion itself.
    rtol : float
        Relative precision of the width.
    bands : int

    Returns
    -------
    windowed : (bands^2, ...) float64
        ``window(L, kind=kind, width=width)``.
    width : float
        The width used; ``inf`` if ``L`` needed no windowing.

    Raises
    ------
    ValueError
        For nan / inf coefficients, or if a channel has ``L_00 < 0`` (no window can help).
    """
    kinds = ("hanning", "lanczos", "gauss")
    if kind not in kinds:
        raise ValueError(f"kind must be one of {kinds}, got {kind!r}.")
    if quantity not in ("irradiance", "radiance"):
        raise ValueError(f"quantity must be one of ('irradiance', 'radiance'), got {quantity!r}.")
    if not 0 < rtol < 1:
        raise ValueError(f"rtol must be in (0, 1), got {rtol!r}.")
    c = check_coeffs(L, bands, "L")
    if not np.all(np.isfinite(c)):
        raise ValueError("L contains nan or inf; cannot choose a window.")
    if np.any(c[0] < 0):
        raise ValueError("L_00 is negative in some channel; no window can make it non-negative.")
    f = irradiance_coefficients(c, bands=bands) if quantity == "irradiance" else c

    def minima(widths: NDArray[np.float64]) -> NDArray[np.float64]:
        return _windowed_minima(f, kind, widths, bands)

    if minima(np.array([np.inf]))[0] >= 0.0:
        return c.copy(), float("inf")
    band0_only = 0.01 if kind == "gauss" else 1.0  # feasible: the constant pi L_00 K0 >= 0
    grid = np.append(np.geomspace(band0_only, 1e3, 48), 1e6)
    feasible = minima(grid) >= 0.0
    feasible[0] = True
    k = int(np.flatnonzero(feasible).max())
    if k == grid.size - 1:
        return _apply_window(c, kind, grid[k], bands), float(grid[k])
    lo, hi = grid[k], grid[k + 1]  # lo feasible, hi not
    while hi / lo > 1.0 + rtol:
        ws = np.geomspace(lo, hi, 18)[1:-1]
        ok = np.flatnonzero(minima(ws) >= 0.0)
        j = int(ok.max()) if ok.size else -1
        lo = ws[j] if j >= 0 else lo
        hi = ws[j + 1] if j + 1 < ws.size else hi
    return _apply_window(c, kind, lo, bands), float(lo)


def check_window_option(window: str) -> None:
    """Refuse a ``window`` option that is not one of :data:`probegrid._types.SHWindow`."""
    allowed = choices(SHWindow)
    if window not in allowed:
        raise ValueError(f"window must be one of {allowed}, got {window!r}.")


def apply_window_option(c: NDArray[np.float64], window: SHWindow, width: float | None, *,
                        bands: int) -> NDArray[np.float64]:
    """Coefficients ``c`` under a diffuse function's ``window`` option: unchanged for "none",
    :func:`auto_window`'s (hanning) for "auto" (no ``width``: it is searched), ``c`` windowed
    by ``window`` at ``width`` otherwise (a ``width`` needed)."""
    if window == "auto":
        if width is not None:
            raise ValueError("width must be None with window='auto' (the width is searched).")
        c, _ = auto_window(c, bands=bands)
    elif window != "none":
        if width is None:
            raise ValueError(f"window={window!r} needs a width.")
        c = _apply_window(c, window, width, bands)
    return c
