"""Compiled conversions of rays to and from Embree's float32 (the tracer's kernels).

Embree takes float32 rays re-centred on the geometry's centre (:class:`~probegrid.raytrace.
tracer.RayTracer`); every ray cast of the project is written by one rounding rule,
:func:`_embree_ray`: the origin ``(o - centre) + tmin d`` in float64, rounded to float32 once,
the direction rounded, the length ``tmax - tmin``. The bake's shadow-ray kernels
(:mod:`probegrid.bake.kernels`) write their rays by it too, as Embree takes them
(:class:`~probegrid.raytrace.rays.EmbreeRays`): no float64 copy of them is made and converted.

* :func:`embree_rays`, :func:`embree_hits` -- :class:`~probegrid.raytrace.tracer.RayTracer`'s
  conversions to and from Embree's rays (tested through the tracer, ``tests/test_raytrace.py``);
* :func:`segment_rays` -- the query's segments as occlusion rays (``tests/test_query_visibility.py``
  compares it with the array expression it restates).

Floating point: the rules of :mod:`probegrid._jit` (float64, FMA contraction and reciprocal
multiplication allowed); float32 only where Embree takes it.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import inline_kernel, kernel

__all__ = ["embree_hits", "embree_rays", "segment_rays"]

#: Room for rays as Embree takes them: float32 ``origins (k, 3)``, ``directions (k, 3)``,
#: ``lengths (k,)`` (:class:`~probegrid.raytrace.rays.EmbreeRays`' fields, in its order).
RayBuffers = tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]
Vector = tuple[float, float, float]


@inline_kernel
def _embree_ray(rays: RayBuffers, k: int, origin: Vector, direction: Vector, lo: float,
                hi: float, centre: NDArray[np.float64]) -> bool:
    """Ray ``k`` of ``rays`` as Embree takes it (:class:`~probegrid.raytrace.rays.EmbreeRays`):
    the origin ``(o - centre) + lo d`` in float64, rounded to float32 once, the direction
    rounded, the length ``hi - lo``. Returns whether the origin and direction are finite in
    float32. The one rounding rule of every ray cast (:func:`embree_rays`, :func:`segment_rays`
    and the bake's shadow rays)."""
    org, d32, far = rays
    ox, oy, oz = origin
    dx, dy, dz = direction
    a0 = np.float32((ox - centre[0]) + lo * dx)
    a1 = np.float32((oy - centre[1]) + lo * dy)
    a2 = np.float32((oz - centre[2]) + lo * dz)
    b0, b1, b2 = np.float32(dx), np.float32(dy), np.float32(dz)
    org[k, 0], org[k, 1], org[k, 2] = a0, a1, a2
    d32[k, 0], d32[k, 1], d32[k, 2] = b0, b1, b2
    far[k] = hi - lo
    # finite iff their float64 sum is (six float32 magnitudes cannot overflow it; an inf or
    # a nan among them makes it inf or nan): one test, no branch per component
    return math.isfinite((np.float64(a0) + np.float64(a1) + np.float64(a2))
                         + (np.float64(b0) + np.float64(b1) + np.float64(b2)))


@kernel
def embree_rays(
    origins: NDArray[np.float64],
    directions: NDArray[np.float64],
    tmin: NDArray[np.float64],
    tmax: NDArray[np.float64],
    centre: NDArray[np.float64],
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32], bool]:
    """Rays as Embree takes them: float32 origins moved to ``tmin`` and re-centred, directions,
    and segment lengths ``tmax - tmin`` (:meth:`probegrid.raytrace.RayTracer._embree_rays`).

    ``origins (1 or m, 3)``, ``directions (m, 3)``, ``tmin``/``tmax (1 or m,)`` float64 (a single
    row is shared by every ray), ``centre (3,)``. The origin is ``(o - centre) + tmin d`` in
    float64, rounded once. The last value is False if an origin or direction is not finite in
    float32.
    """
    m = directions.shape[0]
    org = np.empty((m, 3), np.float32)
    d32 = np.empty((m, 3), np.float32)
    far = np.empty(m, np.float32)
    rays = (org, d32, far)
    one_o = origins.shape[0] == 1
    one_lo = tmin.shape[0] == 1
    one_hi = tmax.shape[0] == 1
    ok = True
    for i in range(m):
        io = 0 if one_o else i
        if not _embree_ray(rays, i, (origins[io, 0], origins[io, 1], origins[io, 2]),
                           (directions[i, 0], directions[i, 1], directions[i, 2]),
                           tmin[0] if one_lo else tmin[i], tmax[0] if one_hi else tmax[i],
                           centre):
            ok = False
    return org, d32, far, ok


@kernel
def embree_hits(
    answers: tuple[NDArray[np.int32], NDArray[np.float32], NDArray[np.float32],
                   NDArray[np.float32]],
    tmin: NDArray[np.float64],
    start: int,
    out: tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64],
               NDArray[np.float64]],
) -> None:
    """Copy Embree's ``answers`` ``(primID, tfar, u, v)`` for rays ``start:start + m`` into
    ``out`` ``(prim_id, t, u, v)`` float64 / int64 (:class:`~probegrid.raytrace.rays.Hits`'
    fields): the hit distance measured from the ray's origin (``tfar + tmin``;
    ``tmin (1 or n,)``), inf and barycentrics 0 for a miss (``primID < 0``)."""
    prim_id, tfar, u, v = answers
    prim_out, t_out, u_out, v_out = out
    one_lo = tmin.shape[0] == 1
    for j in range(prim_id.shape[0]):
        i = start + j
        p = prim_id[j]
        prim_out[i] = p
        if p < 0:
            t_out[i] = math.inf
            u_out[i] = 0.0
            v_out[i] = 0.0
        else:
            t_out[i] = np.float64(tfar[j]) + (tmin[0] if one_lo else tmin[i])
            u_out[i] = u[j]
            v_out[i] = v[j]


@kernel
def segment_rays(
    starts: NDArray[np.float64],
    ends: NDArray[np.float64],
    margin: float,
    centre: NDArray[np.float64],
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32], bool]:
    """Segments ``starts[k] -> ends[k]`` (``starts`` one row: shared) as Embree occlusion rays,
    ``margin`` left out at both ends (:meth:`probegrid.raytrace.RayTracer.segments_occluded`;
    the query side, not the bake).

    The array expression it restates (``tests/test_query_visibility.py`` compares them)::

        d = ends - starts
        lo = margin / max(|d|, 1e-30)
        org = float32((starts - centre) + lo d);  dirs = float32(d);  far = float32(1 - 2 lo)

    ``far <= 0`` marks a segment no longer than ``2 margin`` (never occluded). The last value is
    False if an origin or direction is not finite in float32.
    """
    m = ends.shape[0]
    one = starts.shape[0] == 1  # one start shared by every segment
    org = np.empty((m, 3), np.float32)
    d32 = np.empty((m, 3), np.float32)
    far = np.empty(m, np.float32)
    rays = (org, d32, far)
    ok = True
    for i in range(m):
        j = 0 if one else i
        d0 = ends[i, 0] - starts[j, 0]
        d1 = ends[i, 1] - starts[j, 1]
        d2 = ends[i, 2] - starts[j, 2]
        lo = margin / max(math.sqrt(d0 * d0 + d1 * d1 + d2 * d2), 1e-30)
        if not _embree_ray(rays, i, (starts[j, 0], starts[j, 1], starts[j, 2]),
                           (d0, d1, d2), lo, 1.0 - lo, centre):
            ok = False
        far[i] = np.float32(1.0 - 2.0 * lo)  # (the length as stated above, rounded once)
    return org, d32, far, ok
