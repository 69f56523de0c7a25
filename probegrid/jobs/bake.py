"""The ``probegrid bake`` job: options -> scene, grid, environment, executor -> :func:`bake`.

Option checking lives here, so that every bad value ends as a one-line ``ValueError`` before
any work starts, and so do the refusals that need the scene (issue 10, items 7-9):

* **No silent black.** A scene with no emissive material, no punctual light and no environment
  is refused before any work (:func:`probegrid.bake.nolight.require_light`); ``--allow-black``
  bakes it anyway. A bake none of whose valid probes received light stops before its store is
  finished and says why (the same command with ``--allow-black`` resumes and finishes it).
* **A default grid that fits the scene** (:func:`default_grid`, no ``--grid``/``--spacing``):
  the spacing is the longest side of the box over :data:`DEFAULT_LAYERS`; every axis longer
  than the spacing gets at least two layers of probes, at the centres of equal cells. Without
  ``--bounds``/``--margin`` the box is first fitted to the scene's *free space*: the scene's
  bounds are sampled at half the spacing with the inside test of :mod:`probegrid.bake.inside`,
  and the box shrunk to the samples outside every solid (plus half a sample step), so no outer
  layer of probes sits in a floor slab or an outer wall: the lowest probe is at least a quarter
  of the spacing above the highest sample inside the slab. Probes that still fall inside a solid
  (a slab between storeys) are moved out or invalidated by the bake's classifier, with the same
  test. The chosen grid is printed.
* **Estimate before work** (:func:`estimate`): probes, rays, the store's size (exact to the
  ``.npy`` headers and an allowance for the manifest), the bake's work files and the peak
  memory of a worker are printed; a bake whose store and work files do not fit on the target's
  file system (``shutil.disk_usage``) is refused with the figures.

``--spacing S`` places probes exactly ``S`` apart, centred in the box (without ``--bounds``,
half a spacing inside the scene's bounds); ``--grid NXxNYxNZ`` puts that many probes at the
centres of the box's cells. A grid may have at most :data:`MAX_PROBES` probes.
"""

from __future__ import annotations

import math
import shutil
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from probegrid._types import InputLayout
from probegrid.bake.settings import BakeSettings
from probegrid.core.grid import GridSpec, parse_bounds, parse_grid, parse_spacing
from probegrid.jobs.progress import BakeProgress, resume_note, size_note
from probegrid.store.manifest import check_store_name

if TYPE_CHECKING:  # the heavy modules (Embree, numba, trimesh) load when a bake runs
    from probegrid.bake.driver import BakeReport
    from probegrid.bake.environment import Environment
    from probegrid.scene import Scene
    from probegrid.store import BakeInputs

__all__ = ["BakeEstimate", "BakeJob", "bake_inputs", "default_grid", "estimate", "grid_for",
           "load_environment", "run_bake"]


class BakeJob(BaseModel):
    """One ``probegrid bake`` run: what to bake, where, on what, and the library's settings.

    ``settings`` is the library's own :class:`~probegrid.bake.BakeSettings` (the options that
    decide the bits of the store, each default written once there); the other fields are the
    job's: the scene and output, the grid and environment as the CLI gives them (strings where
    the CLI takes strings; parsed by :func:`grid_for` and :func:`load_environment`), and where
    to run.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    scene: Path
    out: Path
    settings: BakeSettings = BakeSettings()
    grid: str | None = None
    spacing: str | None = None
    bounds: str | None = None
    margin: float | None = None
    environment: list[Path] | None = None
    environment_layout: InputLayout = "auto"
    environment_color: str | None = None
    environment_intensity: float = 1.0
    environment_rotation: float = 0.0
    workers: int | None = Field(default=None, ge=1)
    scheduler: str | None = None
    overwrite: bool = False
    progress: bool = True
    allow_black: bool = False


def grid_for(scene: Scene, *, grid: str | None = None, spacing: str | None = None,
             bounds: str | None = None, margin: float | None = None,
             say: Callable[[str], None] | None = None) -> GridSpec:
    """The probe grid the options describe (see the module docstring); ``say`` receives the
    description of a default grid."""
    if bounds is not None:
        lo, hi = (np.asarray(v, dtype=np.float64) for v in parse_bounds(bounds))
        inset = False
    else:
        lo, hi = (np.array(v, dtype=np.float64) for v in scene.bounds)
        inset = margin is None
        if margin is not None:
            lo, hi = lo - margin, hi + margin
            if np.any(hi < lo):
                raise ValueError(f"margin {margin} leaves an empty box")
    extent = hi - lo
    if not np.all(np.isfinite(extent)):
        raise ValueError("the grid box is not finite; give smaller --bounds or --margin")
    if spacing is not None:
        # probes exactly ``spacing`` apart, centred in the box (half a spacing in from the scene
        # bounds by default, so no probe sits on an outer wall)
        step = np.broadcast_to(np.asarray(parse_spacing(spacing), dtype=np.float64), (3,))
        if inset:
            centre = 0.5 * (lo + hi)
            lo = np.minimum(lo + 0.5 * step, centre)
            hi = np.maximum(hi - 0.5 * step, centre)
        counts_f = np.floor((hi - lo) / step * (1.0 + 1e-9)) + 1.0
        _check_probe_count(counts_f)
        return GridSpec.from_spacing(lo, hi, step)
    if grid is None:
        g, text = default_grid(scene, lo, hi, centred=inset)
        if say is not None:
            say(text)
        return g
    counts = np.array(parse_grid(grid), dtype=np.float64)
    _check_probe_count(counts)
    if inset:
        half = extent / (2 * counts)
        lo, hi = lo + half, hi - half
    return GridSpec.from_counts(lo, hi, tuple(int(c) for c in counts))


#: Probes along the longest side of the box in a default grid.
DEFAULT_LAYERS = 8
#: Most samples of the free-space fit of a default grid (each costs ``inside.DIRECTIONS`` rays).
FIT_SAMPLES = 8192


def default_counts(extent: NDArray[np.float64], spacing: float, *, centred: bool
                   ) -> NDArray[np.float64]:
    """Probe counts of a default grid over a box of ``extent`` for a target ``spacing``: the
    nearest number of cells (``centred``: probes at cell centres; else corner-inclusive), and at
    least two probes along every side longer than the spacing."""
    e = np.asarray(extent, dtype=np.float64)
    cells = np.rint(e / spacing)
    counts = np.maximum(1.0, cells) if centred else np.where(e > 0, cells + 1.0, 1.0)
    return np.where(e > spacing * (1 + 1e-9), np.maximum(counts, 2.0), counts)


def default_grid(scene: Scene, lo: NDArray[np.float64], hi: NDArray[np.float64], *,
                 centred: bool) -> tuple[GridSpec, str]:
    """The default grid over the box ``[lo, hi]`` and its description (module docstring).

    ``centred`` (the box is the scene's bounds): the box is fitted to the scene's free space
    first and the probes sit at the centres of equal cells; otherwise (a box the user gave) the
    lattice includes the box's corners.
    """
    lo, hi = np.array(lo, dtype=np.float64), np.array(hi, dtype=np.float64)
    longest = float((hi - lo).max())
    if not longest > 0:
        raise ValueError("the scene has no extent; give --bounds")
    step = longest / (DEFAULT_LAYERS if centred else DEFAULT_LAYERS - 1)
    note = ""
    if centred:
        lo, hi, note = _fit_free_space(scene, lo, hi, step)
    extent = hi - lo
    counts = default_counts(extent, step, centred=centred)
    _check_probe_count(counts)
    if centred:
        half = extent / (2 * counts)
        lo, hi = lo + half, hi - half
    g = GridSpec.from_counts(lo, hi, tuple(int(c) for c in counts))
    cells = np.where(np.array(g.counts) > 1, extent / (counts if centred else counts - 1), 0.0)
    text = (f"default grid {g.label} = {g.n_probes} probes, spacing "
            + " x ".join(f"{c:.4g}" for c in cells)
            + f" (target {step:.4g} = longest side / {DEFAULT_LAYERS if centred else 7}), "
            + "probes from " + ",".join(f"{v:.4g}" for v in g.lo) + " to "
            + ",".join(f"{v:.4g}" for v in g.hi) + note)
    return g, text


def _fit_free_space(scene: Scene, lo: NDArray[np.float64], hi: NDArray[np.float64],
                    step: float) -> tuple[NDArray[np.float64], NDArray[np.float64], str]:
    """The box ``[lo, hi]`` shrunk to the samples (at about half ``step``) that are outside
    every solid of ``scene`` (:func:`probegrid.bake.inside.inside_solid`), grown by half a
    sample step; the box unchanged when no sample is free."""
    from probegrid.bake.inside import inside_solid
    from probegrid.raytrace import RayTracer

    extent = hi - lo
    f = 0.5 * step
    while True:
        m = np.maximum(1, np.ceil(extent / f * (1 - 1e-9))).astype(np.int64)
        if math.prod(int(x) for x in m) <= FIT_SAMPLES:
            break
        f *= 1.25
    axes = [lo[i] + (np.arange(m[i]) + 0.5) * extent[i] / m[i] for i in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    free = ~inside_solid(RayTracer.shared(scene), scene, pts)
    if not free.any():
        return lo, hi, "; no free space found inside the scene's bounds: probes inside solids"
    half = 0.5 * extent / m
    flo = np.maximum(lo, pts[free].min(axis=0) - half)
    fhi = np.minimum(hi, pts[free].max(axis=0) + half)
    if np.allclose(flo, lo) and np.allclose(fhi, hi):
        return lo, hi, ""
    return flo, fhi, (", fitted to the free space " + ",".join(f"{v:.4g}" for v in flo) + " to "
                      + ",".join(f"{v:.4g}" for v in fhi) + " (outside every solid)")


# ------------------------------------------------------------------------------ estimate
#: Resident memory of a bake worker before its batch: the interpreter, numpy, the compiled
#: kernels and Embree (measured: the peak RSS of the worker process of a face-8,
#: one-probe-per-batch bake of the sample room, 183 MiB, Linux x86-64, Python 3.11, numba 0.68;
#: with this base the model gave 269 MiB for a measured 268 MiB at face 32, batch 8, and 313
#: MiB for 319 MiB at face 64, batch 16).
WORKER_BASE_BYTES = 183 * 2**20
#: Bytes held per traced ray of a batch (directions, weights, origins, radiance, distance,
#: flags and the per-probe patterns) and per ray of a shading chunk (hit records, surfaces,
#: shadow rays: the chunk's temporaries).
BATCH_RAY_BYTES = 160
CHUNK_RAY_BYTES = 640
#: Allowance for a store's manifest.json (settings, plan, conventions, quality figures).
MANIFEST_BYTES = 8 * 2**10
#: Bytes of an ``.npy`` header (format 1.0 pads it to a multiple of 64; 128 for our shapes).
NPY_HEADER_BYTES = 128


@dataclass(frozen=True)
class BakeEstimate:
    """What a bake will cost, from its settings, grid and scene, before any work.

    Attributes
    ----------
    probes : int
    classify_rays, primary_rays, gather_rays, shadow_rays : int
        Rays of the classification (without relocation's extra points), the probes' own rays
        (each cast once: the bounces replay their records), at most the gather rays (``K`` from
        every hit, and one more from each of theirs per further gather level) and at most the
        shadow rays of all their hits (one per punctual light, and ``--light-samples`` toward
        the emitters and the environment each; one each at a gather ray's hit).
    store_bytes : int
        Size of the finished store: every array's ``.npy`` file and the manifest.
    work_bytes : int
        Peak size of the bake's work files (``NAME.probes.work/`` and the unfinished store's
        done mask), kept until the store is finished.
    worker_bytes : int
        Peak resident memory of one worker process (a model: :data:`WORKER_BASE_BYTES` plus the
        scene, the environment, the filter matrix and the batch; grid-sized arrays are
        memory-mapped by local workers and shipped to Dask workers, counted then).
    """

    probes: int
    classify_rays: int
    primary_rays: int
    gather_rays: int
    shadow_rays: int
    store_bytes: int
    work_bytes: int
    worker_bytes: int

    @property
    def rays(self) -> int:
        """All rays, shadow rays at their most."""
        return self.classify_rays + self.primary_rays + self.gather_rays + self.shadow_rays

    @property
    def disk_bytes(self) -> int:
        """Disk the bake needs at its peak: the store and the work files."""
        return self.store_bytes + self.work_bytes

    def summary(self) -> str:
        return (f"estimate: {self.probes} probes, {self.rays / 1e6:.3g} M rays "
                f"({self.classify_rays / 1e6:.3g} M classify, {self.primary_rays / 1e6:.3g} M "
                f"primary, up to {self.gather_rays / 1e6:.3g} M gather and "
                f"{self.shadow_rays / 1e6:.3g} M shadow), store "
                f"{_size(self.store_bytes)} (+ {_size(self.work_bytes)} work files), peak "
                f"worker memory {_size(self.worker_bytes)}")


def _size(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.3g} {unit}"
        n /= 1024
    raise AssertionError  # pragma: no cover


def estimate(settings: BakeSettings, grid: GridSpec, scene: Scene,
             environment: Environment | None = None, *, shares_files: bool = True
             ) -> BakeEstimate:
    """The cost of baking ``grid`` of ``scene`` with ``settings`` (see :class:`BakeEstimate`).

    ``shares_files``: the workers run on this machine and memory-map the grid-sized arrays
    (local processes), else they receive them (Dask)."""
    from probegrid.bake.driver import CLASSIFY_FACE_SIZE, FILTER_GROUP
    from probegrid.bake.inside import DIRECTIONS
    from probegrid.bake.nolight import light_sources
    from probegrid.bake.records import RECORDS_MEMORY, irradiance_size, record_bytes
    from probegrid.bake.render import SHADE_CHUNK
    from probegrid.bake.settings import store_arrays
    from probegrid.core import probefilter

    p = grid.n_probes
    st = settings
    n, s = st.face_size, st.samples
    m = min(st.moments_size, n)
    per_probe_rays = 6 * n * n * s
    # every ray is cast once (probegrid.bake.records): the bounces replay the per-hit records
    primary = p * per_probe_rays
    lights = len(scene.lights)
    sources = light_sources(scene, environment) if environment is not None else []
    emitters = any("emissive" in what for what in sources)
    sky = "the environment" in sources  # sampled as a light at every hit
    # (at most: samples below a hit's horizon cast no ray)
    per_hit = lights + st.light_samples * (int(emitters) + int(sky))
    gather = primary * st.gather_samples * st.gather_levels()  # (one more per hit per level)
    shadow = (primary * per_hit + gather * (lights + int(emitters) + int(sky))
              + (p * lights if st.direct else 0))
    classify = p * (6 * CLASSIFY_FACE_SIZE**2 + DIRECTIONS)

    def npy(shape: tuple[int, ...], dtype: str) -> int:
        return NPY_HEADER_BYTES + p * math.prod(shape) * np.dtype(dtype).itemsize

    store = MANIFEST_BYTES + sum(npy(a.shape, a.dtype) for a in store_arrays(st).values())
    # work files: the classification, the per-hit records of every traced ray (kept until the
    # last pass; probegrid.bake.records), two levels of per-probe irradiance cubes and the
    # moments, the done masks
    g = irradiance_size(st.gather_levels() > 0)
    work = npy((3,), "float64") + npy((), "bool") + npy((), "float64") + npy((), "bool")
    records = record_bytes(primary, st.gather_samples, st.gather_levels())
    work += records
    work += 2 * npy((6, g, g, 3), "float32") + npy((6, m, m, 2), "float32") + npy((), "bool")

    scene_bytes = (scene.vertices.nbytes * 3 + scene.triangles.nbytes * 2
                   + 150 * scene.n_triangles
                   + sum(0 if t is None else t.nbytes for mat in scene.materials
                         for t in (mat.base_color_texture, mat.emissive_texture)))
    env_bytes = 0
    if environment is not None and environment.faces is not None:
        env_bytes = 3 * environment.faces.nbytes
    batch_rays = min(st.batch_size, p) * per_probe_rays * (1 + gather // max(primary, 1))
    cube = 6 * n * n * 3 * 4
    if probefilter.supported(n, st.diffuse_size):
        rows, cols = probefilter.filter_matrix_shape(n, st.diffuse_size, st.levels())
        filt = rows * cols * 4  # float32
    else:
        filt = 16 * FILTER_GROUP * cube
    worker = (WORKER_BASE_BYTES + scene_bytes + env_bytes + filt
              + batch_rays * BATCH_RAY_BYTES + min(batch_rays, SHADE_CHUNK) * CHUNK_RAY_BYTES
              + 3 * min(st.batch_size, p) * cube
              # the records a worker keeps between passes (probegrid.bake.records)
              + min(RECORDS_MEMORY, records))
    if not shares_files:  # positions, validity, the previous bounce's SH, coefficients, moments
        worker += p * (24 + 1 + 2 * 216 + 6 * (m + 2) ** 2 * 8)
    return BakeEstimate(p, classify, primary, gather, shadow, store, work, worker)


def check_disk(out: Path, est: BakeEstimate) -> None:
    """Refuse (``OSError``, one line with the figures) a bake whose store and work files do not
    fit in the free space of ``out``'s file system; what an interrupted bake of the same store
    already reserved counts as available."""
    from probegrid.store import partial_path
    from probegrid.store.manifest import work_path

    target = Path(out).absolute().parent
    while not target.exists() and target != target.parent:
        target = target.parent
    free = shutil.disk_usage(target).free
    have = sum(f.stat().st_size for d in (partial_path(out), work_path(out)) if d.is_dir()
               for f in d.rglob("*") if f.is_file())
    need = est.disk_bytes - have
    if need > free:
        raise OSError(
            f"not enough disk space for {out}: the bake needs {_size(est.disk_bytes)} (store "
            f"{_size(est.store_bytes)} + work files {_size(est.work_bytes)}) and {target} has "
            f"{_size(free)} free; free some space, bake fewer probes or a smaller --face-size")


#: Most probes a grid may have.
MAX_PROBES = 10_000_000


def _check_probe_count(counts: NDArray[np.float64]) -> None:
    """Refuse more than MAX_PROBES probes (counted in float64: no integer overflow)."""
    if math.prod(float(c) for c in counts) > MAX_PROBES:  # (inf if huge; no warning)
        label = "x".join(f"{c:.0f}" if c < 1e15 else f"{c:.3g}" for c in counts)
        raise ValueError(f"a grid of {label} probes is too large (at most {MAX_PROBES:,})")


#: Largest default face size of a bake's environment cube (each worker holds a copy).
MAX_ENVIRONMENT_SIZE = 256


def load_environment(path: Path | list[Path] | None, *, layout: str = "auto",
                     color: str | None = None, intensity: float = 1.0,
                     rotation_deg: float = 0.0) -> Environment:
    """The bake's environment from the CLI's options (default black).

    ``path`` is one image in any layout :mod:`probegrid.core.layouts` reads, or six face files.
    """
    if path is not None and color is not None:
        raise ValueError("give either --environment or --environment-color, not both")
    from probegrid.bake.environment import Environment

    rotation = math.radians(rotation_deg)
    if path is None:
        if color is None:
            return Environment(intensity=intensity, rotation=rotation)
        try:
            rgb = [float(x) for x in color.split(",")]
        except ValueError:
            raise ValueError(f"--environment-color must be R,G,B, got {color!r}") from None
        if len(rgb) == 1:
            rgb = rgb * 3
        if len(rgb) != 3:
            raise ValueError(f"--environment-color must be R,G,B, got {color!r}")
        return Environment(color=np.array(rgb), intensity=intensity, rotation=rotation)
    from probegrid.imageio import read_environment

    faces = read_environment(path, layout=layout, max_size=MAX_ENVIRONMENT_SIZE,
                             report=lambda line: print(line, file=sys.stderr))
    return Environment(faces=faces, intensity=intensity, rotation=rotation)


def bake_inputs(job: BakeJob, scene: Scene, env: Environment) -> BakeInputs:
    """The scene and environment of ``job`` as given, for the store's manifest (``inputs``):
    file names without their directories, sizes, the environment's layout (``auto`` resolved
    as the reader resolves it; six face files named in face order), the scene's counts and each
    one's own content hash (the store's ``scene_hash`` is the SHA-256 of the two)."""
    from probegrid.bake.driver import environment_hash
    from probegrid.bake.nolight import emissive_materials
    from probegrid.core.layouts import detect_layout
    from probegrid.imageio import image_size, order_face_files
    from probegrid.scene.gltf import gltf_mesh_count
    from probegrid.store import BakeInputs, EnvironmentInput, SceneInput
    from probegrid.store.manifest import EnvironmentSource

    scene_in = SceneInput(
        name=job.scene.name, bytes=job.scene.stat().st_size, triangles=scene.n_triangles,
        meshes=gltf_mesh_count(job.scene), materials=len(scene.materials),
        emissive_materials=emissive_materials(scene), punctual_lights=len(scene.lights),
        content_hash=scene.content_hash())
    def env_input(layout: EnvironmentSource, **given: Any) -> EnvironmentInput:
        return EnvironmentInput(layout=layout, intensity=job.environment_intensity,
                                rotation_deg=job.environment_rotation,
                                content_hash=environment_hash(env), **given)

    if job.environment:
        files = (order_face_files(job.environment) if len(job.environment) == 6
                 else list(job.environment))
        w, h = image_size(files[0])
        layout: EnvironmentSource = (
            "faces" if len(files) == 6 else job.environment_layout
            if job.environment_layout != "auto" else detect_layout(h, w))
        env_in = env_input(layout, files=tuple(f.name for f in files), pixel_size=(w, h),
                           bytes=sum(f.stat().st_size for f in files))
    elif job.environment_color is not None:
        env_in = env_input("color", color=tuple(env.color.tolist()))
    else:
        env_in = env_input("none")
    return BakeInputs(scene=scene_in, environment=env_in)


def run_bake(job: BakeJob) -> BakeReport:
    """Run ``probegrid bake``: every option was checked when ``job`` was built; then the scene
    and environment (refused when they hold no light, unless ``allow_black``), the grid (the
    default one printed), the estimate (printed; refused when the disk cannot hold the store)
    and the executor, then :func:`~probegrid.bake.bake`."""
    from probegrid.bake.executors import make_executor
    from probegrid.scene.gltf import check_scene_file

    check_store_name(job.out)
    if job.out.exists() and not job.overwrite:
        raise ValueError(f"{job.out} exists; pass --overwrite to replace it")
    job.settings.levels()
    check_scene_file(job.scene)  # (what needs no parsing, before any process starts)
    executor = make_executor(workers=job.workers, scheduler=job.scheduler,
                             preload=("probegrid.bake.preload",))
    # local processes start (and import the bake) while this one imports it and loads the scene
    executor.start()
    from probegrid.bake.driver import bake
    from probegrid.bake.nolight import require_light
    from probegrid.scene import load_gltf

    bar = BakeProgress(enabled=job.progress)  # a bar on a terminal, else plain lines
    try:
        scene = load_gltf(job.scene)
        env = load_environment(job.environment, layout=job.environment_layout,
                               color=job.environment_color,
                               intensity=job.environment_intensity,
                               rotation_deg=job.environment_rotation)
        require_light(scene, env, allow_black=job.allow_black)
        notes: list[str] = []  # printed once every check passed: an error stays one line
        grid = grid_for(scene, grid=job.grid, spacing=job.spacing, bounds=job.bounds,
                        margin=job.margin, say=notes.append)
        est = estimate(job.settings, grid, scene, env, shares_files=job.scheduler is None)
        notes.append(est.summary())
        check_disk(job.out, est)
        for line in notes:
            print(line, file=sys.stderr)
        print(f"baking {grid.label} = {grid.n_probes} probes of {job.scene} on "
              f"{executor.description}", file=sys.stderr)
        print(size_note(job.settings, grid.n_probes), file=sys.stderr)
        if (note := resume_note(job.out)) is not None:
            print(note, file=sys.stderr)
        return bake(scene, grid, job.out, settings=job.settings, environment=env,
                    executor=executor, progress=bar, overwrite=job.overwrite,
                    scene_file=job.scene, allow_black=job.allow_black,
                    inputs=bake_inputs(job, scene, env))
    finally:
        bar.close()
        executor.close()
