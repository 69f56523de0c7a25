"""Reading grid stores: manifest and file validation and :class:`ProbeStore`.

A store is read only through files opened directly in its directory without following links,
each checked against the manifest (header, size and SHA-256) before use; arrays are then
memory-mapped on first access or, for long-running readers, read into memory at open.
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import stat
import threading
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import ValidationError

from probegrid._version import __version__
from probegrid.core.grid import GridSpec
from probegrid.store import hashcache
from probegrid.store.manifest import (
    DONE_FILE,
    FORMAT_NAME,
    MANIFEST_FILE,
    PARTIAL_SUFFIX,
    PLAN_FILE,
    SUPPORTED_FORMAT_VERSIONS,
    ArrayInfo,
    SceneFile,
    StoreError,
    StoreManifest,
    _final_path,
    _Plan,
    _validation_message,
    partial_path,
)

__all__ = ['ProbeStore', 'file_sha256', 'open_store', 'partial_progress', 'read_manifest']


_OPEN_FLAGS = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)


def _identity(st: os.stat_result) -> tuple[int, int, int, int, int]:
    """What identifies one version of a file on disk."""
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def _open_in_store(directory: Path, name: str, what: str = "file",
                   missing: str | None = None) -> BinaryIO:
    """Open the regular file ``name`` directly inside ``directory`` for reading, following no
    symbolic link: StoreError (one line) when ``name`` is not a plain file name, is missing, is
    a link (wherever it points), is not a regular file or has other hard links (a name outside
    the store for the same file: what is served could be changed from there, and a store
    written without SHA-256s could serve any file of the user's)."""
    if not name or "/" in name or "\\" in name or name in (".", "..") or "\0" in name:
        raise StoreError(f"{directory}: {what} {name[:80]!r} is not a file name inside the store")
    file = directory / name
    try:
        f = open(file, "rb", opener=lambda path, _flags: os.open(path, _OPEN_FLAGS))  # noqa: SIM115
    except FileNotFoundError:
        raise StoreError(missing or f"{directory}: {what} {name} is missing") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise StoreError(f"{file} is a symbolic link; a store's files must be regular files "
                             "inside its directory") from None
        raise StoreError(f"cannot read {file}: {exc.strerror}") from None
    st = os.fstat(f.fileno())
    if not stat.S_ISREG(st.st_mode):
        f.close()
        raise StoreError(f"{file} is not a regular file; the store is damaged")
    if st.st_nlink > 1:  # the same file under another name, maybe outside the store
        f.close()
        raise StoreError(f"{file} has {st.st_nlink} hard links; a store's files must be its own "
                         "(copy the store with cp -r or rsync without --link-dest)")
    return f


def _read_npy_header(f: BinaryIO) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    """Shape, Fortran flag, dtype and data offset of an open .npy file (reads the header only)."""
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
    else:
        raise ValueError(f"unsupported .npy version {version}")
    return shape, fortran, dtype, f.tell()


def _check_sha256(f: BinaryIO, file: Path, expected: str | None,
                  data: bytearray | None = None) -> None:
    """StoreError unless the open file's content has SHA-256 ``expected`` (None: not recorded,
    nothing to check). ``data``, when given, is the file's content already read."""
    if expected is None:
        return
    identity = _identity(os.fstat(f.fileno()))
    if hashcache.is_verified(identity, expected):  # hashed before, here or by another process
        return
    if data is not None:
        digest = hashlib.sha256(data).hexdigest()
    else:
        f.seek(0)
        digest = hashlib.file_digest(f, "sha256").hexdigest()
    if digest != expected:
        raise StoreError(f"{file} does not have the SHA-256 the manifest records; the store is "
                         "damaged or was changed after it was written")
    hashcache.remember(identity, digest)


@dataclass(frozen=True)
class _CheckedFile:
    """A store file as checked: its name, the offset of its data, its identity on disk
    (:func:`_identity`) and, when read into memory, its content."""

    name: str
    offset: int
    identity: tuple[int, int, int, int, int]
    data: bytearray | None = None


def _read_all(f: BinaryIO, size: int, file: Path) -> bytearray:
    """The whole open file (``size`` bytes); StoreError when it is shorter."""
    buf = bytearray(size)
    view = memoryview(buf)
    f.seek(0)
    got = 0
    while got < size:
        n = f.readinto(view[got:])
        if not n:
            raise StoreError(f"{file} was truncated while it was read; the store is changing")
        got += n
    return buf


def _check_array_file(directory: Path, name: str, info: ArrayInfo, *, verify: bool = False,
                      load: bool = False) -> _CheckedFile:
    """Check one array file against its manifest entry: a regular file inside the store, a C
    order ``.npy`` of the recorded dtype and shape, exactly as long as that, and (``verify``)
    of the recorded SHA-256; ``load`` reads it into memory too."""
    with _open_in_store(directory, info.file, f"array {name!r} file",
                        f"{directory}: array {name!r} is missing its file {info.file}") as f:
        file = directory / info.file
        try:
            shape, fortran, dtype, offset = _read_npy_header(f)
        except (OSError, ValueError) as exc:
            raise StoreError(f"{file} is not a valid .npy file ({exc})") from None
        if fortran:
            raise StoreError(f"{file} is in Fortran order; the store needs C order")
        if dtype.str != info.dtype:
            raise StoreError(f"{file} has dtype {dtype.str}, the manifest says {info.dtype}")
        if tuple(shape) != info.shape:
            raise StoreError(f"{file} has shape {tuple(shape)}, the manifest says {info.shape}")
        st = os.fstat(f.fileno())
        size, expected = st.st_size, offset + info.nbytes
        if size != expected:
            state = "truncated" if size < expected else "too long"
            raise StoreError(f"{file} is {state}: {size} bytes, expected {expected}")
        data = _read_all(f, size, file) if load else None
        if verify:
            _check_sha256(f, file, info.sha256, data)
        if load and _identity(os.fstat(f.fileno())) != _identity(st):
            raise StoreError(f"{file} changed while it was read; the store is changing")
        return _CheckedFile(name=info.file, offset=offset, identity=_identity(st), data=data)


def _check_scene_file(directory: Path, kept: SceneFile, *, verify: bool = False,
                      load: bool = False) -> _CheckedFile:
    """Check the store's scene copy: a regular file inside the store of the recorded size and
    (``verify``) SHA-256; ``load`` reads it into memory too."""
    with _open_in_store(directory, kept.file, "scene copy",
                        f"{directory / kept.file} is missing or is not the {kept.bytes} bytes "
                        "the manifest says") as f:
        file = directory / kept.file
        st = os.fstat(f.fileno())
        if st.st_size != kept.bytes:
            raise StoreError(f"{file} is missing or is not the {kept.bytes} bytes the manifest "
                             "says")
        data = _read_all(f, st.st_size, file) if load else None
        if verify:
            _check_sha256(f, file, kept.sha256, data)
        return _CheckedFile(name=kept.file, offset=0, identity=_identity(st), data=data)


def _read_manifest_bytes(file: Path) -> bytes:
    try:
        with _open_in_store(file.parent, file.name, "manifest") as f:
            return f.read()
    except OSError as exc:
        raise StoreError(f"cannot read {file}: {exc}") from None


def _load_manifest_json(file: Path, model: type[_Plan], data: bytes | None = None) -> Any:
    """The manifest (or plan) in ``file`` validated as ``model``; ``data``: its bytes, if read."""
    try:
        text = (_read_manifest_bytes(file) if data is None else data).decode("utf-8")
    except UnicodeDecodeError as exc:
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
        if (isinstance(version, int) and not isinstance(version, bool)
                and version > max(SUPPORTED_FORMAT_VERSIONS)):
            raise StoreError(
                f"{file} has store format version {version}, written by a newer probegrid; "
                f"probegrid {__version__} reads version {supported}: upgrade probegrid to read "
                "this store")
        raise StoreError(
            f"{file} has store format version {version!r}; probegrid {__version__} reads "
            f"version {supported}"
        )
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        raise StoreError(f"{file} is invalid: {_validation_message(exc)}") from None


def _validate_store_dir(directory: Path, *, allow_partial: bool = False) -> StoreManifest:
    return _check_store_dir(directory, allow_partial=allow_partial)[0]


def _check_store_dir(
    directory: Path, *, allow_partial: bool = False, verify: bool = False, load: bool = False
) -> tuple[StoreManifest, dict[str, _CheckedFile], str]:
    """The manifest of a finished store, its files as checked (by array name; the scene copy
    under ``""``) and the SHA-256 of the manifest's bytes: see :func:`open_store`."""
    if not directory.is_dir():
        raise StoreError(f"{directory} is not a probe store (no such directory)")
    if not allow_partial and (
        directory.name.endswith(PARTIAL_SUFFIX) or os.path.lexists(directory / PLAN_FILE)
    ):
        raise StoreError(f"{directory} is an unfinished bake, not a store; resume or rerun it")
    manifest_file = directory / MANIFEST_FILE
    if not os.path.lexists(manifest_file):
        raise StoreError(f"{directory} is not a finished probe store (no {MANIFEST_FILE})")
    manifest_bytes = _read_manifest_bytes(manifest_file)
    manifest = _load_manifest_json(manifest_file, StoreManifest, manifest_bytes)
    checked = {name: _check_array_file(directory, name, info, verify=verify, load=load)
               for name, info in {**manifest.arrays, **manifest.extras}.items()}
    if manifest.scene_file is not None:
        checked[""] = _check_scene_file(directory, manifest.scene_file, verify=verify,
                                        load=load)
    return manifest, checked, hashlib.sha256(manifest_bytes).hexdigest()


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


def file_sha256(file: Path) -> str:
    """SHA-256 (hex) of a store file, opened as the reader opens it (no link followed); the file
    counts as verified while it is unchanged (:mod:`probegrid.store.hashcache`; for the writer,
    which records the hashes)."""
    with _open_in_store(file.parent, file.name) as f:
        digest = hashlib.file_digest(f, "sha256").hexdigest()
        hashcache.remember(_identity(os.fstat(f.fileno())), digest)
    return digest


class _LazyArrays(Mapping[str, NDArray[Any]]):
    """A store's arrays, read-only: memory maps made on first access (thread-safe), or the
    arrays read into memory when the store was opened with ``load=True``."""

    def __init__(self, directory: Path, infos: Mapping[str, ArrayInfo],
                 checked: Mapping[str, _CheckedFile] | None = None) -> None:
        self._directory = directory
        self._infos = dict(infos)
        self._checked = dict(checked or {})
        self._maps: dict[str, NDArray[Any]] = {}
        self._lock = threading.Lock()

    def _make(self, name: str, info: ArrayInfo) -> NDArray[Any]:
        file = self._directory / info.file
        checked = self._checked.get(name)
        if checked is not None and checked.data is not None:
            arr = np.frombuffer(checked.data, dtype=np.dtype(info.dtype),
                                count=math.prod(info.shape), offset=checked.offset)
            arr = arr.reshape(info.shape)
            arr.flags.writeable = False
            return arr
        with _open_in_store(self._directory, info.file, f"array {name!r} file") as f:
            if checked is not None and _identity(os.fstat(f.fileno())) != checked.identity:
                raise StoreError(f"{file} changed on disk since the store was opened")
            try:
                shape, fortran, dtype, offset = _read_npy_header(f)
                if shape != info.shape or dtype.str != info.dtype or fortran:
                    raise StoreError(f"{file} changed on disk since the store was opened")
                return np.memmap(f, dtype=dtype, mode="r", offset=offset, shape=shape)
            except (OSError, ValueError) as exc:
                raise StoreError(f"cannot map {file}: {exc}") from None

    def __getitem__(self, name: str) -> NDArray[Any]:
        arr = self._maps.get(name)
        if arr is not None:
            return arr
        info = self._infos.get(name)
        if info is None:
            raise KeyError(name)
        with self._lock:
            arr = self._maps.get(name)
            if arr is None:
                arr = self._maps[name] = self._make(name, info)
        return arr

    def __iter__(self) -> Iterator[str]:
        return iter(self._infos)

    def __len__(self) -> int:
        return len(self._infos)

    def mapped(self) -> list[str]:
        """Names of the arrays mapped (or taken from memory) so far."""
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
    arrays : Mapping[str, ndarray]
        Read-only arrays ``(P, ...)``: memory maps made on first access (or arrays in memory,
        see :func:`open_store`'s ``load``); index them with probe
        indices (``store.arrays["sh"][indices]``) to read only those probes' pages. The
        manifest's extras are mapped here too (see :attr:`extras`).
    """

    def __init__(self, path: Path, manifest: StoreManifest,
                 checked: Mapping[str, _CheckedFile] | None = None,
                 manifest_sha256: str | None = None) -> None:
        self.path = path
        self.manifest = manifest
        #: SHA-256 (hex) of the manifest's bytes as read: the store's content identity (the
        #: manifest records every file's hash, the bake and its creation time).
        self.manifest_sha256 = manifest_sha256
        self.grid: GridSpec = manifest.grid
        self._checked = dict(checked or {})
        self.arrays: _LazyArrays = _LazyArrays(path, {**manifest.arrays, **manifest.extras},
                                               self._checked)

    @property
    def in_memory(self) -> bool:
        """Whether the arrays were read into memory when the store was opened (``load=True``)."""
        return any(c.data is not None for c in self._checked.values())

    def scene_bytes(self) -> bytes | None:
        """The store's copy of its glTF scene (``manifest.scene_file``), None if it keeps none;
        read now (checked against the recorded size and SHA-256) unless it was read at open."""
        kept = self.manifest.scene_file
        if kept is None:
            return None
        checked = self._checked.get("")
        if checked is not None and checked.data is not None:
            return bytes(checked.data)
        data = _check_scene_file(self.path, kept, verify=True, load=True).data
        return bytes(data) if data is not None else b""

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

    def __getitem__(self, name: str) -> NDArray[Any]:
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


def open_store(path: str | os.PathLike[str], *, verify: bool = True,
               load: bool = False) -> ProbeStore:
    """Open a finished grid store for reading.

    Validates the manifest (format and version, schema) and every file against it: each one a
    regular file directly in the store's directory (opened without following links; a link is
    refused wherever it points), each array's header and size and, with ``verify`` (the
    default), the SHA-256 the manifest records for each file (hashed once while the file is
    unchanged, the digest kept across processes: :mod:`probegrid.store.hashcache`; stores
    written before hashes were recorded are checked by size). A file with other hard links is
    refused too. Raises
    :class:`StoreError` (one line) for a missing directory, an unfinished bake, a bad manifest or
    a damaged, linked or changed file.

    ``load=False`` maps nothing until an array is accessed (read-only memory maps, shared
    between processes through the page cache; a file truncated under a map makes reads of the
    lost pages fault with SIGBUS). ``load=True`` reads every array into memory now (the store's
    size in memory), so later changes to the files cannot reach the arrays: what a long-running
    server needs.
    """
    p = Path(path)
    manifest, checked, digest = _check_store_dir(p, verify=verify, load=load)
    return ProbeStore(p, manifest, checked, digest)
