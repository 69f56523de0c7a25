"""A served grid exported for an engine, made in memory from the store (no files).

* ``GET /v1/grids/{grid}/export/threejs.json`` -- the header of three.js' ``LightProbeGrid`` /
  ``LightProbeGridWebGL`` (examples/jsm/lighting, r187) export: where the volume sits
  (``position``, ``size``, ``resolution``, and the ``min`` / ``max`` the shader then holds), the
  atlas' size and packing, how many invalid probes were filled, and the URLs of the atlas.
* ``GET /v1/grids/{grid}/export/threejs.bin`` -- the atlas as raw little-endian texels, z
  slices, rows, texels, RGBA (the order of three's ``Data3DTexture``): ``float16`` (``?dtype=``
  default; a ``HalfFloatType`` texture, filterable everywhere) or ``float32``.
* ``GET /v1/grids/{grid}/export/threejs.ktx2`` -- the same atlas as the ``probegrid export
  --target threejs`` file (a 3D KTX2 texture, ``R16G16B16A16_SFLOAT``), for ``KTX2Loader``.

The layout, placement and the filling of invalid probes are :mod:`probegrid.export.engines`'
(the same functions the ``export`` command uses): invalid probes (inside geometry) take the mean
of their valid neighbours, the SH are the store's radiance ``L_lm``. Each served store's export
is made once, on first request, and kept with it (a few bytes per probe: 28 floats; a store
replaced on disk gets its own); the request names the grid only, nothing from it becomes a
path. A value beyond half float's range (65504) makes the float16 forms a 422 that says to ask
for ``dtype=float32``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Query, Request, Response
from pydantic_core import to_json
from starlette.concurrency import run_in_threadpool

from probegrid.export import engines, ktx2
from service.deps import GridDep
from service.encoding import conditional_response
from service.errors import ApiError
from service.registry import ServedGrid
from service.schemas import ErrorOut

router = APIRouter(tags=["grids"])

#: Largest finite half float.
HALF_MAX = ktx2.HALF_MAX

_PACKING = ["c0.rgb c1.r", "c1.gb c2.rg", "c2.b c3.rgb", "c4.rgb c5.r", "c5.gb c6.rg",
            "c6.b c7.rgb", "c8.rgb 0"]


@dataclass(frozen=True, eq=False)
class ThreeExport:
    """One grid's three.js export: the float32 atlas ``(7 (nz + 2), ny, nx, 4)``, its header and
    the number of invalid probes filled."""

    atlas: np.ndarray
    header: dict[str, Any]
    filled: int

    @property
    def half_ok(self) -> bool:
        return bool(np.all(np.abs(self.atlas) <= HALF_MAX))


def threejs_export(grid: ServedGrid) -> ThreeExport:
    """Pack a served grid's SH the way three.js' ``LightProbeGrid`` samples them."""
    store, spec = grid.store, grid.store.grid
    if "sh" not in store.manifest.arrays:
        raise ApiError(404, f"Grid {grid.name!r} stores no SH coefficients.")
    nx, ny, nz = spec.counts
    sh = np.asarray(store["sh"], dtype=np.float32)
    valid = (np.asarray(store["valid"], dtype=bool) if "valid" in store.manifest.arrays
             else np.ones(spec.n_probes, dtype=bool))
    if not valid.any():
        raise ApiError(404, f"Grid {grid.name!r} has no valid probe to export.")
    bad = int(np.count_nonzero(~np.isfinite(sh[valid])))
    if bad:
        raise ApiError(500, f"Grid {grid.name!r} holds {bad} non-finite SH values; the store "
                            "is damaged.", code="internal")
    filled_sh, filled = engines.fill_invalid(sh.reshape(nx, ny, nz, 9, 3),
                                             valid.reshape(nx, ny, nz))
    atlas = engines.threejs_atlas(filled_sh)
    base = f"/v1/grids/{grid.name}/export/threejs"
    header = {
        "grid": grid.name,
        **engines.threejs_placement(spec),
        "atlas_size": [nx, ny, 7 * (nz + engines.THREEJS_PADDING * 2)],
        "padding": engines.THREEJS_PADDING,
        "packing": _PACKING,
        "layout": ("sub-volume t in atlas slices t*(nz+2)+1 .. t*(nz+2)+nz, one padding slice "
                   "copied from the edge at each end; x fastest, then y, then z"),
        "sh": ("radiance L_lm, world frame (glTF/three.js: right-handed, +Y up), basis index "
               "l(l+1)+m without Condon-Shortley phase; three's shader applies the cosine lobe"),
        "filled_invalid": filled,
        "float16_range_ok": bool(np.all(np.abs(atlas) <= HALF_MAX)),
        "atlas": {"float16": f"{base}.bin?dtype=float16", "float32": f"{base}.bin?dtype=float32",
                  "ktx2": f"{base}.ktx2", "byte_order": "little",
                  "order": "z slices, rows (y), texels (x), RGBA"},
    }
    return ThreeExport(atlas=atlas, header=header, filled=filled)


async def _export(request: Request, grid: ServedGrid) -> ThreeExport:
    done = grid.responses.get("threejs")
    if done is None:
        done = await run_in_threadpool(grid.kept, "threejs", lambda: threejs_export(grid))
    return done


def _half_or_422(export: ThreeExport, grid: ServedGrid) -> None:
    if not export.half_ok:
        big = int(np.count_nonzero(np.abs(export.atlas) > HALF_MAX))
        raise ApiError(422, f"{big} SH values of grid {grid.name!r} exceed half float's "
                            f"largest value {HALF_MAX:g}; ask for dtype=float32.")


@router.get(
    "/v1/grids/{grid}/export/threejs.json",
    operation_id="get_threejs_export",
    responses={404: {"model": ErrorOut}},
)
async def get_threejs_header(request: Request, grid: GridDep) -> Response:
    """Where three.js' ``LightProbeGrid(size.x, size.y, size.z, nx, ny, nz)`` must sit (at
    ``position``) to sample this grid's probes, and the atlas that goes in its ``texture``."""
    export = await _export(request, grid)
    return conditional_response(request, to_json(export.header), "application/json")


@router.get(
    "/v1/grids/{grid}/export/threejs.bin",
    operation_id="get_threejs_atlas",
    response_class=Response,
    responses={200: {"content": {"application/octet-stream": {}},
                     "description": "The atlas, raw little-endian texels."},
               404: {"model": ErrorOut}, 422: {"model": ErrorOut}},
)
async def get_threejs_atlas(
    request: Request,
    grid: GridDep,
    dtype: Annotated[Literal["float16", "float32"],
                     Query(description="Texel type: float16 (HalfFloatType) or float32.")]
    = "float16",
) -> Response:
    """The SH atlas ``(7 (nz + 2), ny, nx, 4)`` as raw texels (see ``threejs.json``)."""
    export = await _export(request, grid)
    if dtype == "float16":
        _half_or_422(export, grid)
    body = np.ascontiguousarray(export.atlas, dtype="<f2" if dtype == "float16" else "<f4")
    shape = list(export.atlas.shape)
    return conditional_response(request, body.tobytes(), "application/octet-stream",
                                {"X-Shape": ",".join(map(str, shape)), "X-Dtype": dtype})


@router.get(
    "/v1/grids/{grid}/export/threejs.ktx2",
    operation_id="get_threejs_ktx2",
    response_class=Response,
    responses={200: {"content": {"image/ktx2": {}},
                     "description": "The atlas as a 3D KTX2 texture (R16G16B16A16_SFLOAT)."},
               404: {"model": ErrorOut}, 422: {"model": ErrorOut}},
)
async def get_threejs_ktx2(request: Request, grid: GridDep) -> Response:
    """The atlas as the ``export --target threejs`` command writes it (``lightprobegrid.ktx2``)."""
    export = await _export(request, grid)
    _half_or_422(export, grid)
    body = await run_in_threadpool(
        ktx2.encode_ktx2, [export.atlas], kind="3d",
        vk_format=ktx2.VK_FORMAT_R16G16B16A16_SFLOAT,
        key_values={"probegrid:content": "three.js LightProbeGrid SH atlas"})
    return conditional_response(request, body, "image/ktx2")
