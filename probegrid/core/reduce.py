"""Area-average downsampling of images, whole or a band of rows at a time.

An image is read as a piecewise-constant function of its pixel coordinates (pixel ``i`` covers
``[i, i + 1)`` along each axis). Reducing ``n_in`` pixels to ``n_out`` along an axis gives
output pixel ``j`` the **mean of the function over** ``[j r, (j + 1) r)``, ``r = n_in /
n_out``: a box filter exactly one output pixel wide, fractional footprints included (a source
pixel straddling two outputs contributes its overlap to each). Every source pixel's weights sum
to one output pixel's worth, so the image's mean is preserved exactly (up to float64 rounding):
``mean(out) = sum(out) / n_out = sum(in) r / (r n_in) = mean(in)``. Integer ratios reduce to
the plain box average of ``r`` pixels; a reduction that keeps the size is the identity.

The means are differences of prefix sums (:func:`area_average`), in float64, linear in the
pixels. A large image can be reduced a band of rows at a time (:func:`row_bands` says which
source rows each band of output rows needs), so only a band and the output are in memory:
the separable reduction of a band of rows is the same sum as that of the whole image.

Used on linear values (texels decoded from sRGB, radiance): averaging sRGB codes would not
keep the light's mean. Reference: Heckbert, "Filtering by repeated integration", SIGGRAPH 1986
(box filters as differences of integrals).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["area_average", "area_edges", "reduced_shape", "row_bands"]


def area_edges(n_in: int, n_out: int) -> NDArray[np.float64]:
    """The ``n_out + 1`` footprint edges ``j n_in / n_out`` in source pixel units."""
    if n_in < 1 or n_out < 1:
        raise ValueError(f"sizes must be positive, got {n_in} -> {n_out}")
    return np.arange(n_out + 1, dtype=np.float64) * (n_in / n_out)


def area_average(a: ArrayLike, axis: int, edges: ArrayLike, *, offset: float = 0.0,
                 weights: ArrayLike | None = None) -> NDArray[np.float64]:
    """The mean of ``a`` (piecewise constant along ``axis``) over each interval
    ``[edges[j], edges[j + 1])``, each at least one pixel long, in the pixel units of a larger
    image of which ``a`` holds the pixels from ``offset`` on (the intervals must lie in
    ``[offset, offset + len]``); float64, ``len(edges) - 1`` along ``axis``.

    The sum over an interval is that of its whole pixels (``np.add.reduceat``) less the part
    of its first pixel before the interval, plus the part of the pixel at its end inside it.
    ``weights`` (one per pixel of ``a`` along ``axis``, e.g. the solid angle of an equirect
    image's rows) make it the weighted mean ``sum(w x) / sum(w)`` over each interval: then
    ``sum(w x)`` over the image is what is preserved."""
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        shape = [1] * np.ndim(a)
        shape[axis] = -1
        w = w.reshape(shape)
        return (area_average(np.asarray(a) * w, axis, edges, offset=offset)
                / area_average(w, axis, edges, offset=offset))
    x = np.asarray(a)
    n = x.shape[axis]
    e = np.asarray(edges, dtype=np.float64) - offset
    if (e.size < 2 or np.any(np.diff(e) < 1.0 - 1e-9) or e[0] < -1e-9 * n
            or e[-1] > n * (1 + 1e-12)):
        raise ValueError(f"the intervals {e[0] + offset}..{e[-1] + offset} are not inside the "
                         f"pixels {offset}..{offset + n}, or shorter than a pixel")
    e = np.clip(e, 0.0, float(n))
    i = np.minimum(np.floor(e).astype(np.int64), n - 1)
    f = e - i  # the part of pixel i before the edge (1 at the image's end)
    shape = [1] * x.ndim
    shape[axis] = -1
    whole = np.add.reduceat(x, i[:-1], axis=axis, dtype=np.float64)  # pixels i[j]..i[j+1]-1
    # (the last interval's reduceat runs to the end of ``a``: pixels from i[-1] on are removed)
    last = [slice(None)] * x.ndim
    last[axis] = slice(int(i[-1]), None)
    tail = np.sum(x[tuple(last)], axis=axis, dtype=np.float64)
    idx = [slice(None)] * x.ndim
    idx[axis] = -1
    whole[tuple(idx)] -= tail
    at = np.take(x, i, axis=axis).astype(np.float64)
    fr = f.reshape(shape)
    parts = at * fr  # (the integral of pixel i[j] up to edge j)
    lo = [slice(None)] * x.ndim
    lo[axis] = slice(0, -1)
    hi = [slice(None)] * x.ndim
    hi[axis] = slice(1, None)
    sums = whole - parts[tuple(lo)] + parts[tuple(hi)]
    return sums / np.diff(e).reshape(shape)


def reduced_shape(height: int, width: int, max_side: int) -> tuple[int, int]:
    """``(height, width)`` scaled by one factor so that the longer side is at most
    ``max_side`` (rounded, at least 1 pixel); unchanged when it already is."""
    if max(height, width) <= max_side:
        return height, width
    s = max_side / max(height, width)
    return max(1, round(height * s)), max(1, round(width * s))


def row_bands(n_in: int, n_out: int, max_rows: int) -> list[tuple[int, int, int, int]]:
    """Bands ``(j0, j1, s0, s1)``: output rows ``j0..j1`` (exclusive) need source rows
    ``s0..s1``; each band reads at most about ``max_rows`` source rows (at least the
    footprint of one output row)."""
    r = n_in / n_out
    per = max(1, int(max_rows / r))
    bands = []
    for j0 in range(0, n_out, per):
        j1 = min(n_out, j0 + per)
        s0 = math.floor(j0 * r)
        s1 = min(n_in, math.ceil(j1 * r - 1e-9 * r))
        bands.append((j0, j1, s0, max(s1, s0 + 1)))
    return bands
