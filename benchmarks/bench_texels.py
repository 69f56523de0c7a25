"""A probe's own texels against a path tracer: block structure, noise and sharp sunlit patterns.

The sunlit hall of :func:`scenes.sunlit_building` (solid walls, two skylights crossed by
mullions, a 40 lux sun and a sky) is baked on the 4 x 3 x 3 grid whose probes stand at
:func:`scenes.building_interior_points` (``--probes`` keeps the first few for development; a
probe the bake relocates is rendered where it went), with ``store_incoming`` and ``direct=False``
(a camera ray of the reference never sees the sun itself, so neither does the probe: every other
light is as the bake computes it). Mitsuba 3 (:mod:`mitsuba_reference`, ``scalar_rgb``, path
tracer at max depth 64) renders the probes' incoming cubes twice with different seeds, ``spp / 2``
samples each; the reference is their mean, cached under ``--cache``.

Figures, per probe, then the mean and the worst probe:

* **incoming (4x4)**: the relative L1 error over the sphere of the incoming cube averaged over
  4 x 4 texel squares, ``sum dOmega |pg - ref| / sum dOmega ref`` (``bench_bake_accuracy``'s
  :func:`relative_l1`); **diffuse**: the same of the diffuse maps (``diffuse_exact`` of the
  reference at the store's diffuse size).
* **the reference's own noise** at its sample count: the two renders compared the same way,
  ``sum dOmega |a - b| / sum dOmega (a + b)`` (half their difference over their mean: the
  error of their mean for independent noise), printed beside each error.
* **block statistic** of the error field ``e = bake - reference``: in each face, the mean
  absolute difference of horizontally or vertically neighbouring texels of ``e`` across the
  edges between 8-texel blocks (columns or rows ``8k - 1 | 8k``) over the same across every
  other edge within the face (face seams left out), on the luminance ``(r + g + b) / 3``, over
  all faces of all probes; for the incoming cube and every specular level of at least 16
  texels (the reference filtered by the bake's own filter), with the reference's own ratio
  (``e = render A - render B``) beside. What the scene shows cancels in ``e``: 1.0 is no block
  structure. ``--noise-seed S`` bakes again with seed ``S``: the statistic of the difference
  of the two bakes is that of the bake's own noise alone (a mean correction per 8 x 8 block
  makes it a step function of the blocks).
* **time**: the bake's wall time (scene in memory to store), probes per second.

``--sun-only`` isolates how the texels sample the sun's sharp patterns (stripes of sunlight
between the mullions' shadows, finer than a texel): no sky, the bake's ``--bounces 0`` (the
sun's light at the surfaces the probes' rays hit, by shadow rays) against Mitsuba at max depth
2 (the same light, each pixel's footprint sampled ``spp`` times).

Run::

    .venv/bin/python benchmarks/bench_texels.py --face-size 16 --probes 6   # development
    .venv/bin/python benchmarks/bench_texels.py --face-size 32              # the 36 probes
    .venv/bin/python benchmarks/bench_texels.py --samples 4                 # any BakeSettings
    .venv/bin/python benchmarks/bench_texels.py --sun-only --face-size 32   # the sun's patterns
    PYTHONPATH=OTHER_CHECKOUT .venv/bin/python benchmarks/bench_texels.py   # another bake
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

BLOCK = 8


def block_statistic(fields: NDArray[Any], block: int = BLOCK) -> float:
    """The mean absolute difference of neighbouring texels within a face across the edges
    between ``block``-texel blocks (columns or rows ``block k - 1 | block k``) over the same
    across every other edge within the faces (face seams left out), of fields
    ``(P, 6, n, n, 3)`` on the luminance ``(r + g + b) / 3``; nan for faces smaller than
    ``2 block``. Of an error field (the bake minus the reference; the reference's own: one
    render minus the other) what the scene shows cancels: 1 is no block structure."""
    y = np.asarray(fields, np.float64).mean(axis=-1)  # (P, 6, n, n)
    n = y.shape[-1]
    if n < 2 * block:
        return float("nan")
    dx = np.abs(np.diff(y, axis=-1))  # the edge between col c and c + 1: index c
    dy = np.abs(np.diff(y, axis=-2))
    edge = (np.arange(n - 1) + 1) % block == 0

    def jumps(sel: NDArray[np.bool_]) -> float:
        return float(np.concatenate([dx[..., sel].ravel(), dy[..., sel, :].ravel()]).mean())

    return jumps(edge) / max(jumps(~edge), 1e-300)


def average4(cubes: NDArray[Any]) -> NDArray[np.float64]:
    """Cubes averaged over 4 x 4 texel squares (the face size divided by 4)."""
    c = np.asarray(cubes, np.float64)
    p, f, n, _, ch = c.shape
    return c.reshape(p, f, n // 4, 4, n // 4, 4, ch).mean(axis=(3, 5))


def _bake(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    """Bake the hall's grid with this checkout's probegrid; the store's arrays and the time."""
    from scenes import building_interior_points, sunlit_building

    from probegrid.bake import BakeSettings, bake
    from probegrid.bake.executors import make_executor
    from probegrid.core.grid import GridSpec
    from probegrid.store import open_store

    scene, env = sunlit_building(sky=0.0 if args.sun_only else 1.0)
    pts = building_interior_points()
    grid = GridSpec.from_counts(pts.min(axis=0), pts.max(axis=0), (4, 3, 3))
    # the same 36 points (the grid's order: z fastest)
    assert np.allclose(np.sort(grid.positions(), axis=0), np.sort(pts, axis=0))
    extra = json.loads(args.settings) if args.settings else {}
    if args.samples is not None:
        extra["samples"] = args.samples
    if args.seed is not None:
        extra["seed"] = args.seed
    if args.sun_only:
        extra["bounces"] = 0
    settings = BakeSettings(face_size=args.face_size, store_incoming=True, direct=False,
                            **extra)
    out = work / "hall.probes"
    with make_executor(workers=args.workers, preload=("probegrid.bake.preload",)) as ex:
        ex.start()
        t0 = time.perf_counter()
        report = bake(scene, grid, out, settings=settings, environment=env, executor=ex,
                      overwrite=True)
        seconds = time.perf_counter() - t0
    store = open_store(out)
    levels = settings.levels()
    return {"seconds": seconds, "rays": int(report.rays), "settings": settings,
            "positions": np.asarray(store["positions"]), "valid": np.asarray(store["valid"]),
            "incoming": np.asarray(store["incoming"], np.float32),
            "diffuse": np.asarray(store["diffuse"], np.float32),
            "specular": [np.asarray(store[f"specular_{k}"], np.float32) for k in range(levels)],
            "bounces": report.quality.get("bounces"),
            "cache_seconds": report.quality.get("stage_seconds", {}).get("surface cache"),
            "cache": report.quality.get("surface_cache", {})}


def _reference(args: argparse.Namespace, positions: NDArray[np.float64], n: int
               ) -> tuple[NDArray[np.float32], NDArray[np.float32], float]:
    """(render A, render B, seconds) at the positions, cached."""
    import mitsuba_reference as mr
    from bench_bake_accuracy import cached_reference
    from scenes import sunlit_building

    scene, env = sunlit_building(sky=0.0 if args.sun_only else 1.0)
    with mr.MitsubaReference(scene, env) as ref:
        return cached_reference(args.cache, ref, scene, env, positions, face_size=n,
                                spp=args.ref_spp, max_depth=2 if args.sun_only else 64)


def _stats(e: NDArray[np.float64]) -> str:
    return f"{100 * e.mean():6.2f} % mean, {100 * e.max():6.2f} % worst"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--face-size", type=int, default=16)
    p.add_argument("--probes", type=int, default=36, help="the first N of the 36 probes")
    p.add_argument("--samples", type=int, default=None, help="rays per texel (default: the "
                   "checkout's)")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--noise-seed", type=int, default=None,
                   help="bake again with this seed: the bake's own noise and its block "
                        "statistic (the difference of the two bakes)")
    p.add_argument("--settings", default="", help="more BakeSettings as JSON")
    p.add_argument("--ref-spp", type=int, default=512, help="reference samples per pixel")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--cache", type=Path, default=Path("/tmp/texels-cache"))
    p.add_argument("--sun-only", action="store_true",
                   help="the sun's patterns alone: no sky, the sun's light at the first hit "
                        "(the bake's --bounces 0 against Mitsuba at max depth 2)")
    p.add_argument("--reference-only", action="store_true",
                   help="render (cache) the reference at the grid's positions and stop")
    p.add_argument("--save", type=Path, default=None, help="write the figures as JSON")
    p.add_argument("--dump", type=Path, default=None, help="write the cubes as .npz")
    args = p.parse_args(argv)
    if args.face_size % 4 or args.face_size < 8:
        p.error("--face-size must be a multiple of 4, at least 8")
    if not 1 <= args.probes <= 36:
        p.error("--probes must be 1..36")
    from bench_bake_accuracy import half_difference, relative_l1

    from probegrid.core.diffuse import diffuse_exact
    from probegrid.core.probefilter import filter_cube

    n = args.face_size
    with tempfile.TemporaryDirectory(prefix="pg-texels-") as tmp:
        baked = _bake(args, Path(tmp))
    sel = np.flatnonzero(baked["valid"])[:args.probes]
    pos = baked["positions"][sel]
    a, b, ref_seconds = _reference(args, pos, n)
    if args.reference_only:
        print(f"reference cached ({ref_seconds:.0f} s)")
        return
    st = baked["settings"]
    print(f"sunlit hall{' (the sun at the first hit alone)' if args.sun_only else ''}, "
          f"{len(sel)} probes, faces {n}^2, samples {st.samples}, gather "
          f"{st.gather_samples} x {st.gather_levels()}, light samples {st.light_samples}; "
          f"bake {baked['seconds']:.1f} s ({len(baked['valid']) / baked['seconds']:.2f} "
          f"probes/s, {baked['rays'] / 1e6:.1f} M rays), bounces {baked['bounces']}")
    if baked["cache_seconds"] is not None:  # (older checkouts state no surface cache)
        print(f"surface cache: {baked['cache'].get('vertices', '?')} vertices, spacing "
              f"{baked['cache'].get('spacing', float('nan')):.3f}, "
              f"{baked['cache_seconds']:.1f} s of the bake")
    print(f"reference: Mitsuba path, depth {2 if args.sun_only else 64}, {args.ref_spp} spp (2 x {args.ref_spp // 2}, "
          f"seeds 1 and 7000001), {ref_seconds:.0f} s when rendered")
    ref = 0.5 * (a.astype(np.float64) + b)
    inc = baked["incoming"][sel].astype(np.float64)
    err4 = relative_l1(average4(inc), average4(ref))
    noise4 = half_difference(average4(a), average4(b))
    d = baked["diffuse"].shape[2]
    ref_d = np.stack([diffuse_exact(c, d) for c in ref.astype(np.float32)])
    err_d = relative_l1(baked["diffuse"][sel], ref_d)
    noise_d = half_difference(np.stack([diffuse_exact(c, d) for c in a]),
                              np.stack([diffuse_exact(c, d) for c in b]))
    print(f"incoming (4x4): {_stats(err4)}   reference noise {_stats(noise4)}   "
          f"ratio {err4.mean() / noise4.mean():.2f} (mean)")
    print(f"diffuse:        {_stats(err_d)}   reference noise {_stats(noise_d)}")
    rows: dict[str, Any] = {"incoming4": err4.tolist(), "noise4": noise4.tolist(),
                            "diffuse": err_d.tolist(), "noise_diffuse": noise_d.tolist(),
                            "seconds": baked["seconds"], "probes": int(len(baked["valid"]))}
    r, q = block_statistic(inc - ref), block_statistic(a.astype(np.float64) - b)
    print("block statistic (error field's jumps across 8-texel block edges over those across "
          "other edges; 1 = none):")
    print(f"  incoming:         {r:.3f}   (reference, render A - render B: {q:.3f})")
    rows["block_incoming"] = [r, q]
    levels = len(baked["specular"])
    chains = [[filter_cube(c.astype(np.float32), d, levels)[1] for c in x] for x in (ref, a, b)]
    for k in range(levels):
        if (n >> k) < 2 * BLOCK:
            break
        fr, fa, fb = (np.stack([c[k] for c in ch]).astype(np.float64) for ch in chains)
        spec = baked["specular"][k][sel].astype(np.float64)
        r, q = block_statistic(spec - fr), block_statistic(fa - fb)
        e = relative_l1(average4(spec), average4(fr))
        print(f"  specular level {k}: {r:.3f}   (reference {q:.3f});  error (4x4) {_stats(e)}")
        rows[f"block_specular_{k}"] = [r, q]
        rows[f"specular_{k}"] = e.tolist()
    if args.noise_seed is not None:
        # the bake's own noise: the same bake with another seed; its block structure alone
        args.seed = args.noise_seed
        with tempfile.TemporaryDirectory(prefix="pg-texels-") as tmp:
            other = _bake(args, Path(tmp))
        diff = inc - other["incoming"][sel].astype(np.float64)
        noise = half_difference(average4(inc), average4(other["incoming"][sel]))
        print(f"seed {baked['settings'].seed} against seed {args.noise_seed}: incoming (4x4) "
              f"{_stats(noise)} (half the difference over the mean); block statistic of the "
              f"difference {block_statistic(diff):.3f}")
        for k in range(len(baked["specular"])):
            if (n >> k) < 2 * BLOCK:
                break
            r = block_statistic(baked["specular"][k][sel].astype(np.float64)
                                - other["specular"][k][sel])
            print(f"  specular level {k}: block statistic of the difference {r:.3f}")
            rows[f"block_seeds_specular_{k}"] = r
        rows["block_seeds_incoming"] = block_statistic(diff)
        rows["seeds4"] = noise.tolist()
    if args.save:
        args.save.write_text(json.dumps(rows))
    if args.dump:
        np.savez(args.dump, incoming=inc, reference=ref, a=a, b=b, positions=pos,
                 diffuse=baked["diffuse"][sel], specular0=baked["specular"][0][sel])


if __name__ == "__main__":
    main()
