"""Shared fixtures: the real test inputs in ``tests/data`` (see its README), and the test run's
private cache directory.

Markers (registered in ``pyproject.toml``): ``slow`` marks the few long physics and fuzzing
checks; the default run (``pytest -q``, the README's command) leaves them out and ``.ci/run``
runs them in a second invocation (``pytest -q -m slow``); ``pytest -m ""`` runs everything.
``browser`` marks tests that drive a real browser.

Expensive inputs shared by several test modules are fixtures scoped to the whole run here
(pytest's ``scope="session"``), so each is made once per run.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
REAL_DATA = REPO / "tests" / "data"
_CACHE: list[str] = []


def pytest_configure(config: pytest.Config) -> None:
    """A fresh cache directory (``PROBEGRID_CACHE_DIR``) for this test run and the CLI processes
    it starts: the DFG table a filter run caches is computed once per run, never read from the
    user's cache."""
    if not _CACHE and "PROBEGRID_CACHE_DIR" not in os.environ:
        _CACHE.append(tempfile.mkdtemp(prefix="probegrid-test-cache-"))
        os.environ["PROBEGRID_CACHE_DIR"] = _CACHE[0]


def pytest_unconfigure(config: pytest.Config) -> None:
    if _CACHE:
        os.environ.pop("PROBEGRID_CACHE_DIR", None)
        shutil.rmtree(_CACHE.pop(), ignore_errors=True)


@pytest.fixture(scope="session")
def real_data() -> Path:
    """``tests/data``: the real HDRs and glTF scenes (origins and licences in its README)."""
    if not REAL_DATA.is_dir():
        pytest.fail(f"real test data not found at {REAL_DATA}")
    return REAL_DATA


def _read_hdr(path: Path) -> np.ndarray:
    import OpenImageIO as oiio  # tests may read files directly; the library uses imageio.py

    buf = oiio.ImageBuf(str(path))
    if buf.has_error:
        raise RuntimeError(buf.geterror())
    return np.asarray(buf.get_pixels(oiio.FLOAT), dtype=np.float32)[..., :3]


@pytest.fixture(scope="session")
def venice_latlong(real_data: Path) -> np.ndarray:
    """Venice sunset, (512, 1024, 3) float32 lat-long, linear radiance."""
    return _read_hdr(real_data / "hdr" / "venice_sunset_1k.hdr")


@pytest.fixture(scope="session")
def studio_latlong(real_data: Path) -> np.ndarray:
    """Studio small 03, (512, 1024, 3) float32 lat-long, linear radiance."""
    return _read_hdr(real_data / "hdr" / "studio_small_03_1k.hdr")


@pytest.fixture(scope="session", autouse=True)
def _private_user_cache(tmp_path_factory: pytest.TempPathFactory) -> None:
    """The tests (and the CLI runs they start) use their own user cache, not ``~/.cache``."""
    import os

    os.environ["XDG_CACHE_HOME"] = str(tmp_path_factory.mktemp("xdg-cache"))


@pytest.fixture
def full_fs(tmp_path):
    """A 64 KiB tmpfs, filled: a full file system (mounting needs root; skipped otherwise)."""
    mnt = tmp_path / "full"
    mnt.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs",
                                            str(mnt)], capture_output=True).returncode:
        pytest.skip("mounting a small tmpfs needs root")
    try:
        with open(mnt / "fill", "wb") as f, pytest.raises(OSError):
            f.write(b"\0" * 70000)
            f.flush()
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=True)
