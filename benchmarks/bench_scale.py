"""How a bake's cost grows with the scene: a scene of real size beside the bundled room.

The big scene is built here (cached in ``--cache``): a 40 x 40 floor slab under an 8 x 8 array
of instanced icospheres (5 subdivisions, 20,480 triangles each: 1.31 M triangles with the
floor), textured with four 4096^2 RGBA PNG images of noise (64 MiB each decoded, about as
large encoded: 260 MB of PNG, incompressible on purpose), lit by a sun
(``KHR_lights_punctual``) and a constant sky. The loader reduces each texture to 1024^2 on
load (:mod:`probegrid.scene.texels`). Both scenes bake through the command
(``probegrid bake``, local worker processes, the same settings: fixed 2 bounces, ``--samples
1``); the big one a 16 x 8 x 16 grid over the hall, the room a 4 x 3 x 4 grid.

Printed for each: triangles, texture bytes (files, decoded), probes, the command's wall time
and the bake's passes' own seconds (``stage_seconds`` of the manifest), rays and rays/s over
the passes, the peak resident memory of the whole process tree (the command and its workers,
sampled every 0.2 s with psutil; pages a forked worker shares are counted in each process),
then the passes' time per probe and per ray, memory per triangle
and the ratios of the big scene to the room: the growth of time per probe against the growth
in triangles (Embree's traversal is about logarithmic in triangles), and of memory against
triangles and texture bytes.

Run: ``nice .venv/bin/python benchmarks/bench_scale.py [--face-size 8] [--workers 2]
[--cache DIR] [--only small|big]``. The figures are in docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
ROOM = REPO / "data" / "sample_room.glb"
SPHERES = 8  # per side
TEXTURES = 4
TEXTURE_SIZE = 4096


def _icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit icosphere vertices, triangles and spherical UVs."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = np.asarray(m.vertices, dtype=np.float64)
    uv = np.stack([np.arctan2(v[:, 2], v[:, 0]) / (2 * np.pi) + 0.5,
                   np.arccos(np.clip(v[:, 1], -1, 1)) / np.pi], axis=1)
    return v, np.asarray(m.faces, dtype=np.int64), uv


def build_scene(folder: Path) -> Path:
    """Write the big scene (module docstring) into ``folder``; returns the .gltf (cached)."""
    from PIL import Image

    from probegrid.scene.builders import box_mesh

    out = folder / "hall.gltf"
    if out.exists():
        return out
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for t in range(TEXTURES):  # noise around a per-texture colour: incompressible, 64 MiB each
        base = rng.integers(60, 200, 3)
        img = np.empty((TEXTURE_SIZE, TEXTURE_SIZE, 4), np.uint8)
        img[..., :3] = np.clip(base + rng.integers(-50, 50, (TEXTURE_SIZE, TEXTURE_SIZE, 3)),
                               0, 255)
        img[..., 3] = rng.integers(0, 256, (TEXTURE_SIZE, TEXTURE_SIZE))
        Image.fromarray(img).save(folder / f"tex{t}.png", compress_level=1)
        del img
    sv, sf, suv = _icosphere(5)
    fv, ff, fuv = box_mesh((-20.0, -0.5, -20.0), (20.0, 0.0, 20.0))
    blob = b""
    views, accessors = [], []

    def add(data: np.ndarray, kind: str, ctype: int, target: int, minmax: bool = False) -> int:
        nonlocal blob
        raw = np.ascontiguousarray(data).tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(raw),
                      "target": target})
        blob += raw + b"\0" * (-len(raw) % 4)
        acc = {"bufferView": len(views) - 1, "componentType": ctype,
               "count": len(data) if kind != "SCALAR" else data.size, "type": kind}
        if minmax:
            acc["min"], acc["max"] = data.min(0).tolist(), data.max(0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    s_pos = add(sv.astype("<f4"), "VEC3", 5126, 34962, True)
    s_uv = add(suv.astype("<f4"), "VEC2", 5126, 34962)
    s_idx = add(sf.astype("<u4").ravel(), "SCALAR", 5125, 34963)
    f_pos = add(fv.astype("<f4"), "VEC3", 5126, 34962, True)
    f_idx = add(ff.astype("<u4").ravel(), "SCALAR", 5125, 34963)
    (folder / "hall.bin").write_bytes(blob)
    meshes = [{"primitives": [{"attributes": {"POSITION": s_pos, "TEXCOORD_0": s_uv},
                               "indices": s_idx, "material": t}]} for t in range(TEXTURES)]
    meshes.append({"primitives": [{"attributes": {"POSITION": f_pos}, "indices": f_idx,
                                   "material": TEXTURES}]})
    nodes = [{"mesh": TEXTURES, "name": "Floor"}]
    for i in range(SPHERES):
        for k in range(SPHERES):
            nodes.append({"mesh": (i * SPHERES + k) % TEXTURES, "name": f"Sphere{i}_{k}",
                          "translation": [-17.5 + 5 * i, 1.2, -17.5 + 5 * k]})
    nodes.append({"name": "Sun", "rotation": [-0.3826834, 0.0, 0.0, 0.9238795],
                  "extensions": {"KHR_lights_punctual": {"light": 0}}})
    doc = {
        "asset": {"version": "2.0"}, "scene": 0,
        "scenes": [{"nodes": list(range(len(nodes)))}], "nodes": nodes, "meshes": meshes,
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": t},
                                                "metallicFactor": 0}}
                      for t in range(TEXTURES)]
        + [{"pbrMetallicRoughness": {"baseColorFactor": [0.6, 0.6, 0.6, 1],
                                     "metallicFactor": 0}}],
        "textures": [{"source": t} for t in range(TEXTURES)],
        "images": [{"uri": f"tex{t}.png"} for t in range(TEXTURES)],
        "buffers": [{"byteLength": len(blob), "uri": "hall.bin"}],
        "bufferViews": views, "accessors": accessors,
        "extensionsUsed": ["KHR_lights_punctual"],
        "extensions": {"KHR_lights_punctual": {"lights": [
            {"type": "directional", "intensity": 3.0, "color": [1.0, 0.95, 0.85]}]}},
    }
    out.write_text(json.dumps(doc))
    return out


def _tree_rss(proc: "psutil.Process") -> int:  # noqa: F821
    import psutil

    total = 0
    for p in [proc, *proc.children(recursive=True)]:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            pass
    return total


def run_bake(scene: Path, grid: str, extra: list[str], *, face: int, workers: int
             ) -> dict[str, float]:
    """``probegrid bake`` of ``scene``; wall time, peak tree RSS and the bake's figures."""
    import psutil

    out = Path(tempfile.mkdtemp(prefix="bench-scale-")) / "s.probes"
    cmd = [sys.executable, "-m", "probegrid.cli", "bake", str(scene), "--out", str(out),
           "--grid", grid, "--face-size", str(face), "--bounces", "2", "--samples", "1",
           "--environment-color", "0.4,0.5,0.7", "--workers", str(workers), "--no-progress",
           "--seed", "1", *extra]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env,
                            text=True)
    ps = psutil.Process(proc.pid)
    peak = [0]

    def watch() -> None:
        while proc.poll() is None:
            try:
                peak[0] = max(peak[0], _tree_rss(ps))
            except psutil.Error:
                pass
            time.sleep(0.2)

    th = threading.Thread(target=watch, daemon=True)
    th.start()
    text, _ = proc.communicate()
    wall = time.perf_counter() - t0
    th.join()
    if proc.returncode != 0:
        raise SystemExit(f"bake failed ({proc.returncode}):\n{text}")
    rate = re.search(r"([0-9.]+) Mrays/s", text)
    manifest = json.loads((out / "manifest.json").read_text())
    inputs = manifest.get("inputs", {}).get("scene", {})
    stages = float(sum(manifest["quality"]["stage_seconds"].values()))
    return {"wall": wall, "peak": peak[0], "mrays_s": float(rate.group(1)) if rate else 0.0,
            "stages": stages, "rays": manifest["quality"]["rays"],
            "triangles": inputs.get("triangles", 0),
            "probes": manifest["grid"]["counts"][0] * manifest["grid"]["counts"][1]
            * manifest["grid"]["counts"][2]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--face-size", type=int, default=8)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "bench-scale")
    ap.add_argument("--only", choices=("small", "big"))
    a = ap.parse_args()
    rows = []
    if a.only != "big":
        r = run_bake(ROOM, "4x3x4", [], face=a.face_size, workers=a.workers)
        rows.append(("room", ROOM.stat().st_size, 0, r))
    if a.only != "small":
        t = time.perf_counter()
        hall = build_scene(a.cache)
        built = time.perf_counter() - t
        tex = sum(p.stat().st_size for p in a.cache.glob("tex*.png"))
        decoded = TEXTURES * TEXTURE_SIZE**2 * 4
        print(f"big scene: {hall} (built or found in {built:.0f} s), textures {tex / 1e6:.0f} MB "
              f"of PNG, {decoded / 2**20:.0f} MiB decoded", flush=True)
        r = run_bake(hall, "16x8x16", ["--bounds", "-19,0.3,-19,19,8,19"], face=a.face_size,
                     workers=a.workers)
        rows.append(("hall", hall.stat().st_size, tex, r))
    print(f"face size {a.face_size}, 2 bounces, 1 sample, {a.workers} local workers; "
          f"load average {os.getloadavg()[0]:.1f}")
    print("wall: the whole command; stages: the bake's passes (classify, trace, bounces, "
          "final; the rest is loading the scene, starting workers, writing the store)")
    print(f"{'scene':6} {'triangles':>10} {'tex MB':>7} {'probes':>6} {'wall s':>7} "
          f"{'stages s':>8} {'rays':>9} {'Mrays/s':>7} {'peak MiB':>8} {'s/probe':>8} "
          f"{'us/ray':>7} {'KiB/tri':>8}")
    for name, _, tex, r in rows:
        per = r["stages"] / r["probes"]
        print(f"{name:6} {r['triangles']:>10,} {tex / 1e6:>7.0f} {r['probes']:>6} "
              f"{r['wall']:>7.1f} {r['stages']:>8.1f} {r['rays']:>9,} "
              f"{r['rays'] / r['stages'] / 1e6:>7.3f} {r['peak'] / 2**20:>8.0f} {per:>8.3f} "
              f"{1e6 * r['stages'] / r['rays']:>7.1f} "
              f"{r['peak'] / 1024 / max(1, r['triangles']):>8.2f}")
    if len(rows) == 2:
        s, b = rows[0][3], rows[1][3]
        print(f"hall / room: triangles x{b['triangles'] / s['triangles']:,.0f}, probes "
              f"x{b['probes'] / s['probes']:.0f}, stage time per probe "
              f"x{(b['stages'] / b['probes']) / (s['stages'] / s['probes']):.2f}, rays per "
              f"probe x{(b['rays'] / b['probes']) / (s['rays'] / s['probes']):.2f}, rays/s "
              f"x{(b['rays'] / b['stages']) / (s['rays'] / s['stages']):.2f}, peak memory "
              f"x{b['peak'] / s['peak']:.2f}")


if __name__ == "__main__":
    main()
