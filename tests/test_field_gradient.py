"""Limited gradients of a lattice's values (probegrid.core.fieldgradient) and the first-order
term the SH field adds in its outer cells (ProbeField.sh_at)."""

from __future__ import annotations

import numpy as np
from test_sh_field import affine_sh, field_store

from probegrid.bake.shfield import field_lattice
from probegrid.core.fieldgradient import (
    first_order_term,
    gradient_table,
    limited_gradients,
    outer_cells,
)
from probegrid.core.grid import GridSpec
from probe_stores import GRID

LATTICE = GridSpec.from_counts((-1.0, 0.0, 0.5), (2.0, 1.5, 3.0), (7, 4, 6))


def _sloped(grid: GridSpec, valid: np.ndarray) -> np.ndarray:
    """``(P, 3)``: whether a valid point has a valid neighbour along each axis."""
    ok = valid.reshape(grid.counts)
    out = []
    for a in range(3):
        m = np.moveaxis(ok, a, 0)
        near = np.zeros_like(m)
        near[:-1] |= m[1:]
        near[1:] |= m[:-1]
        out.append((np.moveaxis(near, 0, a) & ok).ravel())
    return np.stack(out, axis=1)


def test_an_affine_field_has_its_exact_gradient_everywhere_even_beside_invalid_points():
    rng = np.random.default_rng(1)
    g = rng.normal(size=(5, 3))
    values = 2.0 + LATTICE.positions() @ g.T  # (P, 5)
    valid = rng.random(LATTICE.n_probes) > 0.15
    got = limited_gradients(values, LATTICE, valid=valid)
    assert got.shape == (LATTICE.n_probes, 5, 3)
    sloped = _sloped(LATTICE, valid)
    for a in range(3):  # exact on each axis along which a valid point has a valid neighbour
        has = sloped[:, a]
        assert has.sum() > 0.7 * LATTICE.n_probes
        np.testing.assert_allclose(got[has, :, a], np.broadcast_to(g[:, a], (has.sum(), 5)),
                                   atol=1e-12)
        assert not got[~has, :, a].any()  # none: no slope


def test_the_limiter_takes_the_smaller_slope_and_zero_at_an_extremum():
    grid = GridSpec.from_counts((0.0, 0.0, 0.0), (4.0, 0.0, 0.0), (5, 1, 1))
    x = grid.positions()[:, 0]
    got = limited_gradients((x - 2.0) ** 2, grid)[:, 0]  # differences -3, -1, 1, 3
    np.testing.assert_array_equal(got, [-3.0, -1.0, 0.0, 1.0, 3.0])


def test_outer_cells_are_those_on_the_lattice_box():
    outer = outer_cells(LATTICE).reshape(LATTICE.counts)
    assert outer[0].all() and outer[:, 0].all() and outer[:, :, 0].all()
    assert outer[5].all() and outer[:, 2].all() and outer[:, :, 4].all()  # the last cells
    assert not outer[1:5, 1:2, 1:4].any()


def test_the_term_of_many_points_equals_that_of_each():
    rng = np.random.default_rng(2)
    values = rng.normal(size=(LATTICE.n_probes, 9, 3))
    table = gradient_table(limited_gradients(values, LATTICE), LATTICE.positions())
    pts = LATTICE.lo + rng.random((50, 3)) * (LATTICE.hi - LATTICE.lo)
    idx, w, _ = LATTICE.corners(pts)
    many = first_order_term(table, idx, w, pts)
    one = np.concatenate([first_order_term(table, idx[i:i + 1], w[i:i + 1], pts[i:i + 1])
                          for i in range(50)])
    np.testing.assert_allclose(many, one, rtol=1e-12, atol=1e-12)
    # sum_c w_c g_c . (q - x_c), written out
    x = LATTICE.positions()[idx]
    g = limited_gradients(values, LATTICE).reshape(LATTICE.n_probes, 27, 3)[idx]
    want = np.einsum("nc,ncka,nca->nk", w, g, pts[:, None] - x)
    np.testing.assert_allclose(many, want, rtol=1e-9, atol=1e-12)


def _outer_points(lattice: GridSpec, n: int) -> np.ndarray:
    """Points in the lattice's outer cells (within a step of its -x and +x faces)."""
    rng = np.random.default_rng(3)
    pts = lattice.lo + rng.random((n, 3)) * (lattice.hi - lattice.lo)
    side = rng.integers(0, 2, n)
    step = lattice.spacing[0]
    pts[:, 0] = np.where(side == 0, lattice.lo[0] + rng.uniform(0, 0.95, n) * step,
                         lattice.hi[0] - rng.uniform(0, 0.95, n) * step)
    return pts


def test_with_lost_corners_the_term_restores_an_affine_field(tmp_path):
    lattice = field_lattice(GRID, 2.0)
    pts = _outer_points(lattice, 64)
    idx = lattice.corners(pts)[0]
    valid = np.ones(lattice.n_probes, bool)
    valid[idx[::4, 7]] = False  # a corner lost in a quarter of the points' cells
    f = field_store(tmp_path / "lost.probes", affine_sh, valid=valid)
    truth = affine_sh(pts)
    got, w, used = f.sh_at(pts)
    plain = f.sh_at(pts, gradient=False)[0]
    assert used == "field"
    # the points whose corners all have their exact gradient (a valid neighbour on each axis)
    sloped = _sloped(lattice, valid).all(axis=1)[w.indices] | (w.weights == 0)
    lost = (w.weights == 0).any(axis=1) & sloped.all(axis=1)
    assert lost.sum() >= 8
    scale = np.abs(truth).max()
    # renormalised weights no longer reproduce the point: the plain blend is off
    assert np.median(np.abs(plain - truth)[lost].max(axis=(1, 2))) > 1e-3 * scale
    # the first-order term of the exact gradients puts it back, and every other point whose
    # corners have their slopes stays exact (a corner without a valid neighbour on an axis has
    # no slope there: its points are not)
    exact = sloped.all(axis=1)
    assert exact.sum() >= 20
    assert np.abs(got - truth)[exact].max() <= 1e-5 * scale
    one = np.array([f.sh_at(p)[0][0] for p in pts[:8]])
    np.testing.assert_allclose(one, got[:8], rtol=1e-12, atol=1e-12)


def test_inner_cells_keep_the_plain_interpolation(tmp_path):
    lattice = field_lattice(GRID, 2.0)
    f = field_store(tmp_path / "q.probes", lambda p: affine_sh(p) + (p[:, 1] ** 2)[:, None, None])
    inner = lattice.lo + lattice.spacing * np.array([[2.3, 1.6, 2.2], [3.5, 2.5, 3.1]])
    assert not outer_cells(lattice)[lattice.corners(inner)[0][:, 0]].any()
    np.testing.assert_array_equal(f.sh_at(inner)[0], f.sh_at(inner, gradient=False)[0])
    outer = _outer_points(lattice, 8)
    assert (f.sh_at(outer)[0] != f.sh_at(outer, gradient=False)[0]).any()
