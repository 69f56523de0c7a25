"""Texture sampling for scene materials: wrap modes and bilinear lookups of glTF textures.

Textures are float32 arrays ``(h, w, c)`` in linear values (colour textures are decoded from sRGB
when loaded); texture coordinates follow glTF: ``(0, 0)`` is the image's top-left corner, ``u`` to
the right, ``v`` downward. Wrap modes are glTF's sampler modes (repeat, clamp-to-edge, mirrored
repeat).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._types import Wrap

__all__ = ['Wrap', 'sample_texture']




_WRAPS: Final[tuple[str, ...]] = get_args(Wrap)


def _wrap_index(i: NDArray[np.int64], n: int, mode: str) -> NDArray[np.int64]:
    if mode == "repeat":
        return np.mod(i, n)
    if mode == "clamp":
        return np.clip(i, 0, n - 1)
    m = np.mod(i, 2 * n)  # mirror: period 2n, second half reflected
    return np.where(m < n, m, 2 * n - 1 - m)


def _check_wrap(wrap: Sequence[str]) -> tuple[str, str]:
    w = tuple(wrap)
    if len(w) != 2 or any(x not in _WRAPS for x in w):
        raise ValueError(f"wrap must be two of {', '.join(_WRAPS)} (s, t), got {wrap!r}.")
    return w  # type: ignore[return-value]


def sample_texture(
    texture: ArrayLike, uv: ArrayLike, *, wrap: Sequence[Wrap] = ("repeat", "repeat")
) -> NDArray[np.float64]:
    """Bilinear texture lookup with GPU texel-centre conventions.

    Parameters
    ----------
    texture : (H, W, C) float
        Row 0 is the top of the image (glTF ``v = 0``).
    uv : (..., 2) float
        glTF texture coordinates: ``u`` to the right, ``v`` downward, ``[0, 1]`` over the image;
        texel ``(row, col)`` has its centre at ``((col + 0.5) / W, (row + 0.5) / H)``.
    wrap : (2,) of {"repeat", "clamp", "mirror"}
        Wrap mode along ``u`` (wrapS) and ``v`` (wrapT); glTF's default sampler repeats.

    Returns
    -------
    (..., C) float64
    """
    tex = np.asarray(texture)
    if tex.ndim != 3 or tex.shape[0] < 1 or tex.shape[1] < 1:
        raise ValueError(f"texture must have shape (H, W, C), got {tex.shape}.")
    ws, wt = _check_wrap(wrap)
    coords = np.asarray(uv, dtype=np.float64)
    if coords.shape[-1:] != (2,):
        raise ValueError(f"uv must have shape (..., 2), got {coords.shape}.")
    if not np.all(np.isfinite(coords)):
        raise ValueError("uv must be finite.")
    h, w = tex.shape[:2]
    x = coords[..., 0] * w - 0.5
    y = coords[..., 1] * h - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    xi = x0.astype(np.int64)
    yi = y0.astype(np.int64)
    c0, c1 = _wrap_index(xi, w, ws), _wrap_index(xi + 1, w, ws)
    r0, r1 = _wrap_index(yi, h, wt), _wrap_index(yi + 1, h, wt)
    top = tex[r0, c0] * (1.0 - fx) + tex[r0, c1] * fx
    bottom = tex[r1, c0] * (1.0 - fx) + tex[r1, c1] * fx
    return np.asarray(top * (1.0 - fy) + bottom * fy, dtype=np.float64)

