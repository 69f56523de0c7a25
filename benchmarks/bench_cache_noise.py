"""The surface light cache's noise per lattice vertex against its gather rays, in one run.

A point traced a few centimetres off a wall (:class:`probegrid.bake.point.PointTracer`) sees a
lattice cell of the surface cache (:mod:`probegrid.bake.surfacecache`) across tens of its
texels: the noise of the few vertices nearest it becomes a bright or dark patch of its cube,
which the rough GGX levels and the diffuse map weigh in full. This benchmark takes the bake of
``bench_query_accuracy.py`` (the Cornell box, 4x4x4, faces 32; baked if its cache has none),
gathers the light reflected at least once again at every vertex of the store's own lattice with
``--rays`` cosine rays a vertex (stratified where the count is a square) and, as the reference,
with ``--reference`` rays, and prints per count the relative error of a vertex (mean over RGB;
median, 90th percentile and RMS over the vertices lit in the reference) and the seconds the
gather took, against the reference's. The store's own cache (gathered with the
``CACHE_GATHER`` of the code that baked it) is printed first. Run::

    .venv/bin/python benchmarks/bench_cache_noise.py [--rays 64,100,144,256] [--reference 1024]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def main(argv: list[str] | None = None) -> None:
    import bench_query_accuracy as bq
    import mitsuba_reference as mr

    import probegrid.bake.surfacecache as sc
    from probegrid.bake import BakeSettings
    from probegrid.bake.environment import Environment
    from probegrid.bake.placement import grid_for
    from probegrid.bake.settings import TraceGeometry
    from probegrid.query import ProbeField
    from probegrid.scene import load_gltf
    from probegrid.store import open_store

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rays", default="64,100,144,256")
    ap.add_argument("--reference", type=int, default=1024)
    ap.add_argument("--cache", type=Path,
                    default=Path.home() / ".cache" / "probegrid-bench" / "query")
    args = ap.parse_args(argv)
    path = bq.SHARED / "gltf" / "CornellBox.glb"
    scene = mr.without_light_ranges(load_gltf(path))
    grid = grid_for(scene, grid="4x4x4")
    store = open_store(bq.baked_store(args.cache, "cornell", scene, path, Environment(), grid,
                                      BakeSettings(face_size=32), rebake=False, workers=1))
    tracer = ProbeField(store, scene=scene).point_tracer()
    baked = BakeSettings.model_validate(store.manifest.bake["settings"])
    rd = store.manifest.bake["render"]
    geometry = TraceGeometry(ray_offset=float(rd["ray_offset"]),
                             max_distance=float(rd["max_distance"]))
    lattice = np.asarray(store.arrays[sc.LATTICE_EXTRA])
    stored = np.asarray(store.arrays[sc.LIGHT_EXTRA], np.float64)

    def gather(rays: int) -> tuple[np.ndarray, float]:
        old = sc.CACHE_GATHER
        sc.CACHE_GATHER = rays
        try:
            t0 = time.perf_counter()
            lat, light, _ = sc.bake_surface_cache(scene, Environment(), baked, geometry,
                                                  tracer.data, level=tracer.level)
            secs = time.perf_counter() - t0
        finally:
            sc.CACHE_GATHER = old
        if not np.array_equal(lat, lattice):
            raise SystemExit("the lattice differs from the store's")
        return np.asarray(light, np.float64)[:, 0].mean(axis=1), secs

    ref, ref_secs = gather(args.reference)
    lit = ref > 1e-3 * ref.max()
    print(f"Cornell 4x4x4, {len(stored)} lattice vertices ({int(lit.sum())} lit); reference: "
          f"{args.reference} rays a vertex, {ref_secs:.1f} s")

    def row(label: str, values: np.ndarray, secs: float | None) -> None:
        e = np.abs(values[lit] / ref[lit] - 1.0)
        cost = "" if secs is None else f", {secs:6.1f} s ({secs / ref_secs:.2f}x the reference's)"
        print(f"  {label:24s} median {100 * np.median(e):5.2f} %, "
              f"p90 {100 * np.quantile(e, 0.9):5.2f} %, "
              f"RMS {100 * np.sqrt(np.mean(e ** 2)):5.2f} %{cost}")

    row("the store's cache", stored[:, 0].mean(axis=1), None)
    for k in (int(x) for x in args.rays.split(",")):
        values, secs = gather(k)
        strata = int(np.sqrt(k))
        row(f"{k} rays" + (f" ({strata}x{strata} strata)" if strata * strata == k else ""),
            values, secs)


if __name__ == "__main__":
    main()
