"""Build the probe map service app and run it with uvicorn.

* :func:`create_app` opens the stores (read-only memory maps) and returns the FastAPI app.
* :func:`app_from_environment` is the app factory of worker processes: it reads the store list
  and every setting from ``PROBEGRID_*`` variables (:mod:`service.settings`).
* :func:`example_usage` is what to print at start-up: a query to try and the same client call.
* :func:`run` serves until interrupted; with ``workers > 1`` uvicorn starts that many processes,
  each building its app through the factory (memory-mapped stores share their pages).

Routes (OpenAPI at ``/docs`` and ``/openapi.json``)::

    GET  /                          the viewer (browser page; /docs and /redoc served offline)
    GET  /healthz
    GET  /v1/grids
    GET  /v1/grids/{grid}
    GET  /v1/grids/{grid}/sh?x=&y=&z=[&nx=&ny=&nz=]
    GET  /v1/grids/{grid}/maps/{kind}?x=&y=&z=[&nx=&ny=&nz=][&level=][&format=][&layout=]
    POST /v1/grids/{grid}/shade
    POST /v1/lights/maps
    GET  /v1/grids/{grid}/probes    every probe (positions, SH, validity), for drawing the grid
    GET  /v1/grids/{grid}/scene     the baked glTF scene, when the store keeps it
    GET  /v1/dfg                    the split-sum DFG table
    GET  /v1/grids/{grid}/export/threejs.json|.bin|.ktx2   three.js' LightProbeGrid export
"""

from __future__ import annotations

import os
import shutil
import weakref
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any, Final

from fastapi import FastAPI

from probegrid._version import __version__
from probegrid.store import read_manifest
from service.deps import ServiceState
from service.encoding import scratch_directory
from service.errors import BodyLimitMiddleware, LastResortMiddleware, install_error_handlers
from service.registry import GridRegistry, grid_name
from service.routers import exports, grids, health, lights, maps, sh, shade, viewer, web
from service.settings import Settings, load_settings, settings_environment
from service.webassets import StaticAssets

__all__ = ["NONZERO_VECTORS", "OPENAPI_TAGS", "app_from_environment", "create_app",
           "example_usage", "openapi_document", "run"]

#: The route groups, in the order the docs list them.
OPENAPI_TAGS: Final[tuple[dict[str, str], ...]] = (
    {"name": "health", "description": "Liveness."},
    {"name": "grids", "description": "The served grids: lattice, bounds, map kinds and sizes, "
                                     "manifest and conventions."},
    {"name": "probes", "description": "Queries at any position: blended SH, cube maps, shading."},
    {"name": "lights", "description": "Analytic maps of dynamic (unbaked) lights."},
)


def create_app(
    store_paths: Sequence[str | os.PathLike[str]], settings: Settings | None = None
) -> FastAPI:
    """The service app serving the given stores.

    Parameters
    ----------
    store_paths : sequence of path
        Finished grid stores (``NAME.probes`` directories), served as ``NAME``.
    settings : Settings, optional
        Limits; default ``Settings()`` (environment variables, then defaults).

    Raises
    ------
    probegrid.store.StoreError or ValueError
        A store cannot be opened, or two stores have the same name.
    """
    settings = load_settings() if settings is None else settings
    registry = GridRegistry.open(list(store_paths))
    scratch = scratch_directory()
    remove_scratch: list[weakref.finalize] = []

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        try:
            yield
        finally:
            remove_scratch[0]()

    app = FastAPI(
        title="probegrid map service",
        version=__version__,
        description=(
            "Light-probe grids served at any position: blended SH coefficients and diffuse, "
            "specular and incoming cube maps, split-sum shading, and analytic maps of dynamic "
            "lights. Conventions are in each grid's manifest (GET /v1/grids/{grid})."
        ),
        openapi_tags=[dict(t) for t in OPENAPI_TAGS],
        lifespan=lifespan,
        docs_url=None,  # served by service.routers.web from the vendored files (offline)
        redoc_url=None,
    )
    # the scratch directory goes at shutdown, or with the app if it never ran a lifespan
    remove_scratch.append(weakref.finalize(app, shutil.rmtree, scratch, ignore_errors=True))
    app.state.probegrid = ServiceState(settings=settings, grids=registry, scratch=scratch)
    install_error_handlers(app)
    # Routes are matched in this order: the hot probe queries right after /healthz (routing
    # costs a few microseconds per router passed); the docs list the tags in OPENAPI_TAGS' order.
    for module in (health, sh, maps, grids, shade, lights):
        app.include_router(module.router)
    # the viewer's data and pages (service.routers.viewer, service.routers.web)
    app.state.probegrid_assets = StaticAssets()
    app.state.probegrid_pages = {}
    app.state.probegrid_probes = {}
    app.state.probegrid_scenes = viewer.open_scenes(registry)
    app.state.probegrid_threejs = {}  # grid name -> service.routers.exports.ThreeExport
    app.include_router(viewer.router)
    app.include_router(exports.router)
    app.include_router(web.router)
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_body_bytes)
    app.add_middleware(LastResortMiddleware)  # outermost: sees what every handler missed

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            levels = [g.field.map_levels(k) - 1 for g in registry.values()
                      for k in g.field.kinds]
            app.openapi_schema = openapi_document(FastAPI.openapi(app), settings, levels)
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    return app


#: Request fields that must not be the zero vector (the models refuse it), by schema and field.
NONZERO_VECTORS: Final[tuple[tuple[str, str], ...]] = (
    ("SurfacePoint", "normal"), ("SurfacePoint", "view"), ("LightMapsRequest", "normal"),
    ("SpotLightIn", "direction"), ("DirectionalLightIn", "direction"),
)


def _tuples_as_arrays(node: Any) -> None:
    """Write each homogeneous tuple (``prefixItems`` of equal schemas, pydantic's form) as an
    array of that schema with ``minItems = maxItems``: the same constraint, read alike by
    OpenAPI 3.0 and 3.1 tools, code generators and fuzzers."""
    if isinstance(node, dict):
        prefix = node.get("prefixItems")
        if (isinstance(prefix, list) and prefix and "items" not in node
                and all(item == prefix[0] for item in prefix)):
            del node["prefixItems"]
            node["items"] = prefix[0]
            node["minItems"] = node["maxItems"] = len(prefix)
        for value in node.values():
            _tuples_as_arrays(value)
    elif isinstance(node, list):
        for value in node:
            _tuples_as_arrays(value)


def openapi_document(doc: dict[str, Any], settings: Settings,
                     served_levels: Sequence[int] = ()) -> dict[str, Any]:
    """FastAPI's OpenAPI 3.1 document, made to state what the server enforces.

    * homogeneous tuples as fixed-length arrays (:func:`_tuples_as_arrays`);
    * the vectors of :data:`NONZERO_VECTORS` must hold a non-zero component
      (``contains: {not: {const: 0}}``);
    * the limits of ``settings``: at most ``max_lights`` lights and face sizes up to
      ``max_light_map_size`` in ``/v1/lights/maps``, at most ``max_batch`` points in ``/shade``;
    * ``level`` at most the last level of the served grids' longest chain
      (``served_levels``: the last level of each served map kind) in ``/maps/{kind}``, and of
      that or of a light map of the largest face size in ``/v1/lights/maps``.

    Not stated (they depend on the served data or on arithmetic of several fields, which
    OpenAPI cannot express): a level beyond the chain of the kind asked for (a diffuse map has
    one level; a specular chain's length depends on the face size or the grid); these stay
    422s naming the valid range.

    The normal of ``/sh`` and ``/maps`` (all three components or none, not all zero) is stated
    by :data:`service.deps.POINT_PARAMETERS`.
    """
    schemas = doc["components"]["schemas"]
    for model, name in NONZERO_VECTORS:
        prop = schemas[model]["properties"][name]
        target = next((alt for alt in prop.get("anyOf", []) if alt.get("type") == "array"), prop)
        target["contains"] = {"not": {"const": 0}}
        target["description"] = (target.get("description") or prop.get("description")
                                 or "A vector") + " Not the zero vector."
    maps = schemas["LightMapsRequest"]["properties"]
    for name in ("diffuse_size", "specular_size"):
        maps[name]["maximum"] = settings.max_light_map_size
        maps[name]["description"] = (
            maps[name].get("description", "Face size.")
            + f" At most {settings.max_light_map_size} (PROBEGRID_MAX_LIGHT_MAP_SIZE).")
    maps["lights"]["maxItems"] = settings.max_lights
    # levels: no served grid and no light map of the largest face size has more
    top = max([(settings.max_light_map_size).bit_length() - 1, *served_levels])
    maps["level"]["maximum"] = top
    maps_get = doc["paths"].get("/v1/grids/{grid}/maps/{kind}", {}).get("get", {})
    for param in maps_get.get("parameters", []):
        if param["name"] == "level":
            param["schema"]["maximum"] = max(served_levels, default=0)
    schemas["ShadeRequest"]["properties"]["points"]["maxItems"] = settings.max_batch
    _tuples_as_arrays(doc)
    return doc


def example_usage(store_path: str | os.PathLike[str], base_url: str) -> str:
    """Two lines to print when serving: a query to try, and the client call that does the same.

    The query asks for the SH at the centre of the store's grid box.
    """
    grid = read_manifest(store_path).grid
    name = grid_name(store_path)
    x, y, z = (0.5 * (lo + hi) for lo, hi in zip(grid.bounds_min, grid.bounds_max, strict=True))
    url = f"{base_url.rstrip('/')}/v1/grids/{name}/sh?x={x:g}&y={y:g}&z={z:g}"
    call = (f"ProbeGridClient({base_url.rstrip('/')!r}).sh_at({name!r}, ({x:g}, {y:g}, {z:g}))"
            "  # from probegrid.client import ProbeGridClient")
    return f"try:   curl '{url}'\nor:    {call}"


def app_from_environment() -> FastAPI:
    """App factory for uvicorn workers: stores and settings from ``PROBEGRID_*`` variables."""
    settings = load_settings()
    if not settings.stores:
        raise ValueError("PROBEGRID_STORES lists no store to serve.")
    return create_app(settings.stores, settings)


def run(
    store_paths: Sequence[str | os.PathLike[str]],
    *,
    host: str = "127.0.0.1",
    port: int = 8000,
    workers: int = 1,
    settings: Settings | None = None,
    log_level: str = "info",
    on_ready: Callable[[], None] | None = None,
) -> None:
    """Serve the stores with uvicorn until interrupted.

    The stores are opened (and checked) here first, so a bad store fails before any worker
    starts; ``on_ready`` is called then (the CLI prints where to look). With ``workers > 1``
    each uvicorn worker process builds its app with :func:`app_from_environment` from the
    ``PROBEGRID_*`` variables set here.
    """
    import uvicorn

    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}.")
    settings = load_settings() if settings is None else settings
    paths = [Path(p).resolve() for p in store_paths]
    app = create_app(paths, settings)
    if on_ready is not None:
        on_ready()
    if workers == 1:
        uvicorn.run(app, host=host, port=port, log_level=log_level)
        return
    env = settings_environment(settings.model_copy(update={"stores": paths}))
    os.environ.update(env)
    uvicorn.run(
        "service.main:app_from_environment",
        factory=True,
        host=host,
        port=port,
        workers=workers,
        log_level=log_level,
    )
