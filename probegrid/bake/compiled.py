"""Which of the bake's compiled kernels numba's cache holds on this machine.

A machine's first bake compiles every kernel of the bake (numba, ``cache=True``:
:mod:`probegrid._jit`); later processes load them from numba's cache (``__pycache__`` beside
each kernel module, or ``NUMBA_CACHE_DIR``). The compiling is done once, by the warm-up of the
local workers' fork server (:mod:`probegrid.bake.preload`), while the calling process loads the
scene; :func:`probegrid.jobs.bake.run_bake` asks :func:`uncached_kernels` whether that will
happen and, while it does, shows how many of the kernels are in the cache so far
(``compiling the bake's kernels (first run on this machine only): 12/37``).

A kernel counts as cached when its cache index exists and matches its module's source (numba
drops an index whose source stamp changed). Kernels inlined into their callers
(``inline="always"``) and those a bake never calls on its own (:data:`NOT_BAKED`) are left out:
the warm-up never writes them.

Reads numba's cache through its dispatchers' ``_cache`` objects (numba's own API for the
cache's file names and index, not public): if that fails, the kernel counts as cached (the bake
then says nothing of compiling, and behaves as before).
"""

from __future__ import annotations

import importlib
from typing import Any, Final

__all__ = ["KERNEL_MODULES", "NOT_BAKED", "bake_kernels", "is_cached", "uncached_kernels"]

#: The modules whose kernels a bake runs (each compiled by the warm-up bake).
KERNEL_MODULES: Final[tuple[str, ...]] = (
    "probegrid.raytrace.kernels",
    "probegrid.scene.kernels",
    "probegrid.bake.inside",
    "probegrid.bake.kernels.cube",
    "probegrid.bake.kernels.surfaces",
    "probegrid.bake.kernels.lights",
    "probegrid.bake.kernels.grid",
    "probegrid.bake.kernels.emitters",
    "probegrid.bake.kernels.environment",
    "probegrid.bake.kernels.sampling",
)

#: Kernels of those modules that the warm-up bake does not call: the service's and tests' own,
#: and the bake's paths for settings other than the defaults.
NOT_BAKED: Final[frozenset[str]] = frozenset({
    "probegrid.raytrace.kernels.segment_rays",
    "probegrid.scene.kernels.hit_surfaces",
    "probegrid.bake.kernels.grid.texel_means",
    "probegrid.bake.kernels.surfaces.split_hits",
    "probegrid.bake.kernels.emitters.emitter_shadow_rays",
    "probegrid.bake.kernels.emitters.cluster_samples",  # (emitters of many triangles only)
    "probegrid.bake.kernels.sampling.cosine_directions",
})


def bake_kernels() -> list[Any]:
    """The numba dispatchers a bake compiles, in :data:`KERNEL_MODULES` order."""
    from numba.core.registry import CPUDispatcher

    out = []
    for name in KERNEL_MODULES:
        module = importlib.import_module(name)
        for value in vars(module).values():
            if not isinstance(value, CPUDispatcher) or value.py_func.__module__ != name:
                continue
            if value.targetoptions.get("inline", "never") == "always":
                continue
            if f"{name}.{value.py_func.__name__}" in NOT_BAKED:
                continue
            out.append(value)
    return out


def is_cached(dispatcher: Any) -> bool:
    """Whether numba's cache holds a compiled version of ``dispatcher`` for its current source
    (True also when the cache cannot be read: module docstring)."""
    try:
        cache = dispatcher._cache
        return bool(cache._cache_file._load_index())
    except Exception:  # noqa: BLE001 - numba's internals changed: claim nothing
        return True


def uncached_kernels() -> list[str]:
    """Qualified names of the bake's kernels that numba's cache lacks (empty: none to compile)."""
    return [f"{d.py_func.__module__}.{d.py_func.__name__}" for d in bake_kernels()
            if not is_cached(d)]
