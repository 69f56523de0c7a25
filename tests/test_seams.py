"""Tests of the cube-edge topology, bordered faces and seam export modes (probegrid.core.seams)."""

import numpy as np
import pytest

from probegrid.core import cubemap as cm
from probegrid.core import seams

SIZES = [1, 2, 3, 4, 5, 8]


def _random_cube(n, c=3, seed=0):
    return np.random.default_rng(seed).random((6, n, n, c)).astype(np.float32)


def _ring_mask(n):
    m = n + 2
    k = np.arange(m)
    on_r = (k[:, None] == 0) | (k[:, None] == m - 1)
    on_c = (k[None, :] == 0) | (k[None, :] == m - 1)
    return on_r ^ on_c, on_r & on_c  # edge border, corner border


def _edge_pairs(n):
    """(target, source) real-texel triples (face, row, col) of every edge border texel."""
    f, r, c = seams.border_sources(n)
    m = n + 2
    edge, _ = _ring_mask(n)
    rr, cc = np.nonzero(edge)
    out_t, out_s = [], []
    for face in range(6):
        tr = np.clip(rr, 1, m - 2) - 1
        tc = np.clip(cc, 1, m - 2) - 1
        out_t.append(np.stack([np.full_like(tr, face), tr, tc], -1))
        out_s.append(np.stack([f[face, rr, cc, 0], r[face, rr, cc, 0], c[face, rr, cc, 0]], -1))
    return np.concatenate(out_t), np.concatenate(out_s)


@pytest.mark.parametrize("n", range(1, 65))
def test_border_sources_are_adjacent_edge_texels(n):
    f, r, c = seams.border_sources(n)
    assert f.shape == r.shape == c.shape == (6, n + 2, n + 2, 3)
    assert not f.flags.writeable
    assert r.min() >= 0 and r.max() < n and c.min() >= 0 and c.max() < n
    # interior copies itself
    inner = (slice(None), slice(1, -1), slice(1, -1))
    np.testing.assert_array_equal(f[inner], np.broadcast_to(np.arange(6)[:, None, None, None],
                                                            f[inner].shape))
    np.testing.assert_array_equal(r[inner], np.broadcast_to(np.arange(n)[:, None, None],
                                                            r[inner].shape))
    np.testing.assert_array_equal(c[inner], np.broadcast_to(np.arange(n)[:, None], c[inner].shape))
    t, s = _edge_pairs(n)
    # the source is on another face, on that face's edge
    assert np.all(s[:, 0] != t[:, 0])
    assert np.all((s[:, 1] == 0) | (s[:, 1] == n - 1) | (s[:, 2] == 0) | (s[:, 2] == n - 1))
    # adjacency is symmetric: the set of (target, source) pairs equals its transpose
    key = lambda a: (a[:, 0] * n + a[:, 1]) * n + a[:, 2]
    pairs = set(zip(key(t).tolist(), key(s).tolist(), strict=True))
    assert pairs == {(b, a) for a, b in pairs}
    # every non-corner edge texel has exactly one neighbour across the edge
    if n >= 3:
        counts = np.bincount(key(t), minlength=6 * n * n).reshape(6, n, n)
        assert np.all(counts[:, 0, 1:-1] == 1) and np.all(counts[:, 1:-1, 1:-1] == 0)
    # the two texel centres are about one texel apart on the sphere
    d = cm.texel_directions(n)
    ang = np.arccos(np.clip(np.sum(d[tuple(t.T)] * d[tuple(s.T)], -1), -1, 1))
    assert ang.max() < 2.0 / n  # one texel spacing in uv is 2 / n


@pytest.mark.parametrize("n", [1, 2, 3, 7, 16, 63, 64, 255])
def test_projection_never_lands_near_a_texel_boundary(n):
    # The floor in the derivation is at least 1 / (2 (n + 1)) away from an integer.
    edge, _ = _ring_mask(n)
    rr, cc = np.nonzero(edge)
    for face in range(6):
        u = cm.texel_to_uv(cc - 1, n)
        v = cm.texel_to_uv(rr - 1, n)
        _, gu, gv = cm.direction_to_face_uv(cm.face_uv_to_direction(face, u, v))
        for g in (gu, gv):
            x = (g + 1.0) * 0.5 * n
            frac = np.abs(x - np.round(x))
            assert frac.min() >= 1.0 / (2 * (n + 1)) - 1e-9


def test_known_neighbours_of_plus_z():
    # From the horizontal cross: +Z's right neighbour is +X, left is -X, top is +Y, bottom -Y.
    n = 4
    f, r, c = seams.border_sources(n)
    k = np.arange(1, n + 1)
    np.testing.assert_array_equal(f[4, k, n + 1, 0], 0)  # right border -> +X
    np.testing.assert_array_equal(c[4, k, n + 1, 0], 0)  # ... its left column
    np.testing.assert_array_equal(r[4, k, n + 1, 0], k - 1)  # same row
    np.testing.assert_array_equal(f[4, k, 0, 0], 1)  # left border -> -X
    np.testing.assert_array_equal(c[4, k, 0, 0], n - 1)
    np.testing.assert_array_equal(f[4, 0, k, 0], 2)  # top border -> +Y bottom row
    np.testing.assert_array_equal(r[4, 0, k, 0], n - 1)
    np.testing.assert_array_equal(c[4, 0, k, 0], k - 1)
    np.testing.assert_array_equal(f[4, n + 1, k, 0], 3)  # bottom border -> -Y top row
    np.testing.assert_array_equal(r[4, n + 1, k, 0], 0)
    # +Y's top row borders -Z's top row, reversed (u of -Z runs along -X)
    np.testing.assert_array_equal(f[2, 0, k, 0], 5)
    np.testing.assert_array_equal(r[2, 0, k, 0], 0)
    np.testing.assert_array_equal(c[2, 0, k, 0], n - k)


@pytest.mark.parametrize("n", SIZES)
def test_corner_sources_are_the_three_texels_nearest_the_cube_corner(n):
    f, r, c = seams.border_sources(n)
    d = cm.texel_directions(n).reshape(-1, 3)
    m = n + 2
    for face in range(6):
        for rb, cb in ((0, 0), (0, m - 1), (m - 1, 0), (m - 1, m - 1)):
            src = {(int(f[face, rb, cb, j]), int(r[face, rb, cb, j]), int(c[face, rb, cb, j]))
                   for j in range(3)}
            assert len(src) == 3 and len({s[0] for s in src}) == 3
            corner = np.sign(cm.face_uv_to_direction(face, cm.texel_to_uv(cb - 1, n),
                                                     cm.texel_to_uv(rb - 1, n)))
            nearest = np.argsort(-(d @ corner))[:3]
            want = {tuple(int(x) for x in np.unravel_index(i, (6, n, n))) for i in nearest}
            assert src == want


@pytest.mark.parametrize("n", SIZES)
def test_add_border_copies_neighbours_and_averages_corners(n):
    a = _random_cube(n, 2, seed=n)
    b = seams.add_border(a)
    assert b.shape == (6, n + 2, n + 2, 2) and b.dtype == np.float32
    np.testing.assert_array_equal(b[:, 1:-1, 1:-1], a)
    f, r, c = seams.border_sources(n)
    edge, corner = _ring_mask(n)
    np.testing.assert_array_equal(b[:, edge], a[f[:, edge, 0], r[:, edge, 0], c[:, edge, 0]])
    mean3 = a[f[:, corner], r[:, corner], c[:, corner]].astype(np.float64).mean(axis=-2)
    np.testing.assert_allclose(b[:, corner], mean3, rtol=1e-6)


def test_add_border_of_constant_and_of_3d_input():
    b = seams.add_border(np.full((6, 3, 3), 2.5))
    assert b.shape == (6, 5, 5, 1)
    np.testing.assert_array_equal(b, 2.5)


@pytest.mark.parametrize("n", SIZES)
def test_average_seams_makes_every_edge_pair_equal(n):
    a = _random_cube(n, 3, seed=10 + n)
    avg = seams.average_seams(a)
    assert avg.shape == a.shape and avg.dtype == np.float32
    t, s = _edge_pairs(n)
    np.testing.assert_array_equal(avg[tuple(t.T)], avg[tuple(s.T)])  # bit-equal
    assert seams.seam_score(avg) == 0.0
    # interior texels are untouched
    np.testing.assert_array_equal(avg[:, 1:-1, 1:-1], a[:, 1:-1, 1:-1])
    # the bordered averaged cube has no jump between a border texel and the texel inside it
    b = seams.add_border(avg)
    np.testing.assert_array_equal(b[:, 0, 1:-1], b[:, 1, 1:-1])
    np.testing.assert_array_equal(b[:, 1:-1, -1], b[:, 1:-1, -2])


def test_average_seams_values():
    n = 4
    a = _random_cube(n, 1, seed=3).astype(np.float64)
    avg = seams.average_seams(a)
    f, r, c = seams.border_sources(n)
    # non-corner edge texel: mean of itself and its neighbour
    src = (f[4, 0, 2, 0], r[4, 0, 2, 0], c[4, 0, 2, 0])
    np.testing.assert_allclose(avg[4, 0, 1], 0.5 * (a[4, 0, 1] + a[src]), rtol=1e-6)
    # corner texel: mean of the three at the cube corner
    three = a[f[4, 0, 0], r[4, 0, 0], c[4, 0, 0]]
    np.testing.assert_allclose(avg[4, 0, 0], three.mean(axis=0), rtol=1e-6)
    # n = 1: every face touches four others, so all become the mean
    one = np.arange(6, dtype=np.float32).reshape(6, 1, 1, 1)
    np.testing.assert_allclose(seams.average_seams(one), 2.5)


def test_average_seams_barely_changes_a_smooth_cube():
    n = 32
    d = cm.texel_directions(n).astype(np.float32)
    avg = seams.average_seams(d)
    assert np.abs(avg - d).max() < 1.0 / n


def test_seam_score():
    assert seams.seam_score(np.zeros((6, 4, 4, 3))) == 0.0
    assert seams.seam_score(np.full((6, 4, 4, 3), 7.0)) == 0.0
    # independent faces: a different constant per face -> large score
    per_face = np.arange(1, 7, dtype=np.float32)[:, None, None, None] * np.ones((6, 8, 8, 3))
    assert seams.seam_score(per_face) > 0.3
    # a smooth function of direction: small score, of the order of one texel's variation
    n = 64
    smooth = cm.texel_directions(n).astype(np.float32) + 2.0
    assert 0.0 < seams.seam_score(smooth) < 2.0 / n
    assert seams.seam_score(seams.average_seams(_random_cube(5))) == 0.0
    assert np.isnan(seams.seam_score(np.full((6, 2, 2, 1), np.nan)))


def test_apply_seam_mode():
    chain = [_random_cube(8, seed=1), _random_cube(4, seed=2), _random_cube(2, seed=3),
             _random_cube(1, seed=4)]
    none = seams.apply_seam_mode(chain, "none")
    assert [x.shape for x in none] == [x.shape for x in chain]
    for x, y in zip(none, chain, strict=True):
        np.testing.assert_array_equal(x, y)
        assert x is not y
    avg = seams.apply_seam_mode(chain, "average")
    assert all(seams.seam_score(x) == 0.0 for x in avg)
    bord = seams.apply_seam_mode(chain, "border")
    assert [x.shape[1] for x in bord] == [10, 6, 4, 3]
    np.testing.assert_array_equal(bord[1], seams.add_border(chain[1]))
    assert seams.SEAM_MODES == ("none", "average", "border")


def test_apply_seam_mode_rejects_bad_arguments():
    with pytest.raises(ValueError, match="none, average, border"):
        seams.apply_seam_mode([_random_cube(2)], "clamp")
    with pytest.raises(ValueError, match="sequence"):
        seams.apply_seam_mode(_random_cube(2), "none")
    with pytest.raises(ValueError, match="shape"):
        seams.add_border(np.zeros((5, 2, 2, 3)))
    with pytest.raises(ValueError, match="positive integer"):
        seams.border_sources(0)
