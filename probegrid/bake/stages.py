"""The bake's stages as the workers run them: one task per stage, over a batch of probes.

Each stage is a pass over the whole grid on the executor (:mod:`probegrid.bake.executors`);
the driver (:mod:`probegrid.bake.driver`) writes what a task returns into the stage's
resumable store, and the bounce schedule (:mod:`probegrid.bake.schedule`) says which passes
run. A task is ``fn(state, batch) -> dict`` of per-probe arrays (plus ``"rays"``, the rays it
cast, and ``_``-prefixed values the driver keeps but does not store):

* :func:`classify_task` -- every probe shoots ``6 x CLASSIFY_FACE_SIZE^2`` rays and the inside
  test's rays (:mod:`probegrid.bake.inside`); an invalid probe may be moved to a nearby point
  that passes (:func:`probegrid.bake.placement.relocation_offsets`).
* :func:`trace_task` (bounce 0) -- every probe's rays cast once; the per-hit records are kept by
  the worker (:mod:`probegrid.bake.records`), the probe's distance moments and the irradiance
  cube of its bounced light returned.
* :func:`bounce_task` (bounce k) -- a pass over the records, no ray cast, reading a lower
  level's grid of irradiance cubes.
* :func:`final_task` -- what each probe sees, then its maps (:mod:`probegrid.bake.maps`): SH,
  the diffuse cube, the GGX chain, the distance moments.

The per-process state (:class:`StageState`) comes from :meth:`StageContext.setup`: the record
tracer (BVH, emitters' and environment's tables) is built once per process and bake. Results
depend only on the probe indices, never on the batch or the worker.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from probegrid.bake.environment import Environment
from probegrid.bake.inside import DIRECTIONS as INSIDE_DIRECTIONS
from probegrid.bake.inside import inside_solid
from probegrid.bake.maps import energy_ratio, filter_groups, sh_minima
from probegrid.bake.placement import relocation_offsets
from probegrid.bake.precision import fit_map_dtype
from probegrid.bake.records import (
    GridData,
    RecordTracer,
    all_hit_weights,
    gather_depth,
    has_hit_weights,
    hit_weights,
    irradiance_cubes,
    irradiance_size,
    load_records,
    records_file,
    remove_records,
    resolve_directory,
    save_records,
    select_probes,
    weighted_positions,
)
from probegrid.bake.records.replay import replay
from probegrid.bake.settings import BakeSettings, TraceGeometry
from probegrid.bake.view import ProbeView
from probegrid.core import sh
from probegrid.core.cubemap import solid_angle_integral
from probegrid.core.grid import GridSpec
from probegrid.raytrace import RayTracer
from probegrid.scene import Scene
from probegrid.store import ArraySpec

__all__ = ["CLASSIFY_FACE_SIZE", "StageContext", "StageState", "bounce_arrays", "bounce_task",
           "classify_arrays", "classify_task", "final_task", "load_npy", "trace_arrays",
           "trace_task"]


def load_npy(path: str) -> NDArray[Any]:
    """The read-only memory map of an ``.npy`` file."""
    return np.load(path, mmap_mode="r", allow_pickle=False)


@dataclass(frozen=True, eq=False)
class StageContext:
    """Per-bake-stage worker context: pickled once per worker, ``setup`` builds the BVH.

    The grid-sized arrays (probe positions and validity, the bordered distance moments, the
    previous bounce's bordered irradiance cubes, the moments to store) travel either as arrays
    (for Dask workers, which may not share this machine's files) or as ``.npy`` paths in the
    bake's work directory that ``setup`` memory-maps, so that a local worker's memory is bounded
    by its batch, not by the grid. They are the grid's small per-probe data; the per-hit records
    stay with the workers (``records``: a directory, absolute for workers on this machine, else
    a name under each worker's temporary directory; :mod:`probegrid.bake.records`).
    """

    scene: Scene
    environment: Environment
    settings: BakeSettings
    grid: GridSpec
    geometry: TraceGeometry  # (BakeSettings.trace_geometry of the scene and grid)
    positions: NDArray[np.float64] | str | None = None
    valid: NDArray[np.bool_] | str | None = None
    records: str = ""
    record_files: bool = True  # False: one worker process, which keeps its records in memory
    level: int = 0
    moments_bordered: NDArray[np.float32] | str | None = None
    cubes: NDArray[np.float32] | str | None = None
    moments: NDArray[np.float32] | str | None = None
    # the surface cache's lattice and light the final pass reads (BakeSettings.final_gather)
    surface_cache: tuple[NDArray[Any] | str, NDArray[Any] | str] | None = None
    key: str = ""  # the bake's fingerprint (scene, environment, plan): what the tracer depends on

    @property
    def block_size(self) -> int:
        """Probes per batch: the grid split into as few blocks of at most ``batch_size`` as it
        takes, of (nearly) equal sizes (27 probes in 4 batches of 7, not 8, 8, 8 and 3: the
        workers finish together). Each block's records are kept under its first probe."""
        p, bs = self.grid.n_probes, self.settings.batch_size
        return max(1, -(-p // max(1, -(-p // bs)))) if p else bs

    def records_path(self, batch: NDArray[np.int64]) -> Path:
        """The records directory of the block holding ``batch`` (a whole block or part of one)."""
        bs = self.block_size
        return records_file(resolve_directory(self.records), int(batch[0]) // bs * bs)

    def setup(self) -> StageState:
        """The worker's state for this stage: the bake's record tracer (reused when the process
        built it for an earlier stage of the same bake) and the grid-sized arrays."""
        import multiprocessing

        if multiprocessing.parent_process() is not None:
            # a worker process: one BLAS thread, the executor already runs one task per core
            from threadpoolctl import threadpool_limits

            threadpool_limits(1)
        positions, valid = _array(self.positions), _array(self.valid)
        tracer = _TRACERS.get(self.key) if self.key else None
        if tracer is None:  # built once per process and bake, not once per stage
            tracer = RecordTracer(self.scene, self.environment, self.settings, self.geometry,
                                  tracer=RayTracer.shared(self.scene))
            _TRACERS.clear()
            if self.key:
                _TRACERS[self.key] = tracer
        data = None
        if self.moments_bordered is not None:
            assert positions is not None and valid is not None
            mb = _array(self.moments_bordered)
            assert mb is not None
            cubes = _array(self.cubes)
            data = GridData(self.grid, valid, positions,
                            np.ascontiguousarray(mb).reshape(-1, mb.shape[-1]),
                            mb.shape[2] - 2,
                            None if cubes is None else np.ascontiguousarray(cubes).reshape(-1, 3),
                            tracer.tracer)
        return StageState(tracer, self, data, positions, valid, _array(self.moments))


#: The record tracer of the bake a process last worked for, by the bake's fingerprint
#: (:attr:`StageContext.key`): its stages then share the BVH, the emitters' tables and the
#: environment's sampling tables.
_TRACERS: dict[str, RecordTracer] = {}


def _array(a: NDArray[Any] | str | None) -> NDArray[Any] | None:
    """An array, or the read-only memory map of an ``.npy`` path."""
    return load_npy(a) if isinstance(a, str) else a


@dataclass
class StageState:
    """What a worker holds while it runs a stage's batches (:meth:`StageContext.setup`)."""

    tracer: RecordTracer
    ctx: StageContext
    data: GridData | None
    positions: NDArray[np.float64] | None
    valid: NDArray[np.bool_] | None
    moments: NDArray[np.float32] | None

    @property
    def view(self) -> ProbeView:
        """The scene as the probes' rays see it (the record tracer's)."""
        return self.tracer.view


#: Face size of the texel-centre rays that classify a probe as inside geometry.
CLASSIFY_FACE_SIZE = 8


def classify_arrays() -> dict[str, ArraySpec]:
    """The per-probe arrays :func:`classify_task` returns (the classify stage's store)."""
    return {
        "positions": ArraySpec((3,), "float64", "probe position"),
        "valid": ArraySpec((), "bool", "probe is outside geometry"),
        "backface_fraction": ArraySpec((), "float64", "backface ray fraction"),
    }


def bounce_arrays(settings: BakeSettings) -> dict[str, ArraySpec]:
    """The per-probe arrays :func:`bounce_task` returns: a level of the grid."""
    g = irradiance_size(settings.gather_levels() > 0)
    return {
        "irradiance": ArraySpec((6, g, g, 3), "float32", "irradiance / pi of bounced light"),
        "energy": ArraySpec((), "float64", "solid-angle integral of the bounced light"),
    }


def trace_arrays(settings: BakeSettings) -> dict[str, ArraySpec]:
    """The per-probe arrays :func:`trace_task` returns: level 0 of the grid, the distance
    moments and the backface fraction."""
    m = settings.moments_face_size
    return {**bounce_arrays(settings),
            "moments": ArraySpec((6, m, m, 2), "float32", "distance moments"),
            "backface_fraction": ArraySpec((), "float64", "backface ray fraction")}


def classify_task(state: StageState, batch: NDArray[np.int64]) -> dict[str, Any]:
    """Whether each probe of the batch is outside geometry (the backface fraction, the
    enclosure and the inside tests), and where: an invalid probe moves to the first nearby
    point that passes, with ``relocate``."""
    ctx = state.ctx
    lattice = ctx.grid.positions()[batch]
    # enclosed: every ray hits within this distance (inside a double-sided solid or a cavity
    # smaller than the grid resolves); 0 (no cell, or the setting 0) disables the test
    reach = ctx.settings.enclosure * ctx.grid.smallest_cell()

    def usable(points: NDArray[np.float64]) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
        frac, farthest = state.view.surroundings(points, face_size=CLASSIFY_FACE_SIZE)
        return ((frac <= ctx.settings.invalid_threshold) & ~(farthest <= reach)
                & ~inside_solid(state.view.tracer, ctx.scene, points)), frac

    valid, frac = usable(lattice)
    pos = lattice.copy()
    rays_per_point = 6 * CLASSIFY_FACE_SIZE**2 + INSIDE_DIRECTIONS
    rays = len(batch) * rays_per_point
    if ctx.settings.relocate and ctx.settings.relocate_fraction > 0:
        offsets = relocation_offsets(ctx.grid, ctx.settings.relocate_fraction)
        for j in np.flatnonzero(~valid):  # loop over invalid probes, not rays
            cand = lattice[j] + offsets
            good, f = usable(cand)
            rays += len(cand) * rays_per_point
            ok = np.flatnonzero(good)
            if ok.size:
                pos[j] = cand[ok[0]]
                frac[j] = f[ok[0]]
                valid[j] = True
    return {"positions": pos, "valid": valid, "backface_fraction": frac, "rays": rays}


def _block_records(state: StageState, batch: NDArray[np.int64]
                   ) -> tuple[dict[str, Any], Path | None, int]:
    """The records of ``batch``: from its block's file, or traced again when it is missing
    (deterministic: the same bits). Returns them, the block's file when they came from a whole
    block, and the rays cast."""
    ctx = state.ctx
    path = ctx.records_path(batch)
    rec = load_records(path)
    if rec is not None:
        whole = np.array_equal(rec["probes"], batch)
        sel = select_probes(rec, batch)
        if sel is not None:
            return sel, (path if whole else None), 0
    assert state.positions is not None
    rec, _, rays = state.tracer.trace(state.positions[batch], batch)
    return rec, None, rays


def _bounced_outputs(rec: dict[str, Any], settings: BakeSettings, level: int,
                     cubes: NDArray[np.float32] | None) -> dict[str, Any]:
    """A bounce's per-probe outputs: the irradiance cube of the bounced light and its energy."""
    cube, _ = replay(rec, settings, level, cubes, final=False)
    irr = irradiance_cubes(cube, irradiance_size(gather_depth(rec) > 0))
    energy = np.array([float(solid_angle_integral(c).sum()) for c in cube])
    return {"irradiance": irr, "energy": energy}


def trace_task(state: StageState, batch: NDArray[np.int64]) -> dict[str, Any]:
    """Cast every ray of the batch once, keep the records, return bounce 0's grid data."""
    assert state.positions is not None
    ctx = state.ctx
    rec, moments, rays = state.tracer.trace(state.positions[batch], batch)
    save_records(ctx.records_path(batch), rec, files=ctx.record_files)
    out = _bounced_outputs(rec, ctx.settings, 0, None)
    out.update(moments=moments, backface_fraction=rec["backface_fraction"], rays=rays)
    return out


def _weighted_records(state: StageState, batch: NDArray[np.int64], *, keep: bool = True
                      ) -> tuple[dict[str, Any], Path | None, int]:
    """The batch's records with each hit's probe weights (computed once, then kept when
    ``keep``)."""
    rec, path, rays = _block_records(state, batch)
    if not has_hit_weights(rec):
        assert state.data is not None
        new = all_hit_weights(rec, state.data)
        rec.update(new)
        gone = weighted_positions(rec)
        if path is not None and keep:
            save_records(path, new, drop=gone)
        for k in gone:
            rec.pop(k, None)
    return rec, path, rays


def bounce_task(state: StageState, batch: NDArray[np.int64]) -> dict[str, Any]:
    """One bounce over the batch's records: the grid data of level ``ctx.level``."""
    ctx = state.ctx
    rec, _, rays = _weighted_records(state, batch)
    assert state.data is not None
    out = _bounced_outputs(rec, ctx.settings, ctx.level, state.data.cubes)
    out["rays"] = rays
    return out


#: The final gather's point tracer of the bake a process last worked for (by its key).
_FINAL_TRACERS: dict[str, Any] = {}


def _final_gather_tracer(state: StageState) -> Any:
    """The final gather's point tracer (:func:`probegrid.bake.finalgather.final_gather_tracer`)
    of the stage, built once per process and bake."""
    from probegrid.bake.finalgather import final_gather_tracer

    ctx = state.ctx
    assert ctx.surface_cache is not None and state.data is not None
    pt = _FINAL_TRACERS.get(ctx.key)
    if pt is None or not ctx.key:
        lattice, light = (np.asarray(_array(a)) for a in ctx.surface_cache)
        pt = final_gather_tracer(ctx.scene, ctx.environment, ctx.settings, ctx.geometry,
                                 state.data, level=ctx.level, lattice=lattice, light=light,
                                 tracer=state.tracer.tracer)
        _FINAL_TRACERS.clear()
        if ctx.key:
            _FINAL_TRACERS[ctx.key] = pt
    return pt


def final_task(state: StageState, batch: NDArray[np.int64]) -> dict[str, Any]:
    """What each probe of the batch sees at the final level, and the maps the store keeps
    (:func:`probegrid.bake.settings.store_arrays`)."""
    from probegrid.core import seams

    ctx = state.ctx
    st = ctx.settings
    assert state.positions is not None and state.valid is not None
    assert state.moments is not None
    if ctx.surface_cache is not None:  # the final gather (probegrid.bake.finalgather)
        rec, path, rays = _block_records(state, batch)
        pt = _final_gather_tracer(state)
        incoming = pt.incoming(state.positions[batch])
        rays += int(incoming[..., 0].size) * st.final_gather
    elif ctx.level > 0:
        rec, path, rays = _weighted_records(state, batch, keep=False)
        cubes = None if state.data is None else state.data.cubes
        if gather_depth(rec) and ctx.level >= 2 and state.data is not None:
            # the rays' own probe weights: the final view spreads the gather's noise over
            # the texels around each hit, about the grid read at it (replay._smooth_gathered)
            rec = dict(rec)
            rec["weight_index"], rec["weight"] = hit_weights(rec, state.data)
    else:
        rec, path, rays = _block_records(state, batch)
        cubes = None
    if ctx.surface_cache is None:
        incoming, _ = replay(rec, ctx.settings, ctx.level, cubes, final=True,
                             positions=state.positions[batch])
    if path is not None:  # the block's last use: its records go (a retry traces them again)
        remove_records(path)
    levels = st.levels()
    out: dict[str, Any] = {
        "positions": state.positions[batch],
        "valid": state.valid[batch],
        "moments": np.asarray(state.moments[batch]),
        "rays": rays,
    }
    energy, seam = [], []
    # per probe: results must not depend on the batch
    sh_l = [sh.project_cube(cube) for cube in incoming]
    sh_min = sh_minima(np.stack(sh_l))
    dif, chains = filter_groups(incoming, st.diffuse_size, levels)
    spec = [[c[k] for c in chains] for k in range(levels)]
    for cube, d in zip(incoming, dif, strict=True):
        energy.append(energy_ratio(d, float(solid_angle_integral(cube).sum())))
        seam.append(seams.seam_score(d))
    out["sh"] = np.stack(sh_l).astype(np.float32)
    out["sh_min"] = sh_min.astype(np.float32)
    out["diffuse"] = np.stack(dif)
    for k in range(levels):
        out[f"specular_{k}"] = np.stack(spec[k])
    if st.store_incoming:
        out["incoming"] = incoming
    out["backface_fraction"] = np.asarray(rec["backface_fraction"]).astype(np.float32)
    out["_energy"] = np.array(energy)
    out["_seam"] = np.array(seam)
    fit_map_dtype(out, st.dtype)
    return out
