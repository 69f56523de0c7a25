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

And the SH field (:mod:`probegrid.bake.shfield`, what ``/sh`` interpolates by default): ``field
none`` / ``field normal`` (:meth:`probegrid.query.ProbeField.sh_at`, the normal used for the
visibility segments' start; with the first-order term of the field's limited gradients in the
cells next to the walls, :mod:`probegrid.core.fieldgradient`), ``field plain`` (the same
without that term), next to ``at point``: the SH of a probe traced at the point itself
at the bake's face size (the estimator's own error; the interpolation's share is the rest).
``--refine 1,2,3`` also traces fields of other densities on the same store (``--field-face``
texels a face, ``--field-quality`` the point presets their points are traced with: the surface
cache read at the rays' hits, or the bake's gather) and prints their error against their cost: CPU seconds over the bake's (the
store's ``stage_seconds``, and the default field's own stage when the store has one).

Prints a per-point table, per-variant mean / worst, and how many points a normal makes worse
than no normal (by more than 0.5 %). Run::

    .venv/bin/python benchmarks/bench_sh_blend.py --cache /tmp/maps-cache/bench [--points 16]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
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
    from probegrid.bake.point import PointSettings, PointTracer
    from probegrid.bake.shfield import FIELD_QUALITY, field_lattice, trace_sh_field
    from probegrid.core.ddgi import blend, probe_weights
    from probegrid.core.sh.dering import dering
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
    ap.add_argument("--refine", default="",
                    help="SH field densities (lattice steps per probe cell, comma-separated) "
                         "to trace on the store and compare")
    ap.add_argument("--field-face", default="8",
                    help="their face sizes (comma-separated)")
    ap.add_argument("--field-gather", default="",
                    help="their gather samples and depth, S:D (default: the bake's)")
    ap.add_argument("--field-quality", default="",
                    help="how their points are traced: point presets (fast, accurate, "
                         "reference; comma-separated; default: the bake's field's)")
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

        def errors(coeffs: np.ndarray) -> np.ndarray:
            return np.array([bqa.irradiance_error(coeffs[i], sh_ref[i], nrms[i])
                             for i in range(len(pts))])

        if field.sh_field is not None:
            err["field none"] = errors(field.sh_at(pts, source="field")[0])
            err["field normal"] = errors(field.sh_at(pts, normals=nrms, source="field")[0])
            err["field plain"] = errors(field.sh_at(pts, normals=nrms, source="field",
                                                    gradient=False)[0])
        tracer = field.point_tracer()
        err["at point"] = errors(np.array([sh.project_cube(c) for c in tracer.incoming(pts)]))
        columns = [*variants, *(k for k in ("field none", "field normal", "field plain",
                                            "at point")
                                if k in err)]
        quality = open_store(store_path).manifest.quality
        stages = quality.get("stage_seconds", {})
        bake_s = sum(v for k, v in stages.items() if k != "sh field")
        curve = []
        qualities = args.field_quality.split(",") if args.field_quality else [FIELD_QUALITY]
        for quality, face in ((q, int(x)) for q in qualities for x in args.field_face.split(",")
                              if args.refine):
            gs, gd = ((int(x) for x in args.field_gather.split(":")) if args.field_gather
                      else (None, None))
            ps = dataclasses.replace(PointSettings.preset(quality), face_size=face,
                                     gather_samples=gs, gather_depth=gd)
            ft = PointTracer.from_store(open_store(store_path), scene, tracer=field.tracer,
                                        settings=ps)
            ft.incoming(pts[:1])  # compiled before timing
            inv = float(open_store(store_path).manifest.bake["settings"]["invalid_threshold"])
            for r in (float(x) for x in args.refine.split(",")):
                lattice = field_lattice(field.grid, r)
                t0 = time.process_time()
                raw, fvalid = trace_sh_field(ft, lattice, invalid_threshold=inv)
                cpu = time.process_time() - t0
                der = dering(raw)[0]
                wf = probe_weights(lattice, pts, valid=fvalid, normals=nrms,
                                   normal_bias=field.normal_bias * field.grid.smallest_cell()
                                   / lattice.smallest_cell(), occluded=field._occluded,
                                   extrapolate=0.25, facing=False)
                e = errors(blend(der, wf))
                curve.append((r, f"{quality}, face {face}", lattice, cpu, e))
        print(f"\n== {label}, grid {grid.label}: {len(pts)} points, {int(outside.sum())} outside "
              f"the probes' box; E(n) error %, per point")
        print(f"{'#':>3s} {'kind':10s} {'out':3s} " + " ".join(f"{v:>19s}" for v in columns))
        for i in range(len(pts)):
            print(f"{i:3d} {kinds[i]:10s} {'yes' if outside[i] else '':3s} "
                  + " ".join(f"{100 * err[v][i]:19.2f}" for v in columns))
        print(f"{'mean':18s}" + " ".join(f"{100 * err[v].mean():19.2f}" for v in columns))
        print(f"{'worst':18s}" + " ".join(f"{100 * err[v].max():19.2f}" for v in columns))
        if "field normal" in err:
            gained = err["extrap.25 trilinear"] - err["field normal"]
            worse = err["field normal"] > err["field none"] + 0.005
            print(f"SH field (what /sh answers with, lattice {field.sh_field[0].label}) against "
                  f"the probes' blend (extrap.25 trilinear): mean "
                  f"{100 * err['extrap.25 trilinear'].mean():.2f} -> "
                  f"{100 * err['field normal'].mean():.2f} %, worst "
                  f"{100 * err['extrap.25 trilinear'].max():.2f} -> "
                  f"{100 * err['field normal'].max():.2f} %; better at "
                  f"{int((gained > 0.005).sum())}, worse at {int((gained < -0.005).sum())} of "
                  f"{len(pts)} points; the normal makes it worse at {int(worse.sum())}")
            g = err["field plain"] - err["field normal"]
            print(f"the field's gradient term (field normal) against the plain interpolation "
                  f"(field plain): mean {100 * err['field plain'].mean():.2f} -> "
                  f"{100 * err['field normal'].mean():.2f} %, worst "
                  f"{100 * err['field plain'].max():.2f} -> {100 * err['field normal'].max():.2f}"
                  f" %; better at {int((g > 0.005).sum())}, worse at {int((g < -0.005).sum())} "
                  f"(by up to {100 * max(0.0, -g.min()):.2f} points) of {len(pts)} points")
            if "sh field" in stages:
                print(f"its bake stage: {stages['sh field']:.1f} s over the rest of the bake's "
                      f"{bake_s:.1f} s (x{1 + stages['sh field'] / bake_s:.2f} the bake's time)")
        for r, face, lattice, cpu, e in curve:
            print(f"field refine {r:g} (lattice {lattice.label}, {lattice.n_probes} points, "
                  f"{face}): E(n) mean {100 * e.mean():.2f} %, worst "
                  f"{100 * e.max():.2f} %; traced in {cpu:.1f} CPU s, the store's bake "
                  f"{bake_s:.1f} s wall (x{1 + cpu / bake_s:.2f})")
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
