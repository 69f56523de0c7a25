"""The exact clamped-cosine sum of a cube map, computed hierarchically (same sum, less work).

:func:`probegrid.core.diffuse.diffuse_exact` defines the diffuse map (irradiance / pi) at normal
``n`` as the midpoint rule over every source texel ``i`` (centre ``w_i``, exact solid angle
``dOmega_i``, radiance ``L_i``)::

    E(n) / pi = (1 / pi) sum_i max(0, n . w_i) L_i dOmega_i

The clamped cosine is *linear* wherever it is not clamped. So for a block ``q`` of ``b x b``
source texels that lies wholly in front of ``n`` (every ``n . w_i > 0``) the block's share is
``n . D_q`` with the block's *vector moment* ``D_q = sum_(i in q) L_i dOmega_i w_i`` (three
numbers per channel), and a block wholly behind ``n`` adds nothing -- both *exactly*, not as an
approximation. Only the blocks that straddle the horizon of ``n`` need their texels one by one.
Hence (:func:`clamped_cosine_sum`)::

    sum_i max(0, n . w_i) L_i dOmega_i
        = sum_(q front) n . D_q  +  sum_(q uncertain) sum_(i in q) max(0, n . w_i) L_i dOmega_i

where "front" is decided by each block's bounding cone (centre ``c_q``, half-angle ``r_q``, the
largest angle to one of its texel centres): a block is surely in front when
``n . c_q > sin r_q`` and surely behind when ``n . c_q < -sin r_q``. Every other block is summed
texel by texel, which is also exact for blocks the cone test could not place. The front part is
one dense product ``F (D)`` per chunk of outputs (``F`` the 0/1 front mask, float64 sums), the
uncertain part a gather of about ``7 m`` blocks per output (``m = n / b`` blocks along a face
edge: a great circle crosses ``O(m)`` of them). Work per output falls from ``6 n^2`` texels to
``6 m^2 + O(m b^2)``: for ``n = 128``, ``b = 4``: 6144 block products and ~3000 texels instead
of 98304 texels. The result equals the dense sum to float64 rounding (tested against it).

Conventions are those of :mod:`probegrid.core.cubemap`; no I/O.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from probegrid.core.cubemap import texel_directions, texel_solid_angles

__all__ = ["clamped_cosine_sum"]

#: Float64 values per chunk temporary (about 8 MB; the sum runs beside the GGX chain).
_CHUNK_VALUES = 2**20


@lru_cache(maxsize=4)
def _levels(n: int, top: int, finest: int) -> tuple[tuple[NDArray[np.float64], ...], ...]:
    """Block geometry of the levels ``m = top, 2 top, ..., finest`` of an ``n``-cube (the blocks
    of level ``m`` are the texels of the ``m``-cube, each covering ``(n / m)^2`` source texels).

    Returns, per level, ``(centre (6 m^2, 3), sin_r (6 m^2,))``: each block's centre direction
    and the sine of its cone half-angle (the largest angle from the centre to the centre of a
    source texel it covers; the largest is at a corner texel, since the angle to a fixed axis is
    quasi-convex on the face plane), enlarged by 1e-9 against rounding. Read-only.
    """
    out = []
    m = top
    while m <= finest:
        b = n // m
        centre = texel_directions(m).reshape(-1, 3)
        # the four corner texel centres of every block, in face-plane coordinates
        k = (np.array([0.5, b - 0.5]) / n) * 2.0                   # offsets from the block edge
        e = np.arange(m) * (2.0 * b / n) - 1.0                      # block edges
        uu = (e[:, None] + k[None, :]).reshape(-1)                  # (2 m,) corner coordinates
        f = np.arange(6)[:, None, None]
        cu, cv = uu[None, None, :], uu[None, :, None]
        from probegrid.core.cubemap import face_uv_to_direction
        corners = face_uv_to_direction(f, cu, cv)                  # (6, 2m, 2m, 3)
        corners /= np.linalg.norm(corners, axis=-1, keepdims=True)
        corners = corners.reshape(6, m, 2, m, 2, 3).transpose(0, 1, 3, 2, 4, 5).reshape(-1, 4, 3)
        cos_r = np.min(np.einsum("qkd,qd->qk", corners, centre), axis=1)
        sin_r = np.sqrt(np.maximum(1.0 - cos_r * cos_r, 0.0)) + 1e-9
        for a in (centre, sin_r):
            a.setflags(write=False)
        out.append((centre, sin_r))
        m *= 2
    return tuple(out)


def _children(q: NDArray[np.intp], m: int) -> NDArray[np.intp]:
    """Flat indices ``(P, 4)`` in the ``2m``-cube of the four children of texels ``q`` of the
    ``m``-cube."""
    f, rest = np.divmod(q, m * m)
    r, c = np.divmod(rest, m)
    base = (f * 2 * m + 2 * r) * 2 * m + 2 * c
    return base[:, None] + np.array([0, 1, 2 * m, 2 * m + 1])[None, :]


def clamped_cosine_sum(faces: NDArray[np.floating], normals: NDArray[np.float64], *,
                       top: int = 8, finest: int | None = None) -> NDArray[np.float64]:
    """``sum_i max(0, n . w_i) L_i dOmega_i`` for every normal, exactly (module docstring).

    The blocks of the ``top``-cube are classified for every normal at once (one product); the
    uncertain ones are split into their four children level by level down to the
    ``finest``-cube (default ``n / 4``: blocks of 4 x 4 texels), whose uncertain blocks are
    summed texel by texel.

    Parameters
    ----------
    faces : (6, n, n, C) float
        Source radiance (finite), ``n`` a power of two.
    normals : (N, 3) float64
        Unit normals.
    top, finest : int
        Powers of two, ``top <= finest <= n``.

    Returns
    -------
    (N, C) float64
        Irradiance (radiance x sr); divide by pi for the diffuse map.
    """
    n, c = faces.shape[1], faces.shape[3]
    finest = max(1, n // 4) if finest is None else finest
    top = min(top, finest)
    for name, v in (("n", n), ("top", top), ("finest", finest)):
        if v < 1 or v & (v - 1):
            raise ValueError(f"{name} must be a power of two, got {v}.")
    levels = _levels(n, top, finest)
    # vector moments D = sum L dOmega w of every block of every level, (6 m^2, 3, C) float64
    lw = faces.astype(np.float64) * texel_solid_angles(n)[..., None]       # (6, n, n, C)
    fine_dirs = texel_directions(n)
    d_fine = lw[..., None, :] * fine_dirs[..., :, None]                     # (6, n, n, 3, C)
    moments = []
    for centre, _ in levels:
        m = math.isqrt(len(centre) // 6)
        b = n // m
        moments.append(d_fine.reshape(6, m, b, m, b, 3, c).sum(axis=(2, 4)).reshape(-1, 3 * c))
    bf = n // finest
    # source texels of each finest block, block-major: (6 finest^2, bf^2)
    members = np.arange(6 * n * n).reshape(6, finest, bf, finest, bf).transpose(0, 1, 3, 2, 4)
    members = members.reshape(-1, bf * bf)
    lw_blk = lw.reshape(-1, c)[members]                  # block-major: one block = one row
    dir_blk = fine_dirs.reshape(-1, 3)[members]
    nrm = np.asarray(normals, dtype=np.float64)
    out = np.empty((nrm.shape[0], c))
    centre0 = levels[0][0]
    # normals in chunks through the whole hierarchy: the pair lists of a chunk stay ~8 MB
    # (a normal's horizon crosses about 5 finest blocks per unit of ``finest``; 8 with margin)
    rows = max(1, min(_CHUNK_VALUES // len(centre0),
                      _CHUNK_VALUES // (8 * finest * bf * bf * (3 + c))))
    for r0 in range(0, nrm.shape[0], rows):
        out[r0:r0 + rows] = _chunk(nrm[r0:r0 + rows], levels, moments, dir_blk, lw_blk, top, c)
    return out


def _chunk(nn: NDArray[np.float64], levels: tuple[tuple[NDArray[np.float64], ...], ...],
           moments: list[NDArray[np.float64]], dir_blk: NDArray[np.float64],
           lw_blk: NDArray[np.float64], top: int, c: int) -> NDArray[np.float64]:
    """:func:`clamped_cosine_sum` for a chunk of normals ``nn (R, 3)``."""
    centre0, sin0 = levels[0]
    cosc = nn @ centre0.T
    front = (cosc > sin0).astype(np.float64)
    acc = np.einsum("rd,rdc->rc", nn, (front @ moments[0]).reshape(-1, 3, c))
    # uncertain (output, block) pairs, refined level by level
    pr, pq = np.nonzero(np.abs(cosc) <= sin0)
    rows = len(nn)
    m = top
    for lev in range(1, len(levels)):
        centre, sin_r = levels[lev]
        kids = _children(pq, m)                                             # (P, 4)
        pr = np.repeat(pr, 4)
        pq = kids.reshape(-1)
        npr = np.take(nn, pr, axis=0)
        cosc_p = np.sum(npr * np.take(centre, pq, axis=0), axis=1)
        front_p = cosc_p > sin_r[pq]
        if front_p.any():
            val = np.matmul(npr[front_p][:, None, :],
                            np.take(moments[lev], pq[front_p], axis=0).reshape(-1, 3, c))[:, 0]
            for ch in range(c):
                acc[:, ch] += np.bincount(pr[front_p], weights=val[:, ch], minlength=rows)
        keep = np.abs(cosc_p) <= sin_r[pq]
        pr, pq = pr[keep], pq[keep]
        m *= 2
    # texel by texel in the uncertain finest blocks
    cos_t = np.matmul(np.take(dir_blk, pq, axis=0), np.take(nn, pr, axis=0)[:, :, None])
    np.maximum(cos_t, 0.0, out=cos_t)                                       # (P, b^2, 1)
    val = np.matmul(np.take(lw_blk, pq, axis=0).transpose(0, 2, 1), cos_t)[..., 0]
    for ch in range(c):
        acc[:, ch] += np.bincount(pr, weights=val[:, ch], minlength=rows)
    return acc

