"""Rotation of spherical-harmonic coefficients, exact at any band count.

:func:`rotate` returns the coefficients of the rotated environment ``L'(d) = L(R^T d)`` (what
was seen in direction ``d`` is seen in direction ``R d``). Each band rotates within itself (band
spaces are rotation invariant):

* 3 bands (the fast path): band 1 rotates as the vector ``(x, y, z)``; band 2 as the traceless
  symmetric matrix ``S`` of its quadratic form (``S -> R S R^T``,
  :mod:`probegrid.core.sh.quadratic`), so rotation is exact in closed form.
* Any other band count: the transform ``M_l`` of each band is found by solving
  ``Y_l(B d) = M_l Y_l(d)`` on ``4 (2 l + 1)`` directions by least squares; the spaces being
  invariant, the fit has zero residual and the solution is exact to rounding
  (:func:`rotation_matrix`).

:func:`rotate_y` rotates about world +Y by the right-hand rule (a positive quarter turn takes +Z
to +X). Non-finite coefficients propagate.

References
----------
* P.-P. Sloan, "Stupid Spherical Harmonics (SH) Tricks", GDC 2008 (rotation).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core.sh.basis import (
    K1,
    NUM_BANDS,
    NUM_COEFFS,
    basis_unit,
    check_bands,
    check_coeffs,
    fibonacci_directions,
)
from probegrid.core.sh.quadratic import band2_from_matrix, quadratic_form

__all__ = ["rotate", "rotate_y", "rotation_matrix", "rotation_y"]


def _check_rotation(rotation: ArrayLike) -> NDArray[np.float64]:
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-9):
        raise ValueError("rotation must be an orthogonal (3, 3) matrix.")
    return r


@lru_cache(maxsize=4)
def _fit_directions(count: int) -> NDArray[np.float64]:
    d = fibonacci_directions(count)
    # a generic rotation, so that no fitting direction lies on a symmetry axis of the cube
    r = np.linalg.qr(np.array([[0.3, -0.8, 0.5], [0.9, 0.2, -0.4], [0.1, 0.6, 0.7]]))[0]
    return d @ r.T


def basis_transform(matrix: NDArray[np.float64], bands: int) -> NDArray[np.float64]:
    """``M`` with ``Y(B d) = M Y(d)`` for an orthogonal ``B`` (general basis, any band count):
    block diagonal, one exact least-squares solve per band (band spaces are invariant, so the
    fit has zero residual)."""
    k = bands * bands
    d = _fit_directions(4 * (2 * bands - 1))
    y = basis_unit(d, bands)
    yb = basis_unit(d @ matrix.T, bands)
    out = np.zeros((k, k))
    for l in range(bands):
        sl = slice(l * l, (l + 1) ** 2)
        mt, *_ = np.linalg.lstsq(y[:, sl], yb[:, sl], rcond=None)
        out[sl, sl] = mt.T
    return out


def rotation_matrix(rotation: ArrayLike, *, bands: int = NUM_BANDS) -> NDArray[np.float64]:
    """``(bands^2, bands^2)`` matrix ``Q`` with ``rotate(L, R) = Q @ L`` (to rounding).

    The coefficients of ``L'(d) = L(R^T d)`` (what was seen toward ``d`` is seen toward
    ``R d``), block diagonal by band; for 3 bands the closed form of :func:`rotate` applied to
    the identity.
    """
    b = check_bands(bands)
    r = _check_rotation(rotation)
    if b == NUM_BANDS:
        return rotate(np.eye(NUM_COEFFS), r)
    # L'(d) = c . Y(R^T d) = c . M Y(d) with M the transform of R^T: c' = M^T c.
    return basis_transform(r.T, b).T


def rotate(L: ArrayLike, rotation: ArrayLike, *, bands: int = NUM_BANDS) -> NDArray[np.float64]:
    """Coefficients of the rotated function ``L'(d) = L(R^T d)``.

    Exact (module docstring): for bands 0-2 band 1 rotates as the vector ``(x, y, z)``, band 2
    as the traceless symmetric matrix of its quadratic form (``S -> R S R^T``).

    Parameters
    ----------
    L : (bands^2, ...) float
        Coefficients of any function.
    rotation : (3, 3) float
        Orthogonal matrix ``R`` (world frame) taking a direction of the original environment to
        where it appears after rotation.
    bands : int

    Returns
    -------
    (bands^2, ...) float64
    """
    c = check_coeffs(L, bands, "L")
    if bands != NUM_BANDS:
        return np.tensordot(rotation_matrix(rotation, bands=bands), c, axes=([1], [0]))
    r = _check_rotation(rotation)
    rest = c.shape[1:]
    flat = c.reshape(NUM_COEFFS, -1)
    _, b, s = quadratic_form(flat)
    b_rot = b @ r.T  # b' = R b, since b . (R^T d) = (R b) . d
    s_rot = np.einsum("ij,kjl,ml->kim", r, s, r)  # S' = R S R^T
    out = np.empty_like(flat)
    out[0] = flat[0]
    out[1], out[2], out[3] = b_rot[:, 1] / K1, b_rot[:, 2] / K1, b_rot[:, 0] / K1
    out[4:] = band2_from_matrix(s_rot)
    return out.reshape((NUM_COEFFS,) + rest)


def rotation_y(angle: float) -> NDArray[np.float64]:
    """Right-handed rotation matrix about world +Y by ``angle`` radians (+Z -> +X at pi/2)."""
    ca, sa = np.cos(angle), np.sin(angle)
    return np.array([[ca, 0.0, sa], [0.0, 1.0, 0.0], [-sa, 0.0, ca]])


def rotate_y(L: ArrayLike, angle: float, *, bands: int = NUM_BANDS) -> NDArray[np.float64]:
    """Rotate an environment's coefficients about world +Y by ``angle`` radians.

    ``rotate(L, rotation_y(angle))``: what was seen toward +Z is seen toward +X after a positive
    quarter turn.

    Parameters
    ----------
    L : (bands^2, ...) float
    angle : float
        Radians, right-hand rule about +Y.
    bands : int

    Returns
    -------
    (bands^2, ...) float64
    """
    return rotate(L, rotation_y(float(angle)), bands=bands)
