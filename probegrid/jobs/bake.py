"""The ``probegrid bake`` job: options -> scene, grid, environment, executor -> :func:`bake`.

:class:`BakeJob` holds the command's options (the library's :class:`BakeSettings` and the
job's own: files, grid, environment, where to run); :func:`run_bake` turns them into the
library's inputs and calls the library, printing what it decides on the way. Every check lives
in the library, and every refusal there is a one-line error the CLI prints as it is:

* the grid options (:func:`probegrid.bake.placement.check_grid_options`: syntax, and the
  probe count where the options alone fix it), the environment file's layout from its header
  (:func:`probegrid.imageio.detect_file_layout`: a square LDR image is not taken as an
  angular map unless ``--environment-layout angular`` says so), the bake's inputs that need
  no scene (:func:`probegrid.bake.inputs.check_bake_inputs`) and the scene file's header
  (:func:`probegrid.scene.gltf.check_scene_file`), before any worker process starts;
* **no silent black**: a scene with no emissive material, no punctual light and no
  environment is refused before any work (:func:`probegrid.bake.nolight.require_light`);
  ``--allow-black`` bakes it anyway. A bake none of whose valid probes received light stops
  before its store is finished and says why, leaving no work files (the same command with
  ``--allow-black`` bakes it black);
* the probe volume a scene node marks (``--volume-node NAME``, or the one node named like a
  probe volume, found by itself: :mod:`probegrid.scene.volume`; printed), then the grid
  (:func:`probegrid.bake.placement.grid_for`; a default grid that fits the scene is printed, one
  that would sit inside the scene's geometry is refused with a box to use instead);
* **the estimate before work** (:func:`probegrid.bake.estimate.estimate`): probes, rays, the
  store's size, the bake's work files and the peak memory of a worker are printed, and a bake
  whose store and work files do not fit on the target's file system is refused with the
  figures (:func:`probegrid.bake.estimate.check_disk`).

The heavy modules (Embree, numba, trimesh) load once the worker processes are starting, so that
their start-up overlaps this process's own.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from probegrid._types import InputLayout
from probegrid.bake.settings import BakeSettings
from probegrid.jobs.progress import BakeProgress, resume_note, size_note

if TYPE_CHECKING:  # the heavy modules (Embree, numba, trimesh) load when a bake runs
    from probegrid.bake.driver import BakeReport
    from probegrid.bake.environment import Environment
    from probegrid.scene import Scene
    from probegrid.scene.volume import ProbeVolume
    from probegrid.store import BakeInputs

__all__ = ["BakeJob", "bake_inputs", "load_environment", "probe_volume", "run_bake"]


class BakeJob(BaseModel):
    """One ``probegrid bake`` run: what to bake, where, on what, and the library's settings.

    ``settings`` is the library's own :class:`~probegrid.bake.BakeSettings` (the options that
    decide the bits of the store, each default written once there); the other fields are the
    job's: the scene and output, the grid and environment as the CLI gives them (strings where
    the CLI takes strings; parsed by :func:`probegrid.bake.placement.grid_for` and
    :func:`load_environment`), and where to run.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    scene: Path
    out: Path
    settings: BakeSettings = BakeSettings()
    grid: str | None = None
    spacing: str | None = None
    bounds: str | None = None
    volume_node: str | None = None
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
    allow_paths: list[Path] = []
    ignore_extensions: list[str] = []
    max_texture_pixels: int | None = Field(default=None, ge=1)  # (None: the loader's)
    max_texture_size: int | None = Field(default=None, ge=1)
    max_environment_pixels: int | None = Field(default=None, ge=1)  # (None: imageio's 2^28)


#: Largest default face size of a bake's environment cube (each worker holds a copy).
MAX_ENVIRONMENT_SIZE = 256


def load_environment(path: Path | list[Path] | None, *, layout: str = "auto",
                     color: str | None = None, intensity: float = 1.0,
                     rotation_deg: float = 0.0, max_pixels: int | None = None) -> Environment:
    """The bake's environment from the CLI's options (default black).

    ``path`` is one image in any layout :mod:`probegrid.core.layouts` reads, or six face files,
    each of at most ``max_pixels`` pixels (default :data:`probegrid.imageio.MAX_PIXELS`;
    ``--max-environment-pixels``).
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
                             report=lambda line: print(line, file=sys.stderr),
                             max_pixels=max_pixels, option="--max-environment-pixels")
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
        content_hash=scene.content_hash(), unhonoured=scene.unhonoured)
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


def probe_volume(job: BakeJob) -> ProbeVolume | None:
    """The probe volume of the node ``job.volume_node`` names; without it (and without
    ``bounds``), of the one node the scene names like a probe volume
    (:func:`probegrid.scene.volume.find_volume_node`), else None."""
    from probegrid.scene.volume import find_volume_node, node_volume

    if job.volume_node is not None:
        if job.bounds is not None:
            raise ValueError("give either --bounds or --volume-node, not both")
        return node_volume(job.scene, job.volume_node)
    if job.bounds is not None:
        return None
    return find_volume_node(job.scene)


def run_bake(job: BakeJob) -> BakeReport:
    """Run ``probegrid bake``: every option was checked when ``job`` was built; then the bake's
    inputs and the scene file's header, the executor (its processes start now), the scene and
    environment (refused when they hold no light, unless ``allow_black``), the grid (the
    default one printed), the estimate (printed; refused when the disk cannot hold the store),
    then :func:`~probegrid.bake.bake`."""
    from probegrid.bake.executors import make_executor
    from probegrid.bake.inputs import check_bake_inputs
    from probegrid.bake.placement import check_grid_options
    from probegrid.scene.gltf import check_scene_file

    check_grid_options(grid=job.grid, spacing=job.spacing, bounds=job.bounds, margin=job.margin)
    if job.environment and len(job.environment) == 1 and job.environment_layout == "auto":
        from probegrid.imageio import detect_file_layout

        detect_file_layout(job.environment[0], option="--environment-layout")
    check_bake_inputs(job.out, settings=job.settings, overwrite=job.overwrite)
    check_scene_file(job.scene)  # (what needs no parsing, before any process starts)
    executor = make_executor(workers=job.workers, scheduler=job.scheduler,
                             preload=("probegrid.bake.preload",))
    # local processes start (and import the bake) while this one imports it and loads the scene
    executor.start()
    compiling = _kernels_to_compile(executor)
    from probegrid.bake.driver import bake
    from probegrid.bake.estimate import check_disk, estimate
    from probegrid.bake.nolight import require_light
    from probegrid.bake.placement import grid_for
    from probegrid.scene import load_gltf
    from probegrid.scene.texels import TextureLimits

    bar = BakeProgress(enabled=job.progress)  # a bar on a terminal, else plain lines
    try:
        volume = probe_volume(job)  # (the glTF JSON only: refused before the scene loads)
        if job.environment is not None:  # (the headers only: refused before the scene loads)
            from probegrid.imageio import check_pixels

            check_pixels(list(job.environment), max_pixels=job.max_environment_pixels,
                         option="--max-environment-pixels")
        limits = {k: v for k, v in (("max_pixels", job.max_texture_pixels),
                                    ("max_size", job.max_texture_size)) if v is not None}
        scene = load_gltf(job.scene, allow_paths=job.allow_paths,
                          ignore_extensions=job.ignore_extensions,
                          textures=TextureLimits(**limits))
        env = load_environment(job.environment, layout=job.environment_layout,
                               color=job.environment_color,
                               intensity=job.environment_intensity,
                               rotation_deg=job.environment_rotation,
                               max_pixels=job.max_environment_pixels)
        require_light(scene, env, allow_black=job.allow_black)
        notes: list[str] = []  # printed once every check passed: an error stays one line
        if scene.unhonoured:
            notes.append(f"scene: not honoured: {'; '.join(scene.unhonoured)}")
        if volume is not None:
            notes.append(volume.describe())
        grid = grid_for(scene, grid=job.grid, spacing=job.spacing, bounds=job.bounds,
                        margin=job.margin, say=notes.append,
                        volume=None if volume is None else (volume.lo, volume.hi))
        est = estimate(job.settings, grid, scene, env, shares_files=executor.shares_files)
        notes.append(est.summary())
        check_disk(job.out, est)
        for line in notes:
            print(line, file=sys.stderr)
        print(f"baking {grid.label} = {grid.n_probes} probes of {job.scene} on "
              f"{executor.description}", file=sys.stderr)
        print(size_note(job.settings, grid.n_probes), file=sys.stderr)

        if compiling:
            _wait_compiling(executor, compiling, bar)

        def on_start(dropped: bool) -> None:
            if dropped:
                print(f"note: the interrupted bake of {job.out} had another scene, grid or other "
                      "settings; it was deleted and this bake starts clean", file=sys.stderr)
            elif (note := resume_note(job.out)) is not None:
                print(note, file=sys.stderr)

        return bake(scene, grid, job.out, settings=job.settings, environment=env,
                    executor=executor, progress=bar, overwrite=job.overwrite,
                    scene_file=job.scene, allow_black=job.allow_black,
                    inputs=bake_inputs(job, scene, env), on_start=on_start)
    finally:
        bar.close()
        executor.close()


def _kernels_to_compile(executor: object) -> list[str]:
    """The bake's kernels numba's cache lacks, when local workers will compile them as they
    start (:mod:`probegrid.bake.compiled`); empty otherwise (a warm cache, or remote workers)."""
    from probegrid.bake.executors import LocalExecutor

    if not isinstance(executor, LocalExecutor):
        return []
    from probegrid.bake.compiled import uncached_kernels

    return uncached_kernels()


def _wait_compiling(executor: Any, kernels: list[str], bar: BakeProgress) -> None:
    """Wait for the local workers, whose fork server compiles ``kernels`` (a machine's first
    bake), showing how many of them numba's cache holds so far."""
    from probegrid.bake.compiled import bake_kernels, is_cached

    todo = [d for d in bake_kernels()
            if f"{d.py_func.__module__}.{d.py_func.__name__}" in set(kernels)]
    while True:
        started = executor.wait_started(timeout=1.0)
        done = sum(is_cached(d) for d in todo)
        bar.compiling(done, len(todo), finished=started)
        if started:
            return
