"""Where a block's records are kept between passes: files, this process's memory, or both.

Records live in a directory per block of probes (the fixed batch partition), one ``.npy`` per
named array (:data:`probegrid.bake.records.schema.RecordArrays`, the stored form), written
atomically by the worker that traced them (the ``complete`` mark last); the worker also keeps
the blocks it used last in memory (:data:`RECORDS_MEMORY`), and any other block is
memory-mapped from its files, so a pass over a block reads only that block and a worker's
memory is bounded by its batch. A bake's only worker process (no other process will ask for
its blocks) keeps them in memory alone and writes a block only when the bound pushes it out
(``save_records(files=False)``). A block whose files are missing (a Dask worker on another
machine, a file deleted) is traced again: the records are deterministic, so the result is the
same bits.

The functions here know names and arrays only, not what the records mean.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "RECORDS_MEMORY",
    "load_records",
    "records_file",
    "remove_records",
    "resolve_directory",
    "save_records",
]


def records_file(directory: str | Path, block: int) -> Path:
    """The record directory of the block starting at probe ``block``."""
    return Path(directory) / f"records_{block:09d}"


def resolve_directory(directory: str) -> Path:
    """A records directory: an absolute path as is; a bare name under this machine's
    temporary directory (for workers that do not share the bake's files)."""
    p = Path(directory)
    return p if p.is_absolute() else Path(tempfile.gettempdir()) / directory


def _atomic_npy(path: Path, array: NDArray[Any]) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".npy")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.save(fh, np.asarray(array), allow_pickle=False)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


#: Bytes of records a worker process keeps in memory between passes (the blocks it used last;
#: the files stay the reference: a block it does not hold is read back).
RECORDS_MEMORY = 256 << 20

_held: OrderedDict[tuple[str, str], tuple[dict[str, NDArray[Any]], int]] = OrderedDict()
_held_bytes = [0]
_held_lock = threading.Lock()
#: Blocks this process holds without files (``save_records(files=False)``): directory -> token.
_memory_only: dict[str, str] = {}


def _mark(path: Path) -> tuple[str, str] | None:
    """A block's identity: its directory and the random token its ``complete`` mark holds (a
    later bake of the same store writes a new token, so what a process holds of an earlier
    one is never taken for it)."""
    try:
        return (str(path), (path / "complete").read_text())
    except OSError:
        return None


def _nbytes(records: dict[str, NDArray[Any]]) -> int:
    return sum(np.asarray(v).nbytes for v in records.values())


def _held_get(key: tuple[str, str]) -> dict[str, NDArray[Any]] | None:
    with _held_lock:
        item = _held.get(key)
        if item is None:
            return None
        _held.move_to_end(key)
        return item[0]


def _write_block(path: Path, records: dict[str, NDArray[Any]], token: str | None) -> None:
    """One ``.npy`` per array into the directory ``path``, each atomically, then the
    ``complete`` mark (``token``, a new one when None) last: a killed worker leaves no half
    block. Arrays already there when the mark is (the same bits) are not written again."""
    path.mkdir(parents=True, exist_ok=True)
    done = (path / "complete").is_file()
    for k, v in records.items():
        f = path / f"{k}.npy"
        if not (done and f.is_file()):
            _atomic_npy(f, np.asarray(v))
    if not done:
        (path / "complete").write_text(token or os.urandom(8).hex())


def _hold(key: tuple[str, str], records: dict[str, NDArray[Any]]) -> None:
    """Keep ``records`` (its size as it is now) as the most recently used block. A block held
    without files that has to go (the least recently used beyond :data:`RECORDS_MEMORY`) is
    written to its directory first (spilled): what a pass reads is always somewhere. (Unless the
    directory's bake directory is gone: a later pass would trace it again.)"""
    with _held_lock:
        old = _held.pop(key, None)
        if old is not None:
            _held_bytes[0] -= old[1]
        size = _nbytes(records)
        if size > RECORDS_MEMORY:  # larger than all it may hold: not held
            _spill(key, records)
            return
        _held[key] = (records, size)
        _held_bytes[0] += size
        while _held_bytes[0] > RECORDS_MEMORY and _held:  # the least recently used go first
            gone, (old_records, nbytes) = _held.popitem(last=False)
            _held_bytes[0] -= nbytes
            _spill(gone, old_records)


def _spill(key: tuple[str, str], records: dict[str, NDArray[Any]]) -> None:
    """A block leaving this process's memory (``_held_lock`` held): if it was held without
    files, written to its directory now (unless its bake's directory is gone)."""
    where, token = key
    if _memory_only.get(where) != token:
        return  # (its files are the reference)
    del _memory_only[where]
    if Path(where).parent.parent.is_dir():
        shutil.rmtree(where, ignore_errors=True)  # (files of an earlier bake)
        _write_block(Path(where), records, token)


def _drop(path: Path) -> None:
    with _held_lock:
        _memory_only.pop(str(path), None)
        for key in [k for k in _held if k[0] == str(path)]:
            _held_bytes[0] -= _held.pop(key)[1]


def save_records(path: Path, records: dict[str, NDArray[Any]], *,
                 drop: tuple[str, ...] = (), files: bool = True) -> None:
    """Keep a block's ``records`` for the later passes, and the arrays of ``drop`` no more
    (what no later pass reads).

    With ``files`` the arrays go into the directory ``path`` (:func:`_write_block`: atomic, the
    ``complete`` mark last), which any process of the machine can read, and this process keeps
    them in memory too (:data:`RECORDS_MEMORY`). Without, when no other process will ask for
    the block (a bake's only worker process), this process keeps them in memory alone and
    writes them only if they have to leave it (:func:`_hold`). Arrays added to a block (its
    probe weights, say) go where the block is."""
    sp = str(path)
    with _held_lock:
        token = _memory_only.get(sp)
    if token is None and not files:  # a new block in memory alone
        shutil.rmtree(path, ignore_errors=True)  # (files of an earlier bake)
        token = os.urandom(8).hex()
        with _held_lock:
            _memory_only[sp] = token
        _hold((sp, token), records)
        return
    if token is not None:  # a block held without files: added to and dropped from in memory
        key = (sp, token)
        held = _held_get(key)
        if held is not None:
            if held is not records:
                held.update(records)
            for k in drop:
                held.pop(k, None)
            _hold(key, held)
            return
    done = (path / "complete").is_file()
    _write_block(path, records, None)
    for k in drop:
        (path / f"{k}.npy").unlink(missing_ok=True)
    key = _mark(path)
    if key is None:
        return
    if not done:  # a new block
        _hold(key, records)
        return
    held = _held_get(key)
    if held is not None:  # arrays added to a block this process holds
        if held is not records:
            held.update(records)
        for k in drop:
            held.pop(k, None)
        _hold(key, held)


def load_records(path: Path) -> dict[str, NDArray[Any]] | None:
    """The records in the directory ``path`` (one block: memory bounded by the batch), from
    this process's memory when it holds them, else memory-mapped from their files; None when
    there is no complete record."""
    sp = str(path)
    with _held_lock:  # (a block held without files is spilled under this lock)
        token = _memory_only.get(sp)
        item = None if token is None else _held.get((sp, token))
        if item is not None:
            _held.move_to_end((sp, token))
            return item[0]
    key = _mark(path)
    if key is None:
        return None
    held = _held_get(key)
    if held is not None:
        return held
    try:  # memory-mapped: the page cache holds them, no copy (nothing to hold here)
        out = {f.stem: np.load(f, allow_pickle=False, mmap_mode="r").view(np.ndarray)
               for f in path.glob("*.npy") if not f.name.startswith(".")}
    except (OSError, ValueError):
        return None
    return out


def remove_records(path: Path) -> None:
    """Delete a block's records (its last use)."""
    _drop(path)
    shutil.rmtree(path, ignore_errors=True)
