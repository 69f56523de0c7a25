"""Probe grid geometry: the lattice of probe positions, its index order and trilinear cells.

A probe grid is an axis-aligned box of the world (glTF frame, metres) holding ``nx x ny x nz``
probes on a regular lattice that *includes the box's corners*.

Conventions
-----------
Positions
    Probe ``(i, j, k)``, ``0 <= i < nx``, ``0 <= j < ny``, ``0 <= k < nz``, sits at::

        p = bounds_min + (i, j, k) * (bounds_max - bounds_min) / (counts - 1)

    per axis, so probe ``(0, 0, 0)`` is at ``bounds_min`` and probe ``(nx-1, ny-1, nz-1)`` at
    ``bounds_max``. An axis with a count of 1 has its single probe in the middle of the box,
    ``(bounds_min + bounds_max) / 2``.
Linear index
    ``index = (i * ny + j) * nz + k`` (C order of an ``(nx, ny, nz)`` array, ``k`` fastest). Every
    per-probe array of a grid store has this index as its first axis.
Cells
    For a point ``p`` clamped onto the box, ``t = (p - bounds_min) / spacing`` per axis (``t = 0``
    on an axis with a count of 1); the point's cell has lower corner ``base = clip(floor(t), 0,
    counts - 2)`` and fractional position ``frac = clip(t - base, 0, 1)``. Points on the upper face
    belong to the last cell with ``frac = 1``.
Corners
    The 8 corners of a cell are ordered ``c = 4 di + 2 dj + dk`` with ``di, dj, dk`` in ``{0, 1}``
    (the same C order), corner ``c`` being probe ``base + (di, dj, dk)``. On an axis with a count
    of 1 the ``d = 1`` corner repeats probe 0 and always has weight 0.
Trilinear weights
    ``w_c = prod_axes (frac if d == 1 else 1 - frac)``; they are >= 0, sum to 1, and reproduce
    affine functions of position exactly (up to rounding).
Outside
    A point with any coordinate outside ``[bounds_min, bounds_max]`` is *outside*: it is clamped
    onto the box (nearest point of the box) and flagged.

References: the regular lattice with trilinear blending of a cell's 8 corner probes is the scheme
of engine probe volumes such as Unity's Light Probe Proxy Volumes and of DDGI (Majercik et al.,
"Dynamic Diffuse Global Illumination with Ray-Traced Irradiance Fields", JCGT 8(2), 2019), which
builds its visibility-aware weights (:mod:`probegrid.core.ddgi`) on top of these.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "CORNER_OFFSETS",
    "GridSpec",
    "parse_bounds",
    "parse_grid",
    "parse_spacing",
]

#: ``(8, 3)`` int64: the offsets ``(di, dj, dk)`` of the cell corners in corner order
#: ``c = 4 di + 2 dj + dk``.
CORNER_OFFSETS: Final[NDArray[np.int64]] = np.array(
    [[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)], dtype=np.int64
)
CORNER_OFFSETS.setflags(write=False)

Vec3 = tuple[float, float, float]


@dataclass(init=False, unsafe_hash=True)
class GridSpec:
    """An axis-aligned box with ``counts = (nx, ny, nz)`` probes on its corner-inclusive lattice.

    Immutable, hashable and JSON-serialisable as ``{"bounds_min": [...], "bounds_max": [...],
    "counts": [...]}`` (it is stored in a grid store's manifest, whose model validates it through
    this constructor). Build it with :meth:`from_counts` or :meth:`from_spacing`; the
    constructor takes the same fields as keywords and raises a one-line ``ValueError`` for an
    invalid grid.

    Attributes
    ----------
    bounds_min, bounds_max : 3 floats
        Box corners in world units (metres), finite, ``bounds_min <= bounds_max``; an axis with
        more than one probe needs ``bounds_min < bounds_max``.
    counts : 3 ints >= 1
        Probes per axis ``(nx, ny, nz)``.
    """

    bounds_min: Vec3
    bounds_max: Vec3
    counts: tuple[int, int, int]

    def __init__(self, *, bounds_min: ArrayLike, bounds_max: ArrayLike,
                 counts: Sequence[int]) -> None:
        lo, hi = tuple(bounds_min), tuple(bounds_max)  # type: ignore[arg-type]
        counts = tuple(counts)
        for name, v in (("bounds_min", lo), ("bounds_max", hi)):
            if len(v) != 3:
                raise ValueError(f"invalid grid: {name} must be three numbers, got {v!r}")
            if not all(math.isfinite(float(x)) for x in v):
                raise ValueError("invalid grid: grid bounds must be finite numbers")
        if len(counts) != 3 or not all(
            isinstance(n, (int, np.integer)) and not isinstance(n, bool) for n in counts
        ):
            raise ValueError(f"invalid grid: counts must be three integers, got {counts!r}")
        if min(counts) < 1:
            raise ValueError(f"invalid grid: counts must be >= 1 on every axis, got {counts!r}")
        object.__setattr__(self, "bounds_min", tuple(float(x) for x in lo))
        object.__setattr__(self, "bounds_max", tuple(float(x) for x in hi))
        object.__setattr__(self, "counts", tuple(int(n) for n in counts))
        for axis, a, b, n in zip("xyz", self.bounds_min, self.bounds_max, self.counts):
            if b < a:
                raise ValueError(f"invalid grid: grid bounds are reversed on {axis}: "
                                 f"min {a} > max {b}")
            if n > 1 and not b > a:
                raise ValueError(
                    f"invalid grid: grid has {n} probes on {axis} but an empty extent "
                    f"({a} to {b})"
                )

    def __setattr__(self, name: str, value: Any) -> None:
        raise ValueError(f"GridSpec is frozen: cannot set {name!r} (build a new grid)")

    def __delattr__(self, name: str) -> None:
        raise ValueError(f"GridSpec is frozen: cannot delete {name!r}")

    # ------------------------------------------------------------------ JSON form
    def as_dict(self) -> dict[str, list[float] | list[int]]:
        """The JSON form ``{"bounds_min": [x, y, z], "bounds_max": [...], "counts": [...]}``."""
        return {"bounds_min": list(self.bounds_min), "bounds_max": list(self.bounds_max),
                "counts": list(self.counts)}

    @classmethod
    def from_dict(cls, data: Any) -> GridSpec:
        """The grid of a JSON form (:meth:`as_dict`); a one-line ValueError for anything else."""
        if isinstance(data, GridSpec):
            return data
        keys = ("bounds_min", "bounds_max", "counts")
        if not isinstance(data, dict) or set(data) != set(keys):
            raise ValueError(f"invalid grid: expected an object with exactly the keys "
                             f"{', '.join(keys)}, got {data!r:.200}")
        for k in keys:
            if not isinstance(data[k], (list, tuple)) or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in data[k]
            ):
                raise ValueError(f"invalid grid: {k} must be a list of numbers")
        return cls(bounds_min=tuple(data["bounds_min"]), bounds_max=tuple(data["bounds_max"]),
                   counts=tuple(data["counts"]))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_counts(
        cls, bounds_min: ArrayLike, bounds_max: ArrayLike, counts: Sequence[int]
    ) -> GridSpec:
        """Grid with the given probe counts spanning the box exactly.

        Parameters
        ----------
        bounds_min, bounds_max : (3,) float
        counts : 3 ints >= 1
        """
        lo, hi = _vec3(bounds_min, "bounds_min"), _vec3(bounds_max, "bounds_max")
        c = tuple(counts)
        if len(c) != 3 or not all(
            isinstance(n, (int, np.integer)) and not isinstance(n, bool) for n in c
        ):
            raise ValueError(f"counts must be three integers (nx, ny, nz), got {counts!r}")
        if min(c) < 1:
            raise ValueError(f"counts must be >= 1 on every axis, got {c}")
        return _build(cls, lo, hi, tuple(int(n) for n in c))

    @classmethod
    def from_spacing(
        cls, bounds_min: ArrayLike, bounds_max: ArrayLike, spacing: float | ArrayLike
    ) -> GridSpec:
        """Grid with probes exactly ``spacing`` apart, centred in the box.

        Per axis, ``count = floor(extent / spacing) + 1`` (a relative tolerance of 1e-9 absorbs
        rounding, so an extent of exactly ``m`` spacings gives ``m + 1`` probes), and the box
        shrinks about its centre to ``(count - 1) * spacing`` so the lattice step is exactly
        ``spacing``. An axis left with a single probe keeps the given extent (its probe sits in
        the middle).

        Parameters
        ----------
        bounds_min, bounds_max : (3,) float
        spacing : float or (3,) float
            Probe spacing in world units, > 0.
        """
        lo = np.array(_vec3(bounds_min, "bounds_min"))
        hi = np.array(_vec3(bounds_max, "bounds_max"))
        s = np.broadcast_to(np.asarray(spacing, dtype=np.float64), (3,))
        if not np.all(np.isfinite(s)) or not np.all(s > 0):
            raise ValueError(f"spacing must be finite and > 0, got {spacing!r}")
        if np.any(hi < lo):
            raise ValueError(f"grid bounds are reversed: min {tuple(lo)} > max {tuple(hi)}")
        extent = hi - lo
        counts = np.floor(extent / s * (1.0 + 1e-9)).astype(np.int64) + 1
        centre = 0.5 * (lo + hi)
        half = 0.5 * (counts - 1) * s
        new_lo = np.where(counts > 1, centre - half, lo)
        new_hi = np.where(counts > 1, centre + half, hi)
        return _build(
            cls, tuple(new_lo.tolist()), tuple(new_hi.tolist()), tuple(int(n) for n in counts)
        )

    # ------------------------------------------------------------------ sizes
    @property
    def shape(self) -> tuple[int, int, int]:
        """``(nx, ny, nz)``."""
        return self.counts

    @property
    def n_probes(self) -> int:
        """Number of probes ``P = nx * ny * nz``."""
        nx, ny, nz = self.counts
        return nx * ny * nz

    @property
    def lo(self) -> NDArray[np.float64]:
        """``(3,)`` float64 ``bounds_min``."""
        return np.array(self.bounds_min, dtype=np.float64)

    @property
    def hi(self) -> NDArray[np.float64]:
        """``(3,)`` float64 ``bounds_max``."""
        return np.array(self.bounds_max, dtype=np.float64)

    @property
    def spacing(self) -> NDArray[np.float64]:
        """``(3,)`` float64 lattice step ``(max - min) / (counts - 1)``; 0 on single-probe axes."""
        n = np.array(self.counts, dtype=np.float64)
        return np.where(n > 1, (self.hi - self.lo) / np.maximum(n - 1, 1), 0.0)

    @property
    def cell_size(self) -> NDArray[np.float64]:
        """``(3,)`` float64 size of a cell: the lattice step, or the box extent on single-probe axes.

        This is the length "a fraction of a cell" refers to (e.g. when moving invalid probes).
        """
        n = np.array(self.counts)
        return np.where(n > 1, self.spacing, self.hi - self.lo)

    def smallest_cell(self, default: float = 0.0) -> float:
        """The smallest :attr:`cell_size` over the axes with more than one probe (the length
        biases and margins are counted in), or ``default`` for a single probe."""
        cells = self.cell_size[np.array(self.counts) > 1]
        return float(cells.min()) if cells.size else default

    # ------------------------------------------------------------------ positions and indices
    def axis_coordinates(self, axis: int) -> NDArray[np.float64]:
        """``(counts[axis],)`` float64 coordinates of the probe planes along one axis (0, 1, 2)."""
        if axis not in (0, 1, 2):
            raise ValueError(f"axis must be 0, 1 or 2, got {axis!r}")
        n = self.counts[axis]
        lo, hi = self.bounds_min[axis], self.bounds_max[axis]
        if n == 1:
            return np.array([0.5 * (lo + hi)])
        return lo + np.arange(n, dtype=np.float64) * ((hi - lo) / (n - 1))

    def positions(self) -> NDArray[np.float64]:
        """``(P, 3)`` float64 probe positions in linear index order."""
        x, y, z = (self.axis_coordinates(a) for a in range(3))
        grid = np.meshgrid(x, y, z, indexing="ij")
        return np.stack(grid, axis=-1).reshape(-1, 3)

    def probe_index(self, i: ArrayLike, j: ArrayLike, k: ArrayLike) -> NDArray[np.int64]:
        """Linear index ``(i * ny + j) * nz + k`` of lattice coordinates (broadcast, int64).

        Raises ValueError for a coordinate out of range.
        """
        ijk = np.stack(np.broadcast_arrays(*(np.asarray(a) for a in (i, j, k))), axis=-1)
        if ijk.size and not np.issubdtype(ijk.dtype, np.integer):
            raise ValueError(f"probe coordinates must be integers, got dtype {ijk.dtype}")
        ijk = ijk.astype(np.int64)
        n = np.array(self.counts)
        if np.any(ijk < 0) or np.any(ijk >= n):
            raise ValueError(f"probe coordinates out of range for a {self.label} grid")
        return (ijk[..., 0] * n[1] + ijk[..., 1]) * n[2] + ijk[..., 2]

    def probe_ijk(self, index: ArrayLike) -> NDArray[np.int64]:
        """``(..., 3)`` int64 lattice coordinates of linear indices (inverse of probe_index)."""
        idx = np.asarray(index)
        if idx.size and not np.issubdtype(idx.dtype, np.integer):
            raise ValueError(f"probe indices must be integers, got dtype {idx.dtype}")
        idx = idx.astype(np.int64)
        if np.any(idx < 0) or np.any(idx >= self.n_probes):
            raise ValueError(f"probe index out of range 0..{self.n_probes - 1}")
        _, ny, nz = self.counts
        return np.stack([idx // (ny * nz), (idx // nz) % ny, idx % nz], axis=-1)

    @property
    def label(self) -> str:
        """``"NXxNYxNZ"``, the form :func:`parse_grid` reads."""
        return "x".join(str(n) for n in self.counts)

    # ------------------------------------------------------------------ cells and weights
    def cell_weights(
        self, points: ArrayLike
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.bool_]]:
        """Cell and position within the cell of each point (see the module's conventions).

        Parameters
        ----------
        points : (..., 3) float
            World positions; must be finite.

        Returns
        -------
        base : (..., 3) int64
            Lattice coordinates of the cell's lower corner, ``0 <= base <= max(counts - 2, 0)``.
        frac : (..., 3) float64
            Position inside the cell in ``[0, 1]`` (0 on single-probe axes).
        outside : (...) bool
            The point lay outside the box and was clamped onto it.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.shape[-1:] != (3,):
            raise ValueError(f"points must have shape (..., 3), got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("points must be finite (no nan or inf coordinates)")
        lo, hi = self.lo, self.hi
        outside = np.any((p < lo) | (p > hi), axis=-1)
        n = np.array(self.counts)
        multi = n > 1
        step = np.where(multi, self.spacing, 1.0)
        t = np.where(multi, (np.clip(p, lo, hi) - lo) / step, 0.0)
        base = np.clip(np.floor(t), 0, np.maximum(n - 2, 0)).astype(np.int64)
        frac = np.clip(t - base, 0.0, 1.0)
        return base, frac, outside

    def corner_indices(self, points: ArrayLike) -> NDArray[np.int64]:
        """``(..., 8)`` int64 linear indices of the 8 corners of each point's cell (corner order)."""
        return self.corners(points)[0]

    def trilinear_weights(self, points: ArrayLike) -> NDArray[np.float64]:
        """``(..., 8)`` float64 trilinear weights of the 8 corners (corner order; they sum to 1)."""
        return self.corners(points)[1]

    def corners(
        self, points: ArrayLike
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.bool_]]:
        """Corner indices, trilinear weights and outside flags in one pass.

        Parameters
        ----------
        points : (..., 3) float

        Returns
        -------
        indices : (..., 8) int64
            Linear probe indices of the cell corners, ``c = 4 di + 2 dj + dk``.
        weights : (..., 8) float64
            Trilinear weights, >= 0, summing to 1.
        outside : (...) bool
            See :meth:`cell_weights`.
        """
        base, frac, outside = self.cell_weights(points)
        n = np.array(self.counts)
        ijk = np.minimum(base[..., None, :] + CORNER_OFFSETS, n - 1)  # (..., 8, 3)
        indices = (ijk[..., 0] * n[1] + ijk[..., 1]) * n[2] + ijk[..., 2]
        f = frac[..., None, :]
        weights = np.prod(np.where(CORNER_OFFSETS == 1, f, 1.0 - f), axis=-1)
        return indices, weights, outside

    def point_corners(self, x: float, y: float, z: float) -> tuple[list[int], list[float], bool]:
        """:meth:`corners` of one point, in plain Python float arithmetic.

        For a single point numpy's per-call overhead is nearly all of the cost of
        :meth:`corners` (about 35 us against 1.5 us here); this is the scalar path of per-point
        queries (:func:`probegrid.core.ddgi.probe_weights` of one point). It performs the same
        IEEE-754 double operations in the same order (clamp, ``(p - lo) / step``, floor, clip,
        ``1 - frac``, the product over axes x, y, z), so its indices, weights and flag equal
        :meth:`corners`' (tested bit for bit; a zero weight may differ in sign, as numpy's own
        ``clip`` of ``-0.0`` does between array sizes).

        Parameters
        ----------
        x, y, z : float
            World position, finite (not checked here: :meth:`corners` checks).

        Returns
        -------
        indices : list of 8 int
        weights : list of 8 float
        outside : bool
        """
        (lx, ly, lz), (hx, hy, hz), (nx, ny, nz) = self.bounds_min, self.bounds_max, self.counts
        outside = x < lx or x > hx or y < ly or y > hy or z < lz or z > hz
        i0, i1, wx0, wx1 = _axis_cell(x, lx, hx, nx)
        j0, j1, wy0, wy1 = _axis_cell(y, ly, hy, ny)
        k0, k1, wz0, wz1 = _axis_cell(z, lz, hz, nz)
        r00, r01 = (i0 * ny + j0) * nz, (i0 * ny + j1) * nz  # corner c = 4 di + 2 dj + dk
        r10, r11 = (i1 * ny + j0) * nz, (i1 * ny + j1) * nz
        indices = [r00 + k0, r00 + k1, r01 + k0, r01 + k1, r10 + k0, r10 + k1, r11 + k0, r11 + k1]
        w00, w01, w10, w11 = wx0 * wy0, wx0 * wy1, wx1 * wy0, wx1 * wy1  # (wx * wy) * wz
        weights = [w00 * wz0, w00 * wz1, w01 * wz0, w01 * wz1,
                   w10 * wz0, w10 * wz1, w11 * wz0, w11 * wz1]
        return indices, weights, outside


def _axis_cell(p: float, lo: float, hi: float, n: int) -> tuple[int, int, float, float]:
    """One axis of :meth:`GridSpec.point_corners`: lattice coordinates of the cell's two corner
    planes and their trilinear factors ``1 - frac`` and ``frac``."""
    if n == 1:
        return 0, 0, 1.0, 0.0
    c = lo if p <= lo else min(hi, p)  # np.clip(p, lo, hi)
    t = (c - lo) / ((hi - lo) / (n - 1))  # >= 0, so int() is floor()
    b = min(int(t), n - 2)
    f = t - b
    f = 0.0 if f <= 0.0 else min(1.0, f)  # np.clip(f, 0, 1)
    return b, b + 1, 1.0 - f, f


def _build(cls: type[GridSpec], lo: Vec3, hi: Vec3, counts: tuple[int, ...]) -> GridSpec:
    return cls(bounds_min=lo, bounds_max=hi, counts=counts)  # type: ignore[arg-type]


def _vec3(v: ArrayLike, name: str) -> Vec3:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"{name} must be three numbers (x, y, z), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {tuple(a.tolist())}")
    return (float(a[0]), float(a[1]), float(a[2]))


_GRID_RE = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*[xX]\s*(\d+)\s*$")


def parse_grid(text: str) -> tuple[int, int, int]:
    """Probe counts from ``"NXxNYxNZ"`` (e.g. ``"16x8x16"``), each >= 1.

    Raises ValueError with a one-line message otherwise.
    """
    m = _GRID_RE.match(text) if isinstance(text, str) else None
    if m is None:
        raise ValueError(f"grid must be NXxNYxNZ with three positive integers (e.g. 16x8x16), "
                         f"got {text!r}")
    counts = tuple(int(g) for g in m.groups())
    if min(counts) < 1:
        raise ValueError(f"grid counts must be >= 1 on every axis, got {text!r}")
    return counts  # type: ignore[return-value]


def _parse_floats(text: str, what: str, form: str) -> list[float]:
    if not isinstance(text, str):
        raise TypeError(f"{what} must be a string of the form {form}, got {text!r}")
    try:
        values = [float(t) for t in text.split(",")]
    except ValueError:
        raise ValueError(f"{what} must be {form} with numbers, got {text!r}") from None
    if not all(math.isfinite(x) for x in values):
        raise ValueError(f"{what} must be finite numbers, got {text!r}")
    return values


def parse_bounds(text: str) -> tuple[Vec3, Vec3]:
    """Box corners from ``"x0,y0,z0,x1,y1,z1"`` -> ``((x0, y0, z0), (x1, y1, z1))``.

    Requires six finite numbers with ``x0 <= x1``, ``y0 <= y1``, ``z0 <= z1``; raises ValueError
    with a one-line message otherwise.
    """
    form = "x0,y0,z0,x1,y1,z1"
    v = _parse_floats(text, "bounds", form)
    if len(v) != 6:
        raise ValueError(f"bounds must be six numbers {form}, got {len(v)} in {text!r}")
    lo, hi = (v[0], v[1], v[2]), (v[3], v[4], v[5])
    bad = [a for a, x0, x1 in zip("xyz", lo, hi) if x1 < x0]
    if bad:
        raise ValueError(f"bounds are reversed on {', '.join(bad)} (need min <= max): {text!r}")
    return lo, hi


def parse_spacing(text: str) -> float | Vec3:
    """Probe spacing from ``"S"`` or ``"SX,SY,SZ"``, each finite and > 0.

    Raises ValueError with a one-line message otherwise.
    """
    v = _parse_floats(text, "spacing", "S or SX,SY,SZ")
    if len(v) not in (1, 3):
        raise ValueError(f"spacing must be one number or three (SX,SY,SZ), got {text!r}")
    if min(v) <= 0:
        raise ValueError(f"spacing must be > 0, got {text!r}")
    return v[0] if len(v) == 1 else (v[0], v[1], v[2])
