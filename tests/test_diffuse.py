"""Tests of probegrid.core.diffuse: exact clamped-cosine filter and band-2 SH diffuse maps."""

from __future__ import annotations

import numpy as np
import pytest

from probegrid.core import sh
from probegrid.core.cubemap import texel_directions, texel_solid_angles
from probegrid.core.diffuse import diffuse_exact, diffuse_sh
from probegrid.core.layouts import to_cube


def _integral(cube: np.ndarray) -> np.ndarray:
    n = cube.shape[1]
    return np.einsum("fijc,fij->c", cube.astype(np.float64), texel_solid_angles(n))


def _rel(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    return np.abs(x - ref) / np.abs(ref)


@pytest.fixture(scope="module")
def hdr64(venice_latlong: np.ndarray, studio_latlong: np.ndarray) -> dict[str, np.ndarray]:
    return {"venice": to_cube(venice_latlong, "equirect", 64),
            "studio": to_cube(studio_latlong, "equirect", 64)}


@pytest.fixture(scope="module")
def exact32(hdr64: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: diffuse_exact(v, 32) for k, v in hdr64.items()}


def test_constant_environment() -> None:
    """Constant in, constant out: exact up to the midpoint rule of the input grid (the kink of
    the clamped cosine at the horizon): measured 2.0e-4 at n = 16, 5.0e-5 at 32, 1.3e-5 at 64."""
    value = np.array([0.5, 2.0, 7.0], dtype=np.float32)
    cube = np.broadcast_to(value, (6, 32, 32, 3)).copy()
    np.testing.assert_allclose(diffuse_exact(cube, 8), np.broadcast_to(value, (6, 8, 8, 3)),
                               rtol=1e-4)
    small = np.broadcast_to(value, (6, 16, 16, 3))
    np.testing.assert_allclose(diffuse_exact(small, 8), np.broadcast_to(value, (6, 8, 8, 3)),
                               rtol=3e-4)
    out, info = diffuse_sh(cube, 8)
    np.testing.assert_allclose(out, np.broadcast_to(value, out.shape), rtol=1e-5)
    assert not info.negative
    np.testing.assert_allclose(info.minimum, value, rtol=1e-5)


def test_one_bright_texel_is_its_clamped_cosine_lobe() -> None:
    cube = np.zeros((6, 16, 16, 1), dtype=np.float32)
    cube[2, 5, 9] = 100.0
    out = diffuse_exact(cube, 8)
    w = texel_directions(16)[2, 5, 9]
    omega = texel_solid_angles(16)[2, 5, 9]
    expect = 100.0 * omega * np.maximum(texel_directions(8) @ w, 0.0) / np.pi
    np.testing.assert_allclose(out[..., 0], expect, rtol=1e-6, atol=1e-9)


def test_energy_and_sh_consistency(hdr64: dict[str, np.ndarray],
                                   exact32: dict[str, np.ndarray]) -> None:
    """The clamped cosine / pi integrates to 1 over normals, so the diffuse map keeps the
    environment's solid-angle integral; and its band-0-2 SH coefficients are the Funk-Hecke
    products (A_l / pi) L_lm of the input's (an independent check of the exact sum)."""
    for name, cube in hdr64.items():
        ex = exact32[name]
        np.testing.assert_allclose(_integral(ex), _integral(cube), rtol=2e-4)
        expect = sh.irradiance_coefficients(sh.project_cube(cube)) / np.pi
        got = sh.project_cube(ex)
        assert np.max(np.abs(got - expect)) < 2e-4 * np.max(np.abs(expect)), name


def test_source_size_option_error(hdr64: dict[str, np.ndarray],
                                  exact32: dict[str, np.ndarray]) -> None:
    """Pre-filtering the 64^2 input to 32^2 before the sum (first-order loss of where a bright
    texel sits inside its coarse texel): measured mean 4e-4 / 1.1e-3, max 1.0 % / 13 %
    (venice / studio, whose tiny bright softboxes are the worst case)."""
    worst = {}
    for name, cube in hdr64.items():
        e = _rel(diffuse_exact(cube, 32, source_size=32), exact32[name])
        worst[name] = (float(e.mean()), float(e.max()))
    assert worst["venice"][0] < 1e-3 and worst["venice"][1] < 0.02, worst
    assert worst["studio"][0] < 3e-3 and worst["studio"][1] < 0.2, worst


def test_sh_versus_exact_on_real_hdrs(hdr64: dict[str, np.ndarray],
                                      exact32: dict[str, np.ndarray]) -> None:
    """Band-2 SH against the exact sum: the numbers the module documents.

    venice (strong sun): mean 1.9 %, max 20 % (the sun's clamped-cosine terminator, which
    band 2 cannot represent: R&H's 9.4 %-of-peak error is large relative to the dim side).
    studio (softboxes in a dark room): the raw projection rings below zero (reported), and
    the relative error is huge where the exact irradiance is small (mean 27 %, max ~7x);
    the auto window makes it non-negative.
    """
    v_sh, v_info = diffuse_sh(hdr64["venice"], 32)
    e = _rel(v_sh, exact32["venice"])
    assert e.mean() < 0.025 and e.max() < 0.25, (e.mean(), e.max())
    assert not v_info.negative

    s_sh, s_info = diffuse_sh(hdr64["studio"], 32)
    assert s_info.negative and np.all(s_info.minimum < 0)
    assert np.all(np.isfinite(s_info.minimum_direction))
    # the reported minimum is below every texel's value (it is over the whole sphere)
    assert np.all(s_info.minimum <= s_sh.reshape(-1, 3).min(axis=0) + 1e-6)
    s_auto, a_info = diffuse_sh(hdr64["studio"], 32, window="auto")
    assert not a_info.negative and a_info.window == "hanning" and np.isfinite(a_info.width)
    assert s_auto.min() >= -1e-6
    e = _rel(s_sh, exact32["studio"])
    assert e.mean() > 0.1  # documents that the target below is far away for this scene


@pytest.mark.xfail(strict=True, reason="band-2 SH cannot reach 1 % mean / 3 % max relative "
                   "error on these HDRs (measured: venice 1.9 % / 20 %, studio 27 % / 690 %)")
def test_sh_meets_target(hdr64: dict[str, np.ndarray], exact32: dict[str, np.ndarray]) -> None:
    for name, cube in hdr64.items():
        out, _ = diffuse_sh(cube, 32)
        e = _rel(out, exact32[name])
        assert e.mean() <= 0.01 and e.max() <= 0.03, name


@pytest.mark.parametrize("window, width", [("hanning", 3.0), ("lanczos", 4.0), ("gauss", 2.0)])
def test_windows_are_applied_and_reported(window: str, width: float) -> None:
    cube = np.random.default_rng(0).random((6, 8, 8, 2)).astype(np.float32) + 0.5
    out, info = diffuse_sh(cube, 4, window=window, width=width)  # type: ignore[arg-type]
    np.testing.assert_allclose(info.coefficients, sh.window(info.projected, kind=window,
                                                            width=width))
    assert info.window == window and info.width == width and out.shape == (6, 4, 4, 2)


def test_bad_arguments() -> None:
    cube = np.ones((6, 8, 8, 3), dtype=np.float32)
    with pytest.raises(ValueError, match="window must be one of"):
        diffuse_sh(cube, 4, window="box")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="needs a width"):
        diffuse_sh(cube, 4, window="hanning")
    with pytest.raises(ValueError, match="width must be None"):
        diffuse_sh(cube, 4, width=2.0)
    with pytest.raises(ValueError, match="source_size"):
        diffuse_exact(cube, 4, source_size=3)
    bad = cube.copy()
    bad[1, 2, 3, 0] = np.inf
    with pytest.raises(ValueError, match="finite"):
        diffuse_exact(bad, 4)
    with pytest.raises(ValueError, match="finite"):
        diffuse_sh(bad, 4)
