"""Texture sampling for scene materials: wrap modes and bilinear lookups of glTF textures.

Textures are float32 arrays ``(h, w, c)`` in linear values (colour textures are decoded from sRGB
when loaded); texture coordinates follow glTF: ``(0, 0)`` is the image's top-left corner, ``u`` to
the right, ``v`` downward. Wrap modes are glTF's sampler modes (repeat, clamp-to-edge, mirrored
repeat).

A texture reads one set of texture coordinates (glTF ``texCoord``: ``TEXCOORD_n``) through an
affine map (``KHR_texture_transform``), both held by a :class:`TexCoord`. The map is the
extension's ``T(offset) R(rotation) S(scale)`` applied to ``(u, v, 1)``:

    u' = sx cos(r) u + sy sin(r) v + ox
    v' = -sx sin(r) u + sy cos(r) v + oy

(the extension's example -- offset (0, 1), rotation pi/2, scale 0.5 reads "the lower left
quadrant of the source image, rotated clockwise 90 degrees" -- holds with these signs, as in
three.js's ``setUvTransform`` and the Khronos sample viewer; the extension's GLSL snippet has
the rotation transposed).

Reference: KHR_texture_transform extension specification (Khronos).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final, NamedTuple, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._types import Wrap

__all__ = ['TexCoord', 'Wrap', 'sample_texture', 'texture_transform']




_WRAPS: Final[tuple[str, ...]] = get_args(Wrap)

#: The identity map of texture coordinates, row-major ``(m00, m01, m02, m10, m11, m12)``.
IDENTITY: Final[tuple[float, ...]] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


class TexCoord(NamedTuple):
    """Which texture coordinates a texture reads and how they are mapped (module docstring).

    ``index``: the ``TEXCOORD_n`` set (glTF ``texCoord``, or the transform's override);
    ``matrix``: the affine map ``(m00, m01, m02, m10, m11, m12)``, ``u' = m00 u + m01 v + m02``,
    ``v' = m10 u + m11 v + m12`` (:data:`IDENTITY` by default)."""

    index: int = 0
    matrix: tuple[float, ...] = IDENTITY

    @property
    def is_identity(self) -> bool:
        """No transform: the coordinates are read as they are."""
        return tuple(self.matrix) == IDENTITY

    def apply(self, uv: ArrayLike) -> NDArray[np.float64]:
        """The mapped coordinates of ``uv (..., 2)``."""
        a = np.asarray(uv, dtype=np.float64)
        m = self.matrix
        return np.stack([m[0] * a[..., 0] + m[1] * a[..., 1] + m[2],
                         m[3] * a[..., 0] + m[4] * a[..., 1] + m[5]], axis=-1)


def texture_transform(offset: Sequence[float] = (0.0, 0.0), rotation: float = 0.0,
                      scale: Sequence[float] = (1.0, 1.0), *, index: int = 0) -> TexCoord:
    """The :class:`TexCoord` of a ``KHR_texture_transform`` (module docstring for the signs);
    raises ValueError for values that are not finite numbers."""
    try:
        ox, oy = (float(x) for x in offset)
        sx, sy = (float(x) for x in scale)
        r = float(rotation)
    except (TypeError, ValueError):
        raise ValueError(f"a texture transform needs offset [x, y], rotation r and scale [x, y], "
                         f"got {offset!r}, {rotation!r}, {scale!r}.") from None
    if not all(np.isfinite([ox, oy, sx, sy, r])):
        raise ValueError("a texture transform must be finite.")
    if not isinstance(index, (int, np.integer)) or not 0 <= int(index) < 64:
        raise ValueError(f"texCoord must be an integer in [0, 64), got {index!r}.")
    if r == 0.0:
        return TexCoord(int(index), (sx, 0.0, ox, 0.0, sy, oy))
    c, s = np.cos(r), np.sin(r)
    return TexCoord(int(index), (float(sx * c), float(sy * s), ox,
                                 float(-sx * s), float(sy * c), oy))


def _check_texcoord(tc: object) -> TexCoord:
    try:
        index, matrix = tc  # type: ignore[misc]
        m = tuple(float(x) for x in matrix)
    except (TypeError, ValueError):
        raise ValueError(f"a texture's coordinates must be TexCoord(index, matrix), got {tc!r}.")\
            from None
    if len(m) != 6 or not all(np.isfinite(m)):
        raise ValueError(f"a TexCoord matrix must be 6 finite numbers, got {matrix!r}.")
    if not isinstance(index, (int, np.integer)) or not 0 <= int(index) < 64:
        raise ValueError(f"texCoord must be an integer in [0, 64), got {index!r}.")
    return TexCoord(int(index), m)


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

