"""Environment-map layouts and anti-aliased resampling between them and cube maps.

Array math only: no file I/O (reading and writing images is :mod:`probegrid.imageio`).

Layouts
-------
All directions are in the glTF world frame (right-handed, +Y up); cube faces follow
:mod:`probegrid.core.cubemap` (order ``+X, -X, +Y, -Y, +Z, -Z``, row 0 = top, the KTX2 face table).
Images are ``(H, W, C)`` arrays with row 0 at the top and column 0 at the left.

``"equirect"`` -- latitude-longitude, ``W = 2 H`` (the three.js / glTF-IBL convention).
    Column ``x`` and row ``y`` have their centres at longitude and latitude::

        phi   = 2 pi ((x + 0.5) / W - 0.5)          in (-pi, pi)
        theta = pi (0.5 - (y + 0.5) / H)            in (-pi/2, pi/2)
        d     = (cos phi cos theta,  sin theta,  sin phi cos theta)

    so the centre column looks along +X, a quarter of the width to the right of it along +Z,
    the left and right edges along -X, a quarter to the left along -Z, the top row is +Y and
    the bottom row -Y. Inverse: ``phi = atan2(dz, dx)``, ``theta = atan2(dy, hypot(dx, dz))``.

``"angular"`` -- Debevec's angular map (light probe), a square ``S x S`` image holding the
    disk of radius 1 in image coordinates ``u`` (right) and ``v`` (up), ``[-1, 1]`` across the
    image::

        u = dx r,   v = dy r,   r = acos(dz) / (pi sqrt(dx^2 + dy^2))

    The image centre is +Z, the rim (radius 1) is -Z, image right is +X and image up is +Y
    (what a camera on the +Z axis sees in a mirror ball, so it is the mirror image of a view
    from the centre toward +Z, whose right is -X);
    the radius is proportional to the angle from +Z (an azimuthal equidistant projection), so
    ``radius 1/2`` is the great circle ``z = 0``. Pixel centres outside the disk hold no
    direction: :func:`from_cube` writes 0 there and :func:`to_cube` never reads them. The rim
    is singular (a whole circle is one direction): lookups are pulled inside radius
    ``1 - sqrt(2) / S`` so that they always have a valid pixel, which blurs the last ~1.3
    pixels of the disk (directions within ``sqrt(2) pi / S`` radians of -Z).

``"hcross"`` -- horizontal cross, ``4n x 3n`` (W x H), every face upright as stored::

            +----+
            | +Y |
       +----+----+----+----+
       | -X | +Z | +X | -Z |
       +----+----+----+----+
            | -Y |
            +----+

``"vcross"`` -- vertical cross, ``3n x 4n`` (W x H), the HDRShop / cmft convention: the
    faces as in the horizontal cross except that -Z hangs below -Y *rotated by 180 degrees*
    (so its edges meet the -Y face's bottom edge seamlessly)::

            +----+
            | +Y |
       +----+----+----+
       | -X | +Z | +X |
       +----+----+----+
            | -Y |
            +----+
            |-Z* |   (* rotated 180 degrees: stored face[::-1, ::-1])
            +----+

    Cells of a cross not covered by a face are 0.

``"faces"`` -- six separate ``n x n`` images in the order ``+X, -X, +Y, -Y, +Z, -Z``, given
    and returned as one ``(6, n, n, C)`` array.

Resampling
----------
:func:`to_cube` gives each output texel the *mean radiance over its solid angle* (box filter
on the sphere), not a point sample, so any output size is alias-free. The mean is estimated
by supersampling: each texel is split into ``k x k`` equal sub-texels in ``(u, v)``, the source
is looked up (bilinearly) at their centres, and the lookups are averaged with the sub-texels'
exact solid angles (Girard's corner formula, see :mod:`probegrid.core.cubemap`) as weights.
``k = ceil(2 texel angle / source pixel angle)`` (texel angle ``2 / n`` at the face centre;
pixel angle ``pi / H`` for equirect, the radial ``2 pi / S`` for angular maps), so the
sub-samples are at most half a source pixel apart and integrate the bilinear reconstruction
accurately: every source pixel contributes (up to its bilinear tent) with its own solid angle.
With spacing of a whole pixel the mean of the Venice HDR, whose sun covers ~7 pixels, was off
by 0.24 %; with half a pixel by < 0.09 %. The cost is about ``6 (4 H / pi)^2``, some 5 times
the source pixel count, whatever ``n``. Magnification (``k = 1``) is plain bilinear
interpolation at texel centres. Equirect lookups wrap in longitude and, across a
pole, interpolate with the row on the other side of the pole (column ``x + W / 2``).

Equirect inputs take a faster route to the same quantity (:func:`_equirect_to_cube`, ~0.18 s
CPU instead of ~0.5 s for 1024 x 512 -> 128^2): on the four side faces the longitude depends
on ``u`` alone, so each of the ``k`` sub-columns of a texel is a meridian segment along which
the bilinear reconstruction is linear in latitude between pixel-row centres; its integral
against ``cos(theta) d theta`` between the texel's edges is exact (running sums plus the partial
pieces' closed form), and the sub-columns are weighted by their longitude widths (the midpoint
rule in longitude only). Against a 4 x denser supersampling this is closer than the ``k x k``
lookups (``tests/test_layouts_fast.py``). The polar faces keep the ``k x k`` lookups, with their
angles computed once for both (mirror images) and each channel gathered from a padded plane.
Angular maps take the ``k x k`` lookups with planar gathers too (:func:`_angular_to_cube`).
Near the poles a pixel is narrower than ``pi / H`` in longitude (by ``cos(theta)``), so there
the lookups resolve the pixels' tents less well than elsewhere.
Cube -> cube (crosses and ``faces``) is :func:`probegrid.core.sampling.resample`: the exact
box-filtered mip when the size halves, otherwise the same supersampling with seamless cube
lookups.

:func:`from_cube` does the converse: a target pixel is the solid-angle-weighted mean of
``k x k`` seamless bilinear cube lookups, ``k = ceil(2 pixel angle / texel angle)``
(sub-pixel weights: ``dphi (sin theta1 - sin theta0)`` for equirect, the
Jacobian ``pi sin(pi rho) / rho`` of the angular map at radius ``rho``).

Non-finite source values propagate (as NaN/inf) only into the output texels whose footprint
covers them. Texels are float32; geometry and accumulation are float64. Work is chunked so
that no step holds more than about ``2**18`` samples.

References
----------
* P. Debevec, "Light Probe Image Gallery" (angular map formula), https://www.pauldebevec.com/Probes/
* three.js ``equirectUv`` / Khronos glTF-IBL-Sampler (lat-long orientation).
* M. Driscoll, "Cubemap texel solid angle", 2012 (corner formula).
* cmft (D. Gavrilovic), HDRShop: vertical cross with -Z rotated.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Final, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._types import CrossLayout, Layout
from probegrid.core.cubemap import FACE_NORMALS, FACE_U, FACE_V, check_cube
from probegrid.core.sampling import CubeSampler, resample

__all__ = [
    "LAYOUTS",
    "Layout",
    "angular_directions",
    "cross_to_faces",
    "default_face_size",
    "detect_layout",
    "direction_to_angular",
    "direction_to_equirect",
    "equirect_directions",
    "faces_to_cross",
    "from_cube",
    "layout_shape",
    "sample_angular",
    "sample_equirect",
    "to_cube",
]

#: The allowed layout names.
LAYOUTS: Final[tuple[str, ...]] = get_args(Layout)


#: Largest cube face size whose equirect resampling runs its two parts in two threads.
_THREADED_MAX: Final[int] = 128

#: Upper bound on the number of sub-samples looked up at once.
_CHUNK_SAMPLES: Final[int] = 1 << 18

#: (face, cell row, cell column, rotated 180 degrees) of each cross, in face order.
_CROSS_CELLS: Final[dict[str, tuple[tuple[int, int, bool], ...]]] = {
    "hcross": ((1, 2, False), (1, 0, False), (0, 1, False), (2, 1, False), (1, 1, False),
               (1, 3, False)),
    "vcross": ((1, 2, False), (1, 0, False), (0, 1, False), (2, 1, False), (1, 1, False),
               (3, 1, True)),
}
#: Cross grid size in faces (rows, columns).
_CROSS_GRID: Final[dict[str, tuple[int, int]]] = {"hcross": (3, 4), "vcross": (4, 3)}

Sampler = Callable[[NDArray[np.float64]], NDArray[np.floating]]


# --------------------------------------------------------------------------------------------
# Argument checks


def _check_layout(layout: str) -> None:
    if layout not in LAYOUTS:
        raise ValueError(
            f"unknown layout {layout!r}; choose one of {', '.join(repr(x) for x in LAYOUTS)}."
        )


def _check_positive(name: str, value: int) -> int:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}.")
    return int(value)


def _check_image(image: ArrayLike) -> NDArray[np.float32]:
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[0] < 1 or a.shape[1] < 1 or a.shape[2] < 1:
        raise ValueError(f"image must have shape (H, W, C), got {a.shape}.")
    return np.asarray(a, dtype=np.float32)


# --------------------------------------------------------------------------------------------
# Layout detection and sizes


def detect_layout(height: int, width: int) -> Layout:
    """Layout of a single image from its aspect ratio.

    ``W = 2 H`` -> ``"equirect"``, ``3 W = 4 H`` -> ``"hcross"``, ``4 W = 3 H`` -> ``"vcross"``,
    ``W = H`` -> ``"angular"`` (the only square single-image layout this project reads; a
    mirror-ball photograph is also square and would be misread, so convert those first).
    The ratios must be exact.

    Raises
    ------
    ValueError
        For any other aspect ratio, asking for an explicit layout.
    """
    h = _check_positive("height", height)
    w = _check_positive("width", width)
    if w == 2 * h:
        return "equirect"
    if w == h:
        return "angular"
    if 3 * w == 4 * h:  # then w = 4n and h = 3n
        return "hcross"
    if 4 * w == 3 * h:
        return "vcross"
    raise ValueError(
        f"cannot detect the layout of a {w}x{h} (W x H) image from its aspect ratio "
        "(2:1 equirect, 1:1 angular, 4:3 hcross, 3:4 vcross); give the layout explicitly."
    )


def _round_pow2(x: float) -> int:
    return 1 << max(0, round(math.log2(max(x, 1.0))))


def default_face_size(height: int, width: int, layout: Layout) -> int:
    """Cube face size that matches the resolution of a source image, rounded to a power of two.

    ``equirect``: ``W / 4`` (as many texels around the equator as the image has columns);
    ``angular``: ``S / pi`` (a texel's angle at a face centre equals a pixel's radial angle);
    crosses and ``faces``: the face size. The value is rounded to the nearest power of two in
    log2 (ties up), e.g. 1024 x 512 equirect -> 256, 1000 x 1000 angular -> 256.
    """
    _check_layout(layout)
    h = _check_positive("height", height)
    w = _check_positive("width", width)
    if layout == "equirect":
        n = w / 4
    elif layout == "angular":
        n = w / math.pi
    elif layout == "hcross":
        n = w / 4
    elif layout == "vcross":
        n = w / 3
    else:
        n = min(h, w)
    return _round_pow2(n)


def layout_shape(layout: Layout, size: int) -> tuple[int, int]:
    """Image shape ``(H, W)`` of a layout of the given size.

    ``size`` is the face size for crosses and ``faces`` (for which the shape of *one* face is
    returned), the height for ``equirect`` (``W = 2 H``) and the side for ``angular``.
    """
    _check_layout(layout)
    s = _check_positive("size", size)
    if layout == "equirect":
        return s, 2 * s
    if layout in ("hcross", "vcross"):
        rows, cols = _CROSS_GRID[layout]
        return rows * s, cols * s
    return s, s


# --------------------------------------------------------------------------------------------
# Equirect geometry


def _equirect_dir(phi: NDArray[np.float64], theta: NDArray[np.float64]) -> NDArray[np.float64]:
    ct = np.cos(theta)
    return np.stack(np.broadcast_arrays(np.cos(phi) * ct, np.sin(theta), np.sin(phi) * ct), -1)


def equirect_directions(height: int, width: int) -> NDArray[np.float64]:
    """Unit directions of the pixel centres of an equirect image.

    Returns
    -------
    (H, W, 3) float64
    """
    h = _check_positive("height", height)
    w = _check_positive("width", width)
    phi = 2.0 * np.pi * ((np.arange(w) + 0.5) / w - 0.5)
    theta = np.pi * (0.5 - (np.arange(h) + 0.5) / h)
    return _equirect_dir(phi[None, :], theta[:, None])


def direction_to_equirect(
    directions: ArrayLike, height: int, width: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Continuous pixel coordinates of directions in an equirect image.

    Parameters
    ----------
    directions : (..., 3) float
        Need not be normalised (the zero vector maps to the centre pixel's direction +X).
    height, width : int

    Returns
    -------
    x, y : (...) float64
        Column in ``[-0.5, W - 0.5)`` and row in ``[-0.5, H - 0.5]``; pixel ``(y, x)`` has its
        centre at the integers.
    """
    d = np.asarray(directions, dtype=np.float64)
    if d.shape[-1:] != (3,):
        raise ValueError(f"directions must have shape (..., 3), got {d.shape}.")
    h = _check_positive("height", height)
    w = _check_positive("width", width)
    phi = np.arctan2(d[..., 2], d[..., 0])
    theta = np.arctan2(d[..., 1], np.hypot(d[..., 0], d[..., 2]))
    x = (phi / (2.0 * np.pi) + 0.5) * w - 0.5
    y = (0.5 - theta / np.pi) * h - 0.5
    return x, y


def sample_equirect(image: ArrayLike, directions: ArrayLike) -> NDArray[np.float32]:
    """Bilinear lookup of an equirect image, wrapping in longitude and across the poles.

    Across the top (bottom) edge the neighbour of row 0 (``H - 1``) at column ``x`` is the same
    row at column ``x + W / 2``: the pixel on the other side of the pole.

    Parameters
    ----------
    image : (H, W, C) float, ``W`` even
    directions : (..., 3) float, need not be normalised

    Returns
    -------
    (..., C) float32
    """
    img = _check_image(image)
    h, w, _ = img.shape
    if w % 2:
        raise ValueError(f"an equirect image needs an even width for pole lookups, got {w}.")
    x, y = direction_to_equirect(directions, h, w)
    return _equirect_bilinear(img, x, y).astype(np.float32)


def _equirect_bilinear(
    img: NDArray[np.float32], x: NDArray[np.float64], y: NDArray[np.float64]
) -> NDArray[np.float64]:
    h, w, c = img.shape
    flat = img.reshape(h * w, c)
    x0 = np.floor(x)
    y0 = np.clip(np.floor(y), -1, h - 1)
    tx = (x - x0)[..., None]
    ty = np.clip(y - y0, 0.0, 1.0)[..., None]
    x0 = x0.astype(np.intp)
    y0 = y0.astype(np.intp)
    half = w // 2

    def fetch(yy: NDArray[np.intp], xx: NDArray[np.intp]) -> NDArray[np.float32]:
        over = (yy < 0) | (yy >= h)  # across a pole: same edge row, opposite meridian
        xx = np.where(over, xx + half, xx) % w
        yy = np.clip(yy, 0, h - 1)
        return flat[yy * w + xx]

    top = fetch(y0, x0) * (1.0 - tx) + fetch(y0, x0 + 1) * tx
    bottom = fetch(y0 + 1, x0) * (1.0 - tx) + fetch(y0 + 1, x0 + 1) * tx
    return top * (1.0 - ty) + bottom * ty


class _EquirectLookup:
    """:func:`_equirect_bilinear` at directions, for the many lookups of :func:`to_cube`.

    The same bilinear interpolation with the same wrap (longitude) and pole rule (across the
    top or bottom edge, the same row at the opposite meridian), but on a copy of the image
    padded by one pixel on every side that already holds those neighbours, so a footprint is
    four plain gathers; angles are computed in float32 (pixel coordinates to ~1e-4 pixel).
    """

    def __init__(self, img: NDArray[np.float32]) -> None:
        h, w, c = img.shape
        if w % 2:
            raise ValueError(f"an equirect image needs an even width for pole lookups, got {w}.")
        rows = np.concatenate([np.roll(img[:1], -(w // 2), axis=1), img,
                               np.roll(img[-1:], -(w // 2), axis=1)], axis=0)   # (h + 2, w, c)
        pad = np.concatenate([rows[:, -1:], rows, rows[:, :1]], axis=1)        # (h + 2, w + 2, c)
        self._flat = np.ascontiguousarray(pad.reshape(-1, c), dtype=np.float32)
        self._h, self._w = h, w

    def __call__(self, d: NDArray[np.float64]) -> NDArray[np.float32]:
        h, w = self._h, self._w
        d32 = d.astype(np.float32)
        dx, dy, dz = d32[..., 0], d32[..., 1], d32[..., 2]
        x = np.arctan2(dz, dx) * np.float32(w / (2.0 * np.pi)) + np.float32(0.5 * w - 0.5)
        y = (np.float32(0.5 * h - 0.5)
             - np.arctan2(dy, np.hypot(dx, dz)) * np.float32(h / np.pi))
        x0 = np.floor(x)
        y0 = np.floor(y)
        tx = (x - x0)[..., None]
        ty = (y - y0)[..., None]
        # padded coordinates: column x0 + 1 in [0, w], row y0 + 1 in [0, h]
        i00 = ((y0.astype(np.intp) + 1) * (w + 2) + x0.astype(np.intp) + 1)
        f = self._flat
        top = np.take(f, i00, axis=0) * (1 - tx) + np.take(f, i00 + 1, axis=0) * tx
        i10 = i00 + (w + 2)
        bottom = np.take(f, i10, axis=0) * (1 - tx) + np.take(f, i10 + 1, axis=0) * tx
        return top * (1 - ty) + bottom * ty


# --------------------------------------------------------------------------------------------
# Angular-map geometry


def _angular_uv_to_dir(u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    # angle from +Z is pi rho; the lateral part (u, v) / rho scaled by sin(pi rho)
    rho = np.hypot(u, v)
    s = np.where(rho > 0, np.sin(np.pi * rho) / np.where(rho > 0, rho, 1.0), np.pi)
    return np.stack(np.broadcast_arrays(u * s, v * s, np.cos(np.pi * rho)), -1)


def angular_directions(size: int) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Unit directions of the pixel centres of an ``S x S`` angular map.

    Returns
    -------
    directions : (S, S, 3) float64
        Unit vectors; for pixels whose centre lies outside the disk, the direction of the
        mirrored radius ``2 - rho`` (meaningless, but finite).
    inside : (S, S) bool
        Whether the pixel centre lies in the disk (radius <= 1).
    """
    s = _check_positive("size", size)
    c = (np.arange(s) + 0.5) * (2.0 / s) - 1.0
    u = c[None, :]
    v = -c[:, None]
    u, v = np.broadcast_arrays(u, v)
    d = _angular_uv_to_dir(u, v)
    return d, np.hypot(u, v) <= 1.0


def direction_to_angular(
    directions: ArrayLike, size: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Continuous pixel coordinates ``(x, y)`` (column, row) of directions in an angular map.

    Parameters
    ----------
    directions : (..., 3) float
        Need not be normalised. -Z (and the zero vector's neighbourhood) maps to the bottom of
        the rim.
    size : int
        Side ``S`` of the map.

    Returns
    -------
    x, y : (...) float64, pixel centres at the integers.
    """
    d = np.asarray(directions, dtype=np.float64)
    if d.shape[-1:] != (3,):
        raise ValueError(f"directions must have shape (..., 3), got {d.shape}.")
    s = _check_positive("size", size)
    u, v = _direction_to_angular_uv(d)
    return (u + 1.0) * (0.5 * s) - 0.5, (1.0 - v) * (0.5 * s) - 0.5


def _direction_to_angular_uv(
    d: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    lateral = np.hypot(d[..., 0], d[..., 1])
    rho = np.arctan2(lateral, d[..., 2]) / np.pi  # angle from +Z over pi, in [0, 1]
    safe = np.where(lateral > 0, lateral, 1.0)
    u = np.where(lateral > 0, d[..., 0] / safe, 0.0) * rho
    v = np.where(lateral > 0, d[..., 1] / safe, -1.0) * rho
    return u, v


def sample_angular(image: ArrayLike, directions: ArrayLike) -> NDArray[np.float32]:
    """Bilinear lookup of an angular map using only pixels whose centres lie in the disk.

    The bilinear weights of pixels outside the disk are dropped and the rest renormalised;
    lookups are first pulled inside radius ``1 - sqrt(2) / S`` so at least one is valid.

    Parameters
    ----------
    image : (S, S, C) float
    directions : (..., 3) float, need not be normalised

    Returns
    -------
    (..., C) float32
    """
    img = _check_image(image)
    if img.shape[0] != img.shape[1]:
        raise ValueError(f"an angular map must be square, got {img.shape[1]}x{img.shape[0]}.")
    d = np.asarray(directions, dtype=np.float64)
    if d.shape[-1:] != (3,):
        raise ValueError(f"directions must have shape (..., 3), got {d.shape}.")
    return _angular_bilinear(img, d).astype(np.float32)


def _angular_bilinear(img: NDArray[np.float32], d: NDArray[np.float64]) -> NDArray[np.float64]:
    s, _, c = img.shape
    u, v = _direction_to_angular_uv(d)
    rho = np.hypot(u, v)
    rmax = max(1.0 - math.sqrt(2.0) / s, 0.0)
    scale = np.where(rho > rmax, rmax / np.where(rho > 0, rho, 1.0), 1.0)
    x = (u * scale + 1.0) * (0.5 * s) - 0.5
    y = (1.0 - v * scale) * (0.5 * s) - 0.5
    centres = (np.arange(s) + 0.5) * (2.0 / s) - 1.0
    inside = (centres[None, :] ** 2 + centres[:, None] ** 2 <= 1.0).ravel()
    flat = img.reshape(s * s, c).astype(np.float64)
    x0 = np.floor(x)
    y0 = np.floor(y)
    tx = x - x0
    ty = y - y0
    x0 = x0.astype(np.intp)
    y0 = y0.astype(np.intp)
    acc = np.zeros(d.shape[:-1] + (c,))
    wsum = np.zeros(d.shape[:-1])
    for dy, wy in ((0, 1.0 - ty), (1, ty)):
        for dx, wx in ((0, 1.0 - tx), (1, tx)):
            yy = np.clip(y0 + dy, 0, s - 1)
            xx = np.clip(x0 + dx, 0, s - 1)
            idx = yy * s + xx
            wgt = wx * wy * inside[idx]
            # weight 0 must not turn an unused out-of-disk inf/nan into nan
            acc += np.where(wgt[..., None] > 0, flat[idx], 0.0) * wgt[..., None]
            wsum += wgt
    return acc / wsum[..., None]


# --------------------------------------------------------------------------------------------
# Crosses


def cross_to_faces(image: ArrayLike, layout: CrossLayout) -> NDArray[np.float32]:
    """Cut the six faces out of a cross (exact, no resampling).

    Parameters
    ----------
    image : (3n, 4n, C) for ``"hcross"`` or (4n, 3n, C) for ``"vcross"``
    layout : {"hcross", "vcross"}

    Returns
    -------
    (6, n, n, C) float32
    """
    if layout not in _CROSS_GRID:
        raise ValueError(f"unknown cross layout {layout!r}; choose 'hcross' or 'vcross'.")
    img = _check_image(image)
    rows, cols = _CROSS_GRID[layout]
    h, w = img.shape[:2]
    n = w // cols
    if n < 1 or w != cols * n or h != rows * n:
        raise ValueError(
            f"a {layout} image must be {cols}n x {rows}n (W x H), got {w}x{h}."
        )
    out = np.empty((6, n, n, img.shape[2]), dtype=np.float32)
    for f, (r, col, rotated) in enumerate(_CROSS_CELLS[layout]):
        cell = img[r * n:(r + 1) * n, col * n:(col + 1) * n]
        out[f] = cell[::-1, ::-1] if rotated else cell
    return out


def faces_to_cross(faces: ArrayLike, layout: CrossLayout) -> NDArray[np.float32]:
    """Lay six faces out as a cross (exact, no resampling); uncovered cells are 0.

    Parameters
    ----------
    faces : (6, n, n, C) float
    layout : {"hcross", "vcross"}

    Returns
    -------
    (3n, 4n, C) or (4n, 3n, C) float32
    """
    if layout not in _CROSS_GRID:
        raise ValueError(f"unknown cross layout {layout!r}; choose 'hcross' or 'vcross'.")
    a = check_cube(faces, name="faces")
    n, c = a.shape[1], a.shape[3]
    rows, cols = _CROSS_GRID[layout]
    out = np.zeros((rows * n, cols * n, c), dtype=np.float32)
    for f, (r, col, rotated) in enumerate(_CROSS_CELLS[layout]):
        out[r * n:(r + 1) * n, col * n:(col + 1) * n] = a[f, ::-1, ::-1] if rotated else a[f]
    return out


# --------------------------------------------------------------------------------------------
# Supersampled integration


def _corner(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    # Girard / Driscoll: solid angle of [0, x] x [0, y] on the face plane at distance 1
    # (the same formula as probegrid.core.cubemap's texel solid angles).
    return np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))


def _cell_solid_angles(u_edges: NDArray[np.float64], v_edges: NDArray[np.float64]
                       ) -> NDArray[np.float64]:
    """Exact solid angles of the face cells between consecutive ``u`` and ``v`` edges:
    ``(len(v_edges) - 1, len(u_edges) - 1)``, rows along ``v``."""
    u, v = u_edges[None, :], v_edges[:, None]
    return (_corner(u[:, 1:], v[1:]) - _corner(u[:, :-1], v[1:])
            - _corner(u[:, 1:], v[:-1]) + _corner(u[:, :-1], v[:-1]))



def _sub_texel_grid(n: int, k: int) -> tuple[int, NDArray[np.float64], NDArray[np.float64],
                                              NDArray[np.float64], NDArray[np.float32]]:
    """A face of ``n`` texels cut into ``k x k`` sub-texels: their count per side, edges and
    centres (face coordinates), each texel's solid angle (the sum of its sub-texels') and the
    sub-texels' solid angles as float32 weights."""
    fine = n * k
    edges = np.arange(fine + 1) * (2.0 / fine) - 1.0
    cen = 0.5 * (edges[:-1] + edges[1:])
    wgt = _cell_solid_angles(edges, edges)
    den = wgt.reshape(n, k, n, k).sum(axis=(1, 3))
    return fine, edges, cen, den, wgt.astype(np.float32)

def _rows_per_chunk(row_samples: int) -> int:
    return max(1, _CHUNK_SAMPLES // max(row_samples, 1))


def _block_mean(
    values: NDArray[np.float64], weights: NDArray[np.float64], k: int
) -> NDArray[np.float64]:
    """Weighted mean over k x k blocks of a (rows k, cols k, C) grid."""
    r, c, ch = values.shape[0] // k, values.shape[1] // k, values.shape[2]
    wv = np.where(weights[..., None] > 0, values, 0.0) * weights[..., None]
    num = wv.reshape(r, k, c, k, ch).sum(axis=(1, 3))
    den = weights.reshape(r, k, c, k).sum(axis=(1, 3))[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


def _integrate_cube(sample: Sampler, size: int, k: int, channels: int) -> NDArray[np.float32]:
    """Solid-angle mean of ``sample`` over every texel of a ``size`` cube (k x k supersampling)."""
    fine = size * k
    edges = np.arange(fine + 1) * (2.0 / fine) - 1.0
    centres = 0.5 * (edges[:-1] + edges[1:])
    out = np.empty((6, size, size, channels), dtype=np.float32)
    step = _rows_per_chunk(fine * k)
    for r0 in range(0, size, step):
        r1 = min(size, r0 + step)
        ve = edges[r0 * k:r1 * k + 1]
        vc = centres[r0 * k:r1 * k]
        w = _cell_solid_angles(edges, ve)
        for f in range(6):
            d = (
                FACE_NORMALS[f]
                + centres[None, :, None] * FACE_U[f]
                + vc[:, None, None] * FACE_V[f]
            )
            vals = np.asarray(sample(d), dtype=np.float64)
            out[f, r0:r1] = _block_mean(vals, w, k)
    return out


def _hat_cos_integrals(t0: NDArray[np.float64], t1: NDArray[np.float64], t: NDArray[np.float64]
                       ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``int_{t0}^{t} h0 cos`` and ``int_{t0}^{t} h1 cos`` for the linear hats ``h0`` (1 at
    ``t0``, 0 at ``t1``) and ``h1 = 1 - h0``: with ``s = (x - t0) / (t1 - t0)``,
    ``int (1 - s) cos = [(1 - s) sin x - cos x / (t1 - t0)]`` and ``int s cos = [s sin x +
    cos x / (t1 - t0)]``."""
    inv = 1.0 / (t1 - t0)
    s = (t - t0) * inv
    st, ct, s0, c0 = np.sin(t), np.cos(t), np.sin(t0), np.cos(t0)
    h1 = (s * st + ct * inv) - c0 * inv
    h0 = (st - s0) - h1
    return h0, h1


def _equirect_side_faces(img: NDArray[np.float32], n: int, k: int, out: NDArray[np.float32]
                         ) -> None:
    """The four side faces (+X, -X, +Z, -Z) of :func:`_equirect_to_cube`, by line integrals.

    On a side face (``V = -Y``) the longitude depends on ``u`` alone, so each of the ``k n``
    sub-columns ``u_i`` of a face is a meridian segment: along it the bilinear reconstruction
    is the image interpolated horizontally at that longitude (``C_i``), linear in ``theta``
    between pixel-row centres, and ``int C_i cos(theta) d theta`` between the texel's top and
    bottom edges (``theta = atan2(-v, sqrt(1 + u^2))``, the same on the four faces) is exact:
    running sums of each piece's integral (float64) plus the partial piece at each edge, whose
    weights on the two nodes are geometry (:func:`_hat_cos_integrals`). A texel is the sum
    over its ``k`` sub-columns weighted by their longitude widths, over the same sum for 1 (its
    solid angle in this quadrature): exact in latitude, the midpoint rule in longitude.
    """
    h, w, c = img.shape
    fine = n * k
    theta_p = np.pi * (0.5 - (np.arange(h) + 0.5) / h)             # node p: pixel row centre
    u_edges = np.arange(fine + 1) * (2.0 / fine) - 1.0
    u = 0.5 * (u_edges[:-1] + u_edges[1:])
    v_edges = np.arange(n + 1) * (2.0 / n) - 1.0
    th = np.arctan2(-v_edges[None, :], np.sqrt(1.0 + u[:, None] ** 2))  # (fine, n + 1)
    y = (0.5 - th / np.pi) * h - 0.5                               # pixel-row coordinate
    # the rows a side face reaches (|theta| <= 45 degrees) and one more on each side
    lo = max(0, int(np.floor(y.min())) - 1)
    hi = min(h - 1, int(np.ceil(y.max())) + 1)
    seg = np.clip(np.floor(y).astype(np.intp), lo, hi - 1)         # piece [seg, seg + 1]
    h0, h1 = _hat_cos_integrals(theta_p[seg], theta_p[seg + 1], th)
    tp = theta_p[lo:hi + 1]
    p0, p1 = _hat_cos_integrals(tp[:-1], tp[1:], tp[1:])           # whole pieces
    # flat (row, sub-column) index of each edge's piece start, for the gathers below
    at = (seg - lo) * fine + np.arange(fine)[:, None]                # (fine, n + 1)
    den_e = -(np.sin(th[:, 1:]) - np.sin(th[:, :-1]))              # int cos over texel rows
    rows = img[lo:hi + 1]
    for f in (0, 1, 4, 5):
        nf, uf = FACE_NORMALS[f], FACE_U[f]
        phi_e = np.arctan2(nf[2] + u_edges * uf[2], nf[0] + u_edges * uf[0])
        dphi = np.abs(np.diff(np.unwrap(phi_e)))                   # sub-column widths
        x = (np.arctan2(nf[2] + u * uf[2], nf[0] + u * uf[0]) / (2.0 * np.pi) + 0.5) * w - 0.5
        x0 = np.floor(x)
        tx = (x - x0)[None, :, None]
        x0 = x0.astype(np.intp)
        col = (np.take(rows, x0 % w, axis=1) * (1.0 - tx)
               + np.take(rows, (x0 + 1) % w, axis=1) * tx)         # (rows, fine, c) f64
        piece = col[:-1] * p0[:, None, None] + col[1:] * p1[:, None, None]
        g = np.empty_like(col)  # running integral from node lo down to each node
        g[0] = 0.0
        g[1] = piece[0]
        for r in range(1, len(piece)):  # row by row (a cumsum down axis 0, cache-friendly)
            np.add(g[r], piece[r], out=g[r + 1])
        col = col.reshape(-1, c)
        gq = (np.take(g.reshape(-1, c), at, axis=0) + np.take(col, at, axis=0) * h0[..., None]
              + np.take(col, at + fine, axis=0) * h1[..., None])
        num = ((gq[:, :-1] - gq[:, 1:]) * dphi[:, None, None]).reshape(n, k, n, c).sum(axis=1)
        den = (den_e * dphi[:, None]).reshape(n, k, n).sum(axis=1)
        out[f] = (num / den[..., None]).transpose(1, 0, 2)


def _plane_bilinear(plane: NDArray[np.float32], i00: NDArray[np.intp], stride: int,
                    tx: NDArray[np.float32], ty: NDArray[np.float32]) -> NDArray[np.float32]:
    """Bilinear lookups in a flattened padded plane (rows of ``stride``): ``i00`` is the flat
    index of each lookup's top-left tap, ``tx, ty`` its weights toward the right and bottom."""
    top = np.take(plane, i00)
    top += (np.take(plane, i00 + 1) - top) * tx
    bot = np.take(plane, i00 + stride)
    bot += (np.take(plane, i00 + (stride + 1)) - bot) * tx
    top += (bot - top) * ty
    return top


def _equirect_polar_faces(img: NDArray[np.float32], n: int, k: int, out: NDArray[np.float32]
                          ) -> None:
    """The faces +Y and -Y of :func:`_equirect_to_cube`: ``k x k`` bilinear lookups per texel
    averaged with the sub-texels' exact solid angles (as :func:`_integrate_cube` with
    :class:`_EquirectLookup`). -Y is the mirror image of +Y (row ``j`` of -Y looks up the
    pixel coordinates of row ``k n - 1 - j`` of +Y, with the image row mirrored), so the angles
    are computed once; a lookup gathers each channel from a padded plane of the rows the face
    reaches."""
    h, w, c = img.shape
    half = w // 2
    _, _, cen, den, w32 = _sub_texel_grid(n, k)
    uu, vv = cen[None, :], cen[:, None]
    x = (np.arctan2(vv, uu) / (2.0 * np.pi) + 0.5) * w - 0.5       # +Y: d = (u, 1, v)
    y = (0.5 - np.arctan2(1.0, np.hypot(uu, vv)) / np.pi) * h - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    tx = (x - x0).astype(np.float32)
    ty = (y - y0).astype(np.float32)
    x0 = x0.astype(np.intp) + 1                                    # padded column
    y0 = y0.astype(np.intp) + 1                                    # padded row, >= 0
    rows = int(y0.max()) + 2                                       # padded rows +Y reaches
    for f in (2, 3):
        src = img if f == 2 else img[::-1]                         # -Y: the mirrored image
        # padded as _EquirectLookup: row -1 is row 0 at the opposite meridian, columns wrap
        part = np.concatenate([np.roll(src[:1], -half, axis=1), src[:rows - 1]])
        pad = np.concatenate([part[:, -1:], part, part[:, :1]], axis=1)   # (rows, w + 2, c)
        if f == 2:
            i00, ax, ay = y0 * (w + 2) + x0, tx, ty
        else:  # row j of -Y = row fine - 1 - j of +Y, its v negated: x from atan2(-v, u)
            i00, ax, ay = (y0 * (w + 2) + x0)[::-1], tx[::-1], ty[::-1]
        acc = np.zeros((n, n, c))
        for ch in range(c):
            top = _plane_bilinear(np.ascontiguousarray(pad[..., ch]).reshape(-1), i00, w + 2,
                                  ax, ay)
            top *= w32
            acc[..., ch] = top.reshape(n, k, n, k).sum(axis=(1, 3), dtype=np.float64)
        out[f] = acc / den[..., None]


def _equirect_to_cube(img: NDArray[np.float32], n: int, k: int) -> NDArray[np.float32]:
    """Equirect -> cube, each texel the solid-angle mean of the bilinear reconstruction (see
    the module docstring): the side faces by exact line integrals along meridians
    (:func:`_equirect_side_faces`), the polar faces by ``k x k`` lookups
    (:func:`_equirect_polar_faces`). Images with non-finite pixels (whose running sums would
    carry them down a whole meridian) and tiny ones take :func:`_integrate_cube`."""
    h, _, c = img.shape
    if h < 8 or not np.isfinite(img).all():
        return _integrate_cube(_EquirectLookup(img), n, k, c)
    out = np.empty((6, n, n, c), dtype=np.float32)
    if n > _THREADED_MAX:  # one part at a time: their temporaries would add up
        _equirect_side_faces(img, n, k, out)
        _equirect_polar_faces(img, n, k, out)
        return out
    # the two parts write different faces and spend their time in numpy calls that release
    # the GIL: the polar faces go to a second thread
    with ThreadPoolExecutor(max_workers=1) as pool:
        polar = pool.submit(_equirect_polar_faces, img, n, k, out)
        _equirect_side_faces(img, n, k, out)
        polar.result()
    return out


def _angular_to_cube(img: NDArray[np.float32], n: int, k: int) -> NDArray[np.float32]:
    """:func:`_integrate_cube` of :func:`_angular_bilinear`, faster: the lookups gather each
    channel from a zero-padded plane of ``L inside`` and one of ``inside`` (float32), a value is
    their bilinear ratio (the in-disk taps renormalised, as :func:`_angular_bilinear`), and the
    weighted block sums are float32 against float64 weights. Images with non-finite pixels in
    the disk take :func:`_integrate_cube` (a weight-0 tap must not turn inf into NaN there)."""
    s, _, c = img.shape
    centres = (np.arange(s) + 0.5) * (2.0 / s) - 1.0
    inside = centres[None, :] ** 2 + centres[:, None] ** 2 <= 1.0
    if not np.isfinite(img[inside]).all():
        return _integrate_cube(lambda d: _angular_bilinear(img, d), n, k, c)
    planes = np.zeros((c + 1, s + 2, s + 2), dtype=np.float32)
    planes[:c, 1:-1, 1:-1] = np.where(inside[..., None], img, 0.0).transpose(2, 0, 1)
    planes[c, 1:-1, 1:-1] = inside
    planes = planes.reshape(c + 1, -1)
    _, _, cen, den, w32 = _sub_texel_grid(n, k)
    rmax = max(1.0 - math.sqrt(2.0) / s, 0.0)
    out = np.empty((6, n, n, c), dtype=np.float32)
    for f in range(6):
        d = FACE_NORMALS[f] + cen[None, :, None] * FACE_U[f] + cen[:, None, None] * FACE_V[f]
        u, v = _direction_to_angular_uv(d)
        rho = np.hypot(u, v)
        scale = np.where(rho > rmax, rmax / np.where(rho > 0, rho, 1.0), 1.0)
        x = (u * scale + 1.0) * (0.5 * s) - 0.5
        y = (1.0 - v * scale) * (0.5 * s) - 0.5
        x0 = np.floor(x)
        y0 = np.floor(y)
        tx = (x - x0).astype(np.float32)
        ty = (y - y0).astype(np.float32)
        i00 = (y0.astype(np.intp) + 1) * (s + 2) + x0.astype(np.intp) + 1
        wsum = _plane_bilinear(planes[c], i00, s + 2, tx, ty)
        wsum = w32 / wsum                                          # > 0: rho <= rmax
        for ch in range(c):
            val = _plane_bilinear(planes[ch], i00, s + 2, tx, ty)
            val *= wsum
            out[f, ..., ch] = val.reshape(n, k, n, k).sum(axis=(1, 3), dtype=np.float64) / den
    return out


def _supersampling(texel_angle: float, pixel_angle: float) -> int:
    # sub-samples at most half a source pixel apart
    return max(1, math.ceil(2.0 * texel_angle / pixel_angle - 1e-9))


def _cube_sampler(faces: NDArray[np.float32]) -> Sampler:
    return CubeSampler([faces]).bilinear


def to_cube(image: ArrayLike, layout: Layout, size: int) -> NDArray[np.float32]:
    """Resample an environment image to a cube map, each texel its solid-angle mean radiance.

    Parameters
    ----------
    image : (H, W, C) float, or (6, m, m, C) for ``layout="faces"``
        Linear radiance in the given layout (see the module docstring).
    layout : {"equirect", "angular", "hcross", "vcross", "faces"}
    size : int
        Output face size ``n`` (any positive integer).

    Returns
    -------
    (6, n, n, C) float32
    """
    _check_layout(layout)
    n = _check_positive("size", size)
    if layout == "faces":
        return resample(check_cube(image, name="faces"), n)
    img = _check_image(image)
    if layout in ("hcross", "vcross"):
        return resample(cross_to_faces(img, layout), n)
    h, w, _ = img.shape
    if layout == "equirect":
        if w != 2 * h:
            raise ValueError(f"an equirect image must be 2:1 (W = 2 H), got {w}x{h}.")
        k = _supersampling(2.0 / n, min(np.pi / h, 2.0 * np.pi / w))
        return _equirect_to_cube(img, n, k)
    if h != w:
        raise ValueError(f"an angular map must be square, got {w}x{h}.")
    k = _supersampling(2.0 / n, 2.0 * np.pi / h)
    return _angular_to_cube(img, n, k)


def _from_cube_equirect(faces: NDArray[np.float32], height: int) -> NDArray[np.float32]:
    n, c = faces.shape[1], faces.shape[3]
    h, w = height, 2 * height
    k = _supersampling(np.pi / h, 2.0 / n)
    sample = _cube_sampler(faces)
    fw = w * k
    phi = 2.0 * np.pi * ((np.arange(fw) + 0.5) / fw - 0.5)
    t_edges = np.pi * (0.5 - np.arange(h * k + 1) / (h * k))
    t_centres = 0.5 * (t_edges[:-1] + t_edges[1:])
    wrow = np.sin(t_edges[:-1]) - np.sin(t_edges[1:])  # times dphi, a constant
    out = np.empty((h, w, c), dtype=np.float32)
    step = _rows_per_chunk(fw * k)
    for r0 in range(0, h, step):
        r1 = min(h, r0 + step)
        th = t_centres[r0 * k:r1 * k]
        d = _equirect_dir(phi[None, :], th[:, None])
        vals = np.asarray(sample(d), dtype=np.float64)
        wts = np.broadcast_to(wrow[r0 * k:r1 * k, None], d.shape[:2])
        out[r0:r1] = _block_mean(vals, wts, k)
    return out


def _from_cube_angular(faces: NDArray[np.float32], side: int) -> NDArray[np.float32]:
    n, c = faces.shape[1], faces.shape[3]
    s = side
    k = _supersampling(2.0 * np.pi / s, 2.0 / n)
    sample = _cube_sampler(faces)
    fs = s * k
    centres = (np.arange(fs) + 0.5) * (2.0 / fs) - 1.0
    out = np.empty((s, s, c), dtype=np.float32)
    step = _rows_per_chunk(fs * k)
    for r0 in range(0, s, step):
        r1 = min(s, r0 + step)
        u, v = np.broadcast_arrays(centres[None, :], -centres[r0 * k:r1 * k, None])
        rho = np.hypot(u, v)
        if k == 1:  # point sample at the pixel centre, 0 outside the disk
            wts = (rho <= 1.0).astype(np.float64)
        else:  # area element of the sphere per unit image area: pi sin(pi rho) / rho
            jac = np.pi * np.sin(np.pi * rho) / np.where(rho > 0, rho, 1.0)
            wts = np.where(rho > 0, jac, np.pi**2) * (rho <= 1.0)
        vals = np.asarray(sample(_angular_uv_to_dir(u, v)), dtype=np.float64)
        out[r0:r1] = _block_mean(vals, wts, k)
    _, inside = angular_directions(s)
    out[~inside] = 0.0
    return out


def from_cube(faces: ArrayLike, layout: Layout, size: int | None = None) -> NDArray[np.float32]:
    """Resample a cube map to a layout, anti-aliased when the target is coarser than the cube.

    Parameters
    ----------
    faces : (6, n, n, C) float
    layout : {"equirect", "angular", "hcross", "vcross", "faces"}
    size : int, optional
        Target size as in :func:`layout_shape`: the height for ``equirect`` (default ``2 n``,
        i.e. ``4 n`` columns around the equator, like the cube), the side for ``angular``
        (default ``4 n``), the face size for crosses and ``faces`` (default ``n``).

    Returns
    -------
    (H, W, C) float32, or (6, size, size, C) float32 for ``"faces"``
        Equirect pixels are solid-angle means of seamless bilinear cube lookups; angular-map
        pixels whose centre lies outside the disk are 0; cross cells without a face are 0.
    """
    _check_layout(layout)
    a = check_cube(faces, name="faces")
    n = a.shape[1]
    if layout == "equirect":
        return _from_cube_equirect(a, _check_positive("size", 2 * n if size is None else size))
    if layout == "angular":
        return _from_cube_angular(a, _check_positive("size", 4 * n if size is None else size))
    m = n if size is None else _check_positive("size", size)
    resized = resample(a, m)
    return resized if layout == "faces" else faces_to_cross(resized, layout)
