"""Reading grid stores: manifest validation and the memory-mapped :class:`ProbeStore`.
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import ValidationError

from probegrid._version import __version__
from probegrid.core.grid import GridSpec
from probegrid.store.manifest import (
    DONE_FILE,
    FORMAT_NAME,
    MANIFEST_FILE,
    PARTIAL_SUFFIX,
    PLAN_FILE,
    SUPPORTED_FORMAT_VERSIONS,
    ArrayInfo,
    StoreError,
    StoreManifest,
    _final_path,
    _Plan,
    _validation_message,
    partial_path,
)

__all__ = ['ProbeStore', 'open_store', 'partial_progress', 'read_manifest']


def _read_npy_header(file: Path) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    """Shape, Fortran flag, dtype and data offset of a .npy file (reads the header only)."""
    with open(file, "rb") as f:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f"unsupported .npy version {version}")
        return shape, fortran, dtype, f.tell()


def _check_array_file(directory: Path, name: str, info: ArrayInfo) -> None:
    file = directory / info.file
    if not file.is_file():
        raise StoreError(f"{directory}: array {name!r} is missing its file {info.file}")
    try:
        shape, fortran, dtype, offset = _read_npy_header(file)
    except (OSError, ValueError) as exc:
        raise StoreError(f"{file} is not a valid .npy file ({exc})") from None
    if fortran:
        raise StoreError(f"{file} is in Fortran order; the store needs C order")
    if dtype.str != info.dtype:
        raise StoreError(f"{file} has dtype {dtype.str}, the manifest says {info.dtype}")
    if tuple(shape) != info.shape:
        raise StoreError(f"{file} has shape {tuple(shape)}, the manifest says {info.shape}")
    size, expected = file.stat().st_size, offset + info.nbytes
    if size != expected:
        state = "truncated" if size < expected else "too long"
        raise StoreError(f"{file} is {state}: {size} bytes, expected {expected}")


def _load_manifest_json(file: Path, model: type[_Plan]) -> Any:
    try:
        text = file.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise StoreError(f"cannot read {file}: {exc}") from None
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as exc:
        raise StoreError(f"{file} is not valid JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(raw, dict) or raw.get("format") != FORMAT_NAME:
        raise StoreError(f"{file} is not a probegrid store manifest (format != {FORMAT_NAME!r})")
    version = raw.get("format_version")
    if version not in SUPPORTED_FORMAT_VERSIONS:
        supported = ", ".join(str(v) for v in sorted(SUPPORTED_FORMAT_VERSIONS))
        raise StoreError(
            f"{file} has store format version {version!r}; probegrid {__version__} reads "
            f"version {supported}"
        )
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        raise StoreError(f"{file} is invalid: {_validation_message(exc)}") from None


def _validate_store_dir(directory: Path, *, allow_partial: bool = False) -> StoreManifest:
    if not directory.is_dir():
        raise StoreError(f"{directory} is not a probe store (no such directory)")
    if not allow_partial and (
        directory.name.endswith(PARTIAL_SUFFIX) or (directory / PLAN_FILE).exists()
    ):
        raise StoreError(f"{directory} is an unfinished bake, not a store; resume or rerun it")
    manifest_file = directory / MANIFEST_FILE
    if not manifest_file.is_file():
        raise StoreError(f"{directory} is not a finished probe store (no {MANIFEST_FILE})")
    manifest = _load_manifest_json(manifest_file, StoreManifest)
    for name, info in {**manifest.arrays, **manifest.extras}.items():
        _check_array_file(directory, name, info)
    kept = manifest.scene_file
    if kept is not None:
        f = directory / kept.file
        if not f.is_file() or f.stat().st_size != kept.bytes:
            raise StoreError(f"{f} is missing or is not the {kept.bytes} bytes the manifest says")
    return manifest


def partial_progress(path: str | os.PathLike[str]) -> tuple[int, int] | None:
    """``(probes done, probes in the grid)`` of the unfinished bake of store ``path``, or None.

    For ``probegrid info`` and progress reports; reads the plan and the done mask (read-only).
    """
    partial = partial_path(_final_path(path))
    if (partial / PLAN_FILE).is_file():
        plan = _load_manifest_json(partial / PLAN_FILE, _Plan)
        n = plan.grid.n_probes
        info = ArrayInfo(file=DONE_FILE, dtype="|b1", shape=(n,))
        _check_array_file(partial, "done mask", info)
        return int(np.count_nonzero(np.load(partial / DONE_FILE, mmap_mode="r"))), n
    if (partial / MANIFEST_FILE).is_file():  # killed during finish: every probe is written
        n = _load_manifest_json(partial / MANIFEST_FILE, StoreManifest).grid.n_probes
        return n, n
    return None


def read_manifest(path: str | os.PathLike[str]) -> StoreManifest:
    """The validated manifest of a finished store (array headers and sizes are checked too)."""
    return _validate_store_dir(Path(path))


class _LazyArrays(Mapping[str, np.memmap]):
    """Read-only memory maps of a store's arrays, mapped on first access (thread-safe)."""

    def __init__(self, directory: Path, infos: Mapping[str, ArrayInfo]) -> None:
        self._directory = directory
        self._infos = dict(infos)
        self._maps: dict[str, np.memmap] = {}
        self._lock = threading.Lock()

    def __getitem__(self, name: str) -> np.memmap:
        arr = self._maps.get(name)
        if arr is not None:
            return arr
        info = self._infos.get(name)
        if info is None:
            raise KeyError(name)
        with self._lock:
            arr = self._maps.get(name)
            if arr is None:
                file = self._directory / info.file
                try:
                    arr = np.load(file, mmap_mode="r", allow_pickle=False)
                except (OSError, ValueError) as exc:
                    raise StoreError(f"cannot map {file}: {exc}") from None
                if arr.shape != info.shape or arr.dtype.str != info.dtype:
                    raise StoreError(f"{file} changed on disk since the store was opened")
                self._maps[name] = arr
        return arr

    def __iter__(self) -> Iterator[str]:
        return iter(self._infos)

    def __len__(self) -> int:
        return len(self._infos)

    def mapped(self) -> list[str]:
        """Names of the arrays mapped so far."""
        return list(self._maps)

    def clear(self) -> None:
        with self._lock:
            self._maps.clear()


class ProbeStore:
    """A finished grid store opened for reading; build it with :func:`open_store`.

    Attributes
    ----------
    path : Path
    manifest : StoreManifest
    grid : GridSpec
    arrays : Mapping[str, np.memmap]
        Read-only memory maps ``(P, ...)``, mapped on first access; index them with probe
        indices (``store.arrays["sh"][indices]``) to read only those probes' pages. The
        manifest's extras are mapped here too (see :attr:`extras`).
    """

    def __init__(self, path: Path, manifest: StoreManifest) -> None:
        self.path = path
        self.manifest = manifest
        self.grid: GridSpec = manifest.grid
        self.arrays: _LazyArrays = _LazyArrays(path, {**manifest.arrays, **manifest.extras})

    def __repr__(self) -> str:
        names = ", ".join(self.manifest.arrays)
        return f"ProbeStore({str(self.path)!r}, grid={self.grid.label}, arrays=[{names}])"

    @property
    def n_probes(self) -> int:
        """Number of probes ``P``."""
        return self.grid.n_probes

    @property
    def names(self) -> list[str]:
        """Array names in manifest order."""
        return list(self.manifest.arrays)

    @property
    def extras(self) -> list[str]:
        """Names of the extras (format 2; empty for older stores), also in :attr:`arrays`."""
        return list(self.manifest.extras)

    def __getitem__(self, name: str) -> np.memmap:
        """``store[name]`` is ``store.arrays[name]``; KeyError names the arrays there are."""
        try:
            return self.arrays[name]
        except KeyError:
            raise KeyError(f"no array {name!r} in {self.path.name} (has {self.names})") from None

    def valid_mask(self) -> NDArray[np.bool_] | None:
        """``(P,)`` bool: the bake's per-probe validity (False inside geometry), or None when the
        store records none (or not one value per probe)."""
        if "valid" in self.names and self.manifest.arrays["valid"].shape == (self.n_probes,):
            return np.asarray(self["valid"], dtype=bool)
        return None

    def probe_index(self, i: ArrayLike, j: ArrayLike, k: ArrayLike) -> NDArray[np.int64]:
        """Linear index ``(i * ny + j) * nz + k`` (see :meth:`GridSpec.probe_index`)."""
        return self.grid.probe_index(i, j, k)

    def probe(self, index: int) -> dict[str, NDArray[Any]]:
        """Every array's entry for one probe (read-only views into the maps)."""
        if not isinstance(index, (int, np.integer)) or not 0 <= index < self.n_probes:
            raise ValueError(f"probe index must be an integer in 0..{self.n_probes - 1}")
        return {name: self.arrays[name][int(index)] for name in self.names}

    def close(self) -> None:
        """Drop this object's maps (views already handed out stay valid until released)."""
        self.arrays.clear()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_store(path: str | os.PathLike[str]) -> ProbeStore:
    """Open a finished grid store for reading.

    Validates the manifest (format and version, schema) and every array file's header and size
    against it; maps nothing until an array is accessed. Raises :class:`StoreError` (one line)
    for a missing directory, an unfinished bake, a bad manifest or a damaged array file.
    """
    p = Path(path)
    return ProbeStore(p, _validate_store_dir(p))

