"""Projection onto spherical harmonics: cube maps, lat-long images and weighted sample sets.

:func:`project_cube` computes ``L_i = sum_texels L(texel) Y_i(texel centre) solid_angle`` with
the exact texel solid angles of :mod:`probegrid.core.cubemap`, in float64 throughout (float32
texels are widened, not rounded; measured error vs an extended-precision sum ~2e-16 of
``L_00``). It uses the cube's symmetry: face ``f`` maps its local direction
``l = (u, v, 1) / |(u, v, 1)|`` to the world direction ``d = B_f l`` with the orthogonal
``B_f = [FACE_U | FACE_V | FACE_NORMAL]``, so ``Y(d) = M_f Y(l)`` with ``M_f`` the exact SH
transform of ``B_f`` (:mod:`probegrid.core.sh.rotation`: the closed form for 3 bands, the exact
per-band fit otherwise). Hence one *shared* ``(bands^2, n^2)`` weighted local basis
``G = Y(l) solid_angle`` serves all six faces::

    L = sum_f M_f (G @ faces[f])

``G`` is cached read-only per face size while it is small (3 bands: ``n <= 512``, 19 MB at 512,
1.2 MB at 128; other counts: up to 8 M values, 64 MB) and computed block by block for larger
faces, so memory stays bounded. The 3-band path (the stored coefficients) evaluates the explicit
band-0-2 formulas in blocks of 8192 texels: its sums' order, hence its last bits, are those of
every stored probe and filtered environment.

:func:`project_samples` does the plain weighted sum for any sample set. :func:`project_equirect`
projects a latitude-longitude image pixel by pixel with its exact solid angles
``(2 pi / W)(sin theta_top - sin theta_bottom)`` (the general basis at every band count): the
best projection of a lat-long input (the benchmark's "best this band count allows" reference).

Non-finite input raises ``ValueError`` (a single bad texel would otherwise poison all
coefficients silently).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core import cubemap as cm
from probegrid.core.sh.basis import (
    MAX_BANDS,
    NUM_BANDS,
    NUM_COEFFS,
    basis_unit,
    check_bands,
    sh_basis,
)
from probegrid.core.sh.rotation import basis_transform, rotate

__all__ = ["project_cube", "project_equirect", "project_samples"]

#: Values (coefficients x texels or samples) per block of a projection: bounded
#: ``(bands^2, block)`` float64 basis slices. The 3-band path's blocks are 8192 texels.
_BLOCK_VALUES: Final = 1 << 20
_BLOCK_VALUES_3: Final = NUM_COEFFS * 8192
#: Largest local weighted basis cached, in values (3 bands: faces up to 512^2, 19 MB; other
#: counts: 8 M values, 64 MB).
_CACHE_VALUES: Final = 1 << 23
_CACHE_VALUES_3: Final = NUM_COEFFS * 512 * 512


def _block_values(bands: int) -> int:
    return _BLOCK_VALUES_3 if bands == NUM_BANDS else _BLOCK_VALUES


def _cache_values(bands: int) -> int:
    return _CACHE_VALUES_3 if bands == NUM_BANDS else _CACHE_VALUES


def _raise_if_nonfinite(result: NDArray[np.float64], what: str) -> None:
    # Y_00 > 0 at every sample, so any nan / inf value or weight makes L_00 nan or inf
    # (inf * 0 is nan too): checking the bands^2 x C result is as strict as checking the input.
    bad = ~np.isfinite(result[0])
    if np.any(bad):
        chans = np.flatnonzero(bad.reshape(-1)).tolist()
        raise ValueError(
            f"{what} contain nan or inf values (channel(s) {chans}); the SH projection would be "
            "undefined, so clean or clamp the input first."
        )


def _local_weighted_basis(n: int, row0: int, row1: int, bands: int = NUM_BANDS
                          ) -> NDArray[np.float64]:
    """``Y(l) * solid_angle`` for rows ``row0:row1`` of a face, ``(bands^2, (row1 - row0) n)``.

    ``l = (u, v, 1) / |(u, v, 1)|`` is the texel centre in the face's own frame; the solid angle
    is the exact ``F(u1, v1) - F(u0, v1) - F(u1, v0) + F(u0, v0)`` with ``F`` of
    :func:`probegrid.core.cubemap.solid_angle_corner` (computed here per block so that huge faces
    need no full-size table).
    """
    edges = np.linspace(-1.0, 1.0, n + 1)
    ue = edges[None, :]
    ve = edges[row0 : row1 + 1, None]
    f = cm.solid_angle_corner(ue, ve)  # (rows + 1, n + 1)
    solid = f[1:, 1:] - f[:-1, 1:] - f[1:, :-1] + f[:-1, :-1]
    u = 0.5 * (ue[:, 1:] + ue[:, :-1])
    v = 0.5 * (ve[1:] + ve[:-1])
    local = np.stack(np.broadcast_arrays(u, v, np.ones_like(u * v)), axis=-1)
    if bands == NUM_BANDS:
        y = sh_basis(local)
    else:
        local /= np.linalg.norm(local, axis=-1, keepdims=True)
        y = basis_unit(local, bands)
    return np.ascontiguousarray((y * solid[..., None]).reshape(-1, bands * bands).T)


@lru_cache(maxsize=4)
def _cached_local_weighted_basis(n: int, bands: int = NUM_BANDS) -> NDArray[np.float64]:
    """Read-only ``(bands^2, n^2)`` local weighted basis of a whole face."""
    g = _local_weighted_basis(n, 0, n, bands)
    g.setflags(write=False)
    return g


@lru_cache(maxsize=MAX_BANDS)
def _face_transforms(bands: int) -> NDArray[np.float64]:
    """``M_f`` with ``Y(B_f l) = M_f Y(l)`` for the six faces, ``(6, bands^2, bands^2)``
    float64, read-only."""
    k = bands * bands
    out = np.empty((6, k, k))
    for f in range(6):
        b = np.stack([cm.FACE_U[f], cm.FACE_V[f], cm.FACE_NORMALS[f]], axis=1)
        if bands == NUM_BANDS:
            # rotate(c, B^T) has coefficients of g(B l) for g = c . Y, i.e. M^T c.
            out[f] = rotate(np.eye(k), b.T).T
        else:
            out[f] = basis_transform(b, bands)
    out.setflags(write=False)
    return out


def project_cube(faces: ArrayLike, *, bands: int = NUM_BANDS) -> NDArray[np.float64]:
    """Radiance SH coefficients of a cube map.

    ``L_i = sum_texels L(texel) Y_i(texel centre) solid_angle(texel)`` with exact solid angles;
    float64 products and sums (the float32 texels are widened, not rounded).

    Parameters
    ----------
    faces : (6, n, n, C) or (6, n, n) float
        Radiance texels (face order and orientation of :mod:`probegrid.core.cubemap`).
    bands : int

    Returns
    -------
    (bands^2, C) float64, or (bands^2,) for a 3-D input
        Units: texel units x sr.

    Raises
    ------
    ValueError
        For a wrong shape or nan / inf texels.
    """
    b = check_bands(bands)
    a = np.asarray(faces)
    squeeze = a.ndim == 3
    if squeeze:
        a = a[..., None]
    if a.ndim != 4 or a.shape[0] != 6 or a.shape[1] != a.shape[2] or a.shape[1] < 1:
        raise ValueError(f"faces must have shape (6, n, n, C) or (6, n, n), got {a.shape}.")
    if not np.issubdtype(a.dtype, np.floating) and not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"faces must hold real numbers, got dtype {a.dtype}.")
    n, c, k = int(a.shape[1]), int(a.shape[3]), b * b
    rows = max(1, _block_values(b) // (k * n))  # face rows per block
    cached = _cached_local_weighted_basis(n, b) if k * n * n <= _cache_values(b) else None
    transforms = _face_transforms(b)
    out = np.zeros((k, c), dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite input raises just below
        for f in range(6):
            moments = np.zeros((k, c), dtype=np.float64)  # G @ faces[f]
            for r0 in range(0, n, rows):
                r1 = min(r0 + rows, n)
                if cached is not None:
                    g = cached[:, r0 * n : r1 * n]
                else:
                    g = _local_weighted_basis(n, r0, r1, b)
                moments += g @ a[f, r0:r1].reshape(-1, c).astype(np.float64)
            out += transforms[f] @ moments
    _raise_if_nonfinite(out, "faces")
    return out[:, 0] if squeeze else out


def project_samples(
    values: ArrayLike, directions: ArrayLike, weights: ArrayLike, *, bands: int = NUM_BANDS
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
    bands : int

    Returns
    -------
    (bands^2, C) or (bands^2,) float64

    Raises
    ------
    ValueError
        For mismatched shapes or nan / inf values.
    """
    b = check_bands(bands)
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
    out = np.zeros((b * b, v.shape[1]), dtype=np.float64)
    step = max(1, _block_values(b) // (b * b))
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite input raises just below
        for s in range(0, d.shape[0], step):
            e = s + step
            out += (sh_basis(d[s:e], bands=b) * w[s:e, None]).T @ v[s:e]
    if d.shape[0]:
        _raise_if_nonfinite(out, "values or weights")
    return out[:, 0] if squeeze else out


def project_equirect(image: ArrayLike, *, bands: int = NUM_BANDS) -> NDArray[np.float64]:
    """Radiance SH coefficients of a latitude-longitude image, pixel by pixel.

    Each pixel contributes ``L Y(centre) dOmega`` with its exact solid angle
    ``(2 pi / W)(sin theta_top - sin theta_bottom)`` (the layout of
    :mod:`probegrid.core.layouts`: centre column +X, a quarter to the right +Z, top row +Y).

    Parameters
    ----------
    image : (H, W, C) float, ``W = 2 H``
    bands : int

    Returns
    -------
    (bands^2, C) float64
    """
    from probegrid.core.layouts import equirect_directions

    b = check_bands(bands)
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
        y = basis_unit(dirs[r0:r1].reshape(-1, 3), b)
        wts = np.repeat(row_sa[r0:r1], w)
        with np.errstate(invalid="ignore", over="ignore"):
            out += (y * wts[:, None]).T @ img[r0:r1].reshape(-1, c).astype(np.float64)
    _raise_if_nonfinite(out, "image pixels")
    return out
