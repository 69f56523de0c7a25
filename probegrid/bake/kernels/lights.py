"""The punctual lights' shadow rays at surface points, and the sums of unblocked shadow rays.

* :func:`light_rays` -- :func:`probegrid.core.lights.incident_many` and the choice of shadow
  rays (``tests/test_bake_kernels.py`` compares them);
* :func:`sum_unblocked` -- what the unblocked shadow rays of each point deliver (the punctual
  lights' and the environment's estimate).

A scene's lights reach the kernel as one :class:`PunctualLights`
(:func:`probegrid.core.lights.pack_lights`' arrays). Floating point: :mod:`probegrid._jit`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import kernel
from probegrid.core.lights import Light, pack_lights
from probegrid.raytrace.kernels import _embree_ray

__all__ = ["PunctualLights", "light_rays", "sum_unblocked"]


class PunctualLights(NamedTuple):
    """The punctual lights as :func:`light_rays` reads them (``L`` lights)."""

    #: (L,) int64: 0 point, 1 spot, 2 directional.
    kind: NDArray[np.int64]
    #: (L, 3) position (points and spots).
    position: NDArray[np.float64]
    #: (L, 3) unit direction the light travels (spots and directional lights).
    axis: NDArray[np.float64]
    #: (L, 3) intensity (cd) or illuminance (lux, directional), per channel.
    power: NDArray[np.float64]
    #: (L,) range (inf: none).
    range: NDArray[np.float64]
    #: (L,) the spot cone's ``scale``.
    angle_scale: NDArray[np.float64]
    #: (L,) the spot cone's ``offset``.
    angle_offset: NDArray[np.float64]

    @classmethod
    def of(cls, lights: Sequence[Light]) -> PunctualLights:
        """The table of a scene's ``lights`` (:func:`probegrid.core.lights.pack_lights`)."""
        pk = pack_lights(lights)
        return cls(pk.kind.astype(np.int64), pk.position, pk.axis, pk.power, pk.range,
                   pk.angle_scale, pk.angle_offset)


@kernel
def light_rays(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    lights: PunctualLights,
    eps: float,
    centre: NDArray[np.float64],
) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.float32], NDArray[np.float32],
           NDArray[np.float64], bool]:
    """The shadow rays of the punctual lights at surface points, and what each would deliver.

    :func:`probegrid.core.lights.incident_many` (kinds 0 point, 1 spot, 2 directional; the spec's
    range window ``clamp(1 - (d / range)^4, 0, 1) / d^2`` and spot cone
    ``saturate(cos * scale + offset)^2``) fused with the selection of
    :meth:`probegrid.bake.view.ProbeView.visible_lights`: a (point, light) pair gets a shadow
    ray when the light delivers ``E_perp > 0`` and lies in front of the surface
    (``cos = dot(l, n) > 0``). The ray starts ``eps`` along the normal, with ``tmin = eps`` and
    ``tmax = distance - eps`` (inf for directional lights), and is written as Embree takes it
    (:func:`probegrid.raytrace.kernels._embree_ray`, re-centred on ``centre``, the tracer's).
    ``lights`` is the scene's :class:`PunctualLights`.

    Returns
    -------
    point : (k,) int64
        Which point each ray belongs to.
    origins, directions : (k, 3) float32; lengths : (k,) float32
        The rays (:class:`probegrid.raytrace.EmbreeRays`).
    irradiance : (k, 3) float64
        ``cos * E_perp`` (lux) the point receives if the ray is not occluded.
    ok : bool
        Whether every ray is finite in float32.
    """
    kind, light_pos, axis, power, light_range, angle_scale, angle_offset = lights
    n, nl = points.shape[0], kind.shape[0]
    cap = n * nl
    which = np.empty(cap, np.int64)
    org = np.empty((cap, 3), np.float32)
    dirs = np.empty((cap, 3), np.float32)
    far = np.empty(cap, np.float32)
    rays = (org, dirs, far)
    irr = np.empty((cap, 3))
    ok = True
    k = 0
    for i in range(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        for li in range(nl):
            if kind[li] == 2:
                lx, ly, lz = -axis[li, 0], -axis[li, 1], -axis[li, 2]
                dist = math.inf
                atten = 1.0
            else:
                tx = light_pos[li, 0] - px
                ty = light_pos[li, 1] - py
                tz = light_pos[li, 2] - pz
                dist = math.sqrt(tx * tx + ty * ty + tz * tz)
                if dist == 0.0:
                    continue  # at the light: no direction, no light (incident_many)
                lx, ly, lz = tx / dist, ty / dist, tz / dist
                atten = 1.0 / (dist * dist)
                r = light_range[li]
                if r < math.inf:
                    q = dist / r
                    atten *= min(max(1.0 - q * q * q * q, 0.0), 1.0)
                if kind[li] == 1:
                    cd = -(lx * axis[li, 0] + ly * axis[li, 1] + lz * axis[li, 2])
                    a = min(max(cd * angle_scale[li] + angle_offset[li], 0.0), 1.0)
                    atten *= a * a
            e0, e1, e2 = atten * power[li, 0], atten * power[li, 1], atten * power[li, 2]
            if not max(e0, e1, e2) > 0:
                continue
            cos = lx * nx + ly * ny + lz * nz
            if not cos > 0:
                continue
            which[k] = i
            if not _embree_ray(rays, k, (px + eps * nx, py + eps * ny, pz + eps * nz),
                               (lx, ly, lz), eps, dist - eps if dist < math.inf else math.inf,
                               centre):
                ok = False
            irr[k, 0], irr[k, 1], irr[k, 2] = cos * e0, cos * e1, cos * e2
            k += 1
    return which[:k], org[:k], dirs[:k], far[:k], irr[:k], ok


@kernel
def sum_unblocked(n: int, which: NDArray[np.int64], blocked: NDArray[np.bool_],
                  values: NDArray[np.float64]) -> NDArray[np.float64]:
    """``out[i] = sum of values[k] over k with which[k] == i and not blocked[k]``; ``(n, C)``."""
    out = np.zeros((n, values.shape[1]))
    for k in range(which.shape[0]):
        if not blocked[k]:
            i = which[k]
            for c in range(values.shape[1]):
                out[i, c] += values[k, c]
    return out
