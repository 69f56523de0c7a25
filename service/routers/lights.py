"""``POST /v1/lights/maps``: analytic cube maps of lights that were not baked (dynamic lights).

The maps are :func:`probegrid.core.lights.light_maps` (diffuse = irradiance / pi, GGX specular chain,
no shadows). With ``grid``, the grid's blended map at the position is added, so the response is
"baked + dynamic" lighting there, at the grid's map sizes (blended with the visibility-aware
weights when the request gives the surface ``normal``).
"""

from __future__ import annotations

from typing import cast

import numpy as np
from fastapi import APIRouter, Depends, Response

from probegrid.core.cubemap import CubeMap, mip_sizes
from probegrid.core.lights import DirectionalLight, Light, PointLight, SpotLight, light_maps
from service.cost import check_budget, light_maps_estimate
from service.deps import StateDep, require_json
from service.encoding import MEDIA_TYPES, encode_cube
from service.errors import ApiError
from service.routers.maps import _BINARY, check_json_size
from service.schemas import ErrorOut, LightIn, LightMapsRequest, PointLightIn, SpotLightIn

router = APIRouter(prefix="/v1/lights", tags=["lights"],
                   dependencies=[Depends(require_json)])


def _direction(v: tuple[float, float, float]) -> tuple[float, float, float]:
    """A non-zero vector scaled so its largest component is 1 (the same direction): any
    length the schema allows, 5e-324 included, normalises without underflow."""
    top = max(abs(c) for c in v)
    return (v[0] / top, v[1] / top, v[2] / top)


def to_light(spec: LightIn) -> Light:
    """The library light of a request's light."""
    if isinstance(spec, PointLightIn):
        return PointLight(position=spec.position, color=spec.color, intensity=spec.intensity,
                          range=spec.range)
    if isinstance(spec, SpotLightIn):
        return SpotLight(position=spec.position, direction=_direction(spec.direction),
                         color=spec.color,
                         intensity=spec.intensity, range=spec.range,
                         inner_cone_angle=spec.inner_angle,
                         outer_cone_angle=spec.outer_cone_angle)
    return DirectionalLight(direction=_direction(spec.direction), color=spec.color,
                            intensity=spec.intensity)


@router.post(
    "/maps",
    operation_id="light_maps",
    response_class=Response,
    responses={
        200: _BINARY, 400: {"model": ErrorOut}, 404: {"model": ErrorOut},
        413: {"model": ErrorOut}, 422: {"model": ErrorOut}, 503: {"model": ErrorOut},
    },
)
def post_light_maps(body: LightMapsRequest, state: StateDep) -> Response:
    """Analytic maps of the posted lights at ``position`` (optionally plus a grid's maps).

    The request is priced before any work (lights x the texels of the maps it makes, see the
    service's ``service/cost.py``); over the server's ``request_budget`` (seconds of CPU) it is
    refused with ``422 over_budget`` naming the parameters to lower."""
    settings = state.settings
    if len(body.lights) > settings.max_lights:
        raise ApiError(422, f"{len(body.lights)} lights is over the limit of "
                            f"{settings.max_lights}.")
    for name in ("diffuse_size", "specular_size"):  # checked even where a grid's sizes apply
        if getattr(body, name) > settings.max_light_map_size:
            raise ApiError(422, f"{name} {getattr(body, name)} is over the limit of "
                                f"{settings.max_light_map_size}.")
    served = None
    chain: int | None  # levels of the chain to make (None: full)
    if body.grid is not None:  # the grid's map sizes
        served = state.grids.get(body.grid)
        if served is None:
            raise ApiError(404, f"There is no grid {body.grid!r}.")
        if body.kind not in served.field.kinds:
            raise ApiError(422, f"Grid {body.grid!r} has no {body.kind} maps.")
        size0 = served.field.map_size(body.kind)
        chain = served.field.map_levels(body.kind)
    else:
        size0 = body.diffuse_size if body.kind == "diffuse" else body.specular_size
        chain = 1 if body.kind == "diffuse" else body.specular_levels
    try:  # the other kind is made at size 1 (light_maps makes both)
        levels = len(mip_sizes(size0, chain))
    except ValueError as exc:
        raise ApiError(422, str(exc)) from None
    diffuse_size, specular_size = (size0, 1) if body.kind == "diffuse" else (1, size0)
    specular_levels = levels if body.kind == "specular" else 1
    if body.level >= levels:
        raise ApiError(422, f"level {body.level} is out of range 0..{levels - 1} for "
                            f"{body.kind} maps.")
    size = size0 >> body.level
    if body.format == "json":
        check_json_size(6 * size * size * 3, settings.max_json_values)
    check_budget(light_maps_estimate(len(body.lights), diffuse_size=diffuse_size,
                                     specular_size=specular_size,
                                     specular_levels=specular_levels),
                 settings.request_budget)  # before any work: 422 over_budget
    try:
        with state.heavy():  # at most max_heavy_requests at once; 503 busy beyond
            maps = light_maps(
                [to_light(s) for s in body.lights],
                np.asarray(body.position, dtype=np.float64),
                diffuse_size=diffuse_size,
                specular_size=specular_size,
                specular_levels=specular_levels,
            )
    except ValueError as exc:  # a light practically at the position: 1 / d^2 overflows
        raise ApiError(422, f"The lights cannot be evaluated at this position ({exc}); is a "
                            "light almost exactly at it?") from None
    faces = cast(CubeMap, maps[body.kind]).levels[body.level]
    if served is not None:
        w = served.field.weights(np.asarray(body.position, dtype=np.float64),
                                 normals=body.normal, extrapolate=False)
        faces = faces + served.field.cube(w, body.kind, level=body.level)[0]
    if not np.all(np.isfinite(faces)):
        raise ApiError(422, "The lights' irradiance at this position overflows float32 (a light "
                            "practically at the position, or one too intense for its distance).")
    meta: dict[str, object] = {"kind": body.kind, "level": body.level,
                               "lights": len(body.lights)}
    data = encode_cube(faces.astype(np.float32), fmt=body.format, layout=body.layout,
                       scratch=state.scratch, meta=meta)
    return Response(content=data, media_type=MEDIA_TYPES[body.format])
