"""A filtered environment as a glTF 2.0 file with ``EXT_lights_image_based``, arranged the way
Babylon.js' glTF loader reads it.

The extension (KhronosGroup/glTF, ``extensions/2.0/Vendor/EXT_lights_image_based``) holds one
light: ``specularImages`` (the first mips of a prefiltered cube, six RGBD-encoded PNG faces
each, down to 16^2), ``specularImageSize`` (mip 0's size), ``irradianceCoefficients`` (9 x 3),
``intensity`` and ``rotation``. What its text leaves open, settled from Babylon's loader
(``EXT_lights_image_based.ts``) and shaders:

Mip -> roughness
    The loader sets ``lodGenerationScale = (mips - 1) / log2(specularImageSize)`` and the PBR
    shader samples ``lod = log2(size * alphaG) * lodGenerationScale`` (``getLodFromAlphaG``;
    mips past the given ones are black). So mip ``k`` must hold the GGX lobe at
    ``alpha_k = 2^(k / scale) / size`` (:func:`babylon_alphas`; Babylon's own ``HDRFiltering``
    uses the same formula and ``alpha_0 = 0``, the unblurred input): the last given mip is
    ``alpha = 1``. This module filters each mip at exactly that alpha
    (:func:`probegrid.core.specular.ggx_filter`), not at probegrid's ``roughness = k/(levels-1)``.
Orientation
    Faces in the order +X, -X, +Y, -Y, +Z, -Z. Babylon uploads each decoded face with
    ``invertY`` (``UNPACK_FLIP_Y``, and the same flip when it expands RGBD into a half-float
    cube): a PNG's first row becomes the face's last GL row, ``t = 1``. So each face image is
    written bottom-up relative to the GL / KTX2 cube-face layout (first row ``t = 1``) -- the
    extension's "flipped" images (upright faces read back upside down: right at each face's
    centre, 40-60 % off elsewhere on a smooth sky). Babylon's
    default scene is left-handed and its glTF loader puts the asset under a root with rotation
    ``[0, 1, 0, 0]`` and scale ``(1, 1, -1)``: glTF direction ``(x, y, z)`` is Babylon's
    ``(-x, y, z)``, and the cube (and the SH) are looked up with Babylon's world direction. So
    the cube written here is probegrid's glTF-frame cube mirrored in x
    (:func:`probegrid.export.engines.mirror_cube`: +-X swapped, every face mirrored about its
    vertical axis), then each face stored bottom-up. In a right-handed Babylon scene
    (``useRightHandedSystem``) the shader negates z instead, which shows this file rotated 180
    degrees about +Y; write ``rotation=(0, 1, 0, 0)`` for it. Checked in real Babylon.js
    (npm ``@babylonjs/core`` in headless Chromium, ``tests/test_babylon.py``).
Gamma
    Babylon 9.x creates the light's ``RawCubeTexture`` with ``gammaSpace`` true, so its PBR
    shader raises the (linear) radiance to the power 2.2 once more; set
    ``scene.environmentTexture.gammaSpace = false`` after loading (docs/engines.md).
RGBD
    Babylon's ``toRGBD``: ``D = clamp(floor(max(255 / max(r, g, b), 1)) / 255, 0, 1)``,
    ``rgb' = (rgb D)^(1/2.2)`` in 8 bits, alpha = ``D``; decoded as ``rgb'^2.2 / D``. Values
    above 255 clip; relative precision is about 1/255 of the brightest channel.
Irradiance
    ``irradianceCoefficients`` are irradiance SH in Babylon's basis (Condon-Shortley signs on
    l1-1, l11, l2-1, l21; :func:`probegrid.export.shforms.ext_lights_image_based`) of the same
    x-mirrored function, so diffuse and specular agree.

Pure: arrays in, files out (PNG through Pillow). References: the extension's README; Babylon.js
``loaders/src/glTF/2.0/Extensions/EXT_lights_image_based.ts``, ``environmentTextureTools.ts``
(``UploadLevelsAsync``), ``hdrFiltering.ts``, ``pbrIBLFunctions.fx``, ``helperFunctions.fx``.
"""

from __future__ import annotations

import io
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._fs import atomic_write_bytes, atomic_write_text
from probegrid._version import __version__
from probegrid.export import engines, shforms

__all__ = [
    "FACE_NAMES",
    "GLTF_FILE",
    "MIN_MIP",
    "babylon_alphas",
    "babylon_lod",
    "babylon_sh",
    "check_size",
    "mip_count",
    "rgbd_decode",
    "rgbd_encode",
    "specular_chain",
    "write_environment_gltf",
]

#: The written glTF file's name.
GLTF_FILE = "environment.gltf"
#: The smallest mip written (the extension: "say, 16x16").
MIN_MIP = 16
#: Face file suffixes in the extension's order.
FACE_NAMES = ("px", "nx", "py", "ny", "pz", "nz")
#: Babylon's RGBD range and gamma (helperFunctions.fx: rgbdMaxRange, toGammaSpace).
_RGBD_RANGE = 255.0
_GAMMA = 2.2
#: probegrid SH indices whose basis polynomial is odd in x (x, xy, xz): negated by an x mirror.
_X_ODD = (3, 4, 7)


def check_size(size: int) -> None:
    """ValueError unless ``size`` is a power of two of at least ``2 * MIN_MIP`` (two mips: the
    loader's LOD scale is 0 with one)."""
    if size < 2 * MIN_MIP or size & (size - 1):
        raise ValueError(f"--format gltf needs a power-of-two cube size of at least "
                         f"{2 * MIN_MIP} (mips down to {MIN_MIP}^2), got {size}")


def mip_count(size: int) -> int:
    """Mips from ``size`` down to ``MIN_MIP`` (both included)."""
    check_size(size)
    return int(np.log2(size // MIN_MIP)) + 1


def babylon_alphas(size: int) -> NDArray[np.float64]:
    """GGX alpha of each written mip as Babylon samples it: ``alpha_k = 2^(k / s) / size`` with
    ``s = (mips - 1) / log2(size)``; ``alpha_0 = 0`` (the input itself), the last is 1."""
    n = mip_count(size)
    scale = (n - 1) / np.log2(size)
    a = 2.0 ** (np.arange(n) / scale) / size
    a[0] = 0.0
    return a


def babylon_lod(alpha: ArrayLike, size: int) -> NDArray[np.float64]:
    """The mip Babylon's PBR shader reads for GGX ``alpha`` (``getLodFromAlphaG`` times the
    loader's ``lodGenerationScale``, clamped to the given mips)."""
    n = mip_count(size)
    scale = (n - 1) / np.log2(size)
    with np.errstate(divide="ignore"):
        lod = np.log2(size * np.asarray(alpha, dtype=np.float64)) * scale
    return np.clip(lod, 0.0, n - 1)


def specular_chain(cube: ArrayLike) -> list[NDArray[np.float32]]:
    """The GGX chain at :func:`babylon_alphas`, level ``k`` of size ``n >> k`` down to 16^2,
    in probegrid's (glTF-frame) face table."""
    from probegrid.core.specular import ggx_filter

    c = np.asarray(cube, dtype=np.float32)
    n = int(c.shape[1])
    alphas = babylon_alphas(n)
    return [c.copy()] + [ggx_filter(c, float(a), n >> k) for k, a in enumerate(alphas)
                         if k > 0]


def babylon_sh(L: ArrayLike) -> NDArray[np.float64]:
    """``irradianceCoefficients`` (9, 3) for radiance SH ``L`` in probegrid's frame: mirrored
    in x (Babylon's left-handed view of a glTF asset), then Babylon's irradiance form."""
    c = np.array(L, dtype=np.float64)
    c[..., _X_ODD, :] *= -1.0
    return shforms.ext_lights_image_based(c)


def rgbd_encode(rgb: ArrayLike) -> NDArray[np.uint8]:
    """``(..., 3)`` linear radiance -> ``(..., 4)`` RGBD bytes (Babylon's ``toRGBD``)."""
    c = np.maximum(np.asarray(rgb, dtype=np.float64), 0.0)
    m = np.maximum(c.max(axis=-1, keepdims=True), 1e-7)
    d = np.clip(np.floor(np.maximum(_RGBD_RANGE / m, 1.0)) / 255.0, 0.0, 1.0)
    g = np.clip(c * d, 0.0, 1.0) ** (1.0 / _GAMMA)
    out = np.concatenate([g, d], axis=-1)
    return np.rint(out * 255.0).astype(np.uint8)


def rgbd_decode(rgbd: ArrayLike) -> NDArray[np.float32]:
    """``(..., 4)`` RGBD bytes -> ``(..., 3)`` linear radiance (Babylon's ``fromRGBD``)."""
    b = np.asarray(rgbd, dtype=np.float64) / 255.0
    return ((b[..., :3] ** _GAMMA) / np.maximum(b[..., 3:], 1.0 / 255.0)).astype(np.float32)


def _png(rgba: NDArray[np.uint8]) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgba), "RGBA").save(buf, format="PNG", optimize=False)
    return buf.getvalue()


def write_environment_gltf(
    out_dir: Path,
    chain: Sequence[NDArray[np.float32]],
    sh: ArrayLike,
    *,
    intensity: float = 1.0,
    rotation: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
    name: str = "environment",
) -> list[dict[str, Any]]:
    """Write ``environment.gltf`` and its PNG faces (``ibl/specular_m<k>_<face>.png``) into
    ``out_dir``; return their manifest entries.

    ``chain`` is :func:`specular_chain`'s output (glTF frame), ``sh`` probegrid's radiance SH
    (9, 3). Everything is encoded before the first file is written; ValueError on bad input.
    """
    size = int(chain[0].shape[1]) if len(chain) else 0
    n = mip_count(size)
    if len(chain) != n or any(lv.shape[:3] != (6, size >> k, size >> k)
                              for k, lv in enumerate(chain)):
        raise ValueError(f"the chain must be {n} cubes of {size} >> k texels")
    q = np.asarray(rotation, dtype=np.float64)
    if q.shape != (4,) or not np.isfinite(q).all() or abs(np.linalg.norm(q) - 1) > 1e-6:
        raise ValueError(f"rotation must be a unit quaternion (x, y, z, w), got {rotation!r}")
    if not np.isfinite(intensity) or intensity < 0:
        raise ValueError(f"intensity must be a finite number >= 0, got {intensity!r}")
    coeffs = babylon_sh(sh)
    pngs: dict[str, bytes] = {}
    images: list[dict[str, str]] = []
    mips: list[list[int]] = []
    for k, lv in enumerate(chain):
        faces = rgbd_encode(engines.mirror_cube(lv[..., :3], 0))[:, ::-1]  # bottom-up rows
        row = []
        for f, suffix in enumerate(FACE_NAMES):
            uri = f"ibl/specular_m{k}_{suffix}.png"
            pngs[uri] = _png(faces[f])
            row.append(len(images))
            images.append({"uri": uri, "mimeType": "image/png"})
        mips.append(row)
    alphas = babylon_alphas(size)
    doc = {
        "asset": {"version": "2.0", "generator": f"probegrid {__version__}"},
        "extensionsUsed": ["EXT_lights_image_based"],
        "extensions": {"EXT_lights_image_based": {"lights": [{
            "name": name,
            "intensity": float(intensity),
            "rotation": [float(x) for x in q],
            "irradianceCoefficients": [[float(x) for x in row] for row in coeffs],
            "specularImageSize": size,
            "specularImages": mips,
        }]}},
        "scene": 0,
        "scenes": [{"name": name, "extensions": {"EXT_lights_image_based": {"light": 0}}}],
        "images": images,
        "extras": {"probegrid": {
            "mip_alpha": [float(a) for a in alphas],
            "mip_roughness": [float(np.sqrt(a)) for a in alphas],
            "conventions": "faces +X,-X,+Y,-Y,+Z,-Z for Babylon's left-handed view of glTF "
                           "(glTF frame mirrored in x), first PNG row = t 1 (Babylon uploads "
                           "with invertY), RGBD (gamma 2.2), "
                           "mip k at GGX alpha 2^(k/s)/size, s = (mips-1)/log2(size)",
        }},
    }
    (out_dir / "ibl").mkdir(exist_ok=True)
    for uri, data in pngs.items():
        atomic_write_bytes(out_dir / uri, data)
    atomic_write_text(out_dir / GLTF_FILE, json.dumps(doc, indent=1) + "\n")
    return [
        {"path": GLTF_FILE, "kind": "gltf", "consumer": "Babylon.js (EXT_lights_image_based)",
         "level": None, "roughness": None, "layout": None, "format": "gltf",
         "specular_image_size": size, "mips": n,
         "mip_alpha": [float(a) for a in alphas]},
        {"path": sorted(pngs), "kind": "specular", "levels": n, "layout": "faces",
         "format": "png", "dtype": "rgbd8", "face_size": size,
         "roughness": [float(np.sqrt(a)) for a in alphas],
         "cube_convention": "babylon (glTF mirrored in x, rows bottom-up)"},
    ]
