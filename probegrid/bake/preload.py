"""What a bake's worker processes load before their first batch (a fork server's preload).

``probegrid bake`` starts its local worker processes while it loads the scene
(:meth:`probegrid.bake.executors.LocalExecutor.start`) and names this module as their
``preload``: the fork server imports it once, and every worker forks from it with the bake
imported and its compiled kernels (:mod:`probegrid.bake.kernels`, numba's per-machine cache)
loaded, instead of each worker loading them at its first batch (about 0.4 s of imports and
0.3 s of kernels per process on the reference machine).

Importing this module:

1. imports the bake (:mod:`probegrid.bake.driver`; numpy's OpenBLAS stops its threads before a
   fork, and each worker limits BLAS to one thread in its ``setup``);
2. bakes a tiny built-in scene (a closed box with an emissive panel, a textured floor, a point
   light, a constant environment; 2 probes, 8^2 faces) in this process into a temporary
   directory, which calls every kernel a bake calls with the argument types of a real bake
   (one per kernel: the callers pass their inputs through :func:`probegrid._jit.frozen`), so
   numba loads each from its cache (or compiles it on a machine's first bake, while
   :mod:`probegrid.jobs.bake` shows it: :mod:`probegrid.bake.compiled`). Its result is
   discarded. A failure here is ignored: the workers then load what they need as they go.

Importing it anywhere else works the same (it is only slower to import).
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

from probegrid.bake import driver

__all__: list[str] = []


def _warm_up() -> None:
    """Bake the tiny scene (module docstring), inline, and discard it."""
    import numpy as np

    from probegrid.bake.environment import Environment
    from probegrid.bake.executors import InlineExecutor
    from probegrid.bake.settings import BakeSettings
    from probegrid.core.grid import GridSpec
    from probegrid.core.lights import PointLight
    from probegrid.scene import Material, SceneBuilder

    b = SceneBuilder()
    wall = b.add_material(Material.diffuse(0.5))
    floor = b.add_material(Material(base_color_texture=np.full((2, 2, 4), 0.5, np.float32)))
    lamp = b.add_material(Material(base_color=(0.5, 0.5, 0.5, 1.0), emissive=(2.0, 2.0, 2.0)))
    b.add_box((-1.0, 0.0, -1.0), (1.0, 2.0, 1.0), material=wall, inward=True)
    b.add_quad((-0.25, 1.99, -0.25), (0.5, 0.0, 0.0), (0.0, 0.0, 0.5), material=lamp)
    b.add_quad((-0.5, 0.01, 0.5), (1.0, 0.0, 0.0), (0.0, 0.0, -1.0), material=floor)
    b.add_light(PointLight((0.3, 1.5, 0.2), (1.0, 1.0, 1.0), 5.0))
    scene = b.build()
    grid = GridSpec(bounds_min=(-0.5, 1.0, 0.0), bounds_max=(0.5, 1.0, 0.0), counts=(2, 1, 1))
    env = Environment(color=np.array([0.1, 0.1, 0.1]))
    with tempfile.TemporaryDirectory(prefix="probegrid-preload-") as tmp:
        driver.bake(scene, grid, Path(tmp) / "warm.probes",
                    settings=BakeSettings(face_size=8, batch_size=1), environment=env,
                    executor=InlineExecutor(check_pickle=False))


try:
    _warm_up()
except Exception:
    logging.getLogger(__name__).debug("the warm-up bake failed", exc_info=True)
