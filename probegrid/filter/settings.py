"""The settings of the environment filter (:func:`probegrid.filter.filter_environment`, the
``probegrid filter`` command) and the sizes it chooses by default.

:class:`FilterSettings` holds every option of ``probegrid filter`` with its default and bounds,
written once: the command line's options are generated from its fields (their ``Literal``
choices come from :mod:`probegrid._types`), the manifest records them. :func:`check_settings`
refuses option combinations that cannot work, before any work; :func:`default_cube_size` and
:func:`diffuse_source_size` choose the cube's face size and the face size the exact diffuse
sum reads when no option names them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from functools import lru_cache
from typing import Any, Literal, cast, get_args, get_origin, get_type_hints

import numpy as np

from probegrid._types import (
    CubeConvention,
    CubeLayout,
    DiffuseMethod,
    GGXMethod,
    InputLayout,
    Layout,
    MapFormat,
    SeamMode,
    SHWindow,
    VkFormatName,
)
from probegrid.errors import SettingsError

__all__ = [
    "DEFAULT_DIFFUSE_SOURCE",
    "DEFAULT_MAX_SIZE",
    "FilterSettings",
    "check_settings",
    "default_cube_size",
    "diffuse_source_size",
]


def _option(default: Any, **bounds: float) -> Any:
    """A :class:`FilterSettings` field with its bounds (``ge``, ``le``, ``gt``)."""
    return field(default=default, metadata=bounds)


@dataclass(frozen=True, kw_only=True)
class FilterSettings:
    """Options of :func:`probegrid.filter.filter_environment` and of ``probegrid filter`` (see
    ``probegrid filter --help``), the output files' too (format, layout, previews).

    A frozen dataclass whose every field is checked on construction against its type (a
    ``Literal`` of :mod:`probegrid._types`, an integer, a number or a flag, optionally None)
    and bounds (:class:`probegrid.errors.SettingsError`, naming the field, for a bad value);
    the command line's options are generated from it. (A dataclass, not a pydantic model like
    the bake's settings: the filter command runs in well under a second, and loading pydantic
    and building a model would take a tenth of that.)
    """

    layout: InputLayout = "auto"
    size: int | None = _option(None, ge=1, le=4096)
    diffuse_size: int = _option(32, ge=1, le=1024)
    diffuse_method: DiffuseMethod = "exact"
    diffuse_source_size: int | None = _option(None, ge=1, le=4096)
    specular_levels: int | None = _option(None, ge=1, le=16)
    specular_method: GGXMethod = "tiered"
    samples: int | None = _option(None, ge=1, le=65536)
    sh_bands: int = _option(3, ge=1, le=16)
    sh_window: SHWindow = "none"
    sh_window_width: float | None = _option(None, gt=0)
    format: MapFormat = "exr"
    cube_convention: CubeConvention = "gltf"
    vk_format: VkFormatName | None = None
    zstd: bool = False
    half: bool = True
    output_layout: CubeLayout = "faces"
    seam: SeamMode = "none"
    clamp: float | None = _option(None, gt=0)
    keep_negative: bool = False
    lut_size: int = _option(128, ge=2, le=1024)
    previews: bool = True

    def __post_init__(self) -> None:
        hints = _settings_types()
        for f in fields(self):
            value = _checked(f.name, getattr(self, f.name), hints[f.name], f.metadata)
            object.__setattr__(self, f.name, value)  # (a numpy integer becomes an int)

    def as_dict(self) -> dict[str, Any]:
        """Every field and its value (the manifest's ``settings``)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@lru_cache(maxsize=1)
def _settings_types() -> dict[str, Any]:
    return get_type_hints(FilterSettings)


def _checked(name: str, value: Any, annotation: Any, bounds: Mapping[str, float]) -> Any:
    """``value`` of the field ``name`` checked against its type and bounds (an integer field
    takes any integral number, a number field any real one); a :class:`SettingsError`
    otherwise."""
    kinds = get_args(annotation) if get_origin(annotation) is not Literal else (annotation,)
    kinds = kinds or (annotation,)
    if value is None and type(None) in kinds:
        return None
    literal = next((k for k in kinds if get_origin(k) is Literal), None)
    if literal is not None:
        if isinstance(value, str) and value in get_args(literal):
            return value
        raise SettingsError(name, f"expected one of {', '.join(map(repr, get_args(literal)))}, "
                                  f"got {value!r}")
    if bool in kinds:
        if isinstance(value, (bool, np.bool_)):
            return bool(value)
        raise SettingsError(name, f"expected true or false, got {value!r}")
    if int in kinds:
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise SettingsError(name, f"expected an integer, got {value!r}")
        value = int(value)
    elif float in kinds:
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer,
                                                                          np.floating)):
            raise SettingsError(name, f"expected a number, got {value!r}")
        value = float(value)
    if "ge" in bounds and not value >= bounds["ge"]:
        raise SettingsError(name, f"must be >= {bounds['ge']}, got {value!r}")
    if "le" in bounds and not value <= bounds["le"]:
        raise SettingsError(name, f"must be <= {bounds['le']}, got {value!r}")
    if "gt" in bounds and not value > bounds["gt"]:
        raise SettingsError(name, f"must be > {bounds['gt']}, got {value!r}")
    return value


#: Largest cube face size chosen by default (a 256^2 chain takes ~2 s and ~300 MB here).
DEFAULT_MAX_SIZE = 256


def default_cube_size(height: int, width: int, layout: str) -> int:
    """Face size used when ``--size`` is not given: the input's own resolution
    (:func:`probegrid.core.layouts.default_face_size` before its rounding: ``W / 4`` for equirect,
    ``S / pi`` for angular maps, the face size for crosses and faces) rounded *down* to a power
    of two (the tiered GGX chain needs one, and no texel is finer than the input), at most
    :data:`DEFAULT_MAX_SIZE` and at least 1. 1024 x 512 equirect -> 256, 1500 x 750 -> 256,
    512 x 256 -> 128; six 100^2 faces -> 64."""
    from probegrid.core import layouts

    if layout == "faces":
        exact = float(min(height, width))
    else:
        exact = {"equirect": width / 4, "angular": width / np.pi, "hcross": width / 4,
                 "vcross": width / 3}[layout]
        layouts.default_face_size(height, width, cast(Layout, layout))  # checks the arguments
    n = 1 << max(0, int(np.floor(np.log2(max(exact, 1.0)))))
    return min(n, DEFAULT_MAX_SIZE)


#: The exact diffuse sum reads at most this face size by default (the box mip of larger cubes).
DEFAULT_DIFFUSE_SOURCE = 128


def diffuse_source_size(n: int, requested: int | None) -> int:
    """Face size the exact diffuse sum reads: ``requested`` (``n`` divided by a power of two),
    else ``n`` up to :data:`DEFAULT_DIFFUSE_SOURCE` and that size's box mip of larger cubes.

    Irradiance is band-limited, so the mip changes little: a 32^2 diffuse map from the 128^2 mip
    of a 256^2 cube differs from the sum over all 256^2 texels by 3e-5 / 4e-5 mean and
    0.1 % / 0.55 % max relative (venice / studio, measured), at a third of the time and memory.
    """
    if requested is None:
        if n <= DEFAULT_DIFFUSE_SOURCE or n & (n - 1):
            return n
        return DEFAULT_DIFFUSE_SOURCE
    ratio = n // requested
    if requested > n or n % requested or ratio & (ratio - 1):
        raise ValueError(f"--diffuse-source-size must be the cube size {n} divided by a power "
                         f"of two, got {requested}")
    return requested


def check_settings(settings: FilterSettings) -> None:
    """Refuse option combinations that cannot work (one-line ``ValueError``), before any work."""
    if settings.seam == "border" and settings.output_layout != "faces":
        raise ValueError("--seam border writes (n+2)^2 faces, which only --output-layout faces "
                         f"can hold (got --output-layout {settings.output_layout})")
    if settings.samples is not None and settings.specular_method != "fis":
        raise ValueError("--samples applies to --specular-method fis (importance sampling)")
    if (settings.diffuse_method == "sh" and settings.sh_window not in ("none", "auto")
            and settings.sh_window_width is None):
        raise ValueError(f"--sh-window {settings.sh_window} needs --sh-window-width")
    if settings.format == "ktx2" and (settings.output_layout != "faces"
                                      or settings.seam == "border"):
        raise ValueError("--format ktx2 writes cube maps: it needs --output-layout faces and a "
                         "seam mode other than 'border'")
    if settings.cube_convention != "gltf" and settings.format != "ktx2":
        raise ValueError("--cube-convention applies to --format ktx2")
    if (settings.vk_format is not None or settings.zstd) and settings.format != "ktx2":
        raise ValueError("--vk-format and --zstd apply to --format ktx2")
    if settings.vk_format is not None and not settings.half:
        raise ValueError("give --vk-format or --float, not both (--float is "
                         "--vk-format R32G32B32A32_SFLOAT)")
    engine = {"gltf": "Babylon's", "filament": "Filament's"}.get(settings.format)
    if engine is not None and (settings.output_layout != "faces"
                               or settings.seam == "border"
                               or settings.specular_levels is not None
                               or settings.specular_method != "tiered"):
        raise ValueError(f"--format {settings.format} writes {engine} mip chain (down to 16^2, "
                         "tiered GGX): it needs --output-layout faces, no --specular-levels or "
                         "--specular-method and a seam mode other than 'border'")
    if engine is not None and settings.size is not None:
        from probegrid.export import filament, gltf_ibl

        (gltf_ibl if settings.format == "gltf" else filament).check_size(settings.size)
    if settings.size is not None:
        _check_size(settings.size, settings)


def _check_size(n: int, settings: FilterSettings) -> None:
    """Refuse a ``--size`` the chosen chain cannot take, naming sizes that work: the tiered
    GGX filter (the default) needs a power of two, and ``--specular-levels`` as many halvings."""
    from probegrid.core.cubemap import mip_sizes

    if n & (n - 1) and settings.specular_method == "tiered":
        below = 1 << (n.bit_length() - 1)
        raise ValueError(f"--size {n} is not a power of two, which the default GGX filter "
                         f"(--specular-method tiered) needs: use --size {below} or --size "
                         f"{2 * below} (the nearest powers of two), or --specular-method fis")
    if settings.specular_levels is not None:
        try:
            mip_sizes(n, settings.specular_levels)
        except ValueError:
            most = (n & -n).bit_length()  # n's halvings down to an odd size, plus level 0
            raise ValueError(f"--size {n} cannot be halved {settings.specular_levels - 1} "
                             f"times for --specular-levels {settings.specular_levels}: use "
                             f"--specular-levels {most} or less") from None
    if settings.diffuse_source_size is not None:
        diffuse_source_size(n, settings.diffuse_source_size)
