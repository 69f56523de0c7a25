"""A filtered environment as KTX2 cube maps, the way glTF-IBL-Sampler writes them and the glTF
Sample Viewer and Bevy's ``EnvironmentMapLight`` load them: ``specular.ktx2`` (the whole GGX
chain as mip levels, level ``k`` at perceptual roughness ``k / (levels - 1)``) and
``diffuse.ktx2`` (one level, irradiance / pi).

Faces +X, -X, +Y, -Y, +Z, -Z in the OpenGL/Vulkan/KTX2 table (probegrid's own, which is
glTF-IBL-Sampler's); ``cube_convention`` mirrors them for three.js (x) or Bevy (z) lookups
(:func:`probegrid.export.engines.mirror_cube`). Pure: arrays in, files out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from probegrid._types import CubeConvention
from probegrid.export import engines, ktx2

__all__ = ["write_environment_ktx2"]


def write_environment_ktx2(
    out_dir: Path,
    diffuse: NDArray[np.float32],
    specular: Sequence[NDArray[np.float32]],
    *,
    vk_format: int | str = ktx2.VK_FORMAT_R16G16B16A16_SFLOAT,
    zstd: bool = False,
    cube_convention: CubeConvention = "gltf",
    key_values: Mapping[str, str] | None = None,
) -> list[dict[str, Any]]:
    """Encode both files (raising ``KTX2Error`` before writing anything), write them atomically
    and return their manifest entries."""
    mirror = engines.CUBE_MIRROR[cube_convention]
    sc: Literal["none", "zstd"] = "zstd" if zstd else "none"
    kv = dict(key_values or {})
    n = len(specular)
    parts = {
        "specular.ktx2": ktx2.encode_ktx2_parts(
            [engines.mirror_cube(lv, mirror) for lv in specular], kind="cube",
            vk_format=vk_format, supercompression=sc,
            key_values={**kv, "probegrid:content": "GGX specular chain, level k at perceptual "
                        "roughness k / (levels - 1)"}),
        "diffuse.ktx2": ktx2.encode_ktx2_parts(
            [engines.mirror_cube(diffuse, mirror)], kind="cube", vk_format=vk_format,
            supercompression=sc, key_values={**kv, "probegrid:content": "irradiance / pi"}),
    }
    for name, p in parts.items():
        ktx2.write_parts(out_dir / name, p)
    fmt = ktx2._FORMATS[ktx2._check_format(vk_format)][0]
    return [
        {"path": "specular.ktx2", "kind": "specular", "levels": n, "layout": "ktx2 cube",
         "format": "ktx2", "dtype": fmt, "face_size": int(specular[0].shape[1]),
         "roughness": [k / (n - 1) if n > 1 else 0.0 for k in range(n)],
         "cube_convention": cube_convention},
        {"path": "diffuse.ktx2", "kind": "diffuse", "level": 0, "roughness": None,
         "layout": "ktx2 cube", "format": "ktx2", "dtype": fmt,
         "face_size": int(diffuse.shape[1]), "content": "irradiance / pi",
         "cube_convention": cube_convention},
    ]
