"""``GET /healthz``: liveness and the stores' state on disk, a small JSON document (also the
benchmarks' reference).

``{"status": "ok", "grids": N}`` while every served store is the one on disk. When one was
deleted under the server (or replaced by a store that cannot be served) the answer is still
``200`` -- the process is alive and answers every route whole from the copy it read into memory,
so a supervisor that restarts on a failed check would only lose that copy -- but ``status`` is
``degraded`` and ``problems`` names each grid and why. Monitors read ``status``.
"""

from __future__ import annotations

from fastapi import APIRouter, Response

from service.deps import StateDep
from service.schemas import Health

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, operation_id="healthz")
async def healthz(state: StateDep) -> Response:
    """The service is up; ``grids`` is the number of grids it serves; ``status`` is
    ``degraded`` (with ``problems``) when a served store is no longer the one on disk."""
    problems = state.grids.problems()
    health = Health(grids=len(state.grids), status="degraded" if problems else "ok",
                    problems=problems or None)
    body = health.model_dump_json(exclude_none=True).encode()
    return Response(content=body, media_type="application/json")
