"""What a bake adds to its store once every probe is written: deringed SH and the scene.

:func:`write_store_extras` is the one place that writes the store's extras (format 2, see
:mod:`probegrid.store.manifest`); the bake driver calls it just before publishing the store:

``sh_deringed (P, 9, 3) float32``
    Each probe's radiance SH windowed so that its irradiance is non-negative over the whole
    sphere (:func:`probegrid.core.sh.dering.dering`); equal to ``sh`` where that already holds.
``sh_window (P, 3) float32``
    The band factors ``(1, h_1, h_2)`` of each probe's window (``(1, 1, 1)``: not windowed).
``scene_vertices (V, 3) float32``, ``scene_triangles (T, 3) int32``
    The scene's triangle soup, so that queries can test the visibility between a point and the
    surrounding probes exactly (:class:`probegrid.query.ProbeField`). float32 is what Embree
    traces anyway; 12 bytes per vertex and per triangle.
``grid_irradiance (P, 6, g + 2, g + 2, 3) float32``
    The grid the final pass read: each probe's irradiance / pi cube of the light reflected at
    least once (the converged level, or its extrapolated limit) with its seamless one-texel
    border (:func:`probegrid.core.ddgi.bordered_cubes`, as the pass reads it); zeros for a bake
    of no bounce. With the bordered moments and the environment it is what a probe traced at
    any point needs (:class:`probegrid.bake.point.PointTracer`), memory-mapped as stored;
    ``6 (g + 2)^2 * 12`` bytes per probe (``g = 8`` with gather rays: 7.2 KB).
``moments_bordered (P, 6, m + 2, m + 2, 2) float32``
    ``moments`` with the same border (what the hits' probe weights read; 4.8 KB per probe at
    ``m = 8``). The two are about a tenth of the maps at face 32.
``environment (6, m, m, 3) float32``
    The environment cube the rays saw, box-filtered to the finest size the bake read it at
    (:func:`probegrid.bake.point.environment_extra`), without the rotation and intensity the
    manifest's ``bake.environment`` states; absent for a constant colour (described there).

The windows are chosen from the float32 ``sh`` as stored (so "already non-negative" is decided
on the values a reader sees), with :data:`probegrid.core.sh.dering.DEFAULT_MARGIN` of headroom for
the float32 rounding of the deringed coefficients.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from probegrid.bake.environment import Environment
from probegrid.bake.point import ENVIRONMENT_EXTRA, GRID_EXTRA, MOMENTS_EXTRA, environment_extra
from probegrid.bake.records import GridData, grid_level_read, irradiance_size
from probegrid.bake.settings import BakeSettings, TraceGeometry
from probegrid.bake.surfacecache import (
    CACHE_GATHER,
    LATTICE_EXTRA,
    LIGHT_EXTRA,
    LatticePlan,
    bake_surface_cache,
    plan_lattice,
)
from probegrid.core.ddgi import bordered_cubes
from probegrid.core.grid import GridSpec
from probegrid.core.sh.dering import dering
from probegrid.scene import Scene
from probegrid.store import StoreWriter

__all__ = ["write_store_extras"]


def write_store_extras(writer: StoreWriter, scene: Scene, *,
                       environment: Environment | None = None,
                       grid_irradiance: NDArray[np.float32] | None = None,
                       gather: bool = True, face_size: int = 32,
                       settings: BakeSettings | None = None,
                       geometry: TraceGeometry | None = None, level: int = 0,
                       cache: tuple[NDArray[np.int64], NDArray[np.float32], int] | None = None,
                       plan: LatticePlan | None = None) -> tuple[int, LatticePlan | None]:
    """Add ``sh_deringed``, ``sh_window``, ``scene_vertices`` and ``scene_triangles`` to the
    finished-but-unpublished store of ``writer`` (every probe written), and with an
    ``environment`` the ``grid_irradiance`` (``grid_irradiance``: the cubes the final pass read,
    None for none; ``gather``: the bake traced gather rays) and ``environment`` extras
    (``face_size``: the probes'), and with ``settings`` and ``geometry`` too the surface cache
    of the final pass at bounce ``level`` (with a ``plan``, ``cache`` is the one the final pass
    already built over its lattice, :mod:`probegrid.bake.finalgather`, None for none); see the
    module docstring.
    Idempotent: a resumed bake writes the same extras again. Returns the rays the surface
    cache cast and its lattice (None: no settings, no cache asked of the bake)."""
    raw = np.asarray(writer.array("sh"), dtype=np.float64)
    deringed, window, _ = dering(raw)
    writer.add_extra("sh_deringed", deringed.astype(np.float32),
                     description="radiance SH windowed per probe so that its irradiance is "
                                 "non-negative over the sphere (equal to sh where it was)")
    writer.add_extra("sh_window", window.astype(np.float32),
                     description="band factors (1, h1, h2) of each probe's deringing window")
    writer.add_extra("scene_vertices", np.asarray(scene.vertices, dtype=np.float32),
                     description="scene triangle vertices, world (for exact query visibility)")
    writer.add_extra("scene_triangles", np.asarray(scene.triangles, dtype=np.int32),
                     description="scene triangles: vertex indices into scene_vertices")
    if environment is None:
        return 0, None
    if grid_irradiance is None:
        g = irradiance_size(gather)
        grid_irradiance = np.zeros((writer.n_probes, 6, g, g, 3), np.float32)
    bordered = bordered_cubes(grid_irradiance)
    writer.add_extra(GRID_EXTRA, bordered,
                     description="irradiance / pi cubes of the light reflected at least once, "
                                 "the grid the final pass read, bordered (for probes traced at "
                                 "points)")
    writer.add_extra(MOMENTS_EXTRA, bordered_cubes(writer.array("moments")),
                     description="distance moments with their seamless border (for probes "
                                 "traced at points)")
    env = environment_extra(environment, face_size)
    if env is not None:
        writer.add_extra(ENVIRONMENT_EXTRA, env,
                         description="environment cube the rays saw, box-filtered, without the "
                                     "rotation and intensity of the manifest's bake.environment")
    if settings is None or geometry is None:
        return 0, None
    if plan is None:  # else the final gather's, already built (None: its plan has none)
        plan = plan_lattice(scene, settings.surface_cache_spacing,
                            face_size=settings.face_size)
        cache = surface_cache(scene, environment, settings, geometry, grid=writer.grid,
                              valid=writer.array("valid"), positions=writer.array("positions"),
                              moments=writer.array("moments"), bordered=bordered, level=level,
                              plan=plan)
    got = cache
    if got is None:  # no cache (spacing 0, or more triangles than its cap): queries gather
        return 0, plan
    lattice, light, rays = got
    writer.add_extra(LATTICE_EXTRA, lattice,
                     description="surface light cache: per triangle the first lattice vertex of "
                                 "its front, of its back (-1: one-sided) and its resolution "
                                 "(memory-mappable, probegrid.bake.surfacecache)")
    writer.add_extra(LIGHT_EXTRA, light,
                     description="surface light cache: irradiance / pi at each lattice vertex "
                                 "of the light reflected at least once and of the emitters' "
                                 "and environment's direct light (memory-mappable)")
    return rays, plan


def surface_cache(scene: Scene, environment: Environment, settings: BakeSettings,
                  geometry: TraceGeometry, *, grid: GridSpec, valid: NDArray[np.bool_],
                  positions: NDArray[np.float64], moments: NDArray[np.float32],
                  bordered: NDArray[np.float32], level: int, plan: LatticePlan,
                  iterations: int = 0, gather: int = CACHE_GATHER
                  ) -> tuple[NDArray[np.int64], NDArray[np.float32], int] | None:
    """The surface cache of a bake (:func:`probegrid.bake.surfacecache.bake_surface_cache`)
    of probes at ``positions`` (``valid``, their distance ``moments``) whose final pass, at
    bounce ``level``, reads the ``bordered`` irradiance cubes, over the lattice of ``plan``
    (the scene's, never the grid's), ``gather`` first gather rays a vertex, its indirect light
    gathered ``iterations`` more times from the cache itself."""
    moments = bordered_cubes(moments)
    depth = settings.gather_levels()
    data = GridData(grid, np.asarray(valid, bool), np.asarray(positions, np.float64),
                    moments.reshape(-1, moments.shape[-1]), moments.shape[2] - 2,
                    bordered.reshape(-1, 3) if grid_level_read(level, depth) >= 0 else None)
    return bake_surface_cache(scene, environment, settings, geometry, data, level=level,
                              plan=plan, iterations=iterations, gather=gather)
