"""``probegrid bake``: a probe grid of a scene, multi-bounce, into a memory-mappable store.

:func:`bake` runs the stages (:mod:`probegrid.bake.stages`; each a pass over the whole grid on
the executor, each resumable) in its work directory ``NAME.probes.work/``, under a lock:

1. **classify** -- every probe shoots ``6 x 8^2`` rays; a probe whose rays hit backfaces more
   than ``invalid_threshold`` of the time is inside geometry (the RTXGI classifier's test, 25 %
   by default). So is a probe all of whose rays hit within ``enclosure`` times the smallest cell
   size (default half a cell): inside a double-sided solid, whose inside shows no backface, or a
   cavity smaller than the grid resolves (a closed room larger than that is not affected; 0
   turns the test off). So is a probe inside a closed solid by the geometry's authored winding,
   double-sided or not (:mod:`probegrid.bake.inside`). With ``relocate``, an invalid probe is
   moved to the nearest point of a small lattice within ``relocate_fraction`` of a cell that
   passes the tests (:func:`probegrid.bake.placement.relocation_offsets`); otherwise it stays
   invalid and every reader gives it zero weight.
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
   only the grid's per-probe irradiance cubes move between the driver and the workers. Which
   passes run, and when ``bounces="converge"`` stops and extrapolates, is the bounce schedule's
   (:mod:`probegrid.bake.schedule`, :mod:`probegrid.bake.converge`).
4. **final** (bounce B) -- a last pass gives what each probe sees (emission, its exact direct
   view of the emitters, the punctual lights folded in), then per probe: SH coefficients, the
   diffuse cube (exact clamped-cosine convolution, irradiance / pi), the GGX specular chain, the
   distance moments and, optionally, the raw incoming cube (:mod:`probegrid.bake.maps`), written
   to the store. The block's records are deleted after their last use.

So ``bounces = B`` gives light from emitters and the environment that has bounced B times off
the scene's surfaces (a furnace box reads ``Le (1 - rho^(B+1)) / (1 - rho)``; punctual lights,
as before, add one reflection more, lit by shadow rays at every hit). The store's manifest
records the settings, the scene and environment hash, the conventions and the quality figures
(``bounces`` reached, ``bounce_passes``, ``bounce_residual``, ``bounce_energy`` per level,
``bounce_extrapolation`` and ``bounce_energy_limit``). A killed bake leaves only
``.partial``/``.work`` directories, which never load as a store, and the same command resumes
from the probes it finished; a bake that fails on its own verdict (a ``ValueError``: no light,
a bad input found late) deletes its work directory and partial store (a lost worker or a full
disk does not: the bake resumes). The work directory is keyed by the scene, the grid and the plan: a
bake with another key deletes what it holds (and the final stage's ``.partial``) and starts
clean. A symbolic link at the work directory's name is unlinked, never followed; the finished
store is published by :func:`probegrid._fs.publish_directory` (the path holds the old or the
new store at every instant, the old one deleted afterwards). Results depend only on the settings and seed, not on the executor,
the number of workers or the batch size.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from probegrid._fs import atomic_write_text, recover_publish, remove_path
from probegrid.bake.emitters import Emitters
from probegrid.bake.environment import Environment
from probegrid.bake.executors import Executor, InlineExecutor, Progress, make_batches
from probegrid.bake.extras import surface_cache, write_store_extras
from probegrid.bake.finalgather import (
    FINAL_GATHER_ITERATIONS,
    FINAL_GATHER_RAYS,
    final_gather_plan,
)
from probegrid.bake.shfield import write_sh_field
from probegrid.bake.inputs import check_bake_inputs
from probegrid.bake.maps import energy_ratio, incoming_integral_from_sh
from probegrid.bake.nolight import light_quality, printable
from probegrid.bake.records import irradiance_size, resolve_directory
from probegrid.bake.schedule import BounceSchedule
from probegrid.bake.settings import BakeSettings, store_arrays
from probegrid.bake.stages import (
    StageContext,
    StageState,
    bounce_arrays,
    bounce_task,
    classify_arrays,
    classify_task,
    final_task,
    trace_arrays,
    trace_task,
)
from probegrid.core import probefilter
from probegrid.core.conventions import conventions
from probegrid.core.ddgi import bordered_cubes
from probegrid.core.grid import GridSpec
from probegrid.scene import Scene
from probegrid.store import (
    ArraySpec,
    BakeInputs,
    ProbeStore,
    StoreWriter,
    create_npy,
    directory_lock,
    open_store,
    partial_path,
)
from probegrid.store.manifest import work_path

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
def _save_npy(path: Path, array: NDArray[Any]) -> Path:
    """Write ``array`` to ``path`` (disk blocks reserved first: a full disk is an OSError here,
    not a SIGBUS in a worker later)."""
    out = create_npy(path, array.dtype, array.shape)
    out[...] = array
    out.flush()
    del out
    return path


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
        ] + ([f"  emitters: {q['emitter_sampling']}"]
             if self.quality.get("emitter_sampling", "no emitters") != "no emitters" else [])
          + self._unhonoured_lines())

    def _unhonoured_lines(self) -> list[str]:
        """What the scene file uses that the bake did not honour (manifest ``inputs``)."""
        inputs = getattr(self.store.manifest, "inputs", None)
        names = inputs.scene.unhonoured if inputs is not None else ()
        return [f"  not honoured: {'; '.join(names)}"] if names else []


def _jsonable(obj: Any) -> Any:
    return json.loads(json.dumps(obj))


def _bake_lock(work: Path, out: Path) -> AbstractContextManager[None]:
    """One bake of a store at a time: an exclusive lock on its work directory, held for the
    whole bake (a second bake of the same store, ``--overwrite`` or not, is refused instead of
    deleting the first one's files)."""
    return directory_lock(work, busy=f"another process is baking {out}")


def _work_directory(out: Path) -> Path:
    """The bake's work directory ``NAME.probes.work``, created if missing; a symbolic link or a
    file standing at its name is unlinked first (its target is never entered or emptied)."""
    work = work_path(out)
    if work.is_symlink() or (work.exists() and not work.is_dir()):
        remove_path(work)
    work.mkdir(parents=True, exist_ok=True)
    return work


@dataclass
class _StageRunner:
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
        fn: Callable[[StageState, NDArray[np.int64]], dict[str, Any]],
        ctx: StageContext,
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
    on_start: Callable[[bool], None] | None = None,
) -> BakeReport:
    """Bake a probe grid of ``scene`` into the store ``out`` (``NAME.probes``).

    Resumes an interrupted bake of the same scene and settings. ``executor`` defaults to the
    calling process (:class:`~probegrid.bake.executors.InlineExecutor`); the CLI passes local
    processes or a Dask cluster. ``scene_file``, the glTF file ``scene`` was loaded from, is
    kept in the store for viewers (see :func:`probegrid.store.writer.keepable_scene`).
    ``allow_black=False`` stops before finishing a store none of whose valid probes received
    light (:func:`probegrid.bake.nolight.light_quality`; the CLI's default).
    ``on_start(dropped)`` is called under the bake's lock once the work directory holds only
    what this bake resumes; ``dropped`` says an interrupted bake of another scene or other
    settings was deleted (the CLI prints where the bake resumes from, or that it starts clean).
    """
    st = settings or BakeSettings()
    env = environment or Environment()
    ex = executor or InlineExecutor(check_pickle=False)
    out = check_bake_inputs(out, settings=st, overwrite=overwrite, scene_file=scene_file)
    geometry = st.trace_geometry(scene, grid)
    scene_hash = hashlib.sha256(
        (scene.content_hash() + environment_hash(env)).encode()
    ).hexdigest()
    # (the batch size is left out: it changes no bit of the result, so a bake may resume with
    # another one)
    plan = {"settings": st.model_dump(exclude={"batch_size"}), "environment": env.describe(),
            "render": {"ray_offset": geometry.ray_offset, "max_distance": geometry.max_distance,
                       "moments_size": st.moments_face_size,
                       "environment_lookup_size": env.lookup_size(st.environment_footprint)},
            "filters": probefilter.describe(st.face_size, st.diffuse_size)}
    work = _work_directory(out)
    with _bake_lock(work, out):
        try:
            return _bake_locked(scene, grid, out, work, st, env, ex, plan, geometry, scene_hash,
                                progress=progress, overwrite=overwrite, scene_file=scene_file,
                                allow_black=allow_black, inputs=inputs, on_start=on_start)
        except ValueError:
            # a bake that failed on its own verdict (no light, a bad input found late) leaves
            # nothing behind; an interrupted one (a signal, a lost worker: ExecutorError, a
            # full disk: OSError) keeps its work files and resumes
            remove_path(partial_path(out))
            remove_path(work)
            raise


def _bake_locked(scene: Scene, grid: GridSpec, out: Path, work: Path, st: BakeSettings,
                 env: Environment, ex: Executor, plan: dict[str, Any], geometry: Any,
                 scene_hash: str, *, progress: ProgressFn | None, overwrite: bool,
                 scene_file: str | Path | None, allow_black: bool, inputs: BakeInputs | None,
                 on_start: Callable[[bool], None] | None) -> BakeReport:
    """:func:`bake` under its lock on the work directory ``work``."""
    recover_publish(out)
    # The work directory is keyed by the scene, the grid and the plan (its stamp
    # ``bake.json``): an interrupted bake of the same key resumes; anything else in it
    # (another scene, grid or plan, an unreadable stamp) is dropped with the final
    # stage's partial store, so a re-run with other settings starts clean, --overwrite
    # or not.
    stamp = work / "bake.json"
    fingerprint = json.dumps({"scene": scene_hash, "grid": grid.as_dict(),
                              "plan": _jsonable(plan)}, sort_keys=True)
    dropped = False
    if not (stamp.is_file() and not stamp.is_symlink()
            and stamp.read_text(errors="replace") == fingerprint):
        dropped = any(work.iterdir())
        for child in work.iterdir():
            remove_path(child)
        partial = partial_path(out)
        if StoreWriter.resumable(out, arrays=store_arrays(st), grid=grid,
                                 conventions=conventions(), scene_hash=scene_hash,
                                 bake=plan):
            pass  # (the final stage of this very bake, its work directory gone)
        elif partial.is_dir() and not partial.is_symlink():
            dropped = True
            with directory_lock(partial, busy=f"another process is writing {partial}"):
                remove_path(partial)
        elif partial.is_symlink() or partial.exists():
            dropped = True
            remove_path(partial)
    atomic_write_text(stamp, fingerprint)
    if on_start is not None:
        on_start(dropped)
    runner = _StageRunner(ex, plan, scene_hash, progress)
    t0 = time.perf_counter()
    base = StageContext(scene, env, st, grid, geometry,
                         key=hashlib.sha256((fingerprint + repr(geometry)).encode()).hexdigest())

    # 1. classify
    w, resumed = runner.run("classify", work / "classify.probes", classify_arrays(),
                            classify_task, base)
    cls_store = w.finish() if isinstance(w, StoreWriter) else w
    positions = np.array(cls_store["positions"])
    valid = np.array(cls_store["valid"])
    lattice = grid.positions()
    relocated = int(np.count_nonzero(np.any(positions != lattice, axis=1)))
    # Workers on this machine memory-map the grid-sized arrays from the work directory; others
    # (a Dask cluster) receive them.
    files = ex.shares_files
    probe_pos: NDArray[np.float64] | str = positions
    probe_valid: NDArray[np.bool_] | str = valid
    if files:
        probe_pos = str(work / "classify.probes" / "positions.npy")
        probe_valid = str(work / "classify.probes" / "valid.npy")

    # 2. trace once: every probe's rays, kept as per-hit records by the workers; bounce 0
    records = (str(work / "records") if files
               else "probegrid-records-" + hashlib.sha256(
                   (str(out.resolve()) + fingerprint).encode()).hexdigest()[:16])
    schedule = BounceSchedule.of(st)

    # one worker process on this machine reads every block it wrote: its records stay in
    # its memory (written only if they outgrow it); several workers share them as files
    base = dataclasses.replace(base, record_files=not (files and ex.workers == 1))
    ctx = dataclasses.replace(base, positions=probe_pos, valid=probe_valid, records=records)
    w, _ = runner.run(schedule.label(0), work / "trace.probes", trace_arrays(st),
                      trace_task, ctx)
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

    cubes_at: dict[int, NDArray[np.float32] | str] = {0: grid_cubes(tstore, 0)}
    irradiance_at = {0: tstore["irradiance"]}
    schedule.passed(grid_energy(tstore))

    # 3. bounces: a pass over the records per level, as long as the schedule asks
    while (k := schedule.next_pass()) is not None:
        ctx = dataclasses.replace(base, positions=probe_pos, valid=probe_valid,
                                  records=records, level=k, moments_bordered=moments_b,
                                  cubes=cubes_at.get(schedule.reads(k)))
        w, _ = runner.run(schedule.label(k), work / f"bounce{k}.probes", bounce_arrays(st),
                          bounce_task, ctx)
        bstore = w.finish() if isinstance(w, StoreWriter) else w
        cubes_at[k] = grid_cubes(bstore, k)
        irradiance_at[k] = bstore["irradiance"]
        schedule.passed(grid_energy(bstore))
    level = schedule.level
    assert level is not None
    final_cubes = cubes_at.get(schedule.reads(level)) if level > 0 else None
    final_grid = irradiance_at.get(schedule.reads(level)) if level > 0 else None
    if schedule.extrapolates:  # the final pass reads the grid's extrapolated limit
        final_grid = schedule.limit(irradiance_at)
        cubes = bordered_cubes(final_grid)
        final_cubes = (str(_save_npy(work / "irradiance_limit.npy", cubes)) if files
                       else cubes)

    # the surface cache, built before the final pass when that pass reads it (a final gather,
    # probegrid.bake.finalgather), else once the probes are written (write_store_extras)
    cache = cache_plan = None
    if st.final_gather:
        t_cache = time.perf_counter()
        g = irradiance_size(st.gather_levels() > 0)
        read = (final_grid if final_grid is not None
                else np.zeros((grid.n_probes, 6, g, g, 3), np.float32))
        cache_plan = final_gather_plan(scene, st)
        cache = surface_cache(scene, env, st, geometry, grid=grid, valid=valid,
                              positions=positions, moments=tstore["moments"],
                              bordered=bordered_cubes(read), level=level, plan=cache_plan,
                              iterations=FINAL_GATHER_ITERATIONS, gather=FINAL_GATHER_RAYS)
        runner.seconds["surface cache"] = time.perf_counter() - t_cache
    cache_files = None
    if cache is not None:
        cache_files = ((str(_save_npy(work / "surface_lattice.npy", cache[0])),
                        str(_save_npy(work / "surface_light.npy", cache[1]))) if files
                       else (cache[0], cache[1]))

    # 4. final
    energy = np.full(grid.n_probes, np.nan)
    seam = np.full(grid.n_probes, np.nan)

    def keep(batch: NDArray[np.int64], result: dict[str, Any]) -> None:
        energy[batch] = result["_energy"]
        seam[batch] = result["_seam"]

    ctx = dataclasses.replace(base, positions=probe_pos, valid=probe_valid,
                              records=records, level=level, moments_bordered=moments_b,
                              cubes=final_cubes, moments=moments_all,
                              surface_cache=cache_files)
    w, resumed = runner.run(schedule.label(level, final=True), out, store_arrays(st),
                            final_task, ctx, overwrite=overwrite, intermediate=False,
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
            energy[i] = energy_ratio(d, incoming_integral_from_sh(stored_sh[i]))
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
        "bounce_residual": schedule.residual,
        "bounce_passes": schedule.passes,
        "bounce_energy": schedule.energies,
        "rays": runner.rays,
        "stage_seconds": {k: round(v, 3) for k, v in runner.seconds.items()},
        # how the emitters' light is sampled at hits (exact integral, or clusters)
        "emitter_sampling": Emitters.from_scene(scene).sampling(),
    }
    if schedule.state.factor is not None:  # converged by extrapolation (bake.converge)
        quality["bounce_extrapolation"] = schedule.state.factor
        quality["bounce_energy_limit"] = schedule.state.limit
    quality = light_quality(quality, w.array("sh"), valid, allow_black=allow_black)
    # deringed SH, scene triangles, the grid and environment (probegrid.bake.extras)
    t_cache = time.perf_counter()
    cache_rays, lattice = write_store_extras(w, scene, environment=env,
                                             grid_irradiance=final_grid,
                                             gather=st.gather_levels() > 0,
                                             face_size=st.face_size, settings=st,
                                             geometry=geometry, level=level, cache=cache,
                                             plan=cache_plan)
    quality["stage_seconds"]["surface cache"] = round(
        time.perf_counter() - t_cache + runner.seconds.get("surface cache", 0.0), 3)
    quality["surface_cache_rays"] = cache_rays
    if lattice is not None:  # its spacing and why (the scene's, never the grid's)
        quality["surface_cache"] = lattice.manifest()
    if st.final_gather:  # whether the final pass read the cache (none: no lattice)
        quality["final_gather"] = cache is not None
    if st.sh_field > 0:  # the SH field /sh interpolates (probegrid.bake.shfield)
        t_field = time.perf_counter()
        write_sh_field(w, scene, plan=plan, level=level, refine=st.sh_field,
                       face_size=st.sh_field_face_size,
                       invalid_threshold=st.invalid_threshold)
        quality["stage_seconds"]["sh field"] = round(time.perf_counter() - t_field, 3)
    store = w.finish(quality=quality, scene_file=scene_file, inputs=inputs)
    remove_path(work)  # (a Linux flock lives on the open directory, not on its name)
    if not files:  # (this machine's Dask workers' record directory, emptied block by block)
        shutil.rmtree(resolve_directory(records), ignore_errors=True)

    seconds = time.perf_counter() - t0
    return BakeReport(store, seconds, runner.rays, grid.n_probes, resumed, quality)
