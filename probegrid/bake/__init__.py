"""Baking a probe grid: settings, environment, ray tracing, rendering, executors and the driver.

``settings`` (:class:`BakeSettings`), ``environment`` (the distant light), ``render`` (one
probe's incoming light, traced through :mod:`probegrid.raytrace`), ``executors`` (local processes
or Dask: the one dask importer) and ``driver`` (:func:`bake`: stages, work directory, store).
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
