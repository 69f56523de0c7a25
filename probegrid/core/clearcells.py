"""Clear cells: the cells of a probe lattice whose box no triangle touches.

A point inside such a box sees every corner of the cell: the segment from the point to a corner
lies in the box (a box is convex), and no triangle meets the box. The exact visibility test of
the blending weights (:func:`probegrid.core.ddgi.probe_weights`, ``clear=``) then casts no ray
for it -- in a room whose lattice ends just inside the walls, almost every query.

Cells
-----
A cell is named by its lower corner's linear index (corner 0 of :meth:`GridSpec.corners`, whose
base coordinates run over ``0 .. max(n - 2, 0)`` per axis); its *box* is the axis-aligned
bounding box of its 8 corners' positions (the stored, possibly moved positions: the segments'
ends), so a cell of moved probes is tested as what it spans. A lattice point that is no cell's
lower corner (the last layer of an axis) is never clear.

Padding
-------
Every box is grown by ``pad`` (world units) on each side before the test: the segments are cast
through Embree in float32 relative to the scene's centre, and a triangle within rounding of a
box's face must count as touching it. :func:`clear_pad` gives the default, ``1e-5`` of the
scene's and lattice's extent (0.1 mm in a 10 m room), far above float32 rounding (6e-8
relative) and far below any wall's distance from the lattice that matters. A cell whose padded
box touches a triangle is not clear; its queries cast their segments as before.

The test
--------
Triangle against box by the separating-axis theorem (T. Akenine-Möller, "Fast 3D Triangle-Box
Overlap Testing", 2001): the box's 3 axes, the triangle's normal and the 9 products of the
triangle's edges with the box's axes; the triangle misses the box when the projections of both
on one of these 13 axes do not overlap. Candidates come from a broad phase on the nominal
lattice (each triangle's bounding box against the cells whose nominal box, grown by the largest
displacement of a position from the lattice and the pad, it meets), then every pair is tested
exactly, vectorized over pairs in chunks of :data:`PAIR_CHUNK`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core.grid import GridSpec

__all__ = ["PAD_FRACTION", "PAIR_CHUNK", "REACH", "TRIANGLE_CHUNK", "ClearCells", "clear_cells",
           "clear_pad", "triangles_overlap_boxes"]

#: Padding of every box, as a fraction of the largest extent of the scene and the lattice.
PAD_FRACTION: Final = 1e-5
#: Cells each way a cell's block reaches (:class:`ClearCells`).
REACH: Final = 1
#: Triangles whose candidate cells are listed at once (bounds the broad phase's lists).
TRIANGLE_CHUNK: Final = 4096
#: Triangle-cell pairs tested at once (bounds the temporaries: about 1 KB a pair).
PAIR_CHUNK: Final = 1 << 16


@dataclass(frozen=True, eq=False)
class ClearCells:
    """Per lattice point, the box of the cell it is the lower corner of, the box of that cell's
    block (the cell and its neighbours, :data:`REACH` cells each way, clipped to the lattice)
    and whether each is clear (module docstring).

    Attributes
    ----------
    lo, hi : (P, 3) float64
        The cell's box (its corners' bounding box; not padded).
    clear : (P,) bool
        No triangle touches the box grown by the pad; False for a point that is no cell's lower
        corner.
    block_lo, block_hi : (P, 3) float64
        The block's box (the bounding box of its lattice points).
    block_clear : (P,) bool
        The same for the block's box: a start there (a query point moved off its cell by the
        normal's offset) sees the cell's corners through the block.
    cells : int
        The lattice's cells (points that are a cell's lower corner).
    """

    lo: NDArray[np.float64]
    hi: NDArray[np.float64]
    clear: NDArray[np.bool_]
    block_lo: NDArray[np.float64]
    block_hi: NDArray[np.float64]
    block_clear: NDArray[np.bool_]
    cells: int

    def __post_init__(self) -> None:  # the single-point query's tables, as Python lists
        object.__setattr__(self, "_tables", (
            self.clear.tolist(), self.lo.tolist(), self.hi.tolist(),
            self.block_clear.tolist(), self.block_lo.tolist(), self.block_hi.tolist()))

    @property
    def fraction(self) -> float:
        """The share of the lattice's cells that are clear."""
        return float(self.clear.sum()) / max(1, self.cells)

    def contains(self, base: NDArray[np.int64], points: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether each point lies in the (closed) clear box of cell ``base`` (its lower
        corner's index) or of its block: every segment from it to the cell's corners is then
        clear."""
        def inside(lo: NDArray[np.float64], hi: NDArray[np.float64]) -> NDArray[np.bool_]:
            return (np.logical_and.reduce(points >= lo[base], axis=-1)
                    & np.logical_and.reduce(points <= hi[base], axis=-1))

        return ((self.clear[base] & inside(self.lo, self.hi))
                | (self.block_clear[base] & inside(self.block_lo, self.block_hi)))

    def contains_one(self, base: int, x: float, y: float, z: float) -> bool:
        """:meth:`contains` of one point, in Python floats."""
        clear, lo, hi, block_clear, block_lo, block_hi = self._tables  # type: ignore[attr-defined]
        if clear[base]:
            a, b = lo[base], hi[base]
            if a[0] <= x <= b[0] and a[1] <= y <= b[1] and a[2] <= z <= b[2]:
                return True
        if block_clear[base]:
            a, b = block_lo[base], block_hi[base]
            return a[0] <= x <= b[0] and a[1] <= y <= b[1] and a[2] <= z <= b[2]
        return False


def clear_pad(grid: GridSpec, vertices: ArrayLike) -> float:
    """The default pad: :data:`PAD_FRACTION` of the largest extent of the scene's vertices and
    the lattice's box (world units)."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    ext = np.concatenate([np.abs(grid.lo), np.abs(grid.hi), grid.hi - grid.lo])
    if v.size:
        ext = np.concatenate([ext, np.abs(v).max(axis=0), v.max(axis=0) - v.min(axis=0)])
    return PAD_FRACTION * max(float(ext.max()), 1.0)


def clear_cells(grid: GridSpec, vertices: ArrayLike, triangles: ArrayLike, *,
                positions: ArrayLike | None = None, pad: float | None = None) -> ClearCells:
    """The clear cells of ``grid`` among the triangles ``vertices[triangles]``.

    Parameters
    ----------
    grid : GridSpec
    vertices : (V, 3) float
    triangles : (T, 3) int
    positions : (P, 3) float, optional
        The lattice points' actual positions (moved probes); default the lattice.
    pad : float, optional
        World units each box is grown by (finite, >= 0); default :func:`clear_pad`.
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if tri.size and (tri.min() < 0 or tri.max() >= len(v)):
        raise ValueError("triangles must index the vertices.")
    pad = clear_pad(grid, v) if pad is None else float(pad)
    if not (np.isfinite(pad) and pad >= 0):
        raise ValueError(f"pad must be finite and >= 0, got {pad!r}.")
    lattice = grid.positions()
    pos = lattice if positions is None else np.asarray(positions, dtype=np.float64)
    if pos.shape != lattice.shape or not np.all(np.isfinite(pos)):
        raise ValueError(f"positions must be finite, of shape {lattice.shape}.")
    n = np.array(grid.counts, dtype=np.int64)
    ijk = grid.probe_ijk(np.arange(grid.n_probes))
    is_base = np.all(ijk <= np.maximum(n - 2, 0), axis=1)
    boxes = []
    for reach in (0, REACH):  # the cell, then its block
        lo, hi = _window_boxes(pos.reshape(*grid.counts, 3), reach)
        touched = np.zeros(grid.n_probes, dtype=bool)
        for first in range(0, len(tri), TRIANGLE_CHUNK):  # a loop over chunks of triangles
            part = tri[first:first + TRIANGLE_CHUNK]
            cand_tri, cand_cell = _candidates(grid, v, part, pos, lattice, is_base, pad, reach)
            for s in range(0, len(cand_tri), PAIR_CHUNK):  # a loop over chunks of pairs
                t, c = cand_tri[s:s + PAIR_CHUNK], cand_cell[s:s + PAIR_CHUNK]
                todo = ~touched[c]  # (a cell found touched needs no more tests)
                t, c = t[todo], c[todo]
                hit = triangles_overlap_boxes(v[part[t]], lo[c] - pad, hi[c] + pad)
                touched[c[hit]] = True
        boxes.append((lo, hi, is_base & ~touched))
    (lo, hi, clear), (block_lo, block_hi, block_clear) = boxes
    return ClearCells(lo=lo, hi=hi, clear=clear, block_lo=block_lo, block_hi=block_hi,
                      block_clear=block_clear, cells=int(is_base.sum()))


def _window_boxes(pos: NDArray[np.float64], reach: int
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(lo, hi) (P, 3)``: per lattice point ``b``, the bounding box of the lattice points
    ``b - reach .. b + 1 + reach`` per axis (clipped to the lattice) of ``pos (nx, ny, nz, 3)``."""
    lo, hi = pos.copy(), pos.copy()
    for axis in range(3):  # separable: a running min / max along each axis
        m = pos.shape[axis]
        a, b = lo.copy(), hi.copy()
        for d in range(-reach, 2 + reach):  # a loop over the window's few offsets
            idx = np.clip(np.arange(m) + d, 0, m - 1)
            a = np.minimum(a, np.take(lo, idx, axis=axis))
            b = np.maximum(b, np.take(hi, idx, axis=axis))
        lo, hi = a, b
    return lo.reshape(-1, 3), hi.reshape(-1, 3)


def _candidates(grid: GridSpec, v: NDArray[np.float64], tri: NDArray[np.int64],
                pos: NDArray[np.float64], lattice: NDArray[np.float64],
                is_base: NDArray[np.bool_], pad: float, reach: int
                ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """``(triangle, cell)`` pairs whose boxes (the cells' grown by ``reach`` cells) may meet
    (the broad phase): per axis the range of cells whose nominal extent, grown by ``reach``
    cells, the largest displacement of a position and the pad, meets the triangle's extent."""
    n = np.array(grid.counts, dtype=np.int64)
    cells = np.maximum(n - 1, 1)  # cells per axis (an axis of one probe: one flat cell)
    step = np.where(n > 1, grid.spacing, 1.0)
    grow = np.abs(pos - lattice).max(axis=0) + pad
    tv = v[tri]
    tmin, tmax = tv.min(axis=1) - grow, tv.max(axis=1) + grow
    first = np.clip(np.floor((tmin - grid.lo) / step).astype(np.int64) - 1 - reach, 0,
                    cells - 1)
    last = np.clip(np.floor((tmax - grid.lo) / step).astype(np.int64) + 1 + reach, 0,
                   cells - 1)
    first = np.where(n > 1, first, 0)
    last = np.where(n > 1, last, 0)
    miss = np.any((tmax < lattice.min(axis=0) - step) | (tmin > lattice.max(axis=0) + step),
                  axis=1)  # (beyond the lattice: no cell's box, block or not, reaches it)
    span = np.where(miss[:, None], 0, last - first + 1)
    count = span.prod(axis=1)
    total = int(count.sum())
    t = np.repeat(np.arange(len(tri)), count)
    k = np.arange(total) - np.repeat(np.cumsum(count) - count, count)  # rank in the triangle
    sj, sk = span[t, 1], span[t, 2]
    i = first[t, 0] + k // (sj * sk)
    j = first[t, 1] + k // sk % sj
    kk = first[t, 2] + k % sk
    cell = (i * n[1] + j) * n[2] + kk
    keep = is_base[cell]
    return t[keep], cell[keep]


def triangles_overlap_boxes(tri: ArrayLike, lo: ArrayLike, hi: ArrayLike) -> NDArray[np.bool_]:
    """Whether each triangle ``tri (k, 3, 3)`` meets the closed box ``[lo, hi] (k, 3)`` (the
    separating-axis test of the module docstring: the box's axes first, on every pair, then the
    normal and the 9 edge products on the pairs left; a degenerate triangle's zero axes
    separate nothing, and its other axes decide it)."""
    t = np.asarray(tri, dtype=np.float64)
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    p = t - centre[:, None, :]  # (k, 3, 3) vertices about the box's centre
    out = np.all((p.min(axis=1) <= half) & (p.max(axis=1) >= -half), axis=1)  # the box's axes
    rows = np.flatnonzero(out)
    p, half = p[rows], half[rows]
    edges = p[:, [1, 2, 0]] - p  # (m, 3, 3): e0 = v1 - v0, e1 = v2 - v1, e2 = v0 - v2
    normal = np.cross(edges[:, 0], edges[:, 1])
    apart = np.abs(np.sum(normal * p[:, 0], axis=1)) > np.sum(np.abs(normal) * half, axis=1)
    for a in range(3):  # the products of box axis a with the 3 edges: 3 axes a time
        axis = np.cross(np.eye(3)[a], edges)  # (m, 3 edges, 3)
        proj = (axis[:, :, None, :] * p[:, None, :, :]).sum(axis=-1)  # (m, edge, vertex)
        radius = (np.abs(axis) * half[:, None, :]).sum(axis=-1)
        apart |= np.any((proj.min(axis=2) > radius) | (proj.max(axis=2) < -radius), axis=1)
    out[rows[apart]] = False
    return out
