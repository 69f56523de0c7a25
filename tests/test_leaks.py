"""Light through walls by the grid reads, and emitters of many triangles: physics on small cases.

* A hit reads only the probes it sees (:func:`probegrid.bake.records.replay.hidden_corners`):
  a probe beyond a wall gets weight 0 whatever its distance moments say, and a bake's inside
  probe is unchanged by probes added outside a sunlit wall (to 1 %).
* An icosphere of thousands of emitting triangles (over the exact integral's edge limit) lights
  a point as the analytic sphere does, ``E = pi L (r / d)^2 cos``, within 2 %, for any seed
  (:meth:`probegrid.bake.emitters.Emitters.irradiance` by clusters).
"""

from __future__ import annotations

import numpy as np
import pytest

from probegrid.bake.emitters import MAX_ANALYTIC, Emitters, emitter_clusters
from probegrid.bake.records.replay import GridData, _level_weights, hidden_corners
from probegrid.bake.records.schema import Level
from probegrid.core.grid import GridSpec
from probegrid.raytrace import RayTracer
from probegrid.scene import Material
from probegrid.scene.builders import SceneBuilder


def _wall_scene():
    """A 0.2 m thick wall slab in the plane x = 0 (from y = -5 to 5, z = -5 to 5)."""
    b = SceneBuilder()
    m = b.add_material(Material.diffuse(0.5))
    b.add_box((-0.1, -5.0, -5.0), (0.1, 5.0, 5.0), material=m)
    return b.build(name="wall")


def _hits_on_wall(k: int = 5) -> Level:
    """``k`` front hits on the wall's face x = -0.1, facing -x (the probe at x = -1's side)."""
    pos = np.column_stack([np.full(k, -0.1), np.linspace(-0.4, 0.4, k), np.zeros(k)])
    nrm = np.tile(np.array([[-1.0, 0.0, 0.0]], np.float32), (k, 1))
    return Level(kind=np.ones(k, np.uint8), position=pos, normal=nrm)


def _data(tracer: RayTracer | None, moments: np.ndarray | None = None) -> GridData:
    """Two probes at x = -1 (in front of the wall's face) and x = +1 (behind the wall)."""
    grid = GridSpec(bounds_min=(-1.0, 0.0, 0.0), bounds_max=(1.0, 0.0, 0.0), counts=(2, 1, 1))
    if moments is None:
        mom, n = np.zeros((0, 2), np.float32), 0
    else:
        mom, n = moments, 2
    return GridData(grid, np.ones(2, bool), grid.positions(), mom, n, None, tracer)


def test_probe_behind_a_wall_gets_no_weight() -> None:
    scene = _wall_scene()
    tracer = RayTracer.from_scene(scene)
    level = _hits_on_wall()
    # without visibility (no moments) the probe behind the wall takes a share: the leak
    idx, w = _level_weights(level, _data(None))
    behind = np.where(idx == 1, w, 0.0).sum(axis=1)
    assert (behind > 0.05).all()
    # moments that wrongly say "nothing before 10 m" toward every direction (a coarse texel
    # straddling the wall's edge): the Chebyshev test passes the probe behind the wall
    m = 2
    mom = np.zeros((2 * 6 * (m + 2) ** 2, 2), np.float32)
    mom[:, 0], mom[:, 1] = 10.0, 100.0
    idx, w = _level_weights(level, _data(None, mom))
    assert (np.where(idx == 1, w, 0.0).sum(axis=1) > 0.05).all()
    # the exact test: the probe behind the wall carries nothing, the one in front everything
    idx, w = _level_weights(level, _data(tracer, mom))
    np.testing.assert_array_equal(np.where(idx == 1, w, 0.0).sum(axis=1), 0.0)
    np.testing.assert_allclose(np.where(idx == 0, w, 0.0).sum(axis=1), 1.0, rtol=1e-6)


def test_hidden_corners_traces_only_weighted_valid_probes() -> None:
    tracer = RayTracer.from_scene(_wall_scene())
    level = _hits_on_wall(3)
    grid = GridSpec(bounds_min=(-1.0, 0.0, 0.0), bounds_max=(1.0, 0.0, 0.0), counts=(2, 1, 1))
    rows = np.array([0, 2])
    hid = hidden_corners(level.position, level.normal, rows, grid, np.ones(2, bool),
                         grid.positions(), 0.1, tracer)
    idx, tri, _ = grid.corners(level.position)
    assert hid.shape == (3, 8)
    # behind the wall: hidden (corners of no trilinear weight are not traced)
    np.testing.assert_array_equal(hid[rows], (idx[rows] == 1) & (tri[rows] > 0))
    assert hid[rows].any(axis=1).all()
    assert not hid[1].any()  # a row not listed
    # an invalid probe is not traced (its weight is 0 anyway)
    hid = hidden_corners(level.position, level.normal, rows, grid, np.array([True, False]),
                         grid.positions(), 0.1, tracer)
    assert not hid.any()


def test_a_point_that_sees_no_probe_keeps_the_moments_weights() -> None:
    tracer = RayTracer.from_scene(_wall_scene())
    # hits on the wall's far face (x = +0.1, facing +x) of a grid whose probes both stand at
    # x < -0.1: both hidden; the weights fall back to the soft estimate (they still sum to 1)
    grid = GridSpec(bounds_min=(-2.0, 0.0, 0.0), bounds_max=(-1.0, 0.0, 0.0), counts=(2, 1, 1))
    level = Level(kind=np.ones(2, np.uint8), position=np.array([[0.1, 0.0, 0.0],
                                                                [0.1, 0.3, 0.0]]),
                  normal=np.tile(np.array([[1.0, 0.0, 0.0]], np.float32), (2, 1)))
    data = GridData(grid, np.ones(2, bool), grid.positions(), np.zeros((0, 2), np.float32), 0,
                    None, tracer)
    _, w = _level_weights(level, data)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-6)


# -------------------------------------------------------------------------- emitters
def _icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """A unit icosphere, outward winding (20 * 4^subdivisions triangles)."""
    t = (1.0 + 5.0 ** 0.5) / 2.0
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
                 dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        tri = v[f]
        mids = (tri + np.roll(tri, -1, axis=1)) / 2.0  # (F, 3, 3): ab, bc, ca
        mids /= np.linalg.norm(mids, axis=2, keepdims=True)
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        ab, bc, ca = mids[:, 0], mids[:, 1], mids[:, 2]
        tri = np.concatenate([np.stack([a, ab, ca], 1), np.stack([b, bc, ab], 1),
                              np.stack([c, ca, bc], 1), np.stack([ab, bc, ca], 1)])
        v, inv = np.unique(tri.reshape(-1, 3).round(12), axis=0, return_inverse=True)
        f = inv.reshape(-1, 3)
    p = v[f]
    nrm = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    inward = np.einsum("ij,ij->i", nrm, p.mean(axis=1)) < 0
    f[inward] = f[inward][:, ::-1]
    return v, f


RADIUS, RADIANCE = 0.25, 3.0


@pytest.fixture(scope="module")
def sphere_light():
    """An emissive icosphere of 5,120 triangles (radius 0.25 m at its corners) over a floor."""
    b = SceneBuilder()
    v, f = _icosphere(4)
    m = b.add_material(Material.diffuse(0.0, emission=np.full(3, RADIANCE)))
    b.add_triangles(v * RADIUS, f, material=m)
    floor = b.add_material(Material.diffuse(0.5))
    b.add_quad((-5.0, -1.0, 5.0), (10.0, 0.0, 0.0), (0.0, 0.0, -10.0), material=floor)
    scene = b.build(name="sphere")
    return Emitters.from_scene(scene), RayTracer.from_scene(scene)


def test_icosphere_is_one_cluster_over_the_exact_limit(sphere_light) -> None:
    em, _ = sphere_light
    assert len(em) == 5120 and not em.analytic
    assert len(em.outlines[0]) > MAX_ANALYTIC
    c = em.clusters
    assert len(c.radius) == 1 and c.spread[0] == -1.0  # normals every way: no cone
    np.testing.assert_allclose(c.radius[0], RADIUS, rtol=1e-9)
    assert "sampled by solid angle over 1 clusters" in em.sampling()


@pytest.mark.parametrize(("distance", "normal"), [(0.4, (1.0, 0.0, 0.0)),
                                                  (1.5, (1.0, 0.0, 0.0)),
                                                  (1.0, (0.6, 0.8, 0.0))])
def test_icosphere_irradiance_is_the_sphere_formula(sphere_light, distance, normal) -> None:
    em, tracer = sphere_light
    k = 400
    pts = np.tile([[-distance, 0.0, 0.0]], (k, 1))
    nrm = np.tile([normal], (k, 1))
    # E = pi L (r / d)^2 cos for a sphere wholly above the horizon (the facets lie inside the
    # sphere through the corners: 0.2 % less at 5,120 triangles)
    exact = np.pi * RADIANCE * (RADIUS / distance) ** 2 * normal[0]
    means = []
    for seed in (0, 1, 2):
        rnd = np.random.default_rng(seed).random((k, 2, 3))
        e, rays = em.irradiance(pts, nrm, rnd, tracer, 1e-6)
        assert rays <= 2 * k
        means.append(e[:, 0].mean() / exact)
        # no spike: every point's own estimate (2 samples) under twice the truth (a ray
        # past the facets' edge near the silhouette gives 0: no lower bound)
        assert (e[:, 0] / exact).max() < 2.0
    np.testing.assert_allclose(means, 1.0, atol=0.02)


def test_clusters_split_a_long_tube_and_keep_compact_pieces() -> None:
    # a thin tube 2 m long (radius 2 cm) along x, and a small sphere: the tube splits into
    # pieces about as long as thick, the sphere stays one cluster
    k = 64
    ang = np.linspace(0, 2 * np.pi, 17)[:-1]
    xs = np.linspace(-1, 1, k + 1)
    ring = np.stack([np.zeros_like(ang), 0.02 * np.cos(ang), 0.02 * np.sin(ang)], 1)
    verts = (ring[None] + xs[:, None, None] * np.array([1.0, 0, 0])).reshape(-1, 3)
    tris = []
    for i in range(k):
        for j in range(16):
            a, b = i * 16 + j, i * 16 + (j + 1) % 16
            tris += [[a, b, b + 16], [a, b + 16, a + 16]]
    tv = verts[np.array(tris)]
    sv, sf = _icosphere(2)
    sv = sv[sf] * 0.1 + np.array([0.0, 2.0, 0.0])
    v = np.concatenate([tv, sv])
    nrm = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    area = 0.5 * np.linalg.norm(nrm, axis=1)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    c = emitter_clusters(v, nrm, area)
    sphere = np.flatnonzero(np.isclose(c.centre[:, 1], 2.0))
    assert len(sphere) == 1 and np.isclose(c.radius[sphere[0]], 0.1, rtol=1e-6)
    tube = np.flatnonzero(~np.isclose(c.centre[:, 1], 2.0))
    assert len(tube) >= 8
    assert c.radius[tube].max() < 0.2
    np.testing.assert_allclose(c.power.sum(), area.sum(), rtol=1e-12)
