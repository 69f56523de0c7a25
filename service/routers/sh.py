"""``GET /v1/grids/{grid}/sh``: the blended SH radiance coefficients at a position."""

from __future__ import annotations

from typing import Annotated, Any, get_args

from fastapi import APIRouter, Query, Request, Response
from pydantic_core import to_json

from service.deps import POINT_PARAMETERS, ProbeQueryDep, plain_query, probe_query
from service.encoding import conditional_response
from service.fastroute import FastPathRoute, fast_path
from service.routers._common import flags_json, probes_json
from service.schemas import ErrorOut, SHKind, SHOut, SHSource

router = APIRouter(prefix="/v1/grids/{grid}", tags=["probes"], route_class=FastPathRoute)


def resolve_sh(request: Request) -> dict[str, Any] | None:
    """Arguments of :func:`get_sh` for a query string that needs no decoding (else None: FastAPI
    resolves them); see :mod:`service.fastroute`."""
    params = plain_query(request)
    if params is None:
        return None
    query = probe_query(request, params)
    kind = params.get("sh", "deringed")
    source = params.get("source", "field")
    if kind not in _SH_KINDS or source not in _SH_SOURCES:
        return None
    return {"request": request, "query": query, "sh": kind, "source": source}


_SH_KINDS = frozenset(get_args(SHKind))
_SH_SOURCES = frozenset(get_args(SHSource))


@router.get(
    "/sh",
    response_model=SHOut,
    operation_id="get_sh",
    responses={404: {"model": ErrorOut}, 422: {"model": ErrorOut}},
    openapi_extra={"parameters": POINT_PARAMETERS},
)
@fast_path(resolve_sh)
async def get_sh(
    request: Request,
    query: ProbeQueryDep,
    sh: Annotated[SHKind, Query(description="'deringed' (default): each probe's SH windowed "
                                            "so that its irradiance is >= 0 everywhere; "
                                            "'raw': the projection, which may ring.")
                  ] = "deringed",
    source: Annotated[SHSource, Query(description="'field' (default): the store's SH field "
                                                  "(a lattice about twice as fine as the "
                                                  "probes', reaching the walls), where it has "
                                                  "one; 'probes': the probes' blend.")
                      ] = "field",
) -> Response:
    """The 9 RGB radiance coefficients at ``(x, y, z)``: interpolated on the store's SH field
    (``source=field``, the default, where the store has one) or blended from the surrounding
    probes (``source=probes``); ``source`` in the response says which.

    Deringed by default (``sh=raw`` for the raw projection; ``sh`` in the response says which).
    Probes hidden from the point by the scene get no weight where the store keeps the scene's
    triangles (``flags.visibility_test`` is then ``segments``); a normal ``(nx, ny, nz)``
    moves the visibility test's start off the surface (it does not reweight the probes). A
    position up to a quarter cell outside the probes' box is extrapolated linearly. The
    response lists the probes used and their weights, and flags an outside or unlit position.
    """
    grid, point = query.grid, query.point
    field = grid.field
    coefficients, w, used = field.sh_at(point.position, normals=point.normal, kind=sh,
                                        source=source)
    on_field = used == "field"
    lattice = field.sh_field[0] if on_field and field.sh_field else grid.store.grid
    doc = {  # an SHOut, serialised directly (this is the service's hottest path)
        "grid": grid.name,
        "position": point.position.tolist(),
        "sampled_position": w.points[0].tolist(),
        "coefficients": coefficients[0].tolist(),
        "sh": sh,
        "sh_source": "store" if on_field else field.sh_source(sh),
        "source": used,
        "probes": probes_json(lattice, w, positions=on_field),
        "flags": flags_json(w, visibility=point.normal is not None),
    }
    body = to_json(doc, inf_nan_mode="null")
    return conditional_response(request, body, "application/json")
