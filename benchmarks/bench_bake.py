"""Bake throughput against the physical limit: raw embreex on the same rays, in the same run.

1. Bakes a 4x3x4 grid (32^2 faces, 2 bounces, the bundled sky) in this process while recording
   every ray batch the bake hands to Embree (primary and shadow rays, classification rays
   included), then replays exactly those rays through ``embreex`` directly (float32 arrays, the
   same batches, ``INTERSECT`` / ``OCCLUDED``) and prints both rates and their ratio: the share
   of the bake's time that is ray casting. Two scenes: the bundled room (44 triangles, where a
   ray costs Embree about 75 ns, less than shading its hit) and the same room with a
   327,680-triangle sculpture; 1 and 8 rays per texel (the per-probe filters are amortised over
   more rays at 8). The rays are recorded in one run and the bake is timed in another (recording
   costs time); a third, instrumented run splits the bake's time into ray casting (Embree and
   our argument handling), the indirect lookup at ray hits, the per-probe filters, and the rest.
   From the split it prints the efficiency of the ray casting alone (raw over our casting) and
   two ceilings of the ratio: with the per-probe filters as the bake's only other work, and with
   the filters and the indirect lookup (the two costs the issue's items 3 and 5 require).
2. Probes per second for the sample scene with 1 and 2 local worker processes, for two grid
   sizes (time should grow linearly in probes and fall with workers), and the peak memory of
   the workers.
3. Worker memory for a 32-probe and a 16,384-probe grid: bounded by a batch per worker, not by
   the grid (workers memory-map the previous bounce's grid instead of holding a copy).

Run: ``.venv/bin/python benchmarks/bench_bake.py`` (about 2-4 minutes on 2 cores; ``--part N``
runs one part).
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
from probegrid.jobs.bake import grid_for, load_environment
from probegrid.scene import Material, Scene, load_gltf

SCENE = REPO / "data" / "sample_room.glb"
SKY = REPO / "data" / "sample_sky.hdr"


class Recorder:
    """Wraps RayTracer.intersect / occluded to keep every batch (float32, as Embree sees it)."""

    def __init__(self) -> None:
        self.batches: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = []
        self._orig = (raytrace.RayTracer.intersect, raytrace.RayTracer.occluded)

    def __enter__(self) -> Self:
        rec = self
        intersect, occluded = self._orig

        def rec_intersect(tr, origins, directions, *, tmin=0.0, tmax=np.inf):
            rec._keep("intersect", tr, origins, directions, tmin, tmax)
            return intersect(tr, origins, directions, tmin=tmin, tmax=tmax)

        def rec_occluded(tr, origins, directions, tmax, *, tmin=0.0):
            rec._keep("occluded", tr, origins, directions, tmin, tmax)
            return occluded(tr, origins, directions, tmax, tmin=tmin)

        raytrace.RayTracer.intersect = rec_intersect  # type: ignore[method-assign]
        raytrace.RayTracer.occluded = rec_occluded  # type: ignore[method-assign]
        return self

    def __exit__(self, *exc: object) -> None:
        raytrace.RayTracer.intersect, raytrace.RayTracer.occluded = self._orig  # type: ignore

    def _keep(self, kind, tr, origins, directions, tmin, tmax) -> None:
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        o = np.broadcast_to(np.asarray(origins, np.float64), (*np.shape(directions)[:-1], 3))
        o = o.reshape(-1, 3)
        lo = np.broadcast_to(np.asarray(tmin, np.float64), (len(d),))
        hi = np.broadcast_to(np.asarray(tmax, np.float64), (len(d),))
        org = (o + lo[:, None] * d - tr._centre).astype(np.float32)
        far = (hi - lo).astype(np.float32)
        self.batches.append((kind, org, d.astype(np.float32), far))

    @property
    def rays(self) -> int:
        return sum(len(b[1]) for b in self.batches)


class Split:
    """Times the bake's parts: RayTracer calls (Embree and its argument handling), the indirect
    lookup (IndirectField.irradiance) and the per-probe filters and SH minima."""

    def __init__(self) -> None:
        self.seconds = {"cast": 0.0, "indirect": 0.0, "filters": 0.0}
        self.total = 0.0
        self._patched: list[tuple[object, str, object]] = []

    def _wrap(self, owner: object, name: str, key: str) -> None:
        orig = getattr(owner, name)
        split = self

        def timed(*args, **kwargs):
            t = time.perf_counter()
            try:
                return orig(*args, **kwargs)
            finally:
                split.seconds[key] += time.perf_counter() - t

        self._patched.append((owner, name, orig))
        setattr(owner, name, timed)

    def __enter__(self) -> Self:
        from probegrid.bake import driver as bake_module
        from probegrid.bake.render import IndirectField

        self._wrap(raytrace.RayTracer, "intersect", "cast")
        self._wrap(raytrace.RayTracer, "occluded", "cast")
        self._wrap(IndirectField, "irradiance", "indirect")
        self._wrap(bake_module, "_filter_groups", "filters")
        self._wrap(bake_module, "_sh_minima", "filters")
        self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        self.total = time.perf_counter() - self._t0
        for owner, name, orig in reversed(self._patched):
            setattr(owner, name, orig)

    def shares(self) -> tuple[float, float, float, float]:
        c, i, f = (self.seconds[k] / self.total for k in ("cast", "indirect", "filters"))
        return c, i, f, 1.0 - c - i - f


def raw_embree_seconds(scene, batches, chunk: int = 1 << 16) -> float:
    """Time to cast the recorded batches with embreex alone (best of 3)."""
    centre = 0.5 * (scene.vertices.min(0) + scene.vertices.max(0))
    es = rtcore_scene.EmbreeScene()
    TriangleMesh(scene=es, vertices=(scene.vertices - centre).astype(np.float32),
                 indices=scene.triangles.astype(np.int32))
    best = np.inf
    for _ in range(3):
        t = time.perf_counter()
        for kind, org, d, far in batches:
            for s in range(0, len(d), chunk):
                dist = far[s:s + chunk].copy()
                if kind == "intersect":
                    es.run(org[s:s + chunk], d[s:s + chunk], dists=dist, output=1)
                else:
                    es.run(org[s:s + chunk], d[s:s + chunk], dists=dist,
                           query="OCCLUDED")
        best = min(best, time.perf_counter() - t)
    return best


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
    parts = set(ap.parse_args(argv).part or (1, 2, 3))
    scene = load_gltf(SCENE)
    env = load_environment(SKY)
    tmp = Path(tempfile.mkdtemp(prefix="bench-bake-"))
    try:
        if 1 in parts:
            part_throughput(scene, env, tmp)
        if 2 in parts:
            part_probes_per_second(scene, env, tmp)
        if 3 in parts:
            part_memory(scene, env, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def part_throughput(scene: Scene, env: Environment, tmp: Path) -> None:
    """Part 1: the ratio to raw embreex, where the time goes, and the ceilings."""
    print("1. ray throughput: bake vs raw embreex on the same rays (1 process)")
    print("   grid 4x3x4, 32^2 faces, 2 bounces, the bundled sky")
    print("   scene                     triangles samples      rays   bake Mray/s  raw Mray/s"
          "   ratio  (target >= 0.8)")
    scenes = [("sample room", scene), ("sample room + sculpture", detailed_scene(scene))]
    rows = []
    for label, sc in scenes:
        grid = grid_for(scene, grid="4x3x4")
        # warm-up: numba kernels loaded, the BVH's first traversals
        bake(sc, grid, tmp / f"warm{len(label)}.probes", settings=BakeSettings(face_size=8, bounces=1),
             environment=env, executor=InlineExecutor(check_pickle=False))
        for samples in (1, 8):
            st = BakeSettings(face_size=32, bounces=2, samples=samples)
            run = InlineExecutor(check_pickle=False)
            with Recorder() as rec:  # the rays (recording costs time: not the timed run)
                bake(sc, grid, tmp / f"r{samples}{len(label)}.probes", settings=st,
                     environment=env, executor=run)
            t = time.perf_counter()  # the same bake, timed, uninstrumented
            bake(sc, grid, tmp / f"a{samples}{len(label)}.probes", settings=st,
                 environment=env, executor=run)
            t_bake = time.perf_counter() - t
            with Split() as split:  # and once more, timing its parts
                bake(sc, grid, tmp / f"s{samples}{len(label)}.probes", settings=st,
                     environment=env, executor=run)
            t_raw = raw_embree_seconds(sc, rec.batches)
            n = rec.rays
            rows.append((label, samples, split.shares(), t_raw, dict(split.seconds)))
            print(f"   {label:<25} {sc.n_triangles:9,d} {samples:7d} {n / 1e6:7.2f} M "
                  f"{n / t_bake / 1e6:10.2f} {n / t_raw / 1e6:11.2f}   {t_raw / t_bake:.3f}")
    print("\n   where the bake's time goes (share of an instrumented run):")
    print("   scene                     samples  ray casting  indirect lookup  filters+SH min"
          "  rest")
    for label, samples, (cast, ind, filt, rest), _, _ in rows:
        print(f"   {label:<25} {samples:7d} {cast:11.0%} {ind:16.0%} {filt:15.0%} "
              f"{rest:5.0%}")
    print("\n   what the ratio could be (raw embreex seconds over the sum of the parts kept):")
    print("   casting = raw / the bake's own ray casting (Embree plus argument handling);")
    print("   the ceilings assume everything else in the bake took no time at all.")
    print("   scene                     samples   casting   ceiling: filters only"
          "   filters + indirect")
    for label, samples, _, t_raw, sec in rows:
        cast, ind, filt = sec["cast"], sec["indirect"], sec["filters"]
        print(f"   {label:<25} {samples:7d} {t_raw / cast:9.2f} "
              f"{t_raw / (t_raw + filt):23.2f} {t_raw / (t_raw + filt + ind):20.2f}")


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


def part_memory(scene: Scene, env: Environment, tmp: Path) -> None:
    """Part 3: worker memory against grid size."""
    print("\n3. worker memory against grid size (8^2 faces, 1 bounce, 2 workers)")
    print("   grid        probes   seconds  largest worker: resident, private")
    small_st = BakeSettings(face_size=8, bounces=1)
    for label in ("4x2x4", "32x16x32"):
        g = grid_for(scene, grid=label)
        with LocalExecutor(2) as ex, DescendantMemory() as mem:
            t = time.perf_counter()
            bake(scene, g, tmp / f"m{label}.probes", settings=small_st, environment=env,
                 executor=ex)
            sec = time.perf_counter() - t
        print(f"   {label:<10} {g.n_probes:7d}  {sec:8.2f}  {mem.peak_mb:8.0f} MB, "
              f"{mem.peak_private_mb:4.0f} MB")
    print("   (resident memory includes the pages of the memory-mapped previous bounce a "
          "worker has read; private memory is what it holds alone)")


if __name__ == "__main__":
    main()
