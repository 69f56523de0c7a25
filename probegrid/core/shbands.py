"""Real spherical harmonics of any band count: basis, projection, irradiance, windows, minima.

The generalisation of :mod:`probegrid.core.sh` (which owns the project's SH convention and stays the
9-coefficient, band-0-2 implementation the bake and the store use) to ``bands`` bands
``l = 0 .. bands - 1`` (``bands^2`` coefficients), tested up to 9 bands and accepted up to
:data:`MAX_BANDS`. With ``bands = 3`` every function here returns what :mod:`probegrid.core.sh`
returns (it calls it), so 9-coefficient results do not depend on which module made them.

Basis
-----
The same convention as :mod:`probegrid.core.sh`, extended: real, orthonormal, **no** Condon-Shortley
phase, index ``i = l (l + 1) + m``, polar axis world ``+Z`` of the glTF frame, azimuth
``phi = atan2(y, x)``::

    Y_l0      = K_l0 P_l^0(z)
    Y_lm      = sqrt(2) K_lm P_l^m(z) cos(m phi)       m > 0
    Y_l,-m    = sqrt(2) K_lm P_l^m(z) sin(m phi)       m > 0
    K_lm      = sqrt((2 l + 1) / (4 pi) (l - m)! / (l + m)!)

with ``P_l^m`` the associated Legendre functions *without* the ``(-1)^m`` phase. Bands 0-2 are
exactly the Ramamoorthi-Hanrahan functions of :mod:`probegrid.core.sh` (``Y_11 = K1 x``,
``Y_22 = K4 (x^2 - y^2)``, ...). Evaluation never forms ``phi`` or ``sin theta``: with
``P_l^m(z) = (1 - z^2)^(m/2) Q_l^m(z)`` and ``(x + i y)^m = (1 - z^2)^(m/2) e^(i m phi)``,
``Y_lm = sqrt(2) Qbar_lm(z) Re (x + i y)^m`` (``Im`` for ``-m``), where the normalised polynomial
part follows the stable three-term recurrence of fully normalised Legendre functions (as in
SHTns, Schaeffer 2013, and Sloan 2013)::

    Qbar_mm     = Qbar_(m-1)(m-1) sqrt((2 m + 1) / (2 m)),    Qbar_00 = 1 / sqrt(4 pi)
    Qbar_(m+1)m = sqrt(2 m + 3) z Qbar_mm
    Qbar_lm     = a_lm (z Qbar_(l-1)m + b_lm Qbar_(l-2)m),
    a_lm = sqrt((4 l^2 - 1) / (l^2 - m^2)),  b_lm = -sqrt(((l - 1)^2 - m^2) / (4 (l - 1)^2 - 1))

and ``(x + i y)^m`` by complex multiplication. Every quantity stays of order 1 (no factorials),
so the recurrence is accurate to a few ulps at any band count used here.

Clamped cosine
--------------
The irradiance of radiance ``L = sum L_lm Y_lm`` is ``E(n) = sum A_l L_lm Y_lm(n)`` (Funk-Hecke)
with the clamped-cosine band factors (Ramamoorthi & Hanrahan 2001, eq. 8)::

    A_0 = pi,  A_1 = 2 pi / 3,  A_l = 0 for odd l > 1,
    A_l = 2 pi (-1)^(l/2 - 1) / ((l + 2)(l - 1)) * l! / (2^l ((l/2)!)^2)   for even l >= 2

(``A_2 = pi/4, A_4 = -pi/24, A_6 = pi/64, A_8 = -pi/128``; :func:`clamped_cosine_factors`, computed
with exact integer binomials). Odd bands above 1 carry no irradiance, so a ``2k + 1``-band and a
``2k + 2``-band irradiance are the same function.

Projection
----------
:func:`project_cube` sums ``L(texel) Y_i(texel centre) dOmega`` over every texel with the exact
solid angles of :mod:`probegrid.core.cubemap`, in float64, sharing one local weighted basis between
the six faces through each face's SH transform (as :mod:`probegrid.core.sh` does; the transform of a
band is found exactly by solving ``Y_l(B d) = M_l Y_l(d)`` on ``4 (2 l + 1)`` directions: band
spaces are rotation invariant, so the solution is exact to rounding). :func:`project_equirect`
projects a latitude-longitude image pixel by pixel with its exact solid angles
``(2 pi / W)(sin theta_top - sin theta_bottom)``: the best projection of a lat-long input (used
by the benchmark as the "best this band count allows" reference). :func:`project_samples` is the
weighted sum over any sample set.

Windows and minima
------------------
:func:`window_factors` gives Sloan's (2008) hanning, lanczos and gauss factors for any band count
(formulas in :mod:`probegrid.core.sh`). :func:`min_over_sphere` finds the minimum of any SH function
over the sphere: a dense Fibonacci search (``max(4096, 32 bands^2)`` directions, spacing a
quarter of the shortest wavelength ``2 pi / (bands - 1)`` or better), then damped Newton steps in
a tangent chart of the best 32 candidates per channel, with the gradient and Hessian from central
differences (``h = 1e-3`` rad; the functions are polynomials of degree ``< bands`` on the
sphere, so this converges to the critical point to ~1e-10 rad). :func:`auto_window` picks the
gentlest window that makes the irradiance (or radiance) non-negative, with the search of
:func:`probegrid.sh.auto_window`.

Non-finite input raises in the projections and the minimum search and propagates (as nan) in the
pointwise functions, as in :mod:`probegrid.core.sh`.

References
----------
* R. Ramamoorthi, P. Hanrahan, "An Efficient Representation for Irradiance Environment Maps",
  SIGGRAPH 2001 (``A_l``).
* P.-P. Sloan, "Stupid Spherical Harmonics (SH) Tricks", GDC 2008 (windowing);
  "Efficient Spherical Harmonic Evaluation", JCGT 2(2), 2013 (recurrence without trigonometry).
* N. Schaeffer, "Efficient spherical harmonic transforms aimed at pseudospectral numerical
  simulations", G3 14(3), 2013 (normalised Legendre recurrence).
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Final, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._types import SHWindow, WindowKind
from probegrid.core import cubemap as cm
from probegrid.core import sh as sh3

__all__ = [
    "MAX_BANDS",
    "auto_window",
    "band_of",
    "bands_of",
    "basis",
    "basis_description",
    "clamped_cosine_factors",
    "diffuse_cube",
    "evaluate",
    "irradiance",
    "irradiance_coefficients",
    "min_over_sphere",
    "num_coeffs",
    "project_cube",
    "project_equirect",
    "project_samples",
    "rotate",
    "rotation_matrix",
    "sh_index",
    "sh_lm",
    "window",
    "window_factors",
]

#: Largest band count accepted (tested up to 9).
MAX_BANDS: Final = 16

#: Texels / samples per block of a projection (bounded (block, bands^2) float64 basis slices).
_BLOCK_VALUES: Final = 1 << 20
#: Largest local weighted basis cached (bands^2 x n^2 float64 values): 8 M values = 64 MB.
_CACHE_VALUES: Final = 1 << 23
_MIN_REFINE: Final = 32
_NEWTON_STEPS: Final = 12
_FD_STEP: Final = 1e-3
_MIN_CHANNEL_BLOCK: Final = 64


# --------------------------------------------------------------------------------------------
# Indexing


def _check_bands(bands: int) -> int:
    if (not isinstance(bands, (int, np.integer)) or isinstance(bands, bool)
            or not 1 <= bands <= MAX_BANDS):
        raise ValueError(f"bands must be an integer in 1..{MAX_BANDS}, got {bands!r}.")
    return int(bands)


def num_coeffs(bands: int) -> int:
    """``bands^2``: the number of coefficients of bands ``0 .. bands - 1``."""
    return _check_bands(bands) ** 2


def bands_of(count: int) -> int:
    """The band count of ``count`` coefficients (``count`` must be a square ``1 .. 256``)."""
    b = math.isqrt(int(count))
    if b * b != count or not 1 <= b <= MAX_BANDS:
        raise ValueError(f"an SH coefficient array needs bands^2 rows (1, 4, 9, 16, ...) with at "
                         f"most {MAX_BANDS} bands, got {count}.")
    return b


def band_of(bands: int) -> NDArray[np.intp]:
    """Band ``l`` of every coefficient index, ``(bands^2,)`` intp."""
    b = _check_bands(bands)
    return np.repeat(np.arange(b), 2 * np.arange(b) + 1).astype(np.intp)


def sh_index(l: int, m: int) -> int:
    """Coefficient index ``l (l + 1) + m`` of band ``l`` (``0 <= l < MAX_BANDS``), ``|m| <= l``."""
    if not (0 <= l < MAX_BANDS and -l <= m <= l):
        raise ValueError(f"(l, m) must satisfy 0 <= l < {MAX_BANDS} and -l <= m <= l, "
                         f"got ({l}, {m}).")
    return l * (l + 1) + m


def sh_lm(index: int) -> tuple[int, int]:
    """Band and order ``(l, m)`` of a coefficient index (inverse of :func:`sh_index`)."""
    if not 0 <= index < MAX_BANDS**2:
        raise ValueError(f"SH coefficient index must be in 0..{MAX_BANDS**2 - 1}, got {index}.")
    l = math.isqrt(index)
    return l, index - l * (l + 1)


def basis_description(bands: int) -> str:
    """The basis in words, for files (``sh.json``)."""
    b = _check_bands(bands)
    return (f"real spherical harmonics, bands 0-{b - 1}, {b * b} coefficients, index l(l+1)+m, "
            "no Condon-Shortley phase, orthonormal over the sphere, polar axis world +Z, "
            "phi = atan2(y, x): Y_l0 = K_l0 P_l(z), Y_lm = sqrt(2) K_lm P_l^m(z) cos(m phi), "
            "Y_l-m = sqrt(2) K_lm P_l^m(z) sin(m phi), K_lm = sqrt((2l+1)/(4pi) (l-m)!/(l+m)!); "
            "bands 0-2 are the Ramamoorthi & Hanrahan 2001 functions")


# --------------------------------------------------------------------------------------------
# Basis


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


def _basis_unit(d: NDArray[np.float64], bands: int) -> NDArray[np.float64]:
    """Basis at unit directions ``d (..., 3)`` (nan rows propagate), ``(..., bands^2)``."""
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


def basis(directions: ArrayLike, bands: int) -> NDArray[np.float64]:
    """The ``bands^2`` basis functions at each direction.

    Parameters
    ----------
    directions : (..., 3) float
        Normalised here (need not be unit length); a zero vector raises ``ValueError``, a
        direction with a nan or inf component gives a row of nan.
    bands : int
        Number of bands, ``1 .. MAX_BANDS``.

    Returns
    -------
    (..., bands^2) float64
        ``Y_i(d / |d|)`` in index order ``l (l + 1) + m``; for ``bands = 3`` exactly
        :func:`probegrid.sh.sh_basis`.
    """
    b = _check_bands(bands)
    if b == sh3.NUM_BANDS:
        return sh3.sh_basis(directions)
    return _basis_unit(sh3.unit_directions(directions), b)


# --------------------------------------------------------------------------------------------
# Clamped cosine, evaluation, irradiance


@lru_cache(maxsize=MAX_BANDS)
def _factors(bands: int) -> NDArray[np.float64]:
    out = np.zeros(bands)
    for l in range(bands):
        if l == 0:
            out[l] = math.pi
        elif l == 1:
            out[l] = 2.0 * math.pi / 3.0
        elif l % 2 == 0:
            sign = -1.0 if (l // 2 - 1) % 2 else 1.0
            out[l] = (2.0 * math.pi * sign / ((l + 2) * (l - 1))
                      * (math.comb(l, l // 2) / 2.0**l))
    out.setflags(write=False)
    return out


def clamped_cosine_factors(bands: int) -> NDArray[np.float64]:
    """The clamped-cosine band factors ``A_l``, ``l = 0 .. bands - 1`` (read-only, float64).

    ``A_0 = pi``, ``A_1 = 2 pi / 3``, ``A_l = 0`` for odd ``l > 1`` and the closed form of the
    module docstring for even ``l`` (``A_2 = pi / 4``, ``A_4 = -pi / 24``, ``A_6 = pi / 64``).
    """
    return _factors(_check_bands(bands))


def _coeffs(coeffs: ArrayLike, name: str = "coeffs") -> tuple[NDArray[np.float64], int]:
    c = np.asarray(coeffs, dtype=np.float64)
    if c.ndim < 1:
        raise ValueError(f"{name} must have shape (bands^2, ...), got {c.shape}.")
    try:
        b = bands_of(c.shape[0])
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from None
    return c, b


def _per_coeff(per_band: NDArray[np.float64], c: NDArray[np.float64]) -> NDArray[np.float64]:
    b = len(per_band)
    return per_band[band_of(b)].reshape((b * b,) + (1,) * (c.ndim - 1))


def evaluate(coeffs: ArrayLike, directions: ArrayLike) -> NDArray[np.float64]:
    """``f(d) = sum_i coeffs_i Y_i(d)`` for coefficients ``(bands^2, ...)``.

    Returns
    -------
    (*directions.shape[:-1], *coeffs.shape[1:]) float64
    """
    c, b = _coeffs(coeffs)
    return np.tensordot(basis(directions, b), c, axes=([-1], [0]))


def irradiance_coefficients(L: ArrayLike) -> NDArray[np.float64]:
    """``A_l L_lm`` of radiance coefficients ``(bands^2, ...)``: the irradiance's coefficients."""
    c, b = _coeffs(L, "L")
    return c * _per_coeff(clamped_cosine_factors(b), c)


def irradiance(L: ArrayLike, normals: ArrayLike) -> NDArray[np.float64]:
    """Irradiance ``E(n) = sum A_l L_lm Y_lm(n)`` (radiance x sr) at each normal."""
    return evaluate(irradiance_coefficients(L), normals)


# --------------------------------------------------------------------------------------------
# Rotation (exact per band)


@lru_cache(maxsize=4)
def _fit_directions(count: int) -> NDArray[np.float64]:
    d = sh3._fibonacci_directions(count)
    # a generic rotation, so that no fitting direction lies on a symmetry axis of the cube
    r = np.linalg.qr(np.array([[0.3, -0.8, 0.5], [0.9, 0.2, -0.4], [0.1, 0.6, 0.7]]))[0]
    return d @ r.T


def _transform(matrix: NDArray[np.float64], bands: int) -> NDArray[np.float64]:
    """``M`` with ``Y(B d) = M Y(d)`` for an orthogonal ``B``: block diagonal, one exact
    least-squares solve per band (band spaces are invariant, so the fit has zero residual)."""
    k = bands * bands
    d = _fit_directions(4 * (2 * bands - 1))
    y = _basis_unit(d, bands)
    yb = _basis_unit(d @ matrix.T, bands)
    out = np.zeros((k, k))
    for l in range(bands):
        sl = slice(l * l, (l + 1) ** 2)
        mt, *_ = np.linalg.lstsq(y[:, sl], yb[:, sl], rcond=None)
        out[sl, sl] = mt.T
    return out


def rotation_matrix(rotation: ArrayLike, bands: int) -> NDArray[np.float64]:
    """``(bands^2, bands^2)`` matrix ``Q`` with ``rotate(L, R) = Q @ L``.

    The coefficients of ``L'(d) = L(R^T d)`` (what was seen toward ``d`` is seen toward
    ``R d``), block diagonal by band; the same convention as :func:`probegrid.sh.rotate`.
    """
    b = _check_bands(bands)
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-9):
        raise ValueError("rotation must be an orthogonal (3, 3) matrix.")
    # L'(d) = c . Y(R^T d) = c . M Y(d) with M the transform of R^T: c' = M^T c.
    return _transform(r.T, b).T


def rotate(L: ArrayLike, rotation: ArrayLike) -> NDArray[np.float64]:
    """Coefficients ``(bands^2, ...)`` of the rotated function ``L'(d) = L(R^T d)``."""
    c, b = _coeffs(L, "L")
    return np.tensordot(rotation_matrix(rotation, b), c, axes=([1], [0]))


# --------------------------------------------------------------------------------------------
# Projection


def _raise_if_nonfinite(result: NDArray[np.float64], what: str) -> None:
    bad = ~np.isfinite(result[0])  # Y_00 > 0 everywhere: any nan / inf input reaches L_00
    if np.any(bad):
        chans = np.flatnonzero(bad.reshape(-1)).tolist()
        raise ValueError(f"{what} contain nan or inf values (channel(s) {chans}); the SH "
                         "projection would be undefined, so clean or clamp the input first.")


@lru_cache(maxsize=MAX_BANDS)
def _face_transforms(bands: int) -> NDArray[np.float64]:
    out = np.stack([_transform(np.stack([cm.FACE_U[f], cm.FACE_V[f], cm.FACE_NORMALS[f]],
                                        axis=1), bands) for f in range(6)])
    out.setflags(write=False)
    return out


def _local_weighted_basis(n: int, row0: int, row1: int, bands: int) -> NDArray[np.float64]:
    """``Y(l) dOmega`` for face rows ``row0:row1`` in the face's own frame (``l = (u, v, 1)``
    normalised), ``(bands^2, (row1 - row0) n)``; exact texel solid angles."""
    edges = np.linspace(-1.0, 1.0, n + 1)
    ue = edges[None, :]
    ve = edges[row0:row1 + 1, None]
    f = np.arctan2(ue * ve, np.sqrt(ue * ue + ve * ve + 1.0))
    solid = f[1:, 1:] - f[:-1, 1:] - f[1:, :-1] + f[:-1, :-1]
    u = 0.5 * (ue[:, 1:] + ue[:, :-1])
    v = 0.5 * (ve[1:] + ve[:-1])
    local = np.stack(np.broadcast_arrays(u, v, np.ones_like(u * v)), axis=-1)
    local /= np.linalg.norm(local, axis=-1, keepdims=True)
    y = _basis_unit(local, bands) * solid[..., None]
    return np.ascontiguousarray(y.reshape(-1, bands * bands).T)


@lru_cache(maxsize=4)
def _cached_local_weighted_basis(n: int, bands: int) -> NDArray[np.float64]:
    g = _local_weighted_basis(n, 0, n, bands)
    g.setflags(write=False)
    return g


def project_cube(faces: ArrayLike, bands: int) -> NDArray[np.float64]:
    """Radiance SH coefficients of a cube map, exact texel solid angles, float64 sums.

    Parameters
    ----------
    faces : (6, n, n, C) or (6, n, n) float
    bands : int

    Returns
    -------
    (bands^2, C) float64, or (bands^2,) for a 3-D input; for ``bands = 3``
    :func:`probegrid.sh.project_cube`.
    """
    b = _check_bands(bands)
    if b == sh3.NUM_BANDS:
        return sh3.project_cube(faces)
    a = np.asarray(faces)
    squeeze = a.ndim == 3
    if squeeze:
        a = a[..., None]
    if a.ndim != 4 or a.shape[0] != 6 or a.shape[1] != a.shape[2] or a.shape[1] < 1:
        raise ValueError(f"faces must have shape (6, n, n, C) or (6, n, n), got {a.shape}.")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"faces must hold real numbers, got dtype {a.dtype}.")
    n, c, k = int(a.shape[1]), int(a.shape[3]), b * b
    cached = (_cached_local_weighted_basis(n, b) if k * n * n <= _CACHE_VALUES else None)
    rows = max(1, _BLOCK_VALUES // (k * n))
    transforms = _face_transforms(b)
    out = np.zeros((k, c))
    with np.errstate(invalid="ignore", over="ignore"):
        for f in range(6):
            moments = np.zeros((k, c))
            for r0 in range(0, n, rows):
                r1 = min(r0 + rows, n)
                g = (cached[:, r0 * n:r1 * n] if cached is not None
                     else _local_weighted_basis(n, r0, r1, b))
                moments += g @ a[f, r0:r1].reshape(-1, c).astype(np.float64)
            out += transforms[f] @ moments
    _raise_if_nonfinite(out, "faces")
    return out[:, 0] if squeeze else out


def project_samples(values: ArrayLike, directions: ArrayLike, weights: ArrayLike,
                    bands: int) -> NDArray[np.float64]:
    """``L_i = sum_k values_k Y_i(directions_k) weights_k`` for any weighted sample set.

    Parameters
    ----------
    values : (N, C) or (N,) float
    directions : (N, 3) float, normalised here
    weights : (N,) float or scalar, solid angle per sample (sr)
    bands : int

    Returns
    -------
    (bands^2, C) or (bands^2,) float64
    """
    b = _check_bands(bands)
    v = np.asarray(values, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"directions must have shape (N, 3), got {d.shape}.")
    squeeze = v.ndim == 1
    if squeeze:
        v = v[:, None]
    if v.ndim != 2 or v.shape[0] != d.shape[0]:
        raise ValueError(f"values must have shape (N, C) or (N,) with N = {d.shape[0]}, got "
                         f"{np.shape(values)}.")
    w = np.asarray(weights, dtype=np.float64)
    if w.shape not in ((), (d.shape[0],)):
        raise ValueError(f"weights must be a scalar or have shape ({d.shape[0]},), got {w.shape}.")
    w = np.broadcast_to(w, (d.shape[0],))
    out = np.zeros((b * b, v.shape[1]))
    step = max(1, _BLOCK_VALUES // (b * b))
    with np.errstate(invalid="ignore", over="ignore"):
        for s in range(0, d.shape[0], step):
            y = basis(d[s:s + step], b)
            out += (y * w[s:s + step, None]).T @ v[s:s + step]
    if d.shape[0]:
        _raise_if_nonfinite(out, "values or weights")
    return out[:, 0] if squeeze else out


def project_equirect(image: ArrayLike, bands: int) -> NDArray[np.float64]:
    """Radiance SH coefficients of a latitude-longitude image, pixel by pixel.

    Each pixel contributes ``L Y(centre) dOmega`` with its exact solid angle
    ``(2 pi / W)(sin theta_top - sin theta_bottom)`` (the layout of :mod:`probegrid.core.layouts`:
    centre column +X, a quarter to the right +Z, top row +Y).

    Parameters
    ----------
    image : (H, W, C) float, ``W = 2 H``
    bands : int

    Returns
    -------
    (bands^2, C) float64
    """
    from probegrid.core.layouts import equirect_directions

    b = _check_bands(bands)
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[1] != 2 * img.shape[0] or img.shape[0] < 1:
        raise ValueError(f"image must be a 2:1 (H, 2H, C) lat-long array, got {img.shape}.")
    h, w, c = img.shape
    edges = np.pi * (0.5 - np.arange(h + 1) / h)                  # latitudes of row edges
    row_sa = (2.0 * np.pi / w) * (np.sin(edges[:-1]) - np.sin(edges[1:]))
    dirs = equirect_directions(h, w)
    out = np.zeros((b * b, c))
    rows = max(1, _BLOCK_VALUES // (b * b * w))
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        y = _basis_unit(dirs[r0:r1].reshape(-1, 3), b)
        wts = np.repeat(row_sa[r0:r1], w)
        with np.errstate(invalid="ignore", over="ignore"):
            out += (y * wts[:, None]).T @ img[r0:r1].reshape(-1, c).astype(np.float64)
    _raise_if_nonfinite(out, "image pixels")
    return out


# --------------------------------------------------------------------------------------------
# Windowing


def window_factors(kind: WindowKind, width: float, bands: int) -> NDArray[np.float64]:
    """Per-band window factors ``h_0 .. h_(bands-1)`` (Sloan 2008; formulas in
    :mod:`probegrid.core.sh`), ``h_0 = 1``; ``width = inf`` or kind "none" is no window."""
    return sh3.window_factors(kind, width, bands=_check_bands(bands))


def window(L: ArrayLike, *, kind: WindowKind, width: float) -> NDArray[np.float64]:
    """Scale each band of ``L (bands^2, ...)`` by its window factor."""
    return _apply_window(L, kind, width)


def _apply_window(L: ArrayLike, kind: WindowKind, width: float) -> NDArray[np.float64]:
    c, b = _coeffs(L, "L")
    return c * _per_coeff(window_factors(kind, width, b), c)


# --------------------------------------------------------------------------------------------
# Minimum over the sphere


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
        y = _basis_unit(points, bands)
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


def min_over_sphere(coeffs: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Minimum over all directions of an SH function ``(bands^2, ...)``, per channel.

    Dense Fibonacci search, then Newton refinement of the 32 best samples per channel (module
    docstring); for 9 coefficients :func:`probegrid.sh.min_over_sphere` (exact quadratic form).

    Returns
    -------
    values : (...) float64
    directions : (..., 3) float64, unit vectors where the minima are reached

    Raises
    ------
    ValueError
        For nan / inf coefficients.
    """
    a, b = _coeffs(coeffs)
    if b == sh3.NUM_BANDS:
        return sh3.min_over_sphere(a)
    if not np.all(np.isfinite(a)):
        raise ValueError("coeffs contain nan or inf; the minimum over the sphere is undefined.")
    rest = a.shape[1:]
    flat = a.reshape(b * b, -1)
    if b == 1:  # a constant
        return (flat[0] * sh3.K0).reshape(rest), np.tile([0.0, 0.0, 1.0], flat.shape[1:] + (1,)
                                                          ).reshape(rest + (3,))
    dirs = sh3._fibonacci_directions(max(4096, 32 * b * b))
    y = _basis_unit(dirs, b)
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


def _windowed_minima(f: NDArray[np.float64], kind: WindowKind, widths: NDArray[np.float64]
                     ) -> NDArray[np.float64]:
    b = bands_of(f.shape[0])
    flat = f.reshape(b * b, -1)
    h = np.stack([window_factors(kind, w, b)[band_of(b)] for w in widths], axis=1)
    vals, _ = min_over_sphere(flat[:, None, :] * h[:, :, None])
    return vals.min(axis=1)


def auto_window(
    L: ArrayLike,
    *,
    kind: Literal["hanning", "lanczos", "gauss"] = "hanning",
    quantity: Literal["irradiance", "radiance"] = "irradiance",
    rtol: float = 1e-4,
) -> tuple[NDArray[np.float64], float]:
    """The gentlest window of a kind that makes an SH function of any order non-negative.

    The search of :func:`probegrid.sh.auto_window` (a log-spaced scan of widths, then a
    narrowing of the bracket after the largest feasible one) with this module's minimum; for
    9 coefficients it is :func:`probegrid.sh.auto_window`.

    Returns
    -------
    windowed : (bands^2, ...) float64
    width : float, ``inf`` when no window was needed
    """
    c, b = _coeffs(L, "L")
    if b == sh3.NUM_BANDS:
        return sh3.auto_window(c, kind=kind, quantity=quantity, rtol=rtol)
    sh3.check_auto_window_options(kind, quantity, rtol)
    sh3.check_auto_window_coeffs(c)
    f = irradiance_coefficients(c) if quantity == "irradiance" else c
    return sh3.gentlest_window(c, f, kind, rtol, minima=_windowed_minima, apply=_apply_window)


# --------------------------------------------------------------------------------------------
# Diffuse map


def diffuse_cube(
    L: ArrayLike,
    size: int,
    *,
    window: SHWindow = "none",
    width: float | None = None,
) -> NDArray[np.float32]:
    """Diffuse (irradiance / pi) cube from radiance coefficients ``(bands^2, C)`` of any order.

    ``window`` / ``width`` as in :func:`probegrid.sh.diffuse_cube` (``"auto"``: the gentlest
    hanning window making the irradiance non-negative). Returns ``(6, size, size, C)`` float32.
    """
    c, b = _coeffs(L, "L")
    if b == sh3.NUM_BANDS:
        return sh3.diffuse_cube(c, size, window=window, width=width)
    sh3.check_window_option(window)
    if c.ndim == 1:
        c = c[:, None]
    if c.ndim != 2:
        raise ValueError(f"L must have shape (bands^2, C) or (bands^2,), got {c.shape}.")
    c = sh3.apply_window_option(c, window, width, auto=auto_window, apply=_apply_window)
    dirs = cm.texel_directions(size)
    return (evaluate(irradiance_coefficients(c), dirs) / np.pi).astype(np.float32)
