"""Seamless cube-map sampling: nearest, bilinear and trilinear lookups, mip chains, resizing.

Lookups behave like a GPU with ``TEXTURE_CUBE_MAP_SEAMLESS`` and are also continuous at the eight
cube corners, where OpenGL leaves the result undefined.

Filtering
---------
A direction selects a face and face coordinates ``(u, v)`` exactly as
:func:`probegrid.core.cubemap.direction_to_face_uv` (major axis, ties to X then Y). Bilinear
filtering then works on the *bordered* faces of :func:`probegrid.core.seams.add_border`
(``(n + 2) x (n + 2)``, a one-texel border continued from the neighbour faces, corner border
texels the mean of the three real corner texels). The continuous texel coordinate is::

    x = (u + 1) / 2 * n - 0.5 + 1        (the + 1 skips the border column; likewise y from v)

so ``x`` lies in ``[0.5, n + 0.5]`` and the 2 x 2 footprint ``floor(x) .. floor(x) + 1`` never
leaves the bordered face: nothing is clamped. Near an edge the footprint reaches into the border,
i.e. blends into the neighbour face; exactly on an edge both faces give the same value; at a cube
corner all three faces give the mean of the three corner texels.

Directions need not be normalised (the projection divides by the major component), so the
classic trick of interpolating unnormalised normals and looking them up directly works. The
zero vector gives a valid value (the centre texel of +X); a direction with a nan or infinite
component gives nan.

Trilinear filtering lerps the bilinear lookups of levels ``floor(lod)`` and ``floor(lod) + 1``
with ``lod`` clamped to ``[0, levels - 1]`` (``GL_LINEAR_MIPMAP_LINEAR``); ``lod`` may differ per
direction, as in filtered importance sampling (Colbert and Krivanek, "GPU-based importance
sampling", GPU Gems 3, ch. 20, 2007), for which this sampler is the inner loop.

Implementation
--------------
All levels are bordered once and flattened into one array per channel in which item ``i`` holds
bordered texel ``i`` *and its right-hand neighbour* (two float32, gathered as one 8-byte item;
2 x the memory of the bordered cube), so a bilinear footprint costs two ``np.take`` gathers per
channel, and a trilinear one four. Face selection and texel coordinates are branch-free float32
arithmetic (no ``np.where``: its data-dependent branches are slow on random masks); at face size
4096 the texel coordinate is accurate to about 1e-3 texel, and a direction within float32
rounding of an edge may be projected onto the other face, which is harmless because the lookup
is continuous there. :meth:`CubeSampler.nearest`, where the face matters, uses
:func:`probegrid.core.cubemap.direction_to_texel` in float64 instead. Directions are processed in
chunks of :data:`CHUNK` so that temporaries stay small and cache resident.

Resizing
--------
:func:`resample` makes each output texel the mean radiance over its solid angle. When the output
size is the source size divided by a power of two this is exactly the box-filtered mip
(:func:`probegrid.core.cubemap.downsample`). Otherwise it is estimated with a ``k x k`` grid of
sub-texel points weighted by their exact solid angles (Girard, as in :mod:`probegrid.core.cubemap`;
the weights of an output texel sum to its exact solid angle), each a seamless bilinear lookup of
the source, first box-filtered down while it stays at least ``4 x`` the output size. With
``k = ceil(2 n_src / size)`` the sub-samples are at most half a source texel apart, so the source
texels under the output texel are all seen (no aliasing), and the bilinear reconstruction
widens the footprint by at most half a source texel (``1/8`` of an output texel when
downsizing by 4 or more).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core.cubemap import (
    CubeMap,
    check_cube,
    direction_to_texel,
    downsample,
    face_uv_to_direction,
    mip_sizes,
)
from probegrid.core.seams import add_border

__all__ = [
    "CHUNK",
    "CubeSampler",
    "mip_chain",
    "resample",
    "sample_bilinear",
    "sample_nearest",
    "sample_trilinear",
]

#: Directions per chunk in :class:`CubeSampler` lookups (bounds temporaries to a few MB).
CHUNK: Final[int] = 16384

_F32 = np.float32
# Below this the major component is treated as zero (avoids 0 / 0 for the zero vector).
_TINY: Final = np.float32(1e-30)
# Chunks whose largest |component| lies outside [_LOW, _HIGH] (or is nan / inf) are rescaled in
# float64 per direction before the float32 math, so huge or tiny finite directions stay exact.
_LOW: Final = 1e-20
_HIGH: Final = 1e20

# resample() supersamples the smallest box mip of the source that is at least this many times
# the output size: the bilinear reconstruction then blurs by at most 1 / (2 * this) output texel.
_RESAMPLE_OVERSIZE: Final = 4

# A chunk kernel: (face, u * ma, v * ma, 1 / ma, per-direction extra or None, out (m, C)) -> None
_Kernel = Callable[
    [NDArray[np.intp], NDArray[np.float32], NDArray[np.float32], NDArray[np.float32],
     NDArray | None, NDArray[np.float32]],
    None,
]


def _project(d: NDArray) -> tuple[NDArray[np.intp], NDArray[np.float32], NDArray[np.float32],
                                   NDArray[np.float32], NDArray[np.bool_] | None]:
    """Face selection of a chunk of directions, branch-free.

    Parameters
    ----------
    d : (m, 3) float

    Returns
    -------
    face : (m,) intp
    un, vn : (m,) float32
        ``u * ma`` and ``v * ma``: the face coordinates times the major component magnitude.
    inv : (m,) float32
        ``1 / ma`` (large but finite for the zero vector).
    bad : (m,) bool or None
        Directions with a non-finite component (their other outputs are arbitrary but valid).
    """
    bad = None
    amax = float(np.max(np.abs(d))) if d.size else 1.0
    if not _LOW <= amax <= _HIGH:
        d64 = np.asarray(d, dtype=np.float64)
        finite = np.isfinite(d64).all(axis=-1)
        bad = ~finite if not finite.all() else None
        scale = np.max(np.abs(np.where(finite[:, None], d64, 0.0)), axis=-1, keepdims=True)
        d = np.where(finite[:, None], d64, 0.0) / np.where(scale > 0, scale, 1.0)
    x, y, z = np.asarray(d, dtype=_F32).T.copy()
    ax, ay, az = np.abs(x), np.abs(y), np.abs(z)
    is_x = (ax >= ay) & (ax >= az)
    is_y = (ay >= az) & ~is_x
    is_z = ~(is_x | is_y)
    wx, wy, wz = (m.view(np.uint8).astype(_F32) for m in (is_x, is_y, is_z))
    major = x * wx + y * wy + z * wz  # the signed major component
    sm = np.sign(major)
    # The OpenGL table (see probegrid.core.cubemap): u*ma is -sm z | x | sm x and v*ma is
    # -y | sm z | -y for X-, Y- and Z-major directions, sm = sign of the major component.
    un = x * (wy + wz * sm) - wx * sm * z
    vn = wy * (y + sm * z) - y
    face = (is_y.view(np.uint8) * np.uint8(2) + is_z.view(np.uint8) * np.uint8(4)
            + (major < 0).view(np.uint8)).astype(np.intp)
    inv = _F32(1.0) / np.maximum(np.maximum(np.maximum(ax, ay), az), _TINY)
    return face, un, vn, inv, bad


class CubeSampler:
    """Seamless lookups into a cube map and its mip levels.

    Parameters
    ----------
    levels : CubeMap, (6, n, n, C) array, or sequence of (6, n_k, n_k, C) float arrays
        The levels to sample; any face sizes (a mip chain halves them, but this is not required).
        Bordered copies are made once, at construction.

    Attributes
    ----------
    sizes : tuple of int
        Face size of each level.
    channels : int
    """

    def __init__(self, levels: CubeMap | ArrayLike | Sequence[ArrayLike]) -> None:
        if isinstance(levels, CubeMap):
            lv = list(levels.levels)
        elif isinstance(levels, np.ndarray) and levels.ndim in (3, 4):
            lv = [levels]
        elif isinstance(levels, Sequence) and len(levels) > 0:
            lv = list(levels)
        else:
            raise ValueError("levels must be a CubeMap, a cube array or a non-empty sequence of "
                             "cube arrays.")
        cubes = [check_cube(a, name=f"level {k}") for k, a in enumerate(lv)]
        c = cubes[0].shape[3]
        if any(a.shape[3] != c for a in cubes):
            raise ValueError("All levels must have the same number of channels.")
        self.sizes: tuple[int, ...] = tuple(int(a.shape[1]) for a in cubes)
        self.channels: int = int(c)
        bordered = [add_border(a).reshape(-1, c) for a in cubes]
        offsets = np.cumsum([0] + [b.shape[0] for b in bordered])
        planar = np.concatenate(bordered, axis=0).T  # (C, total)
        # Item i = (texel i, texel i + 1), one float64-sized item, so a bilinear footprint is 2
        # gathers per channel. The item at a row's last column (n + 1) straddles two rows but is
        # never read: the footprint's left column is at most n.
        pairs = np.zeros((c, planar.shape[1], 2), dtype=_F32)
        pairs[..., 0] = planar
        pairs[:, :-1, 1] = planar[:, 1:]
        self._pairs = pairs.view(np.float64)[..., 0]  # (C, total) float64 views of the pairs
        self._pairs.setflags(write=False)
        self._offsets = offsets[:-1].astype(np.intp)
        self._offsets.setflags(write=False)
        n_arr = np.asarray(self.sizes, dtype=np.intp)
        # Per-level constants for vectorised per-direction levels (trilinear with array lod).
        self._half_n = (0.5 * n_arr).astype(_F32)
        self._stride = n_arr + 2
        for a in (self._half_n, self._stride):
            a.setflags(write=False)

    @property
    def num_levels(self) -> int:
        return len(self.sizes)

    def __repr__(self) -> str:
        return f"CubeSampler(sizes={self.sizes}, channels={self.channels})"

    # -- argument checks -------------------------------------------------------------------
    def _check_level(self, level: int) -> int:
        if (not isinstance(level, (int, np.integer)) or isinstance(level, bool)
                or not 0 <= level < self.num_levels):
            raise ValueError(f"level must be an integer in 0..{self.num_levels - 1}, "
                             f"got {level!r}.")
        return int(level)

    @staticmethod
    def _directions(directions: ArrayLike) -> NDArray:
        d = np.asarray(directions)
        if d.shape[-1:] != (3,):
            raise ValueError(f"directions must have shape (..., 3), got {d.shape}.")
        if not np.issubdtype(d.dtype, np.floating):
            d = d.astype(np.float64)
        return d

    # -- core ------------------------------------------------------------------------------
    def _footprint(self, face: NDArray[np.intp], un: NDArray[np.float32],
                   vn: NDArray[np.float32], inv: NDArray[np.float32],
                   level: int | NDArray[np.intp]) -> tuple[NDArray[np.intp], NDArray[np.float32]]:
        """Bilinear footprint of projected directions at ``level`` (scalar or (m,) per direction).

        Returns
        -------
        idx : (2, m) intp
            Indices into ``self._pairs`` of the top and bottom texel pairs of the 2 x 2 block.
        weights : (2, 2 m) float32
            Bilinear weights, interleaved like the gathered pairs: ``weights[0, 2 i + j]`` is the
            weight of the top-row texel ``j`` (0 left, 1 right) of direction ``i``.
        """
        half = self._half_n[level]
        stride = self._stride[level]
        s = half * inv
        h = half + _F32(0.5)
        x = un * s + h
        y = vn * s + h
        x0 = np.floor(x)
        y0 = np.floor(y)
        fx = x - x0
        fy = y - y0
        m = face.shape[0]
        idx = np.empty((2, m), dtype=np.intp)
        np.multiply(face, stride, out=idx[0])
        idx[0] += y0.astype(np.intp)
        idx[0] *= stride
        idx[0] += x0.astype(np.intp)
        idx[0] += self._offsets[level]
        np.add(idx[0], stride, out=idx[1])
        w = np.empty((2, m, 2), dtype=_F32)
        gx = _F32(1.0) - fx
        gy = _F32(1.0) - fy
        np.multiply(gy, gx, out=w[0, :, 0])
        np.multiply(fy, gx, out=w[1, :, 0])
        np.subtract(gy, w[0, :, 0], out=w[0, :, 1])  # (1 - fy) fx
        np.subtract(fy, w[1, :, 0], out=w[1, :, 1])  # fy fx
        return idx, w.reshape(2, 2 * m)

    def _gather(self, idx: NDArray[np.intp], weights: NDArray[np.float32],
                out: NDArray[np.float32]) -> None:
        """Weighted sums of texel pairs into ``out`` (m, C): ``idx`` (k, m) pair indices,
        ``weights`` (k, 2 m) one weight per gathered texel, interleaved as the pairs."""
        for c in range(self.channels):
            texels = np.take(self._pairs[c], idx).view(_F32)  # (k, 2 m)
            texels *= weights
            acc = texels.sum(axis=0) if texels.shape[0] > 1 else texels[0]
            np.add(acc[0::2], acc[1::2], out=out[:, c])

    def _bilinear_values(self, face: NDArray[np.intp], un: NDArray[np.float32],
                         vn: NDArray[np.float32], inv: NDArray[np.float32],
                         level: int | NDArray[np.intp], out: NDArray[np.float32]) -> None:
        """Bilinear values (m, C) of projected directions at ``level`` (scalar or (m,))."""
        self._gather(*self._footprint(face, un, vn, inv, level), out)

    def _trilinear_values(self, face: NDArray[np.intp], un: NDArray[np.float32],
                          vn: NDArray[np.float32], inv: NDArray[np.float32],
                          l0: int | NDArray[np.intp], l1: int | NDArray[np.intp],
                          t: NDArray[np.float32] | np.float32, out: NDArray[np.float32]) -> None:
        """Lerp (m, C) of the bilinear values of levels ``l0`` and ``l1`` with weight ``t``."""
        i0, w0 = self._footprint(face, un, vn, inv, l0)
        i1, w1 = self._footprint(face, un, vn, inv, l1)
        t = np.asarray(t, dtype=_F32)
        if t.ndim:
            t = np.repeat(t, 2)  # interleaved like the weights
        w = np.concatenate([w0 * (_F32(1.0) - t), w1 * t], axis=0)
        self._gather(np.concatenate([i0, i1], axis=0), w, out)

    def _run(self, directions: ArrayLike, kernel: _Kernel, extra: NDArray | None = None
             ) -> NDArray[np.float32]:
        """Chunk ``directions`` (..., 3), let ``kernel(face, un, vn, inv, extra_chunk, out)``
        write each chunk's (m, C) values, and return (..., C) float32 (nan for directions with a
        non-finite component)."""
        d = self._directions(directions)
        lead = d.shape[:-1]
        flat = d.reshape(-1, 3)
        ex = None if extra is None else np.broadcast_to(extra, lead).reshape(-1)
        total = flat.shape[0]
        out = np.empty((total, self.channels), dtype=_F32)
        for i in range(0, total, CHUNK):
            j = min(i + CHUNK, total)
            face, un, vn, inv, bad = _project(flat[i:j])
            kernel(face, un, vn, inv, None if ex is None else ex[i:j], out[i:j])
            if bad is not None:
                out[i:j][bad] = np.nan
        return out.reshape(*lead, self.channels)

    # -- public lookups --------------------------------------------------------------------
    def bilinear(self, directions: ArrayLike, *, level: int = 0) -> NDArray[np.float32]:
        """Seamless bilinear lookup of one level.

        Parameters
        ----------
        directions : (..., 3) float
            Need not be normalised.
        level : int
            Mip level index.

        Returns
        -------
        (..., C) float32
        """
        lv = self._check_level(level)
        return self._run(directions,
                         lambda f, u, v, i, _, o: self._bilinear_values(f, u, v, i, lv, o))

    def trilinear(self, directions: ArrayLike, lod: ArrayLike) -> NDArray[np.float32]:
        """Seamless trilinear lookup: lerp of the bilinear lookups of the two nearest levels.

        Parameters
        ----------
        directions : (..., 3) float
        lod : float or array broadcastable to ``directions.shape[:-1]``
            Fractional level, clamped to ``[0, levels - 1]``; must be finite.

        Returns
        -------
        (..., C) float32
        """
        lod_a = np.asarray(lod, dtype=np.float64)
        if not np.all(np.isfinite(lod_a)):
            raise ValueError("lod must be finite.")
        top = self.num_levels - 1
        lod_a = np.clip(lod_a, 0.0, top)
        if lod_a.ndim == 0:
            l0 = math.floor(float(lod_a))
            l1 = min(l0 + 1, top)
            t = _F32(float(lod_a) - l0)

            def kernel(f, u, v, i, _, o):
                if t == 0:
                    self._bilinear_values(f, u, v, i, l0, o)
                else:
                    self._trilinear_values(f, u, v, i, l0, l1, t, o)

            return self._run(directions, kernel)

        def kernel_arr(f, u, v, i, lc, o):
            l0 = np.floor(lc).astype(np.intp)
            self._trilinear_values(f, u, v, i, l0, np.minimum(l0 + 1, top),
                                   (lc - l0).astype(_F32), o)

        d = self._directions(directions)
        try:
            np.broadcast_shapes(lod_a.shape, d.shape[:-1])
        except ValueError:
            raise ValueError(f"lod of shape {lod_a.shape} does not broadcast to the directions' "
                             f"shape {d.shape[:-1]}.") from None
        if np.broadcast_shapes(lod_a.shape, d.shape[:-1]) != d.shape[:-1]:
            d = np.broadcast_to(d, (*np.broadcast_shapes(lod_a.shape, d.shape[:-1]), 3))
        return self._run(d, kernel_arr, lod_a)

    def nearest(self, directions: ArrayLike, *, level: int = 0) -> NDArray[np.float32]:
        """Value of the texel containing each direction (no filtering).

        The texel is :func:`probegrid.core.cubemap.direction_to_texel`'s, computed in float64, so
        directions on a texel or face boundary resolve exactly as everywhere else in the
        project.

        Parameters
        ----------
        directions : (..., 3) float
        level : int

        Returns
        -------
        (..., C) float32
            nan for directions with a non-finite component.
        """
        lv = self._check_level(level)
        n = self.sizes[lv]
        stride, off = int(self._stride[lv]), int(self._offsets[lv])
        d = self._directions(directions)
        lead = d.shape[:-1]
        flat = d.reshape(-1, 3)
        out = np.empty((flat.shape[0], self.channels), dtype=_F32)
        for i in range(0, flat.shape[0], CHUNK):
            chunk = flat[i:i + CHUNK]
            finite = np.isfinite(chunk).all(axis=-1)
            if not finite.all():
                chunk = np.where(finite[:, None], chunk, 0.0)
            face, row, col = direction_to_texel(chunk, n)
            idx = off + (face * stride + row + 1) * stride + col + 1
            o = out[i:i + CHUNK]
            for c in range(self.channels):
                o[:, c] = np.take(self._pairs[c], idx).view(_F32)[0::2]
            o[~finite] = np.nan
        return out.reshape(*lead, self.channels)


def sample_bilinear(faces: ArrayLike, directions: ArrayLike) -> NDArray[np.float32]:
    """Seamless bilinear lookup of one cube, ``(6, n, n, C)`` at ``(..., 3)`` -> ``(..., C)``.

    Builds a :class:`CubeSampler`; reuse one for repeated lookups of the same cube.
    """
    return CubeSampler([faces]).bilinear(directions)


def sample_nearest(faces: ArrayLike, directions: ArrayLike) -> NDArray[np.float32]:
    """Texel containing each direction, ``(6, n, n, C)`` at ``(..., 3)`` -> ``(..., C)``."""
    return CubeSampler([faces]).nearest(directions)


def sample_trilinear(levels: CubeMap | Sequence[ArrayLike], directions: ArrayLike,
                     lod: ArrayLike) -> NDArray[np.float32]:
    """Seamless trilinear lookup of a mip chain at fractional level(s) ``lod``.

    See :meth:`CubeSampler.trilinear`; builds a :class:`CubeSampler` each call.
    """
    return CubeSampler(levels).trilinear(directions, lod)


def mip_chain(faces: ArrayLike, *, levels: int | None = None) -> list[NDArray[np.float32]]:
    """Box-filtered mip chain of a cube (:func:`probegrid.core.cubemap.downsample` repeatedly).

    Parameters
    ----------
    faces : (6, n, n, C) float
    levels : int, optional
        Number of levels including level 0; default the full chain down to 1 x 1 (``n`` must
        then be a power of two).

    Returns
    -------
    list of (6, n >> k, n >> k, C) float32
    """
    a = check_cube(faces)
    out = [a.copy()]
    for _ in mip_sizes(a.shape[1], levels)[1:]:
        out.append(downsample(out[-1]))
    return out


def _patch_solid_angles(e_u: NDArray[np.float64], e_v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Exact solid angles of the face patches between consecutive edges ``e_v`` (rows) and
    ``e_u`` (columns): ``(len(e_v) - 1, len(e_u) - 1)`` float64 (see :mod:`probegrid.core.cubemap`)."""
    x = e_u[None, :]
    y = e_v[:, None]
    f = np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))
    return f[1:, 1:] - f[:-1, 1:] - f[1:, :-1] + f[:-1, :-1]


def resample(faces: ArrayLike, size: int) -> NDArray[np.float32]:
    """Antialiased resize of a cube map to any face size.

    Each output texel is the mean of the source over its solid angle: the exact box mip when
    ``size`` is ``n / 2^j``, else the solid-angle-weighted mean of ``k x k`` seamless bilinear
    lookups at its sub-texel centres (see the module docstring). Upsizing (``size >= 2 n``) is
    plain seamless bilinear interpolation at the output texel centres.

    Parameters
    ----------
    faces : (6, n, n, C) float
    size : int
        Output face size, ``>= 1``.

    Returns
    -------
    (6, size, size, C) float32
    """
    if not isinstance(size, (int, np.integer)) or isinstance(size, bool) or size < 1:
        raise ValueError(f"size must be a positive integer, got {size!r}.")
    size = int(size)
    src = check_cube(faces)
    n = src.shape[1]
    ratio = n // size
    if n % size == 0 and ratio & (ratio - 1) == 0:  # size = n / 2^j: the exact box mip
        for _ in range(ratio.bit_length() - 1):
            src = downsample(src)
        return src.copy() if ratio == 1 else src
    while src.shape[1] % 2 == 0 and src.shape[1] // 2 >= _RESAMPLE_OVERSIZE * size:
        src = downsample(src)
    ns, c = src.shape[1], src.shape[3]
    k = max(1, math.ceil(2 * ns / size))
    sub = size * k
    edges = np.linspace(-1.0, 1.0, sub + 1)
    centres = 0.5 * (edges[:-1] + edges[1:])
    sampler = CubeSampler([src])
    rows_per_chunk = max(1, (1 << 18) // (k * sub))
    out = np.empty((6, size, size, c), dtype=_F32)
    for f in range(6):
        for r0 in range(0, size, rows_per_chunk):
            r1 = min(r0 + rows_per_chunk, size)
            # sub-texel centre directions (rows k, sub, 3) and exact solid angles (rows k, sub)
            d = face_uv_to_direction(f, centres[None, :], centres[r0 * k: r1 * k, None])
            w = _patch_solid_angles(edges, edges[r0 * k: r1 * k + 1])
            vals = sampler.bilinear(d).astype(np.float64) * w[..., None]
            num = vals.reshape(r1 - r0, k, size, k, c).sum(axis=(1, 3))
            den = w.reshape(r1 - r0, k, size, k).sum(axis=(1, 3))
            out[f, r0:r1] = (num / den[..., None]).astype(_F32)
    return out
