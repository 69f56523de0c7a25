"""Colour: luminance, sRGB encoding and decoding, tone mapping, exposure.

Values are linear scene-referred Rec.709 RGB (the library's colour space); the sRGB functions are
the IEC 61966-2-1 EOTF and its inverse. Two tone mappers turn radiance into display sRGB bytes:

* :func:`tonemap_preview`: scale by ``2**exposure``, Narkowicz's ACES filmic fit per channel,
  sRGB encoding (a fixed curve: everything above about 7 times the key turns white).
* :func:`tonemap_adaptive`, what PNG previews use (:data:`PREVIEW_TONE_MAPPING` says it in
  words): the exposure from the image's own log-average luminance (Reinhard's key 0.18), then
  Reinhard's extended operator on each pixel's largest channel with the white point chosen so
  that the image's own :data:`PREVIEW_WHITE_QUANTILE` quantile maps just below white, the
  pixel's RGB scaled by the same factor (hue and saturation kept: no per-channel fringes), so
  at most about 0.5 % of the pixels reach white whatever the dynamic range.

References: IEC 61966-2-1:1999 (sRGB); K. Narkowicz, "ACES Filmic Tone Mapping Curve", 2016;
E. Reinhard et al., "Photographic Tone Reproduction for Digital Images", SIGGRAPH 2002 (key,
log-average luminance, the extended operator ``L (1 + L / L_white^2) / (1 + L)``).
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Rec.709 / sRGB luminance weights.
_LUMA: Final[NDArray[np.float64]] = np.array([0.2126, 0.7152, 0.0722])
_KEY: Final[float] = 0.18

__all__ = ["PREVIEW_TONE_MAPPING", "PREVIEW_WHITE_QUANTILE", "aces_filmic", "auto_exposure",
           "linear_to_srgb", "luminance", "srgb_to_linear", "tonemap_adaptive",
           "tonemap_preview"]

#: Quantile of a preview's largest channels (after exposure) that maps just below white.
PREVIEW_WHITE_QUANTILE: Final[float] = 0.995
#: What that quantile maps to: 0.995 is sRGB byte 254, so only brighter pixels reach 255.
_BELOW_WHITE: Final[float] = 0.995
#: Most range above the key an 8-bit preview holds (the quantile, in units of the exposed
#: radiance): Reinhard's shoulder maps anything beyond ``t / (1 - t)`` above ``t``.
_MOST_RANGE: Final[float] = 0.9 * _BELOW_WHITE / (1.0 - _BELOW_WHITE)

#: How PNG previews are made (:func:`tonemap_adaptive`), for manifests.
PREVIEW_TONE_MAPPING: Final[str] = (
    "exposure from the image's own log-average luminance (key 0.18, Reinhard 2002), then "
    "Reinhard's extended operator m (1 + m / W^2) / (1 + m) on each pixel's largest channel m, "
    f"white point W such that the image's {PREVIEW_WHITE_QUANTILE:g} quantile of m maps to "
    f"{_BELOW_WHITE:g} (sRGB 254; the exposure lowered when that quantile is above "
    f"{_MOST_RANGE:.4g}), RGB scaled by the same factor (hue kept), sRGB-encoded 8-bit; NaN and "
    "negative values black")


def luminance(rgb: ArrayLike) -> NDArray[np.float64]:
    """Rec.709 luminance ``(...)`` of linear RGB ``(..., 3)`` (float64)."""
    return np.asarray(rgb, dtype=np.float64) @ _LUMA


def srgb_to_linear(encoded: ArrayLike) -> NDArray[np.float32]:
    """The sRGB EOTF (IEC 61966-2-1): encoded ``[0, 1]`` values to linear, float32."""
    v = np.asarray(encoded, dtype=np.float64)
    lin = np.where(v <= 0.04045, v / 12.92, ((np.maximum(v, 0.04045) + 0.055) / 1.055) ** 2.4)
    return lin.astype(np.float32)


def linear_to_srgb(linear: ArrayLike) -> NDArray[np.float32]:
    """The inverse sRGB EOTF: linear values clipped to ``[0, 1]`` (NaN -> 0), encoded, float32."""
    x = np.clip(np.nan_to_num(np.asarray(linear, dtype=np.float64), nan=0.0), 0.0, 1.0)
    enc = np.asarray(12.92 * x)  # (an array for a 0-d input too)
    above = x > 0.0031308  # (the power only where it is used: it is most of the cost)
    enc[above] = 1.055 * x[above] ** (1 / 2.4) - 0.055
    return enc.astype(np.float32)


def aces_filmic(x: NDArray[np.float64]) -> NDArray[np.float64]:
    # Narkowicz 2015 fit of the ACES RRT + ODT, input in scene-linear (mid grey 0.18 -> 0.27).
    return np.clip((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)


def auto_exposure(rgb: NDArray[np.float64], weights: NDArray[np.float64] | None) -> float:
    """Stops that bring the (weighted) log-average luminance of finite pixels to 0.18."""
    lum = rgb @ _LUMA
    ok = np.isfinite(lum)
    if weights is None:
        weights = np.ones_like(lum)
    wts = np.where(ok, weights, 0.0)
    if wts.sum() <= 0:
        return 0.0
    logavg = np.exp((wts * np.log(1e-4 + np.maximum(np.where(ok, lum, 0.0), 0.0))).sum()
                    / wts.sum())
    return float(np.log2(_KEY / logavg))


def tonemap_adaptive(image: ArrayLike, *, exposure: float | None = None,
                     weights: ArrayLike | None = None) -> NDArray[np.uint8]:
    """Tone-map linear radiance ``(..., 3)`` to 8-bit display sRGB by the image's own
    statistics (:data:`PREVIEW_TONE_MAPPING`; module docstring).

    ``exposure`` (stops) overrides the automatic one; ``weights`` (``(...)``, e.g. solid
    angles) weight the log-average. Pixels that are exactly black in every channel (a cross's
    empty cells) do not count toward the exposure. NaN and negative values show black, +inf
    white.
    """
    a = np.asarray(image, dtype=np.float64)
    if a.ndim < 1 or a.shape[-1] != 3:
        raise ValueError(f"image must have shape (..., 3), got {a.shape}.")
    rgb = np.maximum(np.nan_to_num(a, nan=0.0, posinf=np.inf, neginf=0.0), 0.0)
    inf = np.isinf(rgb).any(axis=-1)
    rgb[inf] = 0.0
    m = rgb.max(axis=-1)
    if exposure is None:
        lit = m > 0
        w = None if weights is None else np.broadcast_to(np.asarray(weights, np.float64),
                                                          m.shape)[lit]
        exposure = auto_exposure(rgb[lit], w) if lit.any() else 0.0
    elif not np.isfinite(exposure):
        raise ValueError(f"exposure must be a finite number of stops, got {exposure!r}.")
    scale = 2.0 ** float(exposure)
    top = float(np.quantile(m, PREVIEW_WHITE_QUANTILE)) * scale if m.size else 0.0
    if top > _MOST_RANGE:  # more range than 8 bits hold above the key: expose down
        scale *= _MOST_RANGE / top
        top = _MOST_RANGE
    ms = m * scale
    # W with f(top) = t: top^2 / W^2 = t (1 + top) - top (> 0 below t / (1 - t)); W > top
    white = (top / np.sqrt(_BELOW_WHITE * (1.0 + top) - top)) if top > 1.0 else 1.0
    mapped = ms * (1.0 + ms / (white * white)) / (1.0 + ms)
    factor = np.divide(mapped, m, out=np.zeros_like(m), where=m > 0)
    out = np.minimum(rgb * factor[..., None], 1.0)
    out[inf] = 1.0
    return np.rint(linear_to_srgb(out) * 255.0).astype(np.uint8)


def tonemap_preview(image: ArrayLike, *, exposure: float | None = None) -> NDArray[np.uint8]:
    """Tone-map linear radiance to 8-bit display sRGB.

    Parameters
    ----------
    image : (..., 3) float
        Linear RGB radiance.
    exposure : float, optional
        Exposure in stops (the radiance is multiplied by ``2**exposure``). Default: automatic,
        so that the log-average luminance (``exp(mean(log(1e-4 + Y)))`` over finite pixels,
        Rec.709 ``Y``) maps to the key 0.18.

    Returns
    -------
    (..., 3) uint8
        ACES-filmic (Narkowicz fit) tone-mapped, sRGB-encoded. NaN and negative values show
        black, +inf white.
    """
    a = np.asarray(image, dtype=np.float64)
    if a.ndim < 1 or a.shape[-1] != 3:
        raise ValueError(f"image must have shape (..., 3), got {a.shape}.")
    if exposure is None:
        exposure = auto_exposure(a.reshape(-1, 3), None)
    elif not np.isfinite(exposure):
        raise ValueError(f"exposure must be a finite number of stops, got {exposure!r}.")
    x = np.nan_to_num(a, nan=0.0, posinf=np.inf, neginf=0.0) * 2.0 ** float(exposure)
    inf = np.isinf(x)
    mapped = np.asarray(aces_filmic(np.where(inf, 0.0, np.maximum(x, 0)) if inf.any()
                                    else np.maximum(x, 0)))
    mapped[inf] = 1.0
    return np.rint(linear_to_srgb(mapped) * 255.0).astype(np.uint8)
