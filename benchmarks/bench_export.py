"""Benchmark of ``probegrid export --target threejs|bevy|ktx2`` against merely reading the store.

Writes a 16x8x16 store shaped like a default bake (SH, 8^2 diffuse cubes, a 32^2 GGX chain of 6
levels; random positive light, a few invalid probes) into a temporary directory, or uses
``--store PATH``, then times, in one process, each target's whole export (read, fill, pack,
encode, write files and manifest) next to the floor any export pays: reading the arrays that
target needs from the memory-mapped store into memory (page cache warm for both, median of
``--runs``). Prints both times and their ratio per target, and the file sizes.

Then ``probegrid filter HDR --out DIR --format ktx2`` against the same command with ``--format
exr`` (the default cube size, ``data/sample_sky.hdr`` unless ``--hdr``): each the whole command in
a fresh process, interleaved, median of ``--filter-runs``; printed: wall time, the write stage
from each run's manifest (``timings_s.write``: encoding and writing the maps, the part the
format changes) and the ratios ktx2 / exr (target: at most 1.10 for the whole run).

Usage::

    .venv/bin/python benchmarks/bench_export.py [--store room.probes] [--runs 5] [--zstd]
                                                [--filter-runs 3] [--hdr sky.hdr] [--no-filter]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from probegrid.core.conventions import conventions
from probegrid.core.cubemap import mip_sizes
from probegrid.core.grid import GridSpec
from probegrid.jobs.engine_export import export_grid
from probegrid.store import ArraySpec, StoreWriter, open_store

NEEDS = {"threejs": ("sh",), "bevy": ("diffuse",), "ktx2": ("sh", "diffuse", "specular_*")}


def make_store(path: Path) -> Path:
    grid = GridSpec.from_counts((-4.0, 0.0, -4.0), (4.0, 3.5, 4.0), (16, 8, 16))
    rng = np.random.default_rng(0)
    shapes = {"sh": (9, 3), "diffuse": (6, 8, 8, 3)}
    for k, n in enumerate(mip_sizes(32)):
        shapes[f"specular_{k}"] = (6, n, n, 3)
    specs = {name: ArraySpec(shape=s, dtype="<f4", description=name) for name, s in shapes.items()}
    specs["valid"] = ArraySpec(shape=(), dtype="|b1", description="valid")
    w = StoreWriter.create(path, arrays=specs, grid=grid, conventions=conventions(),
                           scene_hash="bench", bake={"synthetic": True})
    P = grid.n_probes
    for start in range(0, P, 256):
        idx = np.arange(start, min(P, start + 256))
        vals = {name: rng.lognormal(0.0, 1.0, size=(len(idx),) + s).astype(np.float32)
                for name, s in shapes.items()}
        vals["sh"][:, 1:] -= 1.0  # signed higher bands
        vals["valid"] = rng.random(len(idx)) > 0.02
        w.write(idx, vals)
    w.finish().close()
    return path


def median_s(fn, runs: int) -> float:
    fn()  # warm-up: page cache, imports, lazily built tables
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


REPO = Path(__file__).resolve().parents[1]


def bench_filter_formats(hdr: Path, tmp: Path, runs: int) -> None:
    """``filter --format ktx2`` against ``--format exr``: whole-process wall time and the write
    stage (module docstring)."""
    wall: dict[str, list[float]] = {"exr": [], "ktx2": []}
    write: dict[str, list[float]] = {"exr": [], "ktx2": []}
    for _ in range(runs):
        for fmt in ("exr", "ktx2"):  # interleaved: the machine's load hits both alike
            out = tmp / f"filter_{fmt}"
            shutil.rmtree(out, ignore_errors=True)
            t = time.perf_counter()
            subprocess.run([sys.executable, "-m", "probegrid.cli", "filter", str(hdr), "--out",
                            str(out), "--format", fmt], check=True, capture_output=True)
            wall[fmt].append(time.perf_counter() - t)
            manifest = json.loads((out / "manifest.json").read_text())
            write[fmt].append(manifest["timings_s"]["write"])
    size = manifest["input"]["cube_size"]
    print(f"\nprobegrid filter {hdr.name} (cube {size}^2, the default) --format exr | ktx2, "
          f"median of {runs} interleaved runs")
    print(f"{'format':<7} {'wall s':>8} {'write stage s':>14}")
    med = {f: (float(np.median(wall[f])), float(np.median(write[f]))) for f in wall}
    for fmt, (w, st) in med.items():
        print(f"{fmt:<7} {w:8.2f} {st:14.3f}")
    ratio = med["ktx2"][0] / med["exr"][0]
    print(f"ratio ktx2 / exr: whole run {ratio:.3f} (target <= 1.10: "
          f"{'MET' if ratio <= 1.10 else 'NOT MET'}), write stage "
          f"{med['ktx2'][1] / med['exr'][1]:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", type=Path, help="an existing store (default: synthetic)")
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--zstd", action="store_true", help="Zstandard-supercompressed KTX2")
    parser.add_argument("--filter-runs", type=int, default=3)
    parser.add_argument("--hdr", type=Path, default=REPO / "data" / "sample_sky.hdr",
                        help="the environment of the filter comparison")
    parser.add_argument("--no-filter", action="store_true",
                        help="leave out the filter --format ktx2 / exr comparison")
    args = parser.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_export_"))
    try:
        store_path = args.store or make_store(tmp / "bench.probes")
        store = open_store(store_path)
        print(f"store {store_path}: grid {store.grid.label}, {store.n_probes} probes, arrays "
              + ", ".join(f"{n} {tuple(store.manifest.arrays[n].shape[1:])}"
                          for n in store.names))
        print(f"{'target':<8} {'export ms':>10} {'read ms':>9} {'ratio':>7}  files")
        for target, needs in NEEDS.items():
            names = [n for n in store.names
                     if any(n == w or (w.endswith("*") and n.startswith(w[:-1])) for w in needs)]

            def read(names=names) -> None:
                for n in names:
                    np.array(store[n], dtype=np.float32)

            out = tmp / f"out_{target}"

            def export(target=target, out=out) -> None:
                export_grid(store_path, out, target=target, zstd=args.zstd)

            t_export = median_s(export, args.runs)
            t_read = median_s(read, args.runs)
            sizes = ", ".join(f"{p.name} {p.stat().st_size / 2**20:.1f} MiB"
                              for p in sorted(out.glob("*.ktx2")))
            ratio = t_export / t_read
            print(f"{target:<8} {t_export * 1e3:10.1f} {t_read * 1e3:9.2f} {ratio:7.1f}  "
                  f"{sizes}")
        if not args.no_filter:
            bench_filter_formats(args.hdr, tmp, args.filter_runs)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
