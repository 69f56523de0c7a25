"""Request and response models of the probe map service (they define its OpenAPI schema).

Units and conventions are the library's (see ``GET /v1/grids/{grid}``, whose manifest states them
all): positions in world units (metres, glTF frame, +Y up), radiance in the store's units, linear
Rec.709 RGB; SH coefficients are radiance ``L_lm`` of real SH bands 0-2 (index ``l(l+1)+m``, no
Condon-Shortley phase); light intensities follow ``KHR_lights_punctual`` (candela for point and
spot lights, lux for directional ones).

Every number a client sends is validated here (finite, in range, the right count) so that the
library is only ever called with arguments it accepts; limits that depend on the settings
(batch size, number of lights, map sizes) are checked by the routes.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, FiniteFloat, model_validator

from probegrid._types import SHKind, SHSource

__all__ = [
    "CubeFormat",
    "CubeLayout",
    "DirectionalLightIn",
    "ErrorOut",
    "GridDetail",
    "GridList",
    "GridSummary",
    "Health",
    "LightIn",
    "LightMapsRequest",
    "Material",
    "PointLightIn",
    "ProbeUse",
    "ProbesOut",
    "QueryFlags",
    "SHKind",
    "SHSource",
    "SHOut",
    "ShadeOut",
    "ShadeRequest",
    "SpotLightIn",
    "SurfacePoint",
]

CubeFormat = Literal["exr", "hdr", "png", "npy", "json", "ktx2"]
#: ``hcross`` is the name ``probegrid filter`` / ``export`` use for the same horizontal cross.
CubeLayout = Literal["faces", "cross", "hcross"]

def _not_bool(value: Any) -> Any:
    """JSON true/false is not a number (pydantic's lax mode would read it as 1/0)."""
    if isinstance(value, bool):
        raise ValueError("expected a number, not a boolean")  # noqa: TRY004 (pydantic reads ValueError)
    return value


#: Refuses JSON booleans where an integer is expected (integral numbers such as 2.0 pass).
NotBool = BeforeValidator(_not_bool)
Vec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]
Unit = Annotated[float, Field(ge=0.0, le=1.0, strict=True)]
Color = tuple[
    Annotated[float, Field(ge=0.0, le=1e6, strict=True)],
    Annotated[float, Field(ge=0.0, le=1e6, strict=True)],
    Annotated[float, Field(ge=0.0, le=1e6, strict=True)],
]
Reflectance = tuple[Unit, Unit, Unit]
#: Largest magnitude of a coordinate or vector component the service takes (bodies and the
#: ``x, y, z, nx, ny, nz`` query parameters alike).
COORD_LIMIT = 1e12
#: A bounded coordinate: finite and small enough that squares and sums stay finite.
Coord = Annotated[float, Field(ge=-COORD_LIMIT, le=COORD_LIMIT, allow_inf_nan=False,
                               strict=True)]
Point = tuple[Coord, Coord, Coord]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# ------------------------------------------------------------------------------ errors, health
class ErrorOut(_Model):
    """Every 4xx (and 503) response body."""

    error: str = Field(description="Machine-readable code, e.g. 'not_found', 'invalid_request'.")
    message: str = Field(description="One sentence saying what was wrong.")
    detail: list[dict[str, Any]] | None = Field(
        default=None, description="Per-field problems of a rejected request, if any."
    )


class Health(_Model):
    status: Literal["ok", "degraded"] = Field(
        default="ok", description="ok, or degraded when a served store is not the one on disk "
        "(deleted, or replaced by one that cannot be served): every grid is still answered, "
        "from the copy read into memory.")
    grids: int = Field(description="Number of grids served.")
    problems: dict[str, str] | None = Field(
        default=None, description="When degraded: grid name -> what is wrong with its store "
        "on disk.")


# ------------------------------------------------------------------------------ grids
class GridSummary(_Model):
    name: str
    counts: tuple[int, int, int] = Field(description="Probes per axis (nx, ny, nz).")
    bounds_min: tuple[float, float, float]
    bounds_max: tuple[float, float, float]
    spacing: tuple[float, float, float] = Field(description="Lattice step per axis (0 if 1 probe).")
    probes: int
    valid_probes: int
    kinds: list[str] = Field(description="Map kinds served: diffuse, specular, incoming.")
    map_sizes: dict[str, list[int]] = Field(description="Face size of each level, per kind.")
    specular_levels: int = Field(description="Level k holds perceptual roughness k / (levels-1).")
    visibility: bool = Field(description="Whether distance moments are stored (DDGI weights).")
    scene_hash: str
    created: str
    content_hash: str = Field(description="SHA-256 of the served store's manifest.json: which "
                                          "bake is served (a re-bake changes it).")
    replaced_on_disk: str | None = Field(
        default=None, description="Set when the store on disk was replaced by one that cannot "
        "be served (why); the bake opened before is still served.")


class GridList(_Model):
    grids: list[GridSummary]


class GridDetail(GridSummary):
    manifest: dict[str, Any] = Field(
        description="The store's manifest: conventions, grid, bake settings, quality, arrays."
    )


# ------------------------------------------------------------------------------ probe queries
class ProbeUse(_Model):
    index: int = Field(description="Linear probe index (i * ny + j) * nz + k (of the SH "
                       "field's lattice when an SH query's source is 'field').")
    ijk: tuple[int, int, int]
    weight: float = Field(description="Blending weight; the weights of a query sum to 1 "
                          "(negative for a linear extrapolation beyond the probes' box).")
    position: tuple[float, float, float] | None = Field(
        default=None, description="Where the SH field's lattice point is (SH queries answered "
                                  "by the field; the probes' are in /probes).")


class QueryFlags(_Model):
    outside: bool = Field(description="The position was outside the grid box: the SH "
                          "extrapolated linearly up to a quarter cell beyond it (clamped farther "
                          "out), the maps' blend clamped onto it.")
    unlit: bool = Field(description="No valid probe carries weight; the result is zero.")
    visibility: bool = Field(description="A normal was given: the visibility test starts off "
                             "the surface along it.")
    visibility_test: Literal["segments", "moments", "none"] = Field(
        description="The visibility test the weights went through: 'segments' (exact: the "
        "segment from the point, moved off the surface along the normal when one is given, to "
        "each probe cast against the scene's triangles; a probe behind a wall gets weight 0), "
        "'moments' (a normal and a store without triangles: DDGI's Chebyshev test on the "
        "probes' distance moments) or 'none' (a store without triangles, no normal).")


class SHOut(_Model):
    grid: str
    position: tuple[float, float, float] = Field(description="The position asked for.")
    sampled_position: tuple[float, float, float] = Field(
        description="Where the probes were blended (the position, clamped onto the grid box "
        "grown by a quarter cell)."
    )
    coefficients: list[tuple[float, float, float]] = Field(
        description="9 RGB radiance coefficients L_lm, index l(l+1)+m."
    )
    sh: SHKind = Field(
        description="Which coefficients: 'deringed' (each probe's SH windowed so that its "
        "irradiance is non-negative over the sphere; the default) or 'raw' (the projection)."
    )
    sh_source: Literal["store", "computed"] = Field(
        description="'store': read from the store; 'computed': deringed by the server (a store "
        "baked before deringed SH was stored).")
    source: SHSource = Field(
        default="probes",
        description="What was interpolated: 'field', the store's SH field (radiance SH traced "
        "on a lattice about twice as fine as the probes', reaching the walls), or 'probes' "
        "(a store without the field, or asked with source=probes).")
    probes: list[ProbeUse]
    flags: QueryFlags


# ------------------------------------------------------------------------------ shading
class Material(_Model):
    """glTF-style metal/rough inputs of the split-sum shading."""

    albedo: Reflectance = Field(
        default=(1.0, 1.0, 1.0), description="Lambertian colour: glTF baseColor (1 - metallic)."
    )
    f0: Reflectance = Field(default=(0.04, 0.04, 0.04), description="Reflectance at 0 degrees.")
    roughness: Unit = Field(default=0.5, description="Perceptual roughness (glTF).")


class SurfacePoint(_Model):
    """One point to shade; a material here overrides the request's."""

    position: Point = Field(description="World position.")
    normal: Point = Field(description="Surface normal (any non-zero length).")
    view: Point = Field(description="Surface-to-eye vector (any non-zero length).")
    material: Material | None = None

    @model_validator(mode="after")
    def _nonzero(self) -> SurfacePoint:
        for name in ("normal", "view"):
            if not any(getattr(self, name)):
                raise ValueError(f"{name} is the zero vector")
        return self


class ShadeRequest(_Model):
    """Surface points to shade with split-sum IBL from the blended probe maps."""

    points: list[SurfacePoint] = Field(min_length=1)
    material: Material = Field(default_factory=Material, description="Default material.")


class ShadeOut(_Model):
    grid: str
    rgb: list[tuple[float, float, float]] = Field(description="Outgoing radiance per point.")
    outside: list[bool]
    unlit: list[bool]


# ------------------------------------------------------------------------------ lights
Intensity = Annotated[float, Field(ge=0.0, le=1e12, strict=True)]
Range = Annotated[float, Field(gt=0.0, le=1e12, strict=True)]


class PointLightIn(_Model):
    type: Literal["point"]
    position: Point
    color: Color = (1.0, 1.0, 1.0)
    intensity: Intensity = Field(description="Candela.")
    range: Range | None = None


class SpotLightIn(_Model):
    """A spot light. Its cone: ``outer_cone_angle`` (radians from the axis, where the light
    ends) and ``penumbra`` (three.js' ``SpotLight.penumbra``: the fraction of the outer cone
    over which the light fades; the inner cone, at full intensity, is ``outer_cone_angle *
    (1 - penumbra)``). ``penumbra`` 1 (the default) fades from the axis; 0 is a hard edge at the
    outer cone (glTF's formula floors the falloff width ``cos(inner) - cos(outer)`` at 0.001, so
    every inner angle that close to the outer one renders alike). glTF's ``inner_cone_angle``
    (``KHR_lights_punctual``'s ``innerConeAngle``) is taken instead of ``penumbra`` too; it must
    be smaller than ``outer_cone_angle`` (a rule between two fields, which the OpenAPI document
    cannot state; so the document lists ``penumbra`` only)."""

    type: Literal["spot"]
    position: Point
    direction: Point = Field(description="Direction the spot points (world), non-zero.")
    color: Color = (1.0, 1.0, 1.0)
    intensity: Intensity = Field(description="Candela inside the inner cone.")
    range: Range | None = None
    outer_cone_angle: Annotated[float, Field(gt=0.0, le=math.pi / 2, strict=True)] = Field(
        default=math.pi / 4, description="Radians from the axis to where the light ends.")
    penumbra: Annotated[float, Field(ge=0.0, le=1.0, strict=True)] | None = Field(
        default=None, description="Fraction of the outer cone over which the light fades "
        "(the inner cone angle is outer_cone_angle * (1 - penumbra)); 0 is a hard edge. "
        "Default 1 (an inner cone angle of 0).")
    inner_cone_angle: Annotated[float, Field(ge=0.0, lt=math.pi / 2, strict=True)] | None = Field(
        default=None, description="glTF's spelling of the cone, instead of penumbra: must be "
        "smaller than outer_cone_angle.")

    @model_validator(mode="after")
    def _cone(self) -> SpotLightIn:
        if self.inner_cone_angle is not None:
            if self.penumbra is not None:
                raise ValueError("give penumbra or inner_cone_angle, not both")
            if not self.inner_cone_angle < self.outer_cone_angle:
                raise ValueError("inner_cone_angle must be smaller than outer_cone_angle")
        if not any(self.direction):
            raise ValueError("direction is the zero vector")
        return self

    @property
    def inner_angle(self) -> float:
        """The inner cone angle, always smaller than the outer one (a hard edge, ``penumbra``
        0, is the largest float below it: the same light under glTF's formula)."""
        if self.inner_cone_angle is not None:
            return self.inner_cone_angle
        outer = self.outer_cone_angle
        inner = outer * (1.0 - (1.0 if self.penumbra is None else self.penumbra))
        return inner if inner < outer else math.nextafter(outer, 0.0)


class DirectionalLightIn(_Model):
    type: Literal["directional"]
    direction: Point = Field(description="Direction the light travels (world), non-zero.")
    color: Color = (1.0, 1.0, 1.0)
    intensity: Intensity = Field(description="Lux.")

    @model_validator(mode="after")
    def _direction(self) -> DirectionalLightIn:
        if not any(self.direction):
            raise ValueError("direction is the zero vector")
        return self


LightIn = Annotated[
    PointLightIn | SpotLightIn | DirectionalLightIn, Field(discriminator="type")
]

FaceSize = Annotated[int, Field(ge=1, le=4096), NotBool]


class LightMapsRequest(_Model):
    """Analytic maps of punctual lights seen from a position (no shadows).

    With ``grid``, the grid's blended map at that position is added, and the map sizes are the
    grid's (``diffuse_size``, ``specular_size`` and ``specular_levels`` are then ignored); with
    ``normal`` too, the grid's maps are blended with the visibility-aware (DDGI) weights, as
    ``/maps`` does with ``nx, ny, nz``.
    """

    position: Point
    normal: Point | None = Field(
        default=None, description="Surface normal at the position (any non-zero length): "
        "leak-free blending of the grid's maps.")
    lights: list[LightIn] = Field(min_length=1)
    kind: Literal["diffuse", "specular"] = "diffuse"
    level: Annotated[int, Field(ge=0, le=16), NotBool] = 0
    diffuse_size: FaceSize = 16
    specular_size: FaceSize = Field(default=32, description="Power of two for a full chain.")
    specular_levels: Annotated[int, Field(ge=1, le=13), NotBool] | None = None
    grid: Annotated[str, Field(max_length=128)] | None = None
    format: CubeFormat = "npy"
    layout: CubeLayout = "faces"

    @model_validator(mode="after")
    def _nonzero_normal(self) -> LightMapsRequest:
        if self.normal is not None and not any(self.normal):
            raise ValueError("normal is the zero vector")
        return self


# ------------------------------------------------------------------------------ viewer data
class ProbesOut(_Model):
    """Every probe of a grid at once (for drawing the grid): arrays as base64 of little-endian
    binary, decoded in a browser with ``atob`` and a typed array."""

    grid: str
    probes: int = Field(description="Number of probes P, in linear index order (i ny + j) nz + k.")
    counts: tuple[int, int, int]
    positions: str = Field(description="float32 (P, 3): probe positions (after relocation).")
    sh: str = Field(description="float32 (P, 9, 3): radiance SH coefficients L_lm, index "
                                "l(l+1)+m, RGB (the store's, as the probes hold them).")
    valid: str = Field(description="uint8 (P,): 1 for a valid probe, 0 for one inside geometry.")
    relocated: str = Field(description="uint8 (P,): 1 where the probe was moved off its lattice "
                                       "point.")
