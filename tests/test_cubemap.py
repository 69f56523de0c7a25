"""Tests of the face table, texel geometry and solid angles (probegrid.core.cubemap)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from probegrid.core import cubemap as cm


def test_face_table_matches_khr_table():
    # The OpenGL / Vulkan / KTX2 table, spelled out independently of FACE_* arrays.
    u, v = 0.3, -0.7
    expected = {
        0: (1, -v, -u),
        1: (-1, -v, u),
        2: (u, 1, v),
        3: (u, -1, -v),
        4: (u, -v, 1),
        5: (-u, -v, -1),
    }
    for f, e in expected.items():
        np.testing.assert_allclose(cm.face_uv_to_direction(f, u, v), e)


def test_face_centres_and_names():
    d = cm.face_uv_to_direction(np.arange(6), 0.0, 0.0)
    np.testing.assert_array_equal(d, cm.FACE_NORMALS)
    assert cm.FACE_NAMES == ("+X", "-X", "+Y", "-Y", "+Z", "-Z")


@pytest.mark.parametrize(
    "direction, face, row, col",
    [
        # +Z face: top-left texel looks up-left (-X, +Y); u right = +X, v down = -Y
        ((-0.99, 0.99, 1.0), 4, 0, 0),
        ((0.99, -0.99, 1.0), 4, 3, 3),
        # +X face: u right = -Z, v down = -Y
        ((1.0, 0.99, 0.99), 0, 0, 0),
        # +Y face: u right = +X, v down = +Z (top row borders -Z)
        ((-0.99, 1.0, -0.99), 2, 0, 0),
        ((0.99, 1.0, 0.99), 2, 3, 3),
        # -Y face: v down = -Z (top row borders +Z)
        ((-0.99, -1.0, 0.99), 3, 0, 0),
        # -Z face: u right = -X
        ((0.99, 0.99, -1.0), 5, 0, 0),
        # -X face: u right = +Z
        ((-1.0, 0.99, -0.99), 1, 0, 0),
    ],
)
def test_known_directions_land_on_known_texels(direction, face, row, col):
    f, r, c = cm.direction_to_texel(np.array(direction), 4)
    assert (int(f), int(r), int(c)) == (face, row, col)


@pytest.mark.parametrize("n", [1, 2, 3, 7, 16, 128])
def test_texel_round_trip(n):
    d = cm.texel_directions(n)
    f, r, c = cm.direction_to_texel(d * 3.7, n)  # length does not matter
    F, R, C = np.meshgrid(np.arange(6), np.arange(n), np.arange(n), indexing="ij")
    assert (f == F).all() and (r == R).all() and (c == C).all()


@pytest.mark.parametrize("n", [1, 2, 5, 16, 64, 512])
def test_solid_angles_sum_to_4pi(n):
    w = cm.texel_solid_angles(n)
    assert w.shape == (6, n, n)
    assert abs(w.sum() / (4 * np.pi) - 1) < 1e-12
    assert (w > 0).all()


def test_solid_angle_matches_numeric_area_element():
    # Integrate (1 + u^2 + v^2)^(-3/2) over one texel of an 8^2 face with a fine grid.
    n, row, col = 8, 1, 6
    x, w = np.polynomial.legendre.leggauss(40)
    u0, u1 = cm.texel_to_uv(col - 0.5, n), cm.texel_to_uv(col + 0.5, n)
    v0, v1 = cm.texel_to_uv(row - 0.5, n), cm.texel_to_uv(row + 0.5, n)
    uu = 0.5 * (u1 - u0) * (x + 1) + u0
    vv = 0.5 * (v1 - v0) * (x + 1) + v0
    U, V = np.meshgrid(uu, vv)
    f = (1 + U**2 + V**2) ** -1.5
    num = f @ w @ w * 0.25 * (u1 - u0) * (v1 - v0)
    assert cm.texel_solid_angles(n)[2, row, col] == pytest.approx(num, rel=1e-12)


def test_normalization_cube():
    m = cm.normalization_cube(8)
    assert m.dtype == np.float32 and m.shape == (6, 8, 8, 3)
    np.testing.assert_allclose(np.linalg.norm(m, axis=-1), 1, atol=1e-6)
    e = cm.normalization_cube(8, encoded=True)
    assert e.min() >= 0 and e.max() <= 1
    np.testing.assert_allclose(e * 2 - 1, m, atol=1e-6)


def test_downsample_preserves_solid_angle_weighted_mean():
    rng = np.random.default_rng(0)
    a = rng.random((6, 16, 16, 3), dtype=np.float32)
    b = cm.downsample(a)
    w16 = cm.texel_solid_angles(16)[..., None]
    w8 = cm.texel_solid_angles(8)[..., None]
    np.testing.assert_allclose((b * w8).sum((0, 1, 2)), (a * w16).sum((0, 1, 2)), rtol=1e-6)


def test_cubemap_type_and_roughness():
    c = cm.CubeMap.from_faces(np.ones((6, 8, 8, 3)), kind="specular", mips=True)
    assert c.num_levels == 4 and [lv.shape[1] for lv in c.levels] == [8, 4, 2, 1]
    assert [c.roughness(k) for k in range(4)] == [0, 1 / 3, 2 / 3, 1]
    with pytest.raises(ValueError, match="shape"):
        cm.CubeMap((np.ones((5, 8, 8, 3)),))
    with pytest.raises(ValueError, match="positive integer"):
        cm.texel_directions(0)


@settings(max_examples=300, deadline=None)
@given(
    st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1),
)
def test_property_direction_face_uv_round_trip(x, y, z):
    d = np.array([x, y, z])
    if np.linalg.norm(d) < 1e-6:
        return
    f, u, v = cm.direction_to_face_uv(d)
    back = cm.face_uv_to_direction(f, u, v)
    back = back / np.linalg.norm(back)
    np.testing.assert_allclose(back, d / np.linalg.norm(d), atol=1e-9)
    assert -1 <= u <= 1 and -1 <= v <= 1


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 5), st.integers(1, 64), st.data())
def test_property_texel_round_trip(face, n, data):
    row = data.draw(st.integers(0, n - 1))
    col = data.draw(st.integers(0, n - 1))
    d = cm.face_uv_to_direction(face, cm.texel_to_uv(col, n), cm.texel_to_uv(row, n))
    assert tuple(int(a) for a in cm.direction_to_texel(d, n)) == (face, row, col)


def test_face_symmetries_carry_face_zero_onto_each_face():
    """S[f] maps +X's frame (normal, u, v) onto face f's, so texel (0, row, col) onto
    (f, row, col); its texel permutation is one (every texel hit once) and moves each centre
    to the mapped direction."""
    from probegrid.core.cubemap import face_symmetries, texel_permutation

    sym = face_symmetries()
    n = 8
    d = cm.texel_directions(n).reshape(-1, 3)
    for f in range(6):
        s = sym[f]
        assert np.array_equal(s @ cm.FACE_NORMALS[0], cm.FACE_NORMALS[f])
        assert np.array_equal(s @ cm.FACE_U[0], cm.FACE_U[f])
        assert np.array_equal(s @ cm.FACE_V[0], cm.FACE_V[f])
        perm = texel_permutation(s, n)
        assert np.array_equal(np.sort(perm), np.arange(6 * n * n))
        np.testing.assert_allclose(d[perm], d @ s.T, atol=1e-15)
        assert np.array_equal(perm[:n * n], np.arange(f * n * n, (f + 1) * n * n))
    mirror = np.diag([1.0, -1.0, 1.0])  # a reflection: +Y and -Y swap, v flips on the sides
    perm = texel_permutation(mirror, n)
    np.testing.assert_allclose(d[perm], d @ mirror, atol=1e-15)
    with pytest.raises(ValueError, match="signed permutation"):
        texel_permutation(np.eye(3) * 0.5, n)


@pytest.mark.parametrize("n", [1, 2, 5, 8])
def test_symmetry_group_permutes_texel_centres(n):
    """The 48 symmetries are the distinct signed permutation matrices, identity first; each
    one's texel map (index arithmetic) sends every texel centre to the mapped direction and is
    the map :func:`texel_permutation` gives for it."""
    group = cm.symmetry_group()
    assert group.shape == (48, 3, 3) and np.array_equal(group[0], np.eye(3))
    assert len({g.tobytes() for g in group}) == 48
    assert all(np.array_equal(g @ g.T, np.eye(3)) for g in group)
    perms = cm.symmetry_permutations(n)
    assert perms.shape == (48, 6 * n * n) and perms.dtype == np.int32
    d = cm.texel_directions(n).reshape(-1, 3)
    for k, g in enumerate(group):
        assert np.array_equal(np.sort(perms[k]), np.arange(6 * n * n))
        np.testing.assert_allclose(d[perms[k]], d @ g.T, atol=1e-15)
        assert np.array_equal(cm.texel_permutation(g, n), perms[k])
    for g in cm.face_symmetries():  # the six that carry face 0 onto each face belong to it
        assert any(np.array_equal(g, h) for h in group)
