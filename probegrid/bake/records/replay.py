"""Replay every bounce from the records: a pass over a block's per-hit records reads only the
grid's small per-probe data, and no ray is cast.

Once every probe's distance moments are known, each hit's 8 surrounding probes and their DDGI
weights are computed once (:func:`all_hit_weights`,
:func:`probegrid.bake.kernels.grid.hit_probe_weights`) and kept beside the records. A hit reads
only the probes it sees: each is tested by a traced segment (:func:`hidden_corners`), and a
hit that sees none reads the probe whose rays reached it (:func:`_own_probes`). Measured on a
sunlit hall (``benchmarks/bench_leaks.py``): probes added outside its walls, tested by the
moments' Chebyshev bound alone, lit its inside through the gather's reads of hits behind its
furniture, which saw none of their probes and leaned on the soft weights of those beyond the
wall. A bounce is
then a pass over the records (:func:`replay`, :func:`probegrid.bake.kernels.grid.replay_radiance`)
that reads each probe's irradiance cube of the previous bounce (:func:`irradiance_cubes`).

What the grid carries
---------------------
Only light that has been reflected at least once: the ``bounced`` radiance of a ray leaves out
the emission of the surface it hits and, for a miss, the environment. Direct light reaches hits
from the emitters and the environment by explicit sampling and from punctual lights by shadow
rays, so no light is counted twice, and none of it is interpolated between probes (a sun patch
read through the probes leaked into the shadows beside it). A hit reads the grid through each
surrounding probe's own irradiance cube (the exact clamped-cosine convolution of its bounced
radiance, :func:`irradiance_size`-texel faces, looked up bilinearly at the normal): a weighted
mean of non-negative irradiances, which cannot go negative or ring around a small bright source
the way 9 SH coefficients do.

Bounce levels (``bounces = B`` makes a furnace box read ``Le (1 - rho^(B+1)) / (1 - rho)``): at
level 0 a hit returns its emission and the punctual lights' reflected light; at level ``k > 0``
it adds the emitters' and the environment's reflected direct light and the level ``k - 1`` grid.
With gather levels, a bounce at level ``k`` reads the grid at the deepest level's hits, for the
light they reflect at level ``k - depth``, i.e. the grid of level ``k - 1 - depth``
(:func:`grid_level_read`); each level's mean radiance is the level above's irradiance / pi. What
the probe itself finally sees of that light is the grid read at each hit plus the gather's mean
correction smoothed over the texels around each hit on the same surface
(:func:`_smooth_gathered`): the integrals are the gather's, the per-texel noise a fraction of it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import frozen
from probegrid.bake.kernels.cube import CUBE_AXES
from probegrid.bake.kernels.grid import (
    GridLattice,
    ProbeTable,
    ReplayRecords,
    Weighting,
    hit_probe_weights,
    mean_per_parent,
    replay_radiance,
    texel_means,
)
from probegrid.bake.kernels.texels import Smoothing, TexelHits, smooth_texels
from probegrid.bake.records.schema import (
    LEVEL_PREFIXES,
    Level,
    RecordArrays,
    Records,
    gather_depth,
    stored_name,
)
from probegrid.bake.pattern import sample_pattern
from probegrid.bake.settings import BakeSettings
from probegrid.core.arrays import one_blas_thread, sum_rows
from probegrid.core.cubemap import (
    direction_to_face,
    downsample,
    texel_directions,
    texel_solid_angles,
)
from probegrid.core.ddgi import (
    CRUSH_THRESHOLD,
    DEFAULT_NORMAL_BIAS,
    MIN_WEIGHT,
    NORMAL_TERM_FLOOR,
)
from probegrid.core.grid import CORNER_OFFSETS, GridSpec
from probegrid.core.lights import splat_delta
from probegrid.raytrace import RayTracer

__all__ = [
    "GATHER_SMOOTHING",
    "GridData",
    "all_hit_weights",
    "grid_level_read",
    "hidden_corners",
    "hit_weights",
    "irradiance_cubes",
    "irradiance_size",
    "replay",
    "visible_probe",
]


def irradiance_size(gather: bool) -> int:
    """Face size of the per-probe irradiance cubes hits read the grid through: 16 when the hits
    read them at their own normal; 8 when gather rays' hits read them (one reflection further
    from what the probes see: on the sample room against a path tracer, 2.28 % mean error at 8,
    2.30 % at 16)."""
    return 8 if gather else 16

@lru_cache(maxsize=4)
def _irradiance_matrix(n: int, g: int) -> NDArray[np.float32]:
    """``(6 g^2, 6 n^2)`` float32: irradiance / pi at the ``g``-cube's texel directions of an
    ``n``-cube of radiance (the clamped-cosine sum of :func:`probegrid.core.diffuse.diffuse_exact`,
    each row normalised to sum to 1)."""
    out = texel_directions(g).reshape(-1, 3)
    src = texel_directions(n).reshape(-1, 3)
    m = np.maximum(out @ src.T, 0.0) * texel_solid_angles(n).reshape(1, -1)
    # each row normalised to sum to 1 (the clamped cosine / pi integrates to 1): a constant
    # radiance gives exactly itself, as the furnace requires, whatever n
    m = (m / m.sum(axis=1, keepdims=True)).astype(np.float32)
    m.setflags(write=False)
    return m


def irradiance_cubes(cubes: NDArray[np.float32], size: int) -> NDArray[np.float32]:
    """Irradiance / pi cubes ``(B, 6, size, size, 3)`` of radiance cubes ``(B, 6, n, n, 3)``
    (box-filtered to ``max(size, 16)`` first when larger: the clamped cosine is smooth at that
    scale),
    8 probes per product, zero-padded to a fixed shape (the bits do not depend on the batch)."""
    b, _, n0, _, _ = cubes.shape
    n = n0
    while n > max(size, 16) and n % 2 == 0:  # the source box-filtered down to 16 (or the output)
        n //= 2
    mat = _irradiance_matrix(n, size)
    out = np.empty((b, 6, size, size, 3), np.float32)
    group = 8
    for g0 in range(0, b, group):  # groups of probes as the columns of one fixed-shape product
        k = min(group, b - g0)
        stacked = np.zeros((6, n0, n0, group * 3), np.float32)
        stacked[..., :3 * k] = np.moveaxis(cubes[g0:g0 + k], 0, 3).reshape(6, n0, n0, 3 * k)
        while stacked.shape[1] > n:
            stacked = downsample(stacked)
        with one_blas_thread():  # small: threads only spin
            res = mat @ stacked.reshape(6 * n * n, group * 3)  # (6 size^2, group * 3)
        out[g0:g0 + k] = np.moveaxis(res[:, :3 * k].reshape(-1, k, 3), 1, 0).reshape(
            k, 6, size, size, 3)
    return out


@dataclass(frozen=True, eq=False)
class GridData:
    """What a pass reads of the whole grid: probe validity and positions, the distance moments
    (bordered, for the weights), the previous level's irradiance cubes (bordered, flat
    ``(P * 6 (g + 2)^2, 3)``, or None for a black grid) and the scene's tracer that tests
    which probes a hit sees."""

    grid: GridSpec
    valid: NDArray[np.bool_]
    positions: NDArray[np.float64]
    moments: NDArray[np.float32]
    moments_n: int
    cubes: NDArray[np.float32] | None
    #: The scene's tracer for the exact visibility of the probes at hits
    #: (:func:`hidden_corners`); None: the moments' Chebyshev estimate alone.
    tracer: RayTracer | None = None


def grid_level_read(level: int, depth: int) -> int:
    """The grid level a pass at bounce ``level`` reads (negative: none) with ``depth`` gather
    levels: ``level - 1 - depth`` (each gather level's hits reflect light of the level below)."""
    return level - 1 - depth


def all_hit_weights(arrays: Mapping[str, NDArray[Any]], data: GridData, *,
                    stand_in: NDArray[np.int64] | None = None) -> RecordArrays:
    """The probe weights of every hit a bounce reads the grid at: the deepest gather level's
    hits when a block's stored arrays have gather rays (the hits above read the light gathered
    below), else the rays' own hits. Returns the arrays to add to the stored records.

    A hit that sees none of its cell's probes reads the probe whose rays reached it (in the
    same free space by construction): the block's ``probes``, or ``stand_in (B,)``, the grid
    probe standing for each (-1: none; points traced between the probes,
    :class:`probegrid.bake.point.PointTracer`)."""
    depth = gather_depth(arrays)
    level = Level.read(arrays, depth)
    wi, ww = _level_weights(level, data, None if data.tracer is None
                            else _own_probes(arrays, depth, stand_in))
    return {stored_name(depth, "weight_index"): wi, stored_name(depth, "weight"): ww}


def hit_weights(arrays: Mapping[str, NDArray[Any]], data: GridData, *,
                stand_in: NDArray[np.int64] | None = None
                ) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """Each front hit's 8 probes and normalised DDGI weights (0 for misses and back hits) of
    the probes' own rays (level 0 of a block's stored arrays: ``kind``, ``position`` and
    ``normal``); ``stand_in`` as :func:`all_hit_weights`."""
    return _level_weights(Level.read(arrays, 0), data, None if data.tracer is None
                          else _own_probes(arrays, 0, stand_in))


def _own_probes(arrays: Mapping[str, NDArray[Any]], depth: int,
                stand_in: NDArray[np.int64] | None) -> NDArray[np.int64]:
    """``(k,)`` the grid index of the probe whose rays reached each hit of level ``depth``
    (following each gather ray's parent up to the probe's own ray): the block's ``probes``,
    or ``stand_in`` for them."""
    k = len(arrays[stored_name(depth, "kind")])
    row = np.arange(k)
    for d in range(depth, 0, -1):  # each gather level's rows to their parents' rows
        row = np.asarray(arrays[stored_name(d, "primary")], np.int64)[row]
    own = np.asarray(arrays["probes"] if stand_in is None else stand_in, np.int64)
    return own[row // int(arrays["rays_per_probe"])]


def _level_weights(level: Level, data: GridData,
                   fallback: NDArray[np.int64] | None = None
                   ) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """:func:`hit_weights` of one level's records; ``fallback (k,)`` each hit's own probe
    (-1: none) for a hit that sees none of its cell's probes (None: the moments' weights)."""
    g = data.grid
    counts = np.array(g.counts, dtype=np.int64)
    bias = DEFAULT_NORMAL_BIAS * g.smallest_cell()
    points = np.ascontiguousarray(level.position, dtype=np.float64)
    rows = np.flatnonzero(level.kind == 1)
    valid = np.ascontiguousarray(data.valid, dtype=bool)
    positions = np.ascontiguousarray(data.positions, dtype=np.float64)
    hidden = (np.zeros((0, 8), bool) if data.tracer is None else
              hidden_corners(points, level.normal, rows, g, valid, positions, bias,
                             data.tracer))
    return hit_probe_weights(*frozen((
        points, level.normal, rows,
        GridLattice(g.lo, g.hi, np.where(counts > 1, g.spacing, 1.0), counts, CORNER_OFFSETS),
        ProbeTable(valid, positions, data.moments, data.moments_n),
        Weighting(bias, NORMAL_TERM_FLOOR, MIN_WEIGHT, CRUSH_THRESHOLD), CUBE_AXES, hidden,
        np.zeros(0, np.int64) if fallback is None or data.tracer is None
        else np.ascontiguousarray(fallback, dtype=np.int64))))


def visible_probe(points: NDArray[np.float64], grid: GridSpec, valid: NDArray[np.bool_],
                  positions: NDArray[np.float64], tracer: RayTracer) -> NDArray[np.int64]:
    """``(B,)`` for each of ``points (B, 3)`` (in free space), the valid probe of its cell
    that it sees with the largest trilinear weight, -1 where it sees none: what stands for a
    point that is not a probe when its rays' hits see none of theirs."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    idx, tri, _ = grid.corners(p)
    live = (tri > 0) & valid[idx]
    r, c = np.nonzero(live)
    seen = np.zeros(idx.shape, bool)
    if len(r):
        seen[r, c] = ~tracer.segments_occluded(
            p[r], positions[idx[r, c]], margin=SEGMENT_MARGIN * grid.smallest_cell(1.0))
    best = np.argmax(np.where(seen, tri, -1.0), axis=1)
    return np.where(seen.any(axis=1), idx[np.arange(len(p)), best], -1).astype(np.int64)


#: Length left out at both ends of a hit's segment to a probe, in units of the smallest cell
#: (:func:`hidden_corners`): a probe standing on a surface does not hide itself.
SEGMENT_MARGIN = 1e-3


def hidden_corners(points: NDArray[np.float64], normals: NDArray[np.floating],
                   rows: NDArray[np.int64], grid: GridSpec, valid: NDArray[np.bool_],
                   positions: NDArray[np.float64], bias: float, tracer: RayTracer
                   ) -> NDArray[np.bool_]:
    """``(n, 8)`` whether each hit ``rows`` of ``points (n, 3)`` is hidden from each of its
    cell's 8 probes (corner order of :meth:`probegrid.core.grid.GridSpec.corners`): the probe
    stands behind the plane through the hit moved ``bias`` along its unit normal (off its own
    surface, to the side the hit is lit from), or geometry lies on the segment from that point
    to the probe's (possibly moved) position. Only valid probes with a trilinear weight are
    tested; the others and the rows not listed are False.
    This is the exact test that keeps light out of a room: a gather hit on the inside of a wall
    must not read the probes that stand beyond it in the sun (the moments' Chebyshev bound is
    soft: a coarse moments texel straddling the wall's edge, or a probe moved out of a roof
    slab, passes light through; :mod:`probegrid.core.ddgi` "Exact visibility" for queries).
    """
    out = np.zeros((len(points), 8), bool)
    cell = grid.smallest_cell()
    if not len(rows) or cell <= 0:  # (a single probe: no cell to bias or margin by)
        return out
    p = points[rows]
    nrm = np.asarray(normals[rows], np.float64)
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    idx, tri, _ = grid.corners(p)
    live = (tri > 0) & valid[idx]
    r, c = np.nonzero(live)
    if not len(r):
        return out
    start = p[r] + bias * nrm[r]
    end = positions[idx[r, c]]
    # behind the plane through the biased point: on the surface's other side (a probe in a
    # skylight's opening, level with the ceiling: not the light under the ceiling)
    behind = np.einsum("ij,ij->i", end - start, nrm[r]) <= 0.0
    hit = behind.copy()
    front = np.flatnonzero(~behind)
    if len(front):
        hit[front] = tracer.segments_occluded(start[front], end[front],
                                              margin=SEGMENT_MARGIN * cell)
    out[rows[r[hit]], c[hit]] = True
    return out


#: How :func:`_smooth_gathered` spreads the gather rays' noise over a probe's texels
#: (:func:`probegrid.bake.kernels.texels.smooth_texels`): a Gaussian of 3 texels in a 17 x 17
#: window, over the hits on one surface (normals within 10 degrees, off each other's plane by
#: at most 5 % of the hit's distance).
GATHER_SMOOTHING = Smoothing(radius=8, sigma=3.0, same_normal=math.cos(math.radians(10.0)),
                             same_plane=0.05)


def _smooth_gathered(records: Records, settings: BakeSettings,
                     rad: NDArray[np.float32], gathered: NDArray[np.float32],
                     cubes: NDArray[np.float32], g: int,
                     sample_weights: NDArray[np.float64] | None,
                     positions: NDArray[np.float64] | None) -> NDArray[np.float32]:
    """What a probe sees of its hits' gathered light, with the gather rays' noise spread over
    the texels around each: each front hit's ``albedo * gathered`` becomes ``albedo * G`` (the
    grid read at the hit itself: smooth, but biased) plus the correction
    ``albedo * (gathered - G)`` smoothed over the hits around it on the same surface, weighted
    by their solid angles (:data:`GATHER_SMOOTHING`,
    :func:`probegrid.bake.kernels.texels.smooth_texels`). The Gaussian's weights change smoothly
    from texel to texel, so neighbouring texels differ by no more than the light does (a mean
    over fixed 8 x 8 blocks stepped at every block's edge: a checkerboard in the mirror level
    of a sunlit hall, whose gather rays rarely find the small sunlit patches that light it).
    Light is not smoothed across surfaces (a table top and the floor, a wall and the ceiling),
    and what the smoothing moves within the hits facing one side (the normal's cube face; one
    sided windows at a surface's edge) is given back to them evenly, so each probe's integral
    over the hits facing each way is the gather's: the diffuse maps and SH are the gather's,
    and no light moves from the sample room's red wall to its ceiling (spread across that edge,
    a correction did: 2-3 % of each against a path tracer). Needs the rays' own probe weights,
    the rays' sample weights with several rays per texel, and the probes' ``positions`` for the
    test of a surface's plane (None: normals alone)."""
    n, s = settings.face_size, settings.samples
    nr = records.rays_per_probe
    rays = records.levels[0]
    assert rays.albedo is not None and rays.normal is not None
    assert rays.position is not None
    kind = rays.kind
    total = len(kind)
    zeros = np.zeros((total, 3), np.float32)
    _, at_hit = replay_radiance(*frozen((  # albedo * G alone
        ReplayRecords(kind, zeros, zeros, zeros, rays.albedo, rays.normal, rays.weight_index,
                      rays.weight),
        (cubes, g), CUBE_AXES, 1, np.zeros((0, 3), np.float32))))
    front = kind == 1
    corr = np.where(front[:, None], rays.albedo.astype(np.float64) * gathered
                    - at_hit.astype(np.float64), 0.0)
    texel = (np.arange(total) % nr) // s
    w = texel_solid_angles(n).reshape(-1)[texel] * front
    if sample_weights is not None:
        w = w * sample_weights
    origin = (np.zeros((0, 3)) if positions is None
              else np.ascontiguousarray(positions, dtype=np.float64).reshape(-1, 3))
    smooth = smooth_texels(
        TexelHits(corr, w, np.ascontiguousarray(rays.position, dtype=np.float64),
                  np.ascontiguousarray(rays.normal, dtype=np.float32), origin),
        n, s, GATHER_SMOOTHING)
    # what the smoothing moved within a side (near a surface's edge the window is one-sided)
    # goes back to the side evenly: each probe's integral over the hits facing each way is
    # the gather's, so no light moves between a wall and the ceiling, and the diffuse maps and
    # SH are the gather's
    side = (np.arange(total) // nr) * 6 + direction_to_face(rays.normal)
    den = np.bincount(side, weights=w, minlength=int(side.max()) + 1)
    lost = sum_rows(side, w[:, None] * (corr - smooth), len(den))
    lost = np.divide(lost, den[:, None], out=np.zeros_like(lost), where=den[:, None] > 0)
    out = rad.astype(np.float64) - corr + np.where(front[:, None], smooth + lost[side], 0.0)
    return np.maximum(out, 0.0).astype(np.float32)


def _replay_level(records: Level, depth: int, level: int, grid: NDArray[np.float32],
                  gathered: NDArray[np.float32], g: int
                  ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """:func:`probegrid.bake.kernels.grid.replay_radiance` of level ``depth``'s records (with
    its probe weights where it has them): the ``grid`` read at its hits, or the light
    ``gathered`` below them."""
    wi, ww = records.weight_index, records.weight
    if wi is None or ww is None:  # a level that reads no grid (the kernel reads no weights)
        if grid.shape[0]:  # (a bug, not bad input)
            raise RuntimeError(f"records {LEVEL_PREFIXES[depth] or 'of the probes'} read the "
                               "grid without their probe weights")
        wi, ww = np.zeros((0, 8), np.int32), np.zeros((0, 8), np.float32)
    none = np.zeros((0, 3), np.float32)  # (a gather level keeps no emission, and normals
    return replay_radiance(*frozen((  # only where its hits read the grid)
        ReplayRecords(records.kind, none if records.emission is None else records.emission,
                      records.light_punctual, records.light_emitters, records.albedo,
                      none if records.normal is None else records.normal, wi, ww),
        (grid, g), CUBE_AXES, level, gathered)))


def replay(arrays: Mapping[str, NDArray[Any]], settings: BakeSettings, level: int,
           cubes: NDArray[np.float32] | None, *, final: bool,
           indirect: NDArray[np.float32] | None = None,
           positions: NDArray[np.float64] | None = None
           ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """A pass over a batch's records (their stored arrays) at bounce ``level`` with the
    bordered irradiance ``cubes`` (None: a black grid) of the grid level the hits read:
    ``level - 1 - depth`` with ``depth`` gather levels (:func:`grid_level_read`).
    ``indirect`` (records without gather levels): the irradiance / pi of the light reflected
    at least once at each of the probes' rays' hits, read in the grid's place (a probe traced
    at a point reads it from the surface cache, :mod:`probegrid.bake.surfacecache`).

    Returns the probes' incoming cubes ``(B, 6, n, n, 3)`` float32 -- ``final``: what the probe
    sees (emission, its exact direct view of the emitters and the punctual lights included);
    otherwise the bounced light only -- and their texel radiances before the per-probe
    corrections (for the caller's bookkeeping). ``positions (B, 3)``: the probes' (where their
    rays start), which the final view's smoothing of the gather needs to tell surfaces apart
    (:func:`_smooth_gathered`; None: by their normals alone).
    """
    records = Records.from_arrays(arrays)
    levels = records.levels
    n, s = settings.face_size, settings.samples
    probes = records.probes
    b = len(probes)
    empty = np.zeros((0, 3), np.float32)
    depth = records.depth
    g = irradiance_size(depth > 0)
    grid = empty if cubes is None else cubes

    # gather levels, deepest first: its hits read the grid; each level above reads the light
    # the level below brings back (the rays' hits reflect at level - 1, theirs at level - 2)
    below = empty
    if indirect is not None:
        if depth:  # (a bug, not bad input)
            raise RuntimeError("records with gather levels read no indirect light")
        below = np.ascontiguousarray(indirect, np.float32)
    for d in range(depth, 0, -1):
        parents = len(levels[d - 1].kind)
        if level - d < 0:
            below = np.zeros((parents, 3), np.float32)
            continue
        _, reflected = _replay_level(levels[d], d, level - d, grid if d == depth else empty,
                                     below, g)
        primary = levels[d].primary
        assert primary is not None
        below = mean_per_parent(*frozen((primary, reflected)), parents)
    rad, bnc = _replay_level(levels[0], 0, level, empty if depth else grid, below, g)
    wts = (np.repeat(sample_pattern(settings)[1].reshape(1, -1), b, axis=0)
           if s > 1 else None)
    if (final and depth and level >= 2 and grid.shape[0]
            and levels[0].weight_index is not None):
        rad = _smooth_gathered(records, settings, rad, below, grid, g,
                               None if wts is None else wts.reshape(-1), positions)
    if not final and records.sky_sampled:
        # the environment reaches hits by sampling (light_emitters): the grid carries only
        # light reflected at least once, not what the probe's misses see of the sky
        bnc[levels[0].kind == 0] = 0.0
    use = rad if final else bnc
    if wts is not None:
        cube = texel_means(use, wts.reshape(-1), s)
    else:
        cube = use
    cube = cube.reshape(b, 6, n, n, 3)
    if final:
        vo, lo = records.view_offsets, records.lights_offsets
        for j in range(b):  # loop over probes: their sparse corrections
            flat = cube[j].reshape(-1, 3)
            tex = records.view_texel[vo[j]:vo[j + 1]]
            if tex.size:
                flat[tex] = np.maximum(
                    flat[tex].astype(np.float64) + records.view_value[vo[j]:vo[j + 1]], 0.0)
            if lo[j + 1] > lo[j]:
                cube[j] = splat_delta(cube[j], records.lights_direction[lo[j]:lo[j + 1]],
                                      records.lights_irradiance[lo[j]:lo[j + 1]])
    return cube, use
