"""Emissive triangles as lights at surface points (probegrid.bake.emitters.Emitters.irradiance):
exact where nothing occludes them, exactly 0 where everything does, never negative."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from probegrid.bake.emitters import Emitters
from probegrid.raytrace import RayTracer
from probegrid.scene import Material, SceneBuilder


def _scene(occluder: bool):
    b = SceneBuilder()
    lamp = b.add_material(Material(base_color=(0.5, 0.5, 0.5, 1.0), emissive=(3.0, 2.0, 1.0)))
    grey = b.add_material(Material.diffuse(0.5))
    b.add_quad((-0.5, 2, -0.5), (1, 0, 0), (0, 0, 1), material=lamp)  # faces -Y, down
    if occluder:  # a plate at y = 1 that hides the lamp from points under it near x = 0
        b.add_quad((-3, 1, -3), (0, 0, 6), (6, 0, 0), material=grey)  # faces +Y
    b.add_quad((-5, -1, -5), (0, 0, 10), (10, 0, 0), material=grey)  # a floor far below
    return b.build()


def _estimate(scene, points, samples=2, seed=0):
    em = Emitters.from_scene(scene)
    tracer = RayTracer(scene.vertices, scene.triangles)
    normals = np.tile([0.0, 1.0, 0.0], (len(points), 1))
    rnd = np.random.default_rng(seed).random((len(points), samples, 3))
    return em, em.irradiance(points, normals, rnd, tracer, 1e-4)[0]


def test_unoccluded_points_get_the_exact_integral():
    from probegrid.bake.kernels.emitters import emitter_irradiance

    pts = np.column_stack([np.linspace(-2, 2, 50), np.zeros(50), np.linspace(-1, 1, 50)])
    em, e = _estimate(_scene(False), pts)
    exact = emitter_irradiance(pts, np.tile([0.0, 1.0, 0.0], (50, 1)), em.vertices, em.normals,
                               em.factor)
    np.testing.assert_allclose(e, exact, rtol=1e-12)


def test_points_in_full_shadow_read_exactly_zero():
    """The plate hides the lamp from every point under its middle: 0, not a clamped
    difference of the exact integral and a noisy estimate of what is hidden."""
    pts = np.column_stack([np.linspace(-1, 1, 200), np.zeros(200), np.zeros(200)])
    for seed in range(5):
        _, e = _estimate(_scene(True), pts, seed=seed)
        assert e.max() == 0.0


def test_penumbra_is_between_zero_and_the_unoccluded_integral():
    pts = np.column_stack([np.linspace(5.0, 7.0, 400), np.zeros(400), np.zeros(400)])
    _, shaded = _estimate(_scene(True), pts, samples=4)
    _, free = _estimate(_scene(False), pts, samples=4)
    assert np.all(shaded >= 0) and np.all(shaded <= free * (1 + 1e-12))
    assert (shaded < free).any() and (shaded > 0).any()


def _fan(centre, radius, k, y, *, hole=0.0):
    """Triangles of a horizontal disc (or an annulus with ``hole`` > 0) at height ``y``,
    wound as the squares of the test below."""
    a = np.linspace(0, 2 * np.pi, k + 1)
    rim = np.column_stack([np.cos(a), np.zeros(k + 1), np.sin(a)])
    rim[-1] = rim[0]  # closed bit for bit (sin(2 pi) is not 0)
    c = np.array([centre[0], y, centre[1]])
    if hole == 0.0:
        return np.stack([np.stack([c, c + radius * rim[i + 1], c + radius * rim[i]])
                         for i in range(k)])
    tris = []
    for i in range(k):  # two triangles per ring segment
        o0, o1 = c + radius * rim[i], c + radius * rim[i + 1]
        i0, i1 = c + hole * rim[i], c + hole * rim[i + 1]
        tris += [np.stack([i0, o1, o0]), np.stack([i0, i1, o1])]
    return np.stack(tris)


def test_merged_outlines_integrate_as_their_triangles():
    """polygon_irradiance over emitter_outlines (coplanar triangles merged into loops: a quad,
    a fan-tessellated disc, an annulus with its hole, an L-shape, a separate square of another
    radiance) equals the per-triangle sum at points all around, receivers tilted so the
    horizon clips the regions (non-convex loops included), and has only the outlines' edges."""
    from probegrid.bake.emitters import emitter_outlines
    from probegrid.bake.kernels.emitters import emitter_irradiance, polygon_irradiance

    quad = np.array([[[0, 2, 0], [1, 2, 1], [1, 2, 0]], [[0, 2, 0], [0, 2, 1], [1, 2, 1]]],
                    float)
    ell = np.array([[[2, 2, 0], [3, 2, 1], [3, 2, 0]], [[2, 2, 0], [2, 2, 1], [3, 2, 1]],
                    [[2, 2, 1], [3, 2, 2], [3, 2, 1]], [[2, 2, 1], [2, 2, 2], [3, 2, 2]],
                    [[3, 2, 0], [4, 2, 1], [4, 2, 0]], [[3, 2, 0], [3, 2, 1], [4, 2, 1]]],
                   float)
    disc = _fan((-2.0, 0.5), 0.8, 24, 2.5)
    ring = _fan((0.5, -2.0), 1.0, 20, 1.5, hole=0.4)
    other = quad + [5.0, 0.0, 0.0]
    tris = np.concatenate([quad, ell, disc, ring, other])[:, [0, 2, 1]]  # wound facing down
    nrm = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    assert np.allclose(nrm, [0, -1, 0])
    rad = np.ones((len(tris), 3))
    rad[-2:] = [2.0, 1.0, 0.5]
    outlines = emitter_outlines(tris, nrm, rad)
    loops = np.diff(outlines[1])
    # quad + L-shape (one region: same plane and radiance) | disc | ring | other square
    assert len(outlines[3]) == 4
    assert sorted(loops.tolist()) == sorted([4, 8, 24, 20, 20, 4])
    rng = np.random.default_rng(3)
    pts = rng.uniform([-4, -1, -4], [6, 1.4, 3], (400, 3))
    n = rng.normal(size=(400, 3)) + [0, 1.5, 0]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ref = emitter_irradiance(pts, n, tris, nrm, rad)
    got = polygon_irradiance(pts, n, outlines)
    assert (ref > 0).mean() > 0.8
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-13 * ref.max())


def test_the_sample_rooms_panel_is_one_quad():
    from probegrid.scene import load_gltf

    em = Emitters.from_scene(load_gltf(Path(__file__).parents[1] / "data" / "sample_room.glb"))
    assert len(em) == 2 and em.analytic
    assert em.outlines[1].tolist() == [0, 4] and em.outlines[2].tolist() == [0, 1]


def _triangle_solid_angle(p: np.ndarray, tri: np.ndarray) -> float:
    """Van Oosterom & Strackee's solid angle of triangle ``tri (3, 3)`` seen from ``p``."""
    a, b, c = tri - p
    la, lb, lc = np.linalg.norm(a), np.linalg.norm(b), np.linalg.norm(c)
    num = abs(np.dot(a, np.cross(b, c)))
    den = la * lb * lc + np.dot(a, b) * lc + np.dot(a, c) * lb + np.dot(b, c) * la
    return 2.0 * np.arctan2(num, den)


def test_texel_views_of_many_cubes_are_each_cubes_view(monkeypatch):
    """Cubes at many points at once (their shadow rays in shared queries, however they are
    split) give each point's own view bit for bit; unoccluded, a view's radiance times the
    texels' solid angles is the lamp's radiance times its exact solid angle."""
    from probegrid.bake import emitters as mod
    from probegrid.core.cubemap import texel_solid_angles

    scene = _scene(True)
    em = Emitters.from_scene(scene)
    tracer = RayTracer(scene.vertices, scene.triangles)
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(-6, 6, 40), rng.uniform(-0.5, 2.5, 40),
                           rng.uniform(-6, 6, 40)])
    n = 8
    one = [em.texel_view(p, n, tracer, 1e-5) for p in pts]
    assert sum(len(t) for t, _, _ in one) > 0 and any(len(t) == 0 for t, _, _ in one)
    for batch in (mod.VIEW_BATCH, 7):  # one query, and many small ones
        monkeypatch.setattr(mod, "VIEW_BATCH", batch)
        tex, val, off, rays = em.texel_views(pts, n, tracer, 1e-5)
        assert off[0] == 0 and off[-1] == len(tex) and rays == sum(r for _, _, r in one)
        for j, (t, v, _) in enumerate(one):
            np.testing.assert_array_equal(tex[off[j]:off[j + 1]], t)
            np.testing.assert_array_equal(val[off[j]:off[j + 1]], v)
    # above the plate (y = 1.5, nothing between the point and the lamp): exact energy
    p = np.array([0.1, 1.5, -0.2])
    tex, val, _ = em.texel_view(p, n, tracer, 1e-5)
    lamp = np.asarray(scene.vertices)[np.asarray(scene.triangles)[:2]]
    omega = sum(_triangle_solid_angle(p, t) for t in lamp)
    sa = texel_solid_angles(n).reshape(-1)
    np.testing.assert_allclose((val * sa[tex, None]).sum(axis=0), np.array([3.0, 2.0, 1.0])
                               * omega, rtol=1e-9)
