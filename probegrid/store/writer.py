"""Writing grid stores atomically and resumably (:class:`StoreWriter`, :func:`create_npy`).

The format is :mod:`probegrid.store.manifest`'s.

Atomic, resumable writes
------------------------
:class:`StoreWriter` never writes into ``NAME.probes`` itself. A bake works in
``NAME.probes.partial/``:

1. ``create`` preallocates every array with ``np.lib.format.open_memmap``, an all-false done
   mask ``_done.npy (P,) bool``, and last the bake plan ``_bake.json`` (grid, arrays, bake
   settings, scene hash, conventions), written atomically. A ``.partial`` directory without
   ``_bake.json`` is an interrupted start and holds nothing worth keeping (a failed ``create``
   removes it). ``open_memmap`` makes *sparse* files, whose blocks the file system only allocates
   when a page of the map is first written; on a full disk that write cannot fail with an error
   code and the kernel kills the process with ``SIGBUS``. So every array file's blocks are
   reserved with ``posix_fallocate`` right after it is created: a full disk raises
   ``OSError(ENOSPC)`` in ``create``, before any probe is baked. (File systems without
   ``fallocate`` support, ``EOPNOTSUPP``/``EINVAL``, keep sparse files.)
2. ``write(indices, values)`` stores a batch into the maps, ``msync``s them, and only *then* sets
   and ``msync``s the batch's entries of the done mask, so a probe marked done always has its data
   on disk, whenever the process dies. (``durable=False`` skips the ``msync``s: stores to shared
   maps outlive a killed process in program order, so this still holds for a killed process,
   not for an OS crash.)
3. ``finish`` checks every probe is done, flushes and ``fsync``s the arrays, records each
   file's SHA-256 (readers check them), writes ``manifest.json`` atomically (temporary file,
   ``fsync``, ``os.replace``, ``fsync`` of the directory), removes the plan and the done mask, and renames the directory to ``NAME.probes``
   (one atomic ``rename``; an existing store is only replaced with ``overwrite=True``, by
   :func:`probegrid._fs.publish_directory`: the path holds the old or the new store at every
   instant, the old one is deleted afterwards, and readers that still map its files keep
   valid maps).

Nothing in a ``.partial`` directory ever loads: :func:`open_store` refuses a ``.partial`` name, a
directory holding a bake plan, one without a valid manifest, and arrays that disagree with the
manifest. ``resume`` reopens the partial directory, checks that the grid, arrays, bake settings,
scene hash and conventions are the ones it was started with, and carries on: ``remaining()`` lists
the probes still to bake. A bake killed during ``finish`` after the manifest was written resumes
straight into the final rename. One writer at a time: the partial directory is ``flock``-ed.

All failures raise :class:`~probegrid.errors.StoreError` with a one-line message.
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import shutil
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Final, Literal, Self

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray
from pydantic import BaseModel

from probegrid._fs import (
    atomic_write_bytes,
    atomic_write_text,
    fsync_dir,
    fsync_file,
    lock_dir,
    publish_directory,
    remove_path,
)
from probegrid.core.grid import GridSpec
from probegrid.store.manifest import (
    DONE_FILE,
    FORMAT_VERSION,
    MANIFEST_FILE,
    PLAN_FILE,
    ArrayInfo,
    ArraySpec,
    BakeInputs,
    SceneFile,
    StoreError,
    StoreManifest,
    _check_dtype,
    _check_name,
    _final_path,
    _jsonable,
    _Plan,
    partial_path,
)
from probegrid.store.reader import (
    ProbeStore,
    _check_array_file,
    _load_manifest_json,
    _validate_store_dir,
    file_sha256,
    open_store,
)

__all__ = ['StoreWriter', 'create_npy']


# ---------------------------------------------------------------------------- the scene copy
_GLB_MAGIC: Final = b"glTF"


def keepable_scene(path: str | os.PathLike[str]) -> Literal["scene.glb", "scene.gltf"] | None:
    """The name a store would keep a copy of this glTF file under, or None when it cannot.

    A GLB is kept as ``scene.glb``; a ``.gltf`` whose buffers and images are all embedded
    (``data:`` URIs, or a buffer without a URI) as ``scene.gltf``. A ``.gltf`` that refers to
    other files is not kept (None): the copy would be incomplete. Raises :class:`StoreError`
    when the file cannot be read or is neither.
    """
    p = Path(path)
    try:
        with open(p, "rb") as f:
            head = f.read(4)
            if head == _GLB_MAGIC:
                return "scene.glb"
            doc = json.loads(head + f.read())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise StoreError(f"cannot keep the scene {p}: not a readable glTF file ({exc})") from None
    if not isinstance(doc, dict):
        raise StoreError(f"cannot keep the scene {p}: not a glTF document")
    for key in ("buffers", "images"):
        for item in doc.get(key) or []:
            uri = item.get("uri") if isinstance(item, dict) else None
            if isinstance(uri, str) and not uri.startswith("data:"):
                return None
    return "scene.gltf"


def _keep_scene(source: Path, directory: Path) -> SceneFile | None:
    """Copy ``source`` into ``directory`` under its fixed name (atomically); its manifest entry."""
    name = keepable_scene(source)
    if name is None:
        return None
    try:
        data = source.read_bytes()
    except OSError as exc:
        raise StoreError(f"cannot keep the scene {source}: {exc}") from None
    atomic_write_bytes(directory / name, data)
    media = "model/gltf-binary" if name == "scene.glb" else "model/gltf+json"
    return SceneFile(file=name, media_type=media, bytes=len(data),
                     sha256=hashlib.sha256(data).hexdigest(), source=source.name)


# ---------------------------------------------------------------------------- writing
#: ``posix_fallocate`` errors meaning "this file system cannot reserve blocks" (keep it sparse).
_NO_FALLOCATE: Final = frozenset({errno.EOPNOTSUPP, errno.ENOTSUP, errno.EINVAL, errno.ENOSYS})


def _reserve_blocks(file: Path) -> None:
    """Allocate every block of ``file`` now (``posix_fallocate``), so that writing through a
    memory map of it can never meet a full disk (which is ``SIGBUS``, not an error code).

    Raises ``OSError`` (``ENOSPC`` on a full disk) with a one-line message; does nothing on file
    systems that do not support ``fallocate``.
    """
    fd = os.open(file, os.O_RDWR)
    size = 0
    try:
        size = os.fstat(fd).st_size
        if size:
            os.posix_fallocate(fd, 0, size)
    except OSError as exc:
        if exc.errno in _NO_FALLOCATE:
            return
        raise OSError(
            exc.errno, f"cannot reserve {_size_text(size)} on disk for {file}: {exc.strerror}"
        ) from None
    finally:
        os.close(fd)


def _size_text(nbytes: int) -> str:
    return f"{nbytes} bytes" if nbytes < 2**20 else f"{nbytes / 2**20:.1f} MiB"


def create_npy(file: str | os.PathLike[str], dtype: DTypeLike, shape: tuple[int, ...]
               ) -> np.memmap:
    """A new zero-filled ``.npy`` file, memory-mapped read-write, its disk blocks reserved.

    ``np.lib.format.open_memmap(mode="w+")`` followed by ``posix_fallocate`` over the whole file
    and an ``fsync``: a full disk raises ``OSError(ENOSPC)`` here instead of killing the process
    with ``SIGBUS`` when a page of the map is first written (see the module docstring). Use it
    for every memory-mapped array a bake writes.

    Parameters
    ----------
    file : path of the new file (replaced if it exists)
    dtype : numpy dtype
    shape : tuple of int
    """
    file = Path(file)
    mm = np.lib.format.open_memmap(file, mode="w+", dtype=np.dtype(dtype), shape=shape)
    try:
        _reserve_blocks(file)
        fsync_file(file)
    except BaseException:
        del mm
        raise
    return mm


@contextmanager
def _locked_setup(directory: Path) -> Iterator[int]:
    """Lock ``directory`` (:func:`lock_dir`) and yield the fd; release it if the block raises.

    On success the fd stays open: the new :class:`StoreWriter` holds the lock until it closes.
    """
    fd = lock_dir(directory)
    try:
        yield fd
    except BaseException:
        os.close(fd)
        raise


def _check_target(final: Path, overwrite: bool) -> None:
    if final.exists() and not overwrite:
        raise StoreError(f"{final} already exists; pass overwrite=True (--overwrite) to replace it")


def _plan_differences(old: _Plan, new: _Plan) -> list[str]:
    diffs = []
    if old.grid != new.grid:
        diffs.append(f"grid ({old.grid.label} {old.grid.bounds_min}..{old.grid.bounds_max} "
                     f"vs {new.grid.label} {new.grid.bounds_min}..{new.grid.bounds_max})")
    old_arrays = {n: (a.shape, a.dtype) for n, a in old.arrays.items()}
    new_arrays = {n: (a.shape, a.dtype) for n, a in new.arrays.items()}
    if old_arrays != new_arrays:
        changed = sorted(set(old_arrays) ^ set(new_arrays)) + sorted(
            n for n in set(old_arrays) & set(new_arrays) if old_arrays[n] != new_arrays[n]
        )
        diffs.append(f"arrays ({', '.join(changed)})")
    if old.scene_hash != new.scene_hash:
        diffs.append(f"scene_hash ({old.scene_hash[:16]} vs {new.scene_hash[:16]})")
    if old.bake != new.bake:
        keys = sorted(
            k for k in set(old.bake) | set(new.bake) if old.bake.get(k) != new.bake.get(k)
        )
        diffs.append(f"bake settings ({', '.join(keys)})")
    if old.conventions != new.conventions:
        diffs.append("conventions")
    return diffs


class StoreWriter:
    """Writes a grid store atomically and resumably (see the module docstring).

    Build it with :meth:`create`, :meth:`resume` or :meth:`create_or_resume`; then ``write``
    batches and ``finish``. Usable as a context manager: leaving the block without ``finish``
    (an exception, say) closes the writer and keeps the partial directory for ``resume``.
    """

    def __init__(
        self,
        *,
        final: Path,
        plan: _Plan,
        lock_fd: int,
        overwrite: bool,
        durable: bool,
        maps: dict[str, np.memmap],
        done_map: np.memmap | None,
        manifest: StoreManifest | None = None,
    ) -> None:
        self._final = final
        self._partial = partial_path(final)
        self._plan = plan
        self._lock_fd: int | None = lock_fd
        self._overwrite = overwrite
        self._durable = durable
        self._maps = maps
        self._done_map = done_map
        self._finished_manifest = manifest  # resumed after manifest.json was written
        self._done = (
            np.ones(plan.grid.n_probes, dtype=bool) if done_map is None else done_map
        )
        #: Extras added so far (kept from a manifest written by an interrupted ``finish``).
        self._extras: dict[str, ArrayInfo] = dict(manifest.extras) if manifest else {}

    # ------------------------------------------------------------------ construction
    @staticmethod
    def _make_plan(
        *,
        arrays: Mapping[str, ArraySpec],
        grid: GridSpec,
        conventions: Mapping[str, Any] | BaseModel,
        scene_hash: str,
        bake: Mapping[str, Any] | BaseModel | None,
    ) -> _Plan:
        if not isinstance(grid, GridSpec):
            raise TypeError(f"grid must be a GridSpec, got {type(grid).__name__}")
        if not isinstance(scene_hash, str) or not scene_hash:
            raise ValueError(f"scene_hash must be a non-empty string, got {scene_hash!r}")
        if not arrays:
            raise ValueError("a store needs at least one array")
        infos = {}
        for name, spec in arrays.items():
            _check_name(name)
            if not isinstance(spec, ArraySpec):
                raise TypeError(f"array {name!r} must be declared with an ArraySpec")
            infos[name] = ArrayInfo(
                file=f"{name}.npy",
                dtype=spec.dtype,
                shape=(grid.n_probes, *spec.shape),
                description=spec.description,
            )
        conv = _jsonable(conventions, "conventions")
        if not conv:
            raise ValueError("conventions must be a non-empty record (probegrid.core.conventions)")
        return _Plan(
            bake_started=datetime.now(UTC),
            conventions=conv,
            grid=grid,
            bake=_jsonable({} if bake is None else bake, "bake settings"),
            scene_hash=scene_hash,
            arrays=infos,
        )

    @classmethod
    def create(
        cls,
        path: str | os.PathLike[str],
        *,
        arrays: Mapping[str, ArraySpec],
        grid: GridSpec,
        conventions: Mapping[str, Any] | BaseModel,
        scene_hash: str,
        bake: Mapping[str, Any] | BaseModel | None = None,
        overwrite: bool = False,
        durable: bool = True,
    ) -> StoreWriter:
        """Start a new bake of the store ``path`` (``NAME.probes``) in ``NAME.probes.partial``.

        Parameters
        ----------
        path : path of the finished store
        arrays : name -> ArraySpec
            The per-probe arrays every :meth:`write` must fill.
        grid : GridSpec
        conventions : mapping or pydantic model
            The conventions record (JSON-serialisable, non-empty).
        scene_hash : str
            Content hash of the scene; ``resume`` refuses a different one.
        bake : mapping or pydantic model, optional
            Bake settings (JSON-serialisable); ``resume`` refuses different ones.
        overwrite : bool
            Replace an existing store at ``path`` on ``finish`` and discard an unfinished bake
            in ``NAME.probes.partial``; without it either one is an error.
        durable : bool
            ``msync`` the data, then the done mask, after every batch (the default), so the
            mask never runs ahead of the data even across a power loss or an OS crash. With
            False, batches stay in the page cache until ``finish``: still safe when the *process*
            is killed (its writes to shared maps survive it, in order), several times faster on
            slow disks, but an OS crash may leave probes marked done without their data.
        """
        final = _final_path(path)
        plan = cls._make_plan(
            arrays=arrays, grid=grid, conventions=conventions, scene_hash=scene_hash, bake=bake
        )
        _check_target(final, overwrite)
        partial = partial_path(final)
        if partial.is_symlink() or (partial.exists() and not partial.is_dir()):
            remove_path(partial)  # not ours: the link goes, never its target's contents
        if partial.exists():
            has_state = (partial / PLAN_FILE).exists() or (partial / MANIFEST_FILE).exists()
            if has_state and not overwrite:
                raise StoreError(
                    f"an unfinished bake exists at {partial}; resume it or pass overwrite=True"
                )
            fd = lock_dir(partial)  # never delete a directory another writer is using
            try:
                remove_path(partial)
            finally:
                os.close(fd)
        partial.mkdir(parents=True)
        with _locked_setup(partial) as fd:
            maps: dict[str, np.memmap] = {}
            try:
                for name, info in plan.arrays.items():
                    maps[name] = create_npy(partial / info.file, info.dtype, info.shape)
                done = create_npy(partial / DONE_FILE, "|b1", (grid.n_probes,))
                atomic_write_text(partial / PLAN_FILE, plan.model_dump_json(indent=2))
            except BaseException:
                # nothing here is worth keeping (no plan yet); give the reserved space back
                maps.clear()
                shutil.rmtree(partial, ignore_errors=True)
                raise
        return cls(
            final=final,
            plan=plan,
            lock_fd=fd,
            overwrite=overwrite,
            durable=durable,
            maps=maps,
            done_map=done,
        )

    @classmethod
    def resume(
        cls,
        path: str | os.PathLike[str],
        *,
        arrays: Mapping[str, ArraySpec],
        grid: GridSpec,
        conventions: Mapping[str, Any] | BaseModel,
        scene_hash: str,
        bake: Mapping[str, Any] | BaseModel | None = None,
        overwrite: bool = False,
        durable: bool = True,
    ) -> StoreWriter:
        """Continue the unfinished bake of ``path`` from the probes it finished.

        Takes the same arguments as :meth:`create`; the grid, arrays (shapes and dtypes), bake
        settings, scene hash and conventions must equal those the bake was started with,
        otherwise a :class:`StoreError` names what differs.
        """
        final = _final_path(path)
        plan = cls._make_plan(
            arrays=arrays, grid=grid, conventions=conventions, scene_hash=scene_hash, bake=bake
        )
        partial = partial_path(final)
        if not partial.is_dir() or partial.is_symlink():
            raise StoreError(f"no unfinished bake at {partial} to resume")
        with _locked_setup(partial) as fd:
            _check_target(final, overwrite)
            if (partial / PLAN_FILE).is_file():
                stored: _Plan = _load_manifest_json(partial / PLAN_FILE, _Plan)
                manifest = None
            elif (partial / MANIFEST_FILE).is_file():
                manifest = _validate_store_dir(partial, allow_partial=True)
                stored = manifest
            else:
                raise StoreError(
                    f"{partial} holds no bake state (interrupted while starting); start again"
                )
            diffs = _plan_differences(stored, plan)
            if diffs:
                raise StoreError(
                    f"the unfinished bake at {partial} was started with different "
                    f"{'; '.join(diffs)}; start again with overwrite=True"
                )
            maps: dict[str, np.memmap] = {}
            done = None
            if manifest is None:
                for name, info in stored.arrays.items():
                    _check_array_file(partial, name, info)
                    _reserve_blocks(partial / info.file)  # e.g. a bake started by an old version
                    maps[name] = np.load(partial / info.file, mmap_mode="r+")
                done_info = ArrayInfo(file=DONE_FILE, dtype="|b1", shape=(grid.n_probes,))
                _check_array_file(partial, "done mask", done_info)
                done = np.load(partial / DONE_FILE, mmap_mode="r+")
        return cls(
            final=final,
            plan=stored,
            lock_fd=fd,
            overwrite=overwrite,
            durable=durable,
            maps=maps,
            done_map=done,
            manifest=manifest,
        )

    @classmethod
    def create_or_resume(
        cls,
        path: str | os.PathLike[str],
        *,
        arrays: Mapping[str, ArraySpec],
        grid: GridSpec,
        conventions: Mapping[str, Any] | BaseModel,
        scene_hash: str,
        bake: Mapping[str, Any] | BaseModel | None = None,
        overwrite: bool = False,
        durable: bool = True,
    ) -> StoreWriter:
        """:meth:`resume` when ``NAME.probes.partial`` holds a resumable bake, else :meth:`create`.

        A partial bake started with different settings is an error (as in :meth:`resume`);
        ``overwrite`` only concerns an existing finished store at ``path``.
        """
        kw: dict[str, Any] = {
            "arrays": arrays,
            "grid": grid,
            "conventions": conventions,
            "scene_hash": scene_hash,
            "bake": bake,
            "overwrite": overwrite,
            "durable": durable,
        }
        partial = partial_path(_final_path(path))
        if not partial.is_symlink() and ((partial / PLAN_FILE).is_file()
                                         or (partial / MANIFEST_FILE).is_file()):
            return cls.resume(path, **kw)
        return cls.create(path, **kw)

    @classmethod
    def resumable(
        cls,
        path: str | os.PathLike[str],
        *,
        arrays: Mapping[str, ArraySpec],
        grid: GridSpec,
        conventions: Mapping[str, Any] | BaseModel,
        scene_hash: str,
        bake: Mapping[str, Any] | BaseModel | None = None,
    ) -> bool:
        """Whether ``NAME.probes.partial`` (a real directory, not a link) holds an unfinished
        bake that :meth:`resume` with these arguments would continue."""
        partial = partial_path(_final_path(path))
        if partial.is_symlink() or not partial.is_dir():
            return False
        plan = cls._make_plan(
            arrays=arrays, grid=grid, conventions=conventions, scene_hash=scene_hash, bake=bake
        )
        try:
            if (partial / PLAN_FILE).is_file():
                stored: _Plan = _load_manifest_json(partial / PLAN_FILE, _Plan)
            elif (partial / MANIFEST_FILE).is_file():
                stored = _validate_store_dir(partial, allow_partial=True)
            else:
                return False
        except (StoreError, OSError, ValueError):
            return False
        return not _plan_differences(stored, plan)

    # ------------------------------------------------------------------ state
    @property
    def path(self) -> Path:
        """Path of the finished store (``NAME.probes``)."""
        return self._final

    @property
    def partial_path(self) -> Path:
        """The working directory ``NAME.probes.partial``."""
        return self._partial

    @property
    def grid(self) -> GridSpec:
        return self._plan.grid

    @property
    def n_probes(self) -> int:
        return self._plan.grid.n_probes

    @property
    def array_infos(self) -> dict[str, ArrayInfo]:
        """The declared arrays (full shapes ``(P, ...)``)."""
        return dict(self._plan.arrays)

    @property
    def done(self) -> NDArray[np.bool_]:
        """``(P,)`` bool copy of the done mask."""
        return np.array(self._done, dtype=bool)

    @property
    def n_done(self) -> int:
        return int(np.count_nonzero(self._done))

    def remaining(self) -> NDArray[np.int64]:
        """Linear indices of the probes not written yet, ascending, int64."""
        return np.flatnonzero(~np.asarray(self._done)).astype(np.int64)

    def array(self, name: str) -> NDArray[Any]:
        """Read-only view of one array as written so far (e.g. for quality figures)."""
        self._require_open()
        if self._finished_manifest is not None:
            return np.load(self._partial / self._plan.arrays[name].file, mmap_mode="r")
        view = self._maps[name].view(np.ndarray)
        view.flags.writeable = False
        return view

    def _require_open(self) -> None:
        if self._lock_fd is None:
            raise StoreError(f"the writer of {self._final} is closed")

    # ------------------------------------------------------------------ writing
    def write(self, indices: ArrayLike, values: Mapping[str, ArrayLike]) -> None:
        """Store one batch of probes and mark them done (durably, data first).

        Parameters
        ----------
        indices : (B,) int
            Distinct linear probe indices.
        values : name -> (B, *shape) array
            Every declared array, castable to its dtype (``same_kind``; e.g. float32 into a
            float16 array). Everything is checked before anything is written.
        """
        self._require_open()
        idx = np.asarray(indices)
        if idx.ndim != 1 or (idx.size and not np.issubdtype(idx.dtype, np.integer)):
            raise ValueError(f"indices must be a 1-D integer array, got {idx.dtype} {idx.shape}")
        idx = idx.astype(np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= self.n_probes):
            raise ValueError(f"probe indices must lie in 0..{self.n_probes - 1}")
        if np.unique(idx).size != idx.size:
            raise ValueError("probe indices of a batch must be distinct")
        missing = sorted(set(self._plan.arrays) - set(values))
        unknown = sorted(set(values) - set(self._plan.arrays))
        if missing or unknown:
            raise ValueError(
                f"a batch must give exactly the store's arrays; missing {missing}, unknown "
                f"{unknown}"
            )
        checked = {}
        for name, info in self._plan.arrays.items():
            v = np.asarray(values[name])
            want = (idx.size, *info.shape[1:])
            if v.shape != want:
                raise ValueError(f"array {name!r} needs shape {want} for this batch, got {v.shape}")
            if not np.can_cast(v.dtype, info.dtype, casting="same_kind"):
                raise ValueError(f"array {name!r} is {info.dtype}; cannot store {v.dtype} in it")
            checked[name] = v
        if idx.size == 0:
            return
        if self._finished_manifest is not None:
            raise StoreError(f"every probe of {self._partial} is already written; call finish()")
        for name, v in checked.items():
            self._maps[name][idx] = v
        if self._durable:
            for mm in self._maps.values():
                mm.flush()  # msync(MS_SYNC): the data is on disk before the mask says so
        assert self._done_map is not None
        self._done_map[idx] = True
        if self._durable:
            self._done_map.flush()

    def add_extra(self, name: str, values: ArrayLike, *, description: str = "") -> None:
        """Add an extra array to the store (see :mod:`probegrid.store.manifest`): written now,
        atomically, into the partial directory, and listed in the manifest by :meth:`finish`.

        Call it when every probe is written (extras are derived from the probes or describe
        the scene); calling it again with the same name replaces the array (a resumed bake
        redoes its extras).

        Parameters
        ----------
        name : str
            Not the name of one of the store's arrays.
        values : array
            Any shape with at least one element on every axis; bool, int, uint or float.
        description : str
        """
        self._require_open()
        _check_name(name)
        if name in self._plan.arrays:
            raise ValueError(f"extra {name!r} has the name of one of the store's arrays")
        left = self.n_probes - self.n_done
        if left:
            raise StoreError(f"cannot add {name!r} to {self._final}: {left} of "
                             f"{self.n_probes} probes are not written")
        a = np.ascontiguousarray(values)
        info = ArrayInfo(file=f"{name}.npy", dtype=_check_dtype(a.dtype), shape=a.shape,
                         description=description)
        buffer = io.BytesIO()
        np.save(buffer, a, allow_pickle=False)
        atomic_write_bytes(self._partial / info.file, buffer.getvalue())
        self._extras[name] = info

    def finish(
        self,
        *,
        quality: Mapping[str, Any] | BaseModel | None = None,
        scene_file: str | os.PathLike[str] | None = None,
        inputs: BakeInputs | Mapping[str, Any] | None = None,
    ) -> ProbeStore:
        """Publish the finished store atomically and return it opened for reading.

        Parameters
        ----------
        quality : mapping, optional
            Per-bake quality figures for the manifest (JSON-serialisable). When resuming a bake
            that was killed during a previous ``finish``, ``None`` keeps the recorded figures.
        scene_file : path, optional
            The glTF file that was baked: a copy is kept in the store and recorded in the
            manifest (``scene_file``) when :func:`keepable_scene` allows it.
        inputs : BakeInputs, optional
            The scene and environment as given (manifest ``inputs``); when resuming a bake
            killed during a previous ``finish``, ``None`` keeps the recorded ones.
        """
        self._require_open()
        left = self.n_probes - self.n_done
        if left:
            raise StoreError(
                f"cannot finish {self._final}: {left} of {self.n_probes} probes are not written"
            )
        if quality is None and self._finished_manifest is not None:
            q = self._finished_manifest.quality
        else:
            q = _jsonable({} if quality is None else quality, "quality figures")
        for name, mm in self._maps.items():
            mm.flush()
            fsync_file(self._partial / self._plan.arrays[name].file)
        self._maps = {}
        kept = None
        if scene_file is not None:
            kept = _keep_scene(Path(scene_file), self._partial)
        elif self._finished_manifest is not None:
            kept = self._finished_manifest.scene_file
        if inputs is None and self._finished_manifest is not None:
            inputs = self._finished_manifest.inputs
        elif inputs is not None and not isinstance(inputs, BakeInputs):
            inputs = BakeInputs.model_validate(inputs)
        plan_fields = self._plan.model_dump(include=set(_Plan.model_fields))
        plan_fields["arrays"] = self._hashed(self._plan.arrays)
        self._extras = self._hashed(self._extras)
        if self._extras:  # a version-1 plan (a bake resumed across versions) gains extras
            plan_fields["format_version"] = FORMAT_VERSION
        manifest = StoreManifest(**plan_fields, created=datetime.now(UTC), quality=q,
                                 scene_file=kept, extras=self._extras, inputs=inputs)
        atomic_write_text(self._partial / MANIFEST_FILE, manifest.model_dump_json(indent=2))
        self._done = np.ones(self.n_probes, dtype=bool)
        self._done_map = None
        for state in (PLAN_FILE, DONE_FILE):
            (self._partial / state).unlink(missing_ok=True)
        fsync_dir(self._partial)
        _check_target(self._final, self._overwrite)
        publish_directory(self._partial, self._final)
        self.close()
        return open_store(self._final)

    def _hashed(self, infos: Mapping[str, ArrayInfo]) -> dict[str, ArrayInfo]:
        """``infos`` with each file's SHA-256 recorded (the manifest's, checked by readers)."""
        return {name: info.model_copy(update={"sha256": file_sha256(self._partial / info.file)})
                for name, info in infos.items()}

    def close(self) -> None:
        """Release the maps and the lock without finishing (the partial bake stays resumable)."""
        for mm in self._maps.values():
            mm.flush()
        self._maps = {}
        if self._done_map is not None:
            self._done_map.flush()
            self._done = np.array(self._done_map)
            self._done_map = None
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        # A writer dropped without close() still releases its lock (as a dead process does).
        fd = getattr(self, "_lock_fd", None)
        if fd is not None:
            os.close(fd)
            self._lock_fd = None

