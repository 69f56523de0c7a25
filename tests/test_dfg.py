"""Tests of probegrid.core.dfg: the split-sum DFG table and its lookup."""

from __future__ import annotations

import numpy as np
import pytest

from probegrid.core import lobes
from probegrid.core.dfg import dfg_lookup, dfg_lut, smith_ggx_correlated_visibility


@pytest.fixture(scope="module")
def lut32() -> np.ndarray:
    return dfg_lut(32)


def _brute_force(n_dot_v: float, roughness: float, n: int = 1500) -> tuple[float, float]:
    """(A, B) by an independent midpoint double integral over the *light* direction.

    ``A = integral D V (1 - Fc) (n.l) dl`` over the upper hemisphere, in spherical coordinates
    of ``l`` about ``n`` (the table integrates over the half vector instead), with the GGX NDF
    of probegrid.core.lobes and the visibility written out here.
    """
    alpha = roughness**2
    v = np.array([np.sqrt(1.0 - n_dot_v**2), 0.0, n_dot_v])
    # theta_l: cluster points near the mirror direction with a sinh grading (sharp lobes)
    t = (np.arange(n) + 0.5) / n
    mirror = np.arccos(n_dot_v)
    scale = max(alpha, 1e-3)
    lo, hi = np.arcsinh(-mirror / scale), np.arcsinh((0.5 * np.pi - mirror) / scale)
    s = lo + (hi - lo) * t
    th = mirror + scale * np.sinh(s)
    dth = scale * np.cosh(s) * (hi - lo) / n
    ph = (np.arange(2 * n) + 0.5) / (2 * n) * np.pi          # [0, pi], doubled by symmetry
    dph = np.pi / (2 * n)
    th_, ph_ = np.meshgrid(th, ph, indexing="ij")
    l = np.stack([np.sin(th_) * np.cos(ph_), np.sin(th_) * np.sin(ph_), np.cos(th_)], -1)
    h = l + v
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    nl = l[..., 2]
    nh = h[..., 2]
    vh = np.clip(h @ v, 0.0, 1.0)
    a2 = alpha * alpha
    vis = 0.5 / (n_dot_v * np.sqrt(nl * nl * (1 - a2) + a2) + nl * np.sqrt(n_dot_v**2 * (1 - a2) + a2))
    f = lobes.ggx_ndf(nh, alpha) * vis * nl
    fc = (1.0 - vh) ** 5
    w = 2.0 * np.sin(th_) * dth[:, None] * dph
    return float(np.sum(f * (1 - fc) * w)), float(np.sum(f * fc * w))


def test_shape_dtype_orientation(lut32: np.ndarray) -> None:
    assert lut32.shape == (32, 32, 2) and lut32.dtype == np.float32
    # row 0 is the smoothest: near-mirror BRDF, A + B ~ 1 away from grazing
    assert lut32[0, 16:].sum(-1).min() > 0.99
    # the rough end loses energy (single-scattering GGX): A + B falls with roughness
    assert lut32[-1, -1].sum() < lut32[0, -1].sum() - 0.2


def test_smooth_normal_incidence_limit(lut32: np.ndarray) -> None:
    """N.V -> 1, r -> 0: A + B -> 1 and B -> (1 - N.V)^5 -> 0."""
    a, b = lut32[0, -1]
    assert abs(a + b - 1.0) < 1e-3
    assert b < 1e-6


def test_smooth_row_is_schlick(lut32: np.ndarray) -> None:
    """At r = 1/64 (alpha = 2.4e-4) the BRDF is a mirror: B = Fc(n.v), A = 1 - Fc(n.v)."""
    nv = (np.arange(32) + 0.5) / 32
    fc = (1.0 - nv) ** 5
    a, b = lut32[0, 4:, 0], lut32[0, 4:, 1]  # grazing columns see masking even when smooth
    np.testing.assert_allclose(b, fc[4:], atol=5e-5)  # measured 6e-6
    np.testing.assert_allclose(a, 1.0 - fc[4:], atol=5e-5)


def test_furnace_energy_bounded(lut32: np.ndarray) -> None:
    """White furnace: F0 = 1 gives the directional albedo A + B, which cannot exceed 1."""
    assert np.all(lut32 >= 0.0)
    assert np.all(lut32.sum(-1) <= 1.0 + 1e-4)


@pytest.mark.parametrize("row, col", [(5, 20), (12, 3), (20, 28), (31, 10), (8, 31)])
def test_entries_match_independent_double_integral(lut32: np.ndarray, row: int, col: int) -> None:
    r = (row + 0.5) / 32
    nv = (col + 0.5) / 32
    a, b = _brute_force(nv, r)
    np.testing.assert_allclose(lut32[row, col], [a, b], atol=1e-5)  # measured < 5e-7


def test_quadrature_is_converged() -> None:
    """The default rule against 2.5 x as many nodes per dimension: < 1e-4 everywhere."""
    a = dfg_lut(16)
    b = dfg_lut(16, samples=160)
    assert np.max(np.abs(a - b)) < 1e-4


def test_visibility_formula() -> None:
    # alpha = 1: V = 0.5 / (nv + nl) (both square roots are 1)
    np.testing.assert_allclose(smith_ggx_correlated_visibility(0.3, 0.6, 1.0), 0.5 / 0.9)
    # alpha -> 0: V -> 1 / (4 nl nv) (no masking)
    np.testing.assert_allclose(smith_ggx_correlated_visibility(0.5, 0.8, 1e-8), 1 / 1.6,
                               rtol=1e-6)
    assert smith_ggx_correlated_visibility(0.0, 0.0, 0.5) == 0.0


def test_lookup_centres_midpoints_and_clamping(lut32: np.ndarray) -> None:
    c = (np.arange(32) + 0.5) / 32
    np.testing.assert_allclose(dfg_lookup(lut32, c[7], c[9]), lut32[9, 7], rtol=1e-6)
    mid = dfg_lookup(lut32, 0.5 * (c[7] + c[8]), c[9])
    np.testing.assert_allclose(mid, 0.5 * (lut32[9, 7] + lut32[9, 8]), rtol=1e-6)
    np.testing.assert_allclose(dfg_lookup(lut32, 2.0, -1.0), lut32[0, -1])
    out = dfg_lookup(lut32, np.full((4, 1), 0.5), np.linspace(0, 1, 5))
    assert out.shape == (4, 5, 2) and out.dtype == np.float32


def test_bad_arguments(lut32: np.ndarray) -> None:
    with pytest.raises(ValueError, match="size"):
        dfg_lut(0)
    with pytest.raises(ValueError, match="samples"):
        dfg_lut(8, samples=2)
    with pytest.raises(ValueError, match="shape"):
        dfg_lookup(lut32[..., :1], 0.5, 0.5)
    with pytest.raises(ValueError, match="finite"):
        dfg_lookup(lut32, np.nan, 0.5)
