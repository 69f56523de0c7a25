"""The scene as a probe's rays see it: one scene's lookups shared by the bake's ray casting.

:class:`ProbeView` holds what the trace-once pass (:class:`probegrid.bake.records.RecordTracer`)
and the classification (:func:`probegrid.bake.stages.classify_task`) share for one scene: the
Embree tracer (:mod:`probegrid.raytrace`), the environment box-filtered to the texel footprint
(:attr:`probegrid.bake.settings.BakeSettings.environment_footprint`, so a sun smaller than a
texel keeps its energy), the punctual lights packed for the kernels and their shadow rays
(:meth:`ProbeView.visible_lights`), the solid angle of each probe ray's texel and the bins of
the visibility moments (per texel of a small ``moments_face_size`` cube, the
solid-angle-weighted mean distance and mean squared distance to the first hit, the inputs of
DDGI's Chebyshev test, Majercik et al. 2019), and :meth:`ProbeView.surroundings` (backface
fraction and farthest hit of a point, for the classification). The probes' ray directions are
:func:`probegrid.bake.pattern.sample_pattern`'s.

Everything here depends on the scene, the settings and the trace geometry only, and each query is
answered per ray or per point, so results do not depend on the batch or process that asks.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from probegrid.bake.environment import Environment
from probegrid.bake.kernels.lights import PunctualLights
from probegrid.bake.settings import BakeSettings, TraceGeometry
from probegrid.core.cubemap import texel_directions, texel_solid_angles
from probegrid.core.lights import incident_many
from probegrid.raytrace import RayTracer
from probegrid.scene import Scene

__all__ = ["ProbeView"]


class ProbeView:
    """One scene's ray tracer, environment lookup and per-ray tables (build once per process:
    it owns the BVH), shared by the classification (:meth:`surroundings`) and the trace-once
    pass (:class:`probegrid.bake.records.RecordTracer`)."""

    def __init__(
        self,
        scene: Scene,
        environment: Environment | None = None,
        settings: BakeSettings | None = None,
        geometry: TraceGeometry | None = None,
        *,
        tracer: RayTracer | None = None,
    ) -> None:
        self.scene = scene
        self.environment = environment or Environment()
        self.settings = settings or BakeSettings()
        self.geometry = geometry or TraceGeometry()
        self.tracer = tracer or RayTracer.from_scene(scene)
        #: The environment as the probes' rays see it (box-filtered to their texels).
        self.environment_view = self.environment.sampler(self.settings.environment_footprint)
        #: ``(T,)`` whether each triangle's back reflects too (the scene's).
        self.double_sided = scene.double_sided
        n, m = self.settings.face_size, self.settings.moments_face_size
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
        ``ray_offset`` off the point (along the normal when given). Through glass or partly
        covering surfaces, ``e_perp`` is scaled by the ray's expected transmittance
        (:meth:`probegrid.raytrace.RayTracer.transmittance`, per channel through a tinted
        pane).

        Returns
        -------
        directions (p, L, 3), e_perp (p, L, 3), visible (p, L) bool, rays cast
        """
        dirs, e_perp, dist = incident_many(self.scene.lights, points)
        lit = e_perp.max(axis=-1) > 0
        if normals is not None:
            lit &= np.einsum("pli,pi->pl", dirs, normals) > 0
        pi, li = np.nonzero(lit)
        eps = self.geometry.ray_offset
        origins = points[pi] if normals is None else points[pi] + eps * normals[pi]
        tmax = np.where(np.isfinite(dist[pi, li]), dist[pi, li] - eps, np.inf)
        visible = np.zeros(lit.shape, dtype=bool)
        if pi.size and self.tracer.coverage is not None:
            # through glass or a partly covering surface: the expected share (one ray would
            # give a probe all of a sun or none of it), folded into e_perp
            if self.tracer.tinted:  # (per channel: a tinted pane passes its tint)
                share = self.tracer.transmittance(origins, dirs[pi, li], tmax, tmin=eps,
                                                  rgb=True)
                visible[pi, li] = share.max(axis=1) > 0
                e_perp = e_perp.copy()
                e_perp[pi, li] *= share
            else:
                share = self.tracer.transmittance(origins, dirs[pi, li], tmax, tmin=eps)
                visible[pi, li] = share > 0
                e_perp = e_perp.copy()
                e_perp[pi, li] *= share[:, None]
        elif pi.size:
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
