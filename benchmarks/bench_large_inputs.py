"""Memory and time for large inputs: big textures in a glTF, big RLE ``.hdr`` environments.

Each case runs in a fresh process (its peak resident memory, ``ru_maxrss``, is its own), against
this tree and, with ``--peer DIR``, against another checkout of probegrid (e.g. the code before
textures and environments were read reduced), side by side with the ratio:

* ``texture 4096``: ``load_gltf`` of a quad whose base colour is an embedded 4096^2 RGBA PNG
  (a smooth pattern: 0.8 MB encoded, 64 MiB decoded); tracemalloc's peak (Python and numpy
  allocations; Pillow's decoded pixels are not traced) and the process's peak RSS over its
  baseline (the imported modules), in multiples of the decoded size.
* ``texture 9000``: the same with a 9000^2 RGB PNG of one colour (1.4 MB of glTF, 309 MiB
  decoded by Pillow as RGBX); this tree only.
* ``filter 8192`` / ``filter 16384``: ``probegrid filter`` of an RLE ``.hdr`` equirect of
  8192 x 4096 (2.1 MB) or 16384 x 8192 (8.6 MB): a sky gradient and a small sun, written here.
  The peer runs the 8192 case only (code that reads the whole image ran out of memory on the
  larger one after minutes).

Run: ``nice .venv/bin/python benchmarks/bench_large_inputs.py [--peer /path/to/old/tree]
[--cache DIR]``. The figures are in docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import base64
import io
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

_LOAD = """
import resource, sys, time, tracemalloc
import numpy, PIL.Image, psutil, trimesh
from probegrid.scene import load_gltf
base = psutil.Process().memory_info().rss / 1024  # (now: the imports' peak may be higher)
tracemalloc.start()
t = time.perf_counter()
scene = load_gltf(sys.argv[1])
print(time.perf_counter() - t, tracemalloc.get_traced_memory()[1],
      int((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) * 1024),
      scene.materials[0].base_color_texture.shape)
"""


def _texture_gltf(path: Path, n: int, flat: bool) -> Path:
    """A unit triangle textured with an embedded n^2 PNG (cached)."""
    if path.exists():
        return path
    from PIL import Image

    if flat:
        img = np.full((n, n, 3), 200, np.uint8)
    else:
        img = (np.add.outer(np.arange(n), np.arange(n)) % 251).astype(np.uint8)
        img = np.repeat(img[..., None], 4, axis=-1)
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", compress_level=1)
    del img
    pos = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1]], "<f4")
    uv = np.array([[0, 0], [1, 0], [1, 1]], "<f4")
    blob = pos.tobytes() + uv.tobytes()
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1},
                                       "material": 0}]}],
           "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
           "textures": [{"source": 0}],
           "images": [{"uri": "data:image/png;base64,"
                       + base64.b64encode(buf.getvalue()).decode()}],
           "buffers": [{"byteLength": len(blob), "uri": "data:application/octet-stream;base64,"
                        + base64.b64encode(blob).decode()}],
           "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36},
                           {"buffer": 0, "byteOffset": 36, "byteLength": 24}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                          "min": [0, 0, 0], "max": [1, 0, 1]},
                         {"bufferView": 1, "componentType": 5126, "count": 3,
                          "type": "VEC2"}]}
    path.write_text(json.dumps(doc))
    return path


def _hdr(path: Path, w: int, h: int) -> Path:
    """An RLE Radiance file of ``w x h`` (OpenImageIO writes RLE scanlines), cached."""
    if path.exists():
        return path
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(w, h, 3, oiio.FLOAT))
    for y0 in range(0, h, 256):
        y1 = min(h, y0 + 256)
        t = (np.arange(y0, y1) + 0.5) / h
        band = np.empty((y1 - y0, w, 3), np.float32)
        band[...] = (np.array([0.3, 0.5, 1.0], np.float32) * (1.2 - t[:, None]))[:, None, :]
        if y0 <= h // 4 < y1:
            band[h // 4 - y0, w // 3: w // 3 + max(1, w // 512)] = 5000.0
        out.write_scanlines(y0, y1, 0, band)
    out.close()
    return path


def _run(tree: Path, args: list[str]) -> tuple[int, str, float]:
    """(exit code, output, wall seconds) of ``python args`` with ``tree`` first on the path."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    t = time.perf_counter()
    p = subprocess.run([sys.executable, *args], env=env, capture_output=True, text=True,
                       cwd=tree)  # (``-c`` puts the working directory first on the path)
    return p.returncode, p.stdout + p.stderr, time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--peer", type=Path, help="another probegrid tree to compare with")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "bench-large")
    a = ap.parse_args()
    a.cache.mkdir(parents=True, exist_ok=True)
    trees = [("this", REPO)] + ([("peer", a.peer)] if a.peer else [])
    print(f"load average {os.getloadavg()[0]:.1f}")
    for n, flat, decoded in ((4096, False, 4096**2 * 4), (9000, True, 9000**2 * 4)):
        f = _texture_gltf(a.cache / f"tex{n}.gltf", n, flat)
        for name, tree in trees:
            if name == "peer" and n > 4096:
                continue  # (code that decodes whole textures to float64 needs 11 GB here)
            code, out, wall = _run(tree, ["-c", _LOAD, str(f)])
            if code != 0:
                print(f"texture {n} {name}: failed ({out.strip().splitlines()[-1]})")
                continue
            secs, traced, rss, shape = out.split(maxsplit=3)
            print(f"texture {n} ({f.stat().st_size / 1e6:.1f} MB glTF, {decoded / 2**20:.0f} "
                  f"MiB decoded) {name}: load {float(secs):.1f} s, tracemalloc peak "
                  f"{int(traced) / 2**20:.0f} MiB ({int(traced) / decoded:.2f}x decoded), "
                  f"RSS over baseline {int(rss) / 2**20:.0f} MiB ({int(rss) / decoded:.2f}x), "
                  f"texture {shape.strip()}", flush=True)
    for w in (8192, 16384):
        f = _hdr(a.cache / f"env{w}.hdr", w, w // 2)
        for name, tree in trees:
            if name == "peer" and w > 8192:
                continue
            out_dir = Path(tempfile.mkdtemp(prefix="bench-large-")) / "maps"
            code, out, wall = _run(tree, [
                "-c", "import resource, sys; from probegrid.cli import main; c = main(sys.argv[1:]);"
                " print('maxrss', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss); "
                "sys.exit(c)", "filter", str(f), "--out", str(out_dir), "--no-previews"])
            rss = next((int(x.split()[1]) * 1024 for x in out.splitlines()
                        if x.startswith("maxrss")), 0)
            status = "ok" if code == 0 else f"exit {code}: {out.strip().splitlines()[-1]}"
            print(f"filter {w}x{w // 2} ({f.stat().st_size / 1e6:.1f} MB .hdr) {name}: "
                  f"{wall:.1f} s, peak RSS {rss / 2**20:.0f} MiB, {status}", flush=True)


if __name__ == "__main__":
    main()
