"""Light through walls by the grid reads, and emitters of many triangles, against Mitsuba 3.

Two experiments, each against a converged path tracer (:mod:`mitsuba_reference`, variant
``scalar_rgb``, max depth 64, two independent halves whose difference is printed as the
reference's noise floor), on scenes built in code (``benchmarks/scenes.py``):

* **Two grids, one interior** (:func:`scenes.sunlit_building`): the 36 interior probe positions
  (:func:`scenes.building_interior_points`, a 4 x 3 x 3 lattice) baked alone, then as part of a
  grid of the same spacing extended by layers of probes (``--extend``): ``walls-roof``, a 4 x 5
  x 5 grid, 64 probes outside the walls (z = +-4.8 m, the walls' outer faces at +-4.2 m), in
  the roof slab (y = 4 m: moved just under the ceiling, or invalid with ``--no-relocate``; two
  stand in the skylights' openings) and above the roof (y = 5 m), in the sun; ``walls``, a 6 x
  3 x 5 grid, 54 probes outside the four walls. The two interior points on the cabinet's face
  are moved off it the same way in both grids. Printed per grid: the interior probes' diffuse
  error against the reference, and how much the added probes changed them (the ratio of each
  interior probe's irradiance integral, extended over alone; the probes draw the same random
  numbers in both grids, so the change is what the added probes bring); then the same for
  :class:`probegrid.bake.point.PointTracer`'s answers at the interior points (what the service
  traces), which read the grids at their gather hits. A read that lets a gather hit see the
  probes beyond a wall lets the sun in.
* **Emissive spheres** (:func:`scenes.emissive_spheres`: a grey room lit only by four icospheres
  of 5,120 triangles each): a 3 x 3 x 3 grid baked with seeds 0 and 1, the diffuse error of each
  against the reference, and the two bakes' difference.

The diffuse error is ``sum dOmega |pg - ref| / sum dOmega ref`` of the diffuse cube (irradiance /
pi at ``--diffuse`` texels per side, both from the incoming cubes by
:func:`probegrid.core.diffuse.diffuse_exact`), per probe; mean and worst over the probes.

References are cached under ``--cache`` (default ``/tmp/leaks-cache``) by content key. Run::

    PYTHONPATH=. .venv/bin/python benchmarks/bench_leaks.py [--face-size 16] [--spp 128]
    PYTHONPATH=. .venv/bin/python benchmarks/bench_leaks.py --only building --extend walls

Each bake uses both cores (local workers); on this 2-core machine, with an empty cache, the
references take about 7 minutes and the bakes about 5.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import scenes  # noqa: E402
from bench_bake_accuracy import cached_reference, diffuse_of, half_difference  # noqa: E402


def relative_l1(a: NDArray, b: NDArray) -> NDArray[np.float64]:
    """Per probe ``sum dOmega |a - b| / sum dOmega b`` of cubes ``(P, 6, n, n, 3)``."""
    from probegrid.core.cubemap import texel_solid_angles

    w = texel_solid_angles(a.shape[2])[None, ..., None]
    num = (w * np.abs(np.asarray(a, np.float64) - b)).sum(axis=(1, 2, 3, 4))
    return num / np.maximum((w * np.asarray(b, np.float64)).sum(axis=(1, 2, 3, 4)), 1e-300)


def energy(a: NDArray) -> NDArray[np.float64]:
    """Per probe solid-angle integral of cubes ``(P, 6, n, n, 3)`` (all channels)."""
    from probegrid.core.cubemap import texel_solid_angles

    w = texel_solid_angles(a.shape[2])[None, ..., None]
    return (w * np.asarray(a, np.float64)).sum(axis=(1, 2, 3, 4))


def stats(e: NDArray[np.float64]) -> str:
    return f"{100 * np.mean(e):6.2f} % mean, {100 * np.max(e):6.2f} % worst"


def bake_store(scene: Any, env: Any, grid: Any, out: Path, *, face: int, seed: int = 0,
               workers: int = 2, bounces: int | str = "converge", relocate: bool = True,
               cache_spacing: float | None = None) -> tuple[Any, float, Any]:
    """Bake ``grid`` into ``out``; returns the open store, the seconds and the report."""
    from probegrid.bake import BakeSettings, bake
    from probegrid.bake.executors import LocalExecutor
    from probegrid.store import open_store

    settings = BakeSettings(face_size=face, seed=seed, store_incoming=True, bounces=bounces,
                            relocate=relocate, surface_cache_spacing=cache_spacing)
    with LocalExecutor(workers=workers, preload=("probegrid.bake.preload",)) as ex:
        t0 = time.perf_counter()
        report = bake(scene, grid, out, settings=settings, environment=env, executor=ex,
                      overwrite=True)
        seconds = time.perf_counter() - t0
    return open_store(out), seconds, report


#: Layers of probes added to the interior grid (below and above along x, y, z): outside the
#: walls along z and above the roof (the y = 4 m layer falls in the roof slab: its probes are
#: moved just under the ceiling, or stand in the skylights' openings), or outside all four
#: walls only.
EXTENSIONS = {"walls-roof": ((0, 0, 1), (0, 2, 1)), "walls": ((1, 0, 1), (1, 0, 1))}


def building_grids(extend: str = "walls-roof") -> tuple[Any, Any, NDArray[np.int64]]:
    """The interior grid, the extended grid and the interior probes' indices in it."""
    from probegrid.core.grid import GridSpec

    pts = scenes.building_interior_points()
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    inner = GridSpec.from_counts(tuple(lo), tuple(hi), (4, 3, 3))
    step = (hi - lo) / (np.array([4, 3, 3]) - 1)
    below, above = (np.array(v) for v in EXTENSIONS[extend])
    lo2 = lo - below * step
    hi2 = hi + above * step
    outer = GridSpec.from_counts(tuple(lo2), tuple(hi2), tuple(np.array([4, 3, 3]) + below
                                                                + above))
    pos = outer.positions()
    idx = np.array([int(np.argmin(np.linalg.norm(pos - p, axis=1)))
                    for p in inner.positions()])
    assert np.allclose(pos[idx], inner.positions())
    return inner, outer, idx


def reference(scene: Any, env: Any, positions: NDArray, args: argparse.Namespace
              ) -> tuple[NDArray, NDArray]:
    """The reference's diffuse cubes and its noise floor per probe."""
    import mitsuba_reference as mr

    with mr.MitsubaReference(scene, env) as ref:
        a, b, secs = cached_reference(args.cache, ref, scene, env, positions,
                                      face_size=args.face_size, spp=args.spp, max_depth=64)
        # the delta lights no camera ray sees
        punct = ref.punctual_diffuse(positions, args.diffuse) if scene.lights else 0.0
    da, db = diffuse_of(a, args.diffuse) + punct, diffuse_of(b, args.diffuse) + punct
    d = 0.5 * (da.astype(np.float64) + db)
    noise = half_difference(da, db)
    print(f"  reference: {len(positions)} probes, {args.spp} spp, {secs:.0f} s, noise "
          f"{stats(noise)}", flush=True)
    return d, noise


def two_grids(args: argparse.Namespace, work: Path) -> None:
    from probegrid.bake.point import PointTracer

    scene, env = scenes.sunlit_building()
    inner, outer, idx = building_grids(args.extend)
    print(f"sunlit building: interior 4x3x3 grid alone and inside a "
          f"{'x'.join(map(str, outer.counts))} grid ({outer.n_probes - 36} probes added, "
          f"{args.extend})", flush=True)
    alone, t1, _ = bake_store(scene, env, inner, work / "inner.probes", face=args.face_size,
                              bounces=args.bounces, relocate=args.relocate,
                              cache_spacing=args.surface_cache_spacing)
    ext, t2, _ = bake_store(scene, env, outer, work / "outer.probes", face=args.face_size,
                            bounces=args.bounces, relocate=args.relocate,
                            cache_spacing=args.surface_cache_spacing)
    print(f"  bounces: {alone.manifest.quality['bounces']} alone, "
          f"{ext.manifest.quality['bounces']} extended", flush=True)
    # (the reference where the probes stand: two interior points on the cabinet's face are
    # moved off it, the same way in both grids)
    keep = np.asarray(alone["valid"])  # (without relocation, the two on the cabinet's face)
    pts = np.asarray(alone["positions"], np.float64)[keep]
    assert np.allclose(pts, np.asarray(ext["positions"])[idx][keep], rtol=0, atol=1e-9)
    ref_d, _ = reference(scene, env, pts, args)
    ok = np.asarray(ext["valid"])
    print(f"  extended grid: {int(ok.sum())} of {len(ok)} valid, "
          f"{int((~np.isclose(np.asarray(ext['positions']), outer.positions()).all(1)).sum())}"
          f" relocated; interior probes compared: {int(keep.sum())}", flush=True)
    idx = idx[keep]
    d_alone = diffuse_of(np.asarray(alone["incoming"])[keep], args.diffuse)
    d_ext = diffuse_of(np.asarray(ext["incoming"])[idx], args.diffuse)
    ratio = energy(d_ext) / energy(d_alone) - 1.0
    print(f"  bake alone   : {t1:6.0f} s, error vs Mitsuba {stats(relative_l1(d_alone, ref_d))}")
    print(f"  bake extended: {t2:6.0f} s, error vs Mitsuba {stats(relative_l1(d_ext, ref_d))}")
    print(f"  interior change (extended / alone - 1): mean {100 * ratio.mean():+.2f} %, "
          f"range {100 * ratio.min():+.2f} .. {100 * ratio.max():+.2f} %, |worst| "
          f"{100 * np.abs(ratio).max():.2f} %", flush=True)
    q = []
    for store in (alone, ext):
        tracer = PointTracer.from_store(store, scene)
        t0 = time.perf_counter()
        q.append(diffuse_of(tracer.incoming(pts), args.diffuse))
        print(f"  points traced in {time.perf_counter() - t0:.0f} s, error vs Mitsuba "
              f"{stats(relative_l1(q[-1], ref_d))}", flush=True)
    r = energy(q[1]) / energy(q[0]) - 1.0
    print(f"  PointTracer change (extended / alone - 1): mean {100 * r.mean():+.2f} %, range "
          f"{100 * r.min():+.2f} .. {100 * r.max():+.2f} %, |worst| "
          f"{100 * np.abs(r).max():.2f} %", flush=True)
    print(f"  PointTracer maps, extended against alone (relative L1): "
          f"{stats(relative_l1(q[1], q[0]))}", flush=True)
    from probegrid.bake.surfacecache import LATTICE_EXTRA, LIGHT_EXTRA

    caches = [s.manifest.quality.get("surface_cache", {}) for s in (alone, ext)]
    same = all(np.array_equal(np.asarray(alone[k]), np.asarray(ext[k]))
               for k in (LATTICE_EXTRA, LIGHT_EXTRA))
    light = [np.asarray(s[LIGHT_EXTRA], np.float64) for s in (alone, ext)]
    lat = np.array_equal(np.asarray(alone[LATTICE_EXTRA]), np.asarray(ext[LATTICE_EXTRA]))
    diff = (np.abs(light[1] - light[0]).sum() / max(np.abs(light[0]).sum(), 1e-300)
            if lat else float("nan"))
    secs = [s.manifest.quality["stage_seconds"] for s in (alone, ext)]
    print(f"  surface cache: {secs[0].get('surface cache', 0):.1f} s / "
          f"{secs[1].get('surface cache', 0):.1f} s of the bakes' "
          f"{sum(secs[0].values()):.1f} s / {sum(secs[1].values()):.1f} s; spacing "
          f"{caches[0].get('spacing', 0):.4g} / "
          f"{caches[1].get('spacing', 0):.4g}, vertices {caches[0].get('vertices')} / "
          f"{caches[1].get('vertices')}; lattice {'the same' if lat else 'differs'}, light "
          f"{'bit-identical' if same else f'differs by {100 * diff:.3f} % (relative L1)'}",
          flush=True)


def spheres(args: argparse.Namespace, work: Path) -> None:
    from probegrid.core.grid import GridSpec

    scene = scenes.emissive_spheres()
    grid = GridSpec.from_counts((-2.0, 0.5, -2.0), (2.0, 2.5, 2.0), (3, 3, 3))
    print("emissive spheres: 4 icospheres of 5,120 triangles, 3x3x3 grid", flush=True)
    ref_d, _ = reference(scene, None, grid.positions(), args)
    ds = []
    for seed in (0, 1):
        store, t, report = bake_store(scene, None, grid, work / f"spheres{seed}.probes",
                                      face=args.face_size, seed=seed)
        d = diffuse_of(np.asarray(store["incoming"]), args.diffuse)
        ds.append(d)
        notes = [str(v) for k, v in report.quality.items() if "emitter" in k]
        print(f"  seed {seed}: {t:6.0f} s, error vs Mitsuba {stats(relative_l1(d, ref_d))}"
              + (f" ({'; '.join(notes)})" if notes else ""), flush=True)
    print(f"  seed 0 vs seed 1: {stats(relative_l1(ds[1], ds[0]))}", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--face-size", type=int, default=16)
    p.add_argument("--diffuse", type=int, default=8)
    p.add_argument("--spp", type=int, default=128)
    p.add_argument("--extend", choices=tuple(EXTENSIONS), default="walls-roof",
                   help="where the extended grid adds probes")
    p.add_argument("--no-relocate", dest="relocate", action="store_false",
                   help="bake with --no-relocate (probes in solids invalid, not moved)")
    p.add_argument("--bounces", default="converge",
                   help="the bakes' --bounces (default converge)")
    p.add_argument("--surface-cache-spacing", type=float, default=None,
                   help="the bakes' --surface-cache-spacing (default: the scene's)")
    p.add_argument("--cache", type=Path, default=Path("/tmp/leaks-cache"))
    p.add_argument("--only", choices=("building", "spheres"), default=None)
    p.add_argument("--work", type=Path, default=None,
                   help="keep the stores in this directory (default: a temporary one)")
    args = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-leaks-") as tmp:
        work = Path(tmp) if args.work is None else args.work
        work.mkdir(parents=True, exist_ok=True)
        if args.only in (None, "building"):
            two_grids(args, work)
        if args.only in (None, "spheres"):
            spheres(args, work)


if __name__ == "__main__":
    main()
