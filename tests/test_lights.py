"""Tests of punctual lights, analytic light maps and delta splatting (probegrid.core.lights)."""

import math

import numpy as np
import pytest

from probegrid.core import lights as lt
from probegrid.core.cubemap import CubeMap, texel_directions, texel_solid_angles
from probegrid.core.lobes import ggx_kernel_integral


def _integral(faces: np.ndarray) -> np.ndarray:
    """Solid-angle integral of a cube, per channel (float64)."""
    n = faces.shape[1]
    return (faces.astype(np.float64) * texel_solid_angles(n)[..., None]).sum(axis=(0, 1, 2))


def _scene() -> list:
    return [
        lt.PointLight(position=(2.0, 1.0, -1.0), color=(1.0, 0.5, 0.25), intensity=20.0),
        lt.PointLight(position=(-1.0, 3.0, 0.5), color=(0.2, 0.9, 1.0), intensity=8.0, range=10),
        lt.SpotLight(
            position=(0.0, 0.0, 3.0),
            direction=(0.1, 0.0, -1.0),
            color=(1.0, 1.0, 1.0),
            intensity=30.0,
            inner_cone_angle=0.2,
            outer_cone_angle=0.5,
        ),
        lt.DirectionalLight(direction=(0.3, -1.0, 0.2), color=(1.0, 0.95, 0.8), intensity=3.0),
    ]


# --------------------------------------------------------------------------- units and falloff


@pytest.mark.parametrize("d", [0.25, 1.0, 3.0, 40.0])
def test_point_inverse_square_law(d):
    light = lt.PointLight(position=(0.0, 0.0, d), color=(1.0, 0.5, 0.0), intensity=7.0)
    dirs, e, dist = lt.incident([light], (0.0, 0.0, 0.0))
    np.testing.assert_allclose(e, [[7.0 / d**2, 3.5 / d**2, 0.0]], rtol=1e-12)
    np.testing.assert_allclose(dirs, [[0.0, 0.0, 1.0]], atol=1e-15)
    np.testing.assert_allclose(dist, [d], rtol=1e-15)


def test_one_candela_at_one_metre_is_one_lux():
    light = lt.PointLight(position=(1.0, 0.0, 0.0), color=(1.0, 1.0, 1.0), intensity=1.0)
    _, e, _ = lt.incident([light], (0.0, 0.0, 0.0))
    np.testing.assert_allclose(e, [[1.0, 1.0, 1.0]], rtol=1e-15)


def test_range_window_values():
    r, intensity = 8.0, 5.0
    positions = np.array([[0.0, 0.0, r / 2], [0.0, 0.0, r], [0.0, 0.0, 1.5 * r]])
    light = lt.PointLight(position=(0.0, 0.0, 0.0), color=(1.0, 1.0, 1.0), intensity=intensity,
                          range=r)
    _, e, _ = lt.incident_many([light], positions)
    # spec: max(min(1 - (d/range)^4, 1), 0) / d^2 ; at d = range/2 the window is 15/16
    np.testing.assert_allclose(e[0, 0], intensity * (15 / 16) / (r / 2) ** 2, rtol=1e-12)
    np.testing.assert_array_equal(e[1:, 0], 0.0)
    np.testing.assert_allclose(lt.range_attenuation(2.0, 4.0), (15 / 16) / 4, rtol=1e-15)
    np.testing.assert_allclose(lt.range_attenuation(2.0), 0.25, rtol=1e-15)
    np.testing.assert_allclose(lt.range_attenuation([2.0, 5.0], [np.inf, 4.0]), [0.25, 0.0])


def test_spot_cone_attenuation_matches_spec():
    inner, outer, intensity = 0.3, 0.6, 12.0
    light = lt.SpotLight(position=(0.0, 2.0, 0.0), direction=(0.0, -2.0, 0.0),
                         color=(1.0, 1.0, 1.0), intensity=intensity,
                         inner_cone_angle=inner, outer_cone_angle=outer)
    assert light.direction == (0.0, -1.0, 0.0)
    theta = np.array([0.0, 0.15, inner, 0.4, 0.45, 0.55, outer, 0.7, 2.0])
    # points at unit distance from the light, at angle theta from the spot axis
    pts = np.stack([np.sin(theta), 2.0 - np.cos(theta), np.zeros_like(theta)], axis=-1)
    _, e, dist = lt.incident_many([light], pts)
    np.testing.assert_allclose(dist[:, 0], 1.0, rtol=1e-12)
    ci, co = math.cos(inner), math.cos(outer)
    expected = intensity * np.clip((np.cos(theta) - co) / (ci - co), 0, 1) ** 2
    np.testing.assert_allclose(e[:, 0, 0], expected, rtol=1e-9, atol=1e-12)
    assert e[0, 0, 0] == pytest.approx(intensity)  # full inside the inner cone
    assert e[2, 0, 0] == pytest.approx(intensity)  # exactly 1 at the inner angle
    assert e[6, 0, 0] == pytest.approx(0.0, abs=1e-9)  # 0 at the outer angle
    assert e[7, 0, 0] == 0.0 and e[8, 0, 0] == 0.0
    mid = (0.5 * (ci + co) - co) / (ci - co)
    assert lt.spot_attenuation(0.5 * (ci + co), inner, outer) == pytest.approx(mid**2)


def test_spot_reference_code_clamps_scale_for_tiny_penumbra():
    # lightAngleScale = 1 / max(0.001, cos(inner) - cos(outer))
    inner, outer = 0.1, 0.1001
    assert math.cos(inner) - math.cos(outer) < 0.001
    got = lt.spot_attenuation(math.cos(inner), inner, outer)
    assert got == pytest.approx(((math.cos(inner) - math.cos(outer)) / 0.001) ** 2)


def test_directional_light_is_lux_everywhere():
    light = lt.DirectionalLight(direction=(0.0, -3.0, 4.0), color=(0.5, 1.0, 2.0), intensity=4.0)
    pts = np.array([[0.0, 0.0, 0.0], [100.0, -5.0, 3.0]])
    dirs, e, dist = lt.incident_many([light], pts)
    np.testing.assert_allclose(e[:, 0], [[2.0, 4.0, 8.0]] * 2, rtol=1e-15)
    np.testing.assert_allclose(dirs[:, 0], [[0.0, 0.6, -0.8]] * 2, rtol=1e-15)
    assert np.all(np.isinf(dist))


def test_incident_many_broadcasts_and_matches_incident():
    lights = _scene()
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(4, 5, 3))
    dirs, e, dist = lt.incident_many(lights, pts)
    assert dirs.shape == (4, 5, 4, 3) and e.shape == (4, 5, 4, 3) and dist.shape == (4, 5, 4)
    assert dirs.dtype == np.float64 and e.dtype == np.float64
    d1, e1, r1 = lt.incident(lights, pts[2, 3])
    np.testing.assert_allclose(dirs[2, 3], d1, rtol=1e-15)
    np.testing.assert_allclose(e[2, 3], e1, rtol=1e-15)
    np.testing.assert_allclose(dist[2, 3], r1, rtol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, rtol=1e-12)
    # no lights
    d0, e0, r0 = lt.incident_many([], pts)
    assert d0.shape == (4, 5, 0, 3) and e0.shape == (4, 5, 0, 3) and r0.shape == (4, 5, 0)


def test_position_at_the_light_gets_nothing():
    light = lt.PointLight(position=(1.0, 2.0, 3.0), color=(1.0, 1.0, 1.0), intensity=1.0)
    dirs, e, dist = lt.incident([light], (1.0, 2.0, 3.0))
    np.testing.assert_array_equal(dirs, 0.0)
    np.testing.assert_array_equal(e, 0.0)
    np.testing.assert_array_equal(dist, 0.0)


@pytest.mark.parametrize(
    "make",
    [
        lambda: lt.PointLight(position=(0, 0, 0), color=(1, 1, 1), intensity=-1.0),
        lambda: lt.PointLight(position=(0, np.nan, 0), color=(1, 1, 1), intensity=1.0),
        lambda: lt.PointLight(position=(0, 0, 0), color=(1, -1, 1), intensity=1.0),
        lambda: lt.PointLight(position=(0, 0, 0), color=(1, 1, 1), intensity=np.inf),
        lambda: lt.PointLight(position=(0, 0, 0), color=(1, 1, 1), intensity=1.0, range=0.0),
        lambda: lt.PointLight(position=(0, 0), color=(1, 1, 1), intensity=1.0),
        lambda: lt.DirectionalLight(direction=(0, 0, 0), color=(1, 1, 1), intensity=1.0),
        lambda: lt.SpotLight((0, 0, 0), (0, 0, -1), (1, 1, 1), 1.0, inner_cone_angle=0.5,
                             outer_cone_angle=0.5),
        lambda: lt.SpotLight((0, 0, 0), (0, 0, -1), (1, 1, 1), 1.0, outer_cone_angle=2.0),
        lambda: lt.SpotLight((0, 0, 0), (0, 0, -1), (1, 1, 1), 1.0, inner_cone_angle=-0.1),
    ],
)
def test_light_validation(make):
    with pytest.raises(ValueError):
        make()


def test_light_defaults_and_normalisation():
    s = lt.SpotLight(position=[0, 0, 0], direction=[0, 0, -5], color=[1, 1, 1], intensity=2)
    assert s.inner_cone_angle == 0.0 and s.outer_cone_angle == pytest.approx(math.pi / 4)
    assert s.direction == (0.0, 0.0, -1.0) and s.range is None
    p = lt.PointLight(position=np.zeros(3), color=np.ones(3), intensity=1, range=np.inf)
    assert p.range is None and p == lt.PointLight((0, 0, 0), (1, 1, 1), 1.0)
    assert hash(p) == hash(lt.PointLight((0, 0, 0), (1, 1, 1), 1.0))


def test_incident_rejects_bad_input():
    with pytest.raises(ValueError):
        lt.incident(["not a light"], (0, 0, 0))
    with pytest.raises(ValueError):
        lt.incident(_scene(), (0, np.inf, 0))
    with pytest.raises(ValueError):
        lt.incident(_scene(), np.zeros((2, 3)))
    with pytest.raises(ValueError):
        lt.incident_many(_scene(), np.zeros((2, 2)))


# ----------------------------------------------------------------------------------- light maps


def _hand_irradiance(position):
    """E_perp and direction of _scene()'s lights, computed without probegrid.core.lights."""
    p = np.asarray(position, dtype=np.float64)
    out = []
    # point 1: inverse square
    t = np.array([2.0, 1.0, -1.0]) - p
    out.append((t / np.linalg.norm(t), np.array([1.0, 0.5, 0.25]) * 20.0 / (t @ t)))
    # point 2: range window
    t = np.array([-1.0, 3.0, 0.5]) - p
    d = np.linalg.norm(t)
    out.append((t / d, np.array([0.2, 0.9, 1.0]) * 8.0 * max(0.0, 1 - (d / 10) ** 4) / d**2))
    # spot
    t = np.array([0.0, 0.0, 3.0]) - p
    d = np.linalg.norm(t)
    axis = np.array([0.1, 0.0, -1.0]) / np.linalg.norm([0.1, 0.0, -1.0])
    cd = axis @ (-t / d)
    ang = np.clip((cd - math.cos(0.5)) / (math.cos(0.2) - math.cos(0.5)), 0, 1) ** 2
    out.append((t / d, np.ones(3) * 30.0 * ang / d**2))
    # directional
    l_ = -np.array([0.3, -1.0, 0.2]) / np.linalg.norm([0.3, -1.0, 0.2])
    out.append((l_, np.array([1.0, 0.95, 0.8]) * 3.0))
    return np.array([o[0] for o in out]), np.array([o[1] for o in out])


def test_diffuse_map_matches_hand_evaluation_and_integrates():
    pos = (0.2, 0.3, -0.1)
    maps = lt.light_maps(_scene(), pos, diffuse_size=16, specular_size=4)
    diffuse = maps["diffuse"]
    assert isinstance(diffuse, CubeMap) and diffuse.kind == "diffuse"
    assert diffuse.faces.shape == (6, 16, 16, 3) and diffuse.faces.dtype == np.float32
    ldir, e = _hand_irradiance(pos)
    assert np.all(e[2] > 0)  # the spot reaches the point
    n = texel_directions(16)
    expected = np.einsum("fijl,lc->fijc", np.maximum(n @ ldir.T, 0.0), e) / np.pi
    np.testing.assert_allclose(diffuse.faces, expected, rtol=2e-6, atol=1e-7)
    # int max(0, N . l) / pi dN = 1: the integral of the map is the total E_perp
    np.testing.assert_allclose(_integral(diffuse.faces), e.sum(axis=0), rtol=1e-3)


def test_directional_light_gives_clamped_cosine_map():
    light = lt.DirectionalLight(direction=(-1.0, -2.0, 0.5), color=(1.0, 1.0, 1.0), intensity=2.0)
    maps = lt.light_maps([light], (5.0, 5.0, 5.0), diffuse_size=8, specular_size=2)
    l_ = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    expected = 2.0 * np.maximum(texel_directions(8) @ l_, 0.0) / np.pi
    np.testing.assert_allclose(maps["diffuse"].faces[..., 1], expected, rtol=1e-6, atol=1e-7)
    assert maps["diffuse"].faces.max() == pytest.approx(2.0 / np.pi, rel=0.02)


@pytest.mark.parametrize("size, levels", [(32, None), (64, 5)])
def test_every_specular_level_holds_the_light_energy(size, levels):
    pos = (0.2, 0.3, -0.1)
    maps = lt.light_maps(_scene(), pos, diffuse_size=4, specular_size=size,
                         specular_levels=levels)
    spec = maps["specular"]
    assert spec.kind == "specular"
    assert spec.num_levels == (levels or int(math.log2(size)) + 1)
    total = _hand_irradiance(pos)[1].sum(axis=0)
    for k, faces in enumerate(spec.levels):
        assert faces.shape == (6, size >> k, size >> k, 3)
        assert np.all(faces >= 0)
        np.testing.assert_allclose(_integral(faces), total, rtol=1e-3, err_msg=f"level {k}")


def test_specular_level_zero_is_one_texel_per_light():
    light = lt.DirectionalLight(direction=(0.2, -1.0, 0.3), color=(1.0, 1.0, 1.0), intensity=5.0)
    faces = lt.light_maps([light], (0, 0, 0), specular_size=16)["specular"].levels[0]
    nz = np.argwhere(faces[..., 0] > 0)
    assert len(nz) == 1
    f, i, j = nz[0]
    assert faces[f, i, j, 0] == pytest.approx(5.0 / texel_solid_angles(16)[f, i, j], rel=1e-6)
    l_ = -np.array([0.2, -1.0, 0.3]) / np.linalg.norm([0.2, -1.0, 0.3])
    assert np.argmax(texel_directions(16).reshape(-1, 3) @ l_) == np.ravel_multi_index(
        (f, i, j), (6, 16, 16)
    )


def test_rough_specular_level_is_the_ggx_lobe():
    # Level 2 of a 3-level 64 chain has roughness 1 (alpha 1), 16x16 faces: wide enough that
    # each texel is the lobe at its centre. Independent GGX: D(h) max(0, R.l) / 4.
    light = lt.DirectionalLight(direction=(0.0, -1.0, 0.0), color=(1.0, 1.0, 1.0), intensity=1.0)
    faces = lt.light_maps([light], (0, 0, 0), specular_size=64, specular_levels=3)[
        "specular"
    ].levels[2][..., 0]
    r = texel_directions(16)
    l_ = np.array([0.0, 1.0, 0.0])
    h = r + l_
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    nh = r @ np.zeros(3) + np.einsum("...i,...i->...", r, h)
    alpha = 1.0
    d = alpha**2 / (np.pi * (nh**2 * (alpha**2 - 1) + 1) ** 2)
    expected = d * np.maximum(r @ l_, 0.0) / 4 / ggx_kernel_integral(alpha)
    np.testing.assert_allclose(faces, expected, rtol=1e-5, atol=1e-8)


def test_phong_maps():
    lights = _scene()
    pos = (0.2, 0.3, -0.1)
    maps = lt.light_maps(lights, pos, diffuse_size=16, specular_size=16,
                         phong_exponents=(0, 1, 8, 200))
    total = _hand_irradiance(pos)[1].sum(axis=0)
    assert sorted(maps["phong"]) == [0.0, 1.0, 8.0, 200.0]
    for p, cube in maps["phong"].items():
        np.testing.assert_allclose(_integral(cube.faces), total, rtol=1e-3, err_msg=f"P={p}")
    # P = 1: (R.l) 2 / (2 pi) is the diffuse lobe
    np.testing.assert_allclose(maps["phong"][1.0].faces, maps["diffuse"].faces, rtol=1e-6,
                               atol=1e-7)
    # P = 0: a hemisphere of constant E / (2 pi)
    one = lt.light_maps(
        [lt.DirectionalLight((0, 0, -1), (1, 1, 1), 3.0)], (0, 0, 0), specular_size=8,
        phong_exponents=(0,),
    )["phong"][0.0].faces
    np.testing.assert_allclose(one[4], 3.0 / (2 * np.pi), rtol=1e-6)  # +Z face: facing light
    np.testing.assert_array_equal(one[5], 0.0)


def test_no_light_and_out_of_range_give_black_maps():
    far = lt.PointLight(position=(0, 0, 50), color=(1, 1, 1), intensity=100, range=10)
    for lights in ([], [far]):
        maps = lt.light_maps(lights, (0, 0, 0), specular_size=8, phong_exponents=(4,))
        assert not maps["diffuse"].faces.any()
        assert not any(a.any() for a in maps["specular"].levels)
        assert not maps["phong"][4.0].faces.any()


def test_light_maps_rejects_bad_arguments():
    with pytest.raises(ValueError):
        lt.light_maps(_scene(), (0, 0, 0), specular_size=12)  # not a power of two
    with pytest.raises(ValueError):
        lt.light_maps(_scene(), (0, 0, 0), specular_size=8, specular_levels=5)
    with pytest.raises(ValueError):
        lt.light_maps(_scene(), (0, 0, 0), phong_exponents=(-1,))
    with pytest.raises(ValueError):
        lt.light_maps(_scene(), (0, 0, np.nan))


# --------------------------------------------------------------------------------- splat_delta


def _edge_and_random_directions(count: int) -> np.ndarray:
    rng = np.random.default_rng(7)
    special = np.array(
        [
            [1.0, 1.0, 1.0],  # cube corner
            [-1.0, 1.0, -1.0],
            [1.0, 0.999, 0.3],  # just off an edge
            [1.0, 1.0, 0.2],  # exactly on an edge
            [0.0, 0.0, 1.0],  # face centre
            [0.5, -1.0, -1.0],
            [1.0, 0.97, 0.97],  # near a corner
        ]
    )
    return np.concatenate([special, rng.normal(size=(count, 3))])


@pytest.mark.parametrize("footprint", [0, 1, 2])
def test_splat_delta_preserves_irradiance_and_centroid(footprint):
    n = 8
    dirs = _edge_and_random_directions(60)
    rng = np.random.default_rng(3)
    e = rng.uniform(0.1, 5.0, size=(len(dirs), 3))
    w = texel_solid_angles(n)
    centres = texel_directions(n)
    texel_angle = 2.0 / n  # angular size of a face-centre texel
    zero = np.zeros((6, n, n, 3), np.float32)
    for d, ei in zip(dirs, e):
        out = lt.splat_delta(zero, d, ei, footprint=footprint)
        assert out.dtype == np.float32 and out.shape == zero.shape
        np.testing.assert_allclose(_integral(out), ei, rtol=1e-6)
        energy = out[..., 0] * w
        centroid = np.einsum("fij,fijk->k", energy, centres)
        cos = centroid @ d / (np.linalg.norm(centroid) * np.linalg.norm(d))
        angle = math.acos(min(1.0, cos))
        limit = 0.75 if footprint == 0 else 0.2  # nearest texel: up to half a diagonal
        assert angle < limit * texel_angle
        assert np.count_nonzero(out[..., 0]) <= max(1, (2 * footprint) ** 2)


def test_splat_delta_is_vectorised_additive_and_pure():
    n = 16
    rng = np.random.default_rng(5)
    base = rng.uniform(0, 1, size=(6, n, n, 3)).astype(np.float32)
    before = base.copy()
    dirs = rng.normal(size=(20, 3))
    e = rng.uniform(0, 2, size=(20, 3))
    together = lt.splat_delta(base, dirs, e)
    np.testing.assert_array_equal(base, before)  # input untouched
    one_by_one = base
    for d, ei in zip(dirs, e):
        one_by_one = lt.splat_delta(one_by_one, d, ei)
    np.testing.assert_allclose(together, one_by_one, rtol=1e-5)
    np.testing.assert_allclose(_integral(together) - _integral(base), e.sum(axis=0), rtol=1e-5)
    # one irradiance for every light broadcasts
    same = lt.splat_delta(np.zeros_like(base), dirs, np.ones(3))
    np.testing.assert_allclose(_integral(same), [20.0] * 3, rtol=1e-6)


def test_splat_delta_on_an_edge_is_shared_by_both_faces():
    n = 8
    out = lt.splat_delta(np.zeros((6, n, n, 1), np.float32), (1.0, 0.1, 1.0), [1.0])
    energy = out[..., 0] * texel_solid_angles(n)
    per_face = energy.sum(axis=(1, 2))
    assert per_face[0] == pytest.approx(0.5, rel=1e-5)  # +X
    assert per_face[4] == pytest.approx(0.5, rel=1e-5)  # +Z
    assert per_face.sum() == pytest.approx(1.0, rel=1e-6)


def test_splatted_cube_convolves_to_the_analytic_diffuse_map():
    lights = _scene()
    pos = (0.2, 0.3, -0.1)
    dirs, e, _ = lt.incident(lights, pos)
    cube = lt.splat_delta(np.zeros((6, 32, 32, 3), np.float32), dirs, e)
    # brute-force exact convolution at the 16^2 texel centres: sum L(w) max(0, N.w) dw / pi
    src = texel_directions(32).reshape(-1, 3)
    lw = cube.reshape(-1, 3).astype(np.float64) * texel_solid_angles(32).reshape(-1, 1)
    cos = np.maximum(texel_directions(16).reshape(-1, 3) @ src.T, 0.0)
    conv = (cos @ lw).reshape(6, 16, 16, 3) / np.pi
    analytic = lt.light_maps(lights, pos, diffuse_size=16, specular_size=1)["diffuse"].faces
    # relative to the largest value a diffuse map of these lights can reach
    err = np.abs(conv - analytic) / (e.sum(axis=0) / np.pi)
    # The splat spreads each light over ~1 source texel (0.06 rad): second order in the smooth
    # part of the cosine, first order where a light grazes the normal (the clamp's kink).
    smooth = np.all(np.abs(texel_directions(16) @ dirs.T) > 0.15, axis=-1)
    assert err[smooth].max() < 1e-3
    assert err.max() < 1e-2


@pytest.mark.parametrize(
    "kwargs",
    [
        {"footprint": -1},
        {"footprint": 1.5},
        {"footprint": True},
        {"footprint": 9},
    ],
)
def test_splat_delta_rejects_bad_footprint(kwargs):
    with pytest.raises(ValueError):
        lt.splat_delta(np.zeros((6, 8, 8, 3)), (0, 0, 1), (1, 1, 1), **kwargs)


def test_splat_delta_rejects_bad_lights():
    z = np.zeros((6, 4, 4, 3))
    with pytest.raises(ValueError):
        lt.splat_delta(z, (0, 0, 0), (1, 1, 1))
    with pytest.raises(ValueError):
        lt.splat_delta(z, (0, np.nan, 1), (1, 1, 1))
    with pytest.raises(ValueError):
        lt.splat_delta(z, np.ones((3, 3)), np.ones((2, 3)))
    with pytest.raises(ValueError):
        lt.splat_delta(z, (0, 0, 1), (1, 1))
    with pytest.raises(ValueError):
        lt.splat_delta(np.zeros((5, 4, 4, 3)), (0, 0, 1), (1, 1, 1))
