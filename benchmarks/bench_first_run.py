"""A machine's first bake against a warm one: what compiling the kernels costs (not a test).

Runs ``probegrid bake data/sample_room.glb --grid 4x3x4 --face-size 16`` (the README's example)
``--repeat`` times in turns with an empty numba cache (``NUMBA_CACHE_DIR`` set to a new
directory: a fresh install) and with that cache filled (a later run), each a separate process,
and prints the wall times, their ratio against the target of 2x, the time the bake printed for
its compiling phase (``compiling kernels (first run only ...)``) and how many kernels it
compiled. Wall times on a shared machine vary with its load, so each run's CPU time is printed
too: the whole process tree's (the command, its fork server and worker processes; psutil,
sampled every 0.2 s, each process's last sample kept), which the machine's load changes far
less. The ratio is taken between runs made back to back.

Usage::

    .venv/bin/python benchmarks/bench_first_run.py [--repeat 2] [--workers N]
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PROBEGRID = str(Path(sys.executable).with_name("probegrid"))


def bake(out: Path, cache: Path, workers: int | None) -> tuple[float, float, str]:
    """Wall seconds, CPU seconds of the process tree and stderr of one bake with numba's cache
    in ``cache``."""
    import psutil

    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    cmd = [PROBEGRID, "bake", str(REPO / "data" / "sample_room.glb"), "--out", str(out),
           "--grid", "4x3x4", "--face-size", "16"]
    if workers:
        cmd += ["--workers", str(workers)]
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    root = psutil.Process(proc.pid)
    cpu: dict[int, float] = {}
    while proc.poll() is None:
        try:
            tree = [root, *root.children(recursive=True)]
        except psutil.NoSuchProcess:
            break
        for p in tree:
            try:
                c = p.cpu_times()
                cpu[p.pid] = c.user + c.system
            except psutil.NoSuchProcess:
                pass
        time.sleep(0.2)
    err = proc.stderr.read() if proc.stderr else ""
    if proc.wait() != 0:
        raise RuntimeError(err)
    return time.perf_counter() - t, sum(cpu.values()), err


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--workers", type=int, default=None)
    args = ap.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeat):
            cache = Path(tmp) / f"numba{r}"
            first, first_cpu, err = bake(Path(tmp) / f"a{r}.probes", cache, args.workers)
            warm, warm_cpu, err2 = bake(Path(tmp) / f"b{r}.probes", cache, args.workers)
            shutil.rmtree(cache, ignore_errors=True)
            done = re.findall(r"compiling kernels[^:]*: (\d+)/\d+ kernels, done in ([^\n]+)",
                              err)
            said = (f"compiling phase: {done[-1][0]} kernels, {done[-1][1]}" if done
                    else "no compiling phase printed")
            print(f"run {r + 1}: first {first:.1f} s, warm {warm:.1f} s, ratio "
                  f"{first / warm:.2f}x (target <= 2x: {'MET' if first <= 2 * warm else 'NOT MET'})"
                  f"; CPU of the process tree: first {first_cpu:.1f} s, warm {warm_cpu:.1f} s "
                  f"({first_cpu / warm_cpu:.2f}x); {said}; warm run printed compiling: "
                  f"{'compiling kernels' in err2}")
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
