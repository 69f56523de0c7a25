"""Durable file-system helpers: atomic writes (file fsync + directory fsync) and directory locks.

Every file probegrid writes under its final name goes through :func:`atomic_write_text`,
:func:`atomic_write_json` or :func:`replace_durably` (images are written to a temporary sibling by
:mod:`probegrid.imageio`, then renamed with it), so a crash or power loss leaves either the old
file or the whole new one, never a half-written file that looks finished, and a failure leaves no
temporary file behind. :func:`directory_lock` gives one writer at a time per directory.
"""

from __future__ import annotations

import fcntl
import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from probegrid.errors import StoreError

__all__ = [
    "atomic_write_bytes",
    "atomic_write_json",
    "atomic_write_text",
    "directory_lock",
    "fsync_dir",
    "fsync_file",
    "lock_dir",
    "replace_durably",
]


def fsync_dir(path: str | os.PathLike[str]) -> None:
    """Flush a directory's entries (renames, new files) to disk."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_file(path: str | os.PathLike[str]) -> None:
    """Flush a file's data to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def replace_durably(tmp: str | os.PathLike[str], path: str | os.PathLike[str]) -> None:
    """Rename the (flushed) file ``tmp`` over ``path`` and flush the directory entry."""
    os.replace(tmp, path)
    fsync_dir(Path(path).parent)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the whole new one.

    The bytes go to a temporary sibling ``.NAME.tmp-PID``, flushed, renamed over ``path``, and
    the directory flushed; on any failure the temporary file is removed.
    """
    p = Path(path)
    tmp = p.with_name(f".{p.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        replace_durably(tmp, p)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """:func:`atomic_write_bytes` of ``text`` encoded as UTF-8."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike[str], data: Any) -> None:
    """:func:`atomic_write_text` of ``data`` as indented JSON (NaN and infinities refused)."""
    atomic_write_text(path, json.dumps(data, indent=2, allow_nan=False) + "\n")


def lock_dir(directory: str | os.PathLike[str], busy: str | None = None) -> int:
    """An exclusive, non-blocking ``flock`` on a directory; the returned fd holds it until closed.

    Raises :class:`~probegrid.errors.StoreError` with the message ``busy`` when another process
    holds it.
    """
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise StoreError(busy or f"another process is writing {directory}") from None
    return fd


@contextmanager
def directory_lock(directory: str | os.PathLike[str], *, busy: str | None = None
                   ) -> Iterator[None]:
    """Hold :func:`lock_dir`'s lock on ``directory`` for the block."""
    fd = lock_dir(directory, busy)
    try:
        yield
    finally:
        os.close(fd)
