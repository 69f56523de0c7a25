"""Baking a probe grid: settings, environment, ray tracing, rendering, executors and the driver.

``settings`` (:class:`BakeSettings`), ``environment`` (the distant light), ``render`` (one
probe's incoming light, traced through :mod:`probegrid.raytrace`), ``executors`` (local processes
or Dask: the one dask importer) and ``driver`` (:func:`bake`: stages, work directory, store).
:func:`bake` and :class:`BakeReport` load the driver (Embree, numba) on first use, so importing
the settings stays cheap.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from probegrid.bake.settings import BakeSettings

if TYPE_CHECKING:
    from probegrid.bake.driver import BakeReport, bake

__all__ = ["BakeReport", "BakeSettings", "bake"]


def __getattr__(name: str) -> Any:
    if name in ("bake", "BakeReport"):
        from probegrid.bake import driver

        return getattr(driver, name)
    raise AttributeError(f"module 'probegrid.bake' has no attribute {name!r}")
