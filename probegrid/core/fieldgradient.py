"""A first-order term for a lattice's interpolation near its faces: limited gradients.

Irradiance caches interpolate better with each record's gradient (Ward and Heckbert's
translational gradients): a point ``q`` takes ``sum_c w_c (f_c + g_c . (q - x_c))`` over the
records ``c`` instead of ``sum_c w_c f_c``. On a lattice whose outer layers sit just inside the
walls (the SH field, :mod:`probegrid.bake.shfield`) the light changes fastest in the cells next
to the walls, where trilinear interpolation between two layers misses how it bends; there the
first-order term follows it.

Gradients are finite differences of the lattice's own values (no extra bake), *limited*: per
axis the minmod of the backward and forward differences (the one whose magnitude is smaller when
they agree in sign, 0 when they do not; one-sided where a neighbour is missing or invalid, 0
with neither), the slope limiter of MUSCL schemes (van Leer 1979). The limiter keeps a point's
term within what its neighbours say: a shadow edge or a point's own noise gives no overshoot.

Properties (``tests/test_field_gradient.py``): an affine field has exact gradients, and
``sum_c w_c g . (q - x_c) = g . (q - sum_c w_c x_c) = 0`` for weights that reproduce the point,
so the term leaves an affine field exact; it changes an answer only where the gradients differ
between corners (curvature) or the weights lost corners (hidden or invalid ones).

Measured against Mitsuba on the SH field (``docs/benchmarks.md``): applied in the lattice's
outer cells (a cell with a face on the lattice's box, and the extrapolated points beyond it) it
lowers the error; applied everywhere it raises it (the inner points' own noise), so
:func:`outer_cells` selects where the term applies.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core.grid import GridSpec

__all__ = ["first_order_term", "gradient_table", "limited_gradients", "outer_cells"]


def limited_gradients(values: ArrayLike, grid: GridSpec, *, valid: ArrayLike | None = None
                      ) -> NDArray[np.float64]:
    """``(P, ..., 3)`` float64 limited gradients (module docstring) of ``values (P, ...)``
    stored at the points of ``grid``; an invalid point has gradient 0 and is no neighbour."""
    v = np.asarray(values, dtype=np.float64)
    if v.shape[0] != grid.n_probes:
        raise ValueError(f"values must have one row per lattice point ({grid.n_probes}), got "
                         f"{v.shape[0]}.")
    ok = np.ones(grid.n_probes, bool) if valid is None else np.asarray(valid, dtype=bool)
    counts = grid.counts
    field = v.reshape(*counts, *v.shape[1:])
    good = ok.reshape(counts)
    out = np.zeros((*counts, *v.shape[1:], 3))
    step = grid.spacing
    extra = (None,) * (v.ndim - 1)
    for a in range(3):  # a loop over the 3 axes
        if counts[a] < 2:
            continue
        f = np.moveaxis(field, a, 0)
        g = np.moveaxis(good, a, 0)
        diff = (f[1:] - f[:-1]) / step[a]  # (n - 1, ...): the difference between layers
        both = (g[1:] & g[:-1])[(...,) + extra]
        fwd = np.zeros_like(f)
        bwd = np.zeros_like(f)
        has_f = np.zeros(f.shape, bool)
        has_b = np.zeros(f.shape, bool)
        fwd[:-1], has_f[:-1] = diff, np.broadcast_to(both, diff.shape)
        bwd[1:], has_b[1:] = diff, np.broadcast_to(both, diff.shape)
        minmod = np.where(np.sign(fwd) == np.sign(bwd),
                          np.sign(fwd) * np.minimum(np.abs(fwd), np.abs(bwd)), 0.0)
        slope = np.where(has_f & has_b, minmod, np.where(has_f, fwd, np.where(has_b, bwd, 0.0)))
        slope = np.where(g[(...,) + extra], slope, 0.0)
        np.moveaxis(out[..., a], a, 0)[...] = slope
    return out.reshape(grid.n_probes, *v.shape[1:], 3)


def outer_cells(grid: GridSpec) -> NDArray[np.bool_]:
    """``(P,)`` bool: whether the cell a lattice point is the lower corner of (its index is a
    weight's corner 0) has a face on the lattice's box -- the cells next to the walls."""
    n = np.array(grid.counts)
    ijk = grid.probe_ijk(np.arange(grid.n_probes))
    last = np.maximum(n - 2, 0)
    return np.any(((ijk == 0) | (ijk == last)) & (n > 1), axis=1)


def gradient_table(gradients: ArrayLike, positions: ArrayLike) -> NDArray[np.float64]:
    """``(P, K, 4)`` float64 per lattice point and value ``k`` (the ``...`` axes flattened)
    ``(g_x, g_y, g_z, -g . x)``: the first-order term at ``q`` of corner ``c`` is
    ``table[c] . (q, 1)``, so a point's term is the blend of the corners' rows dotted with
    ``(q, 1)`` (:func:`first_order_term`)."""
    g = np.asarray(gradients, dtype=np.float64)
    g = g.reshape(g.shape[0], -1, 3)
    x = np.asarray(positions, dtype=np.float64)
    return np.concatenate([g, -np.einsum("pka,pa->pk", g, x)[..., None]], axis=-1)


def first_order_term(table: NDArray[np.float64], indices: NDArray[np.int64],
                     weights: NDArray[np.float64], points: NDArray[np.float64]
                     ) -> NDArray[np.float64]:
    """``(n, K)`` float64 ``sum_c w_c g_c . (q - x_c)`` of points ``q (n, 3)`` over their
    corners ``indices (n, 8)`` with ``weights (n, 8)``, from :func:`gradient_table` (whose
    rows are finite: an invalid point's gradient is 0, so a corner of weight 0 adds 0)."""
    n, k = len(indices), table.shape[1]
    q1 = np.concatenate([points, np.ones((n, 1))], axis=1)
    if n == 1:  # one point: two small products
        return ((weights[0] @ table[indices[0]].reshape(8, 4 * k)).reshape(k, 4) @ q1[0])[None]
    blended = np.einsum("nc,nckd->nkd", weights, table[indices])
    return np.einsum("nkd,nd->nk", blended, q1)
