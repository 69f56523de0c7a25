"""The final gather from the surface light cache: each probe's texels seen again, every hit
reading the light reflected at least once from the cache instead of two gather rays.

A probe's final pass shades each texel ray's hit with its direct light and the indirect light
of ``gather_samples`` cosine rays (:mod:`probegrid.bake.records`). Where the indirect light
comes from a few small bright patches (sunlight through a skylight's mullions on a floor), two
rays per hit rarely find them: two seeds of the sunlit hall of ``benchmarks/scenes.py`` differ
by 11 % over 4 x 4 texels, the reference's two renders by 2.8 %. The surface light cache
(:mod:`probegrid.bake.surfacecache`) holds that indirect light gathered with
:data:`~probegrid.bake.surfacecache.CACHE_GATHER` rays at the vertices of a lattice over every
triangle. With ``BakeSettings.final_gather = k``, the cache is built *before* the final pass,
from the grid that pass reads, and the pass renders each probe as
:class:`probegrid.bake.point.PointTracer` renders a point: ``k`` rays per texel (stratified, as
the bake's), each hit's direct light sampled there (the sun's shadow rays, the emitters' and
the sky's samples; the cache's direct light only where a lattice cell looks smaller than a
mirror texel) plus the cache's indirect light interpolated at the hit. The texels' own
patterns of light are then resolved by ``k`` rays, and the indirect light by many rays per
lattice vertex, which the hits of every probe share (Jensen's final gather over a photon map,
"Global Illumination Using Photon Maps", 1996; the radiance of a surface cache as Lumen reads it,
Wright et al., SIGGRAPH 2022 course).

The cache's lattice must be fine enough for the indirect light's variation (an interpolated
coarse lattice darkens what lies near a bright patch): the final gather's lattice
(:func:`final_gather_plan`, :func:`probegrid.bake.surfacecache.plan_lattice`) has
:data:`~probegrid.bake.surfacecache.CACHE_TEXEL_VERTICES` vertices per texel of a face *and
ray* of the final view instead of per texel (in the sunlit hall at faces 16 and ``k = 16``,
32,848 vertices, 0.35 m apart), each vertex gathering :data:`FINAL_GATHER_RAYS` rays
(the hits of every probe's ``k`` rays a texel average the vertices' noise, which a traced
point a few centimetres off a wall sees whole: the bake's own cache gathers
:data:`~probegrid.bake.surfacecache.CACHE_GATHER`); the iteration keeps every vertex's first
gather rays' hits in memory, which bounds it (:data:`FINAL_GATHER_MAX_VERTICES`, 300 MB).
Figures: docs/benchmarks.md (the sunlit hall). A final pass's random streams are the point
tracer's (keyed by the bake's seed and the probe's position), so a resumed bake draws the same
rays.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from probegrid.bake.environment import Environment
from probegrid.bake.point import PointTracer
from probegrid.bake.records import GridData
from probegrid.bake.settings import BakeSettings, TraceGeometry
from probegrid.bake.surfacecache import (
    ITERATE_MAX_RAYS,
    LatticePlan,
    SurfaceCache,
    plan_lattice,
)
from probegrid.raytrace import RayTracer
from probegrid.scene import Scene

__all__ = ["FINAL_GATHER_ITERATIONS", "FINAL_GATHER_MAX_VERTICES", "FINAL_GATHER_RAYS",
           "final_gather_plan", "final_gather_tracer"]

#: With a final gather, the cache's first gather rays a lattice vertex (stratified 8 x 8).
FINAL_GATHER_RAYS = 64
#: With a final gather, the cache's indirect light is gathered this many more times from the
#: cache itself (:func:`probegrid.bake.surfacecache.bake_surface_cache`'s ``iterations``).
FINAL_GATHER_ITERATIONS = 8
#: Most lattice vertices of a final gather's cache: those whose first gather rays the
#: iteration keeps (:data:`~probegrid.bake.surfacecache.ITERATE_MAX_RAYS`).
FINAL_GATHER_MAX_VERTICES = ITERATE_MAX_RAYS // FINAL_GATHER_RAYS


def final_gather_plan(scene: Scene, settings: BakeSettings) -> LatticePlan:
    """The surface cache's lattice of a bake with a final gather
    (:func:`probegrid.bake.surfacecache.plan_lattice`): by default that of a view of
    ``final_gather`` rays per texel, or the bake's ``surface_cache_spacing``, at most
    :data:`FINAL_GATHER_MAX_VERTICES` vertices."""
    return plan_lattice(scene, settings.surface_cache_spacing, face_size=settings.face_size,
                        rays=max(1, settings.final_gather),
                        max_vertices=FINAL_GATHER_MAX_VERTICES)


def final_gather_tracer(scene: Scene, environment: Environment, settings: BakeSettings,
                        geometry: TraceGeometry, data: GridData, *, level: int,
                        lattice: NDArray[np.int64], light: NDArray[np.float32],
                        tracer: RayTracer | None = None) -> PointTracer:
    """The point tracer of a bake's final gather: ``settings.final_gather`` rays per texel,
    no gather ray, each hit reading the cache ``lattice``, ``light``
    (:func:`probegrid.bake.surfacecache.bake_surface_cache`) on one thread."""
    depth = settings.gather_levels()
    st = settings.model_copy(update={"samples": settings.final_gather, "gather_samples": 0,
                                     "gather_depth": max(depth, 1)})
    cache = SurfaceCache(scene, lattice, light)
    return PointTracer(scene, environment, st, geometry, data, level=level,
                       diffuse_size=settings.diffuse_size, specular_levels=settings.levels(),
                       tracer=tracer, cache=cache, direct="sample", threads=1)

