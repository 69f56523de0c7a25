"""Tests of seamless cube-map sampling, mip chains and resizing (probegrid.core.sampling)."""

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from probegrid.core import cubemap as cm
from probegrid.core import sampling as smp
from probegrid.core import seams

CORNERS = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))


def _random_cube(n, c=3, seed=0):
    return np.random.default_rng(seed).random((6, n, n, c)).astype(np.float32)


def _random_dirs(k, seed=0):
    return np.random.default_rng(seed).normal(size=(k, 3))


def _special_dirs():
    """Face centres, the 8 cube corners, and points on all 12 edges (incl. their midpoints)."""
    t = np.linspace(-1.0, 1.0, 9)
    edges = []
    for axis in range(3):
        a, b = [i for i in range(3) if i != axis]
        for sa, sb in itertools.product((-1.0, 1.0), repeat=2):
            p = np.zeros((t.size, 3))
            p[:, axis] = t
            p[:, a] = sa
            p[:, b] = sb
            edges.append(p)
    return np.concatenate([cm.FACE_NORMALS, CORNERS, *edges])


def _reference_bilinear(faces, dirs):
    """Float64 bilinear lookup on the bordered faces, written directly from the conventions."""
    b = seams.add_border(faces).astype(np.float64)
    n = faces.shape[1]
    f, u, v = cm.direction_to_face_uv(dirs)
    x = cm.uv_to_texel(u, n) + 1.0
    y = cm.uv_to_texel(v, n) + 1.0
    x0 = np.floor(x).astype(int)
    y0 = np.floor(y).astype(int)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    top = b[f, y0, x0] * (1 - fx) + b[f, y0, x0 + 1] * fx
    bot = b[f, y0 + 1, x0] * (1 - fx) + b[f, y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bot * fy


# -- basic lookups ----------------------------------------------------------------------------

@pytest.mark.parametrize("n", [1, 2, 5, 16])
def test_constant_cube_everywhere(n):
    value = np.array([0.25, 3.0, 1e4], dtype=np.float32)
    s = smp.CubeSampler(smp.mip_chain(np.broadcast_to(value, (6, n, n, 3)), levels=1))
    d = np.concatenate([_random_dirs(5000, seed=n), _special_dirs()])
    for out in (s.bilinear(d), s.nearest(d), s.trilinear(d, 0.3)):
        assert out.shape == (d.shape[0], 3) and out.dtype == np.float32
        np.testing.assert_allclose(out, np.broadcast_to(value, out.shape), rtol=1e-6)


@pytest.mark.parametrize("n", [1, 3, 8, 32])
def test_matches_float64_reference(n):
    faces = _random_cube(n, 2, seed=n)
    d = np.concatenate([_random_dirs(20000, seed=1), _special_dirs()])
    np.testing.assert_allclose(smp.sample_bilinear(faces, d), _reference_bilinear(faces, d),
                               atol=2e-5)


def test_interior_lookup_is_plain_bilinear_of_the_face():
    # A point well inside +Z, spelled out by hand: u = 0.1, v = -0.3 on an 8 x 8 face.
    n = 8
    faces = _random_cube(n, 1, seed=4).astype(np.float64)
    # x = (0.1 + 1) / 2 * n - 0.5 = 3.9, y = (-0.3 + 1) / 2 * n - 0.5 = 2.3
    f = faces[4, :, :, 0]
    want = (f[2, 3] * 0.1 * 0.7 + f[2, 4] * 0.9 * 0.7 + f[3, 3] * 0.1 * 0.3
            + f[3, 4] * 0.9 * 0.3)
    got = smp.sample_bilinear(faces, cm.face_uv_to_direction(4, 0.1, -0.3))
    np.testing.assert_allclose(got[0], want, rtol=1e-5)


@pytest.mark.parametrize("n", [4, 16, 64])
def test_linear_function_of_direction_is_reproduced(n):
    # Faces holding the unit direction itself; sampling must return ~ the normalised direction,
    # across edges and at the 8 corners too. The border copies the neighbour's edge texel, whose
    # centre is up to half a texel off the extended-plane position along the edge: O(1/n).
    faces = cm.texel_directions(n).astype(np.float32)
    d = np.concatenate([_random_dirs(50000, seed=n), _special_dirs()])
    unit = d / np.linalg.norm(d, axis=-1, keepdims=True)
    err = np.abs(smp.sample_bilinear(faces, d) - unit).max()
    assert err < 0.25 / n
    corner_err = np.abs(smp.sample_bilinear(faces, CORNERS) - CORNERS / np.sqrt(3)).max()
    assert corner_err < 0.5 / n**2
    # inside the faces, bilinear interpolation of a smooth function: O(1/n^2)
    _, u, v = cm.direction_to_face_uv(d)
    inner = (np.abs(u) < 1 - 2 / n) & (np.abs(v) < 1 - 2 / n)
    err_in = np.abs(smp.sample_bilinear(faces, d[inner]) - unit[inner]).max()
    assert err_in < 1.0 / n**2


def _edge_points(k, rng):
    """Points on the 12 cube edges and, for each, the two unit vectors into the two faces."""
    pts, into_a, into_b = [], [], []
    for axis in range(3):
        a, b = [i for i in range(3) if i != axis]
        for sa, sb in itertools.product((-1.0, 1.0), repeat=2):
            p = np.zeros((k, 3))
            p[:, axis] = rng.uniform(-1, 1, k)
            p[:, a] = sa
            p[:, b] = sb
            ea = np.zeros(3)
            ea[b] = -sb  # moving off the b-face plane stays on face a
            eb = np.zeros(3)
            eb[a] = -sa
            pts.append(p)
            into_a.append(np.broadcast_to(ea, p.shape))
            into_b.append(np.broadcast_to(eb, p.shape))
    return np.concatenate(pts), np.concatenate(into_a), np.concatenate(into_b)


@pytest.mark.parametrize("n", [1, 2, 7, 32])
def test_continuous_across_every_edge_and_corner(n):
    rng = np.random.default_rng(n)
    s = smp.CubeSampler(_random_cube(n, 3, seed=n))
    p, ea, eb = _edge_points(200, rng)
    eps = 1e-5
    va, vb, v0 = s.bilinear(p + eps * ea), s.bilinear(p + eps * eb), s.bilinear(p)
    # texel values are in [0, 1]; the gradient is at most ~ n per unit uv
    assert np.abs(va - vb).max() < 4 * eps * (n + 1)
    assert np.abs(va - v0).max() < 4 * eps * (n + 1)
    # corners: approach from inside each of the three faces
    for c in CORNERS:
        vals = []
        for axis in range(3):
            d = c.copy()
            others = [i for i in range(3) if i != axis]
            d[others] -= eps * c[others]  # stays on the face of `axis`
            vals.append(s.bilinear(d))
        assert np.ptp(np.stack(vals), axis=0).max() < 4 * eps * (n + 1)


def test_corner_value_is_mean_of_three_corner_texels():
    n = 5
    faces = _random_cube(n, 1, seed=7).astype(np.float64)
    got = smp.sample_bilinear(faces, CORNERS)[:, 0]
    d = cm.texel_directions(n).reshape(-1, 3)
    for c, g in zip(CORNERS, got, strict=True):
        nearest3 = np.argsort(-(d @ c))[:3]
        np.testing.assert_allclose(g, faces.reshape(-1)[nearest3].mean(), rtol=1e-5)


def test_unnormalised_zero_nan_and_extreme_directions():
    s = smp.CubeSampler(_random_cube(8, 3, seed=2))
    d = _random_dirs(1000, seed=3)
    base = s.bilinear(d)
    for scale in (1e-30, 1e-3, 7.0, 1e6, 1e200):
        np.testing.assert_allclose(s.bilinear(d * scale), base, atol=2e-6)
    np.testing.assert_allclose(s.bilinear(d.astype(np.float32)), base, atol=2e-6)
    zero = s.bilinear(np.zeros(3))
    assert zero.shape == (3,) and np.all(np.isfinite(zero))
    bad = np.array([[np.nan, 0, 1], [np.inf, 1, 0], [1.0, 2.0, 3.0], [0, -np.inf, 0]])
    for out in (s.bilinear(bad), s.nearest(bad), s.trilinear(bad, 0)):
        assert np.all(np.isnan(out[[0, 1, 3]])) and np.all(np.isfinite(out[2]))
    # integer directions are accepted
    np.testing.assert_allclose(s.bilinear(np.array([0, 0, 3])), s.bilinear([0.0, 0.0, 1.0]))


def test_shapes_and_broadcasting():
    s = smp.CubeSampler(smp.mip_chain(_random_cube(8, 2)))
    d = _random_dirs(20, seed=5).reshape(4, 5, 3)
    assert s.bilinear(d).shape == (4, 5, 2)
    assert s.nearest(d[0]).shape == (5, 2)
    assert s.bilinear(d[0, 0]).shape == (2,)
    assert s.bilinear(np.zeros((0, 3))).shape == (0, 2)
    assert s.trilinear(d, np.linspace(0, 3, 5)).shape == (4, 5, 2)
    # lod with more dimensions than the directions broadcasts them
    out = s.trilinear(d[0], np.array([[0.0], [1.5], [3.0]]))
    assert out.shape == (3, 5, 2)
    np.testing.assert_allclose(out[1], s.trilinear(d[0], 1.5), rtol=1e-6)
    # more than one chunk
    big = _random_dirs(smp.CHUNK * 2 + 17, seed=6)
    np.testing.assert_allclose(s.bilinear(big)[-17:], s.bilinear(big[-17:]))


def test_bad_arguments():
    s = smp.CubeSampler(smp.mip_chain(_random_cube(4)))
    with pytest.raises(ValueError, match="shape"):
        s.bilinear(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="level"):
        s.bilinear(np.zeros(3), level=3)
    with pytest.raises(ValueError, match="level"):
        s.nearest(np.zeros(3), level=-1)
    with pytest.raises(ValueError, match="finite"):
        s.trilinear(np.zeros(3), np.nan)
    with pytest.raises(ValueError, match="broadcast"):
        s.trilinear(np.zeros((4, 3)), np.zeros(3))
    with pytest.raises(ValueError, match="channels"):
        smp.CubeSampler([_random_cube(4, 3), _random_cube(2, 1)])
    with pytest.raises(ValueError, match="CubeMap"):
        smp.CubeSampler([])


# -- nearest and texel ids (property tests) ---------------------------------------------------

direction = st.tuples(*[st.floats(-1e3, 1e3, allow_nan=False, width=32)] * 3).filter(
    lambda t: max(map(abs, t)) > 1e-6)


def _one_hot(n):
    return np.eye(6 * n * n, dtype=np.float32).reshape(6, n, n, 6 * n * n)


def _neighbourhood(n, face, row, col):
    """Real texel ids of the 3 x 3 bordered block around a texel (corners: all three)."""
    f, r, c = seams.border_sources(n)
    blk = (face, slice(row, row + 3), slice(col, col + 3))
    return set(((f[blk] * n + r[blk]) * n + c[blk]).ravel().tolist())


@settings(max_examples=300, deadline=None)
@given(d=direction, n=st.sampled_from([1, 2, 3, 4, 6]))
def test_lookups_of_texel_ids_stay_around_the_texel(d, n):
    d = np.array(d, dtype=np.float64)
    s = smp.CubeSampler(_one_hot(n))
    face, row, col = (int(x) for x in cm.direction_to_texel(d, n))
    around = _neighbourhood(n, face, row, col)
    w = s.bilinear(d).astype(np.float64)
    assert np.all(w >= -1e-6) and abs(w.sum() - 1.0) < 1e-5
    assert set(np.nonzero(w > 1e-6)[0].tolist()) <= around
    ids = np.nonzero(s.nearest(d))[0].tolist()
    assert len(ids) == 1 and ids[0] in around


def test_nearest_matches_direction_to_texel():
    n = 16
    ids = np.arange(6 * n * n, dtype=np.float32).reshape(6, n, n, 1)
    d = _random_dirs(20000, seed=9)
    got = smp.sample_nearest(ids, d)[:, 0].astype(int)
    f, r, c = cm.direction_to_texel(d, n)
    np.testing.assert_array_equal(got, (f * n + r) * n + c)


# -- trilinear ----------------------------------------------------------------------------------

def test_trilinear_levels_and_lerp():
    chain = smp.mip_chain(_random_cube(16, 3, seed=11))
    s = smp.CubeSampler(cm.CubeMap(tuple(chain)))
    d = np.concatenate([_random_dirs(3000, seed=12), _special_dirs()])
    for lv in range(s.num_levels):
        np.testing.assert_array_equal(s.trilinear(d, lv), s.bilinear(d, level=lv))
    half = 0.5 * (s.bilinear(d, level=1) + s.bilinear(d, level=2))
    np.testing.assert_allclose(s.trilinear(d, 1.5), half, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(s.trilinear(d, -3.0), s.bilinear(d, level=0))
    np.testing.assert_allclose(s.trilinear(d, 99.0), s.bilinear(d, level=4))
    # a per-direction lod: each direction lerps its own two levels
    lods = np.random.default_rng(13).uniform(-0.5, 4.5, d.shape[0])
    per_level = np.stack([s.bilinear(d, level=lv) for lv in range(5)])  # (5, m, 3)
    lc = np.clip(lods, 0, 4)
    l0 = np.floor(lc).astype(int)
    l1 = np.minimum(l0 + 1, 4)
    t = (lc - l0)[:, None]
    i = np.arange(d.shape[0])
    want = per_level[l0, i] * (1 - t) + per_level[l1, i] * t
    np.testing.assert_allclose(s.trilinear(d, lods), want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(s.trilinear(d, np.full(d.shape[0], 2.75)), s.trilinear(d, 2.75),
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(
        smp.sample_trilinear(chain, d[:10], 0.25),
        0.75 * s.bilinear(d[:10]) + 0.25 * s.bilinear(d[:10], level=1), rtol=1e-5, atol=1e-6)


# -- mip chains and resizing --------------------------------------------------------------------

def _weighted_mean(c):
    w = cm.texel_solid_angles(c.shape[1])[..., None]
    return (c.astype(np.float64) * w).sum(axis=(0, 1, 2)) / (4 * np.pi)


def test_mip_chain():
    a = _random_cube(8, 2)
    chain = smp.mip_chain(a)
    assert [x.shape[1] for x in chain] == [8, 4, 2, 1]
    np.testing.assert_array_equal(chain[0], a)
    np.testing.assert_array_equal(chain[2], cm.downsample(cm.downsample(a)))
    assert len(smp.mip_chain(a, levels=2)) == 2
    np.testing.assert_allclose(_weighted_mean(chain[-1]), _weighted_mean(a), rtol=1e-6)
    with pytest.raises(ValueError):
        smp.mip_chain(_random_cube(6))


@pytest.mark.parametrize("size", [1, 2, 3, 5, 7, 12, 13, 24, 31, 33, 48, 100])
def test_resample_preserves_energy(size):
    a = _random_cube(32, 3, seed=size)
    r = smp.resample(a, size)
    assert r.shape == (6, size, size, 3) and r.dtype == np.float32
    np.testing.assert_allclose(_weighted_mean(r), _weighted_mean(a), rtol=1e-3)


def test_resample_to_one_texel_gives_each_face_mean():
    w = cm.texel_solid_angles(16)[..., None]
    a = _random_cube(16, 3, seed=21)
    face_mean = (a * w).sum(axis=(1, 2)) / w.sum(axis=(1, 2))
    np.testing.assert_allclose(smp.resample(a, 1)[:, 0, 0], face_mean, rtol=1e-5)
    # non-power-of-two source: supersampled, smooth content -> close to the face means
    n = 12
    smooth = cm.texel_directions(n).astype(np.float32) + 1.5
    w = cm.texel_solid_angles(n)[..., None]
    face_mean = (smooth * w).sum(axis=(1, 2)) / w.sum(axis=(1, 2))
    np.testing.assert_allclose(smp.resample(smooth, 1)[:, 0, 0], face_mean, atol=0.01)


def test_resample_constant_identity_and_smooth():
    np.testing.assert_allclose(smp.resample(np.full((6, 8, 8, 3), 2.0), 5), 2.0, rtol=1e-6)
    a = _random_cube(8)
    same = smp.resample(a, 8)
    np.testing.assert_array_equal(same, a)
    assert same is not a
    np.testing.assert_array_equal(smp.resample(a, 2), cm.downsample(cm.downsample(a)))
    # a smooth function resized up and down lands on its values at the new texel centres
    for n_out in (7, 20, 45):
        got = smp.resample(cm.texel_directions(24).astype(np.float32), n_out)
        assert np.abs(got - cm.texel_directions(n_out)).max() < 0.02
    with pytest.raises(ValueError, match="positive integer"):
        smp.resample(a, 0)
