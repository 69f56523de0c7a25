"""Tests of image reading, writing and previews (probegrid.imageio)."""

import os
import shutil

import numpy as np
import OpenImageIO as oiio  # only to make inputs the library does not write (8-bit, grey, alpha)
import pytest

from probegrid import imageio as io
from probegrid.core import cubemap as cm
from probegrid.core import layouts as L


def _hdr_image(h=24, w=48, seed=0):
    rng = np.random.default_rng(seed)
    return (np.exp(rng.normal(0.0, 2.0, (h, w, 3)))).astype(np.float32)  # ~1e-3 .. 1e3


def _oiio_write(path, data, pixel_type):
    out = oiio.ImageOutput.create(str(path))
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, pixel_type)
    spec.attribute("oiio:UnassociatedAlpha", 1)  # store colour as given, not divided by alpha
    assert out.open(str(path), spec)
    assert out.write_image(data)
    assert out.close()


def _truncate(src, dst, fraction):
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * fraction)])
    return dst


def _assert_one_line_naming(exc_info, path):
    msg = str(exc_info.value)
    assert "\n" not in msg and str(path) in msg


# ---------------------------------------------------------------- transfer functions


def test_srgb_transfer_functions_are_the_exact_piecewise_curves():
    v = np.array([0.0, 0.04045, 0.5, 1.0])
    expected = [0.0, 0.04045 / 12.92, ((0.5 + 0.055) / 1.055) ** 2.4, 1.0]
    np.testing.assert_allclose(io.srgb_to_linear(v), expected, rtol=1e-6)
    x = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(io.srgb_to_linear(io.linear_to_srgb(x)), x, atol=2e-7)
    assert io.linear_to_srgb([np.nan, -1.0, 2.0, np.inf]).tolist() == [0, 0, 1, 1]


# ---------------------------------------------------------------- round trips


@pytest.mark.parametrize(
    "name, half, rtol",
    [("a.exr", True, 1e-3), ("a.exr", False, 0), ("a.pfm", False, 0), ("a.tif", False, 0),
     ("a.tiff", True, 1e-3)],
)
def test_float_format_round_trips(tmp_path, name, half, rtol):
    img = _hdr_image()
    p = io.write_image(tmp_path / name, img, half=half)
    back = io.read_image(p)
    assert back.shape == img.shape and back.dtype == np.float32
    if rtol:
        np.testing.assert_allclose(back, img, rtol=rtol)
    else:
        np.testing.assert_array_equal(back, img)


def test_hdr_round_trip_within_rgbe_precision(tmp_path):
    img = _hdr_image()
    back = io.read_image(io.write_image(tmp_path / "a.hdr", img))
    # one shared 8-bit mantissa: error below 1/128 of the pixel's largest channel, and below
    # 1 % for that channel itself (its mantissa is >= 128)
    big = img.max(-1, keepdims=True)
    assert (np.abs(back - img) <= big / 128).all()
    assert np.abs(back / img - 1)[img == big].max() < 0.01


def test_png_round_trip_within_quantisation(tmp_path):
    img = np.random.default_rng(1).random((20, 30, 3)).astype(np.float32)  # linear, in [0, 1]
    back = io.read_image(io.write_image(tmp_path / "a.png", img))
    code = io.linear_to_srgb(img) * 255
    code_back = io.linear_to_srgb(back) * 255
    assert np.abs(code_back - code).max() <= 0.5 + 1e-3


def test_8bit_files_are_decoded_from_srgb(tmp_path):
    codes = np.arange(256, dtype=np.uint8).reshape(16, 16, 1)
    rgb = np.concatenate([codes, codes[::-1], np.full_like(codes, 7)], axis=-1)
    _oiio_write(tmp_path / "rgb.png", rgb, "uint8")
    got = io.read_image(tmp_path / "rgb.png")
    np.testing.assert_allclose(got, io.srgb_to_linear(rgb / 255.0), rtol=1e-6, atol=1e-9)
    assert got[0, 10, 0] == pytest.approx(10 / 255 / 12.92, rel=1e-6)  # linear segment
    assert got[8, 0, 0] == pytest.approx(((128 / 255 + 0.055) / 1.055) ** 2.4, rel=1e-6)
    # grey -> RGB
    _oiio_write(tmp_path / "grey.png", codes, "uint8")
    grey = io.read_image(tmp_path / "grey.png")
    assert grey.shape == (16, 16, 3)
    np.testing.assert_array_equal(grey[..., 0], grey[..., 2])
    # alpha is dropped, the colour is not multiplied by it
    rgba = np.concatenate([rgb, np.full_like(codes, 64)], axis=-1)
    _oiio_write(tmp_path / "rgba.png", rgba, "uint8")
    np.testing.assert_allclose(io.read_image(tmp_path / "rgba.png"), got, rtol=0.02, atol=1e-3)
    # a JPEG decodes too (lossy: compare loosely)
    smooth = np.repeat(np.linspace(0, 255, 32, dtype=np.uint8)[None, :, None], 16, 0)
    _oiio_write(tmp_path / "a.jpg", np.repeat(smooth, 3, -1), "uint8")
    jpg = io.read_image(tmp_path / "a.jpg")
    np.testing.assert_allclose(jpg, io.srgb_to_linear(np.repeat(smooth, 3, -1) / 255), atol=0.03)


def test_exr_metadata_round_trip(tmp_path):
    meta = {"probegrid:faceOrder": "+X,-X,+Y,-Y,+Z,-Z", "probegrid:kind": "specular"}
    p = io.write_image(tmp_path / "m.exr", _hdr_image(), metadata=meta)
    got = io.read_metadata(p)
    assert {k: got[k] for k in meta} == meta
    with pytest.raises(ValueError, match="metadata"):
        io.write_image(tmp_path / "m.exr", _hdr_image(), metadata={"a": 1.0})


@pytest.mark.parametrize("layout", ["faces", "hcross", "vcross", "equirect"])
@pytest.mark.parametrize("fmt", ["exr", "hdr"])
def test_write_cube_and_read_environment_round_trip(tmp_path, layout, fmt):
    n = 16
    cube = np.exp(L.to_cube(np.zeros((8, 16, 3), np.float32), "equirect", n)
                  + cm.texel_directions(n).astype(np.float32))  # smooth, positive
    paths = io.write_cube(tmp_path / "env", cube, layout=layout, fmt=fmt,
                          metadata={"probegrid:layout": layout})
    if layout == "faces":
        assert [p.name for p in paths] == [f"env{s}.{fmt}" for s in io.FACE_SUFFIXES]
    else:
        assert [p.name for p in paths] == [f"env.{fmt}"]
    if fmt == "exr":
        assert io.read_metadata(paths[0])["probegrid:layout"] == layout
    back = io.read_environment(paths, size=n)  # layout detected from the aspect / six files
    # half: 1e-3 relative; RGBE: 1 % of the texel's largest channel; equirect adds resampling
    err = np.abs(back - cube) / cube.max(-1, keepdims=True)
    tol = {"exr": 1e-3, "hdr": 0.01}[fmt] + (0.015 if layout == "equirect" else 0)
    assert err.max() < tol
    assert sorted(os.listdir(tmp_path)) == sorted(p.name for p in paths)  # no temporaries


def _oiio_read(path):
    """Pixels and stored pixel type of a file, straight from OpenImageIO (no probegrid code)."""
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None
    try:
        return inp.read_image(0, 0, 0, inp.spec().nchannels, oiio.FLOAT), inp.spec().format
    finally:
        inp.close()


def test_exr_beyond_half_range_falls_back_to_float32(tmp_path):
    # 65504 is the largest half; 65520 and up round to inf in half. Values of a real sun.
    img = np.full((4, 5), 0.25, np.float32)
    img[1, 2], img[3, 4], img[0, 0] = 1e5, -7.0e4, 65504.0
    with np.errstate(over="ignore"):
        assert np.isinf(img.astype(np.float16)).sum() == 2  # what half would have stored
    p = io.write_image(tmp_path / "sun.exr", img, half=True)
    data, fmt = _oiio_read(p)
    assert fmt == oiio.FLOAT and io.stored_pixel_type(p) == "float"
    assert np.isfinite(data).all()
    np.testing.assert_array_equal(data[..., 0], img)  # exact, not clamped


def test_exr_within_half_range_stays_half(tmp_path):
    img = np.full((4, 5, 3), 1.5, np.float32)
    img[0, 0] = [65504.0, -65504.0, 6e-5]
    img[1, 1] = [np.inf, np.nan, 0.0]  # non-finite values are no reason for float32
    p = io.write_image(tmp_path / "ok.exr", img, half=True)
    data, fmt = _oiio_read(p)
    assert fmt == oiio.HALF and io.stored_pixel_type(p) == "half"
    np.testing.assert_array_equal(data, img.astype(np.float16).astype(np.float32))
    q = io.write_image(tmp_path / "f.exr", img, half=False)
    assert io.stored_pixel_type(q) == "float"


def test_cube_beyond_half_range_is_float32_in_every_face(tmp_path):
    cube = np.full((6, 4, 4, 3), 2.0, np.float32)
    cube[4, 1:3, 1:3] = [1e5, 8e4, 3e4]  # a sun on +Z only
    paths = io.write_cube(tmp_path / "spec", cube, half=True)
    assert isinstance(paths, list) and len(paths) == 6 and paths.pixel_type == "float"
    for f, path in enumerate(paths):
        data, fmt = _oiio_read(path)
        assert fmt == oiio.FLOAT  # one pixel type per cube, not just the +Z face
        np.testing.assert_array_equal(data, cube[f])
    assert io.read_environment(paths).max() == np.float32(1e5)
    for layout in ("hcross", "equirect"):
        (q,) = written = io.write_cube(tmp_path / layout, cube, layout=layout, half=True)
        assert written.pixel_type == "float" and _oiio_read(q)[1] == oiio.FLOAT
        data, _ = _oiio_read(q)
        assert np.isfinite(data).all() and data.max() > io.HALF_MAX
    dim = io.write_cube(tmp_path / "dim", cube / 2, half=True)
    assert dim.pixel_type == "half" and all(_oiio_read(q)[1] == oiio.HALF for q in dim)
    assert io.write_cube(tmp_path / "f", cube / 2, half=False).pixel_type == "float"


@pytest.mark.parametrize("name, expected", [("a.hdr", "rgbe"), ("a.pfm", "float"),
                                            ("a.tif", "float"), ("a.png", "uint8")])
def test_half_is_ignored_by_formats_without_half(tmp_path, name, expected):
    img = np.full((3, 4, 3), 0.5, np.float32)
    img[0, 0] = 1e5 if expected != "uint8" else 1.0
    p = io.write_image(tmp_path / name, img, half=True)
    assert io.stored_pixel_type(p) == expected
    back = io.read_image(p)
    tol = {"rgbe": 0.01, "float": 0.0, "uint8": 0.5 / 255}[expected]
    np.testing.assert_allclose(back, img, rtol=tol, atol=tol if expected == "uint8" else 0)
    assert io.write_cube(tmp_path / "c", np.ones((6, 2, 2, 3)), fmt="hdr").pixel_type == "rgbe"


# ---------------------------------------------------------------- errors


def test_truncated_real_hdr_is_detected(tmp_path, real_data):
    src = real_data / "hdr" / "venice_sunset_1k.hdr"
    for fraction in (0.999, 0.5, 0.01):
        bad = _truncate(src, tmp_path / f"venice_{fraction}.hdr", fraction)
        with pytest.raises(io.ImageError, match="truncated|cannot read") as exc:
            io.read_image(bad)
        _assert_one_line_naming(exc, bad)


@pytest.mark.parametrize("name", ["a.exr", "b.png", "c.tif", "d.pfm", "e.hdr", "f.jpg"])
def test_truncated_written_files_are_detected(tmp_path, name):
    img = _hdr_image(64, 96)
    if name.endswith(".jpg"):
        _oiio_write(tmp_path / name, np.rint(io.linear_to_srgb(img) * 255).astype(np.uint8),
                    "uint8")
        good = tmp_path / name
    else:
        good = io.write_image(tmp_path / name, img, half=False)
    io.read_image(good)
    for fraction in (0.9, 0.5):
        bad = _truncate(good, tmp_path / f"cut{fraction}_{name}", fraction)
        with pytest.raises(io.ImageError) as exc:
            io.read_image(bad)
        _assert_one_line_naming(exc, bad)


@pytest.mark.parametrize("name", ["g.exr", "g.png", "g.hdr", "g.tif", "g.pfm", "g.jpg"])
def test_garbage_files_raise_image_error(tmp_path, name):
    p = tmp_path / name
    p.write_bytes(np.random.default_rng(0).integers(0, 256, 600, dtype=np.uint8).tobytes())
    with pytest.raises(io.ImageError) as exc:
        io.read_image(p)
    _assert_one_line_naming(exc, p)


def test_missing_unsupported_and_directory_paths(tmp_path):
    with pytest.raises(io.ImageError, match="no such file") as exc:
        io.read_image(tmp_path / "nope.exr")
    _assert_one_line_naming(exc, tmp_path / "nope.exr")
    (tmp_path / "x.gif").write_bytes(b"GIF89a")
    with pytest.raises(io.ImageError, match="unsupported") as exc:
        io.read_image(tmp_path / "x.gif")
    _assert_one_line_naming(exc, tmp_path / "x.gif")
    (tmp_path / "d.exr").mkdir()
    with pytest.raises(io.ImageError, match="not a regular file"):
        io.read_image(tmp_path / "d.exr")
    assert issubclass(io.ImageError, ValueError)
    with pytest.raises(io.ImageError, match="unsupported output extension"):
        io.write_image(tmp_path / "x.bmp", _hdr_image())
    with pytest.raises(io.ImageError, match="does not exist"):
        io.write_image(tmp_path / "no_dir" / "x.exr", _hdr_image())


def test_read_environment_errors(tmp_path):
    odd = io.write_image(tmp_path / "odd.exr", _hdr_image(30, 50))
    with pytest.raises(io.ImageError, match="give the layout explicitly") as exc:
        io.read_environment(odd)
    _assert_one_line_naming(exc, odd)
    with pytest.raises(io.ImageError, match="2:1"):
        io.read_environment(odd, layout="equirect")
    with pytest.raises(ValueError, match="six files"):
        io.read_environment(odd, layout="faces")
    with pytest.raises(ValueError, match="one environment image or six"):
        io.read_environment([odd, odd])
    faces = [io.write_image(tmp_path / f"f{i}.exr", np.ones((8, 8, 3))) for i in range(5)]
    faces.append(io.write_image(tmp_path / "f5.exr", np.ones((4, 4, 3))))
    with pytest.raises(io.ImageError, match="equal in size"):
        io.read_environment(faces)
    with pytest.raises(ValueError, match="'auto', 'equirect'"):
        io.read_environment(odd, layout="cube")
    with pytest.raises(ValueError, match="positive integer"):
        io.read_environment(odd, size=0)


def test_nonfinite_pixels_are_counted_and_rejected_unless_clamped(tmp_path):
    img = np.ones((16, 32, 3), np.float32)
    img[2, 3, 1] = np.nan
    img[5, 6] = np.inf
    img[7, 8, 0] = -np.inf
    img[9, 9] = 50.0
    assert io.count_nonfinite(img) == 3
    assert io.count_nonfinite(np.ones((6, 2, 2, 3))) == 0
    p = io.write_image(tmp_path / "nf.exr", img, half=False)
    with pytest.raises(io.ImageError, match="3 non-finite pixels") as exc:
        io.read_environment(p)
    _assert_one_line_naming(exc, p)
    cube = io.read_environment(p, clamp=10.0, size=4)
    assert np.isfinite(cube).all() and cube.max() <= 10.0 and cube.min() >= 0.0
    clamped = io.clamp_radiance(img, 10.0)
    assert clamped[2, 3, 1] == 0 and clamped[5, 6, 0] == 10 and clamped[7, 8, 0] == 0
    assert clamped[9, 9, 0] == 10
    with pytest.raises(ValueError, match="positive finite"):
        io.clamp_radiance(img, np.nan)


# ---------------------------------------------------------------- real data, atomicity


def test_read_environment_of_venice_keeps_its_energy(real_data):
    cube = io.read_environment(real_data / "hdr" / "venice_sunset_1k.hdr", size=32)
    assert cube.shape == (6, 32, 32, 3) and cube.dtype == np.float32
    w = cm.texel_solid_angles(32)[..., None]
    mean = (cube * w).sum((0, 1, 2)) / (4 * np.pi)
    np.testing.assert_allclose(mean, [0.51, 0.48, 0.61], atol=0.006)  # tests/data/README.md


def test_default_environment_size_from_the_source(tmp_path, venice_latlong):
    small = venice_latlong[::8, ::8]  # 128 x 64 equirect -> 32
    p = io.write_image(tmp_path / "small.exr", small, half=False)
    assert io.read_environment(p).shape == (6, 32, 32, 3)


def test_failed_cube_write_leaves_no_partial_output(tmp_path):
    cube = np.ones((6, 4, 4, 3), np.float32)
    old = io.write_image(tmp_path / "env_px.exr", np.full((4, 4, 3), 7.0))
    (tmp_path / "env_ny.exr").mkdir()  # the fourth face cannot be written
    with pytest.raises(io.ImageError, match="env_ny.exr"):
        io.write_cube(tmp_path / "env", cube)
    assert sorted(os.listdir(tmp_path)) == ["env_ny.exr", "env_px.exr"]  # no temporaries
    np.testing.assert_array_equal(io.read_image(old), 7.0)  # the old file is untouched
    shutil.rmtree(tmp_path / "env_ny.exr")
    io.write_cube(tmp_path / "env", cube)
    np.testing.assert_array_equal(io.read_image(old), 1.0)  # now replaced as a whole


# ---------------------------------------------------------------- previews


def test_tonemap_preview():
    grey = np.full((2, 2, 3), 0.18)
    aces = (0.18 * (2.51 * 0.18 + 0.03)) / (0.18 * (2.43 * 0.18 + 0.59) + 0.14)
    expected = round(float(io.linear_to_srgb(aces)) * 255)
    out = io.tonemap_preview(grey, exposure=0.0)
    assert out.dtype == np.uint8 and (out == expected).all()
    assert (io.tonemap_preview(grey) == expected).all()  # auto exposure keys 0.18 to 0.18
    img = _hdr_image()
    diff = io.tonemap_preview(8 * img).astype(int) - io.tonemap_preview(img)
    assert np.abs(diff).max() <= 1  # auto exposure: a brighter image previews the same
    assert (io.tonemap_preview(img, exposure=1.0).astype(int)
            >= io.tonemap_preview(img, exposure=0.0)).all()
    special = io.tonemap_preview(np.array([[np.nan, np.inf, -1.0]]), exposure=0.0)
    assert special.tolist() == [[0, 255, 0]]
    with pytest.raises(ValueError, match="exposure"):
        io.tonemap_preview(grey, exposure=np.inf)


def test_write_preview_png_of_cube_and_image(tmp_path):
    n = 8
    cube = np.exp(cm.texel_directions(n).astype(np.float32))
    p = io.write_preview_png(tmp_path / "cube.png", cube)
    spec = oiio.ImageInput.open(str(p)).spec()
    assert (spec.height, spec.width, spec.nchannels) == (3 * n, 4 * n, 3)
    png = io.read_image(p)
    assert not png[:n, :n].any() and png[n:2 * n].all()  # empty cells black, faces lit
    q = io.write_preview_png(tmp_path / "eq.png", cube, layout="equirect", exposure=-1.0)
    assert io.read_image(q).shape == (2 * n, 4 * n, 3)
    io.write_preview_png(tmp_path / "img.png", _hdr_image())
    with pytest.raises(ValueError, match=r"\.png"):
        io.write_preview_png(tmp_path / "x.exr", cube)
    with pytest.raises(ValueError, match="preview layout"):
        io.write_preview_png(tmp_path / "x.png", cube, layout="faces")


def test_adaptive_tone_mapping_keeps_hue_and_clips_almost_nothing():
    from probegrid.core.color import PREVIEW_WHITE_QUANTILE, tonemap_adaptive

    rng = np.random.default_rng(5)
    lum = np.exp(rng.normal(0.0, 3.0, size=(64, 64)))  # 26 stops of range
    tint = np.array([1.0, 0.5, 0.2])
    img = lum[..., None] * tint
    out = tonemap_adaptive(img)
    top = (out == 255).any(axis=-1).mean()
    assert top <= 1.0 - PREVIEW_WHITE_QUANTILE + 0.002
    # hue kept: every unclipped pixel's red is the brightest channel, green about half of it
    lin = io.srgb_to_linear(out[..., :].astype(np.float64) / 255.0)
    ok = (out[..., 0] > 40) & (out[..., 0] < 255)
    np.testing.assert_allclose(lin[ok][:, 1] / lin[ok][:, 0], 0.5, atol=0.03)
    # monotonic in the radiance, and a brighter image previews the same
    order = np.argsort(lum.ravel())
    assert (np.diff(out[..., 0].ravel()[order].astype(int)) >= 0).all()
    assert np.abs(tonemap_adaptive(8 * img).astype(int) - out).max() <= 1
    special = tonemap_adaptive(np.array([[np.nan, 0, 0], [1.0, np.inf, 0], [-1.0, 0, 0]]),
                               exposure=0.0)
    assert special.tolist() == [[0, 0, 0], [255, 255, 255], [0, 0, 0]]


# ------------------------------------------------------------------------------ failed writes
class _LosesItsLastFlush:
    """An OpenImageIO writer whose file loses its buffered bytes at close, as on a full disk,
    while close still reports success."""

    def __init__(self, out, path):
        self._out, self._path = out, path

    def __getattr__(self, name):
        return getattr(self._out, name)

    def open(self, path, spec):
        self._path = path
        return self._out.open(path, spec)

    def close(self):
        ok = self._out.close()
        os.truncate(self._path, 0)
        return ok


@pytest.mark.parametrize("ext", ["exr", "hdr", "png", "tif", "pfm"])
def test_a_write_that_loses_its_last_flush_raises_and_leaves_nothing(tmp_path, monkeypatch, ext):
    real = oiio.ImageOutput.create
    monkeypatch.setattr(oiio.ImageOutput, "create",
                        staticmethod(lambda path, *a: _LosesItsLastFlush(real(path, *a), path)))
    with pytest.raises(io.ImageError, match=r"x\.%s: cannot write image" % ext):
        io.write_image(tmp_path / f"x.{ext}", np.ones((12, 2, 3), np.float32))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("ext", ["exr", "hdr", "png", "tif", "pfm"])
@pytest.mark.parametrize("n", [1, 4, 32])
def test_writes_on_a_full_file_system_raise(full_fs, ext, n):
    # OpenImageIO closes a small image (one buffer) "successfully" with 0 bytes on disk
    with pytest.raises(io.ImageError, match="cannot write image"):
        io.write_image(full_fs / f"x.{ext}", np.ones((6 * n, n, 3), np.float32), half=False)
    assert sorted(p.name for p in full_fs.iterdir()) == ["fill"]


# ------------------------------------------------------------------------------ pixel limits
def test_an_image_with_too_many_pixels_is_refused_from_its_header(tmp_path, monkeypatch):
    small = io.write_image(tmp_path / "s.exr", np.ones((4, 4, 3), np.float32))
    with pytest.raises(io.ImageError, match="4x4 is 16 pixels, over the limit of 15"):
        io.read_image(small, max_pixels=15)
    assert io.read_image(small, max_pixels=16).shape == (4, 4, 3)
    assert io.MAX_PIXELS == 1 << 28
    monkeypatch.setattr(io, "MAX_PIXELS", 8)  # the default limit
    with pytest.raises(io.ImageError, match="16 pixels, over the limit of 8"):
        io.read_image(small)
