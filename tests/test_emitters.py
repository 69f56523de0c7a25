"""Emissive triangles as lights at surface points (probegrid.bake.emitters.Emitters.irradiance):
exact where nothing occludes them, exactly 0 where everything does, never negative."""

from __future__ import annotations

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
    from probegrid.kernels import emitter_irradiance

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
