"""Real spherical harmonics: the project's basis, its indexing and evaluation, any band count.

This module *owns* the project's spherical-harmonic (SH) convention; every other module takes it
from here (through :mod:`probegrid.core.sh`).

Bands 0-2 (the stored basis)
----------------------------
Nine real, orthonormal SH basis functions of the unit direction ``d = (x, y, z)`` (bands
``l = 0, 1, 2``), stored at index ``i = l (l + 1) + m``, **without** the Condon-Shortley phase
``(-1)^m``, with the constants of Ramamoorthi & Hanrahan (2001), eq. 3 (printed there to six
digits; here exact)::

    i  (l, m)   Y_i(d)
    0  (0,  0)  K0                    K0 = 1 / (2 sqrt(pi))     = 0.282095
    1  (1, -1)  K1 y                  K1 = sqrt(3 / (4 pi))     = 0.488603
    2  (1,  0)  K1 z
    3  (1,  1)  K1 x
    4  (2, -2)  K2 x y                K2 = sqrt(15 / pi) / 2    = 1.092548
    5  (2, -1)  K2 y z
    6  (2,  0)  K3 (3 z^2 - 1)        K3 = sqrt(5 / pi) / 4     = 0.315392
    7  (2,  1)  K2 x z
    8  (2,  2)  K4 (x^2 - y^2)        K4 = sqrt(15 / pi) / 4    = 0.546274

``x, y, z`` are the glTF world axes (right-handed, **+Y up**). The formulas are applied to the
world components as they stand, so the zonal function ``Y_20`` is symmetric about world +Z (not
about "up"): this is the common graphics convention (Sloan 2008, R&H 2001 with their ``z``
renamed to ours), and it is what a shader evaluating ``sh_basis(n)`` with a world normal expects.
Directions are normalised inside :func:`sh_basis`, so any non-zero vector may be passed.

Any band count
--------------
The package's functions take ``bands`` (keyword, default :data:`NUM_BANDS` = 3, the
9-coefficient basis the bake and the store use; up to :data:`MAX_BANDS`, tested up to 9): bands
``l = 0 .. bands - 1``, ``bands^2`` coefficients (the quadratic form and the per-probe deringing
are band-0-2 ideas and take 9 coefficients). The same convention, extended: polar axis world
``+Z``, azimuth ``phi = atan2(y, x)``::

    Y_l0      = K_l0 P_l^0(z)
    Y_lm      = sqrt(2) K_lm P_l^m(z) cos(m phi)       m > 0
    Y_l,-m    = sqrt(2) K_lm P_l^m(z) sin(m phi)       m > 0
    K_lm      = sqrt((2 l + 1) / (4 pi) (l - m)! / (l + m)!)

with ``P_l^m`` the associated Legendre functions *without* the ``(-1)^m`` phase; bands 0-2 are
exactly the functions above (``Y_11 = K1 x``, ``Y_22 = K4 (x^2 - y^2)``, ...). With 3 bands the
explicit formulas are evaluated (the fast path); otherwise the general evaluation never forms
``phi`` or ``sin theta``: with ``P_l^m(z) = (1 - z^2)^(m/2) Q_l^m(z)`` and
``(x + i y)^m = (1 - z^2)^(m/2) e^(i m phi)``, ``Y_lm = sqrt(2) Qbar_lm(z) Re (x + i y)^m``
(``Im`` for ``-m``), where the normalised polynomial part follows the stable three-term
recurrence of fully normalised Legendre functions (as in SHTns, Schaeffer 2013, and Sloan
2013)::

    Qbar_mm     = Qbar_(m-1)(m-1) sqrt((2 m + 1) / (2 m)),    Qbar_00 = 1 / sqrt(4 pi)
    Qbar_(m+1)m = sqrt(2 m + 3) z Qbar_mm
    Qbar_lm     = a_lm (z Qbar_(l-1)m + b_lm Qbar_(l-2)m),
    a_lm = sqrt((4 l^2 - 1) / (l^2 - m^2)),  b_lm = -sqrt(((l - 1)^2 - m^2) / (4 (l - 1)^2 - 1))

and ``(x + i y)^m`` by complex multiplication. Every quantity stays of order 1 (no factorials),
so the recurrence is accurate to a few ulps at any band count used here.

Coefficients
------------
A coefficient array has shape ``(bands^2, ...)`` (typically ``(9, C)`` for ``C`` colour
channels) and float64 dtype. Stored coefficients are always *radiance* coefficients
``L_lm = integral L(w) Y_lm(w) dw`` (units: radiance x sr); for a constant environment ``L``,
``L_00 = 2 sqrt(pi) L`` and every other coefficient is 0. The pointwise functions
(:func:`sh_basis`, :func:`evaluate`) propagate nan / inf by IEEE arithmetic, without warnings.

References
----------
* R. Ramamoorthi, P. Hanrahan, "An Efficient Representation for Irradiance Environment Maps",
  SIGGRAPH 2001 (basis constants).
* P.-P. Sloan, "Stupid Spherical Harmonics (SH) Tricks", GDC 2008; "Efficient Spherical Harmonic
  Evaluation", JCGT 2(2), 2013 (recurrence without trigonometry).
* N. Schaeffer, "Efficient spherical harmonic transforms aimed at pseudospectral numerical
  simulations", G3 14(3), 2013 (normalised Legendre recurrence).
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "BAND_OF",
    "BASIS_SCALE",
    "K0",
    "K1",
    "K2",
    "K3",
    "K4",
    "MAX_BANDS",
    "NUM_BANDS",
    "NUM_COEFFS",
    "band_of",
    "bands_of",
    "basis_description",
    "evaluate",
    "num_coeffs",
    "sh_basis",
    "sh_index",
    "sh_lm",
]

#: Number of bands (l = 0, 1, 2) and of coefficients ((l_max + 1)^2) of the stored basis.
NUM_BANDS: Final = 3
NUM_COEFFS: Final = 9
#: Largest band count accepted (tested up to 9).
MAX_BANDS: Final = 16

#: Basis constants (R&H 2001 eq. 3, exact).
K0: Final = 0.5 * np.sqrt(1.0 / np.pi)
K1: Final = np.sqrt(3.0 / (4.0 * np.pi))
K2: Final = 0.5 * np.sqrt(15.0 / np.pi)
K3: Final = 0.25 * np.sqrt(5.0 / np.pi)
K4: Final = 0.25 * np.sqrt(15.0 / np.pi)

#: Constant factor of each of the 9 basis functions, (9,) float64.
BASIS_SCALE: Final[NDArray[np.float64]] = np.array([K0, K1, K1, K1, K2, K2, K3, K2, K4])
BASIS_SCALE.setflags(write=False)


# --------------------------------------------------------------------------------------------
# Indexing
# --------------------------------------------------------------------------------------------


def check_bands(bands: int) -> int:
    """``bands`` as an int, or ``ValueError`` unless it is an integer in ``1 .. MAX_BANDS``."""
    if (not isinstance(bands, (int, np.integer)) or isinstance(bands, bool)
            or not 1 <= bands <= MAX_BANDS):
        raise ValueError(f"bands must be an integer in 1..{MAX_BANDS}, got {bands!r}.")
    return int(bands)


def num_coeffs(bands: int) -> int:
    """``bands^2``: the number of coefficients of bands ``0 .. bands - 1``."""
    return check_bands(bands) ** 2


def bands_of(count: int) -> int:
    """The band count of ``count`` coefficients (``count`` must be a square ``1 .. 256``)."""
    b = math.isqrt(int(count))
    if b * b != count or not 1 <= b <= MAX_BANDS:
        raise ValueError(f"an SH coefficient array needs bands^2 rows (1, 4, 9, 16, ...) with at "
                         f"most {MAX_BANDS} bands, got {count}.")
    return b


def band_of(bands: int) -> NDArray[np.intp]:
    """Band ``l`` of every coefficient index, ``(bands^2,)`` intp."""
    b = check_bands(bands)
    return np.repeat(np.arange(b), 2 * np.arange(b) + 1).astype(np.intp)


#: Band ``l`` of each coefficient index of the stored basis, (9,) intp.
BAND_OF: Final[NDArray[np.intp]] = band_of(NUM_BANDS)
BAND_OF.setflags(write=False)


def sh_index(l: int, m: int, *, bands: int = NUM_BANDS) -> int:
    """Coefficient index ``l (l + 1) + m`` of band ``l`` (``0 .. bands - 1``), order ``m``
    (``-l .. l``)."""
    b = check_bands(bands)
    if not (0 <= l < b and -l <= m <= l):
        raise ValueError(f"(l, m) must satisfy 0 <= l <= {b - 1} and -l <= m <= l, "
                         f"got ({l}, {m}).")
    return l * (l + 1) + m


def sh_lm(index: int, *, bands: int = NUM_BANDS) -> tuple[int, int]:
    """Band and order ``(l, m)`` of a coefficient index ``0 .. bands^2 - 1`` (inverse of
    :func:`sh_index`)."""
    b = check_bands(bands)
    if not 0 <= index < b * b:
        raise ValueError(f"SH coefficient index must be in 0..{b * b - 1}, got {index}.")
    l = math.isqrt(index)
    return l, index - l * (l + 1)


def basis_description(bands: int) -> str:
    """The basis in words, for files (``sh.json``)."""
    b = check_bands(bands)
    return (f"real spherical harmonics, bands 0-{b - 1}, {b * b} coefficients, index l(l+1)+m, "
            "no Condon-Shortley phase, orthonormal over the sphere, polar axis world +Z, "
            "phi = atan2(y, x): Y_l0 = K_l0 P_l(z), Y_lm = sqrt(2) K_lm P_l^m(z) cos(m phi), "
            "Y_l-m = sqrt(2) K_lm P_l^m(z) sin(m phi), K_lm = sqrt((2l+1)/(4pi) (l-m)!/(l+m)!); "
            "bands 0-2 are the Ramamoorthi & Hanrahan 2001 functions")


def check_coeffs(coeffs: ArrayLike, bands: int, name: str = "coeffs") -> NDArray[np.float64]:
    """``coeffs`` as float64, or ``ValueError`` unless its first axis has ``bands^2`` rows."""
    b = check_bands(bands)
    c = np.asarray(coeffs, dtype=np.float64)
    if c.ndim < 1 or c.shape[0] != b * b:
        raise ValueError(f"{name} must have shape ({b * b}, ...) (bands^2 rows for {b} bands), "
                         f"got {c.shape}.")
    return c


# --------------------------------------------------------------------------------------------
# The basis
# --------------------------------------------------------------------------------------------


def unit_directions(directions: ArrayLike) -> NDArray[np.float64]:
    """``(..., 3)`` directions normalised as the SH bases take them: scaled by the largest
    component first (neither 1e-200 nor 1e200 under- or overflows); a row with a non-finite
    component becomes all nan (not a partly finite mixture); a zero vector raises."""
    d = np.asarray(directions, dtype=np.float64)
    if d.shape[-1:] != (3,):
        raise ValueError(f"directions must have shape (..., 3), got {d.shape}.")
    big = np.max(np.abs(d), axis=-1, keepdims=True)
    if np.any(big == 0.0):
        raise ValueError("directions must be non-zero vectors; got a zero vector.")
    with np.errstate(invalid="ignore"):
        d = d / big
        d = d / np.sqrt(np.einsum("...i,...i->...", d, d))[..., None]
    d[~np.all(np.isfinite(d), axis=-1)] = np.nan
    return d


def _basis3(d: NDArray[np.float64]) -> NDArray[np.float64]:
    """The nine band-0-2 functions at unit directions ``d (..., 3)`` by their explicit
    formulas, ``(..., 9)``."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = np.empty(d.shape[:-1] + (NUM_COEFFS,), dtype=np.float64)
    out[..., 0] = np.where(np.isnan(x), np.nan, K0)
    out[..., 1] = K1 * y
    out[..., 2] = K1 * z
    out[..., 3] = K1 * x
    out[..., 4] = K2 * x * y
    out[..., 5] = K2 * y * z
    out[..., 6] = K3 * (3.0 * z * z - 1.0)
    out[..., 7] = K2 * x * z
    out[..., 8] = K4 * (x * x - y * y)
    return out


def _recurrence(bands: int) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """``Qbar_mm`` (bands,), ``a_lm`` and ``b_lm`` (bands, bands) of the module docstring."""
    qmm = np.empty(bands)
    qmm[0] = 0.5 / math.sqrt(math.pi)
    for m in range(1, bands):
        qmm[m] = qmm[m - 1] * math.sqrt((2 * m + 1) / (2 * m))
    a = np.zeros((bands, bands))
    b = np.zeros((bands, bands))
    for m in range(bands):
        for l in range(m + 2, bands):
            a[l, m] = math.sqrt((4 * l * l - 1) / (l * l - m * m))
            b[l, m] = -math.sqrt(((l - 1) ** 2 - m * m) / (4 * (l - 1) ** 2 - 1))
    return qmm, a, b


def basis_unit(d: NDArray[np.float64], bands: int) -> NDArray[np.float64]:
    """The general basis (the recurrence of the module docstring, any band count) at unit
    directions ``d (..., 3)`` (nan rows propagate), ``(..., bands^2)``."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = np.empty(d.shape[:-1] + (bands * bands,), dtype=np.float64)
    qmm, a, b = _recurrence(bands)
    root2 = math.sqrt(2.0)
    c = np.ones_like(x)
    s = np.zeros_like(x)
    for m in range(bands):
        if m:
            c, s = x * c - y * s, x * s + y * c  # Re, Im of (x + i y)^m
        p2 = None
        p1 = np.full_like(z, qmm[m])
        for l in range(m, bands):
            if l == m:
                p = p1
            elif l == m + 1:
                p, p2 = math.sqrt(2 * m + 3) * z * qmm[m], p1
            else:
                p, p2 = a[l, m] * (z * p1 + b[l, m] * p2), p1
            p1 = p
            i = l * (l + 1)
            if m == 0:
                out[..., i] = p
            else:
                out[..., i + m] = root2 * p * c
                out[..., i - m] = root2 * p * s
    out[np.isnan(x)] = np.nan  # a non-finite direction gives a whole row of nan (Y_00 too)
    return out


def sh_basis(directions: ArrayLike, *, bands: int = NUM_BANDS) -> NDArray[np.float64]:
    """The ``bands^2`` basis functions at each direction.

    Parameters
    ----------
    directions : (..., 3) float
        Directions, normalised here (need not be unit length). A zero vector raises
        ``ValueError``; a direction with a nan or inf component gives a row of nan.
    bands : int
        Number of bands, ``1 .. MAX_BANDS``; 3 (the default) evaluates the explicit band-0-2
        formulas.

    Returns
    -------
    (..., bands^2) float64
        ``Y_i(d / |d|)`` in index order ``l (l + 1) + m`` (see the module docstring).
    """
    b = check_bands(bands)
    d = unit_directions(directions)
    return _basis3(d) if b == NUM_BANDS else basis_unit(d, b)


def evaluate(coeffs: ArrayLike, directions: ArrayLike, *, bands: int = NUM_BANDS
             ) -> NDArray[np.float64]:
    """Evaluate an SH expansion ``f(d) = sum_i coeffs_i Y_i(d)``.

    Parameters
    ----------
    coeffs : (bands^2, ...) float
        E.g. (9, C) for colour, (9,) for one channel.
    directions : (..., 3) float
        Normalised here.
    bands : int

    Returns
    -------
    (*directions.shape[:-1], *coeffs.shape[1:]) float64
    """
    c = check_coeffs(coeffs, bands)
    y = sh_basis(directions, bands=bands)
    return np.tensordot(y, c, axes=([-1], [0]))


@lru_cache(maxsize=4)
def fibonacci_directions(n: int) -> NDArray[np.float64]:
    """``n`` near-uniform unit directions on a Fibonacci spiral, (n, 3) float64, read-only."""
    k = np.arange(n, dtype=np.float64) + 0.5
    y = 1.0 - 2.0 * k / n
    r = np.sqrt(np.maximum(0.0, 1.0 - y * y))
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    d = np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=-1)
    d.setflags(write=False)
    return d
