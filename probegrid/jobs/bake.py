"""The ``probegrid bake`` job: options -> scene, grid, environment, executor -> :func:`bake`.

Option checking lives here, so that every bad value ends as a one-line ``ValueError`` before
any work starts. The default grid, when neither ``--grid`` nor ``--spacing`` is given, has 8
probes along the longest axis of the box and proportionally fewer along the others; without
``--bounds`` the box is the scene's bounds and the probes sit at the *centres* of the grid's
cells (half a cell inside the bounds), so none starts on a wall. ``--spacing S`` places probes
exactly ``S`` apart, centred in the box (without ``--bounds``, half a spacing inside the scene's
bounds). A grid may have at most :data:`MAX_PROBES` probes.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

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

__all__ = ["BakeJob", "grid_for", "load_environment", "run_bake"]


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


def grid_for(scene: Scene, *, grid: str | None = None, spacing: str | None = None,
             bounds: str | None = None, margin: float | None = None) -> GridSpec:
    """The probe grid the options describe (see the module docstring)."""
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
    if grid is not None:
        counts = np.array(parse_grid(grid), dtype=np.float64)
    else:
        longest = float(extent.max())
        if longest <= 0:
            raise ValueError("the scene has no extent; give --bounds")
        counts = np.maximum(1, np.rint(8 * extent / longest))
    _check_probe_count(counts)
    if inset:
        half = extent / (2 * counts)
        lo, hi = lo + half, hi - half
    return GridSpec.from_counts(lo, hi, tuple(int(c) for c in counts))


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


def run_bake(job: BakeJob) -> BakeReport:
    """Run ``probegrid bake``: every option was checked when ``job`` was built; then the scene,
    grid, environment and executor, then :func:`~probegrid.bake.bake`."""
    from probegrid.bake.driver import bake
    from probegrid.bake.executors import make_executor
    from probegrid.scene import load_gltf

    check_store_name(job.out)
    if job.out.exists() and not job.overwrite:
        raise ValueError(f"{job.out} exists; pass --overwrite to replace it")
    job.settings.levels()
    scene = load_gltf(job.scene)
    grid = grid_for(scene, grid=job.grid, spacing=job.spacing, bounds=job.bounds,
                    margin=job.margin)
    env = load_environment(job.environment, layout=job.environment_layout,
                           color=job.environment_color, intensity=job.environment_intensity,
                           rotation_deg=job.environment_rotation)
    executor = make_executor(workers=job.workers, scheduler=job.scheduler)
    bar = BakeProgress(enabled=job.progress)  # a bar on a terminal, else plain lines
    print(f"baking {grid.label} = {grid.n_probes} probes of {job.scene} on "
          f"{executor.description}", file=sys.stderr)
    print(size_note(job.settings, grid.n_probes), file=sys.stderr)
    if (note := resume_note(job.out)) is not None:
        print(note, file=sys.stderr)
    try:
        return bake(scene, grid, job.out, settings=job.settings, environment=env,
                    executor=executor, progress=bar, overwrite=job.overwrite)
    finally:
        bar.close()
        executor.close()
