"""The probe's view of a scene: sample patterns, render settings and the shared per-scene state.

For each probe, one ray per texel sample leaves the probe position; the texel holds the mean
radiance its rays bring back (:class:`RenderSettings.samples` rays per texel, jittered inside
the texel by a seeded, deterministic pattern and weighted by the cube's area element
``(1 + u^2 + v^2)^(-3/2)``, so the texel value estimates the mean radiance over its solid angle;
:func:`sample_pattern`). The rays are cast once, by the trace-once pass of
:mod:`probegrid.bake.records`, which keeps a record of every hit and replays it per bounce.

:class:`ProbeRenderer` holds what that pass and the classification share for one scene: the
Embree tracer (:mod:`probegrid.raytrace`), the environment box-filtered to the texel footprint
(:attr:`RenderSettings.environment_footprint`, so a sun smaller than a texel keeps its energy),
the punctual lights packed for the kernels with their shadow rays, the per-texel solid angles
and the bins of the visibility moments (per texel of a small ``moments_size`` cube, the
solid-angle-weighted mean distance and mean squared distance to the first hit, the inputs of
DDGI's Chebyshev test, Majercik et al. 2019), and :meth:`ProbeRenderer.surroundings` (backface
fraction and farthest hit of a point, for the classification).

Determinism
-----------
A probe's jitter comes from :func:`probegrid.bake.executors.probe_rng` (its seed and linear index),
rays are traced independently and every reduction is done per probe, so a probe's result does
not depend on which batch or process rendered it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
from numpy.typing import NDArray

from probegrid.bake.environment import Environment
from probegrid.bake.executors import probe_rng
from probegrid.bake.kernels.cube import CUBE_AXES, cube_sample_directions
from probegrid.bake.kernels.lights import PunctualLights
from probegrid.core.cubemap import texel_directions, texel_solid_angles
from probegrid.core.lights import incident_many
from probegrid.raytrace import RayTracer
from probegrid.scene import Scene

__all__ = [
    "ProbeRenderer",
    "RenderSettings",
    "sample_pattern",
]

# R2 low-discrepancy sequence (Roberts 2018): the plastic number's inverse powers.
_PLASTIC = 1.32471795724474602596
_R2 = np.array([1.0 / _PLASTIC, 1.0 / _PLASTIC**2])


#: Rays shaded together: every per-ray temporary of a chunk stays in cache-sized, reused memory
#: (a whole batch of probes at once spends much of its time in page faults). Each ray's result
#: does not depend on its chunk.
SHADE_CHUNK = 1 << 15


@dataclass(frozen=True)
class RenderSettings:
    """How a probe's incoming cube is rendered.

    Attributes
    ----------
    face_size : int
        Face size of the incoming cube.
    samples : int
        Rays per texel. 1 shoots through the texel centre; more are an R2 low-discrepancy
        pattern with a per-probe random shift (Cranley-Patterson rotation).
    seed : int
        Bake seed; a probe's randomness depends on it and the probe's index only.
    moments_size : int
        Face size of the visibility-moments cube.
    direct : bool
        Fold the punctual lights' direct light into the probe's cube.
    ray_offset : float
        Distance rays start off a surface (shadow rays, metres).
    max_distance : float
        Distance recorded for misses in the moments.
    """

    face_size: int = 32
    samples: int = 1
    seed: int = 0
    moments_size: int = 8
    direct: bool = True
    ray_offset: float = 1e-4
    max_distance: float = 1e3

    @property
    def environment_footprint(self) -> int:
        """Face size of the environment cube misses read (box-filtered to it,
        :meth:`probegrid.bake.environment.Environment.sampler`): the incoming cube's, whatever the
        samples per texel. A texel holds the mean radiance over its solid angle, and each of its
        rays then reads the environment's mean over a texel-sized footprint, so the texel mean
        keeps the environment's energy (measured on venice_sunset at 32^2: sunward irradiance
        exact, worst texel 1.1 %; a finer footprint of 64^2 with 4 samples: 3.3 %); more samples
        still resolve the edges of geometry inside the texel."""
        return self.face_size

    def __post_init__(self) -> None:
        for name in ("face_size", "samples", "moments_size"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if self.face_size % self.moments_size:
            raise ValueError(
                f"moments_size {self.moments_size} must divide face_size {self.face_size}"
            )
        if not (self.ray_offset > 0 and np.isfinite(self.ray_offset)):
            raise ValueError(f"ray_offset must be > 0, got {self.ray_offset}")
        if not (self.max_distance > 0 and np.isfinite(self.max_distance)):
            raise ValueError(f"max_distance must be > 0, got {self.max_distance}")


def sample_pattern(settings: RenderSettings, probe_index: int) -> tuple[
    NDArray[np.float64], NDArray[np.float64]
]:
    """Ray directions of one probe and their weights within their texels.

    Returns
    -------
    directions : (6, n, n, s, 3) float64
        Unit directions, ``s = settings.samples`` per texel.
    weights : (6, n, n, s) float64
        Area-element weights normalised to sum to 1 over each texel's samples.
    """
    if settings.samples == 1:  # texel centres: the same for every probe
        return _centre_pattern(settings.face_size)
    return _sample_pattern(settings, probe_index)


@lru_cache(maxsize=8)
def _centre_pattern(n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    d, w = _sample_pattern(RenderSettings(face_size=n, moments_size=1), 0)
    d.setflags(write=False)
    w.setflags(write=False)
    return d, w


def _jitter(settings: RenderSettings, probe_index: int) -> NDArray[np.float64]:
    """``(s, 2)`` positions of a probe's samples inside every texel, in ``[0, 1)^2``: the
    centre for one sample, else the R2 sequence shifted by the probe's random offset."""
    s = settings.samples
    if s == 1:
        return np.array([[0.5, 0.5]])
    shift = probe_rng(settings.seed, probe_index).random(2)
    return np.mod(0.5 + np.arange(1, s + 1)[:, None] * _R2[None, :] + shift, 1.0)


def _sample_pattern(settings: RenderSettings, probe_index: int) -> tuple[
    NDArray[np.float64], NDArray[np.float64]
]:
    n = settings.face_size
    jitter = _jitter(settings, probe_index)
    # sample k of texel (row, col) at continuous texel coordinates (col - 0.5 + jitter_x,
    # row - 0.5 + jitter_y), weighted by the area element (1 + u^2 + v^2)^(-3/2)
    return cube_sample_directions(n, np.ascontiguousarray(jitter, dtype=np.float64), CUBE_AXES)


class ProbeRenderer:
    """One scene's ray tracer, environment lookup and per-texel tables (build once per process:
    it owns the BVH), shared by the classification (:meth:`surroundings`) and the trace-once
    pass (:class:`probegrid.bake.records.RecordTracer`)."""

    def __init__(
        self,
        scene: Scene,
        environment: Environment | None = None,
        settings: RenderSettings | None = None,
        *,
        tracer: RayTracer | None = None,
    ) -> None:
        self.scene = scene
        self.environment = environment or Environment()
        self.settings = settings or RenderSettings()
        self.tracer = tracer or RayTracer.from_scene(scene)
        #: The environment as the probes' rays see it (box-filtered to their texels).
        self.environment_view = self.environment.sampler(self.settings.environment_footprint)
        #: ``(T,)`` whether each triangle's back reflects too (the scene's).
        self.double_sided = scene.double_sided
        n, m = self.settings.face_size, self.settings.moments_size
        f, r, c = np.meshgrid(np.arange(6), np.arange(n), np.arange(n), indexing="ij")
        k = n // m
        bins = (f * m + r // k) * m + c // k  # moments texel of every incoming texel
        #: The moments texel of each of a probe's rays (texel by texel, ``samples`` each).
        self.moment_bins = np.repeat(bins.reshape(-1), self.settings.samples)
        #: The solid angle of each of a probe's rays' texels (texel by texel).
        self.ray_solid_angles = np.repeat(texel_solid_angles(n).reshape(-1),
                                          self.settings.samples)

    # -- lights ---------------------------------------------------------------------------

    def visible_lights(
        self, points: NDArray[np.float64], normals: NDArray[np.float64] | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], int]:
        """Which punctual lights reach which points, by shadow rays.

        One shadow ray per (point, light) pair that could deliver light (``E_perp > 0`` and, when
        ``normals (p, 3)`` are given, the light in front of the surface), starting
        ``ray_offset`` off the point (along the normal when given).

        Returns
        -------
        directions (p, L, 3), e_perp (p, L, 3), visible (p, L) bool, rays cast
        """
        dirs, e_perp, dist = incident_many(self.scene.lights, points)
        lit = e_perp.max(axis=-1) > 0
        if normals is not None:
            lit &= np.einsum("pli,pi->pl", dirs, normals) > 0
        pi, li = np.nonzero(lit)
        eps = self.settings.ray_offset
        origins = points[pi] if normals is None else points[pi] + eps * normals[pi]
        tmax = np.where(np.isfinite(dist[pi, li]), dist[pi, li] - eps, np.inf)
        visible = np.zeros(lit.shape, dtype=bool)
        if pi.size:
            visible[pi, li] = ~self.tracer.occluded(origins, dirs[pi, li], tmax, tmin=eps)
        return dirs, e_perp, visible, len(pi)

    @cached_property
    def punctual_lights(self) -> PunctualLights:
        """The scene's punctual lights as the kernels take them."""
        return PunctualLights.of(self.scene.lights)

    # -- classification -------------------------------------------------------------------

    def backface_fraction(self, positions: NDArray[np.float64], *, face_size: int = 8
                          ) -> NDArray[np.float64]:
        """Fraction of ``6 face_size^2`` texel-centre rays from each point that hit a backface.

        A cheap test for probes inside geometry; ``positions (B, 3)``, returns ``(B,)``.
        Double-sided materials have no back.
        """
        return self.surroundings(positions, face_size=face_size)[0]

    def surroundings(self, positions: NDArray[np.float64], *, face_size: int = 8
                     ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """What ``6 face_size^2`` texel-centre rays from each point find: the fraction that hit a
        backface (:meth:`backface_fraction`) and the distance of the farthest hit (inf when a
        ray misses), which tells a point enclosed by a small closed surface -- inside a
        double-sided solid, whose inside shows no backface -- from one in open space.

        ``positions (B, 3)``; returns two ``(B,)`` float64 arrays.
        """
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        d = texel_directions(face_size).reshape(-1, 3)
        dirs = np.tile(d, (len(pos), 1))
        hits = self.tracer.intersect(np.repeat(pos, len(d), axis=0), dirs)
        prim = hits.prim_id
        back = self.tracer.backface(prim, dirs) & ~self.double_sided[np.maximum(prim, 0)]
        farthest = np.where(prim < 0, np.inf, hits.t).reshape(len(pos), -1).max(axis=1)
        return back.reshape(len(pos), -1).mean(axis=1), farthest
