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
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict

from probegrid.bake import BakeReport, BakeSettings, bake
from probegrid.environment import Environment
from probegrid.executors import Progress
from probegrid.grid import GridSpec, parse_bounds, parse_grid, parse_spacing
from probegrid.scene import Scene, load_gltf

__all__ = ["BakeOptions", "grid_for", "load_environment", "run_bake"]


class BakeOptions(BaseModel):
    """The CLI's options, as given (strings where the CLI takes strings)."""

    model_config = ConfigDict(frozen=True, extra="forbid", arbitrary_types_allowed=True)

    scene: Path
    out: Path
    grid: str | None = None
    spacing: str | None = None
    bounds: str | None = None
    margin: float | None = None
    environment: list[Path] | None = None
    environment_layout: str = "auto"
    environment_color: str | None = None
    environment_intensity: float = 1.0
    environment_rotation: float = 0.0
    face_size: int = 32
    bounces: int = 2
    samples: int = 1
    seed: int = 0
    diffuse_size: int = 8
    specular_levels: int | None = None
    no_direct: bool = False
    store_incoming: bool = False
    no_relocate: bool = False
    batch_size: int = 8
    workers: int | None = None
    scheduler: str | None = None
    overwrite: bool = False
    no_progress: bool = False


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

    ``path`` is one image in any layout :mod:`probegrid.layouts` reads, or six face files.
    """
    if path is not None and color is not None:
        raise ValueError("give either --environment or --environment-color, not both")
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

    faces = read_environment(path, layout=layout, max_size=MAX_ENVIRONMENT_SIZE)
    return Environment(faces=faces, intensity=intensity, rotation=rotation)


class _Bar:
    """A progress bar per stage: probes done, rays per second, time left (tqdm, stderr)."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self._bar = None
        self._stage: str | None = None
        self._t0 = time.perf_counter()
        self._rays0 = 0

    def __call__(self, stage: str, p: Progress, rays: int) -> None:
        if not self.enabled:
            return
        from tqdm import tqdm

        if stage != self._stage:
            self.close()
            self._stage = stage
            width = shutil.get_terminal_size(fallback=(100, 24)).columns or 100
            self._bar = tqdm(total=p.probes_total, desc=stage, unit="probe", file=sys.stderr,
                             ncols=min(width, 120), mininterval=0.5)
            self._t0 = time.perf_counter() - p.elapsed
            self._rays0 = rays
        assert self._bar is not None
        self._bar.n = p.probes_done
        dt = max(time.perf_counter() - self._t0, 1e-9)
        self._bar.set_postfix_str(f"{(rays - self._rays0) / dt / 1e6:.2f} Mrays/s", refresh=False)
        self._bar.refresh()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def run_bake(opts: BakeOptions) -> BakeReport:
    """Run ``probegrid bake`` with the given options."""
    from probegrid.executors import make_executor

    if not opts.out.name.endswith(".probes"):
        raise ValueError(f"--out must name a store NAME.probes, got {str(opts.out)!r}")
    if opts.out.exists() and not opts.overwrite:
        raise ValueError(f"{opts.out} exists; pass --overwrite to replace it")
    if opts.bounces < 0:
        raise ValueError(f"--bounces must be >= 0, got {opts.bounces}")
    if opts.seed < 0:
        raise ValueError(f"--seed must be >= 0, got {opts.seed}")
    settings = BakeSettings(
        face_size=opts.face_size, samples=opts.samples, seed=opts.seed, bounces=opts.bounces,
        diffuse_size=opts.diffuse_size, specular_levels=opts.specular_levels,
        direct=not opts.no_direct, store_incoming=opts.store_incoming,
        relocate=not opts.no_relocate, batch_size=opts.batch_size,
    )
    settings.levels()
    scene = load_gltf(opts.scene)
    grid = grid_for(scene, grid=opts.grid, spacing=opts.spacing, bounds=opts.bounds,
                    margin=opts.margin)
    env = load_environment(opts.environment, layout=opts.environment_layout,
                           color=opts.environment_color, intensity=opts.environment_intensity,
                           rotation_deg=opts.environment_rotation)
    executor = make_executor(workers=opts.workers, scheduler=opts.scheduler)
    bar = _Bar(enabled=not opts.no_progress and sys.stderr.isatty())
    print(f"baking {grid.label} = {grid.n_probes} probes of {opts.scene} on "
          f"{executor.description}", file=sys.stderr)
    try:
        return bake(scene, grid, opts.out, settings=settings, environment=env,
                    executor=executor, progress=bar, overwrite=opts.overwrite,
                    scene_file=opts.scene)
    finally:
        bar.close()
        executor.close()
