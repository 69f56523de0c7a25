"""Data for drawing a grid: every probe at once, the baked scene, and the DFG table.

* ``GET /v1/grids/{grid}/probes`` -- positions, SH, validity and relocation of every probe
  (:class:`service.schemas.ProbesOut`), for instanced drawing; made once per served store and
  kept with it (:meth:`service.registry.ServedGrid.kept`).
* ``GET /v1/grids/{grid}/scene`` -- the glTF scene the grid was baked from, when the store keeps
  a copy (``scene_file`` in its manifest, see :func:`probegrid.store.keepable_scene`). The file
  is the store's own fixed-name copy, read and checked (a regular file inside the store, of the
  recorded size and SHA-256) with the served store, and sent with the ETag of those bytes; the
  request only names the grid.
* ``GET /v1/dfg`` -- the split-sum DFG table ``/shade`` uses (:func:`probegrid.core.dfg.dfg_lut`):
  ``(n, n, 2)`` float32, rows perceptual roughness, columns N.V, channels (A, B).
"""

from __future__ import annotations

import base64
import io
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Query, Request, Response
from pydantic_core import to_json
from starlette.concurrency import run_in_threadpool

from service.deps import GridDep, StateDep
from service.encoding import conditional_response
from service.errors import ApiError
from service.registry import ServedGrid
from service.schemas import ErrorOut, ProbesOut

router = APIRouter(tags=["grids"])


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a).tobytes()).decode("ascii")


def probes_body(grid: ServedGrid) -> bytes:
    """The :class:`ProbesOut` JSON of a grid."""
    store, spec = grid.store, grid.store.grid
    if "sh" not in store.manifest.arrays:
        raise ApiError(404, f"Grid {grid.name!r} stores no SH coefficients.")
    lattice = spec.positions()
    pos = (np.asarray(store["positions"], dtype=np.float64) if "positions" in store.manifest.arrays
           else lattice)
    # moved = further from its lattice point than float32 rounding of the coordinates
    tol = 1e-6 * max(1.0, float(np.max(np.abs(lattice))))
    relocated = np.any(np.abs(pos - lattice) > tol, axis=1)
    valid = (np.asarray(store["valid"], dtype=bool) if "valid" in store.manifest.arrays
             else np.ones(spec.n_probes, dtype=bool))
    doc = {
        "grid": grid.name,
        "probes": spec.n_probes,
        "counts": list(spec.counts),
        "positions": _b64(pos.astype("<f4")),
        "sh": _b64(np.asarray(store["sh"]).astype("<f4")),
        "valid": _b64(valid.astype(np.uint8)),
        "relocated": _b64(relocated.astype(np.uint8)),
    }
    return to_json(doc)


@router.get(
    "/v1/grids/{grid}/probes",
    response_model=ProbesOut,
    operation_id="get_probes",
    responses={404: {"model": ErrorOut}},
)
async def get_probes(request: Request, grid: GridDep) -> Response:
    """Positions, SH, validity and relocation of every probe (base64 arrays, see the schema)."""
    body = grid.kept("probes", lambda: probes_body(grid))
    return conditional_response(request, body, "application/json")


@router.get(
    "/v1/grids/{grid}/scene",
    operation_id="get_scene",
    response_class=Response,
    responses={200: {"content": {"model/gltf-binary": {}, "model/gltf+json": {}},
                     "description": "The baked glTF scene."},
               404: {"model": ErrorOut}},
)
async def get_scene(request: Request, grid: GridDep) -> Response:
    """The glTF scene the grid was baked from (a GLB, or a self-contained .gltf), if the store
    keeps one; 404 otherwise (stores baked by older versions, or from a .gltf that refers to
    other files)."""
    data = grid.scene
    kept = grid.store.manifest.scene_file
    if data is None or kept is None:
        raise ApiError(404, f"The store of grid {grid.name!r} keeps no copy of its scene.")
    return conditional_response(request, data, kept.media_type)


@router.get(
    "/v1/dfg",
    operation_id="get_dfg",
    response_class=Response,
    responses={200: {"content": {"application/x-npy": {}, "application/json": {}},
                     "description": "The (n, n, 2) float32 DFG table."}},
)
async def get_dfg(
    request: Request,
    state: StateDep,
    fmt: Annotated[Literal["npy", "json"], Query(alias="format", description="Encoding.")] = "npy",
) -> Response:
    """The split-sum DFG table: rows perceptual roughness, columns N.V (texel centres), channels
    (A, B), so that specular = prefiltered (F0 A + B) (``/shade`` uses the same table)."""
    lut = np.ascontiguousarray(await run_in_threadpool(state.dfg), dtype="<f4")
    if fmt == "json":
        body = to_json({"shape": list(lut.shape), "data": lut.tolist()})
        return conditional_response(request, body, "application/json")
    buf = io.BytesIO()
    np.save(buf, lut)
    return conditional_response(request, buf.getvalue(), "application/x-npy")
