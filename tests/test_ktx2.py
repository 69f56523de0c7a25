"""KTX2 writer and reader (probegrid.export.ktx2), checked against independent references:

* RGB9E5 against a brute-force encoder written from the format's definition (the smallest shared
  exponent whose rounded mantissas fit in 9 bits), plus hand-computed words;
* every file against npm's ``ktx-parse`` under node (header fields, the DFD field by field
  against the Khronos Data Format values, key/value data, level sizes), against a struct-level
  parse of the level index here (levels smallest first, mip padding), against ktx-parse's own
  writer (re-serialising what it read gives our bytes back, byte for byte), and the texels
  ktx-parse returns decoded here against the source arrays after the format's rounding;
* round trips through our reader.
"""

from __future__ import annotations

import base64
import math
import struct

import numpy as np
import pytest
from node_readers import ktx_parse_dump, node_package_dir

from probegrid.export import ktx2

RNG = np.random.default_rng(11)


@pytest.fixture(scope="session")
def ktx_parse(tmp_path_factory):
    return node_package_dir(tmp_path_factory, "ktx-parse")


# ------------------------------------------------------------------------------- RGB9E5
def _rgb9e5_reference(rgb: np.ndarray) -> np.ndarray:
    """Brute force: the smallest exponent e in 0..31 for which floor(c / 2^(e-24) + 0.5) <= 511
    for the largest (clamped) component; mantissas rounded at that exponent."""
    c = np.clip(np.nan_to_num(np.asarray(rgb, np.float64), nan=0.0), 0.0, 65408.0)
    e = np.arange(32)
    scale = 2.0 ** (e - 24)  # (32,)
    mant = np.floor(c.max(axis=-1)[..., None] / scale + 0.5)  # (..., 32)
    best = np.argmax(mant <= 511, axis=-1)
    m = np.floor(c / scale[best][..., None] + 0.5).astype(np.uint64)
    return (m[..., 0] | m[..., 1] << 9 | m[..., 2] << 18 | best.astype(np.uint64) << 27
            ).astype(np.uint32)


def test_rgb9e5_matches_brute_force_definition():
    # values across the whole range, exact powers of two, and values that round up to the next
    # exponent (1.999 -> 2.0)
    logs = RNG.uniform(-30, 16, size=(4000, 1))
    v = RNG.uniform(0.0, 1.0, size=(4000, 3)) * 2.0 ** logs
    special = np.array([[1.0, 0.5, 0.25], [65408.0, 0.0, 1e-9], [0.0, 0.0, 0.0],
                        [1.999, 0.0, 0.0], [2.0**-15, 2.0**-16, 2.0**-24], [1e6, -1.0, np.nan],
                        [511.75, 1.0, 0.0]])
    v = np.concatenate([v, special])
    np.testing.assert_array_equal(ktx2.encode_rgb9e5(v), _rgb9e5_reference(v))
    words = ktx2.encode_rgb9e5(special[:4])
    # 1.0 = 256 * 2^(16-24), 0.5 = 128, 0.25 = 64 at exponent 16; 65408 = 511 * 2^(31-24)
    assert [hex(w) for w in words] == ["0x81010100", "0xf80001ff", "0x0", "0x88000100"]
    dec = ktx2.decode_rgb9e5(words)
    np.testing.assert_array_equal(dec[3], [2.0, 0.0, 0.0])
    # relative error of the largest component is at most half a 9-bit step
    big = v[:4000].max(axis=-1)
    got = ktx2.decode_rgb9e5(ktx2.encode_rgb9e5(v[:4000])).max(axis=-1)
    ok = big > 2.0**-14
    assert np.all(np.abs(got[ok] - big[ok]) <= big[ok] * 2.0**-9 + 1e-30)


# ------------------------------------------------------------------------------- files
def _mips(kind: str, size: int, levels: int, channels: int = 3, layers: int | None = None):
    out = []
    for p in range(levels):
        n = max(1, size >> p)
        shape = {"2d": (n, max(1, (size // 2) >> p)), "cube": (6, n, n),
                 "3d": (max(1, (size // 4) >> p), n, max(1, (size // 2) >> p))}[kind]
        if layers:
            shape = (layers,) + shape
        out.append(RNG.uniform(0.0, 40.0, size=shape + (channels,)).astype(np.float32))
    return out


CASES = [  # (kind, base size, levels, vkFormat, supercompression, layers)
    ("cube", 16, 5, 97, "none", None),
    ("cube", 8, 4, 109, "zstd", None),
    ("cube", 8, 4, 123, "none", None),
    ("cube", 4, 3, 123, "zstd", 3),
    ("2d", 16, 5, 97, "zstd", None),
    ("2d", 8, 1, 109, "none", None),
    ("3d", 16, 3, 123, "none", None),
    ("3d", 8, 2, 97, "none", None),
]


def _rounded(a: np.ndarray, fmt: int) -> np.ndarray:
    """What the format stores for float RGB(A) ``a``, decoded (independent of probegrid)."""
    if fmt == 97:
        return a.astype(np.float16).astype(np.float32)
    if fmt == 109:
        return a
    w = _rgb9e5_reference(a[..., :3]).astype(np.int64)
    m = np.stack([w & 511, (w >> 9) & 511, (w >> 18) & 511], -1).astype(np.float64)
    return (m * 2.0 ** ((w >> 27) - 24)[..., None]).astype(np.float32)


def _raw_index(data: bytes) -> tuple[tuple[int, ...], list[tuple[int, int, int]]]:
    head = struct.unpack_from("<9I", data, 12)
    n = max(1, head[7])
    return head, [struct.unpack_from("<QQQ", data, 80 + 24 * p) for p in range(n)]


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    d = tmp_path_factory.mktemp("ktx2")
    out = []
    for i, (kind, size, levels, fmt, sc, layers) in enumerate(CASES):
        src = _mips(kind, size, levels, layers=layers)
        path = ktx2.write_ktx2(d / f"case{i}.ktx2", src, kind=kind, vk_format=fmt,
                               supercompression=sc, layered=layers is not None,
                               key_values={"probegrid:test": f"case {i}", "zz": b"\x01\x02"})
        out.append((path, src))
    return out


def test_round_trip_through_our_reader(written):
    for (path, src), (kind, _, levels, fmt, sc, layers) in zip(written, CASES, strict=True):
        tex = ktx2.read_ktx2(path)
        assert (tex.vk_format, tex.kind, tex.level_count) == (fmt, kind, levels)
        assert tex.layer_count == (layers or 0)
        assert tex.supercompression_scheme == (2 if sc == "zstd" else 0)
        assert tex.key_values["KTXwriter"].startswith(b"probegrid ")
        for got, want in zip(tex.levels, src, strict=True):
            np.testing.assert_array_equal(got[..., :3], _rounded(want, fmt)[..., :3])
            if fmt != 123:
                assert np.all(got[..., 3] == 1.0)


def test_layout_levels_smallest_first_with_mip_padding(written):
    for (path, _), (_, _, levels, fmt, sc, _) in zip(written, CASES, strict=True):
        data = path.read_bytes()
        _, index = _raw_index(data)
        offsets = [off for off, _, _ in index]
        assert offsets == sorted(offsets, reverse=True)  # level 0 (largest) is last
        block = {97: 8, 109: 16, 123: 4}[fmt]
        if sc == "none":
            assert all(off % math.lcm(block, 4) == 0 for off in offsets)
            assert all(length == raw for _, length, raw in index)
            # padding between levels is the minimum: each level starts at the next aligned byte
            ends = [off + length for off, length, _ in index]
            for p in range(levels - 1):
                gap = offsets[p] - ends[p + 1]
                assert 0 <= gap < math.lcm(block, 4)
        assert index[0][0] + index[0][1] == len(data)  # level 0 ends the file


def test_ktx_parse_reads_every_file(written, ktx_parse):
    dumps = ktx_parse_dump(ktx_parse, [p for p, _ in written])
    for d, (path, src), (kind, size, levels, fmt, sc, layers) in zip(
            dumps, written, CASES, strict=True):
        base = src[0].shape[1:] if layers else src[0].shape
        w, h, depth = {"2d": (base[1], base[0], 0), "cube": (base[2], base[1], 0),
                       "3d": (base[2], base[1], base[0])}[kind]
        assert (d["vkFormat"], d["typeSize"]) == (fmt, {97: 2, 109: 4, 123: 4}[fmt])
        assert (d["pixelWidth"], d["pixelHeight"], d["pixelDepth"]) == (w, h, depth)
        assert d["faceCount"] == (6 if kind == "cube" else 1)
        assert d["layerCount"] == (layers or 0)
        assert d["levelCount"] == levels
        assert d["supercompressionScheme"] == (2 if sc == "zstd" else 0)
        assert d["keyValue"]["KTXwriter"]["text"].startswith("probegrid ")
        assert base64.b64decode(d["keyValue"]["probegrid:test"]["base64"]) == \
            f"case {path.stem[4:]}".encode() + b"\0"
        assert base64.b64decode(d["keyValue"]["zz"]["base64"]) == b"\x01\x02"
        # ktx-parse's own writer re-serialises the container to our exact bytes (it applies
        # the specification's ordering and padding independently of us)
        assert d["rewriteIdentical"], path
        _check_dfd(d["dfd"], fmt)
        block = {97: 8, 109: 16, 123: 4}[fmt]
        for p, (lv, want) in enumerate(zip(d["levels"], src, strict=True)):
            raw = base64.b64decode(lv["base64"])
            assert lv["uncompressedByteLength"] == want[..., 0].size * block
            if sc == "zstd":
                import zstandard

                raw = zstandard.ZstdDecompressor().decompress(
                    raw, max_output_size=lv["uncompressedByteLength"])
            else:
                assert lv["byteLength"] == lv["uncompressedByteLength"]
            assert len(raw) == lv["uncompressedByteLength"], (path, p)
            _check_texels(raw, want, fmt)


def _check_texels(raw: bytes, want: np.ndarray, fmt: int) -> None:
    """Texels in file order (layer, face, z, row, texel) decoded here, against the source."""
    if fmt == 123:
        w = np.frombuffer(raw, "<u4").astype(np.int64).reshape(want.shape[:-1])
        m = np.stack([w & 511, (w >> 9) & 511, (w >> 18) & 511], -1).astype(np.float64)
        got = m * 2.0 ** ((w >> 27) - 24)[..., None]
    else:
        got = np.frombuffer(raw, "<f2" if fmt == 97 else "<f4").reshape(
            want.shape[:-1] + (4,)).astype(np.float64)
        assert np.all(got[..., 3] == 1.0)
    np.testing.assert_array_equal(got[..., :3], _rounded(want, fmt)[..., :3])


def _check_dfd(dfd: dict, fmt: int) -> None:
    """The Basic DFD against the Khronos Data Format values libktx's vk2dfd writes."""
    assert (dfd["vendorId"], dfd["descriptorType"], dfd["versionNumber"]) == (0, 0, 2)
    assert (dfd["colorModel"], dfd["colorPrimaries"], dfd["transferFunction"], dfd["flags"]) \
        == (1, 1, 1, 0)  # RGBSDA, BT709, LINEAR, alpha straight
    assert dfd["texelBlockDimension"] == [0, 0, 0, 0]
    assert dfd["bytesPlane"] == [{97: 8, 109: 16, 123: 4}[fmt], 0, 0, 0, 0, 0, 0, 0]
    s = dfd["samples"]
    if fmt == 123:  # mantissa (9 bits at 0/9/18, upper 8448) then exponent (5 bits at 27)
        want = []
        for ch in range(3):
            want.append((9 * ch, 8, ch, 0, 8448))
            want.append((27, 4, ch | 0x20, 15, 31))
    else:
        bits = 16 if fmt == 97 else 32
        # FLOAT | SIGNED; lower -1.0f, upper 1.0f read as int32 (ktx-parse: signed samples)
        want = [(bits * i, bits - 1, ch | 0xC0, -1082130432, 1065353216)
                for i, ch in enumerate((0, 1, 2, 15))]
    got = [(x["bitOffset"], x["bitLength"], x["channelType"], x["sampleLower"],
            x["sampleUpper"]) for x in s]
    assert got == want
    assert all(x["samplePosition"] == [0, 0, 0, 0] for x in s)


def test_dfd_bytes_and_sizes():
    for fmt, n in ((97, 4), (109, 4), (123, 6)):
        dfd = ktx2.basic_dfd(fmt)
        assert len(dfd) == 4 + 24 + 16 * n
        total, w0, w1 = struct.unpack_from("<III", dfd)
        assert total == len(dfd) and w0 == 0 and w1 == 2 | ((24 + 16 * n) << 16)


def test_key_value_data_sorted_and_padded(tmp_path):
    data = ktx2.encode_ktx2([np.ones((2, 2, 3))], kind="2d",
                            key_values={"b": "xy", "a": b"\x00" * 5, "Z": "1"})
    kvd_off, kvd_len = struct.unpack_from("<II", data, 56)
    pos, keys = kvd_off, []
    while pos < kvd_off + kvd_len:
        (n,) = struct.unpack_from("<I", data, pos)
        keys.append(data[pos + 4:pos + 4 + n].split(b"\0", 1)[0].decode())
        assert (pos + 4 + n + (-n % 4)) % 4 == 0
        pos += 4 + n + (-n % 4)
    assert pos == kvd_off + kvd_len
    assert keys == ["KTXwriter", "Z", "a", "b"]  # Unicode code point order


@pytest.mark.parametrize("levels, options, message", [
    ([np.full((2, 2, 3), np.nan)], {"kind": "2d"}, "non-finite"),
    ([np.full((2, 2, 3), 7e4)], {"kind": "2d"}, "half float"),
    ([np.full((2, 2, 3), 7e4)], {"kind": "2d", "vk_format": 123}, "E5B9G9R9"),
    ([np.ones((6, 4, 2, 3))], {"kind": "cube"}, "cube level"),
    ([np.ones((4, 4, 3)), np.ones((3, 2, 3))], {"kind": "2d"}, "level 1"),
    ([np.ones((2, 2, 3))] * 3, {"kind": "2d"}, "at most 2"),
    ([np.ones((2, 2, 3))], {"kind": "2d", "vk_format": 37}, "not supported"),
    ([np.ones((2, 2, 3))], {"kind": "2d", "key_values": {"KTXorientation": "rd"}}, "reserved"),
])
def test_bad_input_is_one_line_error(levels, options, message):
    with pytest.raises(ktx2.KTX2Error, match=message) as err:
        ktx2.encode_ktx2(levels, **options)
    assert "\n" not in str(err.value)


def test_reader_refuses_damaged_files(tmp_path):
    good = ktx2.encode_ktx2([np.ones((4, 4, 3))], kind="2d")
    with pytest.raises(ktx2.KTX2Error, match="identifier"):
        ktx2.read_ktx2(b"x" + good[1:])
    with pytest.raises(ktx2.KTX2Error, match="past the end|truncated"):
        ktx2.read_ktx2(good[:-8])
    bad = bytearray(good)
    struct.pack_into("<I", bad, 12, 37)
    with pytest.raises(ktx2.KTX2Error, match="vkFormat 37"):
        ktx2.read_ktx2(bytes(bad))


def test_independent_reader_skips_with_a_reason_without_node(monkeypatch, tmp_path_factory):
    import shutil

    import node_readers

    monkeypatch.setattr(shutil, "which", lambda name: None)
    with pytest.raises(pytest.skip.Exception, match="node is not installed"):
        node_readers.node_package_dir(tmp_path_factory, "ktx-parse")
