"""Textures in bounded memory: area-average reduction that keeps the mean, a pixel limit refused
from the header with the option named (probegrid.core.reduce, probegrid.scene.texels)."""

from __future__ import annotations

import base64
import io
import json
import struct
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from probegrid.core.color import srgb_to_linear
from probegrid.core.reduce import area_average, area_edges, reduced_shape, row_bands
from probegrid.errors import SceneError
from probegrid.scene import load_gltf
from probegrid.scene.texels import TextureLimits, decode_texture, texture_limits

#: The exact sRGB EOTF of every 8-bit code, for reference means (by counting codes).
_LUT = srgb_to_linear(np.arange(256) / 255.0).astype(np.float64)


def _exact_mean(codes: np.ndarray) -> np.ndarray:
    """Per-channel mean of the linear texels of 8-bit ``codes (H, W, 4)``: colour through the
    sRGB EOTF, alpha as code / 255 (an exact sum over a histogram, no float image)."""
    out = []
    for c in range(codes.shape[-1]):
        counts = np.bincount(codes[..., c].ravel(), minlength=256)
        table = _LUT if c < 3 else np.arange(256) / 255.0
        out.append(counts @ table / codes[..., c].size)
    return np.array(out)


def _weights(n_in: int, n_out: int) -> np.ndarray:
    """The box filter one output pixel wide as an explicit (n_out, n_in) weight matrix."""
    e = area_edges(n_in, n_out)
    k = np.arange(n_in)
    w = np.clip(np.minimum(e[1:, None], k + 1) - np.maximum(e[:-1, None], k), 0, None)
    return w / np.diff(e)[:, None]


def _dense_reference(x: np.ndarray, n_out: int) -> np.ndarray:
    return _weights(len(x), n_out) @ x


@pytest.mark.parametrize(("n_in", "n_out"), [(10, 3), (7, 7), (12, 4), (9, 2), (1000, 37)])
def test_the_area_average_is_the_box_filter_and_keeps_the_mean(n_in, n_out):
    x = np.random.default_rng(n_in).random((n_in, 3))
    out = area_average(x, 0, area_edges(n_in, n_out))
    np.testing.assert_allclose(out, _dense_reference(x, n_out), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out.mean(axis=0), x.mean(axis=0), rtol=1e-13)
    if n_out == n_in:
        np.testing.assert_array_equal(out, x)
    # a band of rows at a time gives the same rows as the whole
    e = area_edges(n_in, n_out)
    for j0, j1, s0, s1 in row_bands(n_in, n_out, 5):
        part = area_average(x[s0:s1], 0, e[j0:j1 + 1], offset=s0)
        np.testing.assert_allclose(part, out[j0:j1], rtol=1e-12, atol=1e-12)


def test_reduced_shape_keeps_the_aspect_and_bounds_the_longer_side():
    assert reduced_shape(4096, 4096, 1024) == (1024, 1024)
    assert reduced_shape(1000, 1536, 640) == (417, 640)
    assert reduced_shape(300, 200, 1024) == (300, 200)
    assert reduced_shape(1, 9000, 1024) == (1, 1024)


def test_a_texture_is_reduced_to_the_size_and_keeps_its_mean_exactly():
    """1536 x 1000 random RGBA codes to a 640-texel side (a non-integer ratio, 2.4): every
    channel's linear mean is the source's, to float32 rounding; alpha is averaged linearly."""
    codes = np.random.default_rng(3).integers(0, 256, (1000, 1536, 4), dtype=np.uint8)
    with texture_limits(TextureLimits(max_size=640)):
        out = decode_texture(Image.fromarray(codes), 4, "t")
    assert out.shape == (417, 640, 4) and out.dtype == np.float32
    np.testing.assert_allclose(out.astype(np.float64).mean(axis=(0, 1)), _exact_mean(codes),
                               rtol=2e-7)
    # the first 10 x 16 texels against explicit weights over the source texels they cover
    # (rows 0..24: 10 x 2.398 = 23.98; columns 0..38: 16 x 2.4 = 38.4)
    lin = np.concatenate([_LUT[codes[:25, :39, :3]], codes[:25, :39, 3:] / 255.0], axis=-1)
    ref = np.einsum("ij,jkc,lk->ilc", _weights(1000, 417)[:10, :25], lin,
                    _weights(1536, 640)[:16, :39])
    np.testing.assert_allclose(out[:10, :16], ref, rtol=1e-6)


def test_a_texture_within_the_size_decodes_to_the_same_bits_as_the_whole_image():
    codes = np.random.default_rng(4).integers(0, 256, (300, 500, 4), dtype=np.uint8)
    out = decode_texture(Image.fromarray(codes), 4, "t")
    expect = srgb_to_linear(codes[..., :3] / 255.0)
    np.testing.assert_array_equal(out[..., :3], expect)
    np.testing.assert_array_equal(out[..., 3], (codes[..., 3] / 255.0).astype(np.float32))
    rgb = decode_texture(Image.fromarray(codes[..., :3]), 3, "t")
    np.testing.assert_array_equal(rgb, expect)


def test_with_an_alpha_cutoff_a_reduced_texels_alpha_is_its_coverage():
    """A checker of opaque (alpha 0.8) and clear (0.2) texels, cutoff 0.5: reduced 4:1, each
    texel is half covered: alpha 0.5 exactly, where averaging alpha first would give 0.5 too
    but compare 0.5 >= 0.5 later; with alpha 0.9 / 0.3 the average 0.6 would read opaque."""
    a = np.where(np.add.outer(np.arange(64), np.arange(64)) % 2 == 0, 230, 77).astype(np.uint8)
    codes = np.dstack([np.full((64, 64, 3), 128, np.uint8), a])
    with texture_limits(TextureLimits(max_size=16)):
        cov = decode_texture(Image.fromarray(codes), 4, "t", alpha_cutoff=0.5)
        avg = decode_texture(Image.fromarray(codes), 4, "t")
    np.testing.assert_array_equal(cov[..., 3], 0.5)
    np.testing.assert_allclose(avg[..., 3], (230 + 77) / 2 / 255.0, rtol=1e-6)


@pytest.mark.slow
def test_a_4096_texture_costs_at_most_three_times_its_decoded_size():
    """tracemalloc's peak while decoding a 4096^2 RGBA texture (Pillow's decoded image, 64
    MiB, is already there): the float work stays under 3x the decoded size; the mean holds."""
    codes = np.random.default_rng(5).integers(0, 256, (4096, 4096, 4), dtype=np.uint8)
    image = Image.fromarray(codes)
    decoded = codes.nbytes
    tracemalloc.start()
    try:
        out = decode_texture(image, 4, "t")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert out.shape == (1024, 1024, 4)
    assert peak <= 3 * decoded, f"peak {peak / 2**20:.0f} MiB"
    np.testing.assert_allclose(out.astype(np.float64).mean(axis=(0, 1)), _exact_mean(codes),
                               rtol=2e-7)


def _png(codes: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(codes).save(buf, format="PNG")
    return buf.getvalue()


def _png_header_only(width: int, height: int) -> bytes:
    """A PNG whose header declares ``width x height`` RGBA and that holds no pixels."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b"")


def textured_quad(path: Path, png: bytes) -> Path:
    """A unit quad with ``png`` as its base colour texture, embedded, as a .gltf."""
    pos = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], "<f4")
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], "<f4")
    idx = np.array([0, 2, 1, 0, 3, 2], "<u2")
    blob = pos.tobytes() + uv.tobytes() + idx.tobytes()
    views = [(0, 48), (48, 32), (80, 12)]
    doc = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1},
                                    "indices": 2, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "textures": [{"source": 0}],
        "images": [{"uri": "data:image/png;base64," + base64.b64encode(png).decode()}],
        "buffers": [{"byteLength": len(blob), "uri": "data:application/octet-stream;base64,"
                     + base64.b64encode(blob).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": o, "byteLength": n} for o, n in views],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [0, 0, 0], "max": [1, 0, 1]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"}],
    }
    path.write_text(json.dumps(doc))
    return path


def test_the_loader_reduces_large_textures_and_refuses_oversized_ones_from_the_header(
        tmp_path):
    codes = np.random.default_rng(6).integers(0, 256, (256, 512, 4), dtype=np.uint8)
    f = textured_quad(tmp_path / "q.gltf", _png(codes))
    tex = load_gltf(f).materials[0].base_color_texture
    assert tex.shape == (256, 512, 4)  # within the default size: as it is
    small = load_gltf(f, textures=TextureLimits(max_size=128)).materials[0].base_color_texture
    assert small.shape == (64, 128, 4)
    np.testing.assert_allclose(small.astype(np.float64).mean(axis=(0, 1)),
                               tex.astype(np.float64).mean(axis=(0, 1)), rtol=1e-6)
    # a 40000 x 30000 header (1.2 G pixels, 4.5 GiB decoded): refused before any decoding,
    # Pillow's own decompression-bomb check (which would drop the image silently) bypassed
    huge = textured_quad(tmp_path / "huge.gltf", _png_header_only(40000, 30000))
    with pytest.raises(SceneError) as err:
        load_gltf(huge)
    msg = str(err.value)
    assert "\n" not in msg and "40000x30000 = 1200.0 M pixels" in msg
    assert "limit of 134.2 M pixels" in msg and "--max-texture-pixels N" in msg
    with pytest.raises(SceneError, match="512x256 = 0.1 M pixels, over the limit of 0.1 M"):
        load_gltf(f, textures=TextureLimits(max_pixels=100_000))


def test_the_bake_names_the_texture_options_in_its_errors(tmp_path, capsys, monkeypatch):
    from probegrid.bake import executors
    from probegrid.bake.executors import InlineExecutor
    from probegrid.cli import EXIT_BAD_INPUT, main

    monkeypatch.setattr(executors, "make_executor",
                        lambda **kw: InlineExecutor(check_pickle=False))

    codes = np.full((64, 64, 4), 200, dtype=np.uint8)
    f = textured_quad(tmp_path / "q.gltf", _png(codes))
    args = ["bake", str(f), "--out", str(tmp_path / "q.probes"), "--grid", "2x2x2",
            "--environment-color", "1,1,1", "--no-progress"]
    assert main([*args, "--max-texture-pixels", "1000"]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("probegrid: error:") and "64x64" in err[-1]
    assert "--max-texture-pixels N raises it" in err[-1]
    assert main([*args, "--max-texture-size", "0"]) == EXIT_BAD_INPUT
    assert "--max-texture-size" in capsys.readouterr().err
    assert not (tmp_path / "q.probes").exists()
