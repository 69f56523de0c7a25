"""KTX 2.0 writer and reader for linear HDR textures: 2D, cube, cube arrays and 3D, with mips.

Formats (``vkFormat``):

* ``97``  ``VK_FORMAT_R16G16B16A16_SFLOAT`` (typeSize 2, texel block 8 bytes): half floats,
  round to nearest even; what glTF-IBL-Sampler writes.
* ``109`` ``VK_FORMAT_R32G32B32A32_SFLOAT`` (typeSize 4, 16 bytes): float32, exact.
* ``123`` ``VK_FORMAT_E5B9G9R9_UFLOAT_PACK32`` (typeSize 4, 4 bytes): RGB with a shared 5-bit
  exponent, what Bevy ships. Encoded exactly as the Vulkan specification's "Shared exponent
  conversion" (identical to OpenGL's EXT_texture_shared_exponent): N = 9 mantissa bits, bias
  B = 15, Emax = 31; components clamped to ``[0, 65408]`` (NaN -> 0), ``exp_shared_p =
  max(-B-1, floor(log2(max))) + 1 + B``, ``max_s = floor(max / 2^(exp_shared_p-B-N) + 0.5)``,
  ``exp_shared = exp_shared_p + (max_s == 2^N)``, each ``c_s = floor(c / 2^(exp_shared-B-N) +
  0.5)``; decoded as ``c_s * 2^(exp - B - N)``. Negative input is clamped to 0 (the format is
  unsigned), as the specification says.

File layout (KTX 2.0 specification, Khronos, sections 3-4): 12-byte identifier; header
(vkFormat, typeSize, pixelWidth/Height/Depth, layerCount, faceCount, levelCount,
supercompressionScheme); index (dfd/kvd offsets and lengths, sgd = 0); level index (level 0
first); the Basic Data Format Descriptor; key/value data sorted by key, each entry padded to 4
bytes, with ``KTXwriter``; then the mip levels **smallest first**, each uncompressed level
preceded by ``mipPadding`` to ``lcm(texel block size, 4)`` bytes of the file offset (none when
supercompressed). A level holds layers, then faces (+X, -X, +Y, -Y, +Z, -Z), then z slices, then
rows (row 0 first), then texels, tightly packed. No ``KTXorientation`` key: cube faces are ``rd``
(row 0 at the top, as :mod:`probegrid.core.cubemap` stores them), the default.

The DFD is one Khronos basic descriptor block, version 2 (KDF 1.3), colour model RGBSDA,
primaries BT.709, transfer LINEAR, straight alpha, 1x1x1x1 texel blocks, ``bytesPlane0`` = the
texel size, and one sample per channel as libktx's ``vk2dfd`` writes it: for the SFLOAT formats
channels R, G, B, A (ids 0, 1, 2, 15) with qualifiers FLOAT|SIGNED, sampleLower = -1.0f and
sampleUpper = 1.0f; for E5B9G9R9 six samples, each channel's 9-bit mantissa (bit offsets 0, 9,
18, sampleLower 0, sampleUpper 8448) followed by the shared 5-bit exponent (bit offset 27,
qualifier EXPONENT, sampleLower 15, sampleUpper 31) -- the descriptor libktx compares
E5B9G9R9 files against (``e5b9g9r9_ufloat_comparator`` in KTX-Software lib/texture2.c).

Supercompression: scheme 0 (none) or 2 (Zstandard, one frame per level, via the optional
``zstandard`` package); the DFD keeps the uncompressed values, as the specification requires.

The reader reads this subset (the three formats, schemes 0 and 2) back to float32 arrays and the
header, DFD and key/value data; it is what the tests use beside an independent reader (npm's
``ktx-parse``).

References: KTX File Format Specification 2.0 (KhronosGroup/KTX-Specification ktxspec.adoc);
Khronos Data Format Specification 1.3, sections 5 and 15; Vulkan specification, "Shared Exponent
Conversion"; RFC 8878 (Zstandard).
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._version import __version__
from probegrid.errors import ProbegridError

__all__ = [
    "IDENTIFIER",
    "VK_FORMAT_E5B9G9R9_UFLOAT_PACK32",
    "VK_FORMAT_R16G16B16A16_SFLOAT",
    "VK_FORMAT_R32G32B32A32_SFLOAT",
    "KTX2Error",
    "KTX2Texture",
    "basic_dfd",
    "decode_rgb9e5",
    "encode_ktx2",
    "encode_ktx2_parts",
    "encode_rgb9e5",
    "read_ktx2",
    "write_ktx2",
    "write_parts",
]

IDENTIFIER: Final[bytes] = bytes([0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB,
                                  0x0D, 0x0A, 0x1A, 0x0A])
VK_FORMAT_R16G16B16A16_SFLOAT: Final = 97
VK_FORMAT_R32G32B32A32_SFLOAT: Final = 109
VK_FORMAT_E5B9G9R9_UFLOAT_PACK32: Final = 123

SUPERCOMPRESSION_NONE: Final = 0
SUPERCOMPRESSION_ZSTD: Final = 2

#: vkFormat -> (name, typeSize, texel block size in bytes, channels stored)
_FORMATS: Final[dict[int, tuple[str, int, int, int]]] = {
    97: ("R16G16B16A16_SFLOAT", 2, 8, 4),
    109: ("R32G32B32A32_SFLOAT", 4, 16, 4),
    123: ("E5B9G9R9_UFLOAT_PACK32", 4, 4, 3),
}
_FORMAT_NAMES: Final[dict[str, int]] = {v[0]: k for k, v in _FORMATS.items()}

# Khronos Data Format enumerants (khr_df.h)
_KHR_DF_MODEL_RGBSDA = 1
_KHR_DF_PRIMARIES_BT709 = 1
_KHR_DF_TRANSFER_LINEAR = 1
_KHR_DF_VERSIONNUMBER_1_3 = 2
_QUAL_EXPONENT = 0x20
_QUAL_SIGNED = 0x40
_QUAL_FLOAT = 0x80
_CHANNEL_ALPHA = 15

# RGB9E5 constants (Vulkan "Shared exponent conversion")
_E5_N = 9
_E5_B = 15
_E5_EMAX = 31
#: largest encodable value, (2^N - 1) / 2^N * 2^(Emax - B) = 65408
RGB9E5_MAX: Final[float] = (2**_E5_N - 1) / 2**_E5_N * 2.0 ** (_E5_EMAX - _E5_B)
HALF_MAX: Final[float] = 65504.0

Kind = Literal["2d", "cube", "3d"]


class KTX2Error(ProbegridError, ValueError):
    """A KTX2 file this module cannot read (or data it cannot write); one line."""


# --------------------------------------------------------------------------- RGB9E5
def encode_rgb9e5(rgb: ArrayLike) -> NDArray[np.uint32]:
    """``(..., 3)`` float RGB -> ``(...)`` uint32 ``E5B9G9R9`` (R in bits 0-8, G 9-17, B 18-26,
    exponent 27-31), by the Vulkan specification's conversion (see the module docstring)."""
    c = np.asarray(rgb, dtype=np.float64)
    if c.shape[-1:] != (3,):
        raise ValueError(f"encode_rgb9e5 needs (..., 3) RGB, got shape {c.shape}")
    c = np.where(np.isnan(c), 0.0, c)
    c = np.clip(c, 0.0, RGB9E5_MAX)
    max_c = c.max(axis=-1)
    # floor(log2(max_c)) exactly: max_c = m 2^e with m in [0.5, 1) -> e - 1; -inf at 0
    _, e = np.frexp(max_c)
    floor_log2 = np.where(max_c > 0, e.astype(np.int64) - 1, -_E5_B - 1)
    exp_p = np.maximum(-_E5_B - 1, floor_log2) + 1 + _E5_B
    max_s = np.floor(np.ldexp(max_c, -(exp_p - _E5_B - _E5_N)) + 0.5)
    exp_shared = np.where(max_s == 2**_E5_N, exp_p + 1, exp_p)
    scaled = np.floor(np.ldexp(c, -(exp_shared - _E5_B - _E5_N)[..., None]) + 0.5)
    m = scaled.astype(np.uint32)
    return (m[..., 0] | (m[..., 1] << 9) | (m[..., 2] << 18)
            | (exp_shared.astype(np.uint32) << 27)).astype(np.uint32)


def decode_rgb9e5(packed: ArrayLike) -> NDArray[np.float32]:
    """``(...)`` uint32 ``E5B9G9R9`` -> ``(..., 3)`` float32 RGB (``mantissa 2^(e - 24)``)."""
    p = np.asarray(packed, dtype=np.uint32)
    m = np.stack([p & 0x1FF, (p >> 9) & 0x1FF, (p >> 18) & 0x1FF], axis=-1).astype(np.float64)
    e = (p >> 27).astype(np.int64) - _E5_B - _E5_N
    return np.ldexp(m, e[..., None]).astype(np.float32)


# --------------------------------------------------------------------------- DFD
def _sample(bit_offset: int, bit_length: int, channel: int, lower: int, upper: int) -> bytes:
    return struct.pack("<IIII", bit_offset | ((bit_length - 1) << 16) | (channel << 24), 0,
                       lower & 0xFFFFFFFF, upper & 0xFFFFFFFF)


def _f32_bits(x: float) -> int:
    return int(np.array(x, dtype="<f4").view("<u4"))


def basic_dfd(vk_format: int) -> bytes:
    """The Data Format Descriptor (``dfdTotalSize`` first) of a supported vkFormat."""
    if vk_format not in _FORMATS:
        raise KTX2Error(f"vkFormat {vk_format} is not supported (97, 109 or 123)")
    _, _, block, _ = _FORMATS[vk_format]
    samples: list[bytes] = []
    if vk_format == VK_FORMAT_E5B9G9R9_UFLOAT_PACK32:
        for ch in range(3):
            samples.append(_sample(9 * ch, 9, ch, 0, 8448))
            samples.append(_sample(27, 5, ch | _QUAL_EXPONENT, 15, 31))
    else:
        bits = 8 * (block // 4)
        for i, ch in enumerate((0, 1, 2, _CHANNEL_ALPHA)):
            samples.append(_sample(bits * i, bits, ch | _QUAL_FLOAT | _QUAL_SIGNED,
                                   _f32_bits(-1.0), _f32_bits(1.0)))
    block_size = 24 + 16 * len(samples)
    head = struct.pack(
        "<IIBBBBBBBB8B",
        0,  # vendorId 0 (Khronos), descriptorType 0 (basic)
        _KHR_DF_VERSIONNUMBER_1_3 | (block_size << 16),
        _KHR_DF_MODEL_RGBSDA, _KHR_DF_PRIMARIES_BT709, _KHR_DF_TRANSFER_LINEAR, 0,
        0, 0, 0, 0,  # texelBlockDimension0..3: 1x1x1x1
        block, 0, 0, 0, 0, 0, 0, 0,  # bytesPlane0..7
    )
    body = head + b"".join(samples)
    return struct.pack("<I", 4 + len(body)) + body


def parse_dfd(data: bytes) -> dict[str, object]:
    """The fields of a DFD holding one basic descriptor block (as :func:`basic_dfd` writes)."""
    if len(data) < 4 + 24:
        raise KTX2Error("data format descriptor is shorter than one basic block")
    total, w0, w1 = struct.unpack_from("<III", data, 0)
    model, primaries, transfer, flags = data[12:16]
    dims = list(data[16:20])
    planes = list(data[20:28])
    block_size = w1 >> 16
    n = (block_size - 24) // 16
    if total != len(data) or block_size != len(data) - 4 or n < 0 or (block_size - 24) % 16:
        raise KTX2Error(f"data format descriptor sizes do not add up (total {total}, block "
                        f"{block_size}, {len(data)} bytes)")
    samples = []
    for i in range(n):
        word, _pos, lower, upper = struct.unpack_from("<IIII", data, 28 + 16 * i)
        samples.append({"bitOffset": word & 0xFFFF, "bitLength": ((word >> 16) & 0xFF) + 1,
                        "channelType": word >> 24, "sampleLower": lower, "sampleUpper": upper})
    return {"totalSize": total, "vendorId": w0 & 0x1FFFF, "descriptorType": w0 >> 17,
            "versionNumber": w1 & 0xFFFF, "descriptorBlockSize": block_size,
            "colorModel": model, "colorPrimaries": primaries, "transferFunction": transfer,
            "flags": flags, "texelBlockDimension": dims, "bytesPlane": planes,
            "samples": samples}


# --------------------------------------------------------------------------- texels
def _check_format(vk_format: int | str) -> int:
    if isinstance(vk_format, str):
        name = vk_format.upper().removeprefix("VK_FORMAT_")
        if name not in _FORMAT_NAMES:
            raise KTX2Error(f"vkFormat {vk_format!r} is not supported: "
                            + ", ".join(v[0] for v in _FORMATS.values()))
        return _FORMAT_NAMES[name]
    if vk_format not in _FORMATS:
        raise KTX2Error(f"vkFormat {vk_format} is not supported: "
                        + ", ".join(f"{k} ({v[0]})" for k, v in _FORMATS.items()))
    return int(vk_format)


def _check_range(a: NDArray[np.floating], p: int, vk_format: int) -> None:
    """KTX2Error unless level ``p`` is finite and within the format's range (one pass each for
    the minimum and maximum; the counts are computed only on failure)."""
    lo, hi = (float(a.min()), float(a.max())) if a.size else (0.0, 0.0)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        bad = int(np.count_nonzero(~np.isfinite(a)))
        raise KTX2Error(f"level {p} holds {bad} non-finite values (NaN or inf)")
    if vk_format == VK_FORMAT_E5B9G9R9_UFLOAT_PACK32 and hi > RGB9E5_MAX:
        big = int(np.count_nonzero(a[..., :3] > RGB9E5_MAX))
        raise KTX2Error(f"{big} values exceed E5B9G9R9's largest value {RGB9E5_MAX:g}; use "
                        "vkFormat 109 (R32G32B32A32_SFLOAT)")
    if vk_format == VK_FORMAT_R16G16B16A16_SFLOAT and max(-lo, hi) > HALF_MAX:
        big = int(np.count_nonzero(np.abs(a) > HALF_MAX))
        raise KTX2Error(f"{big} values exceed half float's largest value {HALF_MAX:g}; use "
                        "vkFormat 109 (R32G32B32A32_SFLOAT)")


#: Texels per block of the threaded conversion (numpy releases the GIL while casting).
_BLOCK_TEXELS = 1 << 20


def _encode_rows(src: NDArray[np.floating], dst: NDArray[Any], vk_format: int) -> None:
    if vk_format == VK_FORMAT_E5B9G9R9_UFLOAT_PACK32:
        dst[:] = encode_rgb9e5(src[:, :3])
    else:
        dst[:, :3] = src[:, :3]
        dst[:, 3] = src[:, 3] if src.shape[1] == 4 else 1.0


def _encode_texels(a: NDArray[np.floating], vk_format: int) -> memoryview:
    """``(..., C)`` float texels (C = 3 or 4) -> the level's bytes in ``vk_format`` (large
    levels converted in blocks on all cores)."""
    src = a.reshape(-1, a.shape[-1])
    if vk_format == VK_FORMAT_E5B9G9R9_UFLOAT_PACK32:
        out = np.empty(src.shape[0], dtype="<u4")
    else:
        dtype = "<f2" if vk_format == VK_FORMAT_R16G16B16A16_SFLOAT else "<f4"
        out = np.empty((src.shape[0], 4), dtype=dtype)
    starts = range(0, src.shape[0], _BLOCK_TEXELS)
    workers = min(len(starts), os.cpu_count() or 1)
    if workers > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(lambda s: _encode_rows(src[s:s + _BLOCK_TEXELS],
                                                 out[s:s + _BLOCK_TEXELS], vk_format), starts))
    else:
        _encode_rows(src, out, vk_format)
    return memoryview(out.reshape(-1).view(np.uint8))


def _decode_texels(raw: bytes, shape: tuple[int, ...], vk_format: int) -> NDArray[np.float32]:
    if vk_format == VK_FORMAT_E5B9G9R9_UFLOAT_PACK32:
        return decode_rgb9e5(np.frombuffer(raw, dtype="<u4").reshape(shape))
    dtype = "<f2" if vk_format == VK_FORMAT_R16G16B16A16_SFLOAT else "<f4"
    return np.frombuffer(raw, dtype=dtype).reshape(shape + (4,)).astype(np.float32)


def _level_dims(kind: Kind, base: tuple[int, int, int], p: int) -> tuple[int, int, int]:
    w, h, d = base
    return (max(1, w >> p), max(1, h >> p), max(1, d >> p) if kind == "3d" else 0)


def _align(offset: int, alignment: int) -> int:
    return -offset % alignment


# --------------------------------------------------------------------------- writer
def _base_and_layers(kind: Kind, level0: NDArray[np.floating], layered: bool
                     ) -> tuple[tuple[int, int, int], int]:
    """(pixelWidth, pixelHeight, pixelDepth) and layerCount of level 0's array."""
    shape = level0.shape
    lead = 1 if layered else 0
    want = {"2d": 3, "cube": 4, "3d": 4}[kind] + lead
    if level0.ndim != want or shape[-1] not in (3, 4):
        form = {"2d": "(H, W, C)", "cube": "(6, N, N, C)", "3d": "(D, H, W, C)"}[kind]
        raise KTX2Error(f"a {kind} level must be {'(layers, ...) of ' if layered else ''}"
                        f"{form} with C = 3 or 4, got shape {shape}")
    layers = int(shape[0]) if layered else 0
    if layered and layers < 1:
        raise KTX2Error("an array texture needs at least one layer")
    s = shape[lead:]
    if kind == "2d":
        return (int(s[1]), int(s[0]), 0), layers
    if kind == "cube":
        if s[0] != 6 or s[1] != s[2]:
            raise KTX2Error(f"a cube level must be (6, N, N, C), got {tuple(s)}")
        return (int(s[2]), int(s[1]), 0), layers
    return (int(s[2]), int(s[1]), int(s[0])), layers


def encode_ktx2(levels: Sequence[ArrayLike], **options: Any) -> bytes:
    """The bytes of a KTX2 file holding ``levels``; see :func:`encode_ktx2_parts`."""
    return b"".join(encode_ktx2_parts(levels, **options))


def encode_ktx2_parts(
    levels: Sequence[ArrayLike],
    *,
    kind: Kind,
    vk_format: int | str = VK_FORMAT_R16G16B16A16_SFLOAT,
    layered: bool = False,
    supercompression: Literal["none", "zstd"] = "none",
    zstd_level: int = 3,
    key_values: Mapping[str, str | bytes] | None = None,
) -> list[bytes | memoryview]:
    """The pieces of a KTX2 file holding ``levels`` (level 0, the largest, first), in file
    order (joined, they are the file; :func:`write_ktx2` writes them without joining).

    Parameters
    ----------
    levels
        Float RGB or RGBA arrays, level ``p`` of size ``max(1, size0 >> p)`` on each axis:
        ``(H, W, C)`` for ``kind="2d"``, ``(6, N, N, C)`` (faces +X, -X, +Y, -Y, +Z, -Z, row 0 at
        the top) for ``"cube"``, ``(D, H, W, C)`` (z slices, rows, texels) for ``"3d"``; with
        ``layered``, each has a leading layer axis (an array texture, ``layerCount`` = its
        length). RGB input gets alpha 1 in the RGBA formats.
    vk_format
        97, 109 or 123 (or their names without ``VK_FORMAT_``).
    supercompression
        ``"zstd"``: each level is one Zstandard frame (scheme 2; needs ``zstandard``),
        compressed at ``zstd_level`` (default 3, as ``toktx --zcmp``) on all cores.
    key_values
        Extra key/value pairs (str values are written NUL-terminated); ``KTXwriter`` is always
        written. Keys starting with ``KTX``/``ktx`` are reserved and refused.

    Raises ``KTX2Error`` (a ``ValueError``, one line) for shapes, values the format cannot hold
    (non-finite, beyond its range) and unknown options, before anything is encoded.
    """
    fmt = _check_format(vk_format)
    if kind not in ("2d", "cube", "3d"):
        raise KTX2Error(f"kind must be '2d', 'cube' or '3d', got {kind!r}")
    if supercompression not in ("none", "zstd"):
        raise KTX2Error(f"supercompression must be 'none' or 'zstd', got {supercompression!r}")
    arrays = [np.asarray(lv, dtype=np.float32) for lv in levels]
    if not arrays:
        raise KTX2Error("a KTX2 file needs at least one level")
    base, layers = _base_and_layers(kind, arrays[0], layered)
    if kind == "3d" and layered:
        raise KTX2Error("3D array textures are not supported")
    max_levels = max(base).bit_length()  # floor(log2(max)) + 1
    if len(arrays) > max_levels:
        raise KTX2Error(f"{len(arrays)} levels for a {base[0]}x{base[1]} texture; at most "
                        f"{max_levels}")
    for p, a in enumerate(arrays):
        w, h, d = _level_dims(kind, base, p)
        lead = (layers,) if layered else ()
        want = lead + {"2d": (h, w), "cube": (6, h, w), "3d": (d, h, w)}[kind]
        if a.shape[:-1] != want or a.shape[-1] != arrays[0].shape[-1]:
            raise KTX2Error(f"level {p} has shape {a.shape}, expected {want + a.shape[-1:]}")
        _check_range(a, p, fmt)
    kv: dict[str, bytes] = {"KTXwriter": f"probegrid {__version__}".encode() + b"\0"}
    for key, value in (key_values or {}).items():
        if not key or key[:3].upper() == "KTX" or "\0" in key:
            raise KTX2Error(f"key {key!r} is reserved or invalid (keys starting with KTX/ktx "
                            "belong to the KTX specification)")
        kv[key] = value.encode() + b"\0" if isinstance(value, str) else bytes(value)

    compressor = None
    if supercompression == "zstd":
        try:
            import zstandard
        except ImportError:  # pragma: no cover - it is a dependency
            raise KTX2Error("Zstandard supercompression needs the 'zstandard' package") from None
        compressor = zstandard.ZstdCompressor(level=zstd_level, write_content_size=True,
                                              threads=-1)  # one frame, all cores

    raw = [_encode_texels(a, fmt) for a in arrays]
    payload: list[bytes | memoryview] = [compressor.compress(r) if compressor else r
                                         for r in raw]

    _, type_size, block, _ = _FORMATS[fmt]
    n_levels = len(arrays)
    dfd = basic_dfd(fmt)
    kvd = b""
    for key in sorted(kv):  # sorted by Unicode code points of the keys
        entry = key.encode() + b"\0" + kv[key]
        kvd += struct.pack("<I", len(entry)) + entry + b"\0" * _align(len(entry), 4)
    index_end = 80 + 24 * n_levels
    dfd_offset = index_end
    kvd_offset = dfd_offset + len(dfd)
    data_start = kvd_offset + len(kvd)
    alignment = math.lcm(block, 4) if compressor is None else 1
    offsets = [0] * n_levels
    pos = data_start
    chunks: list[bytes | memoryview] = []
    for p in reversed(range(n_levels)):  # smallest level first in the file
        pad = _align(pos, alignment)
        chunks += [b"\0" * pad, payload[p]]
        offsets[p] = pos + pad
        pos += pad + _nbytes(payload[p])
    header = IDENTIFIER + struct.pack(
        "<9I", fmt, type_size, base[0], base[1], base[2], layers,
        6 if kind == "cube" else 1, n_levels,
        SUPERCOMPRESSION_ZSTD if compressor else SUPERCOMPRESSION_NONE,
    ) + struct.pack("<IIIIQQ", dfd_offset, len(dfd), kvd_offset if kvd else 0, len(kvd), 0, 0)
    index = b"".join(struct.pack("<QQQ", offsets[p], _nbytes(payload[p]), _nbytes(raw[p]))
                     for p in range(n_levels))
    assert len(header) == 80
    return [header + index + dfd + kvd, *chunks]


def _nbytes(b: bytes | memoryview) -> int:
    return b.nbytes if isinstance(b, memoryview) else len(b)


def write_ktx2(path: str | os.PathLike[str], levels: Sequence[ArrayLike], **options: object
               ) -> Path:
    """:func:`encode_ktx2` into ``path``, written atomically (a temporary file, then
    ``os.replace``: never a half-written file). Returns the path."""
    parts = encode_ktx2_parts(levels, **options)  # type: ignore[arg-type]
    return write_parts(path, parts)


def write_parts(path: str | os.PathLike[str], parts: Sequence[bytes | memoryview]) -> Path:
    """Write ``parts`` one after the other into ``path`` atomically (temporary file, then
    ``os.replace``). Returns the path."""
    target = Path(path)
    tmp = target.with_name(f".{target.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as fh:
            fh.writelines(parts)
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    return target


# --------------------------------------------------------------------------- reader
@dataclass
class KTX2Texture:
    """A KTX2 file read back: header fields, the DFD, key/value data and float32 levels.

    ``levels[p]`` has the shapes :func:`encode_ktx2` takes, with 4 channels for the RGBA
    formats and 3 for E5B9G9R9.
    """

    vk_format: int
    type_size: int
    pixel_width: int
    pixel_height: int
    pixel_depth: int
    layer_count: int
    face_count: int
    level_count: int
    supercompression_scheme: int
    dfd: dict[str, object]
    dfd_bytes: bytes
    key_values: dict[str, bytes]
    levels: list[NDArray[np.float32]] = field(default_factory=list)
    #: per level: (byteOffset, byteLength, uncompressedByteLength), level 0 first
    level_index: list[tuple[int, int, int]] = field(default_factory=list)

    @property
    def kind(self) -> Kind:
        """``"cube"``, ``"3d"`` or ``"2d"``."""
        return "cube" if self.face_count == 6 else "3d" if self.pixel_depth else "2d"

    @property
    def format_name(self) -> str:
        """The vkFormat's name without ``VK_FORMAT_``."""
        return _FORMATS[self.vk_format][0]


def read_ktx2(source: str | os.PathLike[str] | bytes) -> KTX2Texture:
    """Read a KTX2 file of the subset :func:`encode_ktx2` writes (formats 97, 109, 123;
    supercompression none or Zstandard; 2D, cube, cube array or 3D).

    Raises ``KTX2Error`` (one line) for anything else or for an inconsistent file.
    """
    data = bytes(source) if isinstance(source, (bytes, bytearray)) else Path(source).read_bytes()
    if len(data) < 80 or data[:12] != IDENTIFIER:
        raise KTX2Error("not a KTX 2.0 file (bad identifier)")
    (fmt, type_size, width, height, depth, layers, faces, n_levels, scheme) = struct.unpack_from(
        "<9I", data, 12)
    dfd_off, dfd_len, kvd_off, kvd_len, _sgd_off, sgd_len = struct.unpack_from("<IIIIQQ", data, 48)
    if fmt not in _FORMATS:
        raise KTX2Error(f"vkFormat {fmt} is not supported (97, 109 or 123)")
    if scheme not in (SUPERCOMPRESSION_NONE, SUPERCOMPRESSION_ZSTD):
        raise KTX2Error(f"supercompression scheme {scheme} is not supported (0 or 2)")
    if type_size != _FORMATS[fmt][1]:
        raise KTX2Error(f"typeSize {type_size} is wrong for vkFormat {fmt}")
    if faces not in (1, 6) or width == 0 or (faces == 6 and (height != width or depth)):
        raise KTX2Error(f"faceCount {faces} with size {width}x{height}x{depth} is invalid")
    if depth and layers:
        raise KTX2Error("3D array textures are not supported")
    if height == 0:
        raise KTX2Error("1D textures are not supported")
    levels_n = max(1, n_levels)
    if 80 + 24 * levels_n > len(data) or dfd_off + dfd_len > len(data) or \
            kvd_off + kvd_len > len(data):
        raise KTX2Error("file is truncated (index points past its end)")
    if sgd_len:
        raise KTX2Error("supercompression global data is not supported")
    dfd_bytes = data[dfd_off:dfd_off + dfd_len]
    dfd = parse_dfd(dfd_bytes)
    if kvd_len and kvd_off != dfd_off + dfd_len:
        raise KTX2Error("key/value data does not follow the data format descriptor")
    kv: dict[str, bytes] = {}
    pos, end = kvd_off, kvd_off + kvd_len
    while pos < end:
        (n,) = struct.unpack_from("<I", data, pos)
        entry = data[pos + 4:pos + 4 + n]
        if len(entry) != n or b"\0" not in entry:
            raise KTX2Error("key/value data is malformed")
        key, value = entry.split(b"\0", 1)
        kv[key.decode("utf-8")] = value
        pos += 4 + n + _align(n, 4)
    kind: Kind = "cube" if faces == 6 else "3d" if depth else "2d"
    block = _FORMATS[fmt][2]
    index = [struct.unpack_from("<QQQ", data, 80 + 24 * p) for p in range(levels_n)]
    decompressor = None
    if scheme == SUPERCOMPRESSION_ZSTD:
        try:
            import zstandard
        except ImportError:  # pragma: no cover
            raise KTX2Error("reading Zstandard KTX2 needs the 'zstandard' package") from None
        decompressor = zstandard.ZstdDecompressor()
    out: list[NDArray[np.float32]] = []
    for p, (off, length, raw_len) in enumerate(index):
        w, h, d = _level_dims(kind, (width, height, depth), p)
        lead = (layers,) if layers else ()
        shape = lead + {"2d": (h, w), "cube": (6, h, w), "3d": (d, h, w)}[kind]
        expect = int(np.prod(shape)) * block
        if raw_len != expect:
            raise KTX2Error(f"level {p} has uncompressedByteLength {raw_len}, expected {expect}")
        if off + length > len(data):
            raise KTX2Error(f"level {p} runs past the end of the file")
        chunk = data[off:off + length]
        if decompressor is not None:
            chunk = decompressor.decompress(chunk, max_output_size=raw_len)
        elif off % math.lcm(block, 4):
            raise KTX2Error(f"level {p} at offset {off} is not aligned to "
                            f"{math.lcm(block, 4)} bytes")
        if len(chunk) != raw_len:
            raise KTX2Error(f"level {p} holds {len(chunk)} bytes, expected {raw_len}")
        out.append(_decode_texels(chunk, shape, fmt))
    return KTX2Texture(fmt, type_size, width, height, depth, layers, faces, n_levels, scheme,
                       dfd, dfd_bytes, kv, out, [tuple(map(int, i)) for i in index])
