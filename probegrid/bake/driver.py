"""``probegrid bake``: a probe grid of a scene, multi-bounce, into a memory-mappable store.

Stages (each a pass over the whole grid on the executor, each resumable):

1. **classify** -- every probe shoots ``6 x 8^2`` rays; a probe whose rays hit backfaces more
   than ``invalid_threshold`` of the time is inside geometry (the RTXGI classifier's test, 25 %
   by default). So is a probe all of whose rays hit within ``enclosure`` times the smallest cell
   size (default half a cell): inside a double-sided solid, whose inside shows no backface, or a
   cavity smaller than the grid resolves (a closed room larger than that is not affected; 0
   turns the test off). So is a probe inside a closed solid by the geometry's authored winding,
   double-sided or not (:mod:`probegrid.bake.inside`). With ``relocate``, an invalid probe is
   moved to the nearest point of a small lattice within ``relocate_fraction`` of a cell that
   passes the tests; otherwise it stays invalid and every reader gives it zero weight.
2. **trace** (bounce 0) -- every probe's rays are cast once
   (:class:`probegrid.bake.records.RecordTracer`: primary rays, shadow rays toward the punctual
   lights and toward points sampled on the emitters at every hit, the probe's own rays toward
   the lights and the emitter pieces of its direct view); the worker keeps per-hit records in
   per-block work files (``NAME.probes.work/records/``, or its temporary directory on a Dask
   worker) and returns only the probe's small data: distance moments and the irradiance cube of
   its bounced light at level 0.
3. **bounce 1 .. B-1** -- a pass over the records per bounce, no ray cast
   (:func:`probegrid.bake.records.replay`): each gather ray's hit (each hit, without gather
   rays) reads a lower level's irradiance cubes of its 8 probes (DDGI weights computed once, in
   the first pass, and kept with the records);
   only the grid's per-probe irradiance cubes move between the driver and the workers. With
   ``bounces="converge"`` the passes go on until the estimated limit of the grid's total energy
   (over valid probes; :mod:`probegrid.bake.converge`) changes by less than ``tolerance``
   (relative), at most ``max_bounces``; the final pass then reads the grid extrapolated to that
   limit. With gather rays a pass at level ``k`` reads the grid of level ``k - 2``, so a
   ``bounces = B`` bake makes the grids up to level ``B - 2`` only.
4. **final** (bounce B) -- a last pass gives what each probe sees (emission, its exact direct
   view of the emitters, the punctual lights folded in), then per probe: SH coefficients, the
   diffuse cube (exact clamped-cosine convolution, irradiance / pi), the GGX specular chain, the
   distance moments and, optionally, the raw incoming cube, written to the store. The block's
   records are deleted after their last use.

So ``bounces = B`` gives light from emitters and the environment that has bounced B times off
the scene's surfaces (a furnace box reads ``Le (1 - rho^(B+1)) / (1 - rho)``; punctual lights,
as before, add one reflection more, lit by shadow rays at every hit). The store's manifest
records the settings, the scene and environment hash, the conventions and the quality figures
(``bounces`` reached, ``bounce_passes``, ``bounce_residual``, ``bounce_energy`` per level,
``bounce_extrapolation`` and ``bounce_energy_limit``). A killed bake leaves only
``.partial``/``.work`` directories, which never load as a store, and the same command resumes
from the probes it finished. Results depend only on the settings and seed, not on the executor,
the number of workers or the batch size.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import shutil
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from probegrid import usercache
from probegrid.bake.converge import Convergence, convergence
from probegrid.bake.environment import Environment
from probegrid.bake.executors import Executor, InlineExecutor, Progress, make_batches
from probegrid.bake.extras import write_store_extras
from probegrid.bake.inside import DIRECTIONS as INSIDE_DIRECTIONS
from probegrid.bake.inside import inside_solid
from probegrid.bake.nolight import light_quality, printable
from probegrid.bake.precision import fit_map_dtype
from probegrid.bake.records import (
    GridData,
    RecordTracer,
    all_hit_weights,
    gather_depth,
    grid_level_read,
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
from probegrid.bake.render import ProbeRenderer, RenderSettings
from probegrid.bake.settings import BakeSettings, store_arrays
from probegrid.core import probefilter, sh
from probegrid.core.conventions import conventions
from probegrid.core.cubemap import solid_angle_integral
from probegrid.core.ddgi import bordered_cubes
from probegrid.core.dering import irradiance_minimum
from probegrid.core.grid import GridSpec
from probegrid.raytrace import RayTracer
from probegrid.scene import Scene
from probegrid.store import (
    ArraySpec,
    BakeInputs,
    ProbeStore,
    StoreWriter,
    create_npy,
    directory_lock,
    keepable_scene,
    open_store,
    partial_path,
)
from probegrid.store.manifest import check_store_name, work_path

__all__ = ["BakeReport", "BakeSettings", "bake", "environment_hash", "store_arrays"]

ProgressFn = Callable[[str, Progress, int], None]


def environment_hash(env: Environment) -> str:
    """Content hash of an environment (part of the store's scene hash)."""
    h = hashlib.sha256()
    h.update(repr((env.intensity, env.rotation, env.color.tolist())).encode())
    if env.faces is not None:
        h.update(np.ascontiguousarray(env.faces, dtype="<f4").tobytes())
    return h.hexdigest()


# ------------------------------------------------------------------------------ work files
def _load(path: str) -> NDArray[Any]:
    """The read-only memory map of an ``.npy`` file."""
    return np.load(path, mmap_mode="r", allow_pickle=False)


def _save_npy(path: Path, array: NDArray[Any]) -> Path:
    """Write ``array`` to ``path`` (disk blocks reserved first: a full disk is an OSError here,
    not a SIGBUS in a worker later)."""
    out = create_npy(path, array.dtype, array.shape)
    out[...] = array
    out.flush()
    del out
    return path


# ------------------------------------------------------------------------------ worker side
@dataclass(frozen=True, eq=False)
class _Context:
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
    render: RenderSettings
    settings: BakeSettings
    grid: GridSpec
    positions: NDArray[np.float64] | str | None = None
    valid: NDArray[np.bool_] | str | None = None
    records: str = ""
    record_files: bool = True  # False: one worker process, which keeps its records in memory
    level: int = 0
    moments_bordered: NDArray[np.float32] | str | None = None
    cubes: NDArray[np.float32] | str | None = None
    moments: NDArray[np.float32] | str | None = None
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

    def setup(self) -> _State:
        import multiprocessing

        if multiprocessing.parent_process() is not None:
            # a worker process: one BLAS thread, the executor already runs one task per core
            from threadpoolctl import threadpool_limits

            threadpool_limits(1)
        positions, valid = _array(self.positions), _array(self.valid)
        tracer = _TRACERS.get(self.key) if self.key else None
        if tracer is None:  # built once per process and bake, not once per stage
            tracer = RecordTracer(self.scene, self.environment, self.render,
                                  light_samples=self.settings.light_samples,
                                  gather_samples=(self.settings.gather_samples
                                                  if self.settings.gather_levels() else 0),
                                  gather_depth=max(self.settings.gather_levels(), 1),
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
                            None if cubes is None else np.ascontiguousarray(cubes).reshape(-1, 3))
        return _State(tracer, self, data, positions, valid, _array(self.moments))


#: The record tracer of the bake a process last worked for, by the bake's fingerprint
#: (:attr:`_Context.key`): its stages then share the BVH, the emitters' tables and the
#: environment's sampling tables.
_TRACERS: dict[str, RecordTracer] = {}


def _array(a: NDArray[Any] | str | None) -> NDArray[Any] | None:
    """An array, or the read-only memory map of an ``.npy`` path."""
    return _load(a) if isinstance(a, str) else a


@dataclass
class _State:
    tracer: RecordTracer
    ctx: _Context
    data: GridData | None
    positions: NDArray[np.float64] | None
    valid: NDArray[np.bool_] | None
    moments: NDArray[np.float32] | None

    @property
    def renderer(self) -> ProbeRenderer:
        return self.tracer.renderer


#: Face size of the texel-centre rays that classify a probe as inside geometry.
CLASSIFY_FACE_SIZE = 8


def _relocation_offsets(steps: int = 2) -> NDArray[np.float64]:
    """Lattice offsets in [-1, 1]^3 (without 0), nearest first, ties in a fixed order."""
    k = np.arange(-steps, steps + 1) / steps
    g = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3)
    g = g[np.any(g != 0, axis=1)]
    order = np.lexsort((g[:, 2], g[:, 1], g[:, 0], np.linalg.norm(g, axis=1)))
    return g[order]


def _classify_task(state: _State, batch: NDArray[np.int64]) -> dict[str, Any]:
    ctx = state.ctx
    lattice = ctx.grid.positions()[batch]
    # enclosed: every ray hits within this distance (inside a double-sided solid or a cavity
    # smaller than the grid resolves); 0 (no cell, or the setting 0) disables the test
    reach = ctx.settings.enclosure * ctx.grid.smallest_cell()

    def usable(points: NDArray[np.float64]) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
        frac, farthest = state.renderer.surroundings(points, face_size=CLASSIFY_FACE_SIZE)
        return ((frac <= ctx.settings.invalid_threshold) & ~(farthest <= reach)
                & ~inside_solid(state.renderer.tracer, ctx.scene, points)), frac

    valid, frac = usable(lattice)
    pos = lattice.copy()
    rays_per_point = 6 * CLASSIFY_FACE_SIZE**2 + INSIDE_DIRECTIONS
    rays = len(batch) * rays_per_point
    if ctx.settings.relocate and ctx.settings.relocate_fraction > 0:
        cell = np.where(np.array(ctx.grid.counts) > 1, ctx.grid.cell_size, 0.0)
        offsets = _relocation_offsets() * (ctx.settings.relocate_fraction * cell)
        offsets = offsets[np.any(offsets != 0, axis=1)]
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


def _block_records(state: _State, batch: NDArray[np.int64]
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


def _bounced_outputs(rec: dict[str, Any], settings: RenderSettings, level: int,
                     cubes: NDArray[np.float32] | None) -> dict[str, Any]:
    """A bounce's per-probe outputs: the irradiance cube of the bounced light and its energy."""
    cube, _ = replay(rec, settings, level, cubes, final=False)
    irr = irradiance_cubes(cube, irradiance_size(gather_depth(rec) > 0))
    energy = np.array([float(solid_angle_integral(c).sum()) for c in cube])
    return {"irradiance": irr, "energy": energy}


def _trace_task(state: _State, batch: NDArray[np.int64]) -> dict[str, Any]:
    """Cast every ray of the batch once, keep the records, return bounce 0's grid data."""
    assert state.positions is not None
    ctx = state.ctx
    rec, moments, rays = state.tracer.trace(state.positions[batch], batch)
    save_records(ctx.records_path(batch), rec, files=ctx.record_files)
    out = _bounced_outputs(rec, ctx.render, 0, None)
    out.update(moments=moments, backface_fraction=rec["backface_fraction"], rays=rays)
    return out


def _weighted_records(state: _State, batch: NDArray[np.int64], *, keep: bool = True
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


def _bounce_task(state: _State, batch: NDArray[np.int64]) -> dict[str, Any]:
    """One bounce over the batch's records: the grid data of level ``ctx.level``."""
    ctx = state.ctx
    rec, _, rays = _weighted_records(state, batch)
    assert state.data is not None
    out = _bounced_outputs(rec, ctx.render, ctx.level, state.data.cubes)
    out["rays"] = rays
    return out


def _final_task(state: _State, batch: NDArray[np.int64]) -> dict[str, Any]:
    from probegrid.core import seams

    ctx = state.ctx
    st = ctx.settings
    assert state.positions is not None and state.valid is not None
    assert state.moments is not None
    if ctx.level > 0:
        rec, path, rays = _weighted_records(state, batch, keep=False)
        cubes = None if state.data is None else state.data.cubes
        if gather_depth(rec) and ctx.level >= 2 and state.data is not None:
            # the rays' own probe weights: the final view spreads the gather's noise over
            # blocks around the grid read at each hit (records._smooth_gathered)
            rec = dict(rec)
            rec["weight_index"], rec["weight"] = hit_weights(rec, state.data)
    else:
        rec, path, rays = _block_records(state, batch)
        cubes = None
    incoming, _ = replay(rec, ctx.render, ctx.level, cubes, final=True)
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
    sh_min = _sh_minima(np.stack(sh_l))
    dif, chains = _filter_groups(incoming, st.diffuse_size, levels)
    spec = [[c[k] for c in chains] for k in range(levels)]
    for cube, d in zip(incoming, dif, strict=True):
        energy.append(_energy_ratio(d, float(solid_angle_integral(cube).sum())))
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


def _energy_ratio(diffuse: NDArray[np.float32], incoming_integral: float) -> float:
    """Solid-angle integral of a diffuse map over that of its incoming cube (all channels):
    1 for an energy-conserving filter, since the clamped cosine / pi integrates to 1 over the
    normals. NaN for a probe that receives no light (nothing to conserve)."""
    if not incoming_integral > 0:
        return math.nan
    return float(solid_angle_integral(diffuse).sum()) / incoming_integral


def _incoming_integral_from_sh(sh_l: NDArray[Any]) -> float:
    """The incoming cube's integral over the sphere from its stored SH, all channels:
    ``integral L = L_00 / Y_00 = 2 sqrt(pi) L_00`` (the projection is the same discrete sum)."""
    return float(2.0 * math.sqrt(math.pi) * np.asarray(sh_l, np.float64)[0].sum())


#: Probes filtered together, as channels of one cube (a fixed shape, see _filter_groups).
FILTER_GROUP = 8


def _padded_groups(items: NDArray[Any]) -> Iterator[tuple[int, int, NDArray[Any]]]:
    """``(start, count, group)`` for FILTER_GROUP items of ``items (B, ...)`` at a time, the
    last group padded with zeros: every group has the same shape, so what is computed from an
    item does not depend on which items share its group, i.e. on the batch."""
    b = len(items)
    for g0 in range(0, b, FILTER_GROUP):  # loop over groups of probes
        k = min(FILTER_GROUP, b - g0)
        group = np.zeros((FILTER_GROUP, *items.shape[1:]), items.dtype)
        group[:k] = items[g0:g0 + k]
        yield g0, k, group


def _sh_minima(coeffs: NDArray[np.float64]) -> NDArray[np.float64]:
    """Minimum over the sphere of SH irradiance / pi of ``coeffs (B, 9, 3)``; ``(B, 3)``: the
    certified minimum of :func:`probegrid.core.dering.irradiance_minimum` (what ``/sh``'s
    deringing holds to; each probe's and channel's result does not depend on the others).
    It replaced :func:`probegrid.core.sh.min_over_sphere`'s sampled search, 25x slower here,
    which missed the global minimum of 9 in 36 000 ringing probes (``tests/test_dering.py``)."""
    return irradiance_minimum(np.moveaxis(coeffs, 1, 2)) / np.pi


def _unstack_probes(cube: NDArray[np.float32], channels: int) -> NDArray[np.float32]:
    """``(6, m, m, G * C)`` -> ``(G, 6, m, m, C)``: undo the probes-as-channels stacking."""
    m = cube.shape[1]
    return np.moveaxis(cube.reshape(6, m, m, -1, channels), 3, 0)


def _filter_groups(cubes: NDArray[np.float32], diffuse_size: int, levels: int
                   ) -> tuple[list[NDArray[np.float32]], list[list[NDArray[np.float32]]]]:
    """Diffuse maps and GGX chains of ``cubes (B, 6, n, n, 3)``.

    The filters are linear and act on each channel alike, so FILTER_GROUP probes go through one
    call as the channels of a single cube, which amortises the per-call work
    (:func:`_padded_groups`: every call has the same shape). Faces up to
    :data:`probegrid.core.probefilter.MAX_FACE` go through the exact sums as one cached matrix
    (:func:`probegrid.core.probefilter.filter_cube`); larger ones through
    :func:`~probegrid.core.diffuse.diffuse_exact` and the tiered
    :func:`~probegrid.core.specular.ggx_prefilter` (:func:`probegrid.core.probefilter.describe`, in the
    manifest, says which).
    """
    from probegrid.core import diffuse, specular

    _, _, n, _, c = cubes.shape
    dense = probefilter.supported(n, diffuse_size)
    dif: list[NDArray[np.float32]] = []
    chains: list[list[NDArray[np.float32]]] = []
    matrix = usercache.probe_filter_matrix(n, diffuse_size, levels) if dense else None
    for _, k, group in _padded_groups(cubes):
        stacked = np.ascontiguousarray(np.moveaxis(group, 0, 3).reshape(6, n, n, -1))
        if dense:
            d, chain = probefilter.filter_cube(stacked, diffuse_size, levels, matrix=matrix)
        else:
            d = diffuse.diffuse_exact(stacked, diffuse_size)
            chain = specular.ggx_prefilter(stacked, levels=levels)

        ds = _unstack_probes(d, c)
        cs = [_unstack_probes(lv, c) for lv in chain]
        for j in range(k):
            dif.append(np.ascontiguousarray(ds[j]))
            chains.append([np.ascontiguousarray(lv[j]) for lv in cs])
    return dif, chains


# ------------------------------------------------------------------------------ driver
@dataclass
class BakeReport:
    """What a bake did: the store, timing and throughput, quality figures."""

    store: ProbeStore
    seconds: float
    rays: int
    probes: int
    resumed_probes: int
    quality: dict[str, Any]

    def summary(self) -> str:
        q = {k: printable(v) for k, v in self.quality.items()}
        return "\n".join([
            f"baked {self.probes} probes ({self.store.grid.label}) into {self.store.path}/ in "
            f"{self.seconds:.1f} s, {self.rays / max(self.seconds, 1e-9) / 1e6:.2f} Mrays/s"
            + (f" ({self.resumed_probes} probes resumed)" if self.resumed_probes else ""),
            (f"  invalid probes: {q['invalid_probes']} (relocated {q['relocated_probes']}); "
            f"backface rays {q['backface_ray_fraction']:.3%}"),
            (f"  energy (diffuse / incoming): worst |1 - ratio| {q['energy_max_error']:.2e}; "
            f"raw SH min irradiance/pi {q['sh_min_irradiance_over_pi']:.4g}"
            + (" (ringing: the deringed SH that /sh serves is >= 0)"
               if (self.quality.get("sh_min_irradiance_over_pi") or 0.0) < 0 else "") + "; "
            f"seam score {q['seam_score_mean']:.2e}"),
        ])


def _jsonable(obj: Any) -> Any:
    return json.loads(json.dumps(obj))


def _bake_lock(work: Path, out: Path) -> AbstractContextManager[None]:
    """One bake of a store at a time: an exclusive lock on its work directory, held for the
    whole bake (a second bake of the same store, ``--overwrite`` or not, is refused instead of
    deleting the first one's files)."""
    return directory_lock(work, busy=f"another process is baking {out}")


@dataclass
class _Stages:
    """Runs the bake's stages into (resumable) stores and counts their rays and seconds.

    Holds what every stage shares: the executor, the bake's plan and scene hash (a finished
    intermediate stage of the same bake is reused) and the progress callback.
    """

    executor: Executor
    plan: dict[str, Any]
    scene_hash: str
    on_progress: ProgressFn | None
    rays: int = 0
    seconds: dict[str, float] = field(default_factory=dict)

    def run(
        self,
        name: str,
        path: Path,
        arrays: dict[str, ArraySpec],
        fn: Callable[[_State, NDArray[np.int64]], dict[str, Any]],
        ctx: _Context,
        *,
        overwrite: bool = False,
        intermediate: bool = True,
        extra: Callable[[NDArray[np.int64], dict[str, Any]], None] | None = None,
    ) -> tuple[StoreWriter | ProbeStore, int]:
        """Run one stage into a store; returns the writer (unfinished) and the probes resumed."""
        grid = ctx.grid
        if intermediate and path.exists():
            done = open_store(path)
            if (done.manifest.scene_hash != self.scene_hash
                    or done.manifest.bake != _jsonable(self.plan)):
                raise ValueError(
                    f"{path.parent} holds an interrupted bake with other settings or another "
                    "scene; pass --overwrite to start again"
                )
            return done, grid.n_probes
        writer = StoreWriter.create_or_resume(
            path, arrays=arrays, grid=grid, conventions=conventions(),
            scene_hash=self.scene_hash, bake=self.plan, overwrite=overwrite, durable=False,
        )
        resumed = writer.n_done
        batches = make_batches(grid.n_probes, batch_size=ctx.block_size, done=writer.done)
        started = time.perf_counter()

        def progress(p: Progress) -> None:
            if self.on_progress is not None:
                self.on_progress(name, p, self.rays)

        for batch, result in self.executor.map(fn, ctx, batches, progress=progress):
            self.rays += int(result.pop("rays"))
            if extra is not None:
                extra(batch, result)
            writer.write(batch, {k: v for k, v in result.items() if not k.startswith("_")})
        self.seconds[name] = time.perf_counter() - started
        return writer, resumed


def bake(
    scene: Scene,
    grid: GridSpec,
    out: str | Path,
    *,
    settings: BakeSettings | None = None,
    environment: Environment | None = None,
    executor: Executor | None = None,
    progress: ProgressFn | None = None,
    overwrite: bool = False,
    scene_file: str | Path | None = None,
    allow_black: bool = True,
    inputs: BakeInputs | None = None,  # (manifest ``inputs``: the scene/environment as given)
) -> BakeReport:
    """Bake a probe grid of ``scene`` into the store ``out`` (``NAME.probes``).

    Resumes an interrupted bake of the same scene and settings. ``executor`` defaults to the
    calling process (:class:`~probegrid.bake.executors.InlineExecutor`); the CLI passes local
    processes or a Dask cluster. ``scene_file``, the glTF file ``scene`` was loaded from, is
    kept in the store for viewers (see :func:`probegrid.store.writer.keepable_scene`).
    ``allow_black=False`` stops before finishing a store none of whose valid probes received
    light (:func:`probegrid.bake.nolight.light_quality`; the CLI's default).
    """
    st = settings or BakeSettings()
    env = environment or Environment()
    ex = executor or InlineExecutor(check_pickle=False)
    out = Path(out)
    check_store_name(out)
    if out.exists() and not overwrite:
        raise ValueError(f"{out} exists; pass --overwrite to replace it")
    st.levels()  # validate
    if scene_file is not None:
        keepable_scene(scene_file)  # readable glTF, checked before any work
    render = st.render_settings(scene, grid)
    scene_hash = hashlib.sha256(
        (scene.content_hash() + environment_hash(env)).encode()
    ).hexdigest()
    # (the batch size is left out: it changes no bit of the result, so a bake may resume with
    # another one)
    plan = {"settings": st.model_dump(exclude={"batch_size"}), "environment": env.describe(),
            "render": {"ray_offset": render.ray_offset, "max_distance": render.max_distance,
                       "moments_size": render.moments_size,
                       "environment_lookup_size": env.lookup_size(
                           render.environment_footprint)},
            "filters": probefilter.describe(st.face_size, st.diffuse_size)}
    work = work_path(out)
    work.mkdir(parents=True, exist_ok=True)
    with _bake_lock(work, out):
        # An interrupted bake of this store resumes when it had the same scene and plan; with
        # ``overwrite`` one of another scene or plan is dropped (without it, an error).
        stamp = work / "bake.json"
        fingerprint = json.dumps({"scene": scene_hash, "plan": _jsonable(plan)}, sort_keys=True)
        if overwrite and not (stamp.is_file() and stamp.read_text() == fingerprint):
            for child in work.iterdir():
                if child.is_dir():
                    shutil.rmtree(child)
                else:
                    child.unlink()
            shutil.rmtree(partial_path(out), ignore_errors=True)
        stamp.write_text(fingerprint)
        stages = _Stages(ex, plan, scene_hash, progress)
        t0 = time.perf_counter()
        base = _Context(scene, env, render, st, grid,
                        key=hashlib.sha256((fingerprint + repr(render)).encode()).hexdigest())

        # 1. classify
        cls_arrays = {
            "positions": ArraySpec((3,), "float64", "probe position"),
            "valid": ArraySpec((), "bool", "probe is outside geometry"),
            "backface_fraction": ArraySpec((), "float64", "backface ray fraction"),
        }
        w, resumed = stages.run("classify", work / "classify.probes", cls_arrays, _classify_task,
                                base)
        cls_store = w.finish() if isinstance(w, StoreWriter) else w
        positions = np.array(cls_store["positions"])
        valid = np.array(cls_store["valid"])
        lattice = grid.positions()
        relocated = int(np.count_nonzero(np.any(positions != lattice, axis=1)))
        # Workers on this machine memory-map the grid-sized arrays from the work directory; others
        # (a Dask cluster) receive them.
        files = bool(getattr(ex, "shares_files", False))
        probe_pos: NDArray[np.float64] | str = positions
        probe_valid: NDArray[np.bool_] | str = valid
        if files:
            probe_pos = str(work / "classify.probes" / "positions.npy")
            probe_valid = str(work / "classify.probes" / "valid.npy")

        # 2. trace once: every probe's rays, kept as per-hit records by the workers; bounce 0
        records = (str(work / "records") if files
                   else "probegrid-records-" + hashlib.sha256(
                       (str(out.resolve()) + fingerprint).encode()).hexdigest()[:16])
        m = render.moments_size
        g = irradiance_size(st.gather_levels() > 0)
        grid_arrays = {
            "irradiance": ArraySpec((6, g, g, 3), "float32", "irradiance / pi of bounced light"),
            "energy": ArraySpec((), "float64", "solid-angle integral of the bounced light"),
        }
        trace_arrays = {**grid_arrays,
                        "moments": ArraySpec((6, m, m, 2), "float32", "distance moments"),
                        "backface_fraction": ArraySpec((), "float64", "backface ray fraction")}
        converge = st.bounces == "converge"
        cap = st.max_bounces if converge else int(st.bounces)

        def label(k: int, residual: float | None, final: bool = False) -> str:
            if not converge:
                return f"bounce {k} of {cap}" + (" (final)" if final else
                                                 " (tracing)" if k == 0 else "")
            r = "-" if residual is None else f"{100 * residual:.2g} %"
            if final:
                return f"converged: bounce {k}, residual {r} (final)"
            return "tracing: bounce 0" if k == 0 else f"converging: bounce {k}, residual {r}"

        # one worker process on this machine reads every block it wrote: its records stay in
        # its memory (written only if they outgrow it); several workers share them as files
        base = dataclasses.replace(base, record_files=not (files and ex.workers == 1))
        ctx = dataclasses.replace(base, positions=probe_pos, valid=probe_valid, records=records)
        w, _ = stages.run(label(0, None), work / "trace.probes", trace_arrays, _trace_task, ctx)
        tstore = w.finish() if isinstance(w, StoreWriter) else w
        moments_all: NDArray[np.float32] | str = np.array(tstore["moments"])
        bordered = bordered_cubes(tstore["moments"])
        moments_b: NDArray[np.float32] | str = bordered
        if files:
            moments_all = str(work / "trace.probes" / "moments.npy")
            moments_b = str(_save_npy(work / "moments_bordered.npy", bordered))

        def grid_cubes(store: StoreWriter | ProbeStore, k: int) -> NDArray[np.float32] | str:
            cubes = bordered_cubes(store["irradiance"])
            return str(_save_npy(work / f"irradiance{k}.npy", cubes)) if files else cubes

        def grid_energy(store: StoreWriter | ProbeStore) -> float:
            return float(np.sum(np.asarray(store["energy"])[valid]))

        depth = st.gather_levels()
        cubes_at: dict[int, NDArray[np.float32] | str] = {0: grid_cubes(tstore, 0)}

        def cubes_for(k: int) -> NDArray[np.float32] | str | None:
            """The grid a pass at bounce k reads (records.grid_level_read)."""
            return cubes_at.get(grid_level_read(k, depth))

        energies = [grid_energy(tstore)]
        irradiance_at = {0: tstore["irradiance"]}
        residual: float | None = None
        state = Convergence(False, None)
        step = 1 + depth  # the final pass at level L reads the grid of level L - step
        period = max(step, 2)  # increments that cycle together (probegrid.bake.converge)
        k = 0
        while True:  # bounce k: a pass over the records that makes the grid of level k
            if not converge and k >= grid_level_read(cap, depth):
                level = cap
                break
            if converge and k + step >= cap:
                level = cap
                break
            k += 1
            ctx = dataclasses.replace(base, positions=probe_pos, valid=probe_valid,
                                      records=records, level=k, moments_bordered=moments_b,
                                      cubes=cubes_for(k))
            w, _ = stages.run(label(k, residual), work / f"bounce{k}.probes", grid_arrays,
                              _bounce_task, ctx)
            bstore = w.finish() if isinstance(w, StoreWriter) else w
            cubes_at[k] = grid_cubes(bstore, k)
            irradiance_at[k] = bstore["irradiance"]
            energies.append(grid_energy(bstore))
            if converge:
                state = convergence(energies, st.tolerance, period)
                residual = state.residual
                if state.done:
                    level = k + step
                    break
        final_cubes = cubes_for(level) if level > 0 else None
        if state.factor is not None and k >= period:
            # the final pass reads the extrapolated limit of the grid (bake.converge)
            g_k = np.asarray(irradiance_at[k], dtype=np.float64)
            limit = g_k + (g_k - np.asarray(irradiance_at[k - period], np.float64)) * state.factor
            cubes = bordered_cubes(limit.astype(np.float32))
            final_cubes = (str(_save_npy(work / "irradiance_limit.npy", cubes)) if files
                           else cubes)

        # 3. final
        energy = np.full(grid.n_probes, np.nan)
        seam = np.full(grid.n_probes, np.nan)

        def keep(batch: NDArray[np.int64], result: dict[str, Any]) -> None:
            energy[batch] = result["_energy"]
            seam[batch] = result["_seam"]

        ctx = dataclasses.replace(base, positions=probe_pos, valid=probe_valid,
                                  records=records, level=level, moments_bordered=moments_b,
                                  cubes=final_cubes, moments=moments_all)
        w, resumed = stages.run(label(level, residual, final=True), out, store_arrays(st),
                                _final_task, ctx, overwrite=overwrite, intermediate=False,
                                extra=keep)
        assert isinstance(w, StoreWriter)
        # quality over every probe (resumed ones included): recompute from the stored arrays
        dif = w.array("diffuse")
        sh_min = w.array("sh_min")
        back = w.array("backface_fraction")
        missing = np.isnan(seam)
        if missing.any():
            from probegrid.core import seams

            stored_sh = w.array("sh")
            for i in np.flatnonzero(missing):  # probes finished by an earlier, interrupted run
                d = np.asarray(dif[i])
                seam[i] = seams.seam_score(d)
                energy[i] = _energy_ratio(d, _incoming_integral_from_sh(stored_sh[i]))
        valid_e = energy[~np.isnan(energy)]
        quality = {
            "invalid_probes": int(np.count_nonzero(~valid)),
            "relocated_probes": relocated,
            "backface_ray_fraction": float(np.mean(back)),
            "energy_max_error": float(np.max(np.abs(1 - valid_e))) if valid_e.size else None,
            "energy_check": "solid-angle integral of each probe's diffuse map over that of its "
                            "incoming cube (1 for a correct, energy-conserving filter)",
            "sh_min_irradiance_over_pi": float(np.min(sh_min)),
            "sh_min_negative_probes": int(np.count_nonzero(np.min(sh_min, axis=1) < 0)),
            "seam_score_mean": float(np.nanmean(seam)),
            "bounces": level,
            "bounce_residual": residual,
            "bounce_passes": k,
            "bounce_energy": energies,
            "rays": stages.rays,
            "stage_seconds": {k: round(v, 3) for k, v in stages.seconds.items()},
        }
        if state.factor is not None:  # converged by extrapolation (probegrid.bake.converge)
            quality["bounce_extrapolation"] = state.factor
            quality["bounce_energy_limit"] = state.limit
        quality = light_quality(quality, w.array("sh"), valid, allow_black=allow_black)
        write_store_extras(w, scene)  # deringed SH, scene triangles (probegrid.bake.extras)
        store = w.finish(quality=quality, scene_file=scene_file, inputs=inputs)
        shutil.rmtree(work, ignore_errors=True)
        if not files:  # (this machine's Dask workers' record directory, emptied block by block)
            shutil.rmtree(resolve_directory(records), ignore_errors=True)

        seconds = time.perf_counter() - t0
        return BakeReport(store, seconds, stages.rays, grid.n_probes, resumed, quality)
