"""The SH field: radiance SH traced on a lattice finer than the probes' and reaching the walls.

The probes of a default grid stand at cell centres (:func:`probegrid.bake.placement.grid_for`),
so the half cell between the outermost probes and the scene's walls -- where most surface points
are -- lies outside the probes' box, and a cell is wide where the light changes fast (under an
emitter, in a corner). ``/sh`` (:meth:`probegrid.query.ProbeField.sh_at`) interpolates instead an
SH-only field baked on a lattice of its own: the box of the grid's cells (the probes' box grown
by half a cell each side, the scene's box for a default grid), inset by :data:`INSET` of a
lattice step from each face, with ``refine`` lattice steps per probe cell (``refine * n + 1``
points along an axis of ``n`` probes). Each lattice point is a probe traced there against the
converged bake (:class:`probegrid.bake.point.PointTracer`, the final pass's sibling) at a low
face size -- three SH bands need about 8 (a ``6 x 8^2`` cube resolves the clamped-cosine lobe)
-- and projected to SH; a point whose rays see too many back faces (inside a solid, the bake's
``invalid_threshold``) is invalid, as a probe would be.

The field is traced after the surface light cache (:mod:`probegrid.bake.surfacecache`) and
reads it as a traced ``/maps`` answer of :data:`FIELD_QUALITY` does: the point's rays alone
are cast, the punctual lights' shadow rays and the emitters' exact view stay exact, and every
hit reads the light reflected at least once and the emitters' and environment's direct light
from the cache, interpolated over its lattice, instead of gathering it (a bake without a cache
gathers with the bake's own estimator). Against Mitsuba 3 that is as accurate as the gather
(the cache averages 64 gather rays where a hit gathers 2) at a sixth of the cost.

Cost: ``(refine n + 1)^3 / n^3`` points (about 8 at ``refine = 2``) of ``6 face^2`` rays where a
probe traces ``6 face_size^2`` (16 times more at 8 against 32), a shadow ray per punctual light
and a cache lookup per hit; the probes cast gather rays and light samples at every hit and pass
over their records once per bounce. Measured in ``docs/benchmarks.md``.

Store extras (memory-mapped as stored; :data:`SH_FIELD_EXTRAS`):

``sh_field_lattice (3, 3) float64``
    Rows ``bounds_min``, ``bounds_max`` and ``counts`` of the lattice (a
    :class:`probegrid.core.grid.GridSpec`; point ``(i, j, k)`` has linear index
    ``(i ny + j) nz + k``).
``sh_field (M, 9, 3) float32``
    Radiance SH at every lattice point, deringed (:func:`probegrid.core.sh.dering.dering`).
``sh_field_raw (M, 9, 3) float32``
    The projection before deringing.
``sh_field_valid (M,) bool``
    False for a point inside a solid.

References: G. J. Ward and P. S. Heckbert, "Irradiance Gradients", 1992 (why a coarse cache
fails near walls and emitters); Unity's Adaptive Probe Volumes (probes denser where lighting
varies; here uniformly, bounded by the bake's cost).
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from probegrid.bake.point import PointSettings, PointTracer
from probegrid.bake.surfacecache import LATTICE_EXTRA, LIGHT_EXTRA
from probegrid.core import sh as shlib
from probegrid.core.grid import GridSpec
from probegrid.core.sh.dering import dering
from probegrid.scene import Scene
from probegrid.store import StoreWriter

__all__ = ["FIELD_QUALITY", "INSET", "SH_FIELD_EXTRAS", "field_lattice", "field_settings",
           "lattice_from_extra", "trace_sh_field", "write_sh_field"]

#: Distance of the lattice's outer layers from the cells' box (the walls), in lattice steps.
INSET: Final = 0.1
#: The store extras of the SH field (module docstring).
SH_FIELD_EXTRAS: Final = ("sh_field_lattice", "sh_field", "sh_field_raw", "sh_field_valid")
#: Lattice points traced at once (bounds the records' memory: about 6 face^2 hits each).
BATCH: Final = 256
#: The point preset (:data:`probegrid.bake.point.POINT_PRESETS`) the field's points are traced
#: with when the store has a surface cache: their rays' hits read the cache.
FIELD_QUALITY: Final = "fast"


def field_settings(has_cache: bool, face_size: int) -> PointSettings:
    """How the field's points are traced: :data:`FIELD_QUALITY` at ``face_size`` texels a face
    with a surface cache, the bake's own gather without one."""
    ps = PointSettings.preset(FIELD_QUALITY) if has_cache else PointSettings(indirect="gather")
    return dataclasses.replace(ps, face_size=int(face_size))


def field_lattice(grid: GridSpec, refine: float) -> GridSpec:
    """The SH field's lattice for the probes of ``grid``: the box of its cells inset by
    :data:`INSET` steps, ``round(refine n) + 1`` points along an axis of ``n`` probes (at
    least 2: an axis of one probe gets its cell's two faces)."""
    if not (np.isfinite(refine) and refine > 0):
        raise ValueError(f"refine must be > 0, got {refine!r}.")
    n = np.asarray(grid.counts, dtype=np.int64)
    lo, hi = np.asarray(grid.bounds_min, np.float64), np.asarray(grid.bounds_max, np.float64)
    cell = np.where(n > 1, (hi - lo) / np.maximum(n - 1, 1), 0.0)
    if np.any(cell == 0):  # an axis of one probe: the other axes' smallest cell
        cell = np.where(cell == 0, grid.smallest_cell(default=1.0), cell)
    box_lo, box_hi = lo - 0.5 * cell, hi + 0.5 * cell
    counts = np.maximum(np.round(refine * n).astype(np.int64) + 1, 2)
    step = (box_hi - box_lo) / (counts - 1)
    return GridSpec.from_counts(box_lo + INSET * step, box_hi - INSET * step,
                                tuple(int(c) for c in counts))


def lattice_from_extra(table: Any) -> GridSpec:
    """The lattice of a store's ``sh_field_lattice`` extra."""
    t = np.asarray(table, dtype=np.float64)
    return GridSpec.from_counts(t[0], t[1], tuple(int(c) for c in t[2]))


def trace_sh_field(tracer: PointTracer, lattice: GridSpec, *, invalid_threshold: float
                   ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """``(sh (M, 9, 3) float64, valid (M,))``: the radiance SH of probes traced at every
    lattice point (in batches of :data:`BATCH`) and their validity."""
    points = lattice.positions()
    out = np.empty((len(points), 9, 3), np.float64)
    back = np.empty(len(points), np.float64)
    for s in range(0, len(points), BATCH):  # a loop over batches of points
        cubes, b = tracer._incoming(points[s:s + BATCH])
        m, _, n, _, c = cubes.shape  # the batch's points as channels of one projection
        flat = shlib.project_cube(np.moveaxis(cubes, 0, 3).reshape(6, n, n, m * c))
        out[s:s + BATCH] = flat.reshape(-1, m, c).transpose(1, 0, 2)
        back[s:s + BATCH] = b
    return out, back <= invalid_threshold


class _UnpublishedStore(SimpleNamespace):
    """What :meth:`PointTracer.from_store` reads of a store, for one not yet published: the
    writer's arrays and extras and the bake's plan and final level."""


def _unpublished(writer: StoreWriter, plan: dict[str, Any], level: int) -> _UnpublishedStore:
    from probegrid.bake.point import ENVIRONMENT_EXTRA, GRID_EXTRA, MOMENTS_EXTRA

    extras = {name for name in (GRID_EXTRA, MOMENTS_EXTRA, ENVIRONMENT_EXTRA, LATTICE_EXTRA,
                                LIGHT_EXTRA)
              if (writer.partial_path / f"{name}.npy").is_file()}
    arrays = {name: np.load(writer.partial_path / f"{name}.npy", mmap_mode="r")
              for name in extras}
    arrays["valid"] = writer.array("valid")
    arrays["positions"] = writer.array("positions")
    manifest = SimpleNamespace(bake=plan, extras=sorted(extras), quality={"bounces": level})
    return _UnpublishedStore(manifest=manifest, arrays=arrays, grid=writer.grid,
                             path=writer.path)


def write_sh_field(writer: StoreWriter, scene: Scene, *, plan: dict[str, Any], level: int,
                   refine: float, face_size: int, invalid_threshold: float,
                   tracer: Any = None) -> GridSpec:
    """Trace the SH field of a bake whose probes, point-tracing extras and surface cache
    (:func:`probegrid.bake.extras.write_store_extras`; its points read the cache,
    :func:`field_settings`) are written, and add its extras
    (module docstring) to ``writer``; returns the lattice. ``plan`` is the manifest's ``bake``
    (settings, render, environment), ``level`` the final pass's bounce level."""
    store = _unpublished(writer, plan, level)
    has_cache = {LATTICE_EXTRA, LIGHT_EXTRA} <= set(store.manifest.extras)
    pt = PointTracer.from_store(store, scene, tracer=tracer,
                                settings=field_settings(has_cache, face_size))
    lattice = field_lattice(writer.grid, refine)
    raw, valid = trace_sh_field(pt, lattice, invalid_threshold=invalid_threshold)
    deringed, _, _ = dering(raw)
    table = np.array([lattice.bounds_min, lattice.bounds_max, lattice.counts], np.float64)
    writer.add_extra("sh_field_lattice", table,
                     description="SH field lattice: rows bounds_min, bounds_max, counts "
                                 "(probegrid.bake.shfield)")
    writer.add_extra("sh_field", deringed.astype(np.float32),
                     description="radiance SH traced at every SH field lattice point, deringed")
    writer.add_extra("sh_field_raw", raw.astype(np.float32),
                     description="radiance SH traced at every SH field lattice point, raw")
    writer.add_extra("sh_field_valid", valid,
                     description="SH field lattice points outside solids")
    return lattice
