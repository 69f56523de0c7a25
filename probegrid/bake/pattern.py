"""A probe's sample pattern: the directions of its rays and their weights within their texels.

For each probe, ``samples`` rays per texel of its ``face_size`` incoming cube leave the probe
position (:class:`probegrid.bake.settings.BakeSettings`); the texel holds the mean radiance its
rays bring back. The rays are jittered inside the texel by a seeded, deterministic pattern and
weighted by the cube's area element ``(1 + u^2 + v^2)^(-3/2)``, so the texel value estimates the
mean radiance over its solid angle (:func:`sample_pattern`): a box filter over the texel's
footprint. The samples of a texel are the first ``samples`` points of the R2 low-discrepancy
sequence (Roberts 2018), stratified over the texel, shifted by a random offset of that texel
(Cranley-Patterson rotation): one sample is a uniformly random point of its texel. Every texel
draws its own offset, so sharp patterns smaller than a texel (sun through a
mullioned skylight, seen on a floor) are sampled to their area fraction on average instead of
being aliased by rays through the texel centres, the same way in every texel (a regular pattern
of rays beats against a regular pattern of light: moire). On the sunlit hall of
``benchmarks/scenes.py``, lit by its sun alone, the rays through the texel centres left the
probes' diffuse maps 15.1 % off a path tracer (mean of 36 probes, 16^2 faces), the ray anywhere
in its texel 10.2 % (``benchmarks/bench_texels.py --sun-only``); what is left is noise, which
more rays per texel reduce (4 rays: 3.5 %, against 6.5 % with one offset for every texel).

Determinism
-----------
The offsets come from the bake's seed alone (:data:`PATTERN_STREAM`), the same for every probe
and every point the service traces: a probe's pattern depends neither on its batch or process
nor on its index, so a grid extended by layers of probes traces its inner probes with the same
rays (their random streams are keyed by position, :mod:`probegrid.bake.records.tracer`).
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from probegrid.bake.kernels.cube import CUBE_AXES, cube_sample_directions

if TYPE_CHECKING:
    from probegrid.bake.settings import BakeSettings

__all__ = ["sample_pattern"]

# R2 low-discrepancy sequence (Roberts 2018): the plastic number's inverse powers.
_PLASTIC = 1.32471795724474602596
_R2 = np.array([1.0 / _PLASTIC, 1.0 / _PLASTIC**2])


#: The spawn key of the pattern's offsets (beyond any probe's index: its own stream).
PATTERN_STREAM = (1 << 62) + 2


def sample_pattern(settings: BakeSettings) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Ray directions of a probe and their weights within their texels (read-only arrays,
    computed once per face size, sample count and seed).

    Returns
    -------
    directions : (6, n, n, s, 3) float64
        Unit directions, ``n = settings.face_size``, ``s = settings.samples`` per texel.
    weights : (6, n, n, s) float64
        Area-element weights normalised to sum to 1 over each texel's samples.
    """
    return _cached_pattern(settings.face_size, settings.samples, settings.seed)


@functools.lru_cache(maxsize=8)
def _cached_pattern(n: int, s: int, seed: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    dirs, wts = _pattern(n, _jitter(n, s, seed))
    dirs.flags.writeable = False
    wts.flags.writeable = False
    return dirs, wts


def _jitter(n: int, s: int, seed: int) -> NDArray[np.float64]:
    """``(6 n^2, s, 2)`` positions of the samples inside each texel, in ``[0, 1)^2``: the R2
    sequence shifted by each texel's random offset (:data:`PATTERN_STREAM` of ``seed``)."""
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(PATTERN_STREAM,)))
    shift = rng.random((6 * n * n, 1, 2))
    return np.mod(0.5 + np.arange(1, s + 1)[None, :, None] * _R2[None, None, :] + shift, 1.0)


def _pattern(n: int, jitter: NDArray[np.float64]) -> tuple[
    NDArray[np.float64], NDArray[np.float64]
]:
    # sample k of texel (row, col) at continuous texel coordinates (col - 0.5 + jitter_x,
    # row - 0.5 + jitter_y), weighted by the area element (1 + u^2 + v^2)^(-3/2)
    return cube_sample_directions(n, np.ascontiguousarray(jitter, dtype=np.float64), CUBE_AXES)
