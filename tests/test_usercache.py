"""The user cache (probegrid.usercache): same bits as the computation, never a failure."""

from __future__ import annotations

import os

import numpy as np
import pytest

from probegrid import usercache
from probegrid.core import dfg


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.delenv(usercache.CACHE_ENV, raising=False)  # (the test run sets its own)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    return tmp_path / "probegrid" / f"v{usercache.CACHE_VERSION}"


def test_the_cache_directory_variable_comes_first(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setenv(usercache.CACHE_ENV, str(tmp_path / "own"))
    assert usercache.cache_dir() == tmp_path / "own" / f"v{usercache.CACHE_VERSION}"
    monkeypatch.setenv(usercache.CACHE_ENV, "relative")  # ignored, like a relative XDG path
    assert usercache.cache_dir() == tmp_path / "xdg" / "probegrid" / f"v{usercache.CACHE_VERSION}"


def test_dfg_table_is_stored_once_and_read_back_bit_for_bit(cache):
    first = usercache.dfg_lut(16, samples=8)
    files = list(cache.glob("dfg_lut-*.npy"))
    assert len(files) == 1
    np.testing.assert_array_equal(first, dfg.dfg_lut(16, samples=8))
    stamp = files[0].stat().st_mtime_ns
    again = usercache.dfg_lut(16, samples=8)
    assert again.tobytes() == first.tobytes() and not again.flags.writeable
    assert files[0].stat().st_mtime_ns == stamp  # read, not rewritten
    usercache.dfg_lut(16, samples=12)  # another key, another file
    assert len(list(cache.glob("dfg_lut-*.npy"))) == 2


def test_damaged_or_wrong_files_are_recomputed(cache):
    ref = usercache.dfg_lut(8, samples=8)
    (path,) = cache.glob("dfg_lut-*.npy")
    path.write_bytes(b"not an array")
    np.testing.assert_array_equal(usercache.dfg_lut(8, samples=8), ref)
    np.save(path, np.full((8, 8, 2), np.nan, np.float32))
    np.testing.assert_array_equal(usercache.dfg_lut(8, samples=8), ref)
    np.save(path, np.zeros((4, 4, 2), np.float32))
    np.testing.assert_array_equal(usercache.dfg_lut(8, samples=8), ref)


def test_unwritable_cache_still_returns_the_table(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("x")  # the cache directory cannot be created under a file
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocker))
    np.testing.assert_array_equal(usercache.dfg_lut(8, samples=8), dfg.dfg_lut(8, samples=8))
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/dir")  # ignored, as the XDG spec says
    assert usercache.cache_dir().is_absolute()
    assert not os.path.exists("relative")


def test_probe_filter_matrix_is_stored_once_with_the_same_bits(cache):
    from probegrid.core import probefilter

    usercache.probe_filter_matrix.cache_clear()
    first = usercache.probe_filter_matrix(8, 4, 3)
    assert len(list(cache.glob("probe_filter-*.npy"))) == 1
    assert first.tobytes() == probefilter.filter_matrix(8, 4, 3)[0].tobytes()
    usercache.probe_filter_matrix.cache_clear()  # a new process reads the file
    again = usercache.probe_filter_matrix(8, 4, 3)
    assert again.tobytes() == first.tobytes() and not again.flags.writeable
    # the bake's filter through the cached matrix gives the bits of the computed one
    cube = np.random.default_rng(1).random((6, 8, 8, 6)).astype(np.float32)
    d0, c0 = probefilter.filter_cube(cube, 4, 3)
    d1, c1 = probefilter.filter_cube(cube, 4, 3, matrix=again)
    assert d0.tobytes() == d1.tobytes()
    assert all(a.tobytes() == b.tobytes() for a, b in zip(c0, c1, strict=True))
    with pytest.raises(ValueError, match="shape"):
        probefilter.filter_cube(cube, 4, 2, matrix=again)
