"""Tests of probegrid.core.probefilter: the cached-matrix diffuse map and GGX chain of probe cubes."""

from __future__ import annotations

import numpy as np
import pytest

from probegrid.core import lobes, probefilter
from probegrid.core.cubemap import texel_directions
from probegrid.core.diffuse import diffuse_exact
from probegrid.core.layouts import to_cube
from probegrid.core.specular import ggx_prefilter


def _mean_cosine_ggx(alpha: float) -> float:
    """E[R . w] under the normalised GGX prefilter lobe (1-D quadrature; cf. test_specular)."""
    t_max = np.arctan(1.0 / alpha)
    t = (np.arange(200_000) + 0.5) * (t_max / 200_000)
    th = 2.0 * np.arctan(alpha * np.tan(t))
    dth = 2.0 * alpha / np.cos(t) ** 2 / (1.0 + (alpha * np.tan(t)) ** 2) * (t_max / 200_000)
    wt = dth * np.sin(th)
    k = lobes.ggx_kernel(np.cos(th), alpha)
    return float(np.sum(k * np.cos(th) * wt) / np.sum(k * wt))


@pytest.fixture(scope="module")
def venice16(venice_latlong: np.ndarray) -> np.ndarray:
    return to_cube(venice_latlong, "equirect", 16)


def test_matches_diffuse_exact_and_the_ggx_reference(venice16: np.ndarray) -> None:
    """Both outputs are the exact sums: diffuse_exact and ggx_prefilter(method="exact")."""
    dif, chain = probefilter.filter_cube(venice16, 4, 5)
    np.testing.assert_allclose(dif, diffuse_exact(venice16, 4), rtol=2e-6)
    ref = ggx_prefilter(venice16, levels=5, method="exact")
    assert [a.shape for a in chain] == [a.shape for a in ref]
    assert np.array_equal(chain[0], venice16)
    for k in range(1, 5):
        np.testing.assert_allclose(chain[k], ref[k], rtol=1e-5)


def test_linear_environment_matches_analytic_results() -> None:
    """L = 1 + b . w: the diffuse map is 1 + (2/3) b . n (the clamped cosine's first moment,
    up to the 32^2 midpoint rule at the horizon) and GGX level k is 1 + E[cos] b . R."""
    b = np.array([[0.3, -0.2, 0.25], [0.0, 0.4, 0.0], [-0.1, 0.1, 0.3]])
    n = 32
    cube = (1.0 + np.einsum("fijd,cd->fijc", texel_directions(n), b)).astype(np.float32)
    dif, chain = probefilter.filter_cube(cube, 8, 6)
    expect = 1.0 + (2.0 / 3.0) * np.einsum("fijd,cd->fijc", texel_directions(8), b)
    np.testing.assert_allclose(dif, expect, rtol=2e-4)
    for k in range(1, 6):
        mu = _mean_cosine_ggx(lobes.roughness_to_alpha(lobes.level_roughness(k, 6)))
        expect = 1.0 + mu * np.einsum("fijd,cd->fijc", texel_directions(n >> k), b)
        np.testing.assert_allclose(chain[k], expect, rtol=2e-3 if k == 1 else 5e-4)


def test_constant_cube_stays_constant() -> None:
    value = np.array([0.5, 2.0, 7.0], np.float32)
    cube = np.broadcast_to(value, (6, 32, 32, 3)).copy()
    dif, chain = probefilter.filter_cube(cube, 8, 6)
    np.testing.assert_allclose(dif, np.broadcast_to(value, dif.shape), rtol=1e-4)  # horizon
    for level in chain:
        np.testing.assert_allclose(level, np.broadcast_to(value, level.shape), rtol=4e-6)


def test_channels_are_independent_probes(venice16: np.ndarray) -> None:
    """Probes side by side as channels filter as they do alone."""
    other = venice16[..., ::-1] * 0.5
    dif, chain = probefilter.filter_cube(np.concatenate([venice16, other], axis=3), 8, 5)
    d1, c1 = probefilter.filter_cube(venice16, 8, 5)
    d2, c2 = probefilter.filter_cube(other, 8, 5)
    np.testing.assert_allclose(dif, np.concatenate([d1, d2], axis=3), rtol=1e-6)
    for k in range(5):
        np.testing.assert_allclose(chain[k], np.concatenate([c1[k], c2[k]], axis=3), rtol=1e-6)


def test_matrix_is_cached_read_only_and_sized() -> None:
    m, sizes = probefilter.filter_matrix(16, 4, 5)
    assert m is probefilter.filter_matrix(16, 4, 5)[0]
    assert not m.flags.writeable and m.dtype == np.float32
    assert sizes == (4, 8, 4, 2, 1)
    assert m.shape == (16 + 64 + 16 + 4 + 1, 6 * 16 * 16)  # face 0's rows
    ggx = m[16:]
    np.testing.assert_allclose(ggx.sum(axis=1, dtype=np.float64), 1.0, rtol=1e-6)
    assert np.all(m >= 0)


def test_every_face_is_face_zero_after_its_symmetry() -> None:
    """The six faces come from face 0's rows through the cube's symmetries: a cube that is
    bright only in one texel lights each face's outputs as a direct sum over the texels would,
    for every face (the diffuse rows straight from their definition)."""
    n = 8
    w = texel_directions(n).reshape(-1, 3)
    from probegrid.core.cubemap import texel_solid_angles
    om = texel_solid_angles(n).reshape(-1)
    rng = np.random.default_rng(3)
    cube = rng.random((6, n, n, 2)).astype(np.float32)
    dif, _ = probefilter.filter_cube(cube, 4, 4)
    d = texel_directions(4).reshape(-1, 3)
    direct = (np.maximum(d @ w.T, 0.0) * om / np.pi) @ cube.reshape(-1, 2).astype(np.float64)
    np.testing.assert_allclose(dif.reshape(-1, 2), direct, rtol=1e-5)


def test_limits_and_bad_input() -> None:
    assert probefilter.supported(32, 8) and not probefilter.supported(64, 8)
    assert "cached" in probefilter.describe(32, 8)["specular"]
    assert "tiered" in probefilter.describe(64, 8)["specular"]
    with pytest.raises(ValueError, match="up to 32"):
        probefilter.filter_matrix(64, 8, 7)
    bad = np.ones((6, 8, 8, 3), np.float32)
    bad[2, 3, 3, 1] = np.nan
    with pytest.raises(ValueError, match="finite"):
        probefilter.filter_cube(bad, 4, 4)
