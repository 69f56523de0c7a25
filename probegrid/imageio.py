"""Reading and writing environment images: the only module that imports OpenImageIO.

Reading
-------
:func:`read_image` returns ``(H, W, 3)`` float32 *linear* Rec.709 RGB, row 0 at the top, from
``.hdr`` (Radiance RGBE), ``.exr``, ``.pfm``, ``.tif`` / ``.tiff``, ``.png`` and ``.jpg`` /
``.jpeg``. Pixel data stored as floating point (half / float, and RGBE) is taken as linear.
Pixel data stored as integers (8- or 16-bit PNG, JPEG, integer TIFF) is taken as sRGB-encoded
and decoded with the exact piecewise sRGB EOTF of IEC 61966-2-1::

    L = V / 12.92                         if V <= 0.04045
    L = ((V + 0.055) / 1.055) ** 2.4      otherwise

A one-channel image is repeated into RGB; of two channels (grey + alpha) the first is
repeated; channels after the third (alpha, ...) are dropped, with alpha read *unassociated*
(the stored colour, not colour times alpha).

Every failure raises :class:`ImageError` (a ``ValueError``) with a one-line message that starts
with the file name: missing file, unsupported extension, a file the format's reader rejects,
and a *truncated* file (OpenImageIO's error state after reading, plus a check that the number
of values returned is ``H W C``; a short read is never returned as partial data).

:func:`read_environment` reads one image in any :mod:`probegrid.core.layouts` layout (detected from
the aspect ratio by default) or six face files (put in the order ``+X, -X, +Y, -Y, +Z, -Z`` by
their names, :func:`order_face_files`) and resamples it, anti-aliased, to a cube map.

Writing
-------
Every writer is *atomic*: the image is written to a hidden temporary file in the destination
directory (``.<name>.<random>.tmp<ext>``, same extension so OpenImageIO picks the same
format), flushed to disk, and only then renamed over the destination with :func:`os.replace`.
An interrupted or failed run leaves either the old file or the complete new one, never half a
file; :func:`write_cube` writes all its files (three encoders at once) before renaming any of
them. ``durable=False`` skips the flushes, for a caller that flushes a whole staging folder
before publishing it (:mod:`probegrid.jobs.staging`). Formats:

* ``.exr``: half (default) or float32, ZIP compression; carries string metadata.
* ``.tif`` / ``.tiff``: float32 (no metadata). OpenImageIO's TIFF writer stores half data as
  float32 (few TIFF readers handle 16-bit float), so ``half`` does not apply.
* ``.hdr``: Radiance RGBE (8-bit shared exponent: ~1 % precision relative to the pixel's
  largest channel; negative and non-finite values become 0).
* ``.pfm``: float32.
* ``.png``: 8-bit sRGB-encoded (the OETF inverse to the EOTF above, values clipped to
  ``[0, 1]``, NaN -> 0), for previews of display-referred data. Use
  :func:`tonemap_preview` / :func:`write_preview_png` for HDR previews.

``half=True`` (the default of the writers) is a *preference*: only ``.exr`` stores half, and
every other format ignores the flag and writes its single pixel type above. An EXR with a
finite value beyond the largest half, ``|x| > 65504`` (a real sun easily is), would hold
``inf`` there, so such an image is written as float32 instead: lossless for those values,
no clamp, no change of energy. (NaN and +-inf are kept as they are in either type.) The
pixel type actually stored is reported: :func:`write_cube` returns a :class:`WrittenFiles`
list with a ``pixel_type`` attribute (one type for all files of a cube: if any face needs
float32, all six are float32, so a cube has one pixel type), and :func:`stored_pixel_type`
reads it back from any written file's header. The names are :data:`PIXEL_TYPES`:
``"half"``, ``"float"`` (32-bit), ``"rgbe"`` (``.hdr``) and ``"uint8"`` (``.png``).

Face files of :func:`write_cube` are named ``<stem>_px``, ``_nx``, ``_py``, ``_ny``, ``_pz``,
``_nz`` plus the extension (:data:`FACE_SUFFIXES`); other layouts write ``<stem>.<ext>``.

Previews
--------
:func:`tonemap_preview` maps linear radiance to display sRGB bytes: scale by ``2**exposure``
(default: automatic, the *key* 0.18 over the log-average luminance, Reinhard et al. 2002),
apply Narkowicz's ACES filmic fit per channel, then the sRGB OETF. :func:`write_preview_png`
tone-maps by the image's own statistics instead
(:func:`probegrid.core.color.tonemap_adaptive`: that exposure, then a shoulder whose white
point is the image's own near-brightest value, so that almost no pixel clips;
:data:`PREVIEW_TONE_MAPPING` says it in words) and writes with the quickest PNG compression
(``fast``).

References
----------
* IEC 61966-2-1:1999, sRGB transfer functions.
* G. Ward, "Real pixels", Graphics Gems II, 1991 (RGBE).
* E. Reinhard et al., "Photographic tone reproduction for digital images", SIGGRAPH 2002.
* K. Narkowicz, "ACES filmic tone mapping curve", 2015.
"""

from __future__ import annotations

import errno
import math
import os
import re
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Final, Literal, get_args

import numpy as np
import OpenImageIO as oiio
from numpy.typing import ArrayLike, NDArray

from probegrid._fs import fsync_dir, fsync_file
from probegrid._types import CubeLayout, ImageFormat, PixelType
from probegrid.core.color import (
    PREVIEW_TONE_MAPPING,
    auto_exposure,
    linear_to_srgb,
    srgb_to_linear,
    tonemap_adaptive,
    tonemap_preview,
)
from probegrid.core.cubemap import check_cube, texel_solid_angles
from probegrid.core.reduce import area_average, area_edges, row_bands
from probegrid.core.layouts import (
    LAYOUTS,
    Layout,
    default_face_size,
    detect_layout,
    from_cube,
    layout_shape,
    to_cube,
)
from probegrid.errors import ImageError

__all__ = [
    "BAND_PIXELS",
    "check_pixels",
    "FACE_NAMES",
    "FACE_ORDER_HELP",
    "FACE_SUFFIXES",
    "HALF_MAX",
    "MAX_PIXELS",
    "PIXEL_TYPES",
    "PREVIEW_TONE_MAPPING",
    "READ_EXTENSIONS",
    "WRITE_EXTENSIONS",
    "CubeLayout",
    "ImageError",
    "ImageFormat",
    "PixelType",
    "WrittenFiles",
    "clamp_radiance",
    "count_nonfinite",
    "cube_exposure",
    "detect_file_layout",
    "face_of",
    "image_size",
    "linear_to_srgb",
    "order_face_files",
    "read_environment",
    "read_image",
    "read_metadata",
    "reduced_environment_shape",
    "srgb_to_linear",
    "stored_pixel_type",
    "tonemap_preview",
    "write_cube",
    "write_image",
    "write_preview_png",
]


#: Extensions :func:`read_image` accepts (lower case).
READ_EXTENSIONS: Final[tuple[str, ...]] = (
    ".hdr", ".exr", ".pfm", ".tif", ".tiff", ".png", ".jpg", ".jpeg",
)
#: Extensions :func:`write_image` accepts (lower case).
WRITE_EXTENSIONS: Final[tuple[str, ...]] = (".exr", ".hdr", ".pfm", ".tif", ".tiff", ".png")
#: File-name suffixes of the six faces, in face order.
FACE_SUFFIXES: Final[tuple[str, ...]] = ("_px", "_nx", "_py", "_ny", "_pz", "_nz")

#: Pixel types a written file can have (see "Writing" above).
PIXEL_TYPES: Final[tuple[str, ...]] = get_args(PixelType)
#: The largest finite half float, 65504 = (2 - 2**-10) * 2**15.
HALF_MAX: Final[float] = float(np.finfo(np.float16).max)
_CUBE_LAYOUTS: Final[tuple[str, ...]] = get_args(CubeLayout)
_CUBE_FORMATS: Final[tuple[str, ...]] = get_args(ImageFormat)



# --------------------------------------------------------------------------------------------
# Transfer functions


# --------------------------------------------------------------------------------------------
# Reading

#: The face names :func:`order_face_files` recognises, per face in face order (+X, -X, +Y, -Y,
#: +Z, -Z), matched case-insensitively as whole words of the file name (delimited by anything
#: but a letter or digit): ``px``/``posx``/``positive_x``/``xpos``/``right``/``+x``, ... The
#: words right, left, top, bottom, front, back follow the usual skybox naming (three.js,
#: Babylon.js): right = +X, top = +Y, front = +Z.
FACE_NAMES: Final[tuple[tuple[str, ...], ...]] = (
    ("px", "posx", "pos_x", "positive_x", "xpos", "xp", "right", "+x"),
    ("nx", "negx", "neg_x", "negative_x", "xneg", "xn", "left", "-x"),
    ("py", "posy", "pos_y", "positive_y", "ypos", "yp", "top", "up", "+y"),
    ("ny", "negy", "neg_y", "negative_y", "yneg", "yn", "bottom", "down", "-y"),
    ("pz", "posz", "pos_z", "positive_z", "zpos", "zp", "front", "+z"),
    ("nz", "negz", "neg_z", "negative_z", "zneg", "zn", "back", "-z"),
)
#: One sentence for ``--help``: how six face files are ordered.
FACE_ORDER_HELP: Final[str] = (
    "six face files are put in the order +X, -X, +Y, -Y, +Z, -Z by their names (px/nx/py/ny/"
    "pz/nz, posx/negx..., right/left/top/bottom/front/back or +X/-X...), whatever their order "
    "on the command line (files without face names are taken in the order given)"
)
_FACE_PATTERNS = [
    [re.compile(r"(?<![a-z0-9])" + re.escape(word) + r"(?![a-z0-9])") for word in words]
    for words in FACE_NAMES
]


def face_of(path: str | os.PathLike[str]) -> int | None:
    """The face (0..5, order +X, -X, +Y, -Y, +Z, -Z) a file's name says, or None.

    Only the file name counts (not its folder), without its extension; when it holds several
    face words, the last one (the suffix, as in ``left_wall_px.hdr``) wins.
    """
    stem = Path(Path(path).name.lower()).stem
    best: tuple[int, int, int] | None = None  # (end, -start, face): the last, longest word
    for face, patterns in enumerate(_FACE_PATTERNS):
        for pattern in patterns:
            for m in pattern.finditer(stem):
                best = max(best or (m.end(), -m.start(), face), (m.end(), -m.start(), face))
    return None if best is None else best[2]


def order_face_files(paths: Sequence[str | os.PathLike[str]]) -> list[Path]:
    """Six face files in face order (+X, -X, +Y, -Y, +Z, -Z), by their names (:data:`FACE_NAMES`).

    Shells sort ``sky_*.exr`` alphabetically (``nx, ny, nz, px, py, pz``), so the order of
    the arguments says nothing; the names do. Six files of which none names a face keep the
    order given. Raises ValueError (one line) when some files name faces and others do not, or
    when two name the same face.
    """
    plist = [Path(p) for p in paths]
    if len(plist) != 6:
        raise ValueError(f"a cube needs six face files, got {len(plist)}.")
    faces = [face_of(p) for p in plist]
    labels = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
    unnamed = [p.name for p, f in zip(plist, faces, strict=True) if f is None]
    if len(unnamed) == 6:  # no face names at all (f0..f5): the order given is the face order
        return plist
    if unnamed:
        raise ValueError(
            f"cannot tell which cube face {unnamed[0]!r} is: name the six face files with "
            "px/nx/py/ny/pz/nz (or posx/negx..., right/left/top/bottom/front/back, +X/-X...), "
            "or give one image in a cross or equirect layout.")
    if sorted(faces) != list(range(6)):  # type: ignore[type-var]
        seen: dict[int, str] = {}
        for p, f in zip(plist, faces, strict=True):
            assert f is not None
            if f in seen:
                raise ValueError(f"{seen[f]!r} and {p.name!r} both name cube face {labels[f]}; "
                                 "give one file per face.")
            seen[f] = p.name
    by_face = dict(zip(faces, plist, strict=True))
    return [by_face[f] for f in range(6)]



def _one_line(text: str) -> str:
    parts = [p.strip() for p in str(text).splitlines() if p.strip()]
    return "; ".join(parts) if parts else "unknown error"


def _check_readable(path: str | os.PathLike[str]) -> Path:
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in READ_EXTENSIONS:
        raise ImageError(
            f"{p}: unsupported image extension {ext or '(none)'!r}; "
            f"readable: {', '.join(READ_EXTENSIONS)}."
        )
    if not p.exists():
        raise ImageError(f"{p}: no such file.")
    if not p.is_file():
        raise ImageError(f"{p}: not a regular file.")
    return p


def _open(p: Path) -> oiio.ImageInput:
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(p), config)
    if inp is None:
        raise ImageError(f"{p}: cannot read image ({_one_line(oiio.geterror())}).")
    return inp


#: Most pixels :func:`read_image` decodes by default (2^28: a 23170^2 image, 16384 x 16384);
#: a header that declares more is refused before any pixel is read or memory allocated.
MAX_PIXELS: Final[int] = 1 << 28
#: Source pixels a reduced read (:func:`read_image` with ``shape``) holds at a time.
BAND_PIXELS: Final[int] = 1 << 20


def read_image(path: str | os.PathLike[str], *, max_pixels: int | None = None,
               shape: tuple[int, int] | None = None, option: str | None = None,
               equirect: bool = False) -> NDArray[np.float32]:
    """Read an image as linear RGB.

    Parameters
    ----------
    path : str or Path
        ``.hdr``, ``.exr``, ``.pfm``, ``.tif``, ``.tiff``, ``.png``, ``.jpg`` or ``.jpeg``.
    max_pixels : int, optional
        Largest ``width x height`` read (default :data:`MAX_PIXELS`); more is an ImageError
        raised from the header alone (OpenImageIO itself refuses a header that declares far
        more pixels than the file holds; this bounds what a real file may cost). ``option``
        names the option that raises it in the message (e.g. ``--max-pixels``).
    shape : (H', W'), optional
        Read the image reduced to this size: scanlines are read a band of about
        :data:`BAND_PIXELS` pixels at a time, decoded to linear and area-averaged
        (:mod:`probegrid.core.reduce`: every output pixel the mean over its footprint, the
        image's mean kept), so memory holds a band and the output, never the whole image.
        Must be no larger than the image along either axis. ``equirect``: rows are averaged
        weighted by their solid angle (``sin`` of their edges' latitudes), so that the light
        the image carries, ``sum L dOmega``, is what the reduction keeps exactly.

    Returns
    -------
    (H, W, 3) float32
        Linear RGB, row 0 at the top (integer-coded files decoded from sRGB).

    Raises
    ------
    ImageError
        Missing, unsupported, unreadable or truncated file (one line naming the file).
    """
    p = _check_readable(path)
    inp = _open(p)
    try:
        spec = inp.spec()
        h, w, c, depth = spec.height, spec.width, spec.nchannels, spec.depth
        if h < 1 or w < 1 or c < 1 or depth != 1 or spec.deep:
            raise ImageError(
                f"{p}: not a flat 2-D image (width {w}, height {h}, depth {depth}, "
                f"{c} channels{', deep' if spec.deep else ''})."
            )
        max_pixels = MAX_PIXELS if max_pixels is None else max_pixels
        if w * h > max_pixels:
            fix = (f"{option} N raises it" if option is not None else "downsample it first")
            raise ImageError(f"{p}: {w}x{h} is {w * h} pixels, over the limit of {max_pixels} "
                             f"an image may have here; {fix}.")
        integer = spec.format.basetype not in (oiio.BASETYPE.HALF, oiio.BASETYPE.FLOAT,
                                               oiio.BASETYPE.DOUBLE)
        if shape is not None and tuple(shape) != (h, w):
            return _read_reduced(inp, p, (h, w, c), tuple(shape), integer, equirect)
        data = inp.read_image(0, 0, 0, c, oiio.FLOAT)
        error = inp.geterror() if inp.has_error else ""
    finally:
        inp.close()
    if data is None or error:
        raise ImageError(f"{p}: truncated or corrupt image data ({_one_line(error)}).")
    a = np.asarray(data, dtype=np.float32)
    if a.size != h * w * c:
        raise ImageError(
            f"{p}: truncated image: read {a.size} values, expected {h * w * c} ({w}x{h}x{c})."
        )
    a = a.reshape(h, w, c)
    rgb = np.repeat(a[..., :1], 3, axis=-1) if c < 3 else a[..., :3]
    return srgb_to_linear(rgb) if integer else np.ascontiguousarray(rgb, dtype=np.float32)


def _read_reduced(inp: oiio.ImageInput, p: Path, hwc: tuple[int, int, int],
                  shape: tuple[int, ...], integer: bool, equirect: bool
                  ) -> NDArray[np.float32]:
    """:func:`read_image` of an open image reduced to ``shape``, a band at a time."""
    h, w, c = hwc
    weights = None
    if equirect:  # (each row's solid angle over 2 pi / W)
        weights = -np.diff(np.sin(0.5 * np.pi - np.arange(h + 1) * (np.pi / h)))
    oh, ow = (int(v) for v in shape)
    if not (1 <= oh <= h and 1 <= ow <= w):
        raise ValueError(f"cannot reduce a {w}x{h} image to {ow}x{oh}")
    out = np.empty((oh, ow, 3), dtype=np.float32)
    ex, ey = area_edges(w, ow), area_edges(h, oh)
    kept = np.empty((0, w, 3), dtype=np.float32)  # the rows read last, from row ``start`` on
    start = 0
    for j0, j1, s0, s1 in row_bands(h, oh, max(1, BAND_PIXELS // w)):
        first = max(s0, start + len(kept))  # (scanlines are read in order, each once)
        data = inp.read_scanlines(0, 0, first, s1, 0, 0, c, oiio.FLOAT)
        if data is None or inp.has_error:
            raise ImageError(f"{p}: truncated or corrupt image data "
                             f"({_one_line(inp.geterror())}).")
        a = np.asarray(data, dtype=np.float32)
        if a.size != (s1 - first) * w * c:
            raise ImageError(f"{p}: truncated image: read {a.size} values of rows {first} to "
                             f"{s1}, expected {(s1 - first) * w * c} ({w}x{h}x{c}).")
        a = a.reshape(s1 - first, w, c)
        rgb = np.repeat(a[..., :1], 3, axis=-1) if c < 3 else a[..., :3]
        rgb = srgb_to_linear(rgb) if integer else rgb
        band = np.concatenate([kept[s0 - start:], rgb]) if first > s0 else rgb
        # (rows first: contiguous sums that leave the column pass a band of output rows)
        rows = area_average(band, 0, ey[j0:j1 + 1], offset=s0,
                            weights=None if weights is None else weights[s0:s0 + len(band)])
        out[j0:j1] = area_average(rows, 1, ex)
        kept, start = band, s0
    return out


def reduced_environment_shape(height: int, width: int, layout: Layout, size: int
                              ) -> tuple[int, int] | None:
    """The size an environment image of ``layout`` is read at for a cube of face ``size``:
    the layout at twice the face size (every cube texel still covers at least two source
    pixels across: equirect ``8 size x 4 size``, crosses ``2 size`` a face, angular
    ``ceil(2 pi size)``; :func:`probegrid.core.layouts.default_face_size` is the inverse), or
    None when the image is not larger than that or its proportions are not the layout's
    exactly (then it is read whole and the resampler judges it)."""
    m = 2 * int(size)
    if layout == "equirect":
        need = layout_shape("equirect", 2 * m)
    elif layout == "angular":
        need = layout_shape("angular", math.ceil(math.pi * m))
    elif layout in ("hcross", "vcross", "faces"):
        need = layout_shape(layout, m)
    else:
        return None
    nh, nw = need
    if height <= nh or width <= nw or height * nw != width * nh:
        return None
    return nh, nw


def image_size(path: str | os.PathLike[str]) -> tuple[int, int]:
    """``(width, height)`` of an image, read from its header only."""
    p = _check_readable(path)
    inp = _open(p)
    try:
        spec = inp.spec()
        return int(spec.width), int(spec.height)
    finally:
        inp.close()


def detect_file_layout(path: str | os.PathLike[str], *, option: str = "--layout") -> Layout:
    """The layout ``auto`` means for one image file, from its header alone (before its pixels
    are read): :func:`probegrid.core.layouts.detect_layout` of its size, except that a square
    *integer-coded* (LDR: PNG, JPEG) image is refused rather than taken as an angular map
    (a photograph or a mirror ball is square too, and an 8-bit file holds no HDR light);
    ``option angular`` (e.g. ``--layout angular``) states it is one. Raises
    :class:`ImageError` (one line naming the file) for that and for an undetectable aspect
    ratio."""
    p = _check_readable(path)
    inp = _open(p)
    try:
        spec = inp.spec()
        w, h = int(spec.width), int(spec.height)
        integer = spec.format.basetype not in (oiio.BASETYPE.HALF, oiio.BASETYPE.FLOAT,
                                               oiio.BASETYPE.DOUBLE)
        hdr = inp.format_name() == "hdr"
    finally:
        inp.close()
    try:
        lay = detect_layout(h, w)
    except ValueError as exc:
        raise ImageError(f"{p}: {exc}") from None
    if lay == "angular" and integer and not hdr:
        raise ImageError(f"{p}: a square {w}x{h} LDR (integer-coded) image is not taken as "
                         "an angular HDR environment by default (it may be a photograph or a "
                         f"mirror ball); give {option} angular if it is an angular map")
    return lay


def read_metadata(path: str | os.PathLike[str]) -> dict[str, str]:
    """The string attributes stored in an image file's header (e.g. an EXR's metadata).

    Returns
    -------
    dict
        Attribute name -> value, string-typed attributes only.
    """
    p = _check_readable(path)
    inp = _open(p)
    try:
        attribs = inp.spec().extra_attribs
        return {a.name: str(a.value) for a in attribs if a.type == oiio.TypeString}
    finally:
        inp.close()


def count_nonfinite(image: ArrayLike) -> int:
    """Number of pixels (or texels) with at least one NaN or infinite channel.

    Parameters
    ----------
    image : (..., C) float
        The last axis holds the channels.
    """
    a = np.asarray(image)
    if a.ndim == 0:
        raise ValueError("count_nonfinite needs an array with a channel axis, got a scalar.")
    return int(np.count_nonzero(~np.isfinite(a).all(axis=-1)))


def clamp_radiance(image: ArrayLike, maximum: float) -> NDArray[np.float32]:
    """Clamp radiance to ``[0, maximum]``: NaN and -inf become 0, +inf becomes ``maximum``.

    Returns
    -------
    float32 array of the input's shape.
    """
    m = float(maximum)
    if not np.isfinite(m) or m <= 0:
        raise ValueError(f"the clamp must be a positive finite number, got {maximum!r}.")
    a = np.asarray(image, dtype=np.float32)
    return np.clip(np.nan_to_num(a, nan=0.0, posinf=m, neginf=0.0), 0.0, m).astype(np.float32)


def read_environment(
    paths: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    *,
    layout: Layout | Literal["auto"] = "auto",
    size: int | None = None,
    max_size: int | None = None,
    clamp: float | None = None,
    keep_negative: bool = False,
    report: Callable[[str], None] | None = None,
    max_pixels: int | None = None,
    option: str | None = None,
) -> NDArray[np.float32]:
    """Read an environment as a cube map of linear radiance.

    Parameters
    ----------
    paths : path or sequence of 1 or 6 paths
        One image in any layout of :mod:`probegrid.core.layouts`, or six face images (square, same
        size), put in the order ``+X, -X, +Y, -Y, +Z, -Z`` by their names
        (:func:`order_face_files`), not by their order here.
    layout : {"auto", "equirect", "angular", "hcross", "vcross", "faces"}
        ``"auto"`` detects a single image's layout from its aspect ratio
        (:func:`probegrid.core.layouts.detect_layout`) and means ``"faces"`` for six files.
    size : int, optional
        Output face size; default :func:`probegrid.core.layouts.default_face_size` of the source
        (e.g. 1024 x 512 equirect -> 256). A source more than twice as fine as that needs is
        read reduced (:func:`reduced_environment_shape`, a band of rows at a time): its memory
        is bounded by the output's size, not the file's.
    max_size : int, optional
        Upper bound on the default face size (ignored when ``size`` is given).
    clamp : float, optional
        If given, source pixels are clamped to ``[0, clamp]`` (NaN -> 0, +inf -> clamp) before
        resampling. If not, a source with non-finite pixels raises :class:`ImageError` giving
        their number.
    keep_negative : bool
        Keep negative source values; by default they are set to 0 (radiance is never
        negative) and ``report`` is told how many there were.
    report : callable, optional
        Receives one line for what was changed in the source (negative values set to 0).
    max_pixels : int, optional
        Most pixels each file may have (default :data:`MAX_PIXELS`), checked from the headers
        before any pixel is read; ``option`` names the option that raises it in the message
        (:func:`read_image`).

    Returns
    -------
    (6, n, n, 3) float32
        Each texel the solid-angle mean radiance of the source (:func:`layouts.to_cube`).
    """
    if isinstance(paths, (str, os.PathLike)):
        plist = [Path(paths)]
    else:
        plist = [Path(p) for p in paths]
    if layout != "auto" and layout not in LAYOUTS:
        raise ValueError(
            f"unknown layout {layout!r}; choose one of 'auto', "
            f"{', '.join(repr(x) for x in LAYOUTS)}."
        )
    if size is not None and (
        not isinstance(size, (int, np.integer)) or isinstance(size, bool) or size < 1
    ):
        raise ValueError(f"size must be a positive integer, got {size!r}.")
    def face_size(h: int, w: int, lay: Layout) -> int:
        n = default_face_size(h, w, lay) if size is None else int(size)
        return min(n, max_size) if size is None and max_size is not None else n

    if len(plist) == 6:
        if layout not in ("auto", "faces"):
            raise ValueError(f"six files are six faces; layout {layout!r} needs one file.")
        plist = order_face_files(plist)
        fw, fh = image_size(plist[0])
        need = reduced_environment_shape(fh, fw, "faces", face_size(fh, fw, "faces"))
        check_pixels(plist, max_pixels=max_pixels, option=option)
        images = [_read_checked(p, clamp, shape=need if image_size(p) == (fw, fh) else None,
                                max_pixels=max_pixels, option=option) for p in plist]
        shapes = {im.shape for im in images}
        first = images[0].shape
        if len(shapes) != 1 or first[0] != first[1]:
            desc = ", ".join(f"{p.name} {im.shape[1]}x{im.shape[0]}" for p, im in
                             zip(plist, images, strict=True))
            raise ImageError(f"the six face files must be square and equal in size: {desc}.")
        source: NDArray[np.float32] = np.stack(images)
        lay: Layout = "faces"
        h, w = first[:2]
    elif len(plist) == 1:
        if layout == "faces":
            raise ValueError("layout 'faces' needs six files (+X, -X, +Y, -Y, +Z, -Z).")
        w, h = image_size(plist[0])  # (the layout and the size read from the header)
        if layout == "auto":
            try:
                lay = detect_layout(h, w)
            except ValueError as exc:
                raise ImageError(f"{plist[0]}: {exc}") from None
        else:
            lay = layout
        need = reduced_environment_shape(h, w, lay, face_size(h, w, lay))
        source = _read_checked(plist[0], clamp, shape=need, equirect=lay == "equirect",
                               max_pixels=max_pixels, option=option)
    else:
        raise ValueError(f"give one environment image or six face files, got {len(plist)} paths.")
    negative = int(np.count_nonzero(source < 0))
    if negative and not keep_negative:
        source = np.maximum(source, np.float32(0.0))
        if report is not None:
            what = plist[0].name if len(plist) == 1 else "the six faces"
            report(f"note: {negative} negative values of {what} "
                   "set to 0 (radiance is never negative)")
    n = face_size(h, w, lay)  # (of the file's size: a reduced source keeps it)
    try:
        return to_cube(source, lay, n)
    except ValueError as exc:
        if isinstance(exc, ImageError) or len(plist) != 1:
            raise
        raise ImageError(f"{plist[0]}: {exc}") from None


def check_pixels(paths: Sequence[str | os.PathLike[str]], *, max_pixels: int | None = None,
                 option: str | None = None) -> None:
    """Refuse, from the headers alone, a file of ``paths`` with more than ``max_pixels``
    pixels (default :data:`MAX_PIXELS`): the :class:`ImageError` :func:`read_image` raises,
    before anything else is read or done."""
    limit = MAX_PIXELS if max_pixels is None else int(max_pixels)
    for p in paths:
        w, h = image_size(p)
        if w * h > limit:
            fix = f"{option} N raises it" if option is not None else "downsample it first"
            raise ImageError(f"{p}: {w}x{h} is {w * h} pixels, over the limit of {limit} an "
                             f"image may have here; {fix}.")


def _read_checked(p: Path, clamp: float | None, *, shape: tuple[int, int] | None = None,
                  equirect: bool = False, max_pixels: int | None = None,
                  option: str | None = None) -> NDArray[np.float32]:
    image = read_image(p, shape=shape, equirect=equirect, max_pixels=max_pixels, option=option)
    if clamp is not None:
        return clamp_radiance(image, clamp)
    bad = count_nonfinite(image)
    if bad:
        raise ImageError(
            f"{p}: {bad} non-finite pixel{'s' if bad != 1 else ''} (NaN or infinite); "
            "repair the image (probegrid filter's --clamp replaces them)."
        )
    return image


# --------------------------------------------------------------------------------------------
# Writing


class WrittenFiles(list[Path]):
    """The paths :func:`write_cube` wrote, in order, and the pixel type they were stored in.

    A ``list`` of :class:`~pathlib.Path` (so existing code indexing or iterating it works)
    with one more attribute, ``pixel_type`` (one of :data:`PIXEL_TYPES`).
    """

    pixel_type: PixelType

    def __init__(self, paths: Sequence[Path], pixel_type: PixelType) -> None:
        super().__init__(paths)
        self.pixel_type = pixel_type

    def __repr__(self) -> str:
        return f"WrittenFiles({list(self)!r}, pixel_type={self.pixel_type!r})"


def _exceeds_half(a: NDArray[np.float32]) -> bool:
    """Whether a finite value of ``a`` has a magnitude above :data:`HALF_MAX` (-> inf in half)."""
    big = np.abs(a) > HALF_MAX  # NaN compares False
    return bool(np.any(big & np.isfinite(a)))


def _prepare(p: Path, image: ArrayLike, half: bool) -> tuple[NDArray, PixelType]:
    """Array and pixel type to write ``image`` to ``p``.

    ``half`` is honoured by ``.exr`` only, and there only if no finite value exceeds
    :data:`HALF_MAX` in magnitude; otherwise the file is float32.
    """
    ext = p.suffix.lower()
    if ext not in WRITE_EXTENSIONS:
        raise ImageError(
            f"{p}: unsupported output extension {ext or '(none)'!r}; "
            f"writable: {', '.join(WRITE_EXTENSIONS)}."
        )
    a = np.asarray(image)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[0] < 1 or a.shape[1] < 1 or a.shape[2] not in (1, 3):
        raise ValueError(f"an image to write must have shape (H, W), (H, W, 1) or (H, W, 3), "
                         f"got {np.shape(image)}.")
    if ext == ".png":
        if a.dtype == np.uint8:
            return np.ascontiguousarray(a), "uint8"
        enc = np.rint(linear_to_srgb(a) * 255.0).astype(np.uint8)
        return enc, "uint8"
    a = np.ascontiguousarray(a, dtype=np.float32)
    if ext == ".hdr":
        return (np.repeat(a, 3, axis=-1) if a.shape[2] == 1 else a), "rgbe"
    if ext == ".exr" and half and not _exceeds_half(a):
        return a, "half"
    return a, "float"


#: Files of one cube encoded at once.
_WRITERS: Final[int] = 3


#: PNG encoder settings of ``fast`` writes (previews): zlib level 1 and the "sub" filter
#: encode a 512 x 384 preview in 5 instead of 27 ms, in a file ~15 % larger (the same pixels).
_FAST_PNG: Final[Mapping[str, int]] = {"png:compressionLevel": 1, "png:filter": 16}


#: The last 12 bytes of every PNG file: the IEND chunk (length 0, type, CRC).
_PNG_END: Final = b"\0\0\0\0IEND\xaeB`\x82"


def _check_written(tmp: Path, p: Path, height: int) -> None:
    """ImageError unless the file just written ends as an image file ends (a PNG in its IEND
    chunk; other formats: their last scanline reads back). OpenImageIO's writers report a
    failed write of the pixels but not the final flush of the file's buffer: on a full disk an
    image of a few KiB is left empty (or short) behind a successful close."""
    try:
        size = tmp.stat().st_size
        if p.suffix.lower() == ".png":
            with open(tmp, "rb") as f:
                f.seek(max(0, size - len(_PNG_END)))
                whole = size > len(_PNG_END) and f.read() == _PNG_END
        else:
            inp = oiio.ImageInput.open(str(tmp)) if size else None
            whole = inp is not None and inp.spec().height == height
            if inp is not None:
                whole = (whole and inp.read_scanline(height - 1, 0, "float") is not None
                         and not inp.has_error)
                inp.close()
    except OSError as exc:
        raise ImageError(f"{p}: cannot write image ({exc.strerror}).") from None
    if not whole:
        try:
            full = os.statvfs(tmp.parent).f_bavail == 0
        except OSError:
            full = False
        reason = os.strerror(errno.ENOSPC) if full else "the file is incomplete"
        raise ImageError(f"{p}: cannot write image ({reason}).")


def _write_tmp(p: Path, data: NDArray, pixel_type: PixelType,
               metadata: Mapping[str, str], durable: bool = True, fast: bool = False) -> Path:
    """Write ``data`` to a temporary sibling of ``p`` and (``durable``) flush it; return the
    temporary path. ``fast``: a PNG with :data:`_FAST_PNG`."""
    directory = p.parent
    if not directory.is_dir():
        raise ImageError(f"{p}: the directory {directory} does not exist.")
    if p.is_dir():
        raise ImageError(f"{p}: is a directory, cannot write an image over it.")
    tmp = directory / f".{p.stem}.{os.urandom(6).hex()}.tmp{p.suffix}"
    try:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise ImageError(f"{p}: cannot create a writer ({_one_line(oiio.geterror())}).")
        h, w, c = data.shape
        # OpenImageIO's Radiance writer takes float data and encodes RGBE itself
        spec = oiio.ImageSpec(w, h, c, "float" if pixel_type == "rgbe" else pixel_type)
        ext = p.suffix.lower()
        if ext == ".exr":
            spec.attribute("compression", "zip")
            for key, value in metadata.items():
                spec.attribute(str(key), str(value))
        elif ext in (".tif", ".tiff"):
            spec.attribute("tiff:write_exif", 0)  # libtiff fails on an empty Exif directory
        elif ext == ".png" and fast:
            for key, level in _FAST_PNG.items():
                spec.attribute(key, level)
        ok = out.open(str(tmp), spec) and out.write_image(data)
        ok = out.close() and ok
        if not ok or out.has_error:
            raise ImageError(f"{p}: cannot write image ({_one_line(out.geterror())}).")
        _check_written(tmp, p, h)
        if durable:
            fsync_file(tmp)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return tmp


def _write_all(items: Sequence[tuple[Path, NDArray, PixelType]],
               metadata: Mapping[str, str], durable: bool = True, fast: bool = False,
               parallel: bool = True) -> None:
    """Write every item to a temporary file (``parallel``: several at once, the encoders
    release the GIL), then rename them all into place; ``durable``: each file and the
    directory are flushed to disk first."""
    tmps: list[Path | None] = [None] * len(items)
    try:
        def one(i: int) -> None:
            p, data, pixel_type = items[i]
            tmps[i] = _write_tmp(p, data, pixel_type, metadata, durable, fast)

        if len(items) > 1 and parallel:
            with ThreadPoolExecutor(max_workers=min(len(items), _WRITERS)) as pool:
                list(pool.map(one, range(len(items))))
        else:
            for i in range(len(items)):
                one(i)
    except BaseException:
        for t in tmps:
            if t is not None:
                t.unlink(missing_ok=True)
        raise
    done = 0
    try:
        for t, (p, _, _) in zip(tmps, items, strict=True):
            assert t is not None
            os.replace(t, p)
            done += 1
        if items and durable:
            fsync_dir(items[0][0].parent)
    except OSError as exc:
        for t in tmps[done:]:
            if t is not None:
                t.unlink(missing_ok=True)
        raise ImageError(f"{items[done][0]}: cannot replace the file ({exc.strerror}).") from None


def _check_metadata(metadata: Mapping[str, str] | None) -> Mapping[str, str]:
    if metadata is None:
        return {}
    if not isinstance(metadata, Mapping) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in metadata.items()
    ):
        raise ValueError("metadata must be a mapping of str attribute names to str values.")
    return metadata


def write_image(
    path: str | os.PathLike[str],
    image: ArrayLike,
    *,
    half: bool = True,
    metadata: Mapping[str, str] | None = None,
    durable: bool = True,
    fast: bool = False,
) -> Path:
    """Write one image atomically.

    Parameters
    ----------
    path : str or Path
        ``.exr``, ``.hdr``, ``.pfm``, ``.tif``, ``.tiff`` or ``.png``; its directory must exist.
    image : (H, W), (H, W, 1) or (H, W, 3) float
        Linear values (a ``uint8`` array for ``.png`` is written as is: already encoded).
    half : bool
        Prefer half-float EXR (default) to float32. Only ``.exr`` stores half: ``.tif``,
        ``.tiff`` and ``.pfm`` are always float32, ``.hdr`` RGBE and ``.png`` 8-bit, whatever
        ``half`` says. An EXR with a finite ``|value| > 65504`` (:data:`HALF_MAX`, beyond
        which half overflows to inf) is written as float32 instead.
    metadata : mapping of str to str, optional
        String attributes stored in an EXR header (other formats have no place for them and
        ignore them).
    durable : bool
        Flush the file and its directory entry to disk before returning (default). A caller
        that flushes a whole staging folder before publishing it passes False.
    fast : bool
        ``.png`` only: the quickest compression (zlib level 1, the "sub" row filter), ~5x
        faster in a file ~15 % larger with the same pixels (previews); other formats ignore it.

    Returns
    -------
    Path
        The written file; :func:`stored_pixel_type` tells the pixel type it got.
    """
    p = Path(path)
    data, pixel_type = _prepare(p, image, half)
    _write_all([(p, data, pixel_type)], _check_metadata(metadata), durable, fast)
    return p


def write_cube(
    path_stem: str | os.PathLike[str],
    faces: ArrayLike,
    *,
    layout: CubeLayout = "faces",
    fmt: ImageFormat = "exr",
    half: bool = True,
    metadata: Mapping[str, str] | None = None,
    durable: bool = True,
    parallel: bool = True,
) -> WrittenFiles:
    """Write a cube map atomically as six face files, a cross or an equirect image.

    Parameters
    ----------
    path_stem : str or Path
        Output name without extension: ``<stem>_px.<fmt>``... for ``"faces"``, else
        ``<stem>.<fmt>``.
    faces : (6, n, n, 3) float
    layout : {"faces", "hcross", "vcross", "equirect"}
        Equirect images have :func:`probegrid.core.layouts.from_cube`'s default size ``4n x 2n``.
    fmt : {"exr", "hdr"}
    half : bool
        Prefer half-float EXR (default) to float32; ignored for ``"hdr"`` (always RGBE). If a
        finite texel of any face exceeds 65504 (:data:`HALF_MAX`) in magnitude, every file of
        the cube is written as float32 instead, so the maps never hold inf for a bright sun.
    metadata : mapping of str to str, optional
        EXR header attributes (ignored for ``"hdr"``).
    durable : bool
        As :func:`write_image`.
    parallel : bool
        Encode the files in threads at once (default); False encodes them one after the other
        in the calling thread, for a caller that writes several cubes at once itself.

    Returns
    -------
    WrittenFiles
        The written files (six, in face order, for ``"faces"``), a list of Path whose
        ``pixel_type`` is the type they were stored in: ``"half"`` or ``"float"`` for EXR,
        ``"rgbe"`` for ``"hdr"``.
    """
    if layout not in _CUBE_LAYOUTS:
        raise ValueError(
            f"unknown cube layout {layout!r}; choose one of "
            f"{', '.join(repr(x) for x in _CUBE_LAYOUTS)}."
        )
    if fmt not in _CUBE_FORMATS:
        raise ValueError(
            f"unknown cube format {fmt!r}; choose one of "
            f"{', '.join(repr(x) for x in _CUBE_FORMATS)}."
        )
    a = check_cube(faces, name="faces")
    stem = str(path_stem)
    if layout == "faces":
        images: list[tuple[Path, NDArray]] = [
            (Path(f"{stem}{suffix}.{fmt}"), a[f]) for f, suffix in enumerate(FACE_SUFFIXES)
        ]
    else:
        images = [(Path(f"{stem}.{fmt}"), from_cube(a, layout))]
    items = [(p, *_prepare(p, im, half)) for p, im in images]
    types = {t for _, _, t in items}
    if types == {"half", "float"}:  # some face overflows half: one pixel type per cube
        items = [(p, data, "float") for p, data, _ in items]
    _write_all(items, _check_metadata(metadata), durable, parallel=parallel)
    return WrittenFiles([p for p, _ in images], items[0][2])


def stored_pixel_type(path: str | os.PathLike[str]) -> PixelType:
    """The pixel type an image file is stored in, read from its header.

    Returns
    -------
    {"half", "float", "rgbe", "uint8"}
        ``"rgbe"`` for a Radiance ``.hdr``; ``"float"`` for 32-bit float (EXR, TIFF, PFM).

    Raises
    ------
    ImageError
        A missing or unreadable file, or one whose pixel type is none of the four (e.g. a
        16-bit integer PNG).
    """
    p = _check_readable(path)
    inp = _open(p)
    try:
        fmt = inp.spec().format
        if inp.format_name() == "hdr":
            return "rgbe"
    finally:
        inp.close()
    # TypeDesc comparison: the bindings' BASETYPE.UINT8 and .UCHAR are unequal aliases
    if fmt == oiio.TypeHalf:
        return "half"
    if fmt == oiio.TypeFloat:
        return "float"
    if fmt == oiio.TypeUInt8:
        return "uint8"
    raise ImageError(f"{p}: pixel type {fmt} is none of {', '.join(PIXEL_TYPES)}.")


# --------------------------------------------------------------------------------------------
# Previews


def cube_exposure(faces: ArrayLike) -> float:
    """Automatic exposure (stops) of a cube map: its solid-angle-weighted log-average luminance
    maps to the key 0.18 (as :func:`tonemap_preview` does for images)."""
    cube = check_cube(faces, name="cube")
    w = np.broadcast_to(texel_solid_angles(cube.shape[1])[..., None], cube.shape[:3] + (1,))
    return auto_exposure(cube[..., :3].reshape(-1, 3).astype(np.float64), w.reshape(-1))


def write_preview_png(
    path: str | os.PathLike[str],
    image_or_cube: ArrayLike,
    *,
    layout: Literal["hcross", "vcross", "equirect", "angular"] = "hcross",
    exposure: float | None = None,
    durable: bool = True,
) -> Path:
    """Write an 8-bit PNG preview of an image or a cube map (atomically), tone-mapped by its
    own statistics (:func:`probegrid.core.color.tonemap_adaptive`).

    Parameters
    ----------
    path : str or Path
        Must end in ``.png``.
    image_or_cube : (H, W, 3) or (6, n, n, 3) float
        Linear radiance. A cube is laid out in ``layout`` (cross cells without a face black) and
        its automatic exposure is computed from the texels weighted by solid angle.
    layout : {"hcross", "vcross", "equirect", "angular"}
        Layout of a cube's preview (ignored for an image).
    exposure : float, optional
        Stops (the radiance is multiplied by ``2**exposure`` before the shoulder); default
        automatic, from the image's (the cube's texels', by solid angle) log-average.
    durable : bool
        As :func:`write_image`.

    Returns
    -------
    Path
    """
    p = Path(path)
    if p.suffix.lower() != ".png":
        raise ValueError(f"a preview must be a .png file, got {p.name!r}.")
    allowed = ("hcross", "vcross", "equirect", "angular")
    if layout not in allowed:
        raise ValueError(
            f"unknown preview layout {layout!r}; choose one of {', '.join(map(repr, allowed))}."
        )
    a = np.asarray(image_or_cube, dtype=np.float32)
    if a.ndim == 4:
        cube = check_cube(a, name="cube")
        if cube.shape[3] != 3:
            raise ValueError(f"a preview cube must have 3 channels, got {cube.shape[3]}.")
        if exposure is None:
            exposure = cube_exposure(cube)
        a = from_cube(cube, layout)
    elif a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(
            f"a preview needs an (H, W, 3) image or a (6, n, n, 3) cube, got {a.shape}."
        )
    return write_image(p, tonemap_adaptive(a, exposure=exposure), durable=durable, fast=True)
