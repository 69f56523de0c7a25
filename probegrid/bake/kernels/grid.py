"""The bake's kernels of the probe grid: the trace-once probe weights of hits, the replay of a
bounce from the records, and a probe's per-texel reductions.

* :func:`hit_probe_weights` -- :func:`probegrid.core.ddgi.probe_weights` with normals and
  moments, normalised (the trace-once weights, computed once per hit);
* :func:`replay_radiance` -- a bounce's pass over a level's per-hit records;
* :func:`texel_means`, :func:`distance_moments`, :func:`mean_per_parent` -- per-texel means,
  distance moments and per-parent means of a probe's rays.

``tests/test_bake_kernels.py`` compares each with the numpy expression it restates. The grid
reaches the kernels as small tables (:class:`GridLattice`, :class:`ProbeTable`,
:class:`Weighting`, :class:`ReplayRecords`), the cube's axes as
:class:`~probegrid.bake.kernels.cube.CubeAxes`; the corner order is
:data:`probegrid.core.grid.CORNER_OFFSETS` and the weighting constants
:mod:`probegrid.core.ddgi`'s, passed at run time (:mod:`probegrid.bake.kernels`).
Floating point: :mod:`probegrid._jit`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import kernel
from probegrid.bake.kernels.cube import CubeAxes, _face_uv

__all__ = [
    "GridLattice",
    "ProbeTable",
    "ReplayRecords",
    "Weighting",
    "distance_moments",
    "hit_probe_weights",
    "mean_per_parent",
    "replay_radiance",
    "texel_means",
]


class GridLattice(NamedTuple):
    """Where the probes stand: the grid's box, cell steps and counts per axis."""

    #: (3,) float64 lowest and highest probe positions.
    lo: NDArray[np.float64]
    hi: NDArray[np.float64]
    #: (3,) float64 the spacing (1 along an axis of one probe).
    step: NDArray[np.float64]
    #: (3,) int64 probes per axis.
    counts: NDArray[np.int64]
    #: (8, 3) int64 the cell's corners (:data:`probegrid.core.grid.CORNER_OFFSETS`).
    corner_offsets: NDArray[np.int64]


class ProbeTable(NamedTuple):
    """The probes a hit's weights read (``P`` probes)."""

    #: (P,) bool whether each probe carries weight.
    valid: NDArray[np.bool_]
    #: (P, 3) float64 positions (relocated).
    positions: NDArray[np.float64]
    #: (P * 6 (m + 2)^2, 2) float32 bordered distance moments, or (0, 2): none.
    moments: NDArray[np.float32]
    #: The moments' face size ``m``.
    moments_n: int


class Weighting(NamedTuple):
    """The DDGI weighting's constants (:mod:`probegrid.core.ddgi`)."""

    #: Normal bias (world units).
    bias: float
    #: :data:`probegrid.core.ddgi.NORMAL_TERM_FLOOR`.
    normal_floor: float
    #: :data:`probegrid.core.ddgi.MIN_WEIGHT`.
    min_weight: float
    #: :data:`probegrid.core.ddgi.CRUSH_THRESHOLD`.
    crush: float


class ReplayRecords(NamedTuple):
    """A level's per-hit records as :func:`replay_radiance` reads them (``N`` rays)."""

    #: (N,) uint8: 0 miss, 1 front hit, 2 back hit.
    kind: NDArray[np.uint8]
    #: (N, 3) float32, or (0, 3): no emission.
    emission: NDArray[np.float32]
    #: (N, 3) float32 the punctual lights' irradiance / pi (a miss: the environment).
    light_punctual: NDArray[np.float32]
    #: (N, 3) float32 the emitters' irradiance / pi.
    light_emitters: NDArray[np.float32]
    #: (N, 3) float32.
    albedo: NDArray[np.float32]
    #: (N, 3) float32, or (0, 3) when no grid is read.
    normals: NDArray[np.float32]
    #: (N, 8) int32 probe indices and float32 weights (:func:`hit_probe_weights`).
    indices: NDArray[np.int32]
    weights: NDArray[np.float32]


@kernel
def hit_probe_weights(
    points: NDArray[np.float64],
    normals: NDArray[np.floating],
    rows: NDArray[np.int64],
    lattice: GridLattice,
    probes: ProbeTable,
    weighting: Weighting,
    axes: CubeAxes,
    hidden: NDArray[np.bool_],
    fallback: NDArray[np.int64],
) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """The 8 probes around surface points ``rows`` of ``points (n, 3)`` (unit ``normals``) and
    their normalised DDGI weights (the other rows, misses say, stay 0).

    The weights of :func:`probegrid.core.ddgi.probe_weights` with normals and moments (the
    normal-facing term, the Chebyshev test on the seamless bilinear moments, the crush),
    divided by their sum. They depend only on the geometry and the probes' distance moments, never on the
    light, so a bake computes them once per hit and every bounce reuses them. The grid's
    ``lattice``, its ``probes`` and the ``weighting`` constants are the tables below; ``axes``
    the cube's (:data:`~probegrid.bake.kernels.cube.CUBE_AXES`, for the moments' lookup).

    ``hidden (n, 8)`` (corner order of :func:`hit_corners`), when not empty, is the exact
    visibility test (:func:`probegrid.bake.records.replay.hidden_corners`: geometry on the
    segment from the biased point to the probe): a hidden probe gets weight 0 and a visible
    one its normal-facing term without the Chebyshev estimate, as
    :func:`probegrid.core.ddgi.probe_weights` with ``occluded``. A point that sees none of its
    valid probes reads, when ``fallback (n,)`` is not empty, probe ``fallback[i]`` alone
    (weight 1 in the first slot: the probe whose rays reached the point, in the same free
    space by construction) or nothing where that is -1 or invalid; with an empty
    ``fallback``, the moments' weights (whose soft test can favour a probe beyond a wall).

    Returns
    -------
    indices : (n, 8) int32
        Linear probe indices (corner order of :data:`probegrid.core.grid.CORNER_OFFSETS`).
    weights : (n, 8) float32
        Normalised weights; all 0 where no valid probe carries weight.
    """
    lo, hi, step, counts, corner_offsets = lattice
    valid, positions, moments, moments_n = probes
    bias, normal_floor, min_weight, crush = weighting
    face_u, face_v = axes.u, axes.v
    n_pts = points.shape[0]
    out_i = np.zeros((n_pts, 8), np.int32)
    out_w = np.zeros((n_pts, 8), np.float32)
    use_moments = moments.shape[0] > 0
    m = moments_n
    mb = m + 2
    texels = 6 * mb * mb
    half = 0.5 * m
    crush2 = crush * crush
    w = np.empty(8)
    base = np.empty(3, np.int64)
    frac = np.empty(3)
    cp = np.empty(3)
    has_hidden = hidden.shape[0] > 0
    for j in range(rows.shape[0]):
        i = rows[j]
        nx = np.float64(normals[i, 0])  # (float() keeps a float32)
        ny, nz = np.float64(normals[i, 1]), np.float64(normals[i, 2])
        big = max(abs(nx), abs(ny), abs(nz))
        if not big > 0:
            continue
        nx, ny, nz = nx / big, ny / big, nz / big
        nl = math.sqrt(nx * nx + ny * ny + nz * nz)
        nx, ny, nz = nx / nl, ny / nl, nz / nl
        for a in range(3):
            c = min(max(points[i, a], lo[a]), hi[a])
            cp[a] = c
            if counts[a] > 1:
                t = (c - lo[a]) / step[a]
                b = min(max(math.floor(t), 0.0), float(max(counts[a] - 2, 0)))
                base[a] = int(b)
                frac[a] = min(max(t - b, 0.0), 1.0)
            else:
                base[a] = 0
                frac[a] = 0.0
        qx, qy, qz = cp[0] + bias * nx, cp[1] + bias * ny, cp[2] + bias * nz
        total = 0.0
        for attempt in range(2 if has_hidden else 1):  # the exact test, then the moments'
            exact = has_hidden and attempt == 0
            total = 0.0
            for c in range(8):
                ii = min(base[0] + corner_offsets[c, 0], counts[0] - 1)
                jj = min(base[1] + corner_offsets[c, 1], counts[1] - 1)
                kk = min(base[2] + corner_offsets[c, 2], counts[2] - 1)
                p = (ii * counts[1] + jj) * counts[2] + kk
                out_i[i, c] = p
                tw = 1.0
                for a in range(3):
                    f = frac[a]
                    tw *= f if corner_offsets[c, a] == 1 else 1.0 - f
                if not valid[p] or (exact and hidden[i, c]):
                    tw *= 0.0
                if tw == 0.0:
                    w[c] = 0.0
                    continue
                ex = positions[p, 0] - cp[0]
                ey = positions[p, 1] - cp[1]
                ez = positions[p, 2] - cp[2]
                el = math.sqrt(ex * ex + ey * ey + ez * ez)
                if el > 1e-300:
                    dot = (ex * nx + ey * ny + ez * nz) / el
                else:
                    dot = 0.0
                s = ((dot + 1.0) * 0.5) ** 2 + normal_floor
                if use_moments and not exact:
                    ox = qx - positions[p, 0]
                    oy = qy - positions[p, 1]
                    oz = qz - positions[p, 2]
                    r = math.sqrt(ox * ox + oy * oy + oz * oz)
                    face, u, v = _face_uv(ox, oy, oz, face_u, face_v)
                    x = (u + 1.0) * half + 0.5
                    y = (v + 1.0) * half + 0.5
                    x0 = min(math.floor(x), float(m))
                    y0 = min(math.floor(y), float(m))
                    fx, fy = x - x0, y - y0
                    gx, gy = 1.0 - fx, 1.0 - fy
                    t0 = p * texels + (face * mb + int(y0)) * mb + int(x0)
                    w00, w01, w10, w11 = gy * gx, gy * fx, fy * gx, fy * fx
                    mean = (moments[t0, 0] * w00 + moments[t0 + 1, 0] * w01
                            + moments[t0 + mb, 0] * w10 + moments[t0 + mb + 1, 0] * w11)
                    if not r <= mean:
                        mean_sq = (moments[t0, 1] * w00 + moments[t0 + 1, 1] * w01
                                   + moments[t0 + mb, 1] * w10 + moments[t0 + mb + 1, 1] * w11)
                        var = abs(mean_sq - mean * mean)
                        excess = max(r - mean, 0.0)
                        den = var + excess * excess
                        if excess > 0:
                            cheb = var / den if den != 0 else math.nan
                        else:
                            cheb = 1.0
                        if math.isnan(cheb):
                            cheb = 0.0
                        s *= cheb * cheb * cheb
                s = max(s, min_weight)
                if s < crush:
                    s = s * s * s / crush2
                tw *= s
                w[c] = tw
                total += tw
            if total > 0:
                break
            if exact and fallback.shape[0] > 0:  # sees none: the probe that reached it
                f = fallback[i]
                if f >= 0 and valid[f]:
                    out_i[i, 0] = f
                    out_w[i, 0] = 1.0
                break
        if total <= 0:
            continue
        for c in range(8):
            out_w[i, c] = w[c] / total
    return out_i, out_w


@kernel
def replay_radiance(
    records: ReplayRecords,
    grid: tuple[NDArray[np.float32], int],
    axes: CubeAxes,
    level: int,
    indirect: NDArray[np.float32],
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """One bounce of a probe's rays from their per-hit records (no ray is cast).

    ``records`` (:class:`ReplayRecords`) are a level's, ``grid`` is ``(cubes, cube_n)`` and
    ``axes`` the cube's (:data:`~probegrid.bake.kernels.cube.CUBE_AXES`). Per ray, by ``kind``
    (0 a miss, 1 a front hit, 2 a back hit):

    * a miss returns ``light_punctual`` (where a miss keeps the environment's radiance);
    * a back hit returns 0;
    * a front hit returns ``emission + albedo * lit`` with, at ``level`` 0,
      ``lit = light_punctual`` (the punctual lights' irradiance / pi) and, at higher levels,
      ``lit = light_punctual + light_emitters + sum_c weights[c] * G[indices[c]](normal)``:
      the emitters' irradiance / pi (next-event estimation) and the grid's bounced
      irradiance / pi, ``G`` each probe's bordered irradiance cube ``cubes`` (face ``cube_n``,
      :class:`probegrid.core.ddgi.BorderedCubes` layout ``(P * 6 (n + 2)^2, 3)``) read
      bilinearly at the normal; an empty ``cubes`` is a black grid. A non-empty ``indirect``
      ``(N, 3)`` (irradiance / pi gathered at each hit) takes the grid's place. An empty
      ``emission`` ``(0, 3)`` is no emission (``normals`` may be empty when no grid is read).

    Returns
    -------
    radiance : (N, 3) float32
        What the probe sees along each ray.
    bounced : (N, 3) float32
        The same without the emission of the surfaces hit: the light that the grid carries
        (reflected at least once, or the environment: the caller zeroes the misses when the
        environment is sampled at the hits instead).
    """
    kind, emission, light_punctual, light_emitters, albedo, normals, indices, weights = records
    cubes, cube_n = grid
    face_u, face_v = axes.u, axes.v
    nr = kind.shape[0]
    rad = np.zeros((nr, 3), np.float32)
    bnc = np.zeros((nr, 3), np.float32)
    has_emission = emission.shape[0] > 0
    use_indirect = level > 0 and indirect.shape[0] > 0
    use_grid = level > 0 and cubes.shape[0] > 0 and not use_indirect
    n = cube_n
    mb = n + 2
    texels = 6 * mb * mb
    half = 0.5 * n
    for i in range(nr):
        k = kind[i]
        if k == 2:
            continue
        if k == 0:
            for c in range(3):
                rad[i, c] = light_punctual[i, c]
                bnc[i, c] = light_punctual[i, c]
            continue
        l0 = np.float64(light_punctual[i, 0])
        l1 = np.float64(light_punctual[i, 1])
        l2 = np.float64(light_punctual[i, 2])
        if level > 0:
            l0 += light_emitters[i, 0]
            l1 += light_emitters[i, 1]
            l2 += light_emitters[i, 2]
        if use_indirect:
            l0 += indirect[i, 0]
            l1 += indirect[i, 1]
            l2 += indirect[i, 2]
        if use_grid:
            face, u, v = _face_uv(np.float64(normals[i, 0]), np.float64(normals[i, 1]),
                                  np.float64(normals[i, 2]), face_u, face_v)
            x = (u + 1.0) * half + 0.5
            y = (v + 1.0) * half + 0.5
            x0 = min(math.floor(x), float(n))
            y0 = min(math.floor(y), float(n))
            fx, fy = x - x0, y - y0
            gx, gy = 1.0 - fx, 1.0 - fy
            off = (face * mb + int(y0)) * mb + int(x0)
            w00, w01, w10, w11 = gy * gx, gy * fx, fy * gx, fy * fx
            for c in range(8):
                wc = np.float64(weights[i, c])
                if wc == 0.0:
                    continue
                t0 = indices[i, c] * texels + off
                l0 += wc * (cubes[t0, 0] * w00 + cubes[t0 + 1, 0] * w01
                            + cubes[t0 + mb, 0] * w10 + cubes[t0 + mb + 1, 0] * w11)
                l1 += wc * (cubes[t0, 1] * w00 + cubes[t0 + 1, 1] * w01
                            + cubes[t0 + mb, 1] * w10 + cubes[t0 + mb + 1, 1] * w11)
                l2 += wc * (cubes[t0, 2] * w00 + cubes[t0 + 1, 2] * w01
                            + cubes[t0 + mb, 2] * w10 + cubes[t0 + mb + 1, 2] * w11)
        b0 = albedo[i, 0] * l0
        b1 = albedo[i, 1] * l1
        b2 = albedo[i, 2] * l2
        bnc[i, 0], bnc[i, 1], bnc[i, 2] = b0, b1, b2
        if has_emission:
            rad[i, 0] = emission[i, 0] + b0
            rad[i, 1] = emission[i, 1] + b1
            rad[i, 2] = emission[i, 2] + b2
        else:
            rad[i, 0], rad[i, 1], rad[i, 2] = b0, b1, b2
    return rad, bnc


@kernel
def texel_means(radiance: NDArray[np.float32], weights: NDArray[np.float64],
                samples: int) -> NDArray[np.float32]:
    """Weighted mean radiance of each texel's rays.

    ``radiance (R, 3)`` float32 of rays stored texel by texel (``samples`` consecutive rays per
    texel) and their ``weights (R,)`` (summing to 1 over each texel's rays); returns
    ``(R / samples, 3)`` float32, summed in float64.
    """
    n = radiance.shape[0] // samples
    out = np.empty((n, 3), np.float32)
    for i in range(n):
        a0 = a1 = a2 = 0.0
        for k in range(i * samples, (i + 1) * samples):
            w = weights[k]
            a0 += w * radiance[k, 0]
            a1 += w * radiance[k, 1]
            a2 += w * radiance[k, 2]
        out[i, 0], out[i, 1], out[i, 2] = a0, a1, a2
    return out


@kernel
def distance_moments(distance: NDArray[np.float64], solid_angle: NDArray[np.float64],
                     bins: NDArray[np.int64], n_bins: int) -> NDArray[np.float32]:
    """Solid-angle-weighted mean distance and mean squared distance per bin.

    ``distance (R,)`` of rays carrying ``solid_angle (R,)`` steradians, ``bins (R,)`` in
    ``[0, n_bins)``; returns ``(n_bins, 2)`` float32 (sums in float64; an empty bin is nan).
    """
    den = np.zeros(n_bins)
    mu = np.zeros(n_bins)
    m2 = np.zeros(n_bins)
    for k in range(distance.shape[0]):
        b = bins[k]
        a = solid_angle[k]
        t = distance[k]
        den[b] += a
        mu[b] += a * t
        m2[b] += a * t * t
    out = np.empty((n_bins, 2), np.float32)
    for b in range(n_bins):
        out[b, 0] = mu[b] / den[b]
        out[b, 1] = m2[b] / den[b]
    return out


@kernel
def mean_per_parent(parent: NDArray[np.int64], radiance: NDArray[np.float32], parents: int
                    ) -> NDArray[np.float32]:
    """The mean of ``radiance (k, 3)`` over the rows of each of ``parents`` parents
    (``parent (k,)`` each row's parent), summed in float64 in row order; 0 for a parent with
    no row. Returns ``(parents, 3)`` float32."""
    total = np.zeros((parents, 3))
    count = np.zeros(parents)
    for i in range(parent.shape[0]):
        p = parent[i]
        count[p] += 1.0
        total[p, 0] += radiance[i, 0]
        total[p, 1] += radiance[i, 1]
        total[p, 2] += radiance[i, 2]
    out = np.zeros((parents, 3), np.float32)
    for p in range(parents):
        if count[p] > 0:
            out[p, 0] = total[p, 0] / count[p]
            out[p, 1] = total[p, 1] / count[p]
            out[p, 2] = total[p, 2] / count[p]
    return out
