"""Bake accuracy and time against a converged path tracer (Mitsuba 3), in one run.

For each scene -- ``tests/data/gltf/CornellBox.glb`` (a small emissive ceiling panel, no other light)
and the bundled sample room (``data/sample_room.glb``, its point light and ``data/sample_sky.hdr``
as the environment) -- a 3x3x3 probe grid (``grid_for(scene, grid="3x3x3")``: probes at the
cell centres of the scene's bounds; relocated and invalid probes as the bake decides) is baked
by probegrid, and Mitsuba 3 (:mod:`mitsuba_reference`, variant ``scalar_rgb``) renders the
incoming cube at each probe's (possibly relocated) position with six 90-degree sensors whose
pixels are probegrid's texels. Before anything else, :func:`mitsuba_reference.check_orientation`
proves that a lopsided environment and an off-axis emitter land on the right texels of the right
faces (README "Conventions": the OpenGL/KTX2 face table), :func:`mitsuba_reference.check_furnace`
that a closed emitting box reads ``Le / (1 - rho)``, and, for a scene with an environment,
:func:`mitsuba_reference.check_environment_energy` that a floor under it reads ``rho E / pi`` with
``E`` probegrid's exact integral of the environment.

Figures (per valid probe, then the mean and the worst probe):

* **diffuse error**: the store's diffuse cube (irradiance / pi) against
  ``probegrid.core.diffuse.diffuse_exact`` of the reference cube at the same size, as the
  relative L1 error over the sphere, ``sum_texels,rgb dOmega |pg - ref| / sum dOmega ref``.
  The reference is a path tracer at max depth 64 (Russian roulette after depth 5, unbiased),
  rendered as two independent halves; half their difference is printed as its noise floor.
* **direct view** (CornellBox): a bake with ``--bounces 0`` against a max-depth-1 render (the
  emitters seen directly; ``--direct-depth`` changes it), whose diffuse map is itself checked
  against the exact polygon form factor of the panel (Lambert's formula, at every diffuse texel
  that sees the whole panel above its horizon).
* **equal wall time**: the error Mitsuba reaches (max depth 64) with the samples per pixel that
  fit in probegrid's bake time (1- and 4-spp renders calibrate its fixed and per-sample time;
  the error is then scaled by ``sqrt(render time / bake time)`` to the bake's time exactly),
  against probegrid's.

Both tools see the same physics: the glTF ``range`` of the sample room's point light has no
Mitsuba counterpart, so both bake the scene without it (pure inverse-square falloff).

The converged reference is cached under ``~/.cache/probegrid-bench/mitsuba`` (``--cache``),
keyed by the scene's and environment's content hash, the probe positions, the face size,
samples, depth and the Mitsuba version, so re-runs cost only the bakes and the equal-time
renders.

Against another checkout: ``--repo PATH`` bakes with that checkout's code (its ``.venv`` if it
has one, else this interpreter with ``PYTHONPATH=PATH``), in a subprocess; Mitsuba and the
comparison run here. Run::

    .venv/bin/pip install mitsuba            # benchmark only (extra "bench")
    .venv/bin/python benchmarks/bench_bake_accuracy.py [--quick] [--repo PATH]

``--quick`` (faces 16, fewer reference samples) runs in under 2 minutes on 2 cores with an
empty cache; the full run (faces 32, 2 x 128 spp reference) takes about 12 minutes the first
time (16 minutes on this loaded 2-core machine) and about 2 minutes cached.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
SHARED = REPO / "tests" / "data"


# ------------------------------------------------------------------------------ bake (subprocess)
def _bake_main(spec_file: str) -> None:
    """Child process: bake one scene with the probegrid on ``sys.path``; write arrays + JSON."""
    spec = json.loads(Path(spec_file).read_text())
    from probegrid.bake.executors import make_executor

    # as ``probegrid bake`` does: the worker processes start (and import the bake) while this
    # process imports it and loads the scene; the timed bake begins once the scene is loaded
    # (what is left of the workers' start-up is timed). (Older checkouts start them with the
    # bake.)
    try:
        executor = make_executor(workers=spec["workers"], preload=("probegrid.bake.preload",))
    except TypeError:
        executor = make_executor(workers=spec["workers"])
    if hasattr(executor, "start"):
        executor.start()
    import probegrid
    from probegrid.bake import BakeSettings, bake
    from probegrid.jobs.bake import load_environment
    from probegrid.scene import load_gltf
    from probegrid.store import open_store

    try:
        from probegrid.bake.placement import grid_for
    except ImportError:  # (older checkouts kept it in the job)
        from probegrid.jobs.bake import grid_for  # type: ignore[attr-defined,no-redef]
    scene = load_gltf(spec["scene"])
    scene = dataclasses.replace(scene, lights=() if spec.get("no_punctual") else tuple(
        dataclasses.replace(lt, range=None) if getattr(lt, "range", None) is not None else lt
        for lt in scene.lights))
    grid = grid_for(scene, grid=spec["grid"])
    env = load_environment(Path(spec["environment"]) if spec["environment"] else None)
    bounces: Any = spec["bounces"]
    note = ""
    try:
        extra = {"gather_depth": spec["gather_depth"]} if spec.get("gather_depth") else {}
        if spec.get("seed") is not None:
            extra["seed"] = spec["seed"]
        if spec.get("final_gather"):
            extra["final_gather"] = spec["final_gather"]
        settings = BakeSettings(face_size=spec["face_size"], bounces=bounces,
                                samples=spec["samples"], store_incoming=True, **extra)
    except ValueError:
        if bounces != "converge":
            raise
        bounces = spec["fallback_bounces"]
        note = f"this checkout has no --bounces converge; baked {bounces} bounces"
        settings = BakeSettings(face_size=spec["face_size"], bounces=bounces,
                                samples=spec["samples"], store_incoming=True)
    out = Path(spec["out"])
    try:
        t0 = time.perf_counter()
        report = bake(scene, grid, out, settings=settings, environment=env, executor=executor,
                      overwrite=True)
        seconds = time.perf_counter() - t0
    finally:
        executor.close()
    store = open_store(out)
    np.savez(Path(spec["result"]).with_suffix(".npz"),
             positions=np.asarray(store["positions"]), valid=np.asarray(store["valid"]),
             diffuse=np.asarray(store["diffuse"]), incoming=np.asarray(store["incoming"]))
    Path(spec["result"]).write_text(json.dumps({
        "seconds": seconds, "rays": int(report.rays), "bounces": bounces, "note": note,
        "probegrid": str(Path(probegrid.__file__).parent),
        "quality": {k: v for k, v in report.quality.items() if isinstance(v, (int, float, str))},
    }, default=str))


def _python_for(repo: Path) -> str:
    venv = repo / ".venv" / "bin" / "python"
    return str(venv) if venv.exists() else sys.executable


def run_bake(repo: Path, work: Path, name: str, **spec: Any) -> tuple[dict[str, Any], Any]:
    """Bake in a subprocess with ``repo``'s probegrid; returns (info, arrays)."""
    result = work / f"{name}.json"
    spec = dict(spec, out=str(work / f"{name}.probes"), result=str(result))
    spec_file = work / f"{name}.spec.json"
    spec_file.write_text(json.dumps(spec))
    env = dict(os.environ, PYTHONPATH=str(repo))
    proc = subprocess.run([_python_for(repo), str(Path(__file__).resolve()), "--_bake",
                           str(spec_file)], cwd=str(repo), env=env, capture_output=True,
                          text=True, check=False)
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise SystemExit(f"the bake of {name} failed in {repo}: {tail}")
    info = json.loads(result.read_text())
    return info, np.load(result.with_suffix(".npz"))


# ------------------------------------------------------------------------------ figures
def relative_l1(a: NDArray, b: NDArray) -> NDArray[np.float64]:
    """Per probe ``sum dOmega |a - b| / sum dOmega b`` over cubes ``(P, 6, n, n, 3)``."""
    from probegrid.core.cubemap import texel_solid_angles

    w = texel_solid_angles(a.shape[2])[None, ..., None]
    num = (w * np.abs(np.asarray(a, np.float64) - b)).sum(axis=(1, 2, 3, 4))
    den = (w * np.asarray(b, np.float64)).sum(axis=(1, 2, 3, 4))
    return num / np.maximum(den, 1e-300)


def half_difference(a: NDArray, b: NDArray) -> NDArray[np.float64]:
    """Noise of the mean of two independent renders ``a``, ``b``, relative, per probe:
    ``sum dOmega |a - b| / sum dOmega (a + b)`` (half the difference over the mean)."""
    return relative_l1(a, 0.5 * (np.asarray(a, np.float64) + b))  # = sum|a-b| / sum(a+b)


def diffuse_of(cubes: NDArray, size: int) -> NDArray[np.float32]:
    from probegrid.core.diffuse import diffuse_exact

    return np.stack([diffuse_exact(c, size) for c in cubes])  # a loop over probes


def polygon_diffuse(points: NDArray[np.float64], normals: NDArray[np.float64],
                    triangles: NDArray[np.float64], radiance: float) -> NDArray[np.float64]:
    """Exact ``E / pi`` at ``points (P, 3)`` for ``normals (P, N, 3)`` from Lambertian
    ``triangles (T, 3, 3)`` of ``radiance`` (Lambert's polygon formula, summed over triangles:
    ``E = L / 2 sum_edges gamma_e n . u_e``); NaN where a triangle is not wholly above the
    horizon of the normal (the formula would need clipping there)."""
    v = triangles[None, :, :, :] - points[:, None, None, :]  # (P, T, 3, 3)
    vn = v / np.linalg.norm(v, axis=-1, keepdims=True)
    nxt = np.roll(vn, -1, axis=2)
    gamma = np.arccos(np.clip((vn * nxt).sum(-1), -1.0, 1.0))  # (P, T, 3)
    c = np.cross(vn, nxt)
    u = c / np.linalg.norm(c, axis=-1, keepdims=True)
    per_edge = np.einsum("pnk,ptek->pnte", normals, u)  # (P, N, T, 3)
    tri = np.abs((gamma[:, None] * per_edge).sum(-1)) * radiance / (2.0 * np.pi)  # E/pi per tri
    above = np.einsum("pnk,ptek->pnte", normals, v).min(axis=-1) > 0  # (P, N, T)
    return np.where(above, tri, np.nan).sum(-1)


# ------------------------------------------------------------------------------ reference cache
def cached_reference(cache: Path, ref: Any, scene: Any, env: Any, positions: NDArray, *,
                     face_size: int, spp: int, max_depth: int) -> tuple[NDArray, NDArray, float]:
    """(cube A, cube B, seconds): two independent renders of ``spp // 2`` samples each."""
    import mitsuba_reference as mr

    key = mr.cache_key(scene, env, positions, face_size=face_size, spp=spp, max_depth=max_depth)
    file = cache / f"{key}.npz"
    if file.exists():
        z = np.load(file)
        return z["a"], z["b"], float(z["seconds"])
    half = max(1, spp // 2)
    a = ref.render(positions, face_size, spp=half, max_depth=max_depth, seed=1)
    b = ref.render(positions, face_size, spp=half, max_depth=max_depth, seed=7_000_001)
    cache.mkdir(parents=True, exist_ok=True)
    tmp = cache / f".{key}.{os.getpid()}.npz"
    np.savez(tmp, a=a.cubes, b=b.cubes, seconds=a.seconds + b.seconds)
    os.replace(tmp, file)
    return a.cubes, b.cubes, a.seconds + b.seconds


# ------------------------------------------------------------------------------ main
def _stats(e: NDArray[np.float64]) -> str:
    """Mean and worst over the probes (NaN entries: probes left out)."""
    return (f"{100 * np.nanmean(e):6.2f} % mean, {100 * np.nanmax(e):6.2f} % worst "
            f"(probe {int(np.nanargmax(e))})")


def bench_scene(label: str, path: Path, sky: Path | None, args: argparse.Namespace,
                work: Path) -> dict[str, Any]:
    import mitsuba_reference as mr

    from probegrid.jobs.bake import load_environment
    from probegrid.scene import load_gltf

    n = args.face_size
    spec = {"scene": str(path), "environment": str(sky) if sky else None, "grid": args.grid,
            "face_size": n, "samples": args.samples, "workers": args.workers,
            "fallback_bounces": args.fallback_bounces, "gather_depth": args.gather_depth,
            "seed": args.seed, "no_punctual": args.no_punctual}
    if args.final_gather:  # (older checkouts have no final gather)
        spec["final_gather"] = args.final_gather
    print(f"\n== {label}: {path.name}" + (f" + {sky.name}" if sky else "") +
          f", grid {args.grid}, faces {n}^2, {args.samples} ray(s) per texel")
    info, baked = run_bake(args.repo, work, f"{label}-conv", bounces=args.bounces, **spec)
    q = info["quality"]
    reached = (f" (reached {q['bounces']}, residual {100 * q['bounce_residual']:.2g} %)"
               if isinstance(q.get("bounce_residual"), float) and "bounces" in q else "")
    print(f"probegrid ({info['probegrid']}): bake {info['seconds']:.2f} s, bounces "
          f"{info['bounces']}{reached}" + (f" ({info['note']})" if info["note"] else ""))
    valid = baked["valid"].astype(bool)
    pos = baked["positions"][valid]
    d = baked["diffuse"].shape[2]
    scene = mr.without_light_ranges(load_gltf(path))
    if args.no_punctual:
        scene = dataclasses.replace(scene, lights=())
    env = load_environment(sky) if sky else None
    out: dict[str, Any] = {"label": label, "valid": int(valid.sum()), "probes": len(valid),
                           "bake_seconds": info["seconds"]}
    if env is not None:
        print(f"environment energy check (floor under the sky, Mitsuba depth 2 vs the exact "
              f"integral): {100 * mr.check_environment_energy(env):.2f} % worst channel")
    with mr.MitsubaReference(scene, env) as ref:
        a, b, ref_seconds = cached_reference(args.cache, ref, scene, env, pos, face_size=n,
                                             spp=args.ref_spp, max_depth=64)
        ref_cube = 0.5 * (a + b)
        direct = ref.punctual_diffuse(pos, d)  # the delta lights no camera ray sees
        ref_d = diffuse_of(ref_cube, d) + direct
        noise = half_difference(diffuse_of(a, d) + direct, diffuse_of(b, d) + direct)
        err = relative_l1(baked["diffuse"][valid], ref_d)
        print(f"reference: Mitsuba path, max depth 64, {args.ref_spp} spp, {ref_seconds:.0f} s "
              f"when rendered; its noise {100 * noise.mean():.2f} % mean, "
              f"{100 * noise.max():.2f} % worst")
        print(f"converged diffuse (irradiance/pi, {d}^2) error: {_stats(err)}  "
              f"[{int(valid.sum())}/{len(valid)} probes valid]")
        out.update(err=err, noise=noise, positions=pos)
        # equal wall time: Mitsuba at the spp that fits in probegrid's bake time
        # (the render's time is fixed + spp * per_spp: two calibration renders fit both)
        t1 = ref.render(pos, n, spp=1, max_depth=64, seed=11).seconds
        t4 = ref.render(pos, n, spp=4, max_depth=64, seed=12).seconds
        per_spp = max((t4 - t1) / 3.0, 1e-3)
        spp = max(1, round((info["seconds"] - max(t1 - per_spp, 0.0)) / per_spp))
        eq = ref.render(pos, n, spp=spp, max_depth=64, seed=13)
        eq_err = relative_l1(diffuse_of(eq.cubes, d) + direct, ref_d)
        print(f"equal time: Mitsuba {spp} spp in {eq.seconds:.2f} s "
              f"({eq.seconds / info['seconds']:.2f}x probegrid's {info['seconds']:.2f} s): "
              f"{_stats(eq_err)}")
        # a shared machine's load moves the render time off the target: scale the error to
        # probegrid's time exactly (Monte Carlo error ~ 1 / sqrt(samples) ~ 1 / sqrt(time))
        eq_err = eq_err * np.sqrt(eq.seconds / info["seconds"])
        print(f"  scaled to probegrid's time (error ~ 1/sqrt(time)): {_stats(eq_err)}")
        print(f"  error ratio probegrid / Mitsuba at equal time: "
              f"{err.mean() / max(eq_err.mean(), 1e-12):.2f} (mean), "
              f"{err.max() / max(eq_err.max(), 1e-12):.2f} (worst)")
        out.update(eq_err=eq_err, eq_spp=spp, eq_seconds=eq.seconds)
        if (args.direct and any(np.any(m.emissive > 0) for m in scene.materials)
                and not scene.lights and env is None):  # (else bounces 0 lights surfaces)
            info0, baked0 = run_bake(args.repo, work, f"{label}-b0", bounces=0, **spec)
            v0 = baked0["valid"].astype(bool)
            if not np.array_equal(v0, valid):
                print("  (bounces 0 classified the probes differently; comparing its own valid "
                      "probes)")
            pos0 = baked0["positions"][v0]
            a0, b0, _ = cached_reference(args.cache, ref, scene, env, pos0, face_size=n,
                                          spp=args.direct_spp, max_depth=args.direct_depth)
            ref0 = diffuse_of(0.5 * (a0 + b0), d)
            # probes that see no emitter (the reference's direct view is below 0.1 % of the
            # brightest probe's: a stray sample through a crack) have no direct view to judge
            total = ref0.sum(axis=(1, 2, 3, 4))
            sees = total > 1e-3 * total.max()
            print("  direct-view irradiance of the probes left out, relative to the brightest: "
                  + (", ".join(f"{t / total.max():.1e}" for t in total[~sees]) or "none"))
            err0 = np.where(sees, relative_l1(baked0["diffuse"][v0], ref0), np.nan)
            noise0 = half_difference(diffuse_of(a0, d)[sees], diffuse_of(b0, d)[sees])
            print(f"direct view (probegrid --bounces 0, {info0['seconds']:.2f} s, vs Mitsuba max "
                  f"depth {args.direct_depth}, {args.direct_spp} spp, noise "
                  f"{100 * noise0.mean():.2f} %), {int(sees.sum())} probes that see an emitter: "
                  f"{_stats(err0)}")
            out.update(err0=err0)
            if args.direct_depth == 1:
                check_form_factor(scene, pos0, ref0)
    return out


def check_form_factor(scene: Any, positions: NDArray, ref_diffuse: NDArray) -> None:
    """Mitsuba's max-depth-1 diffuse against the exact polygon form factor of the emitters."""
    from probegrid.core.cubemap import texel_directions

    emissive = [i for i, m in enumerate(scene.materials) if np.any(m.emissive > 0)]
    if len(emissive) != 1 or scene.materials[emissive[0]].emissive_texture is not None:
        return
    mat = scene.materials[emissive[0]]
    tris = scene.vertices[scene.triangles[scene.material == emissive[0]]]
    d = ref_diffuse.shape[2]
    normals = np.broadcast_to(texel_directions(d).reshape(1, -1, 3),
                              (len(positions), 6 * d * d, 3))
    exact = polygon_diffuse(positions, normals, tris, float(mat.emissive[0]))
    # the formula knows no occluders: keep the probes that see every point of a 6x6 barycentric
    # lattice on each emitter triangle (shadow rays through Embree)
    from probegrid.raytrace import RayTracer

    k = (np.arange(6) + 0.5) / 6
    uu, vv = (x.ravel() for x in np.meshgrid(k, k))
    inside = uu + vv < 1
    uu, vv = uu[inside], vv[inside]
    pts = (tris[:, None, 0] * (1 - uu - vv)[None, :, None] + tris[:, None, 1] * uu[None, :, None]
           + tris[:, None, 2] * vv[None, :, None]).reshape(-1, 3)
    to = pts[None, :, :] - positions[:, None, :]
    dist = np.linalg.norm(to, axis=-1)
    origins = np.broadcast_to(positions[:, None, :], to.shape).reshape(-1, 3)
    blocked = RayTracer(scene.vertices, scene.triangles).occluded(
        origins, (to / dist[..., None]).reshape(-1, 3), (dist * (1 - 1e-4)).reshape(-1))
    clear = ~np.asarray(blocked).reshape(len(positions), -1).any(axis=1)
    got = ref_diffuse[..., 0].reshape(len(positions), -1)
    ok = np.isfinite(exact) & (exact > 0) & clear[:, None]
    rel = np.abs(got[ok] - exact[ok]) / exact[ok]
    print(f"  reference check: max-depth-1 diffuse vs exact polygon form factor at {ok.sum()} "
          f"texels of {int(clear.sum())} probes that see the whole emitter above the texel's "
          f"horizon: {100 * rel.mean():.3f} % mean, {100 * rel.max():.3f} % worst texel")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--_bake", help=argparse.SUPPRESS)
    p.add_argument("--quick", action="store_true", help="faces 16, fewer reference samples")
    p.add_argument("--repo", type=Path, default=REPO, help="checkout whose bake is measured")
    p.add_argument("--cache", type=Path,
                   default=Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
                   / "probegrid-bench" / "mitsuba")
    p.add_argument("--grid", default="3x3x3")
    p.add_argument("--face-size", type=int, default=None)
    p.add_argument("--samples", type=int, default=1, help="probegrid rays per texel")
    p.add_argument("--bounces", default="converge",
                   help="probegrid --bounces (default converge, where the checkout has it)")
    p.add_argument("--gather-depth", type=int, default=None,
                   help="probegrid --gather-depth (default: the checkout's)")
    p.add_argument("--fallback-bounces", type=int, default=8,
                   help="bounces when the checkout has no 'converge' (default 8)")
    p.add_argument("--ref-spp", type=int, default=None, help="reference samples per pixel")
    p.add_argument("--direct-spp", type=int, default=None)
    p.add_argument("--direct-depth", type=int, default=1,
                   help="Mitsuba max depth matching probegrid's --bounces 0 (1: emitters seen)")
    p.add_argument("--no-direct", dest="direct", action="store_false")
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--final-gather", type=int, default=None,
                   help="BakeSettings.final_gather: rays per texel read from the surface cache")
    p.add_argument("--scene", choices=["cornell", "room", "both"], default="both")
    p.add_argument("--no-punctual", action="store_true",
                   help="leave the scenes' punctual lights out (the room lit by its sky and "
                        "panel: the sampled light alone)")
    p.add_argument("--seed", type=int, default=None,
                   help="the bake's seed (default: BakeSettings' own): the error's spread")
    args = p.parse_args(argv)
    if args._bake:
        _bake_main(args._bake)
        return
    if args.bounces != "converge":
        try:
            args.bounces = int(args.bounces)
        except ValueError:
            p.error(f"--bounces must be 'converge' or an integer, got {args.bounces!r}")
    args.repo = args.repo.resolve()
    if not (args.repo / "probegrid").is_dir():
        p.error(f"--repo {args.repo} is not a probegrid checkout")
    args.face_size = args.face_size or (16 if args.quick else 32)
    args.ref_spp = args.ref_spp or (64 if args.quick else 256)
    args.direct_spp = args.direct_spp or (64 if args.quick else 512)
    cornell = SHARED / "gltf" / "CornellBox.glb"
    if args.scene != "room" and not cornell.exists():
        p.error(f"{cornell} not found (the test inputs live in tests/data)")
    try:
        import mitsuba  # noqa: F401
    except ImportError:
        p.error("needs Mitsuba 3: pip install mitsuba (or pip install -e '.[bench]')")
    sys.path.insert(0, str(HERE))
    import mitsuba_reference as mr

    t0 = time.perf_counter()
    print("orientation check (lopsided environment, off-axis emitter):",
          {k: round(v, 4) for k, v in mr.check_orientation().items()})
    print(f"furnace check (closed box, Le / (1 - rho)): {100 * mr.check_furnace():.2f} %")
    results = []
    with tempfile.TemporaryDirectory(prefix="pg-bench-acc-") as tmp:
        if args.scene in ("cornell", "both"):
            results.append(bench_scene("cornell", cornell, None, args, Path(tmp)))
        if args.scene in ("room", "both"):
            results.append(bench_scene("room", REPO / "data" / "sample_room.glb",
                                       REPO / "data" / "sample_sky.hdr", args, Path(tmp)))
    print("\nsummary (diffuse irradiance/pi, relative L1 per probe; ratios probegrid / Mitsuba)")
    print(f"{'scene':8} {'probes':>7} {'pg mean':>8} {'pg worst':>9} {'ref noise':>9} "
          f"{'direct':>15} {'bake s':>7} {'mi spp':>6} {'mi mean':>8} {'mi worst':>9} "
          f"{'ratio mean':>10} {'ratio worst':>11}")
    for r in results:
        direct = (f"{100 * np.nanmean(r['err0']):5.2f}/{100 * np.nanmax(r['err0']):5.2f} %"
                  if "err0" in r else "-")
        print(f"{r['label']:8} {r['valid']:>3}/{r['probes']:<3} {100 * r['err'].mean():7.2f}% "
              f"{100 * r['err'].max():8.2f}% {100 * r['noise'].mean():8.2f}% {direct:>15} "
              f"{r['bake_seconds']:7.2f} {r['eq_spp']:6d} {100 * r['eq_err'].mean():7.2f}% "
              f"{100 * r['eq_err'].max():8.2f}% {r['err'].mean() / r['eq_err'].mean():10.2f} "
              f"{r['err'].max() / r['eq_err'].max():11.2f}")
    print("\nper probe (diffuse error %: probegrid converged | Mitsuba equal time | "
          "probegrid direct view)")
    for r in results:
        for i, (q, e, m) in enumerate(zip(r["positions"], r["err"], r["eq_err"], strict=True)):
            e0 = f"{100 * r['err0'][i]:6.2f}" if "err0" in r and i < len(r["err0"]) else "     -"
            print(f"  {r['label']:8} {i:2d} ({q[0]:9.3f} {q[1]:9.3f} {q[2]:9.3f}) "
                  f"{100 * e:6.2f} | {100 * m:6.2f} | {e0}")
    print(f"\ntotal {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
