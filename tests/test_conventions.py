"""Every statement of the conventions record is checked against the module that owns it
(probegrid.core.conventions)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from probegrid.core import cubemap, dfg, layouts, lights, sh
from probegrid.core.conventions import conventions


@pytest.fixture(scope="module")
def conv():
    return conventions()


def test_face_order_and_texel_table(conv):
    assert conv["cube_face_order"] == list(cubemap.FACE_NAMES)
    u, v = 0.25, -0.6
    for name, formula in conv["cube_texel_to_direction"].items():
        f = cubemap.FACE_NAMES.index(name)
        expected = eval(formula.replace("u", "U").replace("v", "V"), {"U": u, "V": v})
        np.testing.assert_allclose(cubemap.face_uv_to_direction(f, u, v), expected)
    # texel centres as stated
    assert cubemap.texel_to_uv(0, 4) == pytest.approx(2 * 0.5 / 4 - 1)


def test_sh_constants(conv):
    printed = {k: float(re.match(r"[0-9.]+", s).group()) for k, s in conv["sh_constants"].items()}
    d = np.array([[0.36, -0.48, 0.8]])  # a unit vector
    x, y, z = d[0]
    basis = sh.sh_basis(d)[0]
    expected = [
        printed["Y00"], printed["Y1-1"] * y, printed["Y10"] * z, printed["Y11"] * x,
        printed["Y2-2"] * x * y, printed["Y2-1"] * y * z, printed["Y20"] * (3 * z * z - 1),
        printed["Y21"] * x * z, printed["Y22"] * (x * x - y * y),
    ]
    np.testing.assert_allclose(basis, expected, rtol=2e-6)
    np.testing.assert_allclose(sh.A_HAT[[0, 1, 4]], [np.pi, 2 * np.pi / 3, np.pi / 4])


def test_diffuse_map_of_a_constant_environment_is_the_constant(conv):
    assert "constant environment of radiance L gives L" in conv["diffuse_map"]
    cube = np.full((6, 8, 8, 3), 0.7, np.float32)
    np.testing.assert_allclose(sh.diffuse_cube(sh.project_cube(cube), 4), 0.7, rtol=1e-6)


def test_equirect_and_angular_layouts(conv):
    assert conv["equirect_layout"].startswith("centre column = +X")
    h, w = 64, 128
    x, y = layouts.direction_to_equirect(np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]]), h, w)
    assert x[0] == pytest.approx(w / 2 - 0.5) and x[1] == pytest.approx(3 * w / 4 - 0.5)
    assert y[2] == pytest.approx(-0.5)  # the top edge
    col, row = layouts.direction_to_angular(np.array([[0, 0, 1.0]]), 64)
    assert (float(col[0]), float(row[0])) == pytest.approx((31.5, 31.5))


def test_light_falloff(conv):
    assert "max(min(1 - (d/range)^4, 1), 0) / d^2" in conv["light_units"]
    d, r = 2.0, 3.0
    assert lights.range_attenuation(d, r) == pytest.approx(max(min(1 - (d / r) ** 4, 1), 0) / d**2)
    assert lights.range_attenuation(d) == pytest.approx(1 / d**2)


def test_dfg_axes(conv):
    assert "x = N.V" in conv["dfg_lut"] and "y = perceptual roughness" in conv["dfg_lut"]
    lut = dfg.dfg_lut(16)
    # smooth (row 0) at normal incidence (last column): A + B -> 1 (no energy lost)
    assert lut[0, -1].sum() == pytest.approx(1.0, abs=0.02)
    # fully rough (last row) at normal incidence loses most of its single-scattered energy
    assert 0.25 < lut[-1, -1].sum() < 0.4


def test_surfaces_emit_from_the_front_only_and_double_sided_backs_reflect(conv):
    """The 'surfaces' statement against the bake: a double-sided emissive quad (facing down)
    lights a point below it and not one above it, and a probe above it sees no emission; a
    double-sided quad's back is a lit front hit with the normal turned, a single-sided back is
    black."""
    import dataclasses

    from probegrid.bake.emitters import Emitters
    from probegrid.bake.kernels.surfaces import split_hits
    from probegrid.raytrace import RayTracer
    from probegrid.scene import Material, SceneBuilder

    assert "front only, whatever doubleSided" in conv["surfaces"]
    b = SceneBuilder()
    lamp = b.add_material(dataclasses.replace(Material(emissive=(2.0, 2.0, 2.0)),
                                              double_sided=True))
    b.add_quad((-0.5, 1, -0.5), (1, 0, 0), (0, 0, 1), material=lamp)  # faces -Y
    scene = b.build()
    assert np.allclose(scene.triangle_normals, [0, -1, 0])
    em = Emitters.from_scene(scene)
    tracer = RayTracer(scene.vertices, scene.triangles)
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    nrm = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])  # each facing the lamp
    e, _ = em.irradiance(pts, nrm, np.random.default_rng(0).random((2, 4, 3)), tracer, 1e-5)
    assert e[0, 0] > 0.5 and e[1].max() == 0.0
    below = em.texel_view(pts[0], 8, tracer, 1e-5)
    above = em.texel_view(pts[1], 8, tracer, 1e-5)
    assert len(below[0]) > 0 and len(above[0]) == 0
    dirs = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])  # from below (front), from above (back)
    hits = tracer.intersect(np.array([[0.0, 0.0, 0.0], [0.0, 2.0, 0.0]]), dirs)
    for double, back_kind in ((True, 1), (False, 2)):
        kind, rows, flip, _ = split_hits(dirs, hits.prim_id, scene.triangle_normals,
                                         np.array([double]))
        assert kind.tolist() == [1, back_kind]
        assert flip[rows == 1].tolist() == ([True] if double else [])
