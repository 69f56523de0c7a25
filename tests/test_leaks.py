"""Light through walls by the grid reads, and emitters of many triangles: physics on small cases.

* A hit reads only the probes it sees (:func:`probegrid.bake.records.replay.hidden_corners`):
  a probe beyond a wall gets weight 0 whatever its distance moments say; a hit that sees none
  reads the probe whose rays reached it; a bake's inside probe is unchanged by probes added
  outside a sunlit wall (to 1 %).
* A probe's random numbers depend on where it stands, not on its index.
* An icosphere of thousands of emitting triangles (over the exact integral's edge limit) lights
  a point as the analytic sphere does, ``E = pi L (r / d)^2 cos``, within 2 %, for any seed
  (:meth:`probegrid.bake.emitters.Emitters.irradiance` by clusters).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from probegrid.bake.emitters import MAX_ANALYTIC, Emitters, emitter_clusters
from probegrid.bake.records.replay import (
    GridData,
    _level_weights,
    _own_probes,
    hidden_corners,
    visible_probe,
)
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


def test_a_probe_behind_the_hit_plane_is_hidden_even_in_view() -> None:
    """A ceiling hit (normal down) and a probe level with the ceiling in a skylight's opening,
    in view but on the surface's other side: hidden; the probe below the ceiling is not."""
    b = SceneBuilder()
    m = b.add_material(Material.diffuse(0.5))
    b.add_quad((10.0, -5.0, 10.0), (1.0, 0.0, 0.0), (0.0, 0.0, -1.0), material=m)  # far away
    tracer = RayTracer.from_scene(b.build(name="far"))
    grid = GridSpec(bounds_min=(0.0, -1.0, 0.0), bounds_max=(0.0, 0.05, 0.0), counts=(1, 2, 1))
    pos = grid.positions()
    hit = np.array([[0.3, 0.0, 0.0]])
    hid = hidden_corners(hit, np.array([[0.0, -1.0, 0.0]]), np.array([0]), grid,
                         np.ones(2, bool), pos, 0.1, tracer)
    idx, tri, _ = grid.corners(hit)
    live = tri[0] > 0
    np.testing.assert_array_equal(hid[0][live], pos[idx[0][live], 1] > 0)


def test_a_hit_that_sees_no_probe_reads_the_probe_that_reached_it() -> None:
    """Hits on the wall's far face (x = +0.1, facing +x) of a grid whose two probes stand at
    x < -0.1 see neither: with the probe whose rays reached each hit (an index of the grid),
    they read it alone; with none (-1) they read nothing. The soft moments' weights, which
    may favour a probe beyond a wall, are kept only without a tracer."""
    tracer = RayTracer.from_scene(_wall_scene())
    grid = GridSpec(bounds_min=(-2.0, 0.0, 0.0), bounds_max=(-1.0, 0.0, 0.0), counts=(2, 1, 1))
    level = Level(kind=np.ones(3, np.uint8), position=np.array([[0.1, 0.0, 0.0],
                                                                [0.1, 0.3, 0.0],
                                                                [0.1, -0.3, 0.0]]),
                  normal=np.tile(np.array([[1.0, 0.0, 0.0]], np.float32), (3, 1)))
    data = GridData(grid, np.ones(2, bool), grid.positions(), np.zeros((0, 2), np.float32), 0,
                    None, tracer)
    idx, w = _level_weights(level, data, np.array([1, 0, -1]))
    np.testing.assert_array_equal(idx[:2, 0], [1, 0])
    np.testing.assert_array_equal(w[:2], np.eye(8, dtype=np.float32)[[0, 0]])
    np.testing.assert_array_equal(w[2], 0.0)
    _, w = _level_weights(level, dataclasses.replace(data, tracer=None))
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-6)


def test_own_probes_follow_the_gather_rays_to_their_probe() -> None:
    arrays = {"probes": np.array([5, 9]), "rays_per_probe": np.array(3),
              "kind": np.ones(6, np.uint8), "gather_kind": np.ones(4, np.uint8),
              "gather_primary": np.array([0, 2, 3, 5], np.int32),
              "gather2_kind": np.ones(4, np.uint8),
              "gather2_primary": np.array([3, 2, 1, 0], np.int32)}
    np.testing.assert_array_equal(_own_probes(arrays, 2, None), [9, 9, 5, 5])
    np.testing.assert_array_equal(_own_probes(arrays, 1, None), [5, 5, 9, 9])
    np.testing.assert_array_equal(_own_probes(arrays, 0, np.array([-1, 2])),
                                  [-1, -1, -1, 2, 2, 2])


def test_a_point_stands_in_by_the_probe_it_sees() -> None:
    tracer = RayTracer.from_scene(_wall_scene())
    grid = GridSpec(bounds_min=(-1.0, 0.0, 0.0), bounds_max=(1.0, 0.0, 0.0), counts=(2, 1, 1))
    pts = np.array([[-0.5, 0.0, 0.0], [0.8, 0.0, 0.0], [0.5, 0.0, 0.0]])
    near = visible_probe(pts, grid, np.ones(2, bool), grid.positions(), tracer)
    np.testing.assert_array_equal(near, [0, 1, 1])  # each sees only its side's probe
    near = visible_probe(pts, grid, np.array([True, False]), grid.positions(), tracer)
    np.testing.assert_array_equal(near, [0, -1, -1])


# -------------------------------------------------------------------------- emitters
def _icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """A unit icosphere, outward winding (20 * 4^subdivisions triangles; trimesh's)."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


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


# -------------------------------------------------------------------------- random streams
def test_a_probe_draws_by_where_it_stands_not_by_its_index() -> None:
    """Two grids with a probe at one point (its index, and its coordinates' last bits, differ:
    ``0.1 + 0.2`` against ``0.3``) trace it with the same random numbers; another point draws
    others."""
    from probegrid.bake.environment import Environment
    from probegrid.bake.records import RecordTracer
    from probegrid.bake.settings import BakeSettings, TraceGeometry

    b = SceneBuilder()
    m = b.add_material(Material.diffuse(0.5))
    b.add_box((-2.0, -2.0, -2.0), (2.0, 2.0, 2.0), material=m, inward=True)
    lamp = b.add_material(Material.diffuse(0.0, emission=np.full(3, 2.0)))
    b.add_quad((-0.3, 1.9, -0.3), (0.6, 0.0, 0.0), (0.0, 0.0, 0.6), material=lamp)
    scene = b.build(name="box")
    st = BakeSettings(face_size=4, gather_samples=2)
    tracer = RecordTracer(scene, Environment(), st, TraceGeometry())
    here = np.array([[0.1, 0.2, 0.3]])
    there = np.array([[0.1, 0.2, 0.1 + 0.2]])  # the same point, a rounding apart
    assert here[0, 2] != there[0, 2] and abs(here[0, 2] - there[0, 2]) < 1e-12
    a, _, _ = tracer.trace(here, np.array([3]))
    c, _, _ = tracer.trace(there, np.array([17]))
    d, _, _ = tracer.trace(here + 0.01, np.array([3]))
    keys = [k for k in a if k.endswith("light_emitters")]  # (the sampled light, each level)
    assert len(keys) == 1 + st.gather_levels()
    for key in keys:
        np.testing.assert_array_equal(a[key], c[key])
        assert not np.array_equal(a[key], d[key])


# -------------------------------------------------------------------------- a whole bake
def _sunlit_room():
    """A closed 4 x 3 x 4 m room of 20 cm solid slabs with a 1 m skylight, a sun and a sky,
    on an open ground."""
    from probegrid.bake.environment import Environment
    from probegrid.core.lights import DirectionalLight

    b = SceneBuilder()
    wall = b.add_material(Material.diffuse(0.7))
    ground = b.add_material(Material.diffuse(0.4))
    b.add_quad((-20.0, 0.0, 20.0), (40.0, 0.0, 0.0), (0.0, 0.0, -40.0), material=ground)
    w = 0.2
    b.add_box((-2.0 - w, 0.0, -2.0 - w), (-2.0, 3.0, 2.0 + w), material=wall)
    b.add_box((2.0, 0.0, -2.0 - w), (2.0 + w, 3.0, 2.0 + w), material=wall)
    b.add_box((-2.0, 0.0, -2.0 - w), (2.0, 3.0, -2.0), material=wall)
    b.add_box((-2.0, 0.0, 2.0), (2.0, 3.0, 2.0 + w), material=wall)
    for lo, hi in (((-2.0 - w, 3.0, -2.0 - w), (-0.5, 3.0 + w, 2.0 + w)),
                   ((0.5, 3.0, -2.0 - w), (2.0 + w, 3.0 + w, 2.0 + w)),
                   ((-0.5, 3.0, -2.0 - w), (0.5, 3.0 + w, -0.5)),
                   ((-0.5, 3.0, 0.5), (0.5, 3.0 + w, 2.0 + w))):
        b.add_box(lo, hi, material=wall)  # the roof around a 1 m opening
    b.add_light(DirectionalLight((0.3, -0.9, 0.2), (1.0, 1.0, 1.0), 40.0))
    return b.build(name="sunlit_room"), Environment(color=np.array([0.5, 0.7, 1.0]))


@pytest.mark.slow
def test_probes_outside_a_sunlit_wall_do_not_light_the_room(tmp_path) -> None:
    """Two probes inside the room baked alone, then with a layer of probes outside its east
    wall, in the sun: the inside probes' maps (their later bounces read the grid at gather
    hits on that wall) change by less than 1 %."""
    from probegrid.bake import BakeSettings, bake
    from probegrid.store import open_store

    scene, env = _sunlit_room()
    st = BakeSettings(face_size=8, bounces=4)
    alone = GridSpec(bounds_min=(-1.0, 1.5, 0.0), bounds_max=(1.0, 1.5, 0.0), counts=(2, 1, 1))
    more = GridSpec(bounds_min=(-1.0, 1.5, 0.0), bounds_max=(3.0, 1.5, 0.0), counts=(3, 1, 1))
    out = []
    for name, grid in (("alone", alone), ("more", more)):
        bake(scene, grid, tmp_path / f"{name}.probes", settings=st, environment=env)
        out.append(np.asarray(open_store(tmp_path / f"{name}.probes")["diffuse"], np.float64))
    a, m = out[0], out[1][:2]
    assert out[1][2].sum() > 2 * a[1].sum()  # the outside probe is in the sun
    change = np.abs(m - a).sum(axis=(1, 2, 3, 4)) / a.sum(axis=(1, 2, 3, 4))
    assert change.max() < 0.01, change
