"""``POST /v1/grids/{grid}/shade``: split-sum shading of surface points with the blended maps."""

from __future__ import annotations

import numpy as np
from fastapi import APIRouter, Depends

from service.cost import check_budget, shade_estimate
from service.deps import GridDep, StateDep, require_json
from service.errors import ApiError
from service.schemas import ErrorOut, ShadeOut, ShadeRequest

router = APIRouter(prefix="/v1/grids/{grid}", tags=["probes"],
                   dependencies=[Depends(require_json)])


@router.post(
    "/shade",
    response_model=ShadeOut,
    operation_id="shade",
    responses={
        400: {"model": ErrorOut}, 404: {"model": ErrorOut}, 413: {"model": ErrorOut},
        422: {"model": ErrorOut}, 503: {"model": ErrorOut},
    },
)
def shade(body: ShadeRequest, grid: GridDep, state: StateDep) -> ShadeOut:
    """Outgoing radiance of each point: ``kd Diffuse[N] + ks Prefiltered[R, roughness]``.

    ``kd = albedo (1 - s)``, ``ks = s = F0 A + B`` (split sum, DFG table), the maps blended at
    each point with visibility-aware (DDGI) weights from its normal. At most ``max_batch`` points,
    and a batch priced over the server's ``request_budget`` (seconds of CPU) is refused with
    ``422 over_budget`` before any work.
    """
    n, limit = len(body.points), state.settings.max_batch
    if n > limit:
        raise ApiError(413, f"The batch has {n} points, over the limit of {limit}.")
    if "diffuse" not in grid.field.kinds or "specular" not in grid.field.kinds:
        raise ApiError(422, f"Grid {grid.name!r} has no diffuse and specular maps to shade with.")
    check_budget(shade_estimate(n), state.settings.request_budget)  # 422 over_budget
    pts = body.points
    mats = [p.material or body.material for p in pts]
    with state.heavy():  # at most max_heavy_requests at once; 503 busy beyond
        rgb, w = grid.field.shade(
            np.array([p.position for p in pts], dtype=np.float64),
            np.array([p.normal for p in pts], dtype=np.float64),
            np.array([p.view for p in pts], dtype=np.float64),
            albedo=np.array([m.albedo for m in mats], dtype=np.float64),
            roughness=np.array([m.roughness for m in mats], dtype=np.float64),
            f0=np.array([m.f0 for m in mats], dtype=np.float64),
            dfg=state.dfg(),
        )
    return ShadeOut(
        grid=grid.name,
        rgb=[(float(r), float(g), float(b)) for r, g, b in rgb.tolist()],
        outside=w.outside.tolist(),
        unlit=w.unlit.tolist(),
    )
