"""The maps a probe's store entry holds, from its incoming cube: SH minima, diffuse maps and GGX
chains filtered a group of probes at a time, and the energy check of the diffuse filter.

The filters are linear and act on each channel alike, so :data:`FILTER_GROUP` probes go through
one call as the channels of a single cube, always of the same shape (the last group padded with
zeros): what a probe's maps hold does not depend on which probes share its group, i.e. on the
batch. The final stage (:func:`probegrid.bake.stages.final_task`) calls these per batch; the
driver recomputes the energy check of probes an interrupted bake finished
(:func:`incoming_integral_from_sh`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from probegrid import usercache
from probegrid.core import probefilter
from probegrid.core.cubemap import solid_angle_integral
from probegrid.core.sh.dering import irradiance_minimum

__all__ = ["FILTER_GROUP", "energy_ratio", "filter_groups", "incoming_integral_from_sh",
           "sh_minima"]


def energy_ratio(diffuse: NDArray[np.float32], incoming_integral: float) -> float:
    """Solid-angle integral of a diffuse map over that of its incoming cube (all channels):
    1 for an energy-conserving filter, since the clamped cosine / pi integrates to 1 over the
    normals. NaN for a probe that receives no light (nothing to conserve)."""
    if not incoming_integral > 0:
        return math.nan
    return float(solid_angle_integral(diffuse).sum()) / incoming_integral


def incoming_integral_from_sh(sh_l: NDArray[Any]) -> float:
    """The incoming cube's integral over the sphere from its stored SH, all channels:
    ``integral L = L_00 / Y_00 = 2 sqrt(pi) L_00`` (the projection is the same discrete sum)."""
    return float(2.0 * math.sqrt(math.pi) * np.asarray(sh_l, np.float64)[0].sum())


#: Probes filtered together, as channels of one cube (a fixed shape, see filter_groups).
FILTER_GROUP = 8


def padded_groups(items: NDArray[Any]) -> Iterator[tuple[int, int, NDArray[Any]]]:
    """``(start, count, group)`` for FILTER_GROUP items of ``items (B, ...)`` at a time, the
    last group padded with zeros: every group has the same shape, so what is computed from an
    item does not depend on which items share its group, i.e. on the batch."""
    b = len(items)
    for g0 in range(0, b, FILTER_GROUP):  # loop over groups of probes
        k = min(FILTER_GROUP, b - g0)
        group = np.zeros((FILTER_GROUP, *items.shape[1:]), items.dtype)
        group[:k] = items[g0:g0 + k]
        yield g0, k, group


def sh_minima(coeffs: NDArray[np.float64]) -> NDArray[np.float64]:
    """Minimum over the sphere of SH irradiance / pi of ``coeffs (B, 9, 3)``; ``(B, 3)``: the
    certified minimum of :func:`probegrid.core.sh.dering.irradiance_minimum` (what ``/sh``'s
    deringing holds to; each probe's and channel's result does not depend on the others).
    It replaced :func:`probegrid.core.sh.min_over_sphere`'s sampled search, 25x slower here,
    which missed the global minimum of 9 in 36 000 ringing probes (``tests/test_dering.py``)."""
    return irradiance_minimum(np.moveaxis(coeffs, 1, 2)) / np.pi


def unstack_probes(cube: NDArray[np.float32], channels: int) -> NDArray[np.float32]:
    """``(6, m, m, G * C)`` -> ``(G, 6, m, m, C)``: undo the probes-as-channels stacking."""
    m = cube.shape[1]
    return np.moveaxis(cube.reshape(6, m, m, -1, channels), 3, 0)


def filter_groups(cubes: NDArray[np.float32], diffuse_size: int, levels: int
                   ) -> tuple[list[NDArray[np.float32]], list[list[NDArray[np.float32]]]]:
    """Diffuse maps and GGX chains of ``cubes (B, 6, n, n, 3)``.

    The filters are linear and act on each channel alike, so FILTER_GROUP probes go through one
    call as the channels of a single cube, which amortises the per-call work
    (:func:`padded_groups`: every call has the same shape). Faces up to
    :data:`probegrid.core.probefilter.MAX_FACE` go through the exact sums as one cached matrix
    (:func:`probegrid.core.probefilter.filter_cube`); larger ones through
    :func:`~probegrid.core.diffuse.diffuse_exact` and the tiered
    :func:`~probegrid.core.specular.ggx_prefilter` (:func:`probegrid.core.probefilter.describe`, in the
    manifest, says which).
    """
    from probegrid.core import diffuse, specular

    _, _, n, _, c = cubes.shape
    dense = probefilter.supported(n, diffuse_size)
    dif: list[NDArray[np.float32]] = []
    chains: list[list[NDArray[np.float32]]] = []
    matrix = usercache.probe_filter_matrix(n, diffuse_size, levels) if dense else None
    for _, k, group in padded_groups(cubes):
        stacked = np.ascontiguousarray(np.moveaxis(group, 0, 3).reshape(6, n, n, -1))
        if dense:
            d, chain = probefilter.filter_cube(stacked, diffuse_size, levels, matrix=matrix)
        else:
            d = diffuse.diffuse_exact(stacked, diffuse_size)
            chain = specular.ggx_prefilter(stacked, levels=levels)

        ds = unstack_probes(d, c)
        cs = [unstack_probes(lv, c) for lv in chain]
        for j in range(k):
            dif.append(np.ascontiguousarray(ds[j]))
            chains.append([np.ascontiguousarray(lv[j]) for lv in cs])
    return dif, chains
