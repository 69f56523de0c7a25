"""Texture images to texel arrays, in bounded memory: a pixel limit, then decoding a band of rows
at a time, reduced on the way to what a bake resolves.

A bake samples a texture where its rays hit: the primary rays of a probe's cube texel (a face
of ``face_size`` 32 texels (:class:`probegrid.bake.BakeSettings`) covers 90 degrees, about 2.8
degrees a texel) and the gather and shadow rays of their hits, all of them averaged into maps
of 8^2 (diffuse) to 32^2 texels. Texture detail finer than a ray's footprint only adds noise,
and a 4096^2 texture decoded to float32 RGBA is 256 MiB. So, on load:

* **A pixel limit** (:data:`MAX_TEXTURE_PIXELS`, 2^27 = 134 M pixels, e.g. 16384 x 8192; the
  CLI's ``--max-texture-pixels``): an image whose header declares more is refused with its size
  and the option, before any pixel is decoded (the header is all Pillow reads on open).
* **A size** (:data:`MAX_TEXTURE_SIZE`, 1024; ``--max-texture-size``): a texture whose longer
  side exceeds it is reduced, keeping its aspect ratio, to that longer side (32 texels of it
  for each texel of a default probe face seeing the whole texture across 90 degrees). The
  reduction is the **area average** of the *linear* texels (:mod:`probegrid.core.reduce`:
  each texel the mean over its footprint, fractional footprints included), so every channel's
  mean over the texture -- the albedo the light sees on average -- is preserved exactly.
  Texture coordinates are unchanged: ``[0, 1]`` spans the reduced image as it did the source.
* **Bounded memory**: Pillow decodes the file's pixels once (8 or 16 bits a channel); they are
  converted to linear float32 a band of at most :data:`BAND_PIXELS` pixels at a time (sRGB
  codes through a 256-entry table of the exact EOTF) and reduced band by band, so the peak is
  the decoded image plus a band and the output (at most about 2x the decoded size; measured
  in ``tests/test_texture_reduce.py``), never a float64 copy of the whole image.

A texture within the size is decoded to the same bits as a whole-image conversion would give
(the same EOTF values, per texel). With ``alpha_cutoff`` (a glTF ``MASK`` material), alpha is
thresholded per source texel *before* the reduction, so a reduced texel's alpha is the
fraction of its footprint that is opaque (its coverage), not an average alpha compared with
the cutoff later.

The limits hold for the duration of a :func:`texture_limits` block (the glTF loader opens one
around a load); Pillow's own decompression-bomb check on open is off inside it (the pixel limit
is checked before any image is decoded instead, with a message naming the option).
References: IEC 61966-2-1 (sRGB); glTF 2.0 specification, "Alpha Coverage".
"""

from __future__ import annotations

import contextvars
import io
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray

from probegrid.core.color import srgb_to_linear
from probegrid.core.reduce import area_average, area_edges, reduced_shape, row_bands
from probegrid.errors import SceneError

__all__ = ["BAND_PIXELS", "MAX_TEXTURE_PIXELS", "MAX_TEXTURE_SIZE", "TextureLimits",
           "check_texture_size", "decode_texture", "texture_limits"]

#: Default most pixels (width x height) of a texture image; more is refused from its header.
MAX_TEXTURE_PIXELS: Final[int] = 1 << 27
#: Default longest side of a texture after loading; larger ones are area-averaged down to it.
MAX_TEXTURE_SIZE: Final[int] = 1024
#: Source pixels converted to float at a time.
BAND_PIXELS: Final[int] = 1 << 19


@dataclass(frozen=True)
class TextureLimits:
    """The pixel limit and the longest side of loaded textures."""

    max_pixels: int = MAX_TEXTURE_PIXELS
    max_size: int = MAX_TEXTURE_SIZE

    def __post_init__(self) -> None:
        for name in ("max_pixels", "max_size"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"--{name.replace('_', '-').replace('max-', 'max-texture-')} "
                                 f"must be a positive integer, got {v!r}")


_LIMITS: contextvars.ContextVar[TextureLimits] = contextvars.ContextVar(
    "probegrid_texture_limits", default=TextureLimits())
_PIL_LOCK = threading.Lock()


@contextmanager
def texture_limits(limits: TextureLimits) -> Iterator[TextureLimits]:
    """``limits`` for the textures decoded in this block (this thread), Pillow's
    decompression-bomb limit raised or lowered to match (restored after)."""
    import PIL.Image

    token = _LIMITS.set(limits)
    with _PIL_LOCK:
        before = PIL.Image.MAX_IMAGE_PIXELS
        # Pillow refuses on open above twice its limit (trimesh would then drop the image
        # without a word): the limit is checked here instead, from the header, before decoding
        PIL.Image.MAX_IMAGE_PIXELS = None
    try:
        yield limits
    finally:
        with _PIL_LOCK:
            PIL.Image.MAX_IMAGE_PIXELS = before
        _LIMITS.reset(token)


def check_texture_size(width: int, height: int, what: str) -> None:
    """Refuse (one-line :class:`SceneError`) an image over the current pixel limit."""
    limit = _LIMITS.get().max_pixels
    if width * height > limit:
        raise SceneError(f"{what} is {width}x{height} = {width * height / 1e6:.1f} M pixels, "
                         f"over the limit of {limit / 1e6:.1f} M pixels a texture may have "
                         f"(--max-texture-pixels N raises it)")


#: sRGB code (0..255) -> linear float32, and code -> code / 255 (alpha), as float32.
_SRGB8: Final = srgb_to_linear(np.arange(256, dtype=np.float64) / 255.0)
_UNIT8: Final = (np.arange(256, dtype=np.float64) / 255.0).astype(np.float32)


def _band(image: object, y0: int, y1: int, channels: int, cutoff: float | None,
          linear: bool = False) -> NDArray[np.float32]:
    """Rows ``y0..y1`` of a Pillow image as ``(rows, W, channels)`` linear float32 (``linear``:
    the codes are data, ``code / max``, not sRGB colour)."""
    w = image.size[0]  # type: ignore[attr-defined]
    crop = image.crop((0, y0, w, y1))  # type: ignore[attr-defined]
    if crop.mode in ("I;16", "I;16B", "I;16L", "I"):  # 16-bit greyscale PNG modes
        a = np.clip(np.asarray(crop).astype(np.float64) / 65535.0, 0.0, 1.0)
        out = np.empty((*a.shape, channels), dtype=np.float32)
        out[..., :3] = (a if linear else srgb_to_linear(a))[..., None]
        if channels == 4:
            out[..., 3] = 1.0
    else:
        codes = np.asarray(crop.convert("RGBA" if channels == 4 else "RGB"))
        out = np.empty(codes.shape[:2] + (channels,), dtype=np.float32)
        out[..., :3] = (_UNIT8 if linear else _SRGB8)[codes[..., :3]]
        if channels == 4:
            out[..., 3] = _UNIT8[codes[..., 3]]
    if cutoff is not None and channels == 4:
        out[..., 3] = out[..., 3] >= cutoff
    return out


def _own_copy(image: object) -> object:
    """A Pillow image not yet decoded, opened again from its encoded bytes: decoding it leaves
    the caller's image undecoded (trimesh keeps every image of a scene; each decoded in place
    would stay in memory until the scene is dropped). The image itself when it is decoded
    already or its bytes cannot be read again."""
    import PIL.Image

    fp = getattr(image, "fp", None)
    if fp is None or getattr(image, "_im", None) is not None:
        return image
    try:
        where = fp.tell()
        fp.seek(0)
        data = fp.read()
        fp.seek(where)
        return PIL.Image.open(io.BytesIO(data))
    except (OSError, ValueError, AttributeError):
        return image


def decode_texture(image: object, channels: int, what: str, *,
                   alpha_cutoff: float | None = None, linear: bool = False
                   ) -> NDArray[np.float32]:
    """A Pillow image (opened, maybe not yet decoded) -> ``(H', W', channels)`` float32 linear
    RGB(A), reduced to the current :class:`TextureLimits` (module docstring). Colour is
    decoded from sRGB, alpha kept linear (thresholded at ``alpha_cutoff`` per source texel
    when given; ``linear``: colour channels are data, ``code / max``, as a transmission
    texture's); a 16-bit greyscale image is repeated into RGB with alpha 1.

    Raises :class:`SceneError` for an image over the pixel limit (from its header) or one
    Pillow cannot decode.
    """
    limits = _LIMITS.get()
    try:
        w, h = (int(v) for v in image.size)  # type: ignore[attr-defined]
        check_texture_size(w, h, what)
        image = _own_copy(image)
        image.load()  # type: ignore[attr-defined]
        oh, ow = reduced_shape(h, w, limits.max_size)
        out = np.empty((oh, ow, channels), dtype=np.float32)
        if (oh, ow) == (h, w):
            rows = max(1, BAND_PIXELS // w)
            for y0 in range(0, h, rows):
                out[y0:y0 + rows] = _band(image, y0, min(h, y0 + rows), channels,
                                          alpha_cutoff, linear)
            return out
        ex, ey = area_edges(w, ow), area_edges(h, oh)
        for j0, j1, s0, s1 in row_bands(h, oh, max(1, BAND_PIXELS // w)):
            band = _band(image, s0, s1, channels, alpha_cutoff, linear)
            rows = area_average(band, 0, ey[j0:j1 + 1], offset=s0)  # (contiguous sums first)
            del band
            out[j0:j1] = area_average(rows, 1, ex)
        return out
    except SceneError:
        raise
    except (OSError, ValueError, SyntaxError) as exc:
        raise SceneError(f"{what} could not be decoded ({exc}).") from None
