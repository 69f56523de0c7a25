"""Build the probe map service app and run it with uvicorn.

* :func:`create_app` opens the stores (checked, read into memory: :mod:`service.registry`) and
  returns the FastAPI app.
* :func:`app_from_environment` is the app factory of worker processes: it reads the store list
  and every setting from ``PROBEGRID_*`` variables (:mod:`service.settings`).
* :func:`example_usage` is what to print at start-up: a query to try and the same client call.
* :func:`run` serves until interrupted; with ``workers > 1`` uvicorn starts that many processes,
  each building its app through the factory (each holds its own copy of the stores).

Routes (OpenAPI at ``/docs`` and ``/openapi.json``)::

    GET  /                          the viewer (browser page; /docs and /redoc served offline)
    GET  /healthz
    GET  /v1/grids
    GET  /v1/grids/{grid}
    GET  /v1/grids/{grid}/sh?x=&y=&z=[&nx=&ny=&nz=]
    GET  /v1/grids/{grid}/maps/{kind}?x=&y=&z=[&nx=&ny=&nz=][&level=][&format=][&layout=]
                                    (one OpenAPI operation per kind: diffuse, specular, ...)
    POST /v1/grids/{grid}/shade
    POST /v1/lights/maps
    GET  /v1/grids/{grid}/probes    every probe (positions, SH, validity), for drawing the grid
    GET  /v1/grids/{grid}/scene     the baked glTF scene, when the store keeps it
    GET  /v1/dfg                    the split-sum DFG table
    GET  /v1/grids/{grid}/export/threejs.json|.bin|.ktx2   three.js' LightProbeGrid export
"""

from __future__ import annotations

import copy
import math
import os
import shutil
import weakref
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any, Final

from fastapi import FastAPI

from probegrid._version import __version__
from probegrid.store import read_manifest
from service.deps import ServiceState
from service.encoding import scratch_directory
from service.errors import BodyLimitMiddleware, LastResortMiddleware, install_error_handlers
from service.protocol import timed_protocol
from service.registry import GridRegistry, ServedGrid, grid_name
from service.routers import exports, grids, health, lights, maps, sh, shade, viewer, web
from service.schemas import LightMapsRequest
from service.settings import Settings, load_settings, settings_environment
from service.webassets import StaticAssets

__all__ = ["MAPS_ROUTE", "NONZERO_VECTORS", "OPENAPI_TAGS", "app_from_environment",
           "create_app", "example_usage", "openapi_document", "run", "served_chains"]

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
    app.include_router(viewer.router)
    app.include_router(exports.router)
    app.include_router(web.router)
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_body_bytes)
    app.add_middleware(LastResortMiddleware)  # outermost: sees what every handler missed

    built: list[Any] = [None]  # the served chains the cached document describes

    def openapi() -> dict[str, Any]:
        # rebuilt when a store replaced on disk changed the served kinds or chains
        chains = served_chains(registry)
        if app.openapi_schema is None or built[0] != chains:
            app.openapi_schema = openapi_document(FastAPI.openapi(app), settings, chains)
            built[0] = chains
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


def served_chains(registry: Mapping[str, ServedGrid]) -> dict[str, dict[str, list[int]]]:
    """Grid name -> map kind -> the face size of each level, of every served grid."""
    return {name: {kind: [g.field.map_size(kind, k) for k in range(g.field.map_levels(kind))]
                   for kind in g.field.kinds}
            for name, g in registry.items()}


#: The templated map route; the OpenAPI document lists one operation per served kind instead.
MAPS_ROUTE: Final = "/v1/grids/{grid}/maps/{kind}"


Chains = Mapping[str, Mapping[str, Sequence[int]]]


def _map_operations(doc: dict[str, Any], chains: Chains) -> None:
    """Replace the ``/maps/{kind}`` path item by one per map kind served
    (``/v1/grids/{grid}/maps/diffuse`` ...): the same route and URLs, but each operation
    states its own ``level`` range, which one templated operation cannot (``kind`` is a path
    parameter, ``level`` a query parameter). ``level`` is left out where every grid has one
    level (diffuse, incoming; ``level=0`` is still accepted), and its maximum is the last level
    of the served chains; when the grids' chains differ, the description names each grid's
    range (a longer ``level`` on a shorter chain stays a 422 naming it). A grid that does not
    store a kind answers 404 for it, as for an unknown kind."""
    item = doc["paths"].pop(MAPS_ROUTE, None)
    if item is None:
        return
    op = item["get"]
    kinds = [k for k in ("diffuse", "specular", "incoming")
             if any(k in c for c in chains.values())]
    paths: dict[str, Any] = {}
    for kind in kinds:
        levels = {name: len(c[kind]) for name, c in chains.items() if kind in c}
        new = copy.deepcopy(op)
        new["operationId"] = f"{op['operationId']}_{kind}"
        new["summary"] = f"Get {kind} map"
        params = []
        for param in new["parameters"]:
            if param["name"] == "kind":
                continue
            if param["name"] == "level":
                last = max(levels.values()) - 1
                if last == 0:
                    continue
                param["schema"]["maximum"] = last
                text = (f"Level of the {kind} chain: 0..{last}" + (
                    " (perceptual roughness level / (levels - 1))" if kind == "specular"
                    else ""))
                if len(set(levels.values())) > 1:
                    text += "; per grid: " + ", ".join(
                        f"{name} 0..{n - 1}" for name, n in sorted(levels.items()))
                param["description"] = param["schema"]["description"] = text + "."
            if param["name"] == "grid" and len(levels) < len(chains):
                param["description"] = param["schema"]["description"] = (
                    f"Name of a served grid; {kind} maps are stored by "
                    + ", ".join(sorted(levels)) + " (404 for the others).")
            params.append(param)
        new["parameters"] = params
        paths[MAPS_ROUTE.replace("{kind}", kind)] = {"get": new}
    # keep the document's order: the map operations where the templated one was
    ordered = {}
    for path, value in doc["paths"].items():
        ordered[path] = value
        if path == "/v1/grids/{grid}/sh":
            ordered.update(paths)
            paths = {}
    ordered.update(paths)
    doc["paths"] = ordered


def json_face_limit(settings: Settings) -> int:
    """Largest face size a ``format=json`` cube may have (``6 n^2 3`` numbers at most
    ``max_json_values``)."""
    return math.isqrt(settings.max_json_values // 18)


def _light_map_cases(settings: Settings, chains: Chains,
                     base: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The ``/v1/lights/maps`` requests the server takes, as complete object schemas (the
    request schema becomes their ``anyOf``; what :func:`service.routers.lights.post_light_maps`
    enforces between fields, stated where a generator can use it; ``if``/``then`` clauses say
    the same but fuzzers cannot generate from them):

    * a diffuse map (the default kind) has one level;
    * with ``grid``, the grid's chain of that kind (a grid without the kind: no case);
    * without it, a specular chain of ``specular_levels`` levels needs a ``specular_size``
      divisible by ``2^(levels-1)``, and a full chain (no ``specular_levels``) a power of two,
      ``log2(size) + 1`` levels;
    * ``format=json``: at most ``max_json_values`` numbers, i.e. the level's face size at most
      :func:`json_face_limit`.

    ``base`` is the request's object schema (its properties are copied and narrowed). A
    property left out of a case (the default size) is absent: ``additionalProperties`` is false.
    """
    M = settings.max_light_map_size
    N = json_face_limit(settings)
    fields = LightMapsRequest.model_fields
    default_specular = int(fields["specular_size"].default)
    default_diffuse = int(fields["diffuse_size"].default)
    formats = [f for f in base["properties"]["format"]["enum"] if f != "json"]
    cases: list[dict[str, Any]] = []

    def integer(lo: int, hi: int, **more: int) -> dict[str, Any]:
        return {"type": "integer", "minimum": lo, "maximum": hi, **more}

    def case(required: Sequence[str] = (), drop: Sequence[str] = (), **props: Any) -> None:
        properties = copy.deepcopy(base["properties"])
        for name, narrowed in props.items():  # keep the words (title, description, default)
            words = {k: properties[name][k] for k in ("title", "description", "default")
                     if k in properties[name]}
            properties[name] = {**words, **narrowed}
        for name in drop:
            del properties[name]
        cases.append({"type": "object", "properties": properties,
                      "required": sorted({*base.get("required", []), *required}),
                      "additionalProperties": False})

    def with_format(levels: tuple[int, int], json_first: int | None, **props: Any) -> None:
        """A case for the non-JSON formats (levels ``lo..hi``) and one for ``json`` from level
        ``json_first`` (None: no JSON)."""
        lo, hi = levels
        required = list(props.pop("required", ()))
        drop = props.pop("drop", ())
        if json_first is not None and json_first <= lo:  # every format at every level
            case(required, drop, level=integer(lo, hi), **props)
            return
        case(required, drop, format={"type": "string", "enum": formats},
             level=integer(lo, hi), **props)
        if json_first is not None and max(lo, json_first) <= hi:
            case([*required, "format"] + (["level"] if json_first > 0 else []), drop,
                 format={"type": "string", "const": "json"},
                 level=integer(max(lo, json_first), hi), **props)

    def first_json_level(size: int, levels: int) -> int | None:
        ok = [k for k in range(levels) if size >> k <= N]
        return ok[0] if ok else None

    diffuse = {"type": "string", "const": "diffuse"}
    specular = {"type": "string", "const": "specular"}
    no_grid = {"type": "null"}
    # a diffuse map: one level
    if M <= N:  # (with the default settings) every size as JSON too
        case([], kind=diffuse, grid=no_grid, level=integer(0, 0))
    else:
        case([], kind=diffuse, grid=no_grid, format={"type": "string", "enum": formats},
             level=integer(0, 0))
        case(["format"] + (["diffuse_size"] if default_diffuse > N else []), kind=diffuse,
             grid=no_grid, format={"type": "string", "const": "json"}, level=integer(0, 0),
             diffuse_size=integer(1, min(N, M)))
    for name, chain in sorted(chains.items()):
        grid = {"type": "string", "const": name}
        if "diffuse" in chain:
            with_format((0, 0), first_json_level(chain["diffuse"][0], 1), required=["grid"],
                        kind=diffuse, grid=grid)
        if "specular" in chain:
            sizes = list(chain["specular"])
            ok = [k for k, n in enumerate(sizes) if n <= N]
            with_format((0, len(sizes) - 1), ok[0] if ok else None,
                        required=["grid", "kind"], kind=specular, grid=grid)
    # specular without a grid: the full chain of a power-of-two size
    full = {"type": "null"}
    for k in range(M.bit_length()):
        size = 1 << k
        if size <= M:
            with_format((0, k), first_json_level(size, k + 1), required=["kind",
                        "specular_size"], kind=specular, grid=no_grid, specular_levels=full,
                        specular_size={"type": "integer", "const": size})
    d = default_specular.bit_length() - 1
    with_format((0, d), first_json_level(default_specular, d + 1), required=["kind"],
                drop=["specular_size"], kind=specular, grid=no_grid, specular_levels=full)
    # specular without a grid, specular_levels = L: a size divisible by 2^(L-1)
    for levels in range(1, 14):
        step = 1 << (levels - 1)
        if step > M:
            break
        divisible = integer(step, M, multipleOf=step)
        need = ["kind", "specular_levels"]
        every: dict[str, Any] = {} if M <= N else {"format": {"type": "string",
                                                              "enum": formats}}
        case(need + ([] if default_specular % step == 0 else ["specular_size"]),
             kind=specular, grid=no_grid, specular_levels={"type": "integer", "const": levels},
             specular_size=divisible, level=integer(0, levels - 1), **every)
        if M <= N:
            continue
        first = 0  # format=json: sizes (N+1) 2^(t-1) .. (N+1) 2^t - 1 from level t
        while first < levels:
            lo = 1 if first == 0 else (N + 1) << (first - 1)
            hi = min(M, ((N + 1) << first) - 1)
            if lo > M:
                break
            lo = -(-lo // step) * step  # the multiples of step in [lo, hi]
            if lo <= hi:
                default_in = lo <= default_specular <= hi and default_specular % step == 0
                case(need + ["format"] + (["level"] if first else [])
                     + ([] if default_in else ["specular_size"]),
                     kind=specular, grid=no_grid, format={"type": "string", "const": "json"},
                     specular_levels={"type": "integer", "const": levels},
                     specular_size=integer(lo, hi, multipleOf=step),
                     level=integer(first, levels - 1))
            first += 1
    return cases


def openapi_document(doc: dict[str, Any], settings: Settings,
                     chains: Chains | None = None) -> dict[str, Any]:
    """FastAPI's OpenAPI 3.1 document, made to state what the server enforces.

    * homogeneous tuples as fixed-length arrays (:func:`_tuples_as_arrays`);
    * the vectors of :data:`NONZERO_VECTORS` must hold a non-zero component
      (``contains: {not: {const: 0}}``);
    * the limits of ``settings``: at most ``max_lights`` lights and face sizes up to
      ``max_light_map_size`` in ``/v1/lights/maps``, at most ``max_batch`` points in ``/shade``;
    * one ``/maps/<kind>`` operation per served kind, each with its ``level`` range
      (:func:`_map_operations`; ``chains``: :func:`served_chains`), and in
      ``/v1/lights/maps`` a ``level`` at most the last level of the served chains or of a
      light map of the largest face size;
    * the spot light's cone as ``outer_cone_angle`` and ``penumbra``, which any two values
      in range make a valid cone (:class:`service.schemas.SpotLightIn`; glTF's
      ``inner_cone_angle``, whose rule ``inner < outer`` relates two fields, which a schema
      cannot state, is still taken and documented in words).

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
    chains = {} if chains is None else chains
    served_last = [len(n) - 1 for c in chains.values() for n in c.values()]
    maps["level"]["maximum"] = max([settings.max_light_map_size.bit_length() - 1, *served_last])
    request = schemas["LightMapsRequest"]
    cases = _light_map_cases(settings, chains, request)
    for key in ("properties", "required", "additionalProperties", "type"):
        request.pop(key, None)
    request["anyOf"] = cases
    _map_operations(doc, chains)
    schemas["ShadeRequest"]["properties"]["points"]["maxItems"] = settings.max_batch
    # the spot cone as penumbra (any value in range is a cone); inner_cone_angle in words only
    spot = schemas["SpotLightIn"]
    spot["properties"].pop("inner_cone_angle", None)
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
    overrides: Mapping[str, Any] | None = None,
    log_level: str = "info",
    on_ready: Callable[[], None] | None = None,
) -> None:
    """Serve the stores with uvicorn until interrupted.

    ``overrides`` replaces fields of ``settings`` (default: the ``PROBEGRID_*`` variables),
    as ``probegrid serve``'s options do. The stores are opened (and checked) here first, so a bad store fails before any worker
    starts; ``on_ready`` is called then (the CLI prints where to look). With ``workers > 1``
    each uvicorn worker process builds its app with :func:`app_from_environment` from the
    ``PROBEGRID_*`` variables set here. Connections get the settings' header and body
    deadlines (:mod:`service.protocol`).
    """
    import uvicorn

    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}.")
    settings = load_settings() if settings is None else settings
    if overrides:  # the command's options over the settings, validated again
        settings = Settings(**{**settings.model_dump(), **overrides})
    paths = [Path(p).resolve() for p in store_paths]
    app = create_app(paths, settings)
    if on_ready is not None:
        on_ready()
    if workers == 1:
        uvicorn.run(app, host=host, port=port, log_level=log_level,
                    http=timed_protocol(settings))
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
        http="service.protocol:TimedH11Protocol",  # its deadlines from the variables set here
    )
