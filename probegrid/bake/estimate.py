"""What a bake will cost before any work: probes, rays, disk and a worker's memory.

:func:`estimate` gives a :class:`BakeEstimate` from the settings, the grid, the scene and the
environment: the rays of each stage (the classification, the probes' own rays, cast once, and
at most the gather and shadow rays of their hits), the store's size (exact to the ``.npy``
headers, with an allowance for the manifest), the peak size of the bake's work files and the
peak resident memory of a worker process (a model, its constants measured). :func:`check_disk`
refuses a bake whose store and work files do not fit on the target's file system
(``shutil.disk_usage``), with the figures.

The figures follow the stages (:mod:`probegrid.bake.stages`): the classifier's rays
(:data:`~probegrid.bake.stages.CLASSIFY_FACE_SIZE`, :data:`probegrid.bake.inside.DIRECTIONS`),
the records the workers keep (:mod:`probegrid.bake.records`), the shading chunk
(:data:`probegrid.bake.records.tracer.SHADE_CHUNK`), the filters' groups (:mod:`probegrid.bake.maps`)
and the store's arrays (:func:`probegrid.bake.settings.store_arrays`).
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from probegrid.bake.environment import LIGHT_SIZE, Environment
from probegrid.bake.finalgather import final_gather_plan
from probegrid.bake.inside import DIRECTIONS
from probegrid.bake.maps import FILTER_GROUP
from probegrid.bake.nolight import light_sources
from probegrid.bake.records import RECORDS_MEMORY, irradiance_size, record_bytes
from probegrid.bake.records.tracer import SHADE_CHUNK
from probegrid.bake.settings import BakeSettings, store_arrays
from probegrid.bake.stages import CLASSIFY_FACE_SIZE
from probegrid.bake.surfacecache import plan_lattice
from probegrid.core import probefilter
from probegrid.core.grid import GridSpec
from probegrid.scene import Scene
from probegrid.store import partial_path
from probegrid.store.manifest import work_path

__all__ = ["BATCH_RAY_BYTES", "CHUNK_RAY_BYTES", "MANIFEST_BYTES", "NPY_HEADER_BYTES",
           "WORKER_BASE_BYTES", "BakeEstimate", "check_disk", "estimate"]

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
    visibility_rays : int
        At most the segments that test which probes a hit reads the grid through see it (8 per
        hit that reads the grid: the deepest gather level's, and the probes' own;
        :func:`probegrid.bake.records.replay.hidden_corners`).
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
    visibility_rays: int = 0

    @property
    def rays(self) -> int:
        """All rays, shadow and visibility rays at their most."""
        return (self.classify_rays + self.primary_rays + self.gather_rays + self.shadow_rays
                + self.visibility_rays)

    @property
    def disk_bytes(self) -> int:
        """Disk the bake needs at its peak: the store and the work files."""
        return self.store_bytes + self.work_bytes

    def summary(self) -> str:
        return (f"estimate: {self.probes} probes, {self.rays / 1e6:.3g} M rays "
                f"({self.classify_rays / 1e6:.3g} M classify, {self.primary_rays / 1e6:.3g} M "
                f"primary, up to {self.gather_rays / 1e6:.3g} M gather, "
                f"{self.shadow_rays / 1e6:.3g} M shadow and {self.visibility_rays / 1e6:.3g} M "
                f"visibility), store "
                f"{_size(self.store_bytes)} (+ {_size(self.work_bytes)} work files), peak "
                f"worker memory {_size(self.worker_bytes)}")


def _size(n: float) -> str:
    """A number of bytes in words: ``512 B``, ``97.7 KiB``, ``1.5 GiB``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.3g} {unit}"
        n /= 1024
    raise AssertionError  # pragma: no cover


def estimate(settings: BakeSettings, grid: GridSpec, scene: Scene,
             environment: Environment | None = None, *, shares_files: bool = True
             ) -> BakeEstimate:
    """The cost of baking ``grid`` of ``scene`` with ``settings`` (see :class:`BakeEstimate`).

    ``shares_files`` (the executor's :attr:`~probegrid.bake.executors.Executor.shares_files`):
    the workers run on this machine and memory-map the grid-sized arrays (local processes),
    else they receive them (Dask)."""
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
    # the grid read at the deepest gather level's hits (K per primary hit) and at the probes'
    # own hits, 8 probes each (none without bounces that read the grid)
    reads = st.bounces == "converge" or int(st.bounces) >= 1
    visibility = 8 * primary * ((st.gather_samples + 1) if st.gather_levels() else 1) * reads

    def npy(shape: tuple[int, ...], dtype: str) -> int:
        return NPY_HEADER_BYTES + p * math.prod(shape) * np.dtype(dtype).itemsize

    store = MANIFEST_BYTES + sum(npy(a.shape, a.dtype) for a in store_arrays(st).values())
    g = irradiance_size(st.gather_levels() > 0)
    # the extras a probe traced at a point reads (probegrid.bake.extras): the bordered grid
    # and moments, the environment's cube
    store += npy((6, g + 2, g + 2, 3), "float32") + npy((6, m + 2, m + 2, 2), "float32")
    if environment is not None and environment.faces is not None:
        e = min(int(environment.faces.shape[1]), max(LIGHT_SIZE, n))
        store += NPY_HEADER_BYTES + 6 * e * e * 3 * 4
    # the surface light cache (probegrid.bake.surfacecache): its lattice's vertices
    lattice = (final_gather_plan(scene, st) if st.final_gather else
               plan_lattice(scene, st.surface_cache_spacing, face_size=st.face_size))
    store += 2 * NPY_HEADER_BYTES + 24 * (lattice.vertices + scene.n_triangles)
    if st.sh_field > 0:  # the SH field (probegrid.bake.shfield): SH twice and a validity a point
        from probegrid.bake.shfield import field_lattice

        k = field_lattice(grid, st.sh_field).n_probes
        store += 4 * NPY_HEADER_BYTES + 9 * 8 + k * (2 * 9 * 3 * 4 + 1)
    # work files: the classification, the per-hit records of every traced ray (kept until the
    # last pass; probegrid.bake.records), two levels of per-probe irradiance cubes and the
    # moments, the done masks
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
    return BakeEstimate(p, classify, primary, gather, shadow, store, work, worker,
                        int(visibility))


def check_disk(out: Path, est: BakeEstimate) -> None:
    """Refuse (``OSError``, one line with the figures) a bake whose store and work files do not
    fit in the free space of ``out``'s file system; what an interrupted bake of the same store
    already reserved counts as available."""
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
