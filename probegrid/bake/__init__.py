"""Baking a probe grid, by pipeline stage.

``settings`` (:class:`BakeSettings`), ``inputs`` (the checks of a bake's inputs), ``placement``
(the grid, relocation), ``estimate`` (what a bake will cost), ``environment`` and ``emitters``
(the lights), ``pattern`` (a probe's rays), ``view`` (the scene as the probes' rays see it,
through :mod:`probegrid.raytrace`), ``records`` (per-hit records, traced once, replayed per bounce), ``stages`` (the per-batch tasks),
``schedule`` and ``converge`` (the bounce passes, convergence), ``maps`` (SH, diffuse and
specular maps), ``executors`` (inline, local processes or Dask: one per module) and ``driver``
(:func:`bake`: work directory, lock, resume, store).
:func:`bake` and :class:`BakeReport` load the driver (Embree, numba) on first use, and
:class:`BakeSettings` the settings (pydantic), so importing the executors stays cheap (a bake
starts its worker processes first).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from probegrid.bake.driver import BakeReport, bake
    from probegrid.bake.settings import BakeSettings

__all__ = ["BakeReport", "BakeSettings", "bake"]


def __getattr__(name: str) -> Any:
    if name in ("bake", "BakeReport"):
        from probegrid.bake import driver

        return getattr(driver, name)
    if name == "BakeSettings":  # (pydantic and the kernels' numba: not for the executors alone)
        from probegrid.bake.settings import BakeSettings

        return BakeSettings
    raise AttributeError(f"module 'probegrid.bake' has no attribute {name!r}")
