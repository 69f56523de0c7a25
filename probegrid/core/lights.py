"""Punctual lights (glTF ``KHR_lights_punctual``), their irradiance, and analytic light maps.

This module *owns* the project's light units and falloff. It is the fast path of Bloom's "Cube
Map Lighting" (2004) for dynamic lights -- ``DiffuseMap[N] = intensity * (N . L)``,
``SpecularMap[R] = intensity * (R . L)^P`` -- filled per texel in closed form (no rendering),
with every map normalised like the environment filters' maps so the two kinds of map add.

Units (KHR_lights_punctual, quoted)
-----------------------------------
"``point`` and ``spot`` lights use luminous intensity in candela (lm/sr) while ``directional``
lights use illuminance in lux (lm/m^2)". ``color`` is linear RGB and multiplies ``intensity``.
So a 1 cd point light at 1 m gives an illuminance of 1 lux at normal incidence, and a maps'
radiance is in cd/m^2 (nits).

Falloff (KHR_lights_punctual, "Range Property", the spec's recommended implementation)::

    attenuation = max(min(1.0 - (current_distance / range)^4, 1), 0) / current_distance^2

i.e. ``clamp(1 - (d / range)^4, 0, 1) / d^2``; with no ``range`` the light follows the pure
inverse-square law ``1 / d^2``. (The *squared* window ``clamp(1 - (d/range)^4, 0, 1)^2 / d^2`` of
Karis 2013 / Filament is *not* what the glTF spec recommends, and not what the Khronos glTF
Sample Viewer implements; we follow the spec.) Directional lights are not attenuated.

Spot cone (the spec's reference code, verbatim in meaning)::

    lightAngleScale  = 1 / max(0.001, cos(innerConeAngle) - cos(outerConeAngle))
    lightAngleOffset = -cos(outerConeAngle) * lightAngleScale
    cd = dot(spotlightDir, normalizedLightVector)
    angularAttenuation = saturate(cd * lightAngleScale + lightAngleOffset) ** 2

where ``spotlightDir`` is the direction the spot points (the node's local -Z in glTF; here we store
the world direction, :attr:`SpotLight.direction`) and ``normalizedLightVector`` the unit vector from
the light to the lit point. Full intensity inside ``innerConeAngle``, zero outside
``outerConeAngle``.

Directions
----------
``SpotLight.direction`` and ``DirectionalLight.direction`` are the direction the light *travels*
(world frame, unit-normalised on construction); the direction *to* a directional light is
``-direction``. :func:`incident` returns unit directions from the lit point *towards* each light.

Light maps
----------
``E_perp`` is a light's irradiance at normal incidence (lux, RGB). With ``l`` the direction to the
light, the maps of :func:`light_maps` are (all with "constant environment L gives L"
normalisation, see :mod:`probegrid.core.lobes`)::

    diffuse[N]        = sum_lights E_perp max(0, N . l) / pi            (= irradiance / pi)
    specular_k[R]     = sum_lights E_perp ggx_kernel(R . l, a_k) / ggx_kernel_integral(a_k)
    phong_P[R]        = sum_lights E_perp max(0, R . l)^P (P + 1) / (2 pi)

with ``a_k = (k / (levels - 1))^2``. Level 0 of the specular chain (``a = 0``) is a delta: the
light's whole ``E_perp`` goes into the one texel containing ``l`` as radiance
``E_perp / texel_solid_angle``.

A diffuse texel holds the map at its centre, ``E_perp max(0, N_texel . l) / pi`` exactly, like a
diffuse convolution evaluated at texel centres (so the map adds to the filters' diffuse maps); the
solid-angle integral of such a map is ``E_perp`` to 0.07 % at ``n = 16``, 0.3 % at 8, 2 % at 4
(worst light direction). A specular or Phong texel holds the *mean of the map over its solid
angle* (the convention of :func:`probegrid.core.cubemap.downsample`), so the integral of every level is
``E_perp`` however narrow the lobe. The mean is the midpoint rule on an ``m x m`` subdivision of
the texel (the texels of the ``n m`` cube, so sub-solid-angles are exact), with
``m = ceil(SUBSAMPLES_PER_LOBE * (2 / n) / width)`` samples across the lobe's angular width
(``1 / sqrt(P)`` for Phong, ``alpha`` for GGX), capped so ``n m <= MAX_SUBSAMPLED_SIZE``; a lobe
at least ``SUBSAMPLES_PER_LOBE`` texels wide gets ``m = 1``, the value at the centre.

:func:`splat_delta` folds a punctual light into an *incoming radiance* cube instead, so that any
filter applied afterwards sees it (the bake's path).

References
----------
* Khronos, "KHR_lights_punctual", glTF 2.0 extension specification (2018).
* C. Bloom, "Cube Map Lighting", 2004.
* B. Karis, "Real Shading in Unreal Engine 4", SIGGRAPH 2013 course notes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core.cubemap import (
    CubeMap,
    check_cube,
    direction_to_face_uv,
    direction_to_texel,
    face_uv_to_direction,
    mip_sizes,
    texel_directions,
    texel_solid_angles,
    texel_to_uv,
    uv_to_texel,
)
from probegrid.core.lobes import (
    ALPHA_DELTA,
    ggx_kernel,
    ggx_kernel_integral,
    level_roughness,
    phong_kernel,
    phong_kernel_integral,
    roughness_to_alpha,
)

__all__ = [
    "DirectionalLight",
    "Light",
    "PackedLights",
    "PointLight",
    "SpotLight",
    "incident",
    "incident_many",
    "light_maps",
    "light_maps_work",
    "pack_lights",
    "range_attenuation",
    "splat_delta",
    "spot_attenuation",
]

#: Midpoint-rule samples per lobe width when a texel is averaged (see module docstring).
SUBSAMPLES_PER_LOBE: Final[int] = 6
#: Largest face size of the subdivided cube a map is averaged from.
MAX_SUBSAMPLED_SIZE: Final[int] = 1024
#: Upper bound on the elements of one (texels x lights) block, to bound memory.
_CHUNK_ELEMENTS: Final[int] = 1 << 21

_POINT, _SPOT, _DIRECTIONAL = 0, 1, 2


def _vec3(value: ArrayLike, name: str) -> tuple[float, float, float]:
    a = np.asarray(value, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"{name} must be a 3-vector, got shape {a.shape}.")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a.tolist()}.")
    return (float(a[0]), float(a[1]), float(a[2]))


def _color(value: ArrayLike) -> tuple[float, float, float]:
    c = _vec3(value, "color")
    if min(c) < 0:
        raise ValueError(f"color must be non-negative linear RGB, got {list(c)}.")
    return c


def _unit(value: ArrayLike, name: str) -> tuple[float, float, float]:
    d = np.asarray(_vec3(value, name))
    norm = float(np.linalg.norm(d))
    if not norm > 0:
        raise ValueError(f"{name} must be a non-zero vector.")
    d = d / norm
    return (float(d[0]), float(d[1]), float(d[2]))


def _intensity(value: float, unit: str) -> float:
    x = float(value)
    if not (math.isfinite(x) and x >= 0):
        raise ValueError(f"intensity must be a finite non-negative number of {unit}, got {value}.")
    return x


def _range(value: float | None) -> float | None:
    if value is None:
        return None
    x = float(value)
    if not (x > 0 and not math.isnan(x)):
        raise ValueError(f"range must be > 0 (or None for an infinite range), got {value}.")
    return None if math.isinf(x) else x


@dataclass(frozen=True)
class PointLight:
    """A point light (glTF ``"point"``).

    Attributes
    ----------
    position : (3,) float
        World position, metres.
    color : (3,) float
        Linear RGB, non-negative; multiplies ``intensity``.
    intensity : float
        Luminous intensity, candela (lm/sr).
    range : float or None
        Cutoff distance of the spec's range window (> 0); ``None`` = infinite (pure 1/d^2).
    """

    position: tuple[float, float, float]
    color: tuple[float, float, float]
    intensity: float
    range: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _vec3(self.position, "position"))
        object.__setattr__(self, "color", _color(self.color))
        object.__setattr__(self, "intensity", _intensity(self.intensity, "candela"))
        object.__setattr__(self, "range", _range(self.range))


@dataclass(frozen=True)
class SpotLight:
    """A spot light (glTF ``"spot"``).

    Attributes
    ----------
    position : (3,) float
        World position, metres.
    direction : (3,) float
        World direction the spot points (the node's -Z axis), unit-normalised on construction.
    color : (3,) float
        Linear RGB, non-negative.
    intensity : float
        Luminous intensity inside the inner cone, candela.
    range : float or None
        As for :class:`PointLight`.
    inner_cone_angle, outer_cone_angle : float
        Radians from the spot axis, ``0 <= inner < outer <= pi / 2`` (glTF defaults 0 and pi/4).
    """

    position: tuple[float, float, float]
    direction: tuple[float, float, float]
    color: tuple[float, float, float]
    intensity: float
    range: float | None = None
    inner_cone_angle: float = 0.0
    outer_cone_angle: float = math.pi / 4

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _vec3(self.position, "position"))
        object.__setattr__(self, "direction", _unit(self.direction, "direction"))
        object.__setattr__(self, "color", _color(self.color))
        object.__setattr__(self, "intensity", _intensity(self.intensity, "candela"))
        object.__setattr__(self, "range", _range(self.range))
        inner, outer = float(self.inner_cone_angle), float(self.outer_cone_angle)
        if not 0.0 <= inner < outer <= math.pi / 2:
            raise ValueError(
                "cone angles must satisfy 0 <= inner_cone_angle < outer_cone_angle <= pi/2, "
                f"got inner={self.inner_cone_angle}, outer={self.outer_cone_angle}."
            )
        object.__setattr__(self, "inner_cone_angle", inner)
        object.__setattr__(self, "outer_cone_angle", outer)

    @property
    def angle_scale_offset(self) -> tuple[float, float]:
        """The spec's ``(lightAngleScale, lightAngleOffset)``."""
        ci, co = math.cos(self.inner_cone_angle), math.cos(self.outer_cone_angle)
        scale = 1.0 / max(0.001, ci - co)
        return scale, -co * scale


@dataclass(frozen=True)
class DirectionalLight:
    """A directional light (glTF ``"directional"``), infinitely far, not attenuated.

    Attributes
    ----------
    direction : (3,) float
        World direction the light travels (the node's -Z axis), unit-normalised on construction.
    color : (3,) float
        Linear RGB, non-negative.
    intensity : float
        Illuminance at normal incidence, lux (lm/m^2).
    """

    direction: tuple[float, float, float]
    color: tuple[float, float, float]
    intensity: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "direction", _unit(self.direction, "direction"))
        object.__setattr__(self, "color", _color(self.color))
        object.__setattr__(self, "intensity", _intensity(self.intensity, "lux"))


Light = PointLight | SpotLight | DirectionalLight


def range_attenuation(distance: ArrayLike, light_range: ArrayLike | None = None) -> NDArray:
    """The spec's distance attenuation ``clamp(1 - (d / range)^4, 0, 1) / d^2``.

    Parameters
    ----------
    distance : (...) float
        Distance to the light, metres, > 0.
    light_range : (...) float or None
        Range; ``None`` or ``inf`` gives ``1 / d^2``.

    Returns
    -------
    (...) float64, 1/m^2
    """
    d = np.asarray(distance, dtype=np.float64)
    inv_d2 = 1.0 / (d * d)
    if light_range is None:
        return inv_d2
    r = np.asarray(light_range, dtype=np.float64)
    window = np.clip(1.0 - (d / r) ** 4, 0.0, 1.0)
    return window * inv_d2


def spot_attenuation(
    cos_angle: ArrayLike, inner_cone_angle: ArrayLike, outer_cone_angle: ArrayLike
) -> NDArray:
    """The spec's angular attenuation of a spot light.

    Parameters
    ----------
    cos_angle : (...) float
        Cosine between the spot axis and the unit vector from the light to the lit point.
    inner_cone_angle, outer_cone_angle : (...) float
        Radians.

    Returns
    -------
    (...) float64 in [0, 1]: ``saturate(cos_angle * scale + offset)^2``.
    """
    ci = np.cos(np.asarray(inner_cone_angle, dtype=np.float64))
    co = np.cos(np.asarray(outer_cone_angle, dtype=np.float64))
    scale = 1.0 / np.maximum(0.001, ci - co)
    offset = -co * scale
    a = np.clip(np.asarray(cos_angle, dtype=np.float64) * scale + offset, 0.0, 1.0)
    return a * a


@dataclass(frozen=True)
class PackedLights:
    """Lights as arrays, (L, ...): what vectorised and compiled code evaluates."""

    kind: NDArray[np.intp]
    position: NDArray[np.float64]  # (L, 3); zeros for directional lights
    axis: NDArray[np.float64]  # (L, 3) direction the light travels / points; zeros for points
    power: NDArray[np.float64]  # (L, 3) color * intensity
    range: NDArray[np.float64]  # (L,) inf when unlimited
    angle_scale: NDArray[np.float64]  # (L,) 0 for non-spots
    angle_offset: NDArray[np.float64]  # (L,) 1 for non-spots (attenuation 1)


def pack_lights(lights: Sequence[Light]) -> PackedLights:
    """The lights as arrays (kind 0 point, 1 spot, 2 directional)."""
    if isinstance(lights, (PointLight, SpotLight, DirectionalLight)):
        lights = [lights]
    lights = list(lights)
    for i, light in enumerate(lights):
        if not isinstance(light, (PointLight, SpotLight, DirectionalLight)):
            raise ValueError(  # noqa: TRY004 (project rule: bad arguments raise ValueError)
                f"lights[{i}] must be a PointLight, SpotLight or DirectionalLight, "
                f"got {type(light).__name__}."
            )
    n = len(lights)
    kind = np.empty(n, dtype=np.intp)
    position = np.zeros((n, 3))
    axis = np.zeros((n, 3))
    power = np.zeros((n, 3))
    rng = np.full(n, np.inf)
    scale = np.zeros(n)
    offset = np.ones(n)
    for i, light in enumerate(lights):
        power[i] = np.asarray(light.color) * light.intensity
        if isinstance(light, DirectionalLight):
            kind[i] = _DIRECTIONAL
            axis[i] = light.direction
            continue
        position[i] = light.position
        if light.range is not None:
            rng[i] = light.range
        if isinstance(light, SpotLight):
            kind[i] = _SPOT
            axis[i] = light.direction
            scale[i], offset[i] = light.angle_scale_offset
        else:
            kind[i] = _POINT
    return PackedLights(kind, position, axis, power, rng, scale, offset)


def _positions(positions: ArrayLike, name: str) -> NDArray[np.float64]:
    p = np.asarray(positions, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise ValueError(f"{name} must have shape (..., 3), got {p.shape}.")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be finite.")
    return p


def incident_many(
    lights: Sequence[Light], positions: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Direction, irradiance and distance of every light at every position.

    Parameters
    ----------
    lights : sequence of PointLight, SpotLight, DirectionalLight
        ``L`` lights (may be empty).
    positions : (..., 3) float
        World positions, metres.

    Returns
    -------
    directions : (..., L, 3) float64
        Unit direction from the position towards each light (``-direction`` for a directional
        light).
    irradiance : (..., L, 3) float64
        RGB irradiance at normal incidence ``E_perp``, lux: ``color * intensity * attenuation``
        with the spec's range window and spot cone (see the module docstring).
    distance : (..., L) float64
        Metres; ``inf`` for directional lights.

    Notes
    -----
    A position exactly at a point or spot light's position gets direction ``(0, 0, 0)`` and
    irradiance 0 for that light (the direction is undefined and the inverse-square law diverges);
    every other distance follows the law. Memory is ``O(positions x lights)``: callers chunk.
    """
    p = _positions(positions, "positions")
    pk = pack_lights(lights)
    to = pk.position - p[..., None, :]  # (..., L, 3)
    dist = np.linalg.norm(to, axis=-1)
    directional = pk.kind == _DIRECTIONAL
    at_light = (dist == 0) & ~directional
    safe = np.where(dist == 0, 1.0, dist)
    dirs = to / safe[..., None]
    dirs = np.where(directional[:, None], -pk.axis, dirs)
    dirs = np.where(at_light[..., None], 0.0, dirs)
    dist = np.where(directional, np.inf, dist)
    atten = np.where(directional, 1.0, range_attenuation(safe, pk.range))
    cd = -np.einsum("...i,...i->...", dirs, pk.axis)  # axis . (light -> point)
    spot = np.clip(cd * pk.angle_scale + pk.angle_offset, 0.0, 1.0) ** 2
    atten = np.where(pk.kind == _SPOT, atten * spot, atten)
    atten = np.where(at_light, 0.0, atten)
    return dirs, atten[..., None] * pk.power, dist


def incident(
    lights: Sequence[Light], position: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """:func:`incident_many` at one position.

    Parameters
    ----------
    lights : sequence of lights, ``L`` of them
    position : (3,) float

    Returns
    -------
    directions : (L, 3) float64, unit, towards each light
    irradiance : (L, 3) float64, RGB ``E_perp`` in lux
    distance : (L,) float64, metres (``inf`` for directional lights)
    """
    p = _positions(position, "position")
    if p.shape != (3,):
        raise ValueError(f"position must have shape (3,), got {p.shape}; see incident_many.")
    return incident_many(lights, p)


# --------------------------------------------------------------------------------------------
# Light maps


def _subdivision(n: int, width: float | None) -> int:
    """Texel subdivision ``m`` that puts SUBSAMPLES_PER_LOBE samples across a lobe ``width``
    (radians; ``None``: 1, centre sampling)."""
    if width is None:
        return 1
    m = math.ceil(SUBSAMPLES_PER_LOBE * (2.0 / n) / width)
    return int(min(max(m, 1), max(MAX_SUBSAMPLED_SIZE // n, 1)))


def _lobe_map(
    dirs: NDArray[np.float64],
    energy: NDArray[np.float64],
    n: int,
    kernel: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    width: float | None,
) -> NDArray[np.float32]:
    """``sum_l energy_l kernel(D . dirs_l)`` averaged over each texel of an ``n`` cube.

    ``kernel`` maps (..., L) cosines to the normalised lobe (1/sr); ``width`` is the lobe's
    angular width (radians) that sets the texel subdivision, ``None`` for centre values.
    """
    c = energy.shape[-1]
    out = np.zeros((6, n, n, c))
    if dirs.shape[0] == 0:
        return out.astype(np.float32)
    m = _subdivision(n, width)
    fine = n * m
    d = texel_directions(fine)
    w = texel_solid_angles(fine)
    chunk = max(1, _CHUNK_ELEMENTS // (fine * fine))
    for f in range(6):
        df = d[f].reshape(-1, 3)
        acc = np.zeros((fine * fine, c))
        for s in range(0, dirs.shape[0], chunk):
            k = kernel(df @ dirs[s : s + chunk].T)  # (fine^2, chunk)
            acc += k @ energy[s : s + chunk]
        wf = w[f].reshape(n, m, n, m, 1)
        num = (acc.reshape(n, m, n, m, c) * wf).sum(axis=(1, 3))
        out[f] = num / wf.sum(axis=(1, 3))
    return out.astype(np.float32)


@dataclass(frozen=True)
class LightMapsWork:
    """What :func:`light_maps` computes, counted before it runs (its cost model's inputs).

    Attributes
    ----------
    texels : int
        Texels of every (subdivided) cube it fills, the directions and solid angles it makes.
    evaluations : int
        Lobe-kernel evaluations: texels times lights, summed over the maps (the dominant cost).
    """

    texels: int
    evaluations: int


def light_maps_work(
    n_lights: int,
    *,
    diffuse_size: int = 16,
    specular_size: int = 32,
    specular_levels: int | None = None,
    phong_exponents: Sequence[float] = (),
) -> LightMapsWork:
    """The work of :func:`light_maps` with the same arguments and ``n_lights`` lights, from the
    same subdivision rule, without making any map (every light counted as lit).

    Raises
    ------
    ValueError
        A face size or chain :func:`light_maps` would refuse (:func:`mip_sizes`).
    """
    mip_sizes(diffuse_size, 1)
    sizes = mip_sizes(specular_size, specular_levels)
    fine = [diffuse_size]  # centre values: no subdivision
    delta = 0
    for k, n in enumerate(sizes):
        alpha = float(roughness_to_alpha(level_roughness(k, len(sizes))))
        if alpha < ALPHA_DELTA:
            delta += 6 * n * n  # a splat, no kernel
            continue
        fine.append(n * _subdivision(n, alpha))
    for e in phong_exponents:
        width = 1.0 / math.sqrt(max(float(e), 1.0))  # as light_maps
        fine.append(specular_size * _subdivision(specular_size, width))
    texels = sum(6 * f * f for f in fine)
    return LightMapsWork(texels=texels + delta, evaluations=texels * max(int(n_lights), 0))


def light_maps(
    lights: Sequence[Light],
    position: ArrayLike,
    *,
    diffuse_size: int = 16,
    specular_size: int = 32,
    specular_levels: int | None = None,
    phong_exponents: Sequence[float] = (),
) -> dict[str, object]:
    """Analytic diffuse, GGX-specular and Phong cube maps of punctual lights seen from a point.

    No visibility: every light reaches ``position`` (the bake handles shadows).

    Parameters
    ----------
    lights : sequence of lights
    position : (3,) float
        Where the maps are taken, metres.
    diffuse_size : int
        Face size of the diffuse map.
    specular_size : int
        Face size of level 0 of the specular chain and of every Phong map (power of two for a
        full chain).
    specular_levels : int or None
        Mip levels of the specular chain (default: the full chain down to 1 x 1); level ``k``
        holds perceptual roughness ``k / (levels - 1)``.
    phong_exponents : sequence of float
        Cosine powers ``P >= 0`` of the Phong maps to make.

    Returns
    -------
    dict
        ``"diffuse"``: :class:`CubeMap` (kind ``"diffuse"``), ``E_perp max(0, N . l) / pi``;
        ``"specular"``: :class:`CubeMap` (kind ``"specular"``) with ``levels`` mips;
        ``"phong"``: ``{float(P): CubeMap}`` (kind ``"other"``),
        ``E_perp max(0, R . l)^P (P + 1) / (2 pi)``. All float32 RGB radiance, cd/m^2; diffuse
        texels hold the map at their centre, specular and Phong texels its mean over the texel
        (see the module docstring).
    """
    p = _positions(position, "position")
    if p.shape != (3,):
        raise ValueError(f"position must have shape (3,), got {p.shape}.")
    exponents = [float(e) for e in phong_exponents]
    for e in exponents:
        if not (math.isfinite(e) and e >= 0):
            raise ValueError(f"Phong exponents must be finite and >= 0, got {e}.")
    dirs, irradiance, _ = incident(lights, p)
    lit = np.any(irradiance > 0, axis=-1)
    dirs, irradiance = dirs[lit], irradiance[lit]
    mip_sizes(diffuse_size, 1)  # validates the face size
    sizes = mip_sizes(specular_size, specular_levels)

    diffuse = _lobe_map(
        dirs, irradiance, diffuse_size, lambda c: np.maximum(c, 0.0) / np.pi, width=None
    )

    levels = []
    for k, size in enumerate(sizes):
        alpha = float(roughness_to_alpha(level_roughness(k, len(sizes))))
        if alpha < ALPHA_DELTA:
            empty = np.zeros((6, size, size, 3), dtype=np.float32)
            levels.append(splat_delta(empty, dirs, irradiance, footprint=0))
            continue
        norm = ggx_kernel_integral(alpha)
        levels.append(
            _lobe_map(
                dirs, irradiance, size, lambda c, a=alpha, z=norm: ggx_kernel(c, a) / z, alpha
            )
        )

    phong = {}
    for e in exponents:
        # max(0, c)^0 is 1 behind the lobe too (0^0 = 1): mask c <= 0 so P = 0 is a hemisphere,
        # whose integral 2 pi is what phong_kernel_integral(0) divides by.
        norm = phong_kernel_integral(e)
        phong[e] = CubeMap.from_faces(
            _lobe_map(
                dirs,
                irradiance,
                specular_size,
                lambda c, p_=e, z=norm: np.where(c > 0, phong_kernel(c, p_), 0.0) / z,
                1.0 / math.sqrt(max(e, 1.0)),
            )
        )
    return {
        "diffuse": CubeMap.from_faces(diffuse, kind="diffuse"),
        "specular": CubeMap(tuple(levels), kind="specular"),
        "phong": phong,
    }


# --------------------------------------------------------------------------------------------
# Delta lights into incoming-radiance cubes


def splat_delta(
    faces: ArrayLike,
    direction: ArrayLike,
    irradiance: ArrayLike,
    *,
    footprint: int = 1,
) -> NDArray[np.float32]:
    """Add punctual lights to an incoming-radiance cube, preserving their irradiance exactly.

    Each light's energy ``E`` (irradiance at normal incidence, the solid-angle integral of the
    radiance it adds) is spread over the texels around its direction with tent weights
    ``w_ij = t(col_j - s) t(row_i - t_)`` (``t(x) = max(0, 1 - |x| / footprint)``, ``(s, t_)`` the
    light's continuous texel coordinate on its face), normalised to sum to 1; texel ``i`` receives
    radiance ``E w_i / solid_angle_i``, so ``sum(added * solid_angle) == E`` up to float32
    rounding of the stored radiance. The weights live on the lattice of the light's face extended
    past its edges; each lattice point is mapped to the texel containing its direction, so the
    footprint continues seamlessly onto the neighbouring faces. On a flat lattice, tents of
    integer half-width reproduce linear functions, so the energy centroid is the light's
    direction exactly within a face and to a fraction of a texel across edges.

    Parameters
    ----------
    faces : (6, n, n, C) float
        Incoming radiance cube (not modified).
    direction : (3,) or (L, 3) float
        Directions towards the lights (need not be unit).
    irradiance : (C,) or (L, C) float
        ``E_perp`` of each light, e.g. from :func:`incident`.
    footprint : int
        Tent half-width in texels: 0 = all energy in the texel containing the direction;
        1 = bilinear over the 2 x 2 nearest texel centres (default); ``r`` = ``2r x 2r`` texels.

    Returns
    -------
    (6, n, n, C) float32
        ``faces`` plus the lights.
    """
    cube = check_cube(faces)
    n, c = cube.shape[1], cube.shape[3]
    if isinstance(footprint, bool) or not isinstance(footprint, (int, np.integer)):
        raise ValueError(  # noqa: TRY004 (project rule: bad arguments raise ValueError)
            f"footprint must be an integer number of texels, got {footprint!r}."
        )
    if not 0 <= footprint <= n:
        raise ValueError(f"footprint must be between 0 and the face size {n}, got {footprint}.")
    d = np.asarray(direction, dtype=np.float64)
    if d.shape[-1:] != (3,) or d.ndim > 2:
        raise ValueError(f"direction must have shape (3,) or (L, 3), got {d.shape}.")
    d = d.reshape(-1, 3)
    e = np.asarray(irradiance, dtype=np.float64)
    if e.ndim == 0 or e.ndim > 2 or e.shape[-1] != c:
        raise ValueError(f"irradiance must have shape ({c},) or (L, {c}), got {e.shape}.")
    try:
        e = np.broadcast_to(e.reshape(-1, c), (d.shape[0], c))
    except ValueError:
        raise ValueError(
            f"irradiance {e.shape} does not match {d.shape[0]} directions."
        ) from None
    if not (np.all(np.isfinite(d)) and np.all(np.isfinite(e))):
        raise ValueError("direction and irradiance must be finite.")
    if np.any(np.linalg.norm(d, axis=-1) == 0):
        raise ValueError("direction must be non-zero.")

    out = cube.astype(np.float64)
    if d.shape[0] == 0:
        return out.astype(np.float32)
    solid = texel_solid_angles(n)
    if footprint == 0:
        f, row, col = direction_to_texel(d, n)
        weights = np.ones((d.shape[0], 1))
        f, row, col = f[:, None], row[:, None], col[:, None]
    else:
        face, u, v = direction_to_face_uv(d)
        s, t = uv_to_texel(u, n), uv_to_texel(v, n)  # continuous (col, row)
        k = np.arange(-footprint + 1, footprint + 1)
        cols = np.floor(s)[:, None] + k  # (L, 2r)
        rows = np.floor(t)[:, None] + k
        wc = np.maximum(0.0, 1.0 - np.abs(cols - s[:, None]) / footprint)
        wr = np.maximum(0.0, 1.0 - np.abs(rows - t[:, None]) / footprint)
        weights = (wr[:, :, None] * wc[:, None, :]).reshape(d.shape[0], -1)
        weights /= weights.sum(axis=1, keepdims=True)
        uu = np.broadcast_to(texel_to_uv(cols, n)[:, None, :], wr.shape + wc.shape[1:])
        vv = np.broadcast_to(texel_to_uv(rows, n)[:, :, None], uu.shape)
        lattice = face_uv_to_direction(face[:, None, None], uu, vv).reshape(d.shape[0], -1, 3)
        f, row, col = direction_to_texel(lattice, n)
    radiance = e[:, None, :] * (weights / solid[f, row, col])[..., None]  # (L, K, C)
    flat = (f * n + row) * n + col
    np.add.at(out.reshape(-1, c), flat.ravel(), radiance.reshape(-1, c))
    return out.astype(np.float32)
