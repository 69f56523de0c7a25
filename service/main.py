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
from typing import Final

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

__all__ = ["OPENAPI_TAGS", "app_from_environment", "create_app", "example_usage", "run"]

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
    return app


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
