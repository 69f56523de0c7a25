"""Bake throughput against the physical limit: raw embreex on the bake's own rays, same run.

1. Distinct-ray efficiency: bakes a 4x3x4 grid (32^2 faces, the bundled sky)
   in this process while recording every ray batch the bake hands to Embree (classification,
   primary rays, shadow rays toward the punctual lights and the emitters, the probes' rays
   toward the lights and emitter pieces), drops repeated rays (bit for bit) to keep the bake's
   *distinct* rays, casts each of them once through ``embreex`` directly (float32 arrays,
   ``INTERSECT`` / ``OCCLUDED``), and divides that CPU time by the CPU time of the same bake run
   again uninstrumented. Both are CPU times of this process, so a busy machine changes them
   less than wall time, and both are the best of 3 runs, taken in turns (bake, casts, bake,
   casts, ...): a slow spell of this shared machine (one timed bake of the same code varied
   by up to 15 % from run to run here) then slows both alike, where timing the 3 bakes first
   and the casts after compared one spell with another. Two scenes (the bundled room, 44
   triangles, and the same room with a
   327,680-triangle sculpture), 1 and 4 rays per texel, 2 bounces and ``converge``; and the
   converged bake's time over the 2-bounce bake's. A third run of each bake times its compiled
   kernels and filter products alone (:class:`KernelClock`): ``raw / (raw + kernels)`` bounds
   what any implementation of the same estimator could reach, glue-free.
2. Probes per second for the sample scene with 1 and 2 local worker processes, for two grid
   sizes (time should grow linearly in probes and fall with workers), and the peak memory of
   the workers.
3. Worker memory and the records' disk use for 16x8x16 and 32x16x32 grids at 16^2 faces:
   memory bounded by a batch per worker, not by the grid (the per-hit records are per-block
   work files, the grid's per-probe data is memory-mapped).

Run: ``.venv/bin/python benchmarks/bench_bake.py`` (``--part N`` runs one part).
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from typing import Self

from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from probegrid import raytrace
from probegrid.bake.driver import BakeSettings, bake
from probegrid.bake.environment import Environment
from probegrid.bake.executors import InlineExecutor, LocalExecutor
from probegrid.bake.placement import grid_for
from probegrid.jobs.bake import load_environment
from probegrid.raytrace.kernels import embree_rays
from probegrid.scene import Material, Scene, load_gltf

SCENE = REPO / "data" / "sample_room.glb"
SKY = REPO / "data" / "sample_sky.hdr"


class Recorder:
    """Wraps RayTracer.intersect / occluded / occluded_rays to keep every batch (float32, as
    Embree sees it)."""

    def __init__(self) -> None:
        self.batches: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = []
        self._orig = (raytrace.RayTracer.intersect, raytrace.RayTracer.occluded,
                      raytrace.RayTracer.occluded_rays)

    def __enter__(self) -> Self:
        rec = self
        intersect, occluded, occluded_rays = self._orig

        def rec_intersect(tr, origins, directions, *, tmin=0.0, tmax=np.inf):
            rec._keep("intersect", tr, origins, directions, tmin, tmax)
            return intersect(tr, origins, directions, tmin=tmin, tmax=tmax)

        def rec_occluded(tr, origins, directions, tmax, *, tmin=0.0):
            rec._keep("occluded", tr, origins, directions, tmin, tmax)
            return occluded(tr, origins, directions, tmax, tmin=tmin)

        def rec_occluded_rays(tr, rays, ok=True):  # already as Embree takes them: kept as is
            rec.batches.append(("occluded", rays.origins.copy(), rays.directions.copy(),
                                rays.lengths.copy()))
            return occluded_rays(tr, rays, ok)

        raytrace.RayTracer.intersect = rec_intersect  # type: ignore[method-assign]
        raytrace.RayTracer.occluded = rec_occluded  # type: ignore[method-assign]
        raytrace.RayTracer.occluded_rays = rec_occluded_rays  # type: ignore[method-assign]
        return self

    def __exit__(self, *exc: object) -> None:
        (raytrace.RayTracer.intersect, raytrace.RayTracer.occluded,  # type: ignore
         raytrace.RayTracer.occluded_rays) = self._orig  # type: ignore

    def _keep(self, kind, tr, origins, directions, tmin, tmax) -> None:
        """The batch as the tracer hands it to Embree (raytrace.kernels.embree_rays: the same
        bits)."""
        _, o, d, lo, hi = tr._rays(origins, directions, tmin, tmax)
        org, d32, far, _ = embree_rays(o, d, lo.reshape(-1), hi.reshape(-1), tr.centre)
        self.batches.append((kind, org, d32, far))

    @property
    def rays(self) -> int:
        return sum(len(b[1]) for b in self.batches)


class KernelClock:
    """Times every call of the compiled kernels (numba dispatchers) the bake's modules hold, and
    the filter's matrix products: the estimator's arithmetic, as opposed to the Python and
    numpy work around it. With the raw Embree time it bounds the efficiency that any
    implementation of the same estimator, with no other work at all, could reach."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self._undo: list[tuple[object, str, object]] = []

    def __enter__(self) -> Self:
        from numba.core.registry import CPUDispatcher

        from probegrid.core import probefilter

        clock = self
        for name, mod in list(sys.modules.items()):
            if not name.startswith("probegrid") or mod is None:
                continue
            for attr, fn in list(vars(mod).items()):
                if isinstance(fn, CPUDispatcher) or fn is probefilter.filter_cube:
                    def timed(*a, _fn=fn, **k):
                        t = time.process_time()
                        try:
                            return _fn(*a, **k)
                        finally:
                            clock.seconds += time.process_time() - t
                    setattr(mod, attr, timed)
                    self._undo.append((mod, attr, fn))
        return self

    def __exit__(self, *exc: object) -> None:
        for mod, attr, fn in reversed(self._undo):
            setattr(mod, attr, fn)


def embree_scene(scene: Scene) -> rtcore_scene.EmbreeScene:
    """The scene in embreex alone (float32 vertices re-centred as the tracer's)."""
    centre = 0.5 * (scene.vertices.min(0) + scene.vertices.max(0))
    es = rtcore_scene.EmbreeScene()
    TriangleMesh(scene=es, vertices=(scene.vertices - centre).astype(np.float32),
                 indices=scene.triangles.astype(np.int32))
    return es


def raw_embree_seconds(es: rtcore_scene.EmbreeScene, batches, chunk: int = 1 << 16) -> float:
    """CPU time to cast the recorded batches once with embreex alone, into
    :func:`embree_scene` (the caller takes the best of its runs)."""
    t = time.process_time()
    for kind, org, d, far in batches:
        for s in range(0, len(d), chunk):
            dist = far[s:s + chunk].copy()
            if kind == "intersect":
                es.run(org[s:s + chunk], d[s:s + chunk], dists=dist, output=1)
            else:
                es.run(org[s:s + chunk], d[s:s + chunk], dists=dist, query="OCCLUDED")
    return time.process_time() - t


class DescendantMemory:
    """Samples the memory of this process's descendants (the worker processes, which forkserver
    starts as grandchildren) from /proc every 0.1 s; keeps the largest seen: resident memory
    (``VmRSS``, which counts the pages of memory-mapped files a worker has touched) and private
    memory (``RssAnon``: what the worker alone holds)."""

    def __init__(self) -> None:
        self.peak_mb = 0.0
        self.peak_private_mb = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        me = os.getpid()
        while not self._stop.wait(0.1):
            parents: dict[int, int] = {}
            mem: dict[int, tuple[float, float]] = {}
            for entry in os.listdir("/proc"):
                if not entry.isdigit():
                    continue
                try:
                    with open(f"/proc/{entry}/stat") as fh:
                        parents[int(entry)] = int(fh.read().rsplit(")", 1)[1].split()[1])
                    rss = anon = 0.0
                    with open(f"/proc/{entry}/status") as fh:
                        for line in fh:
                            if line.startswith("VmRSS:"):
                                rss = int(line.split()[1]) / 1024
                            elif line.startswith("RssAnon:"):
                                anon = int(line.split()[1]) / 1024
                    mem[int(entry)] = (rss, anon)
                except (OSError, ValueError, IndexError):
                    continue
            for pid, (rss, anon) in mem.items():
                p, depth = pid, 0
                while p in parents and p != me and depth < 8:
                    p, depth = parents[p], depth + 1
                if p == me and pid != me:
                    self.peak_mb = max(self.peak_mb, rss)
                    self.peak_private_mb = max(self.peak_private_mb, anon)


def detailed_scene(scene: Scene, subdivisions: int = 7) -> Scene:
    """The sample room with a bumpy sculpture (an icosphere of ``20 4^subdivisions`` triangles,
    radius 0.45 m, displaced by a few centimetres) on the floor: a scene whose rays cost Embree
    what rays of a detailed real scene do, unlike the 44 triangles of the bare room."""
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.45)
    v = np.asarray(ball.vertices, dtype=np.float64)
    bump = 1.0 + 0.06 * np.sin(9.0 * v[:, 0]) * np.sin(11.0 * v[:, 1]) * np.sin(7.0 * v[:, 2])
    lo, hi = scene.bounds
    centre = np.array([0.5 * (lo[0] + hi[0]) + 0.3, lo[1] + 0.5, 0.5 * (lo[2] + hi[2]) - 0.2])
    v = v * bump[:, None] + centre
    t = np.asarray(ball.faces, dtype=np.int64) + len(scene.vertices)
    stone = len(scene.materials)
    return Scene(
        vertices=np.concatenate([scene.vertices, v]),
        triangles=np.concatenate([scene.triangles, t]),
        material=np.concatenate([scene.material, np.full(len(t), stone)]),
        materials=(*scene.materials, Material.diffuse(0.6)),
        uvs=None if scene.uvs is None else np.concatenate([scene.uvs, np.zeros((len(v), 2))]),
        colors=None if scene.colors is None else np.concatenate(
            [scene.colors, np.ones((len(v), scene.colors.shape[1]))]),
        lights=scene.lights,
        name="sample room + sculpture",
    )


def main(argv: list[str] | None = None) -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--part", type=int, action="append", choices=(1, 2, 3),
                    help="run only this part (repeatable); all three by default")
    ap.add_argument("--memory-grids", default="16x8x16,32x16x32",
                    help="grids of part 3 (comma-separated)")
    args = ap.parse_args(argv)
    parts = set(args.part or (1, 2, 3))
    scene = load_gltf(SCENE)
    env = load_environment(SKY)
    tmp = Path(tempfile.mkdtemp(prefix="bench-bake-"))
    try:
        if 1 in parts:
            part_throughput(scene, env, tmp)
        if 2 in parts:
            part_probes_per_second(scene, env, tmp)
        if 3 in parts:
            part_memory(scene, env, tmp, tuple(args.memory_grids.split(",")))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def distinct_batches(batches: list) -> tuple[list, int, int]:
    """The recorded rays with every repeat dropped (same query, origin, direction and length,
    bit for bit): the bake's distinct rays, as one batch per query kind. Returns them, their
    count and the count of rays the bake cast."""
    out, total, kept = [], 0, 0
    for kind in ("intersect", "occluded"):
        parts = [b for b in batches if b[0] == kind]
        if not parts:
            continue
        org = np.concatenate([b[1] for b in parts])
        d = np.concatenate([b[2] for b in parts])
        far = np.concatenate([b[3] for b in parts])
        key = np.ascontiguousarray(np.concatenate([org, d, far[:, None]], axis=1))
        rows = key.view(np.dtype((np.void, key.dtype.itemsize * 7))).reshape(-1)
        _, first = np.unique(rows, return_index=True)
        first.sort()
        total += len(rows)
        kept += len(first)
        out.append((kind, org[first], d[first], far[first]))
    return out, kept, total


def save_batches(batches: list, path: Path) -> None:
    """:func:`distinct_batches`' rays into the directory ``path`` (one ``.npy`` per array)."""
    path.mkdir(parents=True, exist_ok=True)
    for kind, org, d, far in batches:
        for name, a in (("org", org), ("dir", d), ("far", far)):
            np.save(path / f"{kind}.{name}.npy", a)


def load_batches(path: Path) -> list:
    """The rays :func:`save_batches` wrote, read whole into memory (not mapped: the casts
    timed must not page them in)."""
    return [(kind, *(np.load(path / f"{kind}.{name}.npy") for name in ("org", "dir", "far")))
            for kind in ("intersect", "occluded") if (path / f"{kind}.org.npy").is_file()]


def part_throughput(scene: Scene, env: Environment, tmp: Path) -> None:
    """Part 1: distinct-ray efficiency: the time raw embreex needs for the
    bake's distinct rays, each cast once, over the bake's CPU time."""
    print("1. distinct-ray efficiency: raw embreex time for the bake's distinct rays / bake CPU")
    print("   time, each the best of 3 runs (1 process; grid 4x3x4, 32^2 faces, the bundled")
    print("   sky; targets: >= 0.3 sample room at 1 ray/texel and 2 bounces, >= 0.4 with the")
    print("   sculpture or 4 rays/texel)")
    print("   (kernels s: CPU time inside the compiled kernels and the filter's matrix products,"
          " the\n   estimator's arithmetic; bound = raw / (raw + kernels): the efficiency of this"
          " estimator\n   with no other work at all)")
    print("   scene                     triangles spp bounces  reached  distinct rays (cast)"
          "  bake CPU s  raw s  efficiency  kernels s  bound")
    scenes = [("sample room", scene), ("sample room + sculpture", detailed_scene(scene))]
    times: dict[tuple[str, int, str], float] = {}
    for label, sc in scenes:
        grid = grid_for(scene, grid="4x3x4")
        # warm-up: numba kernels loaded, the BVH's first traversals
        bake(sc, grid, tmp / f"warm{len(label)}.probes",
             settings=BakeSettings(face_size=8, bounces=1), environment=env,
             executor=InlineExecutor(check_pickle=False))
        for samples in (1, 4):
            for bounces in (2, "converge"):
                st = BakeSettings(face_size=32, bounces=bounces, samples=samples)
                run = InlineExecutor(check_pickle=False)
                tag = f"{samples}{bounces}{len(label)}"
                with Recorder() as rec:  # the rays first (recording costs time: not timed)
                    bake(sc, grid, tmp / f"r{tag}.probes", settings=st, environment=env,
                         executor=run)
                batches, distinct, total = distinct_batches(rec.batches)
                del rec
                rays = tmp / f"rays{tag}"
                save_batches(batches, rays)
                del batches
                # the bake, timed, uninstrumented, and the raw casts of its rays, each the best
                # of 3, interleaved: a slow spell of this shared machine slows both alike. The
                # bake runs while this process holds none of the rays (gigabytes at 4
                # rays/texel), as a bake's own process would not; they are read back after it
                cpu, t_raw = np.inf, np.inf
                es = embree_scene(sc)  # (built once, as the bake's tracer is)
                for _ in range(3):
                    c = time.process_time()
                    rep = bake(sc, grid, tmp / f"a{tag}.probes", settings=st, environment=env,
                               executor=run, overwrite=True)
                    cpu = min(cpu, time.process_time() - c)
                    batches = load_batches(rays)
                    t_raw = min(t_raw, raw_embree_seconds(es, batches))
                    del batches
                del es
                shutil.rmtree(rays, ignore_errors=True)
                with KernelClock() as kc:  # the same bake again, its kernels timed
                    bake(sc, grid, tmp / f"k{tag}.probes", settings=st, environment=env,
                         executor=run)
                times[(label, samples, str(bounces))] = cpu
                print(f"   {label:<25} {sc.n_triangles:9,d} {samples:3d} {bounces!s:>8} "
                      f"{rep.quality['bounces']:8d}  {distinct / 1e6:7.2f} M ({total / 1e6:5.2f} M)"
                      f"  {cpu:10.2f} {t_raw:6.2f}  {t_raw / cpu:10.3f}  {kc.seconds:9.2f}"
                      f"  {t_raw / (t_raw + kc.seconds):5.3f}")
    print("\n   converged bake / 2-bounce bake, CPU time (target <= 1.5):")
    for label, _ in scenes:
        for samples in (1, 4):
            r = times[(label, samples, "converge")] / times[(label, samples, "2")]
            print(f"   {label:<25} {samples} ray(s)/texel: {r:.2f}")


def part_probes_per_second(scene: Scene, env: Environment, tmp: Path) -> None:
    """Part 2: probes per second for 1 and 2 workers and two grid sizes."""
    print("\n2. probes per second, sample room, 32^2 faces, 2 bounces, 1 ray per texel")
    print("   grid      probes  workers   seconds  probes/s  largest worker: resident, private")
    st = BakeSettings(face_size=32, bounces=2)
    rows = []
    for label in ("4x2x4", "8x4x8"):
        g = grid_for(scene, grid=label)
        for workers in (1, 2):
            out = tmp / f"{label}-{workers}.probes"
            with LocalExecutor(workers) as ex, DescendantMemory() as mem:
                t = time.perf_counter()
                bake(scene, g, out, settings=st, environment=env, executor=ex)
                sec = time.perf_counter() - t
            rows.append((label, g.n_probes, workers, sec))
            print(f"   {label:<9} {g.n_probes:6d}  {workers:7d}  {sec:8.2f}  "
                  f"{g.n_probes / sec:8.2f}  {mem.peak_mb:8.0f} MB, "
                  f"{mem.peak_private_mb:4.0f} MB")
    small = {w: s for lab, _, w, s in rows if lab == "4x2x4"}
    big = {w: s for lab, _, w, s in rows if lab == "8x4x8"}
    print(f"   time ratio 8x4x8 / 4x2x4 (8x the probes): 1 worker {big[1] / small[1]:.2f}, "
          f"2 workers {big[2] / small[2]:.2f}")
    print(f"   speed-up 2 workers / 1 worker: {small[1] / small[2]:.2f} (4x2x4), "
          f"{big[1] / big[2]:.2f} (8x4x8)")
    est = 2048 / (256 / big[2])
    print(f"   16x8x16 (2048 probes) at the 2-worker rate: about {est:.0f} s")


def part_memory(scene: Scene, env: Environment, tmp: Path, grids: tuple[str, ...]) -> None:
    """Part 3: worker memory against grid size: bounded by the batch, not the grid (records in
    per-block work files, the grid's per-probe data memory-mapped)."""
    print("\n3. worker memory against grid size (16^2 faces, 2 bounces, 2 workers)")
    print("   grid        probes   seconds  largest worker: resident, private   records on disk")
    st = BakeSettings(face_size=16, bounces=2)
    for label in grids:
        g = grid_for(scene, grid=label)
        out = tmp / f"m{label}.probes"
        peak_disk = [0]
        stop = threading.Event()

        def watch(out: Path = out, peak: list[int] = peak_disk,
                  stop: threading.Event = stop) -> None:
            work = out.with_name(out.name + ".work") / "records"
            while not stop.wait(0.5):
                try:
                    size = sum(f.stat().st_size for f in work.rglob("*.npy"))
                except OSError:
                    continue
                peak[0] = max(peak[0], size)

        th = threading.Thread(target=watch, daemon=True)
        th.start()
        with LocalExecutor(2) as ex, DescendantMemory() as mem:
            t = time.perf_counter()
            bake(scene, g, out, settings=st, environment=env, executor=ex)
            sec = time.perf_counter() - t
        stop.set()
        th.join()
        print(f"   {label:<10} {g.n_probes:7d}  {sec:8.2f}  {mem.peak_mb:8.0f} MB, "
              f"{mem.peak_private_mb:4.0f} MB {peak_disk[0] / 2**20:14.0f} MB")
        shutil.rmtree(out, ignore_errors=True)
    print("   (resident memory includes the pages of memory-mapped files a worker has read; "
          "private memory is what it holds alone)")


if __name__ == "__main__":
    main()
