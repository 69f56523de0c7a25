"""Irradiance in spherical harmonics: the clamped cosine's band factors ``A_l`` (Funk-Hecke).

The irradiance of a surface with normal ``n`` lit by radiance ``L = sum L_lm Y_lm`` is the
convolution of ``L`` with the clamped cosine ``max(0, cos theta)``; by the Funk-Hecke theorem it
scales each band (R&H 2001, eq. 7-8 and 12)::

    E(n) = sum_lm A_l L_lm Y_lm(n)

    A_0 = pi,  A_1 = 2 pi / 3,  A_l = 0 for odd l > 1,
    A_l = 2 pi (-1)^(l/2 - 1) / ((l + 2)(l - 1)) * l! / (2^l ((l/2)!)^2)   for even l >= 2

(``A_2 = pi/4, A_4 = -pi/24, A_6 = pi/64, A_8 = -pi/128``; :func:`clamped_cosine_factors`,
computed with exact integer binomials; :data:`A_HAT` per coefficient of the stored 3 bands). Odd
bands above 1 carry no irradiance, so a ``2k + 1``-band and a ``2k + 2``-band irradiance are the
same function. Dropping bands ``l > 2`` costs at most about 9 % of the peak irradiance (R&H
section 2); for one directional light the error is exactly ``3/32 = 9.4 %`` of the peak, at the
terminator (tested).

References
----------
* R. Ramamoorthi, P. Hanrahan, "An Efficient Representation for Irradiance Environment Maps",
  SIGGRAPH 2001 (``A_l``).
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core.sh.basis import (
    BAND_OF,
    MAX_BANDS,
    NUM_BANDS,
    band_of,
    check_bands,
    check_coeffs,
    evaluate,
)

__all__ = ["A_HAT", "clamped_cosine_factors", "irradiance", "irradiance_coefficients"]


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
    return _factors(check_bands(bands))


#: Clamped-cosine band factors ``A_l`` per coefficient of the stored basis (R&H 2001 eq. 8):
#: ``(pi, 2pi/3, 2pi/3, 2pi/3, pi/4, pi/4, pi/4, pi/4, pi/4)``, (9,) float64.
A_HAT: Final[NDArray[np.float64]] = clamped_cosine_factors(NUM_BANDS)[BAND_OF]
A_HAT.setflags(write=False)


def per_coeff(per_band: NDArray[np.float64], c: NDArray[np.float64]) -> NDArray[np.float64]:
    """Broadcast per-band factors ``(bands,)`` over a ``(bands^2, ...)`` coefficient array."""
    b = len(per_band)
    return per_band[band_of(b)].reshape((b * b,) + (1,) * (c.ndim - 1))


def irradiance_coefficients(L: ArrayLike, *, bands: int = NUM_BANDS) -> NDArray[np.float64]:
    """Irradiance coefficients ``A_l L_lm`` of radiance coefficients.

    Parameters
    ----------
    L : (bands^2, ...) float
        Radiance coefficients.
    bands : int

    Returns
    -------
    (bands^2, ...) float64
        Evaluate with :func:`probegrid.core.sh.evaluate` to get irradiance ``E(n)``
        (radiance x sr).
    """
    c = check_coeffs(L, bands, "L")
    return c * per_coeff(clamped_cosine_factors(bands), c)


def irradiance(L: ArrayLike, normals: ArrayLike, *, bands: int = NUM_BANDS
               ) -> NDArray[np.float64]:
    """Irradiance ``E(n) = sum A_l L_lm Y_lm(n)`` (R&H 2001 eq. 12).

    Parameters
    ----------
    L : (bands^2, ...) float
        Radiance coefficients.
    normals : (..., 3) float
        Surface normals, normalised here.
    bands : int

    Returns
    -------
    (*normals.shape[:-1], *L.shape[1:]) float64
        Irradiance (radiance x sr); a constant environment ``L`` gives ``pi L``.
    """
    return evaluate(irradiance_coefficients(L, bands=bands), normals, bands=bands)
