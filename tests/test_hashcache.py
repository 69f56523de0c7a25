"""The verified-digest cache shared by processes (probegrid.store.hashcache).

A store opened once is not hashed again by the next process while its files are unchanged; a
file rewritten in place (same size, even with its modification time put back) is hashed again
and refused; a cache file that others may write, or that is a link, is ignored; a cache entry
forged for a file does not make another version of it pass.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest
from probe_stores import GRID, linear_arrays, write_store

from probegrid.store import StoreError, hashcache, open_store


@pytest.fixture
def fresh(tmp_path, monkeypatch) -> Path:
    """A private cache root and an empty in-process memory (as in a new process)."""
    monkeypatch.setenv("PROBEGRID_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(hashcache, "_memory", set())
    monkeypatch.setattr(hashcache, "_loaded_from", [None])
    return tmp_path / "cache"


def _new_process(monkeypatch) -> None:
    monkeypatch.setattr(hashcache, "_memory", set())
    monkeypatch.setattr(hashcache, "_loaded_from", [None])


def _hash_count(monkeypatch) -> list[int]:
    counted: list[int] = []
    real_file, real_sha = hashlib.file_digest, hashlib.sha256

    def file_digest(f, name, *a, **k):
        counted.append(1)
        return real_file(f, name, *a, **k)

    def sha256(*a, **k):
        if a:  # hashing data (not an empty object to be fed)
            counted.append(1)
        return real_sha(*a, **k)

    monkeypatch.setattr(hashlib, "file_digest", file_digest)
    monkeypatch.setattr(hashlib, "sha256", sha256)
    return counted


def _store(tmp_path: Path) -> Path:
    path = tmp_path / "lin.probes"
    write_store(path, GRID, linear_arrays(GRID))
    return path


def test_a_second_process_does_not_hash_an_unchanged_store_again(fresh, tmp_path, monkeypatch):
    path = _store(tmp_path)
    _new_process(monkeypatch)  # forget what the writer hashed in this process: the file has it
    entries = json.loads(hashcache.cache_file().read_text())
    n_files = len([p for p in path.iterdir() if p.suffix in (".npy", ".glb")])
    assert len(entries) >= n_files
    counted = _hash_count(monkeypatch)
    open_store(path, load=True)
    assert counted.count(1) <= 1  # the manifest's own digest (a few KiB), no store file
    assert oct(hashcache.cache_file().stat().st_mode & 0o777) == "0o600"


def test_a_file_rewritten_in_place_is_hashed_again_and_refused(fresh, tmp_path, monkeypatch):
    path = _store(tmp_path)
    open_store(path)
    target = path / "sh.npy"
    st = target.stat()
    data = bytearray(target.read_bytes())
    data[-1] ^= 1  # same size, one bit changed, the modification time put back
    with open(target, "r+b") as f:
        f.write(data)
    os.utime(target, ns=(st.st_atime_ns, st.st_mtime_ns))
    _new_process(monkeypatch)
    with pytest.raises(StoreError, match="sh.npy does not have the SHA-256"):
        open_store(path)


def test_an_untrusted_cache_file_is_ignored(fresh, tmp_path, monkeypatch):
    path = _store(tmp_path)
    cache = hashcache.cache_file()
    for damage in ("group-writable", "link"):
        _new_process(monkeypatch)
        if damage == "group-writable":
            cache.chmod(0o666)
        else:
            real = cache.with_name("real.json")
            cache.rename(real)
            cache.symlink_to(real)
        counted = _hash_count(monkeypatch)
        open_store(path)
        assert counted.count(1) > 1, damage  # the store's files were hashed
        monkeypatch.undo()
        monkeypatch.setenv("PROBEGRID_CACHE_DIR", str(fresh))
        if damage == "link":
            cache.unlink()
            real.rename(cache)
        cache.chmod(0o600)


def test_a_forged_entry_only_covers_the_file_it_names(fresh, tmp_path, monkeypatch):
    """An entry claims the manifest's digest for the identity the file had; the file is then
    rewritten (its ctime changes, which utime cannot set back): the entry no longer applies."""
    path = _store(tmp_path)
    target = path / "valid.npy"
    manifest = json.loads((path / "manifest.json").read_text())
    expected = manifest["arrays"]["valid"]["sha256"]
    arr = np.load(target)
    np.save(target, ~arr)  # same size, other content
    st = target.stat()
    forged_for = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns - 1)
    hashcache.remember(forged_for, expected)  # as if the file had been verified a moment ago
    _new_process(monkeypatch)
    with pytest.raises(StoreError, match="valid.npy does not have the SHA-256"):
        open_store(path)
