"""The ``/sh`` blend's weights against Mitsuba 3, per point: clamping or extrapolation outside
the probes' box, and the ways a surface normal may enter the weights.

The query points, bakes and references are :mod:`bench_query_accuracy`'s (same seed, same
cache: nothing is re-rendered or re-baked when its cache is warm). For every point the figure is
``E(n)``: the irradiance of the blended SH toward the point's normal against that of the SH of
the reference cube (``sum |E - E_ref| / sum E_ref`` over RGB), next to the same error of the SH
of the reference itself (0 by construction) -- so the column is what the interpolation adds.

Variants (:func:`probegrid.core.ddgi.probe_weights`' options), each with the exact segment
visibility the service applies:

* ``clamp``/``extrap``: a point outside the box clamped onto it, or extrapolated linearly up to
  half a cell;
* ``none``: no normal; ``facing``: DDGI's normal-facing term; ``trilinear``: the normal used only
  for the visibility segments' start; ``offset``: the weights of the point moved
  ``normal_bias`` cells along the normal, no reweighting.

Prints a per-point table, per-variant mean / worst, and how many points a normal makes worse
than no normal (by more than 0.5 %). Run::

    .venv/bin/python benchmarks/bench_sh_blend.py --cache /tmp/maps-cache/bench [--points 16]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

VARIANTS = {  # name: (extrapolate cells, use the normal, facing term, normal offset)
    "clamp none": (0.0, False, True, 0.0),
    "clamp facing": (0.0, True, True, 0.0),
    "clamp trilinear": (0.0, True, False, 0.0),
    "clamp offset": (0.0, True, False, 0.1),
    "extrap none": (0.5, False, True, 0.0),
    "extrap facing": (0.5, True, True, 0.0),
    "extrap trilinear": (0.5, True, False, 0.0),
    "extrap offset": (0.5, True, False, 0.1),
    "extrap.25 none": (0.25, False, True, 0.0),
    "extrap.25 facing": (0.25, True, True, 0.0),
    "extrap.25 trilinear": (0.25, True, False, 0.0),
    "extrap.25 offset": (0.25, True, False, 0.1),
}


def main(argv: list[str] | None = None) -> None:
    import bench_bake_accuracy as bba
    import bench_query_accuracy as bqa
    import mitsuba_reference as mr

    from probegrid.bake.environment import Environment
    from probegrid.bake.placement import grid_for
    from probegrid.bake import BakeSettings
    from probegrid.core import sh
    from probegrid.core.ddgi import probe_weights
    from probegrid.jobs.bake import load_environment
    from probegrid.query import ProbeField
    from probegrid.scene import load_gltf
    from probegrid.store import open_store

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=16)
    ap.add_argument("--scenes", default="cornell,room")
    ap.add_argument("--room-grid", default="8x6x8")
    ap.add_argument("--face-size", type=int, default=32)
    ap.add_argument("--ref-spp", type=int, default=128)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", type=Path,
                    default=Path.home() / ".cache" / "probegrid-bench" / "query")
    ap.add_argument("--cells", default="",
                    help="extra extrapolation limits (cells, comma-separated) to compare, "
                         "with the normal used for visibility only")
    args = ap.parse_args(argv)
    variants = dict(VARIANTS)
    for c in filter(None, args.cells.split(",")):
        variants[f"extrap{c} trilinear"] = (float(c), True, False, 0.0)
    scenes = {"cornell": ("cornell", bqa.SHARED / "gltf" / "CornellBox.glb", None, "4x4x4"),
              "room": ("room", bqa.REPO / "data" / "sample_room.glb",
                       bqa.REPO / "data" / "sample_sky.hdr", args.room_grid)}
    for name in args.scenes.split(","):
        label, path, sky, grid_label = scenes[name]
        scene = mr.without_light_ranges(load_gltf(path))
        env = load_environment(sky) if sky else None
        grid = grid_for(scene, grid=grid_label)
        store_path = bqa.baked_store(args.cache, label, scene, path, env or Environment(), grid,
                                     BakeSettings(face_size=args.face_size), rebake=False,
                                     workers=1)
        field = ProbeField(open_store(store_path), scene=scene)
        pts, nrms, kinds = bqa.query_points(scene, max(1, args.points // len(bqa.KINDS)),
                                            seed=args.seed)
        with mr.MitsubaReference(scene, env) as ref:
            a, b, _ = bba.cached_reference(args.cache / "mitsuba", ref, scene, env, pts,
                                           face_size=args.face_size, spp=args.ref_spp,
                                           max_depth=64)
        ref_cube = bqa.splat_lights(0.5 * (a + b), scene, pts)
        sh_ref = [sh.project_cube(c) for c in ref_cube]
        valid, positions, moments = field._visibility
        outside = field.grid.corners(pts)[2]
        err = {}
        for v, (cells, use_n, facing, offset) in variants.items():
            # offset: the weights (and the segments' start) of the point moved off the surface
            q = pts + offset * field.grid.smallest_cell() * nrms
            w = probe_weights(field.grid, q, valid=valid,
                              normals=nrms if use_n and not offset else None,
                              probe_positions=positions, moments=moments,
                              normal_bias=field.normal_bias, occluded=field._occluded,
                              extrapolate=cells, facing=facing)
            blended = field.sh(w)
            err[v] = np.array([bqa.irradiance_error(blended[i], sh_ref[i], nrms[i])
                               for i in range(len(pts))])
        print(f"\n== {label}, grid {grid.label}: {len(pts)} points, {int(outside.sum())} outside "
              f"the probes' box; E(n) error %, per point")
        print(f"{'#':>3s} {'kind':10s} {'out':3s} " + " ".join(f"{v:>19s}" for v in variants))
        for i in range(len(pts)):
            print(f"{i:3d} {kinds[i]:10s} {'yes' if outside[i] else '':3s} "
                  + " ".join(f"{100 * err[v][i]:19.2f}" for v in variants))
        print(f"{'mean':18s}" + " ".join(f"{100 * err[v].mean():19.2f}" for v in variants))
        print(f"{'worst':18s}" + " ".join(f"{100 * err[v].max():19.2f}" for v in variants))
        for mode in ("extrap", "extrap.25"):
            print(f"{mode} against clamp (no normal): better at "
                  f"{int((err[f'{mode} none'] < err['clamp none'] - 0.005).sum())}, worse at "
                  f"{int((err[f'{mode} none'] > err['clamp none'] + 0.005).sum())} of "
                  f"{int(outside.sum())} outside points")
        for mode in ("clamp", "extrap", "extrap.25"):
            base = err[f"{mode} none"]
            for v in ("facing", "trilinear", "offset"):
                if f"{mode} {v}" not in err:
                    continue
                worse = err[f"{mode} {v}"] > base + 0.005
                print(f"{mode} {v}: worse than without the normal at {int(worse.sum())} of "
                      f"{len(pts)} points" + (f" (max +{100 * (err[f'{mode} {v}'] - base).max():.1f}"
                                              " points)" if worse.any() else ""))


if __name__ == "__main__":
    main()
