"""Helpers shared by the probe-query routes (not a router)."""

from __future__ import annotations

from functools import lru_cache
from typing import Any

from probegrid.core.ddgi import ProbeWeights
from probegrid.core.grid import GridSpec


def _used(weights: ProbeWeights, row: int) -> list[tuple[int, float]]:
    """``(index, weight)`` of the probes with non-zero weight for one point, in corner order
    (a linear extrapolation beyond the probes' box gives some negative weights)."""
    return [(i, w) for i, w in zip(weights.indices[row].tolist(), weights.weights[row].tolist(),
                                   strict=True) if w != 0]


def probes_json(grid: GridSpec, weights: ProbeWeights, row: int = 0, *,
                positions: bool = False) -> list[dict[str, Any]]:
    """The probes (or lattice points) of ``grid`` with non-zero weight for one point, in corner
    order, as :class:`service.schemas.ProbeUse` dicts (with their ``position`` on the lattice
    if asked)."""
    _, ny, nz = grid.counts  # linear index (i * ny + j) * nz + k, see probegrid.core.grid
    cx, cy, cz = _lattice_coordinates(grid) if positions else ((), (), ())
    out = []
    for i, w in _used(weights, row):
        a, b, c = i // (ny * nz), i // nz % ny, i % nz
        p = {"index": i, "ijk": [a, b, c], "weight": w}
        if positions:
            p["position"] = [cx[a], cy[b], cz[c]]
        out.append(p)
    return out


@lru_cache(maxsize=16)
def _lattice_coordinates(grid: GridSpec) -> tuple[list[float], list[float], list[float]]:
    """Per axis the lattice's coordinates ``bounds_min + i (bounds_max - bounds_min) / (n - 1)``
    (``bounds_min`` on an axis of one point), once a grid."""
    lo, hi, n = grid.bounds_min, grid.bounds_max, grid.counts
    x, y, z = ([lo[a] + t * (hi[a] - lo[a]) / (n[a] - 1) if n[a] > 1 else lo[a]
                for t in range(n[a])] for a in range(3))
    return x, y, z


def flags_json(weights: ProbeWeights, *, visibility: bool, row: int = 0) -> dict[str, Any]:
    """A :class:`service.schemas.QueryFlags` dict (``visibility_test`` from the weights)."""
    return {"outside": bool(weights.outside[row]), "unlit": bool(weights.unlit[row]),
            "visibility": visibility, "visibility_test": weights.visibility}


def probe_header(weights: ProbeWeights, row: int = 0) -> str:
    """``index:weight`` pairs of the probes used, comma separated (a response header)."""
    return ",".join(f"{i}:{w!r}" for i, w in _used(weights, row))
