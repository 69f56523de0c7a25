"""The environment sampled as a light at surface points (probegrid.bake.environment):
unbiased against the exact irradiance of the piecewise-constant environment, rotation
included, and shadowed by the scene."""

from __future__ import annotations

import numpy as np
import pytest

from probegrid.bake.environment import Environment, EnvironmentLight
from probegrid.core.cubemap import texel_directions, texel_solid_angles
from probegrid.core.sh import rotation_y
from probegrid.raytrace import RayTracer


def _tracer(*quads):
    """A tracer over quads given as (corner, edge_u, edge_v)."""
    verts, tris = [], []
    for c, eu, ev in quads:
        c, eu, ev = (np.asarray(x, float) for x in (c, eu, ev))
        k = len(verts)
        verts += [c, c + eu, c + eu + ev, c + ev]
        tris += [(k, k + 1, k + 2), (k, k + 2, k + 3)]
    return RayTracer(np.array(verts), np.array(tris))


def _exact(env: Environment, size: int, normal) -> np.ndarray:
    """Irradiance of the environment's ``size`` cube (piecewise constant) at ``normal``,
    integrated on a 16x finer grid."""
    light = EnvironmentLight(env, size)
    fine = 16 * size
    d = texel_directions(fine).reshape(-1, 3) @ rotation_y(env.rotation).T
    idx = np.arange(6 * fine * fine)
    face, rest = np.divmod(idx, fine * fine)
    row, col = np.divmod(rest, fine)
    coarse = (face * size + row // 16) * size + col // 16
    w = texel_solid_angles(fine).reshape(-1) * np.maximum(d @ np.asarray(normal, float), 0)
    return (light.radiance[coarse] * w[:, None]).sum(axis=0)


@pytest.mark.parametrize("normal", [(0, 1, 0), (0.6, 0, -0.8), (-1, 0, 0), (0, -1, 0)])
def test_sampled_irradiance_is_unbiased(normal):
    rng = np.random.default_rng(3)
    faces = rng.gamma(0.7, 1.0, (6, 8, 8, 3)).astype(np.float32)
    faces[2, 3, 4] = 300.0  # a sun
    env = Environment(faces=faces, rotation=0.7, intensity=1.5)
    light = EnvironmentLight(env, 8)
    tracer = _tracer(((100, 100, 100), (0, 0, 1), (0, 1, 0)))  # far away: nothing occludes
    k = 200_000
    e, rays = light.irradiance(np.zeros((1, 3)), np.array([normal], float),
                               rng.random((1, k, 3)), tracer, 1e-4)
    exact = _exact(env, 8, normal)
    np.testing.assert_allclose(e[0], exact, rtol=0.015)
    assert 0 < rays <= k


@pytest.mark.parametrize("normal", [(0, 1, 0), (0.6, 0, -0.8), (0, -1, 0)])
def test_folded_samples_cover_the_hemisphere_once(normal):
    """Draws below the horizon are mirrored above it (sample_above): every sample lies above,
    and its density p(w) + p(mirror) integrates to 1 over the hemisphere, i.e. the mean of
    1 / density over the samples is the hemisphere's 2 pi (a sky with a sun, rotated)."""
    rng = np.random.default_rng(8)
    faces = rng.gamma(0.7, 1.0, (6, 8, 8, 3)).astype(np.float32) + 0.05
    faces[2, 3, 4] = 300.0
    light = EnvironmentLight(Environment(faces=faces, rotation=0.7), 8)
    k = 1_000_000
    n = np.array([normal], float) / np.linalg.norm(normal)
    d, _, pdf = light.sample_above(rng.random((1, k, 3)), n)
    assert np.all(d[0] @ n[0] >= 0) and np.all(pdf > 0)
    # (1 / density is heavy-tailed where the sun makes the rest rare: 2 %; without the
    # mirror's term the mean is 2.5-5x too high here)
    np.testing.assert_allclose(np.mean(1.0 / pdf), 2 * np.pi, rtol=0.02)


def test_sampled_irradiance_is_shadowed():
    """Under a roof the sky above is blocked: only the sky below the roof's edge lights a
    point facing up; a constant sky above a point facing up gives E = pi L."""
    env = Environment(color=(1.0, 2.0, 0.5))
    light = EnvironmentLight(env)
    rng = np.random.default_rng(5)
    open_sky = _tracer(((100, 100, 100), (0, 0, 1), (0, 1, 0)))
    e, _ = light.irradiance(np.zeros((1, 3)), np.array([[0.0, 1.0, 0.0]]),
                            rng.random((1, 100_000, 3)), open_sky, 1e-4)
    np.testing.assert_allclose(e[0], np.pi * np.array([1.0, 2.0, 0.5]), rtol=0.01)
    roof = _tracer(((-1e3, 1, -1e3), (0, 0, 2e3), (2e3, 0, 0)))  # an endless roof at y = 1
    e, _ = light.irradiance(np.zeros((1, 3)), np.array([[0.0, 1.0, 0.0]]),
                            rng.random((1, 1000, 3)), roof, 1e-4)
    assert e.max() == 0.0


def test_a_black_environment_casts_no_ray():
    light = EnvironmentLight(Environment())
    assert light.is_black
    e, rays = light.irradiance(np.zeros((2, 3)), np.array([[0, 1.0, 0]] * 2),
                               np.zeros((2, 4, 3)), _tracer(((0, 5, 0), (1, 0, 0), (0, 0, 1))),
                               1e-4)
    assert rays == 0 and not e.any()


def test_samples_see_what_the_probes_rays_see():
    """A sample at a texel's centre carries the radiance the bake's misses look up in that world
    direction (the same rotation and intensity)."""
    rng = np.random.default_rng(8)
    faces = rng.gamma(0.7, 1.0, (6, 8, 8, 3)).astype(np.float32)
    env = Environment(faces=faces, rotation=-1.1, intensity=0.5)
    light = EnvironmentLight(env, 8)
    r = np.column_stack([rng.random(500), np.full(500, 0.5), np.full(500, 0.5)])
    d, rad, pdf = light.sample(r)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(rad, env.sampler(8).radiance(d), rtol=1e-4)
    assert np.all(pdf > 0)
