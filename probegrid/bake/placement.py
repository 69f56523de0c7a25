"""Where a bake's probes go: the grid over a box of the scene, and where an invalid probe may move.

* **The grid the options describe** (:func:`grid_for`): ``spacing`` places probes exactly that
  far apart, centred in the box (without ``bounds``, half a spacing inside the scene's bounds);
  ``grid NXxNYxNZ`` puts that many probes at the centres of the box's cells. A grid may have at
  most :data:`MAX_PROBES` probes.
* **A default grid that fits the scene** (:func:`default_grid`, neither ``grid`` nor
  ``spacing``): the spacing is the longest side of the box over :data:`DEFAULT_LAYERS`; every
  axis longer than the spacing gets at least two layers of probes, at the centres of equal
  cells. Without ``bounds``/``margin`` the box is first fitted to the scene's *free space*: the
  scene's bounds are sampled at half the spacing with the inside test of
  :mod:`probegrid.bake.inside`, and the box shrunk to the samples outside every solid (plus half
  a sample step), so no outer layer of probes sits in a floor slab or an outer wall: the lowest
  probe is at least a quarter of the spacing above the highest sample inside the slab. Probes
  that still fall inside a solid (a slab between storeys) are moved out or invalidated by the
  bake's classifier (:func:`probegrid.bake.stages.classify_task`), with the same test.
* **A default grid inside the geometry is refused** before any tracing, with a box to use
  instead (:func:`suggested_bounds`: a layer beside the scene's thinnest side, +Y for no
  thinnest): scene bounds thinner than :data:`FLAT_RATIO` of their longest side (a lone floor
  plane), no free sample inside them (a lone floor slab), or more than :data:`INSIDE_LIMIT` of
  the grid's probes inside solids.
* **A probe volume** (``volume``: a scene node's box, :mod:`probegrid.scene.volume`): probes at
  the centres of its cells, as an engine's irradiance volume samples its voxels, without the
  free-space fit (the box is the author's).
* **Relocation** (:func:`relocation_offsets`): the classifier tries the points of a small
  lattice around an invalid probe, within a fraction of a cell, nearest first.

The box and counts arrive as the CLI's text (``x0,y0,z0,x1,y1,z1``, ``NXxNYxNZ``, ``S`` or
``SX,SY,SZ``; parsed by :mod:`probegrid.core.grid`); every refusal is a one-line ValueError.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core.grid import GridSpec, parse_bounds, parse_grid, parse_spacing

if TYPE_CHECKING:  # (Embree and numba load when a default grid is fitted)
    from probegrid.scene import Scene

__all__ = ["DEFAULT_LAYERS", "FIT_SAMPLES", "FLAT_RATIO", "INSIDE_LIMIT", "MAX_PROBES",
           "check_grid_options", "default_counts", "default_grid", "grid_for",
           "relocation_offsets", "suggested_bounds"]

#: Most probes a grid may have.
MAX_PROBES = 10_000_000


def check_grid_options(*, grid: str | None = None, spacing: str | None = None,
                       bounds: str | None = None, margin: float | None = None) -> None:
    """Refuse (one-line ValueError) grid options that no scene could make valid: text that
    does not parse, ``grid`` with ``spacing``, a non-finite ``margin``, and a grid of more than
    :data:`MAX_PROBES` probes when the counts follow from the options alone (``grid``, or
    ``spacing`` with ``bounds``). Needs no scene, so a bake checks them before loading one;
    :func:`grid_for` then builds the grid with the same rules."""
    if grid is not None and spacing is not None:
        raise ValueError("give either --grid or --spacing, not both")
    if margin is not None and not math.isfinite(margin):
        raise ValueError(f"--margin must be a finite number, got {margin}")
    if grid is not None:
        _check_probe_count(np.array(_option(parse_grid, "grid", grid), dtype=np.float64))
    step = None if spacing is None else _option(parse_spacing, "spacing", spacing)
    box = None if bounds is None else _option(parse_bounds, "bounds", bounds)
    if step is not None and box is not None:
        lo, hi = (np.asarray(v, dtype=np.float64) for v in box)  # (margin: without bounds)
        size = np.broadcast_to(np.asarray(step, dtype=np.float64), (3,))
        with np.errstate(over="ignore", invalid="ignore"):
            _check_probe_count(np.floor((hi - lo) / size * (1.0 + 1e-9)) + 1.0)


def _option(parse: Callable[[str], object], name: str, text: str) -> Any:
    """``parse(text)`` with the option's flag leading its message (``--grid: ...``)."""
    try:
        return parse(text)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"--{name}: {exc}") from None


def grid_for(scene: Scene, *, grid: str | None = None, spacing: str | None = None,
             bounds: str | None = None, margin: float | None = None,
             volume: tuple[ArrayLike, ArrayLike] | None = None,
             say: Callable[[str], None] | None = None) -> GridSpec:
    """The probe grid the options describe (see the module docstring); ``say`` receives the
    description of a default grid. ``volume`` is a probe volume's box ``(lo, hi)`` (a scene
    node's, :mod:`probegrid.scene.volume`): probes at the centres of its cells, as an engine's
    irradiance volume samples its voxels, ``margin`` growing it; no free-space fit."""
    fit = True
    if bounds is not None:
        if volume is not None:
            raise ValueError("give either --bounds or --volume-node, not both")
        lo, hi = (np.asarray(v, dtype=np.float64) for v in parse_bounds(bounds))
        inset = False
    elif volume is not None:
        lo, hi = (np.array(v, dtype=np.float64) for v in volume)
        if margin is not None:
            lo, hi = lo - margin, hi + margin
            if np.any(hi <= lo):
                raise ValueError(f"margin {margin} leaves an empty box")
        inset, fit = True, False
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
        g, text = default_grid(scene, lo, hi, centred=inset, fit=fit)
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
                 centred: bool, fit: bool = True) -> tuple[GridSpec, str]:
    """The default grid over the box ``[lo, hi]`` and its description (module docstring).

    ``centred`` (the box is the scene's bounds, or a probe volume's): the probes sit at the
    centres of equal cells; with ``fit`` (the scene's bounds) the box is fitted to the scene's
    free space first, and a grid that would sit inside the geometry is refused
    (:func:`_refuse_inside`); otherwise (a box the user gave) the lattice includes the box's
    corners.
    """
    lo, hi = np.array(lo, dtype=np.float64), np.array(hi, dtype=np.float64)
    longest = float((hi - lo).max())
    if not longest > 0:
        raise ValueError("the scene has no extent; give --bounds")
    step = longest / (DEFAULT_LAYERS if centred else DEFAULT_LAYERS - 1)
    note = ""
    fitted = centred and fit
    if fitted:
        scene_lo, scene_hi = lo, hi
        if np.min(hi - lo) < FLAT_RATIO * longest:
            _refuse_inside(scene_lo, scene_hi, step, "the scene is flat")
        lo, hi, note = _fit_free_space(scene, lo, hi, step)
        if note.startswith(_NO_FREE):
            _refuse_inside(scene_lo, scene_hi, step, "no point inside the scene's bounds is "
                           "outside its solids")
    extent = hi - lo
    counts = default_counts(extent, step, centred=centred)
    _check_probe_count(counts)
    if centred:
        half = extent / (2 * counts)
        lo, hi = lo + half, hi - half
    g = GridSpec.from_counts(lo, hi, tuple(int(c) for c in counts))
    if fitted:
        from probegrid.bake.inside import inside_solid
        from probegrid.raytrace import RayTracer

        inside = inside_solid(RayTracer.shared(scene), scene, g.positions())
        if np.mean(inside) > INSIDE_LIMIT:
            _refuse_inside(scene_lo, scene_hi, step, f"{np.count_nonzero(inside)} of its "
                           f"{g.n_probes} probes are inside solids")
    cells = np.where(np.array(g.counts) > 1, extent / (counts if centred else counts - 1), 0.0)
    text = (f"default grid {g.label} = {g.n_probes} probes, spacing "
            + " x ".join(f"{c:.4g}" for c in cells)
            + f" (target {step:.4g} = longest side / {DEFAULT_LAYERS if centred else 7}), "
            + "probes from " + ",".join(f"{v:.4g}" for v in g.lo) + " to "
            + ",".join(f"{v:.4g}" for v in g.hi) + note)
    return g, text


#: A scene's bounds thinner than this fraction of their longest side along an axis are flat:
#: a default grid over them would put its probes in the geometry.
FLAT_RATIO = 0.01
#: Most probes of a default grid that may be inside solids before the grid is refused.
INSIDE_LIMIT = 0.5
_NO_FREE = "; no free space found"


def suggested_bounds(lo: NDArray[np.float64], hi: NDArray[np.float64], step: float
                     ) -> NDArray[np.float64]:
    """``x0,y0,z0,x1,y1,z1`` of a box over a scene whose default grid sits inside it: along
    the scene's thinnest axis (+Y, glTF's up, when no axis is thinner than the others), from a
    quarter of the default spacing ``step`` beyond the scene's bounds to a quarter of its
    longest side beyond them; along the others, the bounds inset by half a spacing."""
    ext = hi - lo
    a = int(np.argmin(ext)) if np.min(ext) < np.max(ext) else 1
    blo = np.minimum(lo + 0.5 * step, 0.5 * (lo + hi))
    bhi = np.maximum(hi - 0.5 * step, 0.5 * (lo + hi))
    blo[a] = hi[a] + 0.25 * step
    bhi[a] = hi[a] + 0.25 * float(np.max(ext))
    return np.concatenate([blo, bhi])


def _refuse_inside(lo: NDArray[np.float64], hi: NDArray[np.float64], step: float,
                   why: str) -> None:
    """Refuse (one-line ValueError) a default grid inside the scene's geometry, suggesting a
    box (:func:`suggested_bounds`) and the options that place a grid."""
    ext = hi - lo
    box = ",".join(f"{v:.4g}" for v in suggested_bounds(lo, hi, step))
    raise ValueError(
        "a default grid would sit inside the scene's geometry (" + why + "; its bounds are "
        + " x ".join(f"{v:.4g}" for v in ext) + "): give --bounds, e.g. --bounds " + box
        + " (a layer beside it), or --volume-node NAME (a node marking the volume), or --margin")


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
        return lo, hi, _NO_FREE + " inside the scene's bounds: probes inside solids"
    half = 0.5 * extent / m
    flo = np.maximum(lo, pts[free].min(axis=0) - half)
    fhi = np.minimum(hi, pts[free].max(axis=0) + half)
    if np.allclose(flo, lo) and np.allclose(fhi, hi):
        return lo, hi, ""
    return flo, fhi, (", fitted to the free space " + ",".join(f"{v:.4g}" for v in flo) + " to "
                      + ",".join(f"{v:.4g}" for v in fhi) + " (outside every solid)")


def _check_probe_count(counts: NDArray[np.float64]) -> None:
    """Refuse more than MAX_PROBES probes (counted in float64: no integer overflow)."""
    if math.prod(float(c) for c in counts) > MAX_PROBES:  # (inf if huge; no warning)
        label = "x".join(f"{c:.0f}" if c < 1e15 else f"{c:.3g}" for c in counts)
        raise ValueError(f"a grid of {label} probes is too large (at most {MAX_PROBES:,})")


def _lattice_offsets(steps: int = 2) -> NDArray[np.float64]:
    """Lattice offsets in [-1, 1]^3 (without 0), nearest first, ties in a fixed order."""
    k = np.arange(-steps, steps + 1) / steps
    g = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3)
    g = g[np.any(g != 0, axis=1)]
    order = np.lexsort((g[:, 2], g[:, 1], g[:, 0], np.linalg.norm(g, axis=1)))
    return g[order]


def relocation_offsets(grid: GridSpec, fraction: float) -> NDArray[np.float64]:
    """The offsets, nearest first, of the points an invalid probe of ``grid`` may move to:
    a lattice within ``fraction`` of a cell along each axis that has more than one probe."""
    cell = np.where(np.array(grid.counts) > 1, grid.cell_size, 0.0)
    offsets = _lattice_offsets() * (fraction * cell)
    return offsets[np.any(offsets != 0, axis=1)]
