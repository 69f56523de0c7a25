"""Tests of the probe grid geometry (probegrid.core.grid)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from probegrid.core.grid import CORNER_OFFSETS, GridSpec, parse_bounds, parse_grid, parse_spacing


def test_positions_are_the_corner_inclusive_lattice_in_c_order():
    g = GridSpec.from_counts((-1.0, 0.0, 2.0), (1.0, 3.0, 4.0), (3, 4, 2))
    pos = g.positions()
    assert pos.shape == (24, 3) and pos.dtype == np.float64
    np.testing.assert_array_equal(pos[0], g.bounds_min)
    np.testing.assert_array_equal(pos[-1], g.bounds_max)
    for i in range(3):
        for j in range(4):
            for k in range(2):
                idx = (i * 4 + j) * 2 + k
                np.testing.assert_array_equal(pos[idx], [-1.0 + i, 0.0 + j, 2.0 + 2.0 * k])
                assert g.probe_index(i, j, k) == idx
                assert g.probe_ijk(idx).tolist() == [i, j, k]
    # the same order as numpy's C-order ravel of an (nx, ny, nz) array
    ijk = np.stack(np.unravel_index(np.arange(24), (3, 4, 2)), axis=-1)
    np.testing.assert_array_equal(g.probe_index(*ijk.T), np.arange(24))
    np.testing.assert_array_equal(g.probe_ijk(np.arange(24)), ijk)
    np.testing.assert_array_equal(g.spacing, [1.0, 1.0, 2.0])
    assert g.n_probes == 24 and g.shape == (3, 4, 2) and g.label == "3x4x2"


def test_single_probe_axes_sit_in_the_middle():
    g = GridSpec.from_counts((0.0, 0.0, 0.0), (2.0, 4.0, 6.0), (1, 3, 1))
    np.testing.assert_array_equal(g.positions(), [[1.0, 0.0, 3.0], [1.0, 2.0, 3.0], [1.0, 4.0, 3.0]])
    np.testing.assert_array_equal(g.spacing, [0.0, 2.0, 0.0])
    np.testing.assert_array_equal(g.cell_size, [2.0, 2.0, 6.0])
    one = GridSpec.from_counts((5.0, 5.0, 5.0), (5.0, 5.0, 5.0), (1, 1, 1))
    np.testing.assert_array_equal(one.positions(), [[5.0, 5.0, 5.0]])
    idx, w, out = one.corners([[5.0, 5.0, 5.0], [6.0, 5.0, 5.0]])
    np.testing.assert_array_equal(idx, 0)
    np.testing.assert_array_equal(w[:, 0], 1.0)
    np.testing.assert_array_equal(out, [False, True])


def test_from_spacing_counts_and_centring():
    g = GridSpec.from_spacing((0.0, 0.0, 0.0), (1.0, 1.05, 0.05), 0.1)
    assert g.counts == (11, 11, 1)  # 1.0/0.1 = 10 spacings exactly despite rounding
    np.testing.assert_allclose(g.spacing[:2], 0.1, rtol=1e-12)
    np.testing.assert_allclose(g.bounds_min[:2], (0.0, 0.025), atol=1e-12)  # centred
    np.testing.assert_allclose(g.bounds_max[:2], (1.0, 1.025), atol=1e-12)
    assert g.bounds_min[2] == 0.0 and g.bounds_max[2] == 0.05  # single probe keeps the box
    g = GridSpec.from_spacing((0, 0, 0), (4, 2, 1), (1.0, 0.5, 2.0))
    assert g.counts == (5, 5, 1)
    for bad in (0.0, -1.0, float("nan"), (1.0, 0.0, 1.0)):
        with pytest.raises(ValueError, match="spacing must be finite and > 0"):
            GridSpec.from_spacing((0, 0, 0), (1, 1, 1), bad)


def test_validation_is_one_line():
    cases = [
        (((0, 0, 0), (1, 1, 1), (2, 0, 2)), ">= 1"),
        (((0, 0, 0), (1, 1, 1), (2, 2)), "three integers"),
        (((0, 0, 0), (1, 1, 1), (2.0, 2, 2)), "three integers"),
        (((0, 0, 0), (1, -1, 1), (2, 2, 2)), "reversed on y"),
        (((0, 0, 0), (1, 0, 1), (2, 2, 2)), "2 probes on y but an empty extent"),
        (((0, 0, np.nan), (1, 1, 1), (2, 2, 2)), "finite"),
        (((0, 0), (1, 1, 1), (2, 2, 2)), "three numbers"),
    ]
    for args, pattern in cases:
        with pytest.raises(ValueError, match=pattern) as info:
            GridSpec.from_counts(*args)
        assert "\n" not in str(info.value)


def test_json_round_trip_and_hashable():
    g = GridSpec.from_counts((-1.5, 0.1, 2.0), (1.25, 3.3, 4.0), (3, 4, 2))
    again = GridSpec.from_dict(json.loads(json.dumps(g.as_dict())))
    assert again == g and hash(again) == hash(g)
    assert {g: 1}[again] == 1
    with pytest.raises(ValueError, match="frozen"):
        g.counts = (1, 1, 1)


def _affine(p):
    return 0.3 + p @ np.array([1.5, -2.0, 0.75])


@settings(max_examples=40, deadline=None)
@given(
    counts=st.tuples(*(st.integers(1, 5),) * 3),
    seed=st.integers(0, 2**32 - 1),
)
def test_trilinear_reproduces_affine_functions(counts, seed):
    rng = np.random.default_rng(seed)
    lo = rng.uniform(-5, 0, 3)
    hi = lo + rng.uniform(0.5, 4, 3)
    g = GridSpec.from_counts(lo, hi, counts)
    pts = rng.uniform(lo, hi, (50, 3))
    idx, w, out = g.corners(pts)
    assert idx.shape == (50, 8) and w.shape == (50, 8) and not out.any()
    assert np.all(w >= 0) and np.all((idx >= 0) & (idx < g.n_probes))
    np.testing.assert_allclose(w.sum(axis=-1), 1.0, rtol=1e-14)
    values = _affine(g.positions())
    # single-probe axes cannot vary: compare against the function at the probe plane
    expect = np.where(np.array(counts) > 1, pts, g.positions()[0])
    np.testing.assert_allclose((w * values[idx]).sum(-1), _affine(expect), rtol=1e-12, atol=1e-12)


def test_probes_get_weight_one_and_cells_are_consistent():
    g = GridSpec.from_counts((0, 0, 0), (2, 3, 4), (3, 4, 5))
    idx, w, out = g.corners(g.positions())
    assert not out.any()
    top = np.argmax(w, axis=-1)
    np.testing.assert_array_equal(w[np.arange(g.n_probes), top], 1.0)
    np.testing.assert_array_equal(idx[np.arange(g.n_probes), top], np.arange(g.n_probes))
    base, frac, _ = g.cell_weights([[1.5, 3.0, 0.25]])
    assert base.tolist() == [[1, 2, 0]]  # upper face -> last cell, frac 1
    np.testing.assert_allclose(frac, [[0.5, 1.0, 0.25]])
    # corner order c = 4 di + 2 dj + dk
    i, j, k = (base[0] + CORNER_OFFSETS).T
    np.testing.assert_array_equal(g.corner_indices([[1.5, 3.0, 0.25]])[0], g.probe_index(i, j, k))
    np.testing.assert_allclose(
        g.trilinear_weights([[1.5, 3.0, 0.25]])[0], [0, 0, 0.375, 0.125, 0, 0, 0.375, 0.125]
    )


def test_outside_points_are_clamped_and_flagged():
    g = GridSpec.from_counts((0, 0, 0), (1, 1, 1), (2, 2, 2))
    pts = np.array([[2.0, 0.5, 0.5], [-1.0, -1.0, 3.0], [0.5, 0.5, 0.5], [1.0, 1.0, 1.0]])
    idx, w, out = g.corners(pts)
    np.testing.assert_array_equal(out, [True, True, False, False])
    clamped = np.clip(pts, 0, 1)
    idx2, w2, out2 = g.corners(clamped)
    np.testing.assert_array_equal(idx, idx2)
    np.testing.assert_array_equal(w, w2)
    assert not out2.any()


def test_broadcast_shapes_and_bad_points():
    g = GridSpec.from_counts((0, 0, 0), (1, 1, 1), (2, 3, 4))
    pts = np.random.default_rng(0).uniform(0, 1, (4, 5, 3))
    base, frac, out = g.cell_weights(pts)
    assert base.shape == (4, 5, 3) and frac.shape == (4, 5, 3) and out.shape == (4, 5)
    assert g.corner_indices(pts).shape == (4, 5, 8) and g.corner_indices(pts).dtype == np.int64
    assert g.trilinear_weights(pts[0, 0]).shape == (8,)
    for bad in ([[0.5, np.nan, 0.5]], [[np.inf, 0, 0]]):
        with pytest.raises(ValueError, match="finite"):
            g.corners(bad)
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        g.corners([[0.5, 0.5]])
    with pytest.raises(ValueError, match="out of range"):
        g.probe_index(2, 0, 0)
    with pytest.raises(ValueError, match="integers"):
        g.probe_index(0.5, 0, 0)
    with pytest.raises(ValueError, match="out of range 0..23"):
        g.probe_ijk(24)


def test_parse_helpers():
    assert parse_grid("16x8x16") == (16, 8, 16)
    assert parse_grid(" 2X3x4 ") == (2, 3, 4)
    for bad in ("16x8", "16x0x4", "axbxc", "1.5x2x2", "-1x2x3", ""):
        with pytest.raises(ValueError, match="NXxNYxNZ|>= 1") as info:
            parse_grid(bad)
        assert "\n" not in str(info.value)
    assert parse_bounds("-1,0,-2.5,1,3,2.5") == ((-1.0, 0.0, -2.5), (1.0, 3.0, 2.5))
    for bad, pattern in [
        ("0,0,0,1,1", "six numbers"),
        ("0,0,0,1,1,x", "with numbers"),
        ("0,0,0,1,nan,1", "finite"),
        ("0,2,0,1,1,1", "reversed on y"),
    ]:
        with pytest.raises(ValueError, match=pattern):
            parse_bounds(bad)
    assert parse_spacing("0.5") == 0.5
    assert parse_spacing("0.5,1,2") == (0.5, 1.0, 2.0)
    for bad in ("0", "-1", "1,2", "x"):
        with pytest.raises(ValueError, match="spacing"):
            parse_spacing(bad)
    lo, hi = parse_bounds("0,0,0,4,2,2")
    assert GridSpec.from_counts(lo, hi, parse_grid("5x3x3")).spacing.tolist() == [1.0, 1.0, 1.0]


def test_cli_grid_options_honour_spacing_and_refuse_huge_grids():
    """bakejob.grid_for: --spacing gives exactly that spacing (probes half a spacing in from the
    scene bounds), and a grid over the probe limit is refused before any integer overflows."""
    from probegrid.bake.placement import MAX_PROBES, grid_for
    from probegrid.scene import box_scene

    scene = box_scene((-2, 0, -2), (2, 3, 2), albedo=0.5, emission=0.0, inward=True)
    for spacing, counts in (("1.5", (2, 2, 2)), ("0.7", (5, 4, 5)), ("0.5,1,0.5", (8, 3, 8))):
        g = grid_for(scene, spacing=spacing)
        step = [float(x) for x in spacing.split(",")] * (3 if "," not in spacing else 1)
        assert g.counts == counts
        np.testing.assert_allclose(g.spacing, step, rtol=1e-12)
        np.testing.assert_array_less(np.array(scene.bounds[0]) + np.array(step) / 2 - 1e-9,
                                     g.bounds_min)
    for kwargs in ({"spacing": "1e-300"}, {"spacing": "1e-6"},
                   {"grid": "4294967296x4294967296x1"}, {"grid": "1000x1000x11"}):
        with pytest.raises(ValueError, match=f"too large \\(at most {MAX_PROBES:,}\\)"):
            grid_for(scene, **kwargs)
