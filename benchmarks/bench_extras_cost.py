"""What the service's extras add to a bake: the surface light cache and the SH field against the
probes' passes, CPU seconds of the same run.

Bakes a scene in this process (:class:`probegrid.bake.executors.InlineExecutor`: the passes,
the cache and the field all run here) and reads this process's CPU time (every thread) at the
start and end of the two extras' stages (``write_store_extras``, whose time is the surface
cache's, and ``write_sh_field``): the passes' CPU is the rest of the bake. Wall seconds of the
same stages are printed next to them (the store's ``stage_seconds``). CPU time is what a busy
shared machine changes least; the target is ``(passes + extras) / passes <= 1.5``.

Run::

    .venv/bin/python benchmarks/bench_extras_cost.py           # data/sample_room.glb 8x6x8, faces 32
    .venv/bin/python benchmarks/bench_extras_cost.py --grid 4x3x4 --face-size 16
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main(argv: list[str] | None = None) -> None:
    from probegrid.bake import BakeSettings, driver
    from probegrid.bake.executors import InlineExecutor
    from probegrid.bake.placement import grid_for
    from probegrid.scene import load_gltf

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, default=REPO / "data" / "sample_room.glb")
    ap.add_argument("--grid", default="8x6x8")
    ap.add_argument("--face-size", type=int, default=32)
    ap.add_argument("--out", type=Path, default=None,
                    help="where to keep the store (default: a temporary directory)")
    args = ap.parse_args(argv)

    cpu: dict[str, float] = {}

    def timed(name: str, fn):  # the stage's CPU time of this process
        def run(*a, **k):
            t = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                cpu[name] = time.process_time() - t
        return run

    driver.write_store_extras = timed("surface cache", driver.write_store_extras)
    driver.write_sh_field = timed("sh field", driver.write_sh_field)
    scene = load_gltf(args.scene)
    grid = grid_for(scene, grid=args.grid)
    with tempfile.TemporaryDirectory(prefix="bench-extras-") as tmp:
        out = args.out or Path(tmp) / "bake.probes"
        t0 = time.process_time()
        report = driver.bake(scene, grid, out, settings=BakeSettings(face_size=args.face_size),
                             executor=InlineExecutor(check_pickle=False), overwrite=True,
                             scene_file=args.scene)
        total = time.process_time() - t0
    wall = report.quality["stage_seconds"]
    passes_cpu = total - cpu["surface cache"] - cpu.get("sh field", 0.0)
    passes_wall = sum(v for k, v in wall.items() if k not in ("surface cache", "sh field"))
    print(f"{args.scene.name} {grid.label}, faces {args.face_size}: CPU s (wall s)")
    print(f"  passes        {passes_cpu:8.1f} ({passes_wall:.1f})")
    for name in ("surface cache", "sh field"):
        if name in cpu:
            print(f"  {name:13s} {cpu[name]:8.1f} ({wall.get(name, 0.0):.1f})  "
                  f"{cpu[name] / passes_cpu:.3f} of the passes")
    extras = cpu["surface cache"] + cpu.get("sh field", 0.0)
    extras_wall = wall.get("surface cache", 0.0) + wall.get("sh field", 0.0)
    print(f"  bake / passes: {1 + extras / passes_cpu:.2f}x CPU "
          f"({1 + extras_wall / passes_wall:.2f}x wall)")


if __name__ == "__main__":
    main()
