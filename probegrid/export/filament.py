"""A filtered environment as the KTX1 files Filament's ``IndirectLight`` and ``Skybox`` load
(what ``cmgen --format=ktx --deploy`` writes).

Mip -> roughness
    Filament's shader reads the reflections cube at ``lod = (levels - 1) r (2 - r)`` for
    perceptual roughness ``r`` (``perceptualRoughnessToLod``; ``levels`` the texture's mip
    count), so mip ``k`` must hold the GGX lobe at ``r_k = 1 - sqrt(1 - k / (levels - 1))``,
    ``alpha_k = r_k^2`` (:func:`filament_roughness`; cmgen's and ``IBLPrefilterContext``'s
    ``lodToPerceptualRoughness``), not probegrid's ``r = k / (levels - 1)``, which Filament
    would read as rougher than it is. Mips from the cube size down to 16^2 (cmgen's
    ``--ibl-min-lod-size``); mip 0 is the input (``r = 0``).
Orientation
    The faces in the OpenGL / KTX2 table (+X, -X, +Y, -Y, +Z, -Z, each face's first row
    ``t = 0``), in glTF's (and Filament's) right-handed world frame: Filament samples the cube
    with the world direction as it is, so probegrid's faces go in unchanged -- the same bytes
    (up to rounding) as ``cmgen --no-mirror`` makes of probegrid's cross; cmgen's default
    mirror is for inputs that are not yet in this table.
File
    KTX 1.1 (``«KTX 11»``), little-endian, ``glType = glInternalFormat =
    glBaseInternalFormat = GL_R11F_G11F_B10F`` (0x8C3A), ``glTypeSize`` 1, ``glFormat``
    ``GL_RGB``, six faces, one ``imageSize`` per mip (one face's bytes: a non-array cube map),
    texels packed as ``UINT_10F_11F_11F_REV`` (red in bits 0-10, green 11-21, blue 22-31):
    exactly the fields cmgen writes and Filament's ``image::ktx::createTexture`` maps
    (``toPixelDataType`` reads ``glType == R11F_G11F_B10F``). Negative values become 0 and
    values above 65024 clip (the format's range); 6 (5 for blue) mantissa bits.
SH
    The IBL file's key ``sh`` holds 9 lines ``"r g b\\n"``: the pre-scaled irradiance/pi
    coefficients ``IndirectLight::Builder::irradiance(3, sh)`` takes
    (:func:`probegrid.export.shforms.filament_prescaled`, cmgen's ``--sh-shader`` form), which
    ``Ktx1Bundle::getSphericalHarmonics`` parses (27 numbers, whitespace-separated). The key's
    value is not NUL-terminated (as cmgen writes it).

Pure: arrays in, bytes and files out. References: google/filament ``libs/image`` (``Ktx1Bundle``,
``KtxUtility.h``), ``tools/cmgen`` (``iblRoughnessPrefilter``, ``lodToPerceptualRoughness``),
``shaders/src/light_indirect.fs``; the KTX 1.1 specification (Khronos).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._fs import atomic_write_bytes
from probegrid.export import shforms

__all__ = [
    "IBL_FILE",
    "MIN_MIP",
    "SKYBOX_FILE",
    "check_size",
    "decode_r11g11b10",
    "encode_ktx1",
    "encode_r11g11b10",
    "filament_lod",
    "filament_roughness",
    "mip_count",
    "sh_text",
    "specular_chain",
    "write_filament_ibl",
]

#: The written files (cmgen's ``<name>_ibl.ktx`` and ``<name>_skybox.ktx``).
IBL_FILE = "environment_ibl.ktx"
SKYBOX_FILE = "environment_skybox.ktx"
#: The smallest mip written (cmgen's default ``--ibl-min-lod-size``).
MIN_MIP = 16
#: KTX 1.1 identifier and the GL enums cmgen writes.
KTX1_MAGIC = bytes([0xAB, 0x4B, 0x54, 0x58, 0x20, 0x31, 0x31, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A])
GL_RGB = 0x1907
GL_R11F_G11F_B10F = 0x8C3A
_ENDIAN = 0x04030201
_UF_MAX = 65024.0  # the largest finite 11- and 10-bit unsigned float


def check_size(size: int) -> None:
    """ValueError unless ``size`` is a power of two of at least ``2 * MIN_MIP`` (two mips:
    Filament's lod scale is ``levels - 1``)."""
    if size < 2 * MIN_MIP or size & (size - 1):
        raise ValueError(f"--format filament needs a power-of-two cube size of at least "
                         f"{2 * MIN_MIP} (mips down to {MIN_MIP}^2), got {size}")


def mip_count(size: int) -> int:
    """Mips from ``size`` down to ``MIN_MIP`` (both included)."""
    check_size(size)
    return int(np.log2(size // MIN_MIP)) + 1


def filament_roughness(levels: int) -> NDArray[np.float64]:
    """Perceptual roughness of each mip as Filament samples it: ``r_k = 1 - sqrt(1 - k /
    (levels - 1))`` (the inverse of ``lod = (levels - 1) r (2 - r)``)."""
    t = np.arange(levels, dtype=np.float64) / max(levels - 1, 1)
    return 1.0 - np.sqrt(np.clip(1.0 - t, 0.0, 1.0))


def filament_lod(r: ArrayLike, levels: int) -> NDArray[np.float64]:
    """The mip Filament's shader reads for perceptual roughness ``r``."""
    rr = np.asarray(r, dtype=np.float64)
    return (levels - 1) * rr * (2.0 - rr)


def specular_chain(cube: ArrayLike) -> list[NDArray[np.float32]]:
    """The GGX chain at :func:`filament_roughness` (``alpha = r^2``), level ``k`` of size
    ``n >> k`` down to 16^2, in probegrid's (glTF-frame) face table."""
    from probegrid.core.specular import ggx_filter

    c = np.asarray(cube, dtype=np.float32)
    n = int(c.shape[1])
    r = filament_roughness(mip_count(n))
    return [c.copy()] + [ggx_filter(c, float(rk * rk), n >> k)
                         for k, rk in enumerate(r) if k > 0]


def _to_uf(x: NDArray[np.float64], mbits: int) -> NDArray[np.uint32]:
    """Unsigned float with a 5-bit exponent (bias 15) and ``mbits`` mantissa bits, rounded to
    nearest; values <= 0 or NaN -> 0, above the range -> the largest finite value."""
    v = np.nan_to_num(np.clip(x, 0.0, _UF_MAX), nan=0.0)
    out = np.zeros(v.shape, np.uint32)
    pos = v > 0
    e = np.floor(np.log2(np.where(pos, v, 1.0)))
    e = np.maximum(e, -14.0)  # below 2^-14: denormals with the exponent of 2^-14
    m = np.rint(v / 2.0 ** e * (1 << mbits))  # in [0, 2^(mbits+1)]
    normal = m >= (1 << mbits)
    carry = m >= (2 << mbits)  # rounded up to the next power of two
    e = np.where(carry, e + 1, e)
    m = np.where(carry, 1 << mbits, m)
    bits_e = np.where(normal, e + 15, 0).astype(np.int64)
    bits_m = np.where(normal, m - (1 << mbits), m).astype(np.int64)
    big = bits_e > 30
    bits_e = np.where(big, 30, bits_e)
    bits_m = np.where(big, (1 << mbits) - 1, bits_m)
    out[pos] = ((bits_e << mbits) | bits_m)[pos].astype(np.uint32)
    return out


def _from_uf(bits: NDArray[np.uint32], mbits: int) -> NDArray[np.float64]:
    e = ((bits >> mbits) & 31).astype(np.float64)
    m = (bits & ((1 << mbits) - 1)).astype(np.float64) / (1 << mbits)
    return np.where(e == 0, m * 2.0 ** -14, 2.0 ** (e - 15) * (1.0 + m))


def encode_r11g11b10(rgb: ArrayLike) -> NDArray[np.uint32]:
    """``(..., 3)`` linear RGB -> ``UINT_10F_11F_11F_REV`` words."""
    c = np.asarray(rgb, dtype=np.float64)
    return (_to_uf(c[..., 0], 6) | (_to_uf(c[..., 1], 6) << 11)
            | (_to_uf(c[..., 2], 5) << 22)).astype(np.uint32)


def decode_r11g11b10(words: ArrayLike) -> NDArray[np.float32]:
    """``UINT_10F_11F_11F_REV`` words -> ``(..., 3)`` RGB."""
    w = np.asarray(words, dtype=np.uint32)
    return np.stack([_from_uf(w & 0x7FF, 6), _from_uf((w >> 11) & 0x7FF, 6),
                     _from_uf((w >> 22) & 0x3FF, 5)], axis=-1).astype(np.float32)


def sh_text(sh: ArrayLike) -> str:
    """The ``sh`` key's value: 9 lines ``"r g b\\n"`` of pre-scaled coefficients."""
    c = np.asarray(sh, dtype=np.float64).reshape(9, 3)
    return "".join(" ".join(f"{float(v):.9g}" for v in row) + "\n" for row in c)


def encode_ktx1(levels: Sequence[ArrayLike], *, key_values: dict[str, str] | None = None
                ) -> bytes:
    """A KTX 1.1 cube map, R11F_G11F_B10F, from ``levels`` (``(6, s, s, >=3)`` each, halving)."""
    lv = [np.asarray(x, dtype=np.float32)[..., :3] for x in levels]
    size = int(lv[0].shape[1])
    for k, x in enumerate(lv):
        if x.shape != (6, size >> k, size >> k, 3):
            raise ValueError(f"level {k} must be 6 faces of {size >> k}^2 RGB, got {x.shape}")
    kv = b""
    for key, value in (key_values or {}).items():
        body = key.encode() + b"\0" + value.encode()
        kv += struct.pack("<I", len(body)) + body + b"\0" * (3 - (len(body) + 3) % 4)
    head = KTX1_MAGIC + struct.pack(
        "<13I", _ENDIAN, GL_R11F_G11F_B10F, 1, GL_RGB, GL_R11F_G11F_B10F, GL_R11F_G11F_B10F,
        size, size, 0, 0, 6, len(lv), len(kv))
    parts = [head, kv]
    for x in lv:
        words = encode_r11g11b10(x).astype("<u4")
        parts.append(struct.pack("<I", words[0].nbytes))  # one face (a non-array cube)
        parts.append(words.tobytes())
    return b"".join(parts)


def write_filament_ibl(out_dir: Path, chain: Sequence[NDArray[np.float32]], sh: ArrayLike
                       ) -> list[dict[str, Any]]:
    """Write ``environment_ibl.ktx`` (the chain, SH in key ``sh``) and
    ``environment_skybox.ktx`` (mip 0 alone) into ``out_dir``; return their manifest entries.

    ``chain`` is :func:`specular_chain`'s output, ``sh`` probegrid's radiance SH (9, 3)."""
    size = int(chain[0].shape[1]) if len(chain) else 0
    n = mip_count(size)
    if len(chain) != n:
        raise ValueError(f"the chain must be {n} cubes of {size} >> k texels")
    pre = shforms.filament_prescaled(sh)
    ibl = encode_ktx1(chain, key_values={"sh": sh_text(pre)})
    sky = encode_ktx1(chain[:1])
    atomic_write_bytes(out_dir / IBL_FILE, ibl)
    atomic_write_bytes(out_dir / SKYBOX_FILE, sky)
    r = [float(x) for x in filament_roughness(n)]
    conventions = ("KTX 1.1 cube, R11F_G11F_B10F, faces +X,-X,+Y,-Y,+Z,-Z in the OpenGL/KTX2 "
                   "table in glTF's world frame (cmgen --no-mirror), mip k at perceptual "
                   "roughness 1 - sqrt(1 - k/(levels-1)) (Filament's lod = (levels-1) r (2-r)), "
                   "key 'sh': IndirectLight::Builder::irradiance(3, sh) pre-scaled irradiance/pi")
    return [
        {"path": IBL_FILE, "kind": "specular", "consumer": "Filament (IndirectLight)",
         "format": "ktx1", "dtype": "r11g11b10f", "layout": "faces", "face_size": size,
         "levels": n, "roughness": r, "sh_key": "sh", "conventions": conventions},
        {"path": SKYBOX_FILE, "kind": "skybox", "consumer": "Filament (Skybox)",
         "format": "ktx1", "dtype": "r11g11b10f", "layout": "faces", "face_size": size,
         "levels": 1, "roughness": [0.0], "conventions": conventions},
    ]
