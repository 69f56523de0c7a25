"""Durable file-system helpers: atomic writes (file fsync + directory fsync) and directory locks.

Every file probegrid writes under its final name goes through :func:`atomic_write_text`,
:func:`atomic_write_json` or :func:`replace_durably` (images are written to a temporary sibling by
:mod:`probegrid.imageio`, then renamed with it), so a crash or power loss leaves either the old
file or the whole new one, never a half-written file that looks finished, and a failure leaves no
temporary file behind. :func:`directory_lock` gives one writer at a time per directory.
:func:`user_cache_root` is where probegrid keeps per-user files (computed arrays, verified
hashes).

Deleting never follows a symbolic link (:func:`remove_path` unlinks the link, never empties its
target). :func:`publish_directory` puts a finished directory at a path so that the path holds
either the old or the new directory at every instant: on Linux with ``renameat2(RENAME_EXCHANGE)``
(the two entries swap in one step), elsewhere, or on a file system without it, with two renames
(old aside as ``NAME.replaced-PID``, new in) whose crash window :func:`recover_publish` closes at
the next start by putting the old directory back.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import fcntl
import json
import os
import shutil
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from probegrid.errors import StoreError

__all__ = [
    "CACHE_ENV",
    "atomic_write_bytes",
    "atomic_write_json",
    "atomic_write_text",
    "directory_lock",
    "fsync_dir",
    "fsync_file",
    "lock_dir",
    "publish_directory",
    "recover_publish",
    "remove_path",
    "replace_durably",
    "user_cache_root",
]

#: Environment variable that names the per-user cache's root directory instead (the test suite
#: gives each run a fresh one).
CACHE_ENV = "PROBEGRID_CACHE_DIR"


def user_cache_root() -> Path:
    """``$PROBEGRID_CACHE_DIR`` when set (absolute), else ``$XDG_CACHE_HOME/probegrid``
    (``~/.cache`` when unset or relative)."""
    own = os.environ.get(CACHE_ENV, "")
    if own and os.path.isabs(own):
        return Path(own)
    base = os.environ.get("XDG_CACHE_HOME", "")
    root = Path(base) if base and os.path.isabs(base) else Path.home() / ".cache"
    return root / "probegrid"


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


# ------------------------------------------------------------------ deleting and publishing
def remove_path(path: str | os.PathLike[str]) -> None:
    """Delete ``path`` without following a symbolic link: a link or a file is unlinked, a real
    directory removed with its contents (``shutil.rmtree``, which never descends into links);
    a missing path is no error."""
    p = Path(path)
    if p.is_symlink() or (p.exists() and not p.is_dir()):
        p.unlink(missing_ok=True)
    elif p.is_dir():
        shutil.rmtree(p)


_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def _renameat2_exchange(a: Path, b: Path) -> bool:
    """Swap the entries ``a`` and ``b`` in one step; False where the system or the file
    system offers no ``renameat2(RENAME_EXCHANGE)``."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _aside(final: Path) -> Path:
    return final.with_name(f"{final.name}.replaced-{os.getpid()}")


def publish_directory(staged: str | os.PathLike[str], final: str | os.PathLike[str],
                      *, exchange: bool = True) -> None:
    """Move the finished directory ``staged`` to ``final``, replacing what stands there, so that
    ``final`` holds the old entry or the new one at every instant; the old one (a directory, or
    a link, never followed) is deleted afterwards.

    ``staged`` is first renamed to ``NAME.replaced-PID`` beside ``final`` (so no half-published
    state looks like work to resume), then swapped with ``final`` by ``renameat2
    (RENAME_EXCHANGE)``, leaving the old entry under the aside name, which is deleted. Without
    the exchange (``exchange=False``, another system, or a file system that refuses it) the old
    entry is renamed aside and the new one in: a crash between the two renames leaves no entry
    at ``final``, which :func:`recover_publish` puts back at the next start.
    """
    staged, final = Path(staged), Path(final)
    if not final.exists() and not final.is_symlink():
        os.rename(staged, final)
        fsync_dir(final.parent)
        return
    aside = _aside(final)
    remove_path(aside)
    if exchange:
        os.rename(staged, aside)
        try:
            swapped = _renameat2_exchange(aside, final)
        except BaseException:
            os.rename(aside, staged)
            raise
        if not swapped:
            os.rename(aside, staged)
    else:
        swapped = False
    if not swapped:
        os.rename(final, aside)
        os.rename(staged, final)
    fsync_dir(final.parent)
    remove_path(aside)


def recover_publish(final: str | os.PathLike[str]) -> None:
    """Finish what an interrupted :func:`publish_directory` of ``final`` left: with no entry at
    ``final``, the newest ``NAME.replaced-PID`` (the old directory of a two-rename publish) goes
    back to ``final``; every other ``NAME.replaced-*`` is deleted. Call it holding the lock that
    makes its caller the only writer of ``final``."""
    final = Path(final)
    if not final.parent.is_dir():
        return
    left = sorted(final.parent.glob(f"{final.name}.replaced-*"),
                  key=lambda p: p.lstat().st_mtime)
    if left and not final.exists() and not final.is_symlink():
        os.rename(left.pop(), final)
        fsync_dir(final.parent)
    for p in left:
        remove_path(p)
