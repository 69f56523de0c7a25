"""The number type of a store's map arrays: float32 (default) or float16 (``--dtype half``).

A 16,384-probe store with 16^2 faces holds about 507 MB of float32, most of it in the map arrays
(diffuse, the specular chain, incoming); half floats halve that. Half floats carry 11
significant bits (relative rounding at most 2^-11 = 0.05 %, far below what a bake resolves) and
values up to 65504: a larger value (the texel of a direct sun in the sharpest specular level
or the incoming cube) is clamped to 65504, never stored as infinity, so such a store loses that
part of the sun's energy; bake with the default float32 when the sharp maps must keep it.
SH coefficients, moments, positions and every other array stay float32 or wider. The dtype of
each array is recorded in the manifest, and readers blend in float32 whatever is stored
(:func:`probegrid.core.ddgi.blend`), so a half store reads back transparently.

:func:`map_dtype` names the map arrays' dtype for the settings; :func:`fit_map_dtype` clamps a
task's map results into it; :func:`store_bytes` is the store's size for the estimate.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from probegrid._types import MapDType

__all__ = ["HALF_MAX", "MAP_ARRAYS", "fit_map_dtype", "map_dtype"]

#: Largest finite float16.
HALF_MAX = float(np.finfo(np.float16).max)
#: Array name prefixes of the map arrays (the arrays ``--dtype`` applies to).
MAP_ARRAYS = ("diffuse", "specular_", "incoming")


def map_dtype(dtype: MapDType) -> str:
    """The numpy dtype of the map arrays: ``"float16"`` for ``"half"``, else ``"float32"``."""
    return "float16" if dtype == "half" else "float32"


def fit_map_dtype(out: dict[str, Any], dtype: MapDType) -> None:
    """Clamp the map arrays of a task's results into float16's range (in place) when the store
    holds half floats (``dtype="half"``); nothing otherwise."""
    if dtype != "half":
        return
    for name, value in out.items():
        if name.startswith(MAP_ARRAYS):
            out[name] = np.clip(value, -HALF_MAX, HALF_MAX).astype(np.float16)
