"""The compiled kernels: one signature each per bake (``probegrid._jit.frozen``), and the first
bake on a machine saying that it compiles them (``probegrid.bake.compiled``,
``BakeProgress.compiling``).

The slow test bakes the sample room in a subprocess with an empty numba cache (a machine's first
bake) and reads the cache numba wrote: every kernel holds one signature (numba's literal
specializations of a constant argument inside a kernel aside), so no worker process compiled a
second one; a second bake on that cache compiles nothing and says nothing of compiling.
"""

from __future__ import annotations

import io
import os
import pickle
import re
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest

from probegrid._jit import frozen
from probegrid.bake.kernels.grid import ReplayRecords
from probegrid.jobs.progress import COMPILING, BakeProgress

REPO = Path(__file__).resolve().parents[1]


def test_frozen_gives_one_numba_type_for_writable_and_read_only_inputs() -> None:
    a = np.arange(12, dtype=np.float32).reshape(4, 3)
    ro = a.copy()
    ro.flags.writeable = False
    strided = np.arange(24, dtype=np.float32).reshape(4, 6)[:, ::2]
    assert numba.typeof(a) != numba.typeof(ro)  # what would compile a kernel twice
    assert numba.typeof(frozen(a)) == numba.typeof(frozen(ro)) == numba.typeof(frozen(strided))
    np.testing.assert_array_equal(frozen(strided), strided)
    assert np.shares_memory(frozen(a), a) and not frozen(a).flags.writeable
    assert a.flags.writeable
    rec = ReplayRecords(*(ro if k % 2 else a for k in range(8)))
    out = frozen((rec, (a, 3), 1.5))
    assert type(out[0]) is ReplayRecords and out[1][1] == 3 and out[2] == 1.5
    assert numba.typeof(out[0]) == numba.typeof(frozen(ReplayRecords(*([ro] * 8))))


def test_compiling_progress_names_the_phase() -> None:
    now = [0.0]
    stream = io.StringIO()
    bar = BakeProgress(stream=stream, terminal=False, clock=lambda: now[0])
    for t, done in ((0.0, 0), (4.0, 3), (12.0, 10)):
        now[0] = t
        bar.compiling(done, 36)
    now[0] = 50.0
    bar.compiling(30, 36, finished=True)
    lines = stream.getvalue().splitlines()
    assert lines == [f"bake: {COMPILING}: 0/36 kernels, 0 s so far",
                     f"bake: {COMPILING}: 10/36 kernels, 12 s so far",
                     f"bake: {COMPILING}: 36/36 kernels, done in 50 s"]
    assert "first run only" in COMPILING


def test_waiting_for_the_workers_shows_the_kernels_cached_so_far(monkeypatch) -> None:
    from probegrid.bake import compiled
    from probegrid.jobs import bake as job

    kernels = compiled.bake_kernels()
    names = [f"{d.py_func.__module__}.{d.py_func.__name__}" for d in kernels]
    assert len(names) > 20 and len(set(names)) == len(names)
    cached: set[int] = set()

    class Workers:  # their fork server compiles two kernels a second
        calls = 0

        def wait_started(self, timeout: float) -> bool:
            self.calls += 1
            cached.update(id(d) for d in kernels[:2 * self.calls])
            return len(cached) == len(kernels)

    monkeypatch.setattr(compiled, "is_cached", lambda d: id(d) in cached)
    stream = io.StringIO()
    bar = BakeProgress(stream=stream, terminal=False, clock=lambda: 0.0)
    job._wait_compiling(Workers(), names, bar)
    out = stream.getvalue().splitlines()
    assert out[0] == f"bake: {COMPILING}: 2/{len(names)} kernels, 0 s so far"
    assert out[-1] == f"bake: {COMPILING}: {len(names)}/{len(names)} kernels, done in 0 s"


def _signatures(cache: Path) -> dict[str, list[str]]:
    """Each numba cache index under ``cache``: its kernel and the signatures it holds, numba's
    literal specializations (``Literal[int](3)``) read as their type."""
    out: dict[str, list[str]] = {}
    for index in cache.rglob("*.nbi"):
        with index.open("rb") as fh:
            pickle.load(fh)  # numba's version
            _, overloads = pickle.loads(fh.read())
        sigs = {re.sub(r"Literal\[int\]\(-?\d+\)", "int64", str(key[0])) for key in overloads}
        out[index.name.split("-")[0]] = sorted(sigs)
    return out


@pytest.mark.slow
def test_first_bake_compiles_each_kernel_once_and_says_so(tmp_path) -> None:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"),
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    cmd = [sys.executable, "-c", "import sys; from probegrid.cli import main; "
           "sys.exit(main())", "bake", str(REPO / "data" / "sample_room.glb"),
           "--grid", "2x2x2", "--face-size", "8", "--samples", "1", "--bounces", "2",
           "--workers", "2"]
    first = subprocess.run([*cmd, "--out", str(tmp_path / "a.probes")], env=env,
                           capture_output=True, text=True, timeout=1800, check=False)
    assert first.returncode == 0, first.stderr
    lines = [x for x in first.stderr.splitlines() if COMPILING in x]
    assert lines and re.search(r": (\d+)/\1 kernels, done in", lines[-1]), first.stderr
    sigs = _signatures(tmp_path / "numba")
    from probegrid.bake.compiled import bake_kernels

    assert len(sigs) >= len(bake_kernels())
    twice = {k: v for k, v in sigs.items() if len(v) > 1}
    assert not twice, twice
    second = subprocess.run([*cmd, "--out", str(tmp_path / "b.probes")], env=env,
                            capture_output=True, text=True, timeout=600, check=False)
    assert second.returncode == 0, second.stderr
    assert COMPILING not in second.stderr
    assert _signatures(tmp_path / "numba") == sigs  # nothing compiled
