"""The SHA-256 digests of store files already verified, kept in this process and across processes.

Opening a store checks every file against the SHA-256 its manifest records, which reads the
whole store (about 0.1 s per 200 MiB from the page cache, far more from a cold disk). A file is
hashed once: its digest is remembered with the file's identity, ``(device, inode, size,
mtime_ns, ctime_ns)``, in this process (a set) and in a small file of the per-user cache
(``<user cache root>/verified-sha256.json``, :func:`probegrid._fs.user_cache_root`), so the next
command that opens the same unchanged store skips the hashing.

Why an identity is enough: writing a file changes its ``mtime`` and ``ctime``, and the ``ctime``
cannot be set back (``utime`` sets only the access and modification times; only a change of the
system clock or a raw write to the block device, both root's, could). A file replaced by another
has another inode or device. So a cached ``(identity, digest)`` stays true for as long as the
identity is the file's.

Tampering: whoever can write the cache file can make an altered store file pass, but only a
file they altered: the file's identity changes when it is written, so the entry must be made
for the altered file, which needs write access to the store too. The cache is read only when it
is a regular file (not a link) owned by this user and writable by no one else; its directory is
made private (``0700``) and the file ``0600``. A cache that is missing, unreadable, damaged or
not ours is ignored (everything is hashed); one that cannot be written is left as it is.
"""

from __future__ import annotations

import json
import os
import stat
import threading
from pathlib import Path
from typing import Final

from probegrid._fs import user_cache_root

__all__ = ["CACHE_FILE", "MAX_ENTRIES", "Identity", "cache_file", "is_verified", "remember"]

#: The cache file's name under the user cache root.
CACHE_FILE: Final = "verified-sha256.json"
#: Most digests kept on disk (the newest); about 100 bytes each.
MAX_ENTRIES: Final = 4096

#: ``(device, inode, size, mtime_ns, ctime_ns)`` of a file.
Identity = tuple[int, int, int, int, int]

_memory: set[str] = set()
_lock = threading.Lock()
_loaded_from: list[tuple[Path, Identity] | None] = [None]  # the disk file last read, by identity


def cache_file() -> Path:
    """Where the digests are kept across processes."""
    return user_cache_root() / CACHE_FILE


def _entry(identity: Identity, digest: str) -> str:
    return ":".join(str(v) for v in identity) + ":" + digest


def _read_disk(path: Path) -> list[str]:
    """The entries of the cache file when it can be trusted (see the module docstring)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0))
    except OSError:
        return []
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if (not stat.S_ISREG(st.st_mode) or st.st_uid != os.geteuid()
                or st.st_mode & 0o022 or st.st_size > 64 * MAX_ENTRIES * 4):
            return []
        identity = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
        if _loaded_from[0] == (path, identity):
            return []  # nothing new since it was last read
        try:
            entries = json.loads(f.read())
        except (OSError, ValueError):
            return []
    _loaded_from[0] = (path, identity)
    if not isinstance(entries, list):
        return []
    return [e for e in entries if isinstance(e, str) and len(e) < 256]


def is_verified(identity: Identity, digest: str) -> bool:
    """Whether the file of this identity was verified to have SHA-256 ``digest``, in this
    process or (read again from the cache file on a miss) another."""
    entry = _entry(identity, digest)
    if entry in _memory:
        return True
    disk = _read_disk(cache_file())
    with _lock:
        _memory.update(disk)
        return entry in _memory


def remember(identity: Identity, digest: str) -> None:
    """Record that the file of this identity has SHA-256 ``digest`` (hashed just now), in this
    process and in the cache file (merged with what other processes wrote, the newest
    :data:`MAX_ENTRIES` kept, replaced atomically)."""
    entry = _entry(identity, digest)
    with _lock:
        _memory.add(entry)
    path = cache_file()
    try:
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        _loaded_from[0] = None  # read it whole: other processes' entries are kept
        entries = [e for e in _read_disk(path) if e != entry] + [entry]
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}-{threading.get_ident()}")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o600)
        with os.fdopen(fd, "w") as f:
            json.dump(entries[-MAX_ENTRIES:], f, separators=(",", ":"))
        os.replace(tmp, path)
    except OSError:
        try:
            tmp.unlink()  # type: ignore[possibly-undefined]
        except (OSError, NameError):
            pass
