"""The service's cost model (:mod:`service.cost`) against the CPU time the work really takes.

For a range of ``POST /v1/lights/maps`` requests (lights, kind, face size, levels) and of
``/shade`` batches, prints the model's estimate, the measured CPU time of the library call the
route makes (``time.process_time``: the process's CPU seconds, whatever else the machine runs),
and their ratio. A ratio at or above 1 means the model is conservative: a request it admits under
the budget costs at most the budget. ``--fit`` prints the per-texel, per-evaluation and
per-point constants a least-squares fit of these runs gives (the constants in
``service/cost.py`` are such a fit, rounded up).

Shading is timed on a store with a scene (visibility segments), baked here once into
``--cache`` from the sample room. Run::

    .venv/bin/python benchmarks/bench_service_cost.py --cache /tmp/service-cache [--fit]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from probegrid.core.lights import PointLight, light_maps, light_maps_work
from service.cost import light_maps_estimate, shade_estimate

REPO = Path(__file__).resolve().parents[1]
#: (lights, diffuse size, specular size, specular levels): diffuse maps, then specular chains.
LIGHT_CASES = [
    (1, 64, 1, 1), (16, 256, 1, 1),
    (1, 1, 32, None), (16, 1, 32, None), (4, 1, 64, None), (1, 1, 128, None),
    (4, 1, 128, None), (1, 1, 256, None), (16, 1, 64, None), (16, 1, 128, 4),
]
SHADE_POINTS = [64, 512, 4096]


def _cpu(fn) -> float:
    fn()  # warm (first-call allocations, caches)
    t = time.process_time()
    fn()
    return time.process_time() - t


def light_rows() -> list[tuple[str, float, float, int, int]]:
    rows = []
    for n, d, s, lv in LIGHT_CASES:
        lights = [PointLight(position=(1.0 + 0.1 * i, 2.0, 3.0), color=(1.0, 1.0, 1.0),
                             intensity=10.0) for i in range(n)]
        spent = _cpu(lambda lights=lights, d=d, s=s, lv=lv: light_maps(
            lights, (0.0, 0.0, 0.0), diffuse_size=d, specular_size=s, specular_levels=lv))
        est = light_maps_estimate(n, diffuse_size=d, specular_size=s, specular_levels=lv)
        work = light_maps_work(n, diffuse_size=d, specular_size=s, specular_levels=lv)
        name = f"{n:2d} lights, diffuse {d}, specular {s} x {lv or 'full'}"
        rows.append((name, est.seconds, spent, work.texels, work.evaluations))
    return rows


def shade_rows(cache: Path) -> list[tuple[str, float, float, int]]:
    from probegrid.cli import main as cli
    from probegrid.query import ProbeField
    from probegrid.store import open_store
    from probegrid.usercache import dfg_lut

    store = cache / "room.probes"
    if not store.exists():
        cli(["bake", str(REPO / "data" / "sample_room.glb"), "--out", str(store), "--grid",
             "4x3x4", "--face-size", "16", "--seed", "1"])
    field = ProbeField(open_store(store, load=True))
    g = field.store.grid
    rng = np.random.default_rng(0)
    lo, hi = np.array(g.bounds_min), np.array(g.bounds_max)
    dfg = dfg_lut(64)
    rows = []
    for n in SHADE_POINTS:
        p = lo + (hi - lo) * rng.random((n, 3))
        nrm, view, rough = rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.random(n)
        spent = _cpu(lambda p=p, nrm=nrm, view=view, rough=rough: field.shade(
            p, nrm, view, albedo=(0.5, 0.5, 0.5), roughness=rough, f0=(0.04, 0.04, 0.04),
            dfg=dfg))
        rows.append((f"shade {n} points", shade_estimate(n).seconds, spent, n))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/service-cache"))
    ap.add_argument("--fit", action="store_true", help="print the least-squares constants")
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    lights = light_rows()
    shades = shade_rows(args.cache)
    print(f"{'request':44s} {'model s':>8s} {'CPU s':>8s} {'model/CPU':>9s}")
    for name, est, spent, *_ in [*lights, *shades]:
        print(f"{name:44s} {est:8.3f} {spent:8.3f} {est / max(spent, 1e-9):9.2f}")
    ratios = [est / max(spent, 1e-9) for _, est, spent, *_ in [*lights, *shades]
              if spent > 0.05]
    print(f"model/CPU over the requests of more than 50 ms: min {min(ratios):.2f}, "
          f"median {float(np.median(ratios)):.2f}, max {max(ratios):.2f}")
    if args.fit:
        a = np.array([[t, e] for _, _, _, t, e in lights], dtype=np.float64)
        y = np.array([spent for _, _, spent, _, _ in lights])
        (per_texel, per_eval), *_ = np.linalg.lstsq(a, y, rcond=None)
        per_point = np.median([spent / n for _, _, spent, n in shades])
        print(f"fit: {per_texel * 1e9:.0f} ns a texel, {per_eval * 1e9:.0f} ns an evaluation, "
              f"{per_point * 1e6:.0f} us a shaded point")


if __name__ == "__main__":
    main()
