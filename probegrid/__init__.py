"""probegrid: light-probe grids, cube-map environment filtering and a probe map service.

The package is layered; a module imports only the layers below its own (a test reads every
import and fails on an upward or sideways one)::

    errors, _types, _version         the error tree, every option Literal, the version
    _fs, _jit, _machine              durable writes and locks; the one numba importer; the cores
    core/                            pure math on numpy arrays, no I/O
    imageio | scene/ | store/ | raytrace/  OpenImageIO; trimesh, glTF; the grid store; Embree
    bake/ | query | filter/          the baker (Embree, executors); the store-backed probe field;
                                     the environment filter on arrays
    jobs/                            bake, filter, export, samples, demo: options -> library
    cli, client                      the command line; the HTTP client

and ``service/`` (the FastAPI app) beside ``jobs``, importing core, imageio, store and query.

Conventions (face order, orientation, world frame, SH basis, units) are stated once in
:mod:`probegrid.core.conventions` and :mod:`probegrid.core.cubemap`.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from probegrid._version import __version__ as __version__
from probegrid.errors import ProbegridError as ProbegridError

if TYPE_CHECKING:
    from probegrid import imageio as imageio
    from probegrid.bake import BakeSettings as BakeSettings
    from probegrid.bake.executors import LocalExecutor as LocalExecutor
    from probegrid.core import diffuse as diffuse
    from probegrid.core import layouts as layouts
    from probegrid.core import sh as sh
    from probegrid.core import specular as specular
    from probegrid.core.cubemap import CubeMap as CubeMap
    from probegrid.core.grid import GridSpec as GridSpec
    from probegrid.filter import FilterSettings as FilterSettings
    from probegrid.filter import filter_environment as filter_environment
    from probegrid.query import ProbeField as ProbeField
    from probegrid.scene import load_gltf as load_gltf
    from probegrid.store import open_store as open_store

#: The public names the package's face hands on (``probegrid.bake`` is the subpackage; its
#: function is ``probegrid.bake.bake``) (loaded on first use, so importing one
#: submodule stays light): name -> (module, attribute or None for the module itself).
_PUBLIC: dict[str, tuple[str, str | None]] = {
    "BakeSettings": ("probegrid.bake", "BakeSettings"),
    "CubeMap": ("probegrid.core.cubemap", "CubeMap"),
    "FilterSettings": ("probegrid.filter", "FilterSettings"),
    "GridSpec": ("probegrid.core.grid", "GridSpec"),
    "LocalExecutor": ("probegrid.bake.executors", "LocalExecutor"),
    "ProbeField": ("probegrid.query", "ProbeField"),
    "diffuse": ("probegrid.core.diffuse", None),
    "filter_environment": ("probegrid.filter", "filter_environment"),
    "imageio": ("probegrid.imageio", None),
    "layouts": ("probegrid.core.layouts", None),
    "load_gltf": ("probegrid.scene", "load_gltf"),
    "open_store": ("probegrid.store", "open_store"),
    "sh": ("probegrid.core.sh", None),
    "specular": ("probegrid.core.specular", None),
}

__all__ = [
    "BakeSettings",
    "CubeMap",
    "FilterSettings",
    "GridSpec",
    "LocalExecutor",
    "ProbeField",
    "ProbegridError",
    "__version__",
    "diffuse",
    "filter_environment",
    "imageio",
    "layouts",
    "load_gltf",
    "open_store",
    "sh",
    "specular",
]


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        module, attribute = _PUBLIC[name]
        value = importlib.import_module(module)
        return value if attribute is None else getattr(value, attribute)
    raise AttributeError(f"module 'probegrid' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
