"""Maps at query points between probes against a path tracer (Mitsuba 3), and their latency.

A user of the service asks for the maps at the position of a moving object, which is almost
never a probe. This benchmark bakes a grid, picks query points of four kinds -- **free** space
(farther than 15 % of the scene's largest extent from every surface), **near wall** and **near box**
(5-10 cm off the front of a wall of the scene's bounding box, or of any other surface, in a
4 m room: 1.25-2.5 % of the scene's largest extent), **corner** (that far off two walls of an edge of the
bounding box) -- checks each with rays (no back face seen: not inside a solid), renders the
incoming cube there with Mitsuba 3 (:mod:`mitsuba_reference`, variant ``scalar_rgb``, max depth
64, two independent halves whose difference is printed as the reference's noise), and prints per
kind the mean and worst error over the points of:

* ``/maps/diffuse``: relative L1 over the diffuse map (irradiance / pi, the store's size) against
  ``diffuse_exact`` of the reference (plus the punctual lights' direct light, which no camera
  ray sees: :meth:`mitsuba_reference.MitsubaReference.punctual_diffuse`);
* ``/maps/specular`` level 0 (the mirror level): relative L1 of both cubes averaged over 4x4
  texel blocks (the reference with the visible punctual lights splatted as the bake does,
  :func:`probegrid.core.lights.splat_delta`);
* every GGX level against the reference filtered by the bake's filter, next to the same error of
  the store's own probes nearest the points (against references rendered there);
* ``E(n)`` from ``/sh``: the irradiance of the answer's SH toward a normal (the surface's off which
  the point stands; +Y in free space) against that of the SH of the reference cube,
  ``sum |E - E_ref| / sum E_ref`` over RGB;

for each method: ``blend`` (the service's blend of the surrounding probes, weights without a
normal for the maps and with it for the SH, as a client gives them), ``nearest`` (the nearest
valid probe's maps) and ``trace`` (:class:`probegrid.bake.point.PointTracer`: a probe traced at
the point against the stored grid and its surface light cache, ``--quality`` its preset; its SH
is the projection of the traced cube). Queries go through :class:`probegrid.query.ProbeField`,
the service's code. Latency: median milliseconds per answer at the store's face size
(``trace``: one uncached point, every map of it); then cold traced answers at
``--latency-points`` distinct points for each preset of ``--latency-quality``, in process and
over HTTP (:func:`latency`: median wall, CPU per answer, cores used, the machine's load).
A (re)bake prints the cost of its surface cache against the rest of the bake.

Scenes: the shared ``CornellBox.glb`` (an emissive ceiling panel; 4x4x4 probes) and the bundled
sample room (``data/sample_room.glb``, its point light without its glTF range, as both tools
bake it, and ``data/sample_sky.hdr``; ``--room-grid``, 8x6x8 by default). Converged defaults,
face 32. Bakes and references are cached under ``--cache`` (default
``~/.cache/probegrid-bench/query``), keyed by content; ``--rebake`` bakes again (after a change
of the bake). ``--trace-gather`` / ``--trace-depth`` / ``--trace-lights`` trace points with
fewer gather rays, gather levels or light samples than the bake's (the accuracy/latency
trade-off). Run::

    .venv/bin/pip install mitsuba
    .venv/bin/python benchmarks/bench_query_accuracy.py [--points 16] [--scenes cornell,room]
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
SHARED = REPO.parent / "shared" / "data"
sys.path.insert(0, str(HERE))

KINDS = ("free", "near wall", "near box", "corner")
METHODS = ("blend", "nearest", "trace")


# ------------------------------------------------------------------------------ query points
def _walls(scene: Any) -> NDArray[np.bool_]:
    """Triangles lying on a plane of the scene's bounding box."""
    v = np.asarray(scene.vertices, np.float64)[np.asarray(scene.triangles)]  # (T, 3, 3)
    lo, hi = np.asarray(scene.bounds, np.float64)
    tol = 1e-4 * float(np.max(hi - lo))
    on = np.zeros(len(v), bool)
    for a in range(3):
        on |= np.all(np.abs(v[:, :, a] - lo[a]) < tol, axis=1)
        on |= np.all(np.abs(v[:, :, a] - hi[a]) < tol, axis=1)
    return on


def _surroundings(tracer: Any, scene: Any, points: NDArray[np.float64], walls: NDArray[np.bool_]
                  ) -> tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64],
                             NDArray[np.float64]]:
    """Per point: inside a solid (a back face seen), distance to the nearest wall and to the
    nearest other surface, from 6 x 12^2 rays each."""
    from probegrid.core.cubemap import texel_directions

    d = texel_directions(12).reshape(-1, 3)
    k = len(d)
    org = np.repeat(points, k, axis=0)
    dirs = np.tile(d, (len(points), 1))
    hits = tracer.intersect(org, dirs)
    prim = hits.prim_id.reshape(len(points), k)
    t = hits.t.reshape(len(points), k)
    v = np.asarray(scene.vertices, np.float64)[np.asarray(scene.triangles)]
    nrm = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    double = np.asarray(scene.double_sided, bool)
    hit = prim >= 0
    back = hit & (np.einsum("pkc,pkc->pk", nrm[np.maximum(prim, 0)], dirs.reshape(
        len(points), k, 3)) > 0) & ~double[np.maximum(prim, 0)]
    # a back face seen, or enclosed (every ray hits within half the scene's extent: inside a
    # closed double-sided solid)
    lo, hi = np.asarray(scene.bounds, np.float64)
    inside = back.any(axis=1) | (np.where(hit, t, np.inf).max(axis=1)
                                 < 0.5 * float(np.max(hi - lo)))
    is_wall = hit & walls[np.maximum(prim, 0)]
    # the distance to a plane from the rays' hits: t * |cos| is the distance along the normal
    cos = np.abs(np.einsum("pkc,pkc->pk", nrm[np.maximum(prim, 0)],
                           dirs.reshape(len(points), k, 3)))
    dist = np.where(hit, t * cos, np.inf)
    wall_d = np.where(is_wall, dist, np.inf).min(axis=1)
    other_d = np.where(hit & ~is_wall, dist, np.inf).min(axis=1)
    return inside, wall_d, other_d, nrm


def query_points(scene: Any, per_kind: int, seed: int = 0
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64], list[str]]:
    """``per_kind`` points of each kind (module docstring), their normals and kinds."""
    from probegrid.raytrace import RayTracer

    tracer = RayTracer.from_scene(scene)
    lo, hi = np.asarray(scene.bounds, np.float64)
    ext = float(np.max(hi - lo))
    near_lo, near_hi = 0.0125 * ext, 0.025 * ext
    walls = _walls(scene)
    v = np.asarray(scene.vertices, np.float64)[np.asarray(scene.triangles)]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    out_p: list[NDArray[np.float64]] = []
    out_n: list[NDArray[np.float64]] = []
    out_k: list[str] = []
    for kind in KINDS:
        got = 0
        for _ in range(200):  # rounds of candidates until the kind has its points
            m = 256
            if kind == "free":
                cand = lo + rng.random((m, 3)) * (hi - lo)
                nrm = np.tile([0.0, 1.0, 0.0], (m, 1))
            elif kind in ("near wall", "near box"):
                pool = np.flatnonzero(walls if kind == "near wall" else ~walls)
                tri = rng.choice(pool, size=m, p=area[pool] / area[pool].sum())
                a, b = rng.random((2, m, 1))
                flip = (a + b) > 1
                a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
                pts = v[tri, 0] + a * (v[tri, 1] - v[tri, 0]) + b * (v[tri, 2] - v[tri, 0])
                n = np.cross(v[tri, 1] - v[tri, 0], v[tri, 2] - v[tri, 0])
                n /= np.linalg.norm(n, axis=1, keepdims=True)
                nrm = n  # the front (glTF winding: into the room, out of a box)
                cand = pts + nrm * rng.uniform(near_lo, near_hi, (m, 1))
            else:  # corner: off two walls of an edge of the bounding box
                axis = rng.integers(0, 3, m)
                cand = np.empty((m, 3))
                nrm = np.zeros((m, 3))
                for j in range(m):  # loop over candidates (a few hundred)
                    a = axis[j]
                    others = [c for c in range(3) if c != a]
                    p = np.empty(3)
                    p[a] = lo[a] + rng.uniform(0.1, 0.9) * (hi[a] - lo[a])
                    for c in others:
                        at_lo = rng.random() < 0.5
                        off = rng.uniform(near_lo, near_hi)
                        p[c] = lo[c] + off if at_lo else hi[c] - off
                    c0 = others[0]
                    nrm[j, c0] = 1.0 if p[c0] < 0.5 * (lo[c0] + hi[c0]) else -1.0
                    cand[j] = p
            inside, wall_d, other_d, _ = _surroundings(tracer, scene, cand, walls)
            near = (near_lo * 0.9, near_hi * 1.1)
            if kind == "free":
                ok = np.minimum(wall_d, other_d) > 0.15 * ext
            elif kind == "near wall":
                ok = (wall_d >= near[0]) & (wall_d <= near[1]) & (other_d > near[1])
            elif kind == "near box":
                ok = (other_d >= near[0]) & (other_d <= near[1]) & (wall_d > near[1])
            else:
                ok = (wall_d >= near[0]) & (wall_d <= near[1]) & (other_d > near[1])
            ok &= ~inside & np.all((cand > lo) & (cand < hi), axis=1)
            for j in np.flatnonzero(ok)[: per_kind - got]:
                out_p.append(cand[j])
                out_n.append(nrm[j])
                out_k.append(kind)
                got += 1
            if got >= per_kind:
                break
    return np.array(out_p), np.array(out_n), out_k


# ------------------------------------------------------------------------------ figures
def block4(cubes: NDArray) -> NDArray[np.float64]:
    """Cubes ``(..., 6, n, n, 3)`` averaged over 4x4 texel blocks."""
    a = np.asarray(cubes, np.float64)
    *lead, f, n, _, c = a.shape
    return a.reshape(*lead, f, n // 4, 4, n // 4, 4, c).mean(axis=(-4, -2))


def relative_l1(a: NDArray, b: NDArray) -> float:
    """``sum dOmega |a - b| / sum dOmega b`` of two cubes ``(6, n, n, 3)``."""
    from probegrid.core.cubemap import texel_solid_angles

    w = texel_solid_angles(a.shape[1])[..., None]
    return float((w * np.abs(np.asarray(a, np.float64) - b)).sum()
                 / max(float((w * np.asarray(b, np.float64)).sum()), 1e-300))


def irradiance_error(sh_a: NDArray, sh_ref: NDArray, normal: NDArray) -> float:
    from probegrid.core.sh.clampedcosine import irradiance

    e = irradiance(np.asarray(sh_a, np.float64), normal[None])[0]
    r = irradiance(np.asarray(sh_ref, np.float64), normal[None])[0]
    return float(np.abs(e - r).sum() / max(float(np.abs(r).sum()), 1e-300))


def splat_lights(cubes: NDArray, scene: Any, points: NDArray[np.float64]) -> NDArray[np.float32]:
    """Reference cubes with the punctual lights each point sees splatted in (1/d^2 falloff)."""
    from probegrid.core.lights import PointLight, splat_delta
    from probegrid.raytrace import RayTracer

    if not scene.lights:
        return np.asarray(cubes, np.float32)
    tracer = RayTracer.from_scene(scene)
    out = np.array(cubes, np.float32)
    for i, p in enumerate(points):  # a loop over points and lights (a few)
        dirs, irr = [], []
        for lt in scene.lights:
            power = np.asarray(lt.color, np.float64) * lt.intensity
            if isinstance(lt, PointLight):
                to = np.asarray(lt.position, np.float64) - p
                dist = float(np.linalg.norm(to))
                if tracer.segments_occluded(p[None], np.asarray(lt.position)[None],
                                            margin=1e-6 * dist)[0]:
                    continue
                dirs.append(to / dist)
                irr.append(power / dist**2)
            else:
                raise SystemExit("splat_lights handles point lights only")
        if dirs:
            out[i] = splat_delta(out[i], np.array(dirs), np.array(irr))
    return out


# ------------------------------------------------------------------------------ bake
def baked_store(cache: Path, label: str, scene: Any, scene_file: Path, env: Any, grid: Any,
                settings: Any, *, rebake: bool, workers: int) -> Path:
    """The store of a bake, from the cache unless ``rebake``."""
    from probegrid.bake import bake
    from probegrid.bake.driver import environment_hash
    from probegrid.bake.executors import make_executor

    key = hashlib.sha256(json.dumps([scene.content_hash(), environment_hash(env),
                                     grid.label, settings.model_dump()], default=str)
                         .encode()).hexdigest()[:16]
    out = cache / "stores" / f"{label}-{key}.probes"
    if out.is_dir() and not rebake:
        from probegrid.query import ProbeField
        from probegrid.store import open_store

        if ProbeField(open_store(out), scene=scene).trace_support() is None:
            print(f"(reusing the bake {out}; --rebake to bake again)")
            return out
    out.parent.mkdir(parents=True, exist_ok=True)
    ex = make_executor(workers=workers)
    try:
        t0 = time.perf_counter()
        report = bake(scene, grid, out, settings=settings, environment=env, executor=ex,
                      overwrite=True, scene_file=scene_file)
        secs = time.perf_counter() - t0
        cache = float(report.quality["stage_seconds"].get("surface cache", 0.0))
        print(f"baked {grid.label} in {secs:.1f} s, of which the surface cache {cache:.1f} s: "
              f"{secs / max(secs - cache, 1e-9):.2f}x the bake without it "
              f"({report.quality.get('surface_cache_rays', 0) / 1e6:.1f} M rays against "
              f"{report.rays / 1e6:.1f} M)")
    finally:
        ex.close()
    return out


# ------------------------------------------------------------------------------ latency
def latency(store_path: Path, points: NDArray[np.float64], quality: str, *, http: bool
            ) -> tuple[float, float, float]:
    """Median wall milliseconds of a cold traced answer (``/maps/specular`` level 0, every map
    of the point traced at once) at each of ``points`` (distinct: no answer is reused), the
    mean CPU milliseconds per answer, and the cores used (CPU over wall). ``http``: through the
    service (``service.main.run``, one uvicorn worker on 127.0.0.1, the store read into memory
    as it serves it; sequential keep-alive requests, the server process's CPU); else in this
    process (``ProbeField.cube_at`` on a store opened as the service opens it)."""
    import psutil

    from probegrid.query import ProbeField
    from probegrid.store import open_store

    if not http:
        field = ProbeField(open_store(store_path, load=True))
        field.cube_at(points[0] + 1e-7, "specular", quality=quality)  # tracer built, warm
        walls, cpu0, w0 = [], time.process_time(), time.perf_counter()
        for p in points:
            t0 = time.perf_counter()
            field.cube_at(p, "specular", quality=quality)
            walls.append(time.perf_counter() - t0)
        cpu, wall = time.process_time() - cpu0, time.perf_counter() - w0
        return 1000 * float(np.median(walls)), 1000 * cpu / len(points), cpu / wall
    import tempfile

    import httpx
    from bench_service import free_port, start_server

    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        proc = start_server([store_path], port, Path(tmp) / "server.log")
        try:
            base = f"http://127.0.0.1:{port}"
            with httpx.Client(base_url=base, timeout=120) as client:
                for _ in range(600):  # until it answers (bounded: a minute)
                    try:
                        if client.get("/healthz").status_code == 200:
                            break
                    except httpx.TransportError:
                        time.sleep(0.1)
                name = client.get("/v1/grids").json()["grids"][0]["name"]

                def get(p: NDArray[np.float64]) -> None:
                    r = client.get(f"/v1/grids/{name}/maps/specular", params={
                        "x": repr(float(p[0])), "y": repr(float(p[1])),
                        "z": repr(float(p[2])), "level": "0", "quality": quality})
                    if r.status_code != 200 or r.headers.get("x-probegrid-method") != "trace":
                        raise SystemExit(f"/maps answered {r.status_code}: {r.text[:200]}")

                get(points[0] + 1e-7)  # the tracer built, its kernels loaded
                server = psutil.Process(proc.pid)
                c0 = sum(server.cpu_times()[:2])
                walls, w0 = [], time.perf_counter()
                for p in points:
                    t0 = time.perf_counter()
                    get(p)
                    walls.append(time.perf_counter() - t0)
                wall = time.perf_counter() - w0
                cpu = sum(server.cpu_times()[:2]) - c0
        finally:
            proc.terminate()
            proc.wait(30)
    return 1000 * float(np.median(walls)), 1000 * cpu / len(points), cpu / wall


# ------------------------------------------------------------------------------ main
def bench_scene(label: str, path: Path, sky: Path | None, grid_label: str,
                args: argparse.Namespace) -> list[tuple[str, str, str, float, float]]:
    import bench_bake_accuracy as bba
    import mitsuba_reference as mr

    from probegrid.bake import BakeSettings
    from probegrid.bake.placement import grid_for
    from probegrid.bake.point import PointSettings
    from probegrid.core import sh
    from probegrid.jobs.bake import load_environment
    from probegrid.query import ProbeField
    from probegrid.scene import load_gltf
    from probegrid.store import open_store

    scene = mr.without_light_ranges(load_gltf(path))
    env = load_environment(sky) if sky else None
    from probegrid.bake.environment import Environment

    grid = grid_for(scene, grid=grid_label)
    settings = BakeSettings(face_size=args.face_size)
    store_path = baked_store(args.cache, label, scene, path, env or Environment(), grid,
                             settings, rebake=args.rebake, workers=args.workers)
    store = open_store(store_path)
    ps = dataclasses.replace(PointSettings.preset(args.quality),
                             gather_samples=args.trace_gather, gather_depth=args.trace_depth,
                             light_samples=args.trace_lights)
    field = ProbeField(store, scene=scene, point_settings=ps)
    why = field.trace_support()
    if why is not None:
        raise SystemExit(f"{label}: {why}")
    per_kind = max(1, args.points // len(KINDS))
    pts, nrms, kinds = query_points(scene, per_kind, seed=args.seed)
    n = args.face_size
    d = int(store.arrays["diffuse"].shape[2])
    print(f"\n== {label}: {path.name}" + (f" + {sky.name}" if sky else "") +
          f", grid {grid.label}, faces {n}^2, {len(pts)} query points "
          f"({', '.join(f'{k}: {kinds.count(k)}' for k in KINDS)})")
    with mr.MitsubaReference(scene, env) as ref:
        a, b, secs = bba.cached_reference(args.cache / "mitsuba", ref, scene, env, pts,
                                          face_size=n, spp=args.ref_spp, max_depth=64)
        cube = 0.5 * (a + b)
        direct = ref.punctual_diffuse(pts, d)
        ref_d = bba.diffuse_of(cube, d) + direct
        noise_d = bba.half_difference(bba.diffuse_of(a, d) + direct,
                                      bba.diffuse_of(b, d) + direct)
        ref_cube = splat_lights(cube, scene, pts)
        noise_s = np.array([relative_l1(block4(x), 0.5 * (block4(x) + block4(y)))
                            for x, y in zip(a, b, strict=True)])
        # probes for the GGX levels' error at a probe: the valid probe nearest each kind's
        # first point
        valid = np.asarray(store.arrays["valid"], bool)
        positions = np.asarray(store.arrays["positions"], np.float64)
        firsts = [kinds.index(k) for k in KINDS if k in kinds]
        at = sorted({int(np.flatnonzero(valid)[np.argmin(np.linalg.norm(
            positions[valid] - pts[i], axis=1))]) for i in firsts})
        pa, pb, _ = bba.cached_reference(args.cache / "mitsuba", ref, scene, env, positions[at],
                                         face_size=n, spp=args.ref_spp, max_depth=64)
        probe_ref = splat_lights(0.5 * (pa + pb), scene, positions[at])
    print(f"reference: Mitsuba path, depth 64, {args.ref_spp} spp ({secs:.0f} s when "
          f"rendered); its noise: diffuse {100 * noise_d.mean():.2f} % mean, mirror (4x4) "
          f"{100 * noise_s.mean():.2f} % mean")
    err: dict[tuple[str, str], list[tuple[float, float, float]]] = {}
    lat: dict[str, list[float]] = {m: [] for m in METHODS}
    cpu: list[float] = []
    sh_ref = [sh.project_cube(c) for c in ref_cube]
    tracer = field.point_tracer()
    levels = field.specular_levels
    chains = {"probe": [], "blend": [], "trace": []}  # per point, per level: the error

    def level_errors(chain, ref_chain) -> list[float]:
        return [relative_l1(block4(c), block4(r)) if c.shape[1] % 4 == 0 and c.shape[1] >= 8
                else relative_l1(c, r) for c, r in zip(chain, ref_chain, strict=True)]

    for j, i in enumerate(at):  # the store's own probes against the reference there
        ref_chain = tracer.filter(probe_ref[j].astype(np.float32)).specular
        own = [np.asarray(store.arrays[f"specular_{k}"][i], np.float32) for k in range(levels)]
        chains["probe"].append(level_errors(own, ref_chain))
    field.point_tracer()  # built (and its kernels loaded) before the timing
    field.point_maps(pts[0] + 1e-9 * np.abs(pts[0]).max())
    for i, (p, nrm, kind) in enumerate(zip(pts, nrms, kinds, strict=True)):
        # blend: the maps without a normal, the SH with it
        t0 = time.perf_counter()
        dif_b, _, _ = field.cube_at(p, "diffuse", method="blend")
        spec_b, _, _ = field.cube_at(p, "specular", method="blend")
        lat["blend"].append((time.perf_counter() - t0) / 2)
        sh_b = field.sh(field.weights(p, normals=nrm))[0]
        t0 = time.perf_counter()
        near = np.flatnonzero(valid)[np.argmin(np.linalg.norm(positions[valid] - p, axis=1))]
        dif_n = np.asarray(store.arrays["diffuse"][near], np.float32)
        spec_n = np.asarray(store.arrays["specular_0"][near], np.float32)
        lat["nearest"].append((time.perf_counter() - t0) / 2)
        sh_n = np.asarray(field.sh_array("deringed")[near], np.float64)
        t0, c0 = time.perf_counter(), time.process_time()
        maps = field.point_maps(p)
        lat["trace"].append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        sh_t = sh.project_cube(maps.incoming)
        ref_chain = tracer.filter(ref_cube[i].astype(np.float32)).specular
        blend_chain = [field.cube_at(p, "specular", level=k, method="blend")[0]
                       for k in range(levels)]
        chains["blend"].append(level_errors(blend_chain, ref_chain))
        chains["trace"].append(level_errors(list(maps.specular), ref_chain))
        for method, dif, spec, shc in (("blend", dif_b, spec_b, sh_b),
                                       ("nearest", dif_n, spec_n, sh_n),
                                       ("trace", maps.diffuse, maps.specular[0], sh_t)):
            err.setdefault((method, kind), []).append((
                relative_l1(dif, ref_d[i]),
                relative_l1(block4(spec), block4(ref_cube[i])),
                irradiance_error(shc, sh_ref[i], nrm)))
    rows = []
    print(f"{'kind':10s} {'method':8s} {'diffuse mean/worst':>20s} {'mirror 4x4 mean/worst':>23s} "
          f"{'E(n) SH mean/worst':>20s}")
    for kind in (*KINDS, "all"):
        for method in METHODS:
            e = np.array([x for (m, k), v in err.items() for x in v
                          if m == method and (k == kind or kind == "all")])
            if not len(e):
                continue
            cells = [f"{100 * e[:, c].mean():7.2f} / {100 * e[:, c].max():6.2f} %"
                     for c in range(3)]
            print(f"{kind:10s} {method:8s} {cells[0]:>20s} {cells[1]:>23s} {cells[2]:>20s}")
            rows.append((label, kind, method, float(e[:, 0].mean()), float(e[:, 1].mean())))
    probe_mean = np.mean(chains["probe"], axis=0)
    print(f"GGX levels (mean error; 4x4 blocks from 8^2 up) at {len(at)} probes, and at the "
          f"query points blended and traced (ratio to the probes'):")
    for k in range(levels):
        b_k = float(np.mean([c[k] for c in chains["blend"]]))
        t_k = float(np.mean([c[k] for c in chains["trace"]]))
        print(f"  level {k}: probes {100 * probe_mean[k]:6.2f} %, blend {100 * b_k:7.2f} % "
              f"({b_k / probe_mean[k]:5.2f}x), trace {100 * t_k:6.2f} % "
              f"({t_k / probe_mean[k]:4.2f}x)")
    print("latency, median ms per answer: " + ", ".join(
        f"{m} {1000 * np.median(lat[m]):.2f}" for m in METHODS) +
        f" (trace: {1000 * np.median(cpu):.1f} ms CPU; gather samples "
        f"{args.trace_gather or 'bake'}, depth {args.trace_depth or 'bake'}, light samples "
        f"{args.trace_lights or 'bake'})")
    if args.latency_points:
        rng = np.random.default_rng(args.seed + 1)
        lo, hi = np.asarray(scene.bounds, np.float64)
        # distinct points, as a moving object's: the query points and points jittered off them
        extra = pts[rng.integers(0, len(pts), args.latency_points)]
        extra = extra + rng.normal(0.0, 0.01, extra.shape) * (hi - lo)
        lat_pts = np.clip(extra, lo + 1e-3 * (hi - lo), hi - 1e-3 * (hi - lo))
        print(f"cold traced answers at {len(lat_pts)} distinct points (median wall ms, CPU ms "
              f"per answer, cores used; load average {os.getloadavg()[0]:.1f} on "
              f"{os.cpu_count()} cores):")
        for q in args.latency_quality.split(","):
            for http in (False, True):
                wall, cpu, cores = latency(store_path, lat_pts, q, http=http)
                print(f"  {q:9s} {'HTTP' if http else 'in process':10s} {wall:7.1f} ms, CPU "
                      f"{cpu:6.1f} ms, {cores:.2f} cores")
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=16, help="query points per scene (4 kinds)")
    ap.add_argument("--scenes", default="cornell,room")
    ap.add_argument("--room-grid", default="8x6x8")
    ap.add_argument("--face-size", type=int, default=32)
    ap.add_argument("--ref-spp", type=int, default=128, help="reference samples per texel")
    ap.add_argument("--quality", default="accurate",
                    help="the traced answer's preset (probegrid.bake.point.POINT_PRESETS)")
    ap.add_argument("--trace-gather", type=int, default=None)
    ap.add_argument("--trace-depth", type=int, default=None)
    ap.add_argument("--trace-lights", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--latency-points", type=int, default=32,
                    help="distinct points of the cold-latency measurement (0: none)")
    ap.add_argument("--latency-quality", default="accurate,fast,reference",
                    help="presets whose latency is measured, in process and over HTTP")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--rebake", action="store_true")
    ap.add_argument("--cache", type=Path,
                    default=Path.home() / ".cache" / "probegrid-bench" / "query")
    args = ap.parse_args(argv)
    scenes = {"cornell": ("cornell", SHARED / "gltf" / "CornellBox.glb", None, "4x4x4"),
              "room": ("room", REPO / "data" / "sample_room.glb", REPO / "data" / "sample_sky.hdr",
                       args.room_grid)}
    for name in args.scenes.split(","):
        bench_scene(*scenes[name], args)


if __name__ == "__main__":
    main()
