"""Benchmark of :func:`probegrid.core.sh.project_cube` against the physical limit and the 10 ms target.

Times the SH projection of a ``(6, n, n, 3)`` float32 cube (default n = 128) in-process: the
median of many runs after warm-up (the first, cold call also builds the cached local basis and is
reported separately). Next to it, in the same run, the time of one pass that just reads the
cube (``faces.sum()``), the floor any projection must pay, and the ratio of the two. It also
states the precision of the float64 projection (and of a float32-matmul alternative, for the
record) against an extended-precision (``np.longdouble``) evaluation of the same sum.

Usage::

    .venv/bin/python benchmarks/bench_sh.py [--size 128] [--runs 300]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from probegrid.core import cubemap as cm
from probegrid.core import sh
from probegrid.core.sh import projection

TARGET_MS = 10.0


def median_ms(fn, runs: int, warmup: int = 5) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``runs`` calls, after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    times = np.empty(runs)
    for k in range(runs):
        t0 = time.perf_counter()
        fn()
        times[k] = time.perf_counter() - t0
    return float(np.median(times) * 1e3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=128, help="cube face size n")
    parser.add_argument("--runs", type=int, default=300, help="timed runs per measurement")
    args = parser.parse_args()
    n = args.size

    rng = np.random.default_rng(0)
    # Environment-like data: positive, heavy-tailed (a few very bright texels).
    faces = (rng.lognormal(mean=0.0, sigma=2.0, size=(6, n, n, 3))).astype(np.float32)

    projection._cached_local_weighted_basis.cache_clear()
    t0 = time.perf_counter()
    coeffs = sh.project_cube(faces)
    cold_ms = (time.perf_counter() - t0) * 1e3

    project_ms = median_ms(lambda: sh.project_cube(faces), args.runs)
    read_ms = median_ms(lambda: faces.sum(), args.runs)

    # Precision against an extended-precision evaluation of the same weighted sum.
    if n <= 256:  # the (9, 6 n^2) direct basis in long double stays small
        dirs = cm.texel_directions(n).reshape(-1, 3)
        wb = (sh.sh_basis(dirs) * cm.texel_solid_angles(n).reshape(-1, 1)).T
        flat = faces.reshape(-1, 3)
        ref = wb.astype(np.longdouble) @ flat.astype(np.longdouble)
        scale = np.abs(ref[0]).astype(np.float64)  # L_00 per channel
        err64 = np.max(np.abs((coeffs - ref).astype(np.float64)) / scale)
        c32 = (wb.astype(np.float32) @ flat).astype(np.float64)
        err32 = np.max(np.abs((c32 - ref).astype(np.float64)) / scale)
    else:
        err64 = err32 = float("nan")

    print(f"project_cube on 6 x {n}^2 x 3 float32 (median of {args.runs} runs after warm-up)")
    print(
        f"  project_cube            {project_ms:8.3f} ms   (target <= {TARGET_MS:.0f} ms: "
        f"{'met' if project_ms <= TARGET_MS else 'MISSED'}, {TARGET_MS / project_ms:.1f}x margin)"
    )
    print(f"  faces.sum() (one read)  {read_ms:8.3f} ms   (physical limit: read the cube once)")
    print(f"  ratio project / read    {project_ms / read_ms:8.1f} x")
    print(
        f"  cold first call         {cold_ms:8.3f} ms   (builds and caches the (9, n^2) local basis)"
    )
    print(f"  max |error| / L00, float64 path (used)      {err64:.1e}")
    print(
        f"  max |error| / L00, float32 matmul of the direct basis (alternative, not used) {err32:.1e}"
    )


if __name__ == "__main__":
    main()
