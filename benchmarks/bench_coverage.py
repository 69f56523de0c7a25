"""What surfaces a ray may pass cost the tracer: rays per second through a cut-out, a glass
pane and a partly covering roof, against the same roof opaque, in the same run.

Every ray hits the roof (the worst case: in a real scene most rays hit opaque surfaces, which
cost what they cost before). Each kind of query is timed: closest hits (the probes' and the
gather rays), occlusion (the shadow rays), and the expected transmittance (a probe's view of a
punctual light). Prints Mrays/s and the ratio to the opaque roof, and the share of rays that
got through (0.5, 0.6 and 0.7 are the answers).

    PYTHONPATH=. python benchmarks/bench_coverage.py [--rays 500000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from probegrid.raytrace import RayTracer
from probegrid.scene import Material, Scene, quad_mesh


def _roof(material: Material) -> Scene:
    v, t, uv = quad_mesh((-20, 1.0, -20), (0, 0, 40), (40, 0, 0))
    return Scene.from_arrays(v, t, materials=[material], uvs=uv * 80)


def _holes(n: int = 256) -> np.ndarray:
    tex = np.ones((n, n, 4), np.float32)
    alpha = np.zeros(n * n, np.float32)
    alpha[np.random.default_rng(3).permutation(n * n)[: n * n // 2]] = 1.0
    tex[..., 3] = alpha.reshape(n, n)
    return tex


def _rate(fn, n: int) -> float:
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return n / best / 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=500_000)
    n = ap.parse_args().rays
    rng = np.random.default_rng(1)
    o = np.c_[rng.uniform(-10, 10, n), np.zeros(n), rng.uniform(-10, 10, n)]
    d = np.tile([0.0, 1.0, 0.0], (n, 1))
    cases = [("opaque", Material()),
             ("MASK, 50 % holes", Material(base_color_texture=_holes(), alpha_mode="MASK")),
             ("glass, T = 0.6", Material(transmission=0.6)),
             ("BLEND, alpha 0.3", Material(base_color=(1, 1, 1, 0.3), alpha_mode="BLEND"))]
    base: dict[str, float] = {}
    print(f"{n} rays, every one hitting the roof; Mrays/s (ratio to the opaque roof)")
    for name, m in cases:
        tr = RayTracer.from_scene(_roof(m))
        tr.intersect(o[:100], d[:100])  # compile and warm up
        tr.occluded(o[:100], d[:100], 2.0)
        tr.transmittance(o[:100], d[:100], 2.0)
        rates = {"closest hit": _rate(lambda: tr.intersect(o, d), n),
                 "occlusion": _rate(lambda: tr.occluded(o, d, 2.0), n),
                 "transmittance": _rate(lambda: tr.transmittance(o, d, 2.0), n)}
        if not base:
            base = rates
        through = float(np.mean(~tr.occluded(o, d, 2.0)))
        cells = ", ".join(f"{k} {v:.2f} ({v / base[k]:.2f}x)" for k, v in rates.items())
        print(f"  {name:18s} {cells}; through {through:.3f}")


if __name__ == "__main__":
    main()
