"""Light through tinted glass (KHR_materials_transmission's base-colour tint and texture) and
the light of emitters that do not cover their whole area (alpha MASK / BLEND, transmission)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from probegrid.bake.emitters import Emitters
from probegrid.core.lights import DirectionalLight
from probegrid.raytrace import EmbreeRays, RayTracer
from probegrid.raytrace.kernels import embree_rays
from probegrid.scene import Material, SceneBuilder, load_gltf, quad_mesh
from test_gltf_features import FAST, _data_uri, _holes, _png_bytes, _quad_document, _write

RED = (1.0, 0.25, 0.5)  # the pane's base colour: passes red, a quarter of green, half of blue


def _pane_over_floor(pane: Material, *, sun: bool = False):
    """A floor (albedo 0.5, y = 0, facing up) under a pane at y = 2 (facing down) of
    ``pane``; a sun straight down when ``sun``."""
    b = SceneBuilder()
    floor = b.add_material(Material.diffuse(0.5))
    b.add_quad((-50, 0, 50), (100, 0, 0), (0, 0, -100), material=floor)
    m = b.add_material(pane)
    v, t, uv = quad_mesh((-50, 2, -50), (100, 0, 0), (0, 0, 100))
    b.add_triangles(v, t, material=m, uvs=uv)
    if sun:
        b.add_light(DirectionalLight((0.0, -1.0, 0.0), (1.0, 1.0, 1.0), 3.0))
    return b.build()


def _up(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    o = np.c_[rng.uniform(-10, 10, n), np.full(n, 0.5), rng.uniform(-10, 10, n)]
    return o, np.tile([0.0, 1.0, 0.0], (n, 1))


def test_a_tinted_pane_passes_its_transmission_times_its_base_colour() -> None:
    """Through a pane of transmission 0.8 and base colour RED: the expected share is
    0.8 * RED per channel exactly (a probe's view of a sun); a shadow ray passes with
    probability 0.8 carrying RED, so the mean is 0.8 * RED to sampling noise and the
    channels' ratios are RED's exactly; a closest-hit ray through the pane to the floor
    carries RED. A BLEND pane of alpha 0.5 adds the untinted holes: 0.5 + 0.5 * 0.8 * RED."""
    scene = _pane_over_floor(Material(base_color=RED, transmission=0.8))
    tracer = RayTracer.from_scene(scene)
    assert tracer.tinted
    o, d = _up(4000)
    np.testing.assert_allclose(tracer.transmittance(o, d, 5.0, rgb=True),
                               np.tile(0.8 * np.array(RED), (4000, 1)), rtol=1e-12)
    assert np.all(tracer.transmittance(o, d, 5.0) == pytest.approx(0.8))  # (scalar: as before)
    org, dirs, far, ok = embree_rays(o, d, np.zeros(1), np.full(1, 5.0), tracer.centre)
    w = tracer.shadow_weights(EmbreeRays(org, dirs, far), ok)
    passed = w[:, 0] > 0
    assert abs(passed.mean() - 0.8) < 0.03
    np.testing.assert_allclose(w[passed], np.tile(RED, (int(passed.sum()), 1)), rtol=1e-12)
    assert np.array_equal(~passed, tracer.occluded_rays(EmbreeRays(org, dirs, far), ok))
    np.testing.assert_allclose(tracer.occluded_weights(o, d, 5.0), w, rtol=1e-12)
    down = np.c_[o[:, 0], np.full(4000, 3.0), o[:, 2]]
    hits, weight = tracer.intersect_weighted(down, -d)
    floor = hits.prim_id < 2
    assert abs(floor.mean() - 0.8) < 0.03
    np.testing.assert_allclose(weight[floor], np.tile(RED, (int(floor.sum()), 1)), rtol=1e-12)
    np.testing.assert_allclose(weight[~floor], 1.0)
    blend = RayTracer.from_scene(_pane_over_floor(Material(
        base_color=(*RED, 0.5), alpha_mode="BLEND", transmission=0.8)))
    np.testing.assert_allclose(blend.transmittance(o[:5], d[:5], 5.0, rgb=True),
                               np.tile(0.5 + 0.5 * 0.8 * np.array(RED), (5, 1)), rtol=1e-12)


def test_untinted_glass_keeps_the_plain_queries() -> None:
    """White glass passes untinted light: the weighted queries are the plain ones."""
    tracer = RayTracer.from_scene(_pane_over_floor(Material(transmission=0.6)))
    assert not tracer.tinted
    o, d = _up(500)
    np.testing.assert_array_equal(tracer.transmittance(o, d, 5.0, rgb=True)[:, 1],
                                  tracer.transmittance(o, d, 5.0))


@pytest.mark.slow
def test_the_sun_through_a_red_pane_takes_its_tint(tmp_path) -> None:
    """A probe under the RED pane (transmission 0.8) sees the sun at 0.8 * RED per channel
    (its direct view, exact), and the floor it lights through the pane in RED's ratios per
    channel (the floor's shadow rays pass carrying the tint: the ratios exact whatever the
    draw); without the tint the three channels were equal."""
    from probegrid.bake.driver import BakeSettings, bake
    from probegrid.core.cubemap import texel_solid_angles
    from probegrid.core.grid import GridSpec
    from probegrid.core.sh import K0

    grid = GridSpec.from_counts((0, 0.5, 0), (0, 0.5, 0), (1, 1, 1))
    st = BakeSettings(bounces=0, samples=4, store_incoming=True, **FAST)
    s = bake(_pane_over_floor(Material(base_color=(*RED, 1.0), transmission=0.8), sun=True),
             grid, tmp_path / "pane.probes", settings=st).store
    down = np.asarray(s["incoming"][0])[3].astype(np.float64)
    floor = np.einsum("ijc,ij->c", down, texel_solid_angles(16)[3])
    assert floor[0] > 0
    np.testing.assert_allclose(floor / floor[0], RED, rtol=1e-5)
    # the whole view: the sun straight above (K0 * E * 0.8 * RED) and the floor it lights
    # through the pane, both in RED's ratios
    sh0 = np.asarray(s["sh"][0, 0, :], np.float64)
    direct = K0 * 3.0 * 0.8 * np.array(RED)
    assert np.all(sh0 >= direct * (1 - 1e-5))
    np.testing.assert_allclose(sh0 / sh0[0], RED, rtol=1e-4)


def test_a_transmission_texture_reads_its_r_through_its_own_coordinates(tmp_path) -> None:
    """transmissionTexture's R (linear: code 128 is 0.502, not sRGB's 0.216) multiplies the
    factor; read through its own texCoord (TEXCOORD_1, mirrored) and KHR_texture_transform."""
    px = np.zeros((8, 8, 3), np.uint8)
    px[:, :4, 0] = 128  # left half (u < 0.5): R = 128/255; right half: 0 (opaque)
    uv1 = np.array([[1, 0], [0, 0], [0, 1], [1, 1]], np.float32)
    images = [{"uri": _data_uri(_png_bytes(px), "image/png")}]

    def load(info: dict):
        material = {"pbrMetallicRoughness": {"baseColorFactor": [*RED, 1.0],
                                             "metallicFactor": 0.0}, "doubleSided": True,
                    "extensions": {"KHR_materials_transmission": {
                        "transmissionFactor": 0.5, "transmissionTexture": info}}}
        doc = _quad_document(material=material, images=images, uv1=uv1)
        doc["extensionsUsed"] = ["KHR_materials_transmission", "KHR_texture_transform"]
        return load_gltf(_write(tmp_path, json.loads(json.dumps(doc))))

    def through(scene) -> tuple[float, float]:  # (x = -1: u 0.25; x = +1: u 0.75)
        t = RayTracer.from_scene(scene).transmittance([[-1, -1, 0.2], [1, -1, 0.2]],
                                                      [0.0, 1.0, 0.0], 2.0, rgb=True)
        return float(t[0, 0]), float(t[1, 0])

    plain = load({"index": 0})
    assert plain.unhonoured == ()
    assert through(plain) == pytest.approx((0.5 * 128 / 255, 0.0), abs=1e-6)
    np.testing.assert_allclose(RayTracer.from_scene(plain).transmittance(
        [-1, -1, 0.2], [0, 1.0, 0], 2.0, rgb=True), 0.5 * 128 / 255 * np.array(RED), rtol=1e-6)
    assert through(load({"index": 0, "texCoord": 1})) == pytest.approx(
        (0.0, 0.5 * 128 / 255), abs=1e-6)  # TEXCOORD_1 is mirrored
    shifted = load({"index": 0, "extensions": {"KHR_texture_transform": {"offset": [0.5, 0]}}})
    assert through(shifted) == pytest.approx((0.0, 0.5 * 128 / 255), abs=1e-6)


# --------------------------------------------------------------------------------------------
# emitters that do not cover their whole area


def _lamp_over_floor(lamp: Material, *, holes: bool = False):
    """A 1 m emissive quad at y = 2 facing down (its UVs tiled 16 times when ``holes``) over a
    floor at y = 0."""
    b = SceneBuilder()
    floor = b.add_material(Material.diffuse(0.5))
    b.add_quad((-50, 0, 50), (100, 0, 0), (0, 0, -100), material=floor)
    m = b.add_material(lamp)
    v, t, uv = quad_mesh((-0.5, 2, -0.5), (1, 0, 0), (0, 0, 1))
    b.add_triangles(v, t, material=m, uvs=uv * (16 if holes else 1))
    return b.build()


def _lamp_light(scene, *, samples: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """The emitters' irradiance at 40 floor points, and what a probe at (0, 1, 0) sees of
    them (its 16-cube's texels' mean radiance times their solid angles, summed)."""
    from probegrid.core.cubemap import texel_solid_angles

    em = Emitters.from_scene(scene)
    tracer = RayTracer.from_scene(scene)
    pts = np.c_[np.linspace(-1.5, 1.5, 40), np.full(40, 1e-3), np.zeros(40)]
    rnd = np.random.default_rng(3).random((40, samples, 3))
    e, _ = em.irradiance(pts, np.tile([0.0, 1.0, 0.0], (40, 1)), rnd, tracer, 1e-4)
    tex, val, _ = em.texel_view(np.array([0.0, 1.0, 0.0]), 16, tracer, 1e-4)
    seen = (val * texel_solid_angles(16).reshape(-1)[tex, None]).sum(axis=0)
    return e, seen


@pytest.mark.parametrize("analytic", [True, False], ids=["exact-integral", "clusters"])
def test_a_blended_emitter_emits_its_coverage_share(monkeypatch, analytic) -> None:
    """An emitter of BLEND alpha 0.25 lights the floor and shows a probe a quarter of what
    the opaque one does (a ray hitting it stops, and sees its emission, a quarter of the
    time): exactly with the exact integral and the probe's view, to sampling noise when
    sampled by clusters; a MASK emitter of half holes half of it; an emissive pane of
    transmission 0.6 0.4 of it."""
    from probegrid.bake import emitters

    if not analytic:
        monkeypatch.setattr(emitters, "MAX_ANALYTIC", 0)
    opaque_e, opaque_seen = _lamp_light(_lamp_over_floor(Material(emissive=(2.0, 2.0, 2.0))))
    assert opaque_e.min() > 0 and opaque_seen.min() > 0
    for lamp, share, holes in (
            (Material(base_color=(1, 1, 1, 0.25), alpha_mode="BLEND", emissive=(2.0, 2.0, 2.0)),
             0.25, False),
            (Material(base_color_texture=_holes(), alpha_mode="MASK", emissive=(2.0, 2.0, 2.0)),
             0.5, True),
            (Material(transmission=0.6, emissive=(2.0, 2.0, 2.0)), 0.4, False)):
        e, seen = _lamp_light(_lamp_over_floor(lamp, holes=holes))
        if analytic and not holes:
            np.testing.assert_allclose(e, share * opaque_e, rtol=1e-9)
        else:
            assert e.sum() / opaque_e.sum() == pytest.approx(share, rel=0.06)
        # (the probe's view: one visibility ray per sub-texel piece; the holes at 1/1024 m
        # are finer than the pieces, so the view reads them at the pieces' centres)
        np.testing.assert_allclose(seen / opaque_seen, share, rtol=1e-9 if not holes else 0.1)


def test_the_emissive_texture_reads_its_own_texcoord_set(tmp_path) -> None:
    """emissiveTexture with texCoord 1 reads TEXCOORD_1 (mirrored: the halves swap), while
    the base colour texture keeps TEXCOORD_0: each texture the bake reads (base colour and
    alpha, emissive, transmission) has its own coordinates."""
    from test_gltf_features import _halves

    uv1 = np.array([[1, 0], [0, 0], [0, 1], [1, 1]], np.float32)
    images = [{"uri": _data_uri(_png_bytes(_halves()), "image/png")}]
    material = {"emissiveFactor": [1.0, 1.0, 1.0], "emissiveTexture": {"index": 0, "texCoord": 1},
                "pbrMetallicRoughness": {"baseColorTexture": {"index": 0},
                                         "metallicFactor": 0.0}}
    scene = load_gltf(_write(tmp_path, _quad_document(material=material, images=images,
                                                      uv1=uv1)))
    hit = RayTracer.from_scene(scene).intersect([-1.0, 1.0, 0.0], [0.0, -1.0, 0.0])
    surf = scene.surface_at(hit.prim_id, hit.u, hit.v)
    np.testing.assert_allclose(surf.albedo, [1.0, 0.0, 0.0], atol=1e-6)    # u 0.25: red
    np.testing.assert_allclose(surf.emission, [0.0, 1.0, 0.0], atol=1e-6)  # u' 0.75: green
