"""Tests of environment layouts and anti-aliased resampling (probegrid.core.layouts)."""

import numpy as np
import pytest

from probegrid.core import cubemap as cm
from probegrid.core import layouts as L
from probegrid.core.sampling import sample_bilinear

ALL = ("equirect", "angular", "hcross", "vcross", "faces")


def _angle(a, b):
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.arccos(np.clip((a * b).sum(-1), -1, 1))


def _solid_angle_mean(cube):
    w = cm.texel_solid_angles(cube.shape[1])[..., None]
    return (cube.astype(np.float64) * w).sum((0, 1, 2)) / (4 * np.pi)


def _equirect_row_weights(h):
    edges = np.pi * (0.5 - np.arange(h + 1) / h)
    return np.sin(edges[:-1]) - np.sin(edges[1:])  # solid angle per pixel / dphi


def _equirect_mean(img):
    w = _equirect_row_weights(img.shape[0])[:, None, None]
    return (img.astype(np.float64) * w).sum((0, 1)) / (w.sum() * img.shape[1])


def _smooth(d):
    """A smooth, positive, direction-dependent RGB radiance."""
    a = np.array([0.3, 0.5, -0.8])
    return (np.exp(2.0 * d @ a)[..., None] * np.array([1.0, 0.5, 0.25])).astype(np.float32)


# ---------------------------------------------------------------- orientation


def test_equirect_orientation_matches_stated_convention():
    h, w = 8, 16
    cases = {  # direction: (column, row) continuous pixel coordinate
        (1, 0, 0): (w / 2 - 0.5, h / 2 - 0.5),  # centre column = +X
        (0, 0, 1): (3 * w / 4 - 0.5, h / 2 - 0.5),  # a quarter to the right = +Z
        (0, 0, -1): (w / 4 - 0.5, h / 2 - 0.5),
        (-1, 0, 0): (w - 0.5, h / 2 - 0.5),  # the right (= left, wrapped) edge
        (0, 1, 0): (w / 2 - 0.5, -0.5),  # top edge = +Y
        (0, -1, 0): (w / 2 - 0.5, h - 0.5),
    }
    for d, (x, y) in cases.items():
        gx, gy = L.direction_to_equirect(np.array(d, float), h, w)
        assert (gx, gy) == pytest.approx((x, y), abs=1e-12), d
    # pixel (row 1, column 13): phi = 2 pi (13.5 / 16 - 0.5), theta = pi (0.5 - 1.5 / 8)
    phi, theta = 2 * np.pi * (13.5 / 16 - 0.5), np.pi * (0.5 - 1.5 / 8)
    expected = [np.cos(phi) * np.cos(theta), np.sin(theta), np.sin(phi) * np.cos(theta)]
    np.testing.assert_allclose(L.equirect_directions(h, w)[1, 13], expected, atol=1e-15)
    d = L.equirect_directions(h, w)
    x, y = L.direction_to_equirect(d, h, w)
    np.testing.assert_allclose(x, np.broadcast_to(np.arange(w), (h, w)), atol=1e-9)
    np.testing.assert_allclose(y, np.broadcast_to(np.arange(h)[:, None], (h, w)), atol=1e-9)


def test_angular_orientation_matches_stated_convention():
    s = 16
    c = s / 2 - 0.5
    cases = {
        (0, 0, 1): (c, c),  # centre = +Z
        (1, 0, 0): (c + s / 4, c),  # radius 1/2 = 90 degrees, image right = +X
        (0, 1, 0): (c, c - s / 4),  # image up = +Y
        (0, -1, 0): (c, c + s / 4),
        (-1, 0, 0): (c - s / 4, c),
    }
    for d, xy in cases.items():
        got = L.direction_to_angular(np.array(d, float), s)
        assert got == pytest.approx(xy, abs=1e-12), d
    # -Z lands on the rim (radius 1)
    x, y = L.direction_to_angular(np.array([0.3, -0.2, -1e9]), s)
    assert np.hypot(x - c, y - c) == pytest.approx(s / 2, rel=1e-6)
    # Debevec's formula, spelled out, for one direction
    dv = np.array([0.2, -0.5, 0.6])
    dv /= np.linalg.norm(dv)
    r = np.arccos(dv[2]) / (np.pi * np.hypot(dv[0], dv[1]))
    u, v = dv[0] * r, dv[1] * r
    got = L.direction_to_angular(dv, s)
    assert got == pytest.approx(((u + 1) * s / 2 - 0.5, (1 - v) * s / 2 - 0.5), abs=1e-12)
    d, inside = L.angular_directions(s)
    x, y = L.direction_to_angular(d, s)
    np.testing.assert_allclose(x[inside], np.broadcast_to(np.arange(s), (s, s))[inside],
                               atol=1e-6)
    np.testing.assert_allclose(y[inside], np.broadcast_to(np.arange(s)[:, None], (s, s))[inside],
                               atol=1e-6)
    assert inside.sum() == pytest.approx(np.pi * s * s / 4, rel=0.05)


@pytest.mark.parametrize("layout", ["equirect", "angular"])
def test_direction_coded_image_to_cube_gives_texel_directions(layout):
    # An image whose pixels hold their own directions, resampled to a cube, holds (up to the
    # averaging over each texel) the cube's texel directions.
    if layout == "equirect":
        img = L.equirect_directions(128, 256)
    else:
        d, inside = L.angular_directions(256)
        img = d * inside[..., None]
    cube = L.to_cube(img.astype(np.float32), layout, 16)
    err = _angle(cube, cm.texel_directions(16))
    assert err.max() < 2e-3


def test_hcross_cells_and_seams():
    n = 8
    cross = L.faces_to_cross(cm.normalization_cube(n), "hcross")
    assert cross.shape == (3 * n, 4 * n, 3)
    cells = {(1, 0): "-X", (1, 1): "+Z", (1, 2): "+X", (1, 3): "-Z", (0, 1): "+Y", (2, 1): "-Y"}
    for (r, c), name in cells.items():
        centre = cross[r * n + n // 2 - 1:r * n + n // 2 + 1, c * n + n // 2 - 1:c * n + n // 2 + 1]
        np.testing.assert_allclose(_unit(centre.mean((0, 1))),
                                   cm.FACE_NORMALS[cm.FACE_NAMES.index(name)], atol=1e-6)
    for (r, c) in cells:
        assert cross[r * n:(r + 1) * n, c * n:(c + 1) * n].any(axis=-1).all()
    empty = [(0, 0), (0, 2), (0, 3), (2, 0), (2, 2), (2, 3)]
    for (r, c) in empty:
        assert not cross[r * n:(r + 1) * n, c * n:(c + 1) * n].any()
    step = _angle(cross[n + 3, 3], cross[n + 3, 4])  # a within-face neighbour step
    # every face boundary of the cross (and the wrap from -Z back to -X) is continuous
    pairs = [
        (cross[n:2 * n, n - 1], cross[n:2 * n, n]),  # -X | +Z
        (cross[n:2 * n, 2 * n - 1], cross[n:2 * n, 2 * n]),  # +Z | +X
        (cross[n:2 * n, 3 * n - 1], cross[n:2 * n, 3 * n]),  # +X | -Z
        (cross[n:2 * n, 4 * n - 1], cross[n:2 * n, 0]),  # -Z | -X (wrap)
        (cross[n - 1, n:2 * n], cross[n, n:2 * n]),  # +Y over +Z
        (cross[2 * n - 1, n:2 * n], cross[2 * n, n:2 * n]),  # +Z over -Y
    ]
    for a, b in pairs:
        assert _angle(a, b).max() < 1.2 * step


def test_vcross_cells_and_seams():
    n = 8
    cube = cm.normalization_cube(n)
    cross = L.faces_to_cross(cube, "vcross")
    assert cross.shape == (4 * n, 3 * n, 3)
    np.testing.assert_array_equal(cross[3 * n:, n:2 * n], cube[5, ::-1, ::-1])  # -Z rotated
    np.testing.assert_array_equal(cross[:n, n:2 * n], cube[2])
    # the rotated -Z's top-left texel looks toward the (-X, -Y, -Z) corner
    np.testing.assert_allclose(_unit(cross[3 * n, n]), -np.ones(3) / np.sqrt(3), atol=0.15)
    step = _angle(cross[n + 3, 3], cross[n + 3, 4])
    pairs = [
        (cross[n:2 * n, n - 1], cross[n:2 * n, n]),  # -X | +Z
        (cross[n:2 * n, 2 * n - 1], cross[n:2 * n, 2 * n]),  # +Z | +X
        (cross[n - 1, n:2 * n], cross[n, n:2 * n]),  # +Y over +Z
        (cross[2 * n - 1, n:2 * n], cross[2 * n, n:2 * n]),  # +Z over -Y
        (cross[3 * n - 1, n:2 * n], cross[3 * n, n:2 * n]),  # -Y over -Z (rotated)
    ]
    for a, b in pairs:
        assert _angle(a, b).max() < 1.2 * step
    np.testing.assert_array_equal(L.cross_to_faces(cross, "vcross"), cube)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# ---------------------------------------------------------------- round trips and energy


@pytest.mark.parametrize("layout", ALL)
def test_round_trip_cube_layout_cube(layout):
    n = 32
    cube = _smooth(cm.texel_directions(n))
    img = L.from_cube(cube, layout)
    back = L.to_cube(img, layout, n)
    assert back.shape == cube.shape and back.dtype == np.float32
    rel = np.abs(back - cube) / cube
    if layout in ("hcross", "vcross", "faces"):
        assert rel.max() < 1e-6  # exact re-arrangement
    else:
        assert rel.max() < 0.015 and rel.mean() < 0.003


@pytest.mark.parametrize("layout", ALL)
@pytest.mark.parametrize("size", [1, 5, 16])
def test_constant_environment_stays_constant(layout, size):
    cube = np.full((6, 12, 12, 3), 2.5, np.float32)
    img = L.from_cube(cube, layout)
    if layout == "angular":
        _, inside = L.angular_directions(img.shape[0])
        assert np.allclose(img[inside], 2.5, rtol=1e-6) and not img[~inside].any()
    elif layout in ("equirect", "faces"):
        assert np.allclose(img, 2.5, rtol=1e-6)
    out = L.to_cube(img, layout, size)
    assert out.shape == (6, size, size, 3)
    np.testing.assert_allclose(out, 2.5, rtol=1e-5)


def test_to_cube_preserves_venice_energy(venice_latlong):
    ref = _equirect_mean(venice_latlong)
    assert ref == pytest.approx([0.51, 0.48, 0.61], abs=0.006)  # tests/data/README.md
    for n in (8, 32):
        got = _solid_angle_mean(L.to_cube(venice_latlong, "equirect", n))
        np.testing.assert_allclose(got, ref, rtol=0.005)


def test_from_cube_preserves_energy(venice_latlong):
    cube = L.to_cube(venice_latlong, "equirect", 32)
    ref = _solid_angle_mean(cube)
    eq = L.from_cube(cube, "equirect", 24)  # coarser than the cube: supersampled
    np.testing.assert_allclose(_equirect_mean(eq), ref, rtol=0.005)


# ---------------------------------------------------------------- anti-aliasing


def _bin_equirect_to_cube(img, n):
    """Brute force: every pixel's radiance times its solid angle, binned by its centre."""
    h, w, c = img.shape
    f, r, col = cm.direction_to_texel(L.equirect_directions(h, w), n)
    idx = np.ravel_multi_index((f, r, col), (6, n, n)).ravel()
    wt = np.broadcast_to(_equirect_row_weights(h)[:, None], (h, w)).ravel()
    num = np.stack([np.bincount(idx, wt * img[..., k].ravel(), 6 * n * n) for k in range(c)], -1)
    return (num / np.bincount(idx, wt, 6 * n * n)[:, None]).reshape(6, n, n, c)


def test_to_cube_downsampling_is_the_solid_angle_mean_not_a_point_sample():
    rng = np.random.default_rng(7)
    img = rng.exponential(1.0, (512, 1024, 1)).astype(np.float32)  # white noise, mean 1
    n = 16
    ref = _bin_equirect_to_cube(img, n)
    got = L.to_cube(img, "equirect", n)
    rel = np.abs(got - ref) / ref
    assert rel.mean() < 0.015 and rel.max() < 0.08
    # a point sample at the texel centres is far off: the test can tell them apart
    point = L.sample_equirect(img, cm.texel_directions(n))
    assert (np.abs(point - ref) / ref).mean() > 0.3


def test_from_cube_downsampling_is_the_solid_angle_mean():
    rng = np.random.default_rng(8)
    n, h = 128, 8
    cube = rng.exponential(1.0, (6, n, n, 1)).astype(np.float32)
    got = L.from_cube(cube, "equirect", h)
    # brute force: bin every cube texel (weighted by its solid angle) into its equirect pixel
    x, y = L.direction_to_equirect(cm.texel_directions(n), h, 2 * h)
    col = np.floor(x + 0.5).astype(int) % (2 * h)
    row = np.clip(np.floor(y + 0.5).astype(int), 0, h - 1)
    idx = (row * 2 * h + col).ravel()
    wt = cm.texel_solid_angles(n).ravel()
    ref = (np.bincount(idx, wt * cube.ravel(), 2 * h * h) / np.bincount(idx, wt, 2 * h * h))
    rel = np.abs(got[..., 0].ravel() - ref) / ref
    assert rel.mean() < 0.012 and rel.max() < 0.08
    point = sample_bilinear(cube, L.equirect_directions(h, 2 * h))  # no averaging at all
    assert (np.abs(point[..., 0].ravel() - ref) / ref).mean() > 0.3


def test_equirect_lookup_crosses_the_poles():
    h, w = 32, 64
    img = L.equirect_directions(h, w).astype(np.float32)  # dx, dy, dz are smooth on the sphere
    # directions closer to the poles than the first / last row centre, all around
    lat = np.pi / 2 - np.array([0.1, 0.3, 0.49]) * np.pi / h
    phi = np.linspace(-np.pi, np.pi, 37)
    d = np.stack([np.cos(phi)[:, None] * np.cos(lat), np.sin(lat) + 0 * phi[:, None],
                  np.sin(phi)[:, None] * np.cos(lat)], -1)
    for sign in (1, -1):
        dd = d * np.array([1, sign, 1])
        got = L.sample_equirect(img, dd)
        # bilinear across the pole is accurate to second order; clamping would be off by
        # about the pole row's distance from the pole (pi / (2 h) ~ 0.05)
        assert np.abs(got - dd).max() < 0.01


# ---------------------------------------------------------------- detection, shapes, errors


@pytest.mark.parametrize(
    "hw, layout",
    [((512, 1024), "equirect"), ((1, 2), "equirect"), ((300, 400), "hcross"),
     ((400, 300), "vcross"), ((1000, 1000), "angular")],
)
def test_detect_layout(hw, layout):
    assert L.detect_layout(*hw) == layout


@pytest.mark.parametrize("hw", [(500, 1024), (100, 600), (600, 100), (3, 5), (2, 1)])
def test_detect_layout_rejects_unknown_aspect(hw):
    with pytest.raises(ValueError, match="give the layout explicitly"):
        L.detect_layout(*hw)


def test_default_face_size_and_layout_shape():
    assert L.default_face_size(512, 1024, "equirect") == 256
    assert L.default_face_size(1000, 1000, "angular") == 256
    assert L.default_face_size(300, 400, "hcross") == 128
    assert L.default_face_size(64, 64, "faces") == 64
    assert L.layout_shape("equirect", 8) == (8, 16)
    assert L.layout_shape("hcross", 8) == (24, 32)
    assert L.layout_shape("vcross", 8) == (32, 24)
    for layout in ALL:
        img = L.from_cube(np.ones((6, 4, 4, 2), np.float32), layout, 6)
        assert img.shape[-3:-1] == L.layout_shape(layout, 6) and img.shape[-1] == 2


def test_bad_arguments_raise_one_sentence_value_errors():
    cube = np.ones((6, 4, 4, 3), np.float32)
    with pytest.raises(ValueError, match="'equirect', 'angular'"):
        L.to_cube(np.ones((4, 8, 3)), "latlong", 4)
    with pytest.raises(ValueError, match="2:1"):
        L.to_cube(np.ones((4, 9, 3)), "equirect", 4)
    with pytest.raises(ValueError, match="square"):
        L.to_cube(np.ones((4, 5, 3)), "angular", 4)
    with pytest.raises(ValueError, match="4n x 3n"):
        L.to_cube(np.ones((12, 15, 3)), "hcross", 4)
    with pytest.raises(ValueError, match="positive integer"):
        L.to_cube(np.ones((4, 8, 3)), "equirect", 0)
    with pytest.raises(ValueError, match=r"\(H, W, C\)"):
        L.to_cube(np.ones((4, 8)), "equirect", 4)
    with pytest.raises(ValueError, match="shape"):
        L.from_cube(cube[:5], "equirect")
    with pytest.raises(ValueError, match="choose one of"):
        L.from_cube(cube, "octahedral")


def test_sample_broadcasting_and_unnormalised_directions():
    rng = np.random.default_rng(3)
    img = rng.random((16, 32, 2)).astype(np.float32)
    d = rng.normal(size=(4, 5, 3))
    a = L.sample_equirect(img, d)
    assert a.shape == (4, 5, 2) and a.dtype == np.float32
    np.testing.assert_allclose(L.sample_equirect(img, 7.5 * d), a, rtol=1e-6)
    ang = rng.random((16, 16, 2)).astype(np.float32)
    b = L.sample_angular(ang, d)
    assert b.shape == (4, 5, 2)
    np.testing.assert_allclose(L.sample_angular(ang, 0.1 * d), b, rtol=1e-6)


def test_nonfinite_pixels_stay_local():
    img = np.ones((64, 128, 3), np.float32)
    img[20, 40] = np.nan
    out = L.to_cube(img, "equirect", 16)
    bad = ~np.isfinite(out).all(-1)
    assert 1 <= bad.sum() <= 4
    np.testing.assert_allclose(out[~bad], 1.0, rtol=1e-6)
    # an angular map's pixels outside the disk are never read, whatever they hold
    ang = np.full((64, 64, 3), 3.0, np.float32)
    _, inside = L.angular_directions(64)
    ang[~inside] = np.inf
    np.testing.assert_allclose(L.to_cube(ang, "angular", 8), 3.0, rtol=1e-6)
