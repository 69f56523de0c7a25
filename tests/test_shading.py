"""Tests of normal transforms, reflection and the two shading formulas (probegrid.core.shading)."""

import numpy as np
import pytest

from probegrid.core import shading as sh
from probegrid.core.cubemap import FACE_NORMALS, CubeMap
from probegrid.core.dfg import dfg_lookup, dfg_lut


@pytest.fixture(scope="module")
def lut():
    return dfg_lut(32)


def _constant(n: int, value, levels: int = 1) -> list[np.ndarray]:
    return [np.full((6, n >> k, n >> k, 3), value, np.float32) for k in range(levels)]


def _face_cube(n: int, scale: float = 1.0) -> np.ndarray:
    """Each face constant: face f holds (f + 1) * scale in every channel."""
    return np.broadcast_to(
        (np.arange(1, 7, dtype=np.float32) * scale)[:, None, None, None], (6, n, n, 3)
    ).copy()


# ------------------------------------------------------------------------------ normals, reflect


def test_transform_normals_non_uniform_scale_by_hand():
    m = np.diag([2.0, 1.0, 0.5])
    got = sh.transform_normals([1.0, 1.0, 1.0], m)
    np.testing.assert_allclose(got, [0.5, 1.0, 2.0], rtol=1e-15)  # diag(1/2, 1, 2), not renormed
    # with a shear: M = [[1, 1, 0], [0, 1, 0], [0, 0, 1]], M^-T = [[1, 0, 0], [-1, 1, 0], [0, 0, 1]]
    shear = np.array([[1.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(sh.transform_normals([0.0, 1.0, 0.0], shear), [0.0, 1.0, 0.0])
    np.testing.assert_allclose(sh.transform_normals([1.0, 0.0, 0.0], shear), [1.0, -1.0, 0.0])


def test_transform_normals_stay_perpendicular_and_handle_mirrors():
    rng = np.random.default_rng(0)
    m = rng.normal(size=(10, 3, 3))
    m[0] = np.diag([-1.0, 1.0, 1.0])  # mirror
    n = rng.normal(size=(10, 3))
    t = np.cross(n, rng.normal(size=(10, 3)))  # tangents, t . n = 0
    nw = sh.transform_normals(n, m)
    tw = np.einsum("...ij,...j->...i", m, t)
    np.testing.assert_allclose(np.einsum("...i,...i->...", nw, tw), 0.0, atol=1e-9)
    np.testing.assert_allclose(nw[0], n[0] * [-1.0, 1.0, 1.0])  # mirrored outward normal


def test_transform_normals_accepts_affine_4x4_and_broadcasts():
    m4 = np.eye(4)
    m4[:3, :3] = np.diag([4.0, 2.0, 1.0])
    m4[:3, 3] = [10.0, 20.0, 30.0]  # translation ignored
    normals = np.ones((2, 5, 3))
    got = sh.transform_normals(normals, m4)
    assert got.shape == (2, 5, 3)
    np.testing.assert_allclose(got, np.broadcast_to([0.25, 0.5, 1.0], (2, 5, 3)))


@pytest.mark.parametrize(
    "normals, matrix",
    [
        ([0.0, 0.0, 1.0], np.diag([1.0, 1.0, 0.0])),  # singular
        ([0.0, 0.0, 1.0], np.ones((2, 2))),
        ([0.0, np.nan, 1.0], np.eye(3)),
        ([0.0, 0.0, 1.0], np.diag([1.0, np.inf, 1.0])),
    ],
)
def test_transform_normals_rejects(normals, matrix):
    with pytest.raises(ValueError):
        sh.transform_normals(normals, matrix)


def test_reflect_convention():
    # V from the surface to the eye; R = 2 (N.V) N - V with N normalised
    r = sh.reflect([1.0, 1.0, 0.0], [0.0, 5.0, 0.0])
    np.testing.assert_allclose(r, [-1.0, 1.0, 0.0])
    rng = np.random.default_rng(1)
    v = rng.normal(size=(100, 3))
    n = rng.normal(size=(100, 3))
    r = sh.reflect(v, n)
    nu = n / np.linalg.norm(n, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.linalg.norm(r, axis=-1), np.linalg.norm(v, axis=-1))
    np.testing.assert_allclose(np.sum(r * nu, -1), np.sum(v * nu, -1), atol=1e-12)
    np.testing.assert_allclose(np.cross(r + v, nu), 0.0, atol=1e-12)
    assert sh.reflect(np.zeros((4, 1, 3)) + [0, 0, 1], np.ones((3, 3))).shape == (4, 3, 3)
    with pytest.raises(ValueError):
        sh.reflect([0.0, 0.0, 1.0], [0.0, 0.0, 0.0])


# ------------------------------------------------------------------------------------- classic


def test_classic_constant_environment():
    diffuse = _constant(8, 2.0)[0]
    specular = CubeMap.from_faces(_constant(16, 3.0)[0], mips=True)
    rng = np.random.default_rng(2)
    n = rng.normal(size=(7, 3))
    albedo = np.array([0.2, 0.5, 1.0])
    gloss = np.linspace(0, 1, 7)
    out = sh.shade_classic(n, diffuse=diffuse, specular=specular, albedo=albedo, gloss=gloss)
    assert out.shape == (7, 3) and out.dtype == np.float32
    np.testing.assert_allclose(out, 2.0 * albedo + 3.0 * gloss[:, None], rtol=1e-6)


def test_classic_looks_up_diffuse_at_n_and_specular_at_r_or_n():
    diffuse = _face_cube(4)
    specular = _face_cube(4, 10.0)
    # no view: both at N; N scaled (implicit normalisation)
    out = sh.shade_classic(FACE_NORMALS * 3.7, diffuse=diffuse, specular=specular,
                           albedo=np.ones(3), gloss=np.ones(6))
    np.testing.assert_allclose(out[:, 0], np.arange(1, 7) * 11.0, rtol=1e-6)
    # with a view: N = (1, 0, 1)/sqrt2, V = +Z -> R = +X (face 0); N lands on the +X/+Z edge
    out = sh.shade_classic([1.0, 0.0, 1.0], diffuse=diffuse, specular=specular,
                           albedo=np.zeros(3), gloss=1.0, views=[0.0, 0.0, 2.0])
    np.testing.assert_allclose(out, [10.0] * 3, rtol=1e-6)


def test_classic_scaled_normals_shade_the_same():
    rng = np.random.default_rng(3)
    diffuse = rng.uniform(0, 1, size=(6, 8, 8, 3)).astype(np.float32)
    specular = rng.uniform(0, 1, size=(6, 8, 8, 3)).astype(np.float32)
    n = rng.normal(size=(50, 3))
    v = rng.normal(size=(50, 3))
    kw = {"diffuse": diffuse, "specular": specular, "albedo": [0.3, 0.6, 0.9], "gloss": 0.5}
    a = sh.shade_classic(n, views=v, **kw)
    b = sh.shade_classic(n * rng.uniform(0.1, 10, size=(50, 1)), views=v, **kw)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    # a normal transformed by a scaled matrix (not renormalised) shades like the unit normal
    m = np.diag([3.0, 0.2, 1.5])
    nw = sh.transform_normals(n, m)
    unit = nw / np.linalg.norm(nw, axis=-1, keepdims=True)
    np.testing.assert_allclose(sh.shade_classic(nw, views=v, **kw),
                               sh.shade_classic(unit, views=v, **kw), rtol=1e-5, atol=1e-6)


def test_classic_broadcasts_and_rejects():
    d = _constant(4, 1.0)[0]
    out = sh.shade_classic(np.ones((4, 1, 3)), diffuse=d, specular=d,
                           albedo=np.ones((1, 5, 3)), gloss=np.zeros((4, 5)))
    assert out.shape == (4, 5, 3)
    with pytest.raises(ValueError):
        sh.shade_classic([0.0, np.nan, 1.0], diffuse=d, specular=d, albedo=np.ones(3), gloss=1)
    with pytest.raises(ValueError):
        sh.shade_classic([0.0, 0.0, 0.0], diffuse=d, specular=d, albedo=np.ones(3), gloss=1)
    with pytest.raises(ValueError):
        sh.shade_classic(np.ones((4, 3)), diffuse=d, specular=d, albedo=np.ones((5, 3)),
                         gloss=1)
    with pytest.raises(ValueError):
        sh.shade_classic([0.0, 0.0, 1.0], diffuse=d, specular=d[..., :1], albedo=np.ones(3),
                         gloss=1)


# ----------------------------------------------------------------------------------- split sum


def _random_inputs(count: int, seed: int = 4):
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(count, 3))
    v = rng.normal(size=(count, 3))
    v *= np.sign(np.sum(n * v, -1))[:, None]  # views in front of the surface
    return n, v, rng


def test_split_sum_white_furnace(lut):
    # constant environment L, albedo 1: energy removed from the diffuse term by the specular
    # layer is exactly what the specular term returns, so the result is L for any F0, roughness
    # and view.
    L = 1.7
    n, v, rng = _random_inputs(200)
    out = sh.shade_split_sum(
        n, v, albedo=np.ones(3), roughness=rng.uniform(0, 1, 200),
        f0=rng.uniform(0, 1, (200, 3)), diffuse=_constant(8, L)[0],
        specular_levels=_constant(32, L, levels=6), dfg=lut,
    )
    assert out.shape == (200, 3) and out.dtype == np.float32
    np.testing.assert_allclose(out, L, rtol=1e-5)


def test_split_sum_without_diffuse_reduction_adds_the_specular_energy(lut):
    L = 2.0
    n, v, rng = _random_inputs(50)
    r = rng.uniform(0, 1, 50)
    f0 = np.full(3, 0.04)
    out = sh.shade_split_sum(
        n, v, albedo=np.ones(3), roughness=r, f0=f0, diffuse=_constant(8, L)[0],
        specular_levels=_constant(16, L, levels=5), dfg=lut, reduce_diffuse=False,
    )
    nu = n / np.linalg.norm(n, axis=-1, keepdims=True)
    vu = v / np.linalg.norm(v, axis=-1, keepdims=True)
    ab = np.asarray(dfg_lookup(lut, np.clip(np.sum(nu * vu, -1), 0, 1), r))
    expected = L * (1.0 + 0.04 * ab[..., 0] + ab[..., 1])
    np.testing.assert_allclose(out[:, 0], expected, rtol=1e-5)


def test_split_sum_smooth_mirror_is_schlick_fresnel(lut):
    # roughness 0: (A, B) -> (1 - (1 - N.V)^5, (1 - N.V)^5), so a black-albedo surface in a
    # constant environment reflects L (F0 + (1 - F0)(1 - N.V)^5), Schlick's Fresnel.
    L = 1.0
    cos_v = np.array([1.0, 0.8, 0.5, 0.3])
    v = np.stack([np.sqrt(1 - cos_v**2), np.zeros(4), cos_v], -1)
    f0 = np.array([0.04, 0.5, 1.0])
    out = sh.shade_split_sum(
        [0.0, 0.0, 1.0], v, albedo=np.zeros(3), roughness=0.0, f0=f0,
        diffuse=_constant(4, L)[0], specular_levels=_constant(16, L, levels=5), dfg=lut,
    )
    schlick = f0 + (1 - f0) * (1 - cos_v[:, None]) ** 5
    np.testing.assert_allclose(out, L * schlick, atol=0.02)


def test_split_sum_samples_the_chain_at_the_roughness_lod_and_reflection(lut):
    levels = 5
    # level k constant (k + 1): Prefiltered[R, lod] = lod + 1 exactly (trilinear)
    chain = [np.full((6, 16 >> k, 16 >> k, 3), k + 1.0, np.float32) for k in range(levels)]
    r = np.array([0.0, 0.1, 0.5, 0.8, 1.0])
    out = sh.shade_split_sum(
        [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], albedo=np.zeros(3), roughness=r, f0=np.ones(3),
        diffuse=_constant(4, 0.0)[0], specular_levels=chain, dfg=lut,
    )
    ab = np.asarray(dfg_lookup(lut, np.ones(5), r))
    expected = (r * (levels - 1) + 1.0) * (ab[..., 0] + ab[..., 1])
    np.testing.assert_allclose(out[:, 0], expected, rtol=1e-5)
    # direction: N = (1, 0, 1)/sqrt2, V = +Z: R = +X, so the +X face of level 0 is seen
    spec = [_face_cube(8), _face_cube(4)]
    out = sh.shade_split_sum(
        [1.0, 0.0, 1.0], [0.0, 0.0, 1.0], albedo=np.zeros(3), roughness=0.0, f0=np.ones(3),
        diffuse=_constant(4, 0.0)[0], specular_levels=spec, dfg=lut,
    )
    ab = np.asarray(dfg_lookup(lut, np.sqrt(0.5), 0.0))
    np.testing.assert_allclose(out, 1.0 * (ab[0] + ab[1]), rtol=1e-5)


def test_split_sum_diffuse_at_n_and_broadcasting(lut):
    diffuse = _face_cube(4)
    out = sh.shade_split_sum(
        FACE_NORMALS[:, None, :] * 2.0, FACE_NORMALS[:, None, :], albedo=np.ones((1, 3, 3)),
        roughness=np.array([0.2, 0.5, 0.9]), f0=np.zeros(3), diffuse=diffuse,
        specular_levels=_constant(8, 0.0, levels=4), dfg=lut, reduce_diffuse=False,
    )
    assert out.shape == (6, 3, 3)
    np.testing.assert_allclose(out[..., 0], np.arange(1, 7)[:, None] * np.ones(3), rtol=1e-6)


def test_split_sum_rejects(lut):
    kw = {"albedo": np.ones(3), "f0": np.ones(3), "diffuse": _constant(4, 1.0)[0],
          "specular_levels": _constant(8, 1.0, 4), "dfg": lut}
    with pytest.raises(ValueError):
        sh.shade_split_sum([0, 0, 1], [0, 0, 1], roughness=1.5, **kw)
    with pytest.raises(ValueError):
        sh.shade_split_sum([0, 0, 1], [0, 0, 1], roughness=np.nan, **kw)
    with pytest.raises(ValueError):
        sh.shade_split_sum([0, 0, 1], [0, 0, 0], roughness=0.5, **kw)
    with pytest.raises(ValueError):
        sh.shade_split_sum([0, np.inf, 1], [0, 0, 1], roughness=0.5, **kw)
