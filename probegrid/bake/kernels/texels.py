"""A probe's texels, compiled: the edge-aware smoothing of the gather's correction over a face.

* :func:`smooth_texels` -- each ray's value replaced by the weighted mean of the values of the
  rays in a square window of texels around its own, on the same face of the probe's cube, over
  hits on the same surface (:class:`Smoothing`: normals close and, given the probe's position,
  off the ray's plane by at most a fraction of the hit's distance): a Gaussian of the
  texel offset times each ray's weight. The weight of a texel falls off smoothly with its
  distance, so neighbouring texels average nearly the same rays and no edge appears between
  them (a mean over fixed blocks of texels steps at every block's edge).

The restatement in numpy array expressions is in ``tests/test_bake_kernels.py``.
Floating point: :mod:`probegrid._jit`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import kernel

__all__ = ["Smoothing", "TexelHits", "smooth_texels"]


class Smoothing(NamedTuple):
    """How :func:`smooth_texels` weighs the rays around a ray."""

    #: The window's half side, texels.
    radius: int
    #: The Gaussian's standard deviation, texels.
    sigma: float
    #: Two hits are on one surface when their normals' cosine is at least this...
    same_normal: float
    #: ... and the other lies off the ray's plane by at most this fraction of the ray's hit
    #: distance from the probe (a table top and the floor under it face the same way).
    same_plane: float


class TexelHits(NamedTuple):
    """A batch of probes' rays, texel by texel (``samples`` rays per texel, ``6 n^2`` texels
    per probe, probe after probe)."""

    #: (R, 3) float64 each ray's value (0 where the weight is 0).
    value: NDArray[np.float64]
    #: (R,) float64 each ray's weight (0: the ray gives nothing and keeps its value).
    weight: NDArray[np.float64]
    #: (R, 3) float64 hit positions.
    position: NDArray[np.float64]
    #: (R, 3) float32 unit hit normals.
    normal: NDArray[np.float32]
    #: (B, 3) float64 the probes' positions, or (0, 3): no plane test.
    origin: NDArray[np.float64]


@kernel
def smooth_texels(hits: TexelHits, n: int, samples: int, smoothing: Smoothing
                  ) -> NDArray[np.float64]:
    """The edge-aware mean of each ray's value over a ``(2 radius + 1)^2`` window of texels
    around its texel on the same face (module docstring, :class:`Smoothing`): ray ``i`` gets
    ``sum_j g(i, j) w_j v_j / sum_j g(i, j) w_j`` over the rays ``j`` of the window on its
    surface, ``g = exp(-(dr^2 + dc^2) / (2 sigma^2))`` of the texel offset. A ray of weight 0
    keeps its value. Returns ``(R, 3)`` float64."""
    value, weight, position, normal, origin = hits
    radius, sigma, same_normal, same_plane = smoothing
    nr = value.shape[0]
    per_probe = 6 * n * n * samples
    planes = origin.shape[0] > 0
    out = np.empty((nr, 3))
    g = np.empty(2 * radius + 1)
    for d in range(-radius, radius + 1):
        g[d + radius] = math.exp(-0.5 * d * d / (sigma * sigma))
    for i in range(nr):
        if not weight[i] > 0.0:
            out[i, 0], out[i, 1], out[i, 2] = value[i, 0], value[i, 1], value[i, 2]
            continue
        probe = i // per_probe
        texel = (i - probe * per_probe) // samples
        face = texel // (n * n)
        rest = texel - face * n * n
        row = rest // n
        col = rest - row * n
        px, py, pz = position[i, 0], position[i, 1], position[i, 2]
        nx, ny, nz = np.float64(normal[i, 0]), np.float64(normal[i, 1]), \
            np.float64(normal[i, 2])
        reach = 0.0
        if planes:
            ox, oy, oz = px - origin[probe, 0], py - origin[probe, 1], pz - origin[probe, 2]
            reach = same_plane * math.sqrt(ox * ox + oy * oy + oz * oz)
        base = probe * per_probe + face * n * n * samples
        a0 = a1 = a2 = 0.0
        den = 0.0
        for r in range(max(row - radius, 0), min(row + radius + 1, n)):
            gr = g[r - row + radius]
            for c in range(max(col - radius, 0), min(col + radius + 1, n)):
                gc = gr * g[c - col + radius]
                j0 = base + (r * n + c) * samples
                for j in range(j0, j0 + samples):
                    w = weight[j]
                    if not w > 0.0:
                        continue
                    cos = (nx * normal[j, 0] + ny * normal[j, 1] + nz * normal[j, 2])
                    if cos < same_normal:
                        continue
                    if planes:
                        dx = position[j, 0] - px
                        dy = position[j, 1] - py
                        dz = position[j, 2] - pz
                        if abs(dx * nx + dy * ny + dz * nz) > reach:
                            continue
                    w *= gc
                    a0 += w * value[j, 0]
                    a1 += w * value[j, 1]
                    a2 += w * value[j, 2]
                    den += w
        out[i, 0], out[i, 1], out[i, 2] = a0 / den, a1 / den, a2 / den
    return out
