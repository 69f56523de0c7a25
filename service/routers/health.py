"""``GET /healthz``: liveness, a fixed small JSON document (also the benchmarks' reference)."""

from __future__ import annotations

from fastapi import APIRouter, Response

from service.deps import StateDep
from service.schemas import Health

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, operation_id="healthz")
async def healthz(state: StateDep) -> Response:
    """The service is up; ``grids`` is the number of grids it serves."""
    body = Health(grids=len(state.grids)).model_dump_json().encode()
    return Response(content=body, media_type="application/json")
