"""Request dependencies of the routes, as ``Annotated`` aliases.

* :data:`StateDep` -- the app's :class:`ServiceState` (settings, grids, scratch directory, DFG LUT).
* :data:`GridDep` -- the :class:`service.registry.ServedGrid` named by the ``{grid}`` path
  parameter (404 ``not_found`` for a name that is not served).
* :data:`ProbeQueryDep` -- the grid (as above) and the point of a probe query (``/sh``,
  ``/maps``): the ``x``, ``y``, ``z`` query parameters (required, finite, at most
  :data:`~service.schemas.COORD_LIMIT` in magnitude as in request bodies) and the optional
  ``nx``, ``ny``, ``nz`` (all three or none, the same bounds, not all zero; no parameter
  repeated), as a
  :class:`ProbeQuery`.

The same rules as plain functions of the request, for the routes' fast paths
(:mod:`service.fastroute`): :func:`served_grid`, :func:`parse_point`, :func:`probe_query` and
:func:`plain_query`.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
from fastapi import Depends, Request
from fastapi import Path as PathParam
from numpy.typing import NDArray

from probegrid.usercache import dfg_lut
from service.errors import ApiError
from service.registry import GridRegistry, ServedGrid
from service.schemas import COORD_LIMIT
from service.settings import Settings

__all__ = [
    "BUSY_RETRY_AFTER",
    "DFG_SIZE",
    "POINT_PARAMETERS",
    "QUERY_NAMES",
    "GridDep",
    "PointQuery",
    "ProbeQuery",
    "ProbeQueryDep",
    "ServiceState",
    "StateDep",
    "parse_point",
    "plain_query",
    "probe_query",
    "require_json",
    "served_grid",
]

#: Size of the split-sum DFG table used by ``/shade``.
DFG_SIZE = 64

#: Seconds a client is asked to wait when every heavy-request slot is taken (``Retry-After``).
BUSY_RETRY_AFTER = 1


@dataclass(eq=False)
class ServiceState:
    """What one app instance serves; built once by :func:`service.main.create_app`.

    Attributes
    ----------
    settings : Settings
    grids : GridRegistry
    scratch : Path
        Private directory for image encoding (see :mod:`service.encoding`).
    """

    settings: Settings
    grids: GridRegistry
    scratch: Path
    _dfg: NDArray[np.float32] | None = field(default=None, repr=False)
    _dfg_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _heavy: threading.BoundedSemaphore | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self._heavy = threading.BoundedSemaphore(self.settings.max_heavy_requests)

    @contextmanager
    def heavy(self) -> Iterator[None]:
        """Hold one of the ``max_heavy_requests`` slots for the duration; ApiError 503 ``busy``
        with ``Retry-After`` (at once, without waiting) when none is free."""
        assert self._heavy is not None
        if not self._heavy.acquire(blocking=False):
            raise ApiError(503, "The server is busy with other heavy requests; try again in a "
                                "moment.", code="busy",
                           headers={"Retry-After": str(BUSY_RETRY_AFTER)})
        try:
            yield
        finally:
            self._heavy.release()

    def dfg(self) -> NDArray[np.float32]:
        """The DFG LUT, computed on first use (about half a second) and kept."""
        if self._dfg is None:
            with self._dfg_lock:
                if self._dfg is None:
                    self._dfg = dfg_lut(DFG_SIZE)  # computed once per machine (same bits)
        return self._dfg


async def get_state(request: Request) -> ServiceState:
    return request.app.state.probegrid


StateDep = Annotated[ServiceState, Depends(get_state)]


async def get_grid(
    grid: Annotated[str, PathParam(description="Name of a served grid (see /v1/grids).")],
    request: Request,
) -> ServedGrid:
    return served_grid(request, grid)


GridDep = Annotated[ServedGrid, Depends(get_grid)]

#: OpenAPI description of the query parameters :func:`get_point` reads (routes that depend on
#: it add these with ``openapi_extra={"parameters": POINT_PARAMETERS}``). The normal is one
#: exploded form object (serialised ``nx=..&ny=..&nz=..``) so that the schema states what
#: :func:`parse_point` enforces: all three components or none, not all zero.
_COORD_SCHEMA: dict[str, object] = {"type": "number", "minimum": -COORD_LIMIT,
                                    "maximum": COORD_LIMIT}
POINT_PARAMETERS: list[dict[str, object]] = [
    {"name": c, "in": "query", "required": True, "schema": dict(_COORD_SCHEMA),
     "description": f"World {c} coordinate (at most {COORD_LIMIT:g} in magnitude; each "
                    "parameter at most once)."}
    for c in "xyz"
] + [
    {"name": "normal", "in": "query", "required": False, "style": "form", "explode": True,
     "description": "Surface normal nx, ny, nz (any non-zero length, components at most "
                    f"{COORD_LIMIT:g} in magnitude): give all three for visibility-aware (DDGI) "
                    "weights, or none.",
     "schema": {
         "type": "object",
         "properties": {f"n{c}": dict(_COORD_SCHEMA) for c in "xyz"},
         "anyOf": [
             {"not": {"anyOf": [{"required": [f"n{c}"]} for c in "xyz"]}},
             {"required": ["nx", "ny", "nz"],
              "not": {"properties": {f"n{c}": {"const": 0} for c in "xyz"}}},
         ],
     }},
]


#: The query parameters of the probe queries (``/sh``, ``/maps``); each may be given once
#: (others are ignored, as HTTP APIs do).
QUERY_NAMES: frozenset[str] = frozenset({"x", "y", "z", "nx", "ny", "nz", "level", "format",
                                         "layout"})


@dataclass(frozen=True, eq=False)
class PointQuery:
    """A query's point: ``position (3,)`` float64 and ``normal (3,)`` float64 or None."""

    position: NDArray[np.float64]
    normal: NDArray[np.float64] | None


def _number(params: Mapping[str, str], name: str) -> float | None:
    raw = params.get(name)
    if raw is None:
        return None
    try:
        value = float(raw)
    except ValueError:
        raise ApiError(422, f"query {name}: expected a number, got {raw[:40]!r}") from None
    if not math.isfinite(value):
        raise ApiError(422, f"query {name}: expected a finite number, got {raw[:40]!r}")
    if abs(value) > COORD_LIMIT:
        raise ApiError(422, f"query {name}: {raw[:40]} is beyond the largest coordinate the "
                            f"service takes ({COORD_LIMIT:g} in magnitude)")
    return value


def parse_point(params: Mapping[str, str]) -> PointQuery:
    """The ``x, y, z`` (required) and ``nx, ny, nz`` (optional, together, non-zero) parameters.

    Parsed here rather than declared as FastAPI ``Query`` parameters because this is the hot
    path of ``/sh`` and ``/maps``: FastAPI's per-parameter machinery costs several times the
    interpolation itself. The rules are the same: a missing, non-numeric or non-finite value is
    a 422 naming the parameter.

    Parameters
    ----------
    params : mapping of str to str
        The decoded query parameters (``request.query_params`` or :func:`plain_query`). A
        repeated name (``x=1&x=2``) is a 422 naming it (seen through ``multi_items`` of
        Starlette's ``QueryParams``; :func:`plain_query` leaves such queries to it).
    """
    multi = getattr(params, "multi_items", None)
    if multi is not None:  # a repeated parameter (x=1&x=2) is refused, not the last one taken
        names = [k for k, _ in multi() if k in QUERY_NAMES]
        if len(names) != len(set(names)):
            twice = next(k for k in names if names.count(k) > 1)
            raise ApiError(422, f"query {twice}: given more than once; give each parameter "
                                "once.")
    xyz = [_number(params, c) for c in "xyz"]
    for c, v in zip("xyz", xyz, strict=True):
        if v is None:
            raise ApiError(422, f"query {c}: the coordinate is required")
    n = [_number(params, f"n{c}") for c in "xyz"]
    normal = None
    if any(v is not None for v in n):
        if any(v is None for v in n):
            raise ApiError(422, "A normal needs all three of nx, ny and nz.")
        normal = np.array(n, dtype=np.float64)
        if not normal.any():
            raise ApiError(422, "The normal (nx, ny, nz) must not be the zero vector.")
    return PointQuery(position=np.array(xyz, dtype=np.float64), normal=normal)


async def get_point(request: Request) -> PointQuery:
    """:func:`parse_point` of the request's query parameters."""
    return parse_point(request.query_params)


def plain_query(request: Request) -> dict[str, str] | None:
    """The query parameters when the query string needs no decoding, else None.

    Without ``%`` and ``+`` the query string decodes to itself, and splitting it on ``&`` and
    the first ``=`` (empty fields skipped, the last value of a repeated name kept) gives
    exactly Starlette's ``request.query_params`` (``urllib.parse.parse_qsl`` with
    ``keep_blank_values``), at a seventh of the cost. A query that repeats a name gives None
    too: FastAPI's handler then refuses it (:func:`parse_point`). Used by the routes' fast
    paths (:mod:`service.fastroute`).
    """
    raw = request.scope["query_string"]
    if b"%" in raw or b"+" in raw:
        return None
    params: dict[str, str] = {}
    for field_ in raw.decode("latin-1").split("&"):
        if field_:
            name, _, value = field_.partition("=")
            if name in params:
                return None
            params[name] = value
    return params


@dataclass(frozen=True, eq=False)
class ProbeQuery:
    """What a probe query (``/sh``, ``/maps``) names: the served grid and the point."""

    grid: ServedGrid
    point: PointQuery


def served_grid(request: Request, grid: str) -> ServedGrid:
    """The served grid of that name; ApiError 404 ``not_found`` naming the served ones."""
    grids = request.app.state.probegrid.grids
    served = grids.get(grid)
    if served is None:
        names = ", ".join(repr(n) for n in grids) or "none"
        raise ApiError(404, f"There is no grid {grid[:128]!r}; served grids: {names}.")
    return served


def probe_query(request: Request, params: Mapping[str, str]) -> ProbeQuery:
    """:func:`served_grid` of the ``{grid}`` path parameter and :func:`parse_point` of
    ``params``, in that order (a request with both wrong gets the 404)."""
    return ProbeQuery(grid=served_grid(request, request.path_params["grid"]),
                      point=parse_point(params))


async def get_probe_query(
    grid: Annotated[str, PathParam(description="Name of a served grid (see /v1/grids).")],
    request: Request,
) -> ProbeQuery:
    """:func:`served_grid` and :func:`parse_point` in one dependency (one resolution per
    request)."""
    return ProbeQuery(grid=served_grid(request, grid), point=parse_point(request.query_params))


ProbeQueryDep = Annotated[ProbeQuery, Depends(get_probe_query)]


async def require_json(request: Request) -> None:
    """Refuse a request body that is not declared as JSON (415); no Content-Type is taken as
    JSON, as FastAPI does."""
    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media and media != "application/json" and not media.endswith("+json"):
        raise ApiError(415, f"The request body must be JSON (Content-Type: application/json), "
                            f"not {media}.")
