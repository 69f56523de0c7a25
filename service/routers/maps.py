"""``GET /v1/grids/{grid}/maps/{kind}``: the cube map at a position, in several formats.

By default (``method=trace``) the map is what a probe baked at the position holds: a probe
traced there against the grid (:meth:`probegrid.query.ProbeField.cube_at`); ``method=blend``
blends the surrounding probes' maps (cheaper: microseconds instead of a trace). A store that
cannot be traced is answered with the blend; ``X-Probegrid-Method`` says which was used.
"""

from __future__ import annotations

from typing import Annotated, Any, Final, cast, get_args

from fastapi import APIRouter, Path, Query, Request, Response
from starlette.concurrency import run_in_threadpool

from probegrid._types import MapKind, MapMethod, TraceQuality, choices
from probegrid.core.lobes import level_roughness
from probegrid.query import MAP_METHODS
from service.deps import POINT_PARAMETERS, ProbeQueryDep, StateDep, plain_query, probe_query
from service.encoding import MEDIA_TYPES, conditional_response, encode_cube
from service.errors import ApiError
from service.fastroute import FastPathRoute, fast_path
from service.routers._common import flags_json, probe_header, probes_json
from service.schemas import CubeFormat, CubeLayout, ErrorOut

router = APIRouter(prefix="/v1/grids/{grid}", tags=["probes"], route_class=FastPathRoute)

#: Largest face size whose npy map is made on the event loop rather than in a worker thread.
INLINE_FACE_SIZE = 32
#: Largest ``level`` the route accepts (its ``Query(le=...)``); the store decides the real range.
MAX_LEVEL: Final = 64
_FORMATS: Final = frozenset(get_args(CubeFormat))
_LAYOUTS: Final = frozenset(get_args(CubeLayout))
_QUALITIES: Final = frozenset(choices(TraceQuality))

_BINARY = {"content": {t: {} for t in MEDIA_TYPES.values()}, "description": "The map."}


def check_json_size(values: int, limit: int) -> None:
    if values > limit:
        raise ApiError(
            422,
            f"format=json would hold {values} numbers, over the limit of {limit}; "
            "ask for npy or exr instead.",
        )


def _level(raw: str | None) -> int | None:
    """``level`` as FastAPI's ``Query(ge=0, le=MAX_LEVEL)`` int reads it, for canonical decimal
    digits only (``0``, ``7``, ``12``; not ``07``, `` 7`` or ``+7``); None for anything else."""
    if raw is None:
        return 0
    if not (raw.isascii() and raw.isdigit() and len(raw) <= 2) or (len(raw) == 2 and raw[0] == "0"):
        return None
    level = int(raw)
    return level if level <= MAX_LEVEL else None


def resolve_map(request: Request) -> dict[str, Any] | None:
    """Arguments of :func:`get_map` for a plain, well-formed query (else None: FastAPI resolves
    and validates them); see :mod:`service.fastroute`. The grid and point are resolved first,
    raising what the endpoint's dependency raises, as FastAPI does."""
    params = plain_query(request)
    if params is None:
        return None
    query = probe_query(request, params)
    level = _level(params.get("level"))
    fmt = params.get("format", "npy")  # the default of /v1/lights/maps too
    layout = params.get("layout", "faces")
    method = params.get("method", "trace")
    quality = params.get("quality", "accurate")
    if (level is None or fmt not in _FORMATS or layout not in _LAYOUTS
            or method not in MAP_METHODS or quality not in _QUALITIES):
        return None
    return {"request": request, "state": request.app.state.probegrid, "query": query,
            "kind": request.path_params["kind"], "level": level, "fmt": fmt, "layout": layout,
            "method": method, "quality": quality}


@router.get(
    "/maps/{kind}",
    operation_id="get_map",
    response_class=Response,
    responses={200: _BINARY, 404: {"model": ErrorOut}, 422: {"model": ErrorOut}},
    openapi_extra={"parameters": POINT_PARAMETERS},
)
@fast_path(resolve_map)
async def get_map(
    request: Request,
    state: StateDep,
    query: ProbeQueryDep,
    kind: Annotated[str, Path(description="diffuse, specular or incoming (where stored).")],
    level: Annotated[int, Query(ge=0, le=MAX_LEVEL, description="Specular mip level.")] = 0,
    fmt: Annotated[CubeFormat, Query(alias="format", description="Encoding.")] = "npy",
    layout: Annotated[CubeLayout, Query(description="Six faces or a horizontal cross.")] = "faces",
    method: Annotated[MapMethod, Query(
        description="trace: what a probe baked at the point holds (traced there against the "
                    "grid); blend: the surrounding probes' maps blended.")] = "trace",
    quality: Annotated[TraceQuality, Query(
        description="The traced answer (method=trace): accurate (the default: light arriving "
                    "at the rays' hits read from the bake's surface cache, direct light "
                    "sampled there; ~15-30 ms at faces 32), fast (the cache's direct light too: "
                    "softer shadows in reflections, about half the time) or reference (the "
                    "bake's own estimator, gather rays at every hit: 3-5x slower).")
    ] = "accurate",
) -> Response:
    """The cube map of one kind (and specular level) at ``(x, y, z)``: traced at the point
    (``method=trace``, the default; a store that cannot be traced answers with the blend) or
    blended from the probes (``method=blend``); ``quality`` picks the traced answer's preset.
    ``incoming`` is answered by the trace for any store that can be traced (blended only
    where the store keeps it).

    ``faces`` is ``(6, n, n, 3)`` for npy/json and the six faces stacked top to bottom for
    images; ``cross`` is the horizontal cross. Headers ``X-Probegrid-Probes`` (``index:weight``
    pairs), ``X-Probegrid-Outside``, ``X-Probegrid-Unlit`` and ``X-Probegrid-Visibility`` (the
    visibility test: ``segments``, exact against the scene's triangles; ``moments``; ``none``)
    describe the blend; ``X-Probegrid-Method`` the method used.
    """
    grid, point = query.grid, query.point
    field = grid.field
    if kind not in field.kinds:
        have = ", ".join(field.kinds)
        raise ApiError(404, f"Grid {grid.name!r} has no {kind[:64]!r} maps; it has {have}.")
    map_kind = cast(MapKind, kind)
    levels = field.map_levels(map_kind)
    if level >= levels:
        raise ApiError(422, f"level {level} is out of range 0..{levels - 1} for {kind} maps.")
    n = field.map_size(map_kind, level)
    if fmt == "json":
        check_json_size(6 * n * n * 3, state.settings.max_json_values)
    used = field.map_method(method)

    def render() -> tuple[bytes, dict[str, str]]:
        try:
            faces, w, made = field.cube_at(point.position, map_kind, level=level, method=used,
                                           normal=point.normal, quality=quality)
        except ValueError as exc:  # (incoming blended where the store keeps none)
            raise ApiError(422, str(exc)) from None
        f = flags_json(w, visibility=point.normal is not None)
        meta: dict[str, object] = {"grid": grid.name, "kind": kind, "level": level,
                                   "method": made}
        headers = {
            "X-Probegrid-Probes": probe_header(w),
            "X-Probegrid-Outside": str(f["outside"]).lower(),
            "X-Probegrid-Unlit": str(f["unlit"]).lower(),
            "X-Probegrid-Visibility": w.visibility,
            "X-Probegrid-Method": made,
        }
        if made == "trace":
            headers["X-Probegrid-Quality"] = quality
        if kind == "specular":
            r = float(level_roughness(level, levels))
            meta["roughness"] = r
            headers["X-Probegrid-Roughness"] = repr(r)
        if fmt == "json":
            meta["probes"] = probes_json(grid.store.grid, w)
            meta["flags"] = f
        body = encode_cube(faces, fmt=fmt, layout=layout, scratch=state.scratch, meta=meta)
        return body, headers

    # Small blended arrays are cheaper to make on the event loop than to hand to a thread; a
    # trace, image encoding (OpenImageIO releases the GIL) and big maps go to the thread pool.
    if fmt == "npy" and n <= INLINE_FACE_SIZE and used == "blend":
        body, headers = render()
    else:
        body, headers = await run_in_threadpool(render)
    return conditional_response(request, body, MEDIA_TYPES[fmt], headers)
