"""Per-probe SH deringing (probegrid.core.sh.dering): non-negative irradiance everywhere, raw SH
kept where it already was, the gentlest window on the path, and the exact minimum."""

from __future__ import annotations

import numpy as np
import pytest

from probegrid.core import sh
from probegrid.core.sh.dering import DEFAULT_MARGIN, dering, irradiance_minimum, window_path


def _fibonacci(n: int) -> np.ndarray:
    k = np.arange(n) + 0.5
    y = 1 - 2 * k / n
    r = np.sqrt(1 - y * y)
    phi = k * np.pi * (3 - np.sqrt(5))
    return np.column_stack([r * np.cos(phi), y, r * np.sin(phi)])


#: A dense sphere sampling, independent of the module's (which uses none).
DENSE = _fibonacci(20000)
DENSE_BASIS = sh.sh_basis(DENSE) * sh.A_HAT  # irradiance of each radiance coefficient


def _dense_min(coeffs: np.ndarray) -> np.ndarray:
    """Minimum of the irradiance over DENSE of ``coeffs (P, 9, C)``; ``(P, C)``."""
    p, _, c = coeffs.shape
    flat = np.moveaxis(coeffs, 1, 0).reshape(9, -1)
    return (DENSE_BASIS @ flat).min(axis=0).reshape(p, c)


def _probes(n: int, seed: int) -> np.ndarray:
    """Radiance SH of probes lit by a few coloured directional lights and some ambient: many
    ring (negative irradiance behind a bright light), some do not."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    y = sh.sh_basis(d.reshape(-1, 3)).reshape(n, 3, 9)
    power = rng.exponential(size=(n, 3, 3)) * (rng.random((n, 3, 1)) < 0.7)
    coeffs = np.einsum("pkc,pki->pic", power, y)
    coeffs[:, 0] += rng.random((n, 3)) * 0.3 * 2 * np.sqrt(np.pi)
    return coeffs


def test_deringed_irradiance_is_non_negative_and_non_ringing_probes_are_kept():
    raw = _probes(200, 1)
    raw_min = _dense_min(raw)
    ringing = np.any(raw_min < 0, axis=1)
    certified_ok = np.all(irradiance_minimum(np.moveaxis(raw, 1, 2)) >= 0, axis=1)
    assert 30 < ringing.sum() < 170  # both kinds are there
    out, window, minimum = dering(raw)
    assert np.all(_dense_min(out) >= 0)
    assert np.all(_dense_min(out.astype(np.float32).astype(np.float64)) >= 0)  # as stored
    np.testing.assert_array_equal(out[certified_ok], raw[certified_ok])  # bit for bit
    np.testing.assert_array_equal(window[certified_ok], 1.0)
    assert np.all(window[ringing, 2] < 1)  # (h_1 stays 1 where band 1 alone is >= 0)
    # a low-pass: h_0 = 1 >= h_1 >= h_2 >= 0, the coefficients are h_l L_lm
    assert np.all(window[:, 0] == 1) and np.all(window[:, 2] <= window[:, 1])
    assert np.all(window >= 0)
    np.testing.assert_array_equal(out, raw * window[:, sh.BAND_OF][:, :, None])
    # the certified minimum is a lower bound of the dense one, and tight
    dense = _dense_min(out)
    assert np.all(minimum <= dense + 1e-12)
    np.testing.assert_allclose(minimum, dense, atol=2e-3 * raw[:, 0].max())


def test_the_window_is_the_gentlest_on_the_path():
    raw = _probes(60, 2)
    _out, window, _ = dering(raw)
    fixed = np.flatnonzero(window[:, 1] < 1)
    assert fixed.size > 10
    c = np.pi * sh.K0 * raw[:, 0]  # (P, C) irradiance of band 0
    for p in fixed:
        # the path of this probe: (1, 1 - t (1 - a), 1 - t); a slightly gentler window fails
        t = 1 - window[p, 2]
        a = 1 - (1 - window[p, 1]) / t
        gentler = window_path(t - 1e-7, a)
        cand = raw[p] * gentler[sh.BAND_OF][:, None]
        newton, _ = sh.min_over_sphere(sh.irradiance_coefficients(cand))  # independent
        assert np.any(newton < DEFAULT_MARGIN * c[p])


def test_one_directional_light_matches_a_brute_force_search():
    """A delta light along +Z, whose irradiance dips to -19/480 (probegrid.core.sh): the
    window found equals a fine scan of the path with the analytic minimum over the sphere."""
    raw = sh.sh_basis(np.array([[0.0, 0.0, 1.0]]))[0][None, :, None]  # (1, 9, 1)
    assert _dense_min(raw)[0, 0] < 0
    _out, window, _ = dering(raw)
    # L_00 = K0, L_10 = K1, L_20 = Y_20(+Z) = 2 K3: E = A_l L_l0 Y_l0
    c0, b1, g2 = np.pi * sh.K0**2, 2 * np.pi / 3 * sh.K1**2, np.pi / 4 * 2 * sh.K3**2
    assert (c0, b1, g2) == pytest.approx((1 / 4, 1 / 2, 5 / 32), rel=1e-15)
    a = (1 - 2 * DEFAULT_MARGIN) * c0 / b1
    ts = np.linspace(0, 1, 1000001)
    h1, h2 = 1 - ts * (1 - a), 1 - ts
    # E(z) = c0 + b1 h1 z + g2 h2 (3 z^2 - 1), z = cos(theta) in [-1, 1] (zonal about +Z): a
    # parabola in z, its minimum at the vertex or an end
    def e(z):
        return c0 + b1 * h1 * z + g2 * h2 * (3 * z * z - 1)

    with np.errstate(divide="ignore", invalid="ignore"):
        vertex = np.clip(-b1 * h1 / (6 * g2 * h2), -1, 1)
    emin = np.minimum(np.minimum(e(-1.0), e(1.0)), np.where(h2 > 0, e(vertex), np.inf))
    feasible = emin >= DEFAULT_MARGIN * c0
    t_star = ts[np.argmax(feasible)]
    assert emin[0] == pytest.approx(-19 / 480, rel=1e-12)  # the known ringing
    assert not feasible[0] and feasible[-1]
    assert window[0, 2] == pytest.approx(1 - t_star, abs=2e-6)
    assert window[0, 1] == pytest.approx(1 - t_star * (1 - a), abs=2e-6)


def test_exact_minimum_matches_newton_refinement():
    raw = _probes(100, 3)
    mine = irradiance_minimum(np.moveaxis(raw, 1, 2))  # (P, C)
    ref, _ = sh.min_over_sphere(sh.irradiance_coefficients(np.moveaxis(raw, 0, 1)))
    assert np.all(mine <= ref + 1e-12)
    np.testing.assert_allclose(mine, ref, rtol=0, atol=1e-12 * np.abs(raw).max())


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="shape"):
        dering(np.zeros((4, 8, 3)))
    with pytest.raises(ValueError, match="nan"):
        dering(np.full((1, 9, 3), np.nan))
    with pytest.raises(ValueError, match="margin"):
        dering(np.zeros((1, 9, 3)), margin=0.7)
    black = np.zeros((2, 9, 3))
    out, window, minimum = dering(black)
    assert np.all(out == 0) and np.all(window == 1) and np.all(minimum == 0)
