"""``GET /v1/grids`` and ``GET /v1/grids/{grid}``: what is served, with every convention."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from service.deps import GridDep, StateDep
from service.encoding import conditional_response
from service.schemas import ErrorOut, GridDetail, GridList, GridSummary

router = APIRouter(prefix="/v1/grids", tags=["grids"])


@router.get("", response_model=GridList, operation_id="list_grids")
async def list_grids(request: Request, state: StateDep) -> Response:
    """Every served grid: name, lattice, bounds, map kinds and sizes."""
    body = GridList(
        grids=[GridSummary(**g.summary) for g in state.grids.values()]
    ).model_dump_json().encode()
    return conditional_response(request, body, "application/json")


@router.get(
    "/{grid}",
    response_model=GridDetail,
    operation_id="get_grid",
    responses={404: {"model": ErrorOut}},
)
async def get_grid(request: Request, grid: GridDep) -> Response:
    """One grid's summary and its full manifest (conventions, bake settings, quality)."""
    manifest = grid.store.manifest.model_dump(mode="json")
    body = GridDetail(**grid.summary, manifest=manifest).model_dump_json().encode()
    return conditional_response(request, body, "application/json")
