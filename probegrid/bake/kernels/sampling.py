"""Random sampling of the bake, compiled: alias tables, cosine-weighted directions, the final
gather's rays and counter-based random streams.

* :func:`alias_table` (Walker's alias table, Vose's method) and :func:`alias_draw` -- the draws
  of the emitters' and the environment's samples (:func:`_alias_pick`, the same rule compiled,
  is what :mod:`~probegrid.bake.kernels.emitters` and :mod:`~probegrid.bake.kernels.environment`
  draw by);
* :func:`cosine_directions`, :func:`gather_rays` -- cosine-weighted directions about normals and
  the final gather's rays (:func:`_turn` replaces the C library's ``cos`` and ``sin`` of the
  azimuths, tested against numpy to the last bits);
* :func:`stream_uniforms` -- uniform numbers of counter-based streams (SplitMix64), one stream
  per probe and purpose (:mod:`probegrid.bake.records`).

``tests/test_bake_kernels.py`` compares each with the numpy expression it restates.
Floating point: :mod:`probegrid._jit`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._jit import inline_kernel, kernel

__all__ = ["alias_draw", "alias_table", "cosine_directions", "gather_rays", "stream_uniforms"]


@inline_kernel
def _alias_pick(accept: NDArray[np.float64], alias: NDArray[np.int64], r: float) -> int:
    """One draw of :func:`alias_draw` (its rule, compiled): ``i = floor(r N)``, then ``i`` if
    ``frac(r N) < accept[i]`` else ``alias[i]``."""
    n = accept.shape[0]
    x = r * n  # the alias table's column, then its coin
    t = min(int(x), n - 1)
    if not x - t < accept[t]:
        t = alias[t]
    return t


def alias_draw(accept: NDArray[np.float64], alias: NDArray[np.int64], random: ArrayLike
               ) -> NDArray[np.int64]:
    """The entries an :func:`alias_table` ``(accept, alias)`` draws for uniform ``random`` in
    [0, 1) (any shape): ``i = floor(r N)``, then ``i`` if ``frac(r N) < accept[i]`` else
    ``alias[i]`` -- the rule :func:`emitter_samples` and :func:`environment_samples` draw by
    (:func:`_alias_pick`)."""
    n = len(accept)
    x = np.asarray(random, dtype=np.float64) * n
    t = np.minimum(x.astype(np.int64), n - 1)
    return np.where(x - t < accept[t], t, alias[t])


@kernel
def alias_table(prob: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Walker's alias table of a discrete distribution ``prob (N,)`` (summing to 1), built by
    Vose's method: entry ``i`` is kept with probability ``accept[i]`` and otherwise gives
    ``alias[i]``, so ``i = floor(r N)``, then ``i`` if ``frac(r N) < accept[i]`` else
    ``alias[i]`` draws index ``t`` with probability ``prob[t]`` from one uniform ``r`` in O(1)
    (:func:`environment_samples`; a zero-probability entry is never drawn)."""
    n = prob.shape[0]
    scaled = prob * n
    accept = np.ones(n)
    alias = np.arange(n)
    small = np.empty(n, np.int64)
    large = np.empty(n, np.int64)
    ns = 0
    nl = 0
    for i in range(n):
        if scaled[i] < 1.0:
            small[ns] = i
            ns += 1
        else:
            large[nl] = i
            nl += 1
    while ns > 0 and nl > 0:
        ns -= 1
        lo = small[ns]
        hi = large[nl - 1]
        accept[lo] = scaled[lo]
        alias[lo] = hi
        scaled[hi] = (scaled[hi] + scaled[lo]) - 1.0
        if scaled[hi] < 1.0:  # now short itself: the next one to be topped up
            nl -= 1
            small[ns] = hi
            ns += 1
    return accept, alias  # (entries left over are full up to rounding: accept 1)


@kernel
def _turn(r: float) -> tuple[float, float]:
    """``(cos, sin)`` of the angle ``2 pi r`` for ``r`` in [0, 1), to within 2e-16: the quarter
    turn ``q = floor(4 r)`` is exact, the rest ``a = (4 r - q - 1/2) pi / 2`` lies within
    ``pi / 4`` of 0, where the Taylor series of ``sin a`` to ``a^15`` and of ``cos a`` to
    ``a^16`` are exact to 5e-17; then ``pi / 4 + a`` and the quarter turns are rotations.
    Costs a third of the C library's ``cos`` and ``sin`` (:func:`gather_rays`' azimuths)."""
    x = 4.0 * r
    q = min(int(x), 3)
    a = (x - q - 0.5) * (0.5 * math.pi)
    z = a * a
    sa = a * (1.0 + z * (-1.0 / 6 + z * (1.0 / 120 + z * (-1.0 / 5040 + z * (
        1.0 / 362880 + z * (-1.0 / 39916800 + z * (1.0 / 6227020800
                                                   - z / 1307674368000.0)))))))
    ca = 1.0 + z * (-0.5 + z * (1.0 / 24 + z * (-1.0 / 720 + z * (1.0 / 40320 + z * (
        -1.0 / 3628800 + z * (1.0 / 479001600 + z * (-1.0 / 87178291200
                                                     + z / 20922789888000.0)))))))
    h = math.sqrt(0.5)
    c, s = h * (ca - sa), h * (ca + sa)  # the angle pi / 4 + a
    if q == 0:
        return c, s
    if q == 1:
        return -s, c
    if q == 2:
        return -c, -s
    return s, -c


@kernel
def _cosine_direction(nx: float, ny: float, nz: float, r0: float, r1: float
                      ) -> tuple[float, float, float]:
    """One cosine-weighted unit direction about the unit normal ``n`` (:func:`cosine_directions`)."""
    sign = 1.0 if nz >= 0.0 else -1.0
    a = -1.0 / (sign + nz)
    bb = nx * ny * a
    t1x, t1y, t1z = 1.0 + sign * nx * nx * a, sign * bb, -sign * nx
    t2x, t2y, t2z = bb, sign + ny * ny * a, -ny
    r = math.sqrt(r0)
    z = math.sqrt(max(1.0 - r0, 0.0))
    cp, sp = _turn(r1)  # the azimuth 2 pi r1
    c, s = r * cp, r * sp
    dx = c * t1x + s * t2x + z * nx
    dy = c * t1y + s * t2y + z * ny
    dz = c * t1z + s * t2z + z * nz
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    return dx / norm, dy / norm, dz / norm


@kernel
def cosine_directions(normals: NDArray[np.float64], random: NDArray[np.float64]
                      ) -> NDArray[np.float64]:
    """Cosine-weighted unit directions about unit ``normals (n, 3)`` from uniform
    ``random (n, 2)`` (density ``cos / pi``): ``sqrt(r0)`` the sine of the polar angle,
    ``2 pi r1`` the azimuth, in the orthonormal basis of Duff et al., "Building an Orthonormal
    Basis, Revisited", JCGT 6(1), 2017. Returns ``(n, 3)``."""
    n = normals.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        out[i, 0], out[i, 1], out[i, 2] = _cosine_direction(
            normals[i, 0], normals[i, 1], normals[i, 2], random[i, 0], random[i, 1])
    return out


@kernel
def gather_rays(positions: NDArray[np.float64], normals: NDArray[np.floating],
                arriving: NDArray[np.float64], parents: NDArray[np.int64],
                random: NDArray[np.float64], eps: float
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The final gather's rays from hits ``parents (k,)`` of a level (their ``positions``,
    unit ``normals`` facing the side the ray came from, and the ``arriving`` directions that
    found them): origins ``position - eps arriving + eps normal`` (off the surface and back
    along the ray: a hit on an edge of a closed room would start its rays in the next wall)
    and :func:`cosine_directions` about the normals from ``random (k, 2)``. Returns both
    ``(k, 3)``."""
    k = parents.shape[0]
    org = np.empty((k, 3))
    dirs = np.empty((k, 3))
    for j in range(k):
        i = parents[j]
        nx = np.float64(normals[i, 0])  # (float() keeps a float32)
        ny, nz = np.float64(normals[i, 1]), np.float64(normals[i, 2])
        for a in range(3):
            org[j, a] = positions[i, a] - eps * arriving[i, a] + eps * np.float64(normals[i, a])
        dirs[j, 0], dirs[j, 1], dirs[j, 2] = _cosine_direction(nx, ny, nz, random[j, 0],
                                                               random[j, 1])
    return org, dirs


#: SplitMix64's increment (the golden ratio in 64 bits) and its output mix's multipliers
#: (Steele, Lea and Flood, "Fast splittable pseudorandom number generators", OOPSLA 2014).
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)


@kernel
def _splitmix(z: np.uint64) -> np.uint64:
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    return z ^ (z >> np.uint64(31))


@kernel
def stream_uniforms(keys: NDArray[np.uint64], per_key: int, rows: NDArray[np.int64],
                    width: int) -> NDArray[np.float64]:
    """Uniform numbers in [0, 1) of counter-based streams, for the given rows only.

    Row ``r`` belongs to stream ``keys[r // per_key]`` (a probe's stream of one purpose) as its
    row ``j = r % per_key``; its ``width`` numbers are SplitMix64's outputs number
    ``j width .. j width + width - 1`` of that stream (state ``key + (c + 1) golden``, the
    output mix, the top 53 bits over ``2^53``). A number depends only on its key and counter,
    never on which other rows are drawn: a batch draws what its rays use and nothing else.
    Returns ``(len(rows), width)``.
    """
    out = np.empty((rows.shape[0], width))
    scale = 1.0 / 9007199254740992.0  # 2^-53
    q, lo = -1, 0
    key = np.uint64(0)
    for i in range(rows.shape[0]):
        r = rows[i]
        if not (q >= 0 and lo <= r < lo + per_key):  # (rows mostly come in order)
            q = r // per_key
            lo = q * per_key
            key = keys[q]
        base = np.uint64((r - lo) * width)
        for d in range(width):
            z = _splitmix(key + (base + np.uint64(d + 1)) * _GOLDEN)
            out[i, d] = np.int64(z >> np.uint64(11)) * scale
    return out
