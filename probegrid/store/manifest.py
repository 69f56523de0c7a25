"""The grid store's format: a directory of memory-mappable per-probe arrays and a versioned manifest.

Layout
------
A finished store is one directory, by convention ``NAME.probes/``::

    NAME.probes/
        manifest.json       StoreManifest (pydantic), format "probegrid.store", format_version 2
        sh.npy              one .npy file per array, named after the array
        diffuse.npy
        ...
        scene_triangles.npy extras (format 2): arrays added when the probes are done

Every array is *per probe*: its first axis is the probe's linear index (``(i * ny + j) * nz + k``,
see :mod:`probegrid.core.grid`), e.g. ``sh (P, 9, 3) float32``, ``diffuse (P, 6, n, n, 3) float16``,
``valid (P,) bool``. The files are plain NumPy ``.npy`` (format 1.0/2.0, C order, little-endian,
dtype kinds bool / int / uint / float), so any reader can memory-map them; :func:`open_store`
maps them read-only (``np.load(mmap_mode="r")``, i.e. ``MAP_SHARED`` + ``PROT_READ``), so many
reader processes share the same page-cache pages and touch only the probes they index. The
manifest records, for every array, its file, dtype string (``numpy.dtype.str``), full shape, a
description and the file's SHA-256; the reader refuses a store whose files disagree with it in
size, shape, dtype or hash. A store is self-contained: its files are regular files directly in
its directory, opened without following symbolic links (a store is refused when one of its files
is a link, wherever it points), so a store copied or unpacked from elsewhere can never make a
reader open a file outside it.

*Extras* (format version 2; version 1 stores have none) are arrays added to a finished bake by
:meth:`StoreWriter.add_extra` just before it is published, listed under the manifest's ``extras``
with the same file/dtype/shape record: derived per-probe arrays (``sh_deringed (P, 9, 3)``,
``sh_window (P, 3)``) and arrays that are not per probe at all (``scene_vertices (V, 3)``,
``scene_triangles (T, 3)``: the scene's geometry for exact visibility queries). They are not
part of the bake plan (a resumed bake does not compare them) and are mapped like the arrays.

The manifest also carries the conventions record (built by :mod:`probegrid.core.conventions`; the store
treats it as opaque JSON), the grid (:class:`probegrid.core.grid.GridSpec`), the bake settings, the
scene's content hash, per-bake quality figures, the creation time and the probegrid version, and
(``inputs``, optional within format 2) the scene and environment *as given*: file names without
their directories, sizes, the environment's layout, the scene's counts and each one's own hash.

Writing (:mod:`probegrid.store.writer`) is atomic and resumable; reading
(:mod:`probegrid.store.reader`) memory-maps the arrays. This module holds the format: the
manifest models, the array declarations and the naming rule (``NAME.probes``, its
``.partial`` and ``.work`` siblings).

All failures of the store raise :class:`StoreError` with a one-line message.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Annotated, Any, Final, Literal, get_args

import numpy as np
from numpy.typing import DTypeLike
from pydantic import (
    BaseModel,
    ConfigDict,
    PlainSerializer,
    PlainValidator,
    ValidationError,
    field_validator,
    model_validator,
)

from probegrid._version import __version__
from probegrid.core.grid import GridSpec
from probegrid.errors import StoreError
from probegrid.store.names import (  # (the store's names, re-exported: see __all__)
    DONE_FILE,
    MANIFEST_FILE,
    PARTIAL_SUFFIX,
    PLAN_FILE,
    STORE_DIR_SUFFIXES,
    STORE_SUFFIX,
    WORK_SUFFIX,
)

#: A manifest's grid: validated by :meth:`GridSpec.from_dict`, written by :meth:`GridSpec.as_dict`.
GridField = Annotated[GridSpec, PlainValidator(GridSpec.from_dict),
                      PlainSerializer(GridSpec.as_dict)]

__all__ = ['DONE_FILE', 'ENVIRONMENT_SOURCES', 'FORMAT_NAME', 'FORMAT_VERSION', 'MANIFEST_FILE',
           'PARTIAL_SUFFIX', 'PLAN_FILE', 'STORE_DIR_SUFFIXES', 'STORE_SUFFIX',
           'SUPPORTED_FORMAT_VERSIONS', 'WORK_SUFFIX', 'ArrayInfo', 'ArraySpec', 'BakeInputs',
           'EnvironmentInput', 'EnvironmentSource', 'SceneFile', 'SceneInput', 'StoreError',
           'StoreManifest', 'partial_path']


FORMAT_NAME: Final = "probegrid.store"


#: Version of the store layout and manifest schema written by this module (2: ``extras``).
FORMAT_VERSION: Final = 2


#: Versions :func:`open_store` reads (1: no extras).
SUPPORTED_FORMAT_VERSIONS: Final = frozenset({1, 2})


_NAME_RE = re.compile(r"^[a-z][a-z0-9_]{0,63}$")


_DTYPE_KINDS = "biuf"


_SHA256_RE = re.compile(r"^[0-9a-f]{64}$")


# ---------------------------------------------------------------------------- array declarations
def _check_name(name: str) -> str:
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise ValueError(
            f"array name must be 1-64 characters of a-z, 0-9 and _, starting with a letter, "
            f"got {name!r}"
        )
    return name


def _check_dtype(dtype: DTypeLike) -> str:
    try:
        dt = np.dtype(dtype)
    except TypeError:
        raise ValueError(f"unknown dtype {dtype!r}") from None
    if dt.kind not in _DTYPE_KINDS or dt.byteorder == ">" or dt.shape or dt.names:
        raise ValueError(
            f"array dtype must be a little-endian bool, int, uint or float scalar, got {dt}"
        )
    return dt.str


@dataclass(frozen=True)
class ArraySpec:
    """Declaration of one per-probe array for :meth:`StoreWriter.create`.

    Attributes
    ----------
    shape : tuple of int >= 1
        Shape of one probe's entry (the store array is ``(P, *shape)``); ``()`` for a scalar.
    dtype : str
        NumPy dtype; normalised to its ``dtype.str`` (e.g. ``"<f2"``, ``"|b1"``).
    description : str
        Words for the manifest (what it holds, units).
    """

    shape: tuple[int, ...]
    dtype: str
    description: str = ""

    def __post_init__(self) -> None:
        shape = tuple(self.shape)
        if not all(
            isinstance(n, (int, np.integer)) and not isinstance(n, bool) and n >= 1 for n in shape
        ):
            raise ValueError(f"per-probe shape must be positive integers, got {self.shape!r}")
        object.__setattr__(self, "shape", tuple(int(n) for n in shape))
        object.__setattr__(self, "dtype", _check_dtype(self.dtype))
        if not isinstance(self.description, str):
            raise TypeError(f"description must be a string, got {self.description!r}")


class ArrayInfo(BaseModel):
    """Manifest entry of one array: file name, dtype string, full shape ``(P, ...)``, words,
    and the SHA-256 of the whole ``.npy`` file (written by :meth:`StoreWriter.finish`; None in
    plans and in stores written before it was recorded, whose files are then checked by size
    only)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    file: str
    dtype: str
    shape: tuple[int, ...]
    description: str = ""
    sha256: str | None = None

    @field_validator("sha256")
    @classmethod
    def _sha256(cls, v: str | None) -> str | None:
        if v is not None and not _SHA256_RE.match(v):
            raise ValueError(f"sha256 must be 64 lowercase hex digits, got {v[:80]!r}")
        return v

    @field_validator("dtype")
    @classmethod
    def _dtype(cls, v: str) -> str:
        if _check_dtype(v) != v:
            raise ValueError(f"dtype must be a numpy dtype string such as '<f4', got {v!r}")
        return v

    @field_validator("shape")
    @classmethod
    def _shape(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        if len(v) < 1 or min(v) < 1:
            raise ValueError(f"array shape must be (P, ...) with positive sizes, got {v}")
        return v

    @property
    def nbytes(self) -> int:
        """Size of the array's data in bytes."""
        return math.prod(self.shape) * np.dtype(self.dtype).itemsize


class _Plan(BaseModel):
    """What a bake writes; persisted in a partial directory and checked on resume."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    format: Literal["probegrid.store"] = FORMAT_NAME
    format_version: int = FORMAT_VERSION
    probegrid_version: str = __version__
    bake_started: datetime
    conventions: dict[str, Any]
    grid: GridField
    bake: dict[str, Any]
    scene_hash: str
    arrays: dict[str, ArrayInfo]

    @model_validator(mode="after")
    def _arrays_match_grid(self) -> _Plan:
        if not self.arrays:
            raise ValueError("a store needs at least one array")
        for name, info in self.arrays.items():
            _check_name(name)
            if info.file != f"{name}.npy":
                raise ValueError(f"array {name!r} must live in {name}.npy, not {info.file!r}")
            if info.shape[0] != self.grid.n_probes:
                raise ValueError(
                    f"array {name!r} has {info.shape[0]} entries for a grid of "
                    f"{self.grid.n_probes} probes"
                )
        return self


class SceneFile(BaseModel):
    """Manifest entry of the scene copy a store keeps (for viewers; see
    :func:`probegrid.store.writer.keepable_scene`).

    ``file`` is a fixed name inside the store; ``source`` is the baked file's name only (no
    directory), for people to read.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    file: Literal["scene.glb", "scene.gltf"]
    media_type: Literal["model/gltf-binary", "model/gltf+json"]
    bytes: int
    sha256: str
    source: str


def _basename(v: str) -> str:
    if not v or "/" in v or "\\" in v or v in (".", ".."):
        raise ValueError(f"a file name without its directory is expected, got {v!r}")
    return v


class SceneInput(BaseModel):
    """The scene file a store was baked from, as given (manifest ``inputs.scene``).

    ``name`` is the file's name without its directory (no machine path is recorded); ``bytes``
    its size; the counts are those of the loaded scene (``meshes``: the glTF document's meshes;
    ``emissive_materials``: materials in use with a non-zero emission; ``punctual_lights``:
    ``KHR_lights_punctual`` lights). ``content_hash`` is the scene's own hash
    (:meth:`probegrid.scene.Scene.content_hash`): the store's ``scene_hash`` is the SHA-256 of
    it followed by the environment's ``content_hash``. ``unhonoured`` names what the file uses
    that the bake did not honour (:attr:`probegrid.scene.Scene.unhonoured`: metallic-roughness,
    sheen, an extension ignored with ``--ignore-extension``...).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    bytes: int
    triangles: int
    meshes: int | None = None
    materials: int
    emissive_materials: int
    punctual_lights: int
    content_hash: str
    unhonoured: tuple[str, ...] = ()

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        return _basename(v)


#: What a bake's environment was given as: the image layouts of the CLI's
#: ``--environment-layout`` (after ``auto`` was resolved), ``faces`` for ``--environment-faces``,
#: ``color`` for ``--environment-color`` and ``none`` for no environment (black).
EnvironmentSource = Literal["equirect", "angular", "hcross", "vcross", "faces", "color", "none"]
ENVIRONMENT_SOURCES: Final = get_args(EnvironmentSource)


class EnvironmentInput(BaseModel):
    """The environment a store was baked from, as given (manifest ``inputs.environment``).

    ``layout`` is one of :data:`ENVIRONMENT_SOURCES`. For images: ``files`` the file names (no
    directory; for ``faces`` in face order +X, -X, +Y, -Y, +Z, -Z, whatever order they were
    given in), ``bytes`` their total size and ``pixel_size`` the (width, height) of the image
    (of one face for ``faces``). For ``color``: ``color``, the constant radiance. ``intensity``
    and ``rotation_deg`` as given. ``content_hash``: see :class:`SceneInput`.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    layout: EnvironmentSource
    files: tuple[str, ...] = ()
    bytes: int = 0
    pixel_size: tuple[int, int] | None = None
    color: tuple[float, float, float] | None = None
    intensity: float = 1.0
    rotation_deg: float = 0.0
    content_hash: str

    @field_validator("files")
    @classmethod
    def _files(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(_basename(f) for f in v)

    @model_validator(mode="after")
    def _consistent(self) -> EnvironmentInput:
        images = {"faces": 6, "color": 0, "none": 0}.get(self.layout, 1)
        if len(self.files) != images:
            raise ValueError(f"a {self.layout!r} environment has {images} file(s), "
                             f"got {len(self.files)}")
        if (self.pixel_size is not None) != (images > 0):
            raise ValueError("pixel_size is given for an image environment and only for one")
        if (self.color is not None) != (self.layout == "color"):
            raise ValueError("color is given for a 'color' environment and only for one")
        return self


class BakeInputs(BaseModel):
    """The scene and environment a store was baked from, as given (manifest ``inputs``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    scene: SceneInput
    environment: EnvironmentInput


class StoreManifest(_Plan):
    """The ``manifest.json`` of a finished store.

    Attributes
    ----------
    format, format_version : "probegrid.store", int
        Layout identifier and version (see :data:`SUPPORTED_FORMAT_VERSIONS`).
    probegrid_version : str
        Version of probegrid that wrote the store.
    created, bake_started : datetime (UTC)
    conventions : dict
        The conventions record (:func:`probegrid.core.conventions.conventions`).
    grid : GridSpec
    bake : dict
        Bake settings (face size, bounces, samples, seed, ...).
    scene_hash : str
        Content hash of the scene (and environment) the store was baked from.
    quality : dict
        Per-bake quality figures (furnace error, SH minimum, seam score, invalid probes, ...).
    scene_file : SceneFile or None
        The copy of the baked glTF scene kept in the store, if any.
    arrays : dict of str -> ArrayInfo
    extras : dict of str -> ArrayInfo
        Arrays added after the probes (format 2; see the module docstring), possibly not per
        probe.
    inputs : BakeInputs or None
        The scene and environment as given (file names, sizes, layout, counts, each one's
        content hash); None in stores written before it was recorded (still format 2: the
        field is optional) and in stores not written by a bake.
    """

    created: datetime
    quality: dict[str, Any]
    scene_file: SceneFile | None = None
    extras: dict[str, ArrayInfo] = {}
    inputs: BakeInputs | None = None

    @model_validator(mode="after")
    def _extras_apart(self) -> StoreManifest:
        for name, info in self.extras.items():
            _check_name(name)
            if name in self.arrays:
                raise ValueError(f"extra {name!r} has the name of an array")
            if info.file != f"{name}.npy":
                raise ValueError(f"extra {name!r} must live in {name}.npy, not {info.file!r}")
        return self


# ---------------------------------------------------------------------------- JSON helpers
def _json_default(obj: Any) -> Any:
    if isinstance(obj, (np.generic, np.ndarray)):
        return obj.tolist()
    if isinstance(obj, BaseModel):
        return obj.model_dump(mode="json")
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON-serialisable")


def _jsonable(obj: Any, what: str) -> dict[str, Any]:
    """A JSON-normalised copy of a mapping or pydantic model (tuples become lists)."""
    if isinstance(obj, BaseModel):
        obj = obj.model_dump(mode="json")
    if not isinstance(obj, Mapping):
        raise TypeError(f"{what} must be a mapping or a pydantic model, got {type(obj).__name__}")
    try:
        text = json.dumps(dict(obj), default=_json_default, allow_nan=False, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} must be JSON-serialisable with finite numbers: {exc}") from None
    return json.loads(text)


def _validation_message(exc: ValidationError) -> str:
    err = exc.errors()[0]
    loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
    more = f" (and {exc.error_count() - 1} more problems)" if exc.error_count() > 1 else ""
    return f"{loc}: {str(err['msg']).removeprefix('Value error, ')}{more}"


# ---------------------------------------------------------------------------- reading
def check_store_name(path: str | os.PathLike[str]) -> Path:
    """``path`` as a Path when it names a store ``NAME.probes``; ValueError otherwise."""
    p = Path(path)
    if not p.name.endswith(STORE_SUFFIX) or p.name == STORE_SUFFIX:
        raise ValueError(f"a store must be named NAME.probes, got {str(p)!r}")
    return p


def store_name(path: str | os.PathLike[str]) -> str:
    """A store's name: its directory name without ``.probes`` (the whole name without it)."""
    name = Path(path).name
    return name.removesuffix(STORE_SUFFIX) if name.endswith(STORE_SUFFIX) else name


def work_path(path: str | os.PathLike[str]) -> Path:
    """The bake's working directory ``NAME.probes.work`` beside the store ``path``."""
    p = Path(path)
    return p.with_name(p.name + WORK_SUFFIX)


def partial_path(path: str | os.PathLike[str]) -> Path:
    """The working directory ``NAME.probes.partial`` of a bake that will produce ``path``."""
    p = Path(path)
    return p.with_name(p.name + PARTIAL_SUFFIX)


def _final_path(path: str | os.PathLike[str]) -> Path:
    p = Path(path)
    if p.name.endswith(PARTIAL_SUFFIX) or not p.name:
        raise ValueError(f"store path must name the finished store (NAME.probes), got {str(p)!r}")
    return p
