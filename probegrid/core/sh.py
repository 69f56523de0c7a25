"""Real spherical harmonics, bands 0-2: projection, irradiance, windowing and rotation.

This module *owns* the project's spherical-harmonic (SH) convention; every other module imports
it from here.

Basis
-----
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

Coefficients
------------
A coefficient array has shape ``(9, ...)`` (typically ``(9, C)`` for ``C`` colour channels) and
float64 dtype. Stored coefficients are always *radiance* coefficients
``L_lm = integral L(w) Y_lm(w) dw`` (units: radiance x sr). The irradiance of a surface with
normal ``n`` is (R&H 2001, eq. 7-8 and 12)::

    E(n) = sum_lm A_l L_lm Y_lm(n),   A_0 = pi, A_1 = 2 pi / 3, A_2 = pi / 4

(the band factors :data:`A_HAT` of the clamped cosine ``max(0, cos theta)``). Dropping bands
``l > 2`` costs at most about 9 % of the peak irradiance (R&H section 2); for one directional
light the error is exactly ``3/32 = 9.4 %`` of the peak, at the terminator (tested). A *diffuse
map* (:func:`diffuse_cube`) holds ``E / pi``, the outgoing radiance of a white Lambertian surface,
so a constant environment of radiance ``L`` gives ``L`` everywhere (the white furnace). For a
constant environment ``L_00 = 2 sqrt(pi) L`` and every other coefficient is 0.

Projection
----------
:func:`project_cube` computes ``L_i = sum_texels L(texel) Y_i(texel centre) solid_angle`` with
the exact texel solid angles of :mod:`probegrid.core.cubemap`, in float64 throughout (float32 texels
are widened, not rounded; measured error vs an extended-precision sum ~2e-16 of ``L_00``). It uses
the cube's symmetry: face ``f`` maps its local direction ``l = (u, v, 1) / |(u, v, 1)|`` to the
world direction ``d = B_f l`` with the orthogonal ``B_f = [FACE_U | FACE_V | FACE_NORMAL]``, so
``Y(d) = M_f Y(l)`` with ``M_f`` the (exact) SH transform of ``B_f``. Hence one *shared*
``(9, n^2)`` weighted local basis ``G = Y(l) solid_angle`` serves all six faces::

    L = sum_f M_f (G @ faces[f])

``G`` is cached read-only per face size for ``n <= 512`` (19 MB at 512; 1.2 MB at 128) and
computed block by block for larger faces, so memory stays bounded. :func:`project_samples` does
the plain weighted sum for any sample set.

Windowing
---------
Truncating at band 2 rings: a bright sun gives negative irradiance on the far side (for one
directional light the truncated irradiance dips to ``-19/480 = -4 %`` of its peak). Following
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
than band 2 helps; gauss improves monotonically. :func:`min_over_sphere` finds the minimum of any band-0-2 function (dense
Fibonacci sampling, then Riemannian Newton refinement of the quadratic ``c + b . d + d^T S d``
that the function is on the unit sphere), and :func:`auto_window` picks the largest width (the
least smoothing) whose windowed irradiance is non-negative everywhere.

Rotation
--------
:func:`rotate` returns the coefficients of the rotated environment ``L'(d) = L(R^T d)`` (what
was seen in direction ``d`` is seen in direction ``R d``). Band 1 rotates as the vector
``(x, y, z)``; band 2 as the traceless symmetric matrix ``S`` of its quadratic form
(``S -> R S R^T``), so rotation is exact. :func:`rotate_y` rotates about world +Y by the right-hand
rule (a positive quarter turn takes +Z to +X).

Non-finite values
-----------------
The projections (:func:`project_cube`, :func:`project_samples`) and :func:`min_over_sphere` /
:func:`auto_window` **raise** ``ValueError`` on nan / inf input (a single bad texel would
otherwise poison all nine coefficients silently). The pointwise functions (:func:`sh_basis`,
:func:`evaluate`, :func:`irradiance`, :func:`diffuse_cube`, :func:`window`, :func:`rotate`)
**propagate** nan / inf by IEEE arithmetic, without warnings.

References
----------
* R. Ramamoorthi, P. Hanrahan, "An Efficient Representation for Irradiance Environment Maps",
  SIGGRAPH 2001 (basis constants, ``A_l``, eq. 13 quadratic form).
* P.-P. Sloan, "Stupid Spherical Harmonics (SH) Tricks", GDC 2008 (windowing, rotation).
* J. M. Martinez, "Local minimizers of quadratic functions on Euclidean balls and spheres",
  SIAM J. Optim. 4(1), 1994: a quadratic on the sphere has at most one local minimum besides the
  global one, which is why refining the best samples of a dense set finds the global minimum.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache
from typing import Any, Final, Literal, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._types import SHWindow, WindowKind, choices
from probegrid.core import cubemap as cm

__all__ = [
    "A_HAT",
    "BAND_OF",
    "BASIS_SCALE",
    "K0",
    "K1",
    "K2",
    "K3",
    "K4",
    "NUM_BANDS",
    "NUM_COEFFS",
    "WindowKind",
    "auto_window",
    "diffuse_cube",
    "dual_maximiser",
    "eigen_form",
    "evaluate",
    "irradiance",
    "irradiance_coefficients",
    "min_over_sphere",
    "project_cube",
    "project_samples",
    "rotate",
    "rotate_y",
    "rotation_y",
    "sh_basis",
    "sh_index",
    "sh_lm",
    "window",
    "window_factors",
]

#: Number of bands (l = 0, 1, 2) and of coefficients ((l_max + 1)^2).
NUM_BANDS: Final = 3
NUM_COEFFS: Final = 9

#: Basis constants (R&H 2001 eq. 3, exact).
K0: Final = 0.5 * np.sqrt(1.0 / np.pi)
K1: Final = np.sqrt(3.0 / (4.0 * np.pi))
K2: Final = 0.5 * np.sqrt(15.0 / np.pi)
K3: Final = 0.25 * np.sqrt(5.0 / np.pi)
K4: Final = 0.25 * np.sqrt(15.0 / np.pi)

#: Constant factor of each of the 9 basis functions, (9,) float64.
BASIS_SCALE: Final[NDArray[np.float64]] = np.array([K0, K1, K1, K1, K2, K2, K3, K2, K4])
#: Band ``l`` of each coefficient index, (9,) intp.
BAND_OF: Final[NDArray[np.intp]] = np.array([0, 1, 1, 1, 2, 2, 2, 2, 2], dtype=np.intp)
#: Clamped-cosine band factors ``A_l`` per coefficient (R&H 2001 eq. 8):
#: ``(pi, 2pi/3, 2pi/3, 2pi/3, pi/4, pi/4, pi/4, pi/4, pi/4)``, (9,) float64.
A_HAT: Final[NDArray[np.float64]] = np.array(
    [np.pi] + [2.0 * np.pi / 3.0] * 3 + [np.pi / 4.0] * 5, dtype=np.float64
)
for _a in (BASIS_SCALE, BAND_OF, A_HAT):
    _a.setflags(write=False)

_WINDOW_KINDS: Final[tuple[str, ...]] = get_args(WindowKind)

#: Texels per block in the projection (bounded memory: a (9, block) float64 basis slice).
_BLOCK: Final = 8192
#: Largest face size whose (9, n^2) local weighted basis is cached (9 x 512^2 float64 = 19 MB).
_CACHE_MAX_SIZE: Final = 512
#: Fibonacci samples of :func:`min_over_sphere`'s search, and how many of the best are refined.
_MIN_SAMPLES: Final = 4096
_MIN_REFINE: Final = 32
#: Newton steps (quadratic convergence: 6 gave the same bits as 12 on 5000 random functions).
_NEWTON_STEPS: Final = 8
_MIN_CHANNEL_BLOCK: Final = 256


# --------------------------------------------------------------------------------------------
# Indexing and the basis
# --------------------------------------------------------------------------------------------


def sh_index(l: int, m: int) -> int:
    """Coefficient index ``l (l + 1) + m`` of band ``l`` (0-2), order ``m`` (``-l..l``)."""
    if not (0 <= l < NUM_BANDS and -l <= m <= l):
        raise ValueError(f"(l, m) must satisfy 0 <= l <= 2 and -l <= m <= l, got ({l}, {m}).")
    return l * (l + 1) + m


def sh_lm(index: int) -> tuple[int, int]:
    """Band and order ``(l, m)`` of a coefficient index 0-8 (inverse of :func:`sh_index`)."""
    if not 0 <= index < NUM_COEFFS:
        raise ValueError(f"SH coefficient index must be in 0..8, got {index}.")
    l = int(np.floor(np.sqrt(index)))
    return l, index - l * (l + 1)


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


def sh_basis(directions: ArrayLike) -> NDArray[np.float64]:
    """The nine basis functions at each direction.

    Parameters
    ----------
    directions : (..., 3) float
        Directions, normalised here (need not be unit length). A zero vector raises
        ``ValueError``; a direction with a nan or inf component gives a row of nan.

    Returns
    -------
    (..., 9) float64
        ``Y_i(d / |d|)`` in index order ``l (l + 1) + m`` (see the module docstring).
    """
    d = unit_directions(directions)
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


# --------------------------------------------------------------------------------------------
# Projection
# --------------------------------------------------------------------------------------------


def _local_weighted_basis(n: int, row0: int, row1: int) -> NDArray[np.float64]:
    """``Y(l) * solid_angle`` for rows ``row0:row1`` of a face, ``(9, (row1 - row0) n)`` float64.

    ``l = (u, v, 1) / |(u, v, 1)|`` is the texel centre in the face's own frame; the solid angle
    is the exact ``F(u1, v1) - F(u0, v1) - F(u1, v0) + F(u0, v0)``,
    ``F(x, y) = atan2(x y, sqrt(x^2 + y^2 + 1))`` of :mod:`probegrid.core.cubemap` (computed here per
    block so that huge faces need no full-size table).
    """
    edges = np.linspace(-1.0, 1.0, n + 1)
    ue = edges[None, :]
    ve = edges[row0 : row1 + 1, None]

    def corner(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))

    f = corner(ue, ve)  # (rows + 1, n + 1)
    solid = f[1:, 1:] - f[:-1, 1:] - f[1:, :-1] + f[:-1, :-1]
    u = 0.5 * (ue[:, 1:] + ue[:, :-1])
    v = 0.5 * (ve[1:] + ve[:-1])
    local = np.stack(np.broadcast_arrays(u, v, np.ones_like(u * v)), axis=-1)
    return np.ascontiguousarray((sh_basis(local) * solid[..., None]).reshape(-1, NUM_COEFFS).T)


@lru_cache(maxsize=4)
def _cached_local_weighted_basis(n: int) -> NDArray[np.float64]:
    """Read-only ``(9, n^2)`` local weighted basis of a whole face (``n <= 512``)."""
    g = _local_weighted_basis(n, 0, n)
    g.setflags(write=False)
    return g


@lru_cache(maxsize=1)
def _face_transforms() -> NDArray[np.float64]:
    """``M_f`` with ``Y(B_f l) = M_f Y(l)`` for the six faces, ``(6, 9, 9)`` float64, read-only."""
    eye = np.eye(NUM_COEFFS)
    out = np.empty((6, NUM_COEFFS, NUM_COEFFS))
    for f in range(6):
        b = np.stack([cm.FACE_U[f], cm.FACE_V[f], cm.FACE_NORMALS[f]], axis=1)
        # rotate(c, B^T) has coefficients of g(B l) for g = c . Y, i.e. M^T c.
        out[f] = rotate(eye, b.T).T
    out.setflags(write=False)
    return out


def _check_coeffs(coeffs: ArrayLike, name: str = "coeffs") -> NDArray[np.float64]:
    c = np.asarray(coeffs, dtype=np.float64)
    if c.ndim < 1 or c.shape[0] != NUM_COEFFS:
        raise ValueError(f"{name} must have shape (9, ...), got {c.shape}.")
    return c


def _raise_if_nonfinite(result: NDArray[np.float64], what: str) -> None:
    # Y_00 > 0 at every sample, so any nan / inf value or weight makes L_00 nan or inf
    # (inf * 0 is nan too): checking the 9 x C result is as strict as checking the input.
    bad = ~np.isfinite(result[0])
    if np.any(bad):
        chans = np.flatnonzero(bad.reshape(-1)).tolist()
        raise ValueError(
            f"{what} contain nan or inf values (channel(s) {chans}); the SH projection would be "
            "undefined, so clean or clamp the input first."
        )


def project_cube(faces: ArrayLike) -> NDArray[np.float64]:
    """Radiance SH coefficients of a cube map.

    ``L_i = sum_texels L(texel) Y_i(texel centre) solid_angle(texel)`` with exact solid angles;
    float64 products and sums (the float32 texels are widened, not rounded).

    Parameters
    ----------
    faces : (6, n, n, C) or (6, n, n) float
        Radiance texels (face order and orientation of :mod:`probegrid.core.cubemap`).

    Returns
    -------
    (9, C) float64, or (9,) for a 3-D input
        Units: texel units x sr.

    Raises
    ------
    ValueError
        For a wrong shape or nan / inf texels.
    """
    a = np.asarray(faces)
    squeeze = a.ndim == 3
    if squeeze:
        a = a[..., None]
    if a.ndim != 4 or a.shape[0] != 6 or a.shape[1] != a.shape[2] or a.shape[1] < 1:
        raise ValueError(f"faces must have shape (6, n, n, C) or (6, n, n), got {a.shape}.")
    if not np.issubdtype(a.dtype, np.floating) and not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"faces must hold real numbers, got dtype {a.dtype}.")
    n, c = int(a.shape[1]), int(a.shape[3])
    rows = max(1, _BLOCK // n)  # face rows per block: bounded (9, rows n) basis slices
    cached = _cached_local_weighted_basis(n) if n <= _CACHE_MAX_SIZE else None
    transforms = _face_transforms()
    out = np.zeros((NUM_COEFFS, c), dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite input raises just below
        for f in range(6):
            moments = np.zeros((NUM_COEFFS, c), dtype=np.float64)  # G @ faces[f]
            for r0 in range(0, n, rows):
                r1 = min(r0 + rows, n)
                if cached is not None:
                    g = cached[:, r0 * n : r1 * n]
                else:
                    g = _local_weighted_basis(n, r0, r1)
                moments += g @ a[f, r0:r1].reshape(-1, c).astype(np.float64)
            out += transforms[f] @ moments
    _raise_if_nonfinite(out, "faces")
    return out[:, 0] if squeeze else out


def project_samples(
    values: ArrayLike, directions: ArrayLike, weights: ArrayLike
) -> NDArray[np.float64]:
    """Radiance SH coefficients of an arbitrary weighted sample set.

    ``L_i = sum_k values_k Y_i(directions_k) weights_k``. For ``N`` uniform random or
    Fibonacci directions use ``weights = 4 pi / N``; for importance sampling,
    ``1 / (N pdf_k)``.

    Parameters
    ----------
    values : (N, C) or (N,) float
    directions : (N, 3) float
        Normalised here; zero vectors raise.
    weights : (N,) float or scalar
        Solid angle represented by each sample, sr.

    Returns
    -------
    (9, C) or (9,) float64

    Raises
    ------
    ValueError
        For mismatched shapes or nan / inf values.
    """
    v = np.asarray(values, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"directions must have shape (N, 3), got {d.shape}.")
    squeeze = v.ndim == 1
    if squeeze:
        v = v[:, None]
    if v.ndim != 2 or v.shape[0] != d.shape[0]:
        raise ValueError(
            f"values must have shape (N, C) or (N,) with N = {d.shape[0]}, got {np.shape(values)}."
        )
    w = np.asarray(weights, dtype=np.float64)
    if w.shape not in ((), (d.shape[0],)):
        raise ValueError(f"weights must be a scalar or have shape ({d.shape[0]},), got {w.shape}.")
    w = np.broadcast_to(w, (d.shape[0],))
    out = np.zeros((NUM_COEFFS, v.shape[1]), dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite input raises just below
        for s in range(0, d.shape[0], _BLOCK):
            e = s + _BLOCK
            out += (sh_basis(d[s:e]) * w[s:e, None]).T @ v[s:e]
    if d.shape[0]:
        _raise_if_nonfinite(out, "values or weights")
    return out[:, 0] if squeeze else out


# --------------------------------------------------------------------------------------------
# Evaluation and irradiance
# --------------------------------------------------------------------------------------------


def _per_coeff(factors: NDArray[np.float64], c: NDArray[np.float64]) -> NDArray[np.float64]:
    """Broadcast a (9,) factor over a (9, ...) coefficient array."""
    return factors.reshape((NUM_COEFFS,) + (1,) * (c.ndim - 1))


def irradiance_coefficients(L: ArrayLike) -> NDArray[np.float64]:
    """Irradiance coefficients ``A_l L_lm`` of radiance coefficients.

    Parameters
    ----------
    L : (9, ...) float
        Radiance coefficients.

    Returns
    -------
    (9, ...) float64
        Evaluate with :func:`evaluate` to get irradiance ``E(n)`` (radiance x sr).
    """
    c = _check_coeffs(L, "L")
    return c * _per_coeff(A_HAT, c)


def evaluate(coeffs: ArrayLike, directions: ArrayLike) -> NDArray[np.float64]:
    """Evaluate an SH expansion ``f(d) = sum_i coeffs_i Y_i(d)``.

    Parameters
    ----------
    coeffs : (9, ...) float
        E.g. (9, C) for colour, (9,) for one channel.
    directions : (..., 3) float
        Normalised here.

    Returns
    -------
    (*directions.shape[:-1], *coeffs.shape[1:]) float64
    """
    c = _check_coeffs(coeffs)
    y = sh_basis(directions)
    return np.tensordot(y, c, axes=([-1], [0]))


def irradiance(L: ArrayLike, normals: ArrayLike) -> NDArray[np.float64]:
    """Irradiance ``E(n) = sum A_l L_lm Y_lm(n)`` (R&H 2001 eq. 12).

    Parameters
    ----------
    L : (9, ...) float
        Radiance coefficients.
    normals : (..., 3) float
        Surface normals, normalised here.

    Returns
    -------
    (*normals.shape[:-1], *L.shape[1:]) float64
        Irradiance (radiance x sr); a constant environment ``L`` gives ``pi L``.
    """
    return evaluate(irradiance_coefficients(L), normals)


def diffuse_cube(
    L: ArrayLike,
    size: int,
    *,
    window: SHWindow = "none",
    width: float | None = None,
) -> NDArray[np.float32]:
    """Diffuse (irradiance / pi) cube map from radiance coefficients.

    Each texel holds ``E(n) / pi`` at its centre direction ``n`` (the project's diffuse-map
    convention: the outgoing radiance of a white Lambertian surface).

    Parameters
    ----------
    L : (9, C) or (9,) float
        Radiance coefficients.
    size : int
        Face size in texels.
    window : {"none", "hanning", "lanczos", "gauss", "auto"}
        Anti-ringing window applied to ``L`` first (see :func:`window`); ``"auto"`` uses
        :func:`auto_window` with a Hanning window (``width`` must then be None).
    width : float, optional
        Window width, required for "hanning", "lanczos" and "gauss".

    Returns
    -------
    (6, size, size, C) float32 (or (6, size, size, 1) for a (9,) input)
    """
    check_window_option(window)
    c = _check_coeffs(L, "L")
    if c.ndim == 1:
        c = c[:, None]
    if c.ndim != 2:
        raise ValueError(f"L must have shape (9, C) or (9,), got {c.shape}.")
    c = apply_window_option(c, window, width, auto=auto_window, apply=_apply_window)
    dirs = cm.texel_directions(size)
    return (evaluate(irradiance_coefficients(c), dirs) / np.pi).astype(np.float32)


def check_window_option(window: str) -> None:
    """Refuse a ``window`` option that is not one of :data:`probegrid._types.SHWindow`."""
    allowed = choices(SHWindow)
    if window not in allowed:
        raise ValueError(f"window must be one of {allowed}, got {window!r}.")


def apply_window_option(
    c: NDArray[np.float64],
    window: SHWindow,
    width: float | None,
    *,
    auto: Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], Any]],
    apply: Callable[[NDArray[np.float64], str, float], NDArray[np.float64]],
) -> NDArray[np.float64]:
    """Coefficients ``c`` under a diffuse function's ``window`` option: unchanged for "none",
    ``auto(c)``'s for "auto" (no ``width``: it is searched), ``apply(c, window, width)``
    otherwise (a ``width`` needed). ``auto`` and ``apply`` are the band count's own (this
    module's for 3 bands, :mod:`probegrid.core.shbands`' for any)."""
    if window == "auto":
        if width is not None:
            raise ValueError("width must be None with window='auto' (the width is searched).")
        c, _ = auto(c)
    elif window != "none":
        if width is None:
            raise ValueError(f"window={window!r} needs a width.")
        c = apply(c, window, width)
    return c


# --------------------------------------------------------------------------------------------
# Windowing
# --------------------------------------------------------------------------------------------


def window_factors(kind: WindowKind, width: float, *, bands: int = NUM_BANDS
                   ) -> NDArray[np.float64]:
    """Per-band window factors ``(h_0, h_1, h_2)`` (Sloan 2008; formulas in the module docstring).

    Parameters
    ----------
    kind : {"none", "hanning", "lanczos", "gauss"}
    width : float
        Window width ``w > 0`` (``inf`` means no windowing); ignored for "none".
    bands : int
        Bands to give factors for (:mod:`probegrid.core.shbands` asks for any count).

    Returns
    -------
    (bands,) float64, ``h_0 = 1``.
    """
    if kind not in _WINDOW_KINDS:
        raise ValueError(f"window kind must be one of {_WINDOW_KINDS}, got {kind!r}.")
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


def _apply_window(c: NDArray[np.float64], kind: WindowKind, width: float) -> NDArray[np.float64]:
    return c * _per_coeff(window_factors(kind, width)[BAND_OF], c)


def window(L: ArrayLike, *, kind: WindowKind, width: float) -> NDArray[np.float64]:
    """Scale each band of SH coefficients by a window to reduce ringing (Sloan 2008).

    Parameters
    ----------
    L : (9, ...) float
        Coefficients of any function (radiance or irradiance: windowing commutes with ``A_l``).
    kind : {"none", "hanning", "lanczos", "gauss"}
    width : float
        Window width ``w > 0``; larger is gentler, ``inf`` is no windowing. Check the result
        (e.g. with :func:`min_over_sphere`) or use :func:`auto_window`: some hanning / lanczos
        widths deepen the negative lobe instead (module docstring).

    Returns
    -------
    (9, ...) float64
    """
    return _apply_window(_check_coeffs(L, "L"), kind, width)


def _quadratic_form(
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
    Moré & Sorensen 1983; :mod:`probegrid.core.dering`). ``(K,)``."""
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


def _dual_direction(b: NDArray[np.float64], s: NDArray[np.float64]) -> NDArray[np.float64]:
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


def _band2_from_matrix(s: NDArray[np.float64]) -> NDArray[np.float64]:
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


@lru_cache(maxsize=4)
def _fibonacci_directions(n: int) -> NDArray[np.float64]:
    """``n`` near-uniform unit directions on a Fibonacci spiral, (n, 3) float64, read-only."""
    k = np.arange(n, dtype=np.float64) + 0.5
    y = 1.0 - 2.0 * k / n
    r = np.sqrt(np.maximum(0.0, 1.0 - y * y))
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    d = np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=-1)
    d.setflags(write=False)
    return d


def _refine_minimum(
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
    for _ in range(_NEWTON_STEPS):
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


def min_over_sphere(coeffs: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Minimum over all directions of a band-0-2 SH function, per channel.

    The function is sampled at 4096 Fibonacci directions; the 32 lowest samples of each channel,
    and the direction the Lagrangian dual points to (:func:`dual_maximiser`), are refined by
    damped Riemannian Newton steps on the quadratic form the function is on the unit sphere
    (converging quadratically), and the best result is kept. (Without the dual's start the
    search missed the global minimum of 9 in 36 000 ringing probes, by up to 1e-4 of their
    scale: ``tests/test_sh.py``.) Pass
    :func:`irradiance_coefficients` of ``L`` for the minimum irradiance.

    Parameters
    ----------
    coeffs : (9, ...) float
        Coefficients of the function (any trailing channel shape).

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
    a = _check_coeffs(coeffs)
    if not np.all(np.isfinite(a)):
        raise ValueError("coeffs contain nan or inf; the minimum over the sphere is undefined.")
    rest = a.shape[1:]
    flat = a.reshape(NUM_COEFFS, -1)
    dirs = _fibonacci_directions(_MIN_SAMPLES)
    basis = sh_basis(dirs)  # (N, 9)
    m = _MIN_REFINE
    vmin = np.empty(flat.shape[1])
    dmin = np.empty((flat.shape[1], 3))
    for j in range(0, flat.shape[1], _MIN_CHANNEL_BLOCK):  # bounded memory for many channels
        blk = flat[:, j : j + _MIN_CHANNEL_BLOCK]
        k = blk.shape[1]
        # the samples' values summed coefficient by coefficient (not a BLAS product, whose
        # rounding may depend on how many channels share it): each channel's minimum is
        # the same bits whatever channels it is computed with
        vals = basis[:, :1] * blk[0]
        for i in range(1, NUM_COEFFS):
            vals += basis[:, i:i + 1] * blk[i]
        best = np.argpartition(vals, m - 1, axis=0)[:m]  # (m, k) sample indices
        c, b, s = _quadratic_form(blk)
        # One refinement per (channel, candidate), laid out channel-major as (k * (m + 1)):
        # the m lowest samples and the dual's direction (a narrow global minimum can lie
        # between the samples, all of the lowest of them in another basin)
        start = np.concatenate([dirs[best.T], _dual_direction(b, s)[:, None]], axis=1)
        val, d = _refine_minimum(
            np.repeat(c, m + 1), np.repeat(b, m + 1, axis=0), np.repeat(s, m + 1, axis=0),
            start.reshape(-1, 3)
        )
        val, d = val.reshape(k, m + 1), d.reshape(k, m + 1, 3)
        pick = np.argmin(val, axis=1)
        vmin[j : j + k] = val[np.arange(k), pick]
        dmin[j : j + k] = d[np.arange(k), pick]
    return vmin.reshape(rest), dmin.reshape(rest + (3,))


def _windowed_minima(
    f: NDArray[np.float64], kind: WindowKind, widths: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Minimum over the sphere and over channels of ``f`` windowed at each width, (G,)."""
    flat = f.reshape(NUM_COEFFS, -1)
    h = np.stack([window_factors(kind, w)[BAND_OF] for w in widths], axis=1)  # (9, G)
    vals, _ = min_over_sphere(flat[:, None, :] * h[:, :, None])  # one vectorised call, (G, K)
    return vals.min(axis=1)


def auto_window(
    L: ArrayLike,
    *,
    kind: Literal["hanning", "lanczos", "gauss"] = "hanning",
    quantity: Literal["irradiance", "radiance"] = "irradiance",
    rtol: float = 1e-4,
) -> tuple[NDArray[np.float64], float]:
    """The gentlest window of a kind that makes an SH function non-negative everywhere.

    Useful for bright suns: band-2 truncation of a near-delta light gives negative irradiance on
    the far side. One width serves all channels (so the colour of the result is consistent).
    Every ``h_l`` grows with the width ``w``, so the gentlest window is the *largest* feasible
    ``w``. The minimum is **not** monotone in ``w`` for hanning and lanczos (for one directional
    light, hanning at ``w = 2.5`` dips to -4.7 % of the peak, deeper than the unwindowed -4.0 %;
    lanczos at ``w = 2`` to -6.8 %), so the feasible widths need not form an interval and a plain
    bisection could stop at the wrong end. Hence: the windowed minimum (by
    :func:`min_over_sphere`, all candidate widths in one vectorised call) is scanned on 48
    log-spaced widths from the band-0-only width (``w = 1`` for hanning / lanczos, ``0.01`` for
    gauss) to ``1e3``, plus ``1e6``; the bracket after the largest feasible grid width is then
    narrowed 17-fold per round to ``rtol``. The returned width is always feasible (minimum
    ``>= 0``); a feasible island narrower than the grid step (a factor 1.15) could be missed.

    Parameters
    ----------
    L : (9, ...) float
        Radiance coefficients.
    kind : {"hanning", "lanczos", "gauss"}
    quantity : {"irradiance", "radiance"}
        Which function must be non-negative: the irradiance ``A_l L_lm`` (default, what a
        diffuse map shows) or the radiance expansion itself.
    rtol : float
        Relative precision of the width.

    Returns
    -------
    windowed : (9, ...) float64
        ``window(L, kind=kind, width=width)``.
    width : float
        The width used; ``inf`` if ``L`` needed no windowing.

    Raises
    ------
    ValueError
        For nan / inf coefficients, or if a channel has ``L_00 < 0`` (no window can help).
    """
    check_auto_window_options(kind, quantity, rtol)
    c = _check_coeffs(L, "L")
    check_auto_window_coeffs(c)
    f = irradiance_coefficients(c) if quantity == "irradiance" else c
    return gentlest_window(c, f, kind, rtol, minima=_windowed_minima, apply=_apply_window)


def check_auto_window_options(kind: str, quantity: str, rtol: float) -> None:
    """Refuse :func:`auto_window`'s options when they are not a window kind, a quantity and a
    relative precision in (0, 1) (one-line ``ValueError``)."""
    kinds = ("hanning", "lanczos", "gauss")
    if kind not in kinds:
        raise ValueError(f"kind must be one of {kinds}, got {kind!r}.")
    if quantity not in ("irradiance", "radiance"):
        raise ValueError(f"quantity must be one of ('irradiance', 'radiance'), got {quantity!r}.")
    if not 0 < rtol < 1:
        raise ValueError(f"rtol must be in (0, 1), got {rtol!r}.")


def check_auto_window_coeffs(c: NDArray[np.float64]) -> None:
    """Refuse coefficients no window search can serve: non-finite, or ``L_00 < 0``."""
    if not np.all(np.isfinite(c)):
        raise ValueError("L contains nan or inf; cannot choose a window.")
    if np.any(c[0] < 0):
        raise ValueError("L_00 is negative in some channel; no window can make it non-negative.")


def gentlest_window(
    c: NDArray[np.float64],
    f: NDArray[np.float64],
    kind: WindowKind,
    rtol: float,
    *,
    minima: Callable[[NDArray[np.float64], WindowKind, NDArray[np.float64]], NDArray[np.float64]],
    apply: Callable[[NDArray[np.float64], str, float], NDArray[np.float64]],
) -> tuple[NDArray[np.float64], float]:
    """:func:`auto_window`'s search (its docstring): ``c`` windowed at the largest width whose
    window makes ``f`` non-negative, and that width (``inf`` when none is needed). ``minima``
    and ``apply`` are the band count's own (this module's for 3 bands,
    :mod:`probegrid.core.shbands`' for any)."""
    if minima(f, kind, np.array([np.inf]))[0] >= 0.0:
        return c.copy(), float("inf")
    band0_only = 0.01 if kind == "gauss" else 1.0  # feasible: the constant pi L_00 K0 >= 0
    grid = np.append(np.geomspace(band0_only, 1e3, 48), 1e6)
    feasible = minima(f, kind, grid) >= 0.0
    feasible[0] = True
    k = int(np.flatnonzero(feasible).max())
    if k == grid.size - 1:
        return apply(c, kind, grid[k]), float(grid[k])
    lo, hi = grid[k], grid[k + 1]  # lo feasible, hi not
    while hi / lo > 1.0 + rtol:
        ws = np.geomspace(lo, hi, 18)[1:-1]
        ok = np.flatnonzero(minima(f, kind, ws) >= 0.0)
        j = int(ok.max()) if ok.size else -1
        lo = ws[j] if j >= 0 else lo
        hi = ws[j + 1] if j + 1 < ws.size else hi
    return apply(c, kind, lo), float(lo)


# --------------------------------------------------------------------------------------------
# Rotation
# --------------------------------------------------------------------------------------------


def rotate(L: ArrayLike, rotation: ArrayLike) -> NDArray[np.float64]:
    """Coefficients of the rotated function ``L'(d) = L(R^T d)``.

    Exact for bands 0-2: band 1 rotates as the vector ``(x, y, z)``, band 2 as the traceless
    symmetric matrix of its quadratic form (``S -> R S R^T``).

    Parameters
    ----------
    L : (9, ...) float
        Coefficients of any band-0-2 function.
    rotation : (3, 3) float
        Orthogonal matrix ``R`` (world frame) taking a direction of the original environment to
        where it appears after rotation.

    Returns
    -------
    (9, ...) float64
    """
    c = _check_coeffs(L, "L")
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-9):
        raise ValueError("rotation must be an orthogonal (3, 3) matrix.")
    rest = c.shape[1:]
    flat = c.reshape(NUM_COEFFS, -1)
    _, b, s = _quadratic_form(flat)
    b_rot = b @ r.T  # b' = R b, since b . (R^T d) = (R b) . d
    s_rot = np.einsum("ij,kjl,ml->kim", r, s, r)  # S' = R S R^T
    out = np.empty_like(flat)
    out[0] = flat[0]
    out[1], out[2], out[3] = b_rot[:, 1] / K1, b_rot[:, 2] / K1, b_rot[:, 0] / K1
    out[4:] = _band2_from_matrix(s_rot)
    return out.reshape((NUM_COEFFS,) + rest)


def rotation_y(angle: float) -> NDArray[np.float64]:
    """Right-handed rotation matrix about world +Y by ``angle`` radians (+Z -> +X at pi/2)."""
    ca, sa = np.cos(angle), np.sin(angle)
    return np.array([[ca, 0.0, sa], [0.0, 1.0, 0.0], [-sa, 0.0, ca]])


def rotate_y(L: ArrayLike, angle: float) -> NDArray[np.float64]:
    """Rotate an environment's coefficients about world +Y by ``angle`` radians.

    ``rotate(L, rotation_y(angle))``: what was seen toward +Z is seen toward +X after a positive
    quarter turn.

    Parameters
    ----------
    L : (9, ...) float
    angle : float
        Radians, right-hand rule about +Y.

    Returns
    -------
    (9, ...) float64
    """
    return rotate(L, rotation_y(float(angle)))
