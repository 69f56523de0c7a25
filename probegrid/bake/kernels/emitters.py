"""The bake's kernels of emitting surfaces: exact polygon integrals, next-event estimation and
the exact texel coverage of a probe's view.

* :func:`polygon_irradiance`, :func:`emitter_irradiance` -- the unoccluded irradiance of
  uniformly emitting planar regions (Lambert's edge formula over clipped loops, exact);
* :func:`emitter_shadow_rays`, :func:`emitter_samples`, :func:`emitter_estimate` -- the light
  sampled on the emitters at hits (:class:`probegrid.bake.emitters.Emitters`: its ratio
  estimator, with the exact integral as control variate);
* :func:`cluster_samples` -- directions toward compact clusters of emitting triangles, by
  solid angle (the emitters too many edges for the exact integral);
* :func:`texel_emitter_coverage` -- the exact solid angle of every (cube texel, emitting
  triangle) overlap seen from a probe.

``tests/test_bake_kernels.py`` compares each with the numpy expression it restates;
:func:`_angle` replaces the C library's ``atan2`` of the polygon integrals (tested against
``numpy.arctan2`` to the last bits). Shadow rays are written as Embree takes them
(:func:`probegrid.raytrace.kernels._embree_ray`). The emitters reach the kernels as small tables
(:class:`EmitterOutlines`, :class:`EmitterTriangles`). Floating point: :mod:`probegrid._jit`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import inline_kernel, kernel
from probegrid.bake.kernels.cube import CubeAxes
from probegrid.bake.kernels.sampling import _alias_pick
from probegrid.raytrace.kernels import Vector, _embree_ray

__all__ = [
    "EmitterClusters",
    "EmitterOutlines",
    "EmitterTriangles",
    "emitter_estimate",
    "emitter_irradiance",
    "emitter_samples",
    "cluster_samples",
    "emitter_shadow_rays",
    "polygon_irradiance",
    "texel_emitter_coverage",
]


class EmitterOutlines(NamedTuple):
    """Uniformly emitting planar regions bounded by closed loops
    (:func:`probegrid.bake.emitters.emitter_outlines`; ``G`` regions of ``L`` loops)."""

    #: (V, 3) float64 the loops' vertices, loop after loop.
    loop_vertices: NDArray[np.float64]
    #: (L + 1,) int64 where each loop starts in ``loop_vertices``.
    loop_start: NDArray[np.int64]
    #: (G + 1,) int64 where each region's loops start.
    group_loops: NDArray[np.int64]
    #: (G, 3) float64 each region's unit normal (its emitting side).
    group_normals: NDArray[np.float64]
    #: (G, 3) float64 each region's radiance.
    group_radiance: NDArray[np.float64]


class EmitterTriangles(NamedTuple):
    """Untextured emitting triangles as :func:`emitter_samples` draws points on them (``E``)."""

    #: (E, 3, 3) float64 corners.
    vertices: NDArray[np.float64]
    #: (E, 3) float64 unit normals as wound (the emitting side).
    normals: NDArray[np.float64]
    #: (E, 3) float64 radiance.
    radiance: NDArray[np.float64]
    #: (E, 3) float64 the control variate's radiance (0 without one).
    control: NDArray[np.float64]


_Receivers = tuple[NDArray[np.float64], NDArray[np.float64]]
_Emission = tuple[NDArray[np.float64], NDArray[np.float64]]


@kernel
def _clip_plane(px: NDArray[np.float64], count: int, nx: float, ny: float, nz: float,
                out: NDArray[np.float64]) -> int:
    """Sutherland-Hodgman: the polygon ``px[:count] (k, 3)`` clipped to ``dot(p, n) >= 0``
    into ``out``; returns its vertex count."""
    k = 0
    for i in range(count):
        j = (i + 1) % count
        di = px[i, 0] * nx + px[i, 1] * ny + px[i, 2] * nz
        dj = px[j, 0] * nx + px[j, 1] * ny + px[j, 2] * nz
        if di >= 0:
            out[k, 0], out[k, 1], out[k, 2] = px[i, 0], px[i, 1], px[i, 2]
            k += 1
        if (di >= 0) != (dj >= 0):
            t = di / (di - dj)
            for a in range(3):
                out[k, a] = px[i, a] + t * (px[j, a] - px[i, a])
            k += 1
    return k


#: ``atan(t) = t + t^3 P(t^2)`` for ``|t| <= tan(pi / 8)``: the coefficients of ``P`` (degree 8),
#: fitted here by least squares (weighted by ``t^2``, for the relative error; 4000 Chebyshev
#: nodes in ``t^2``) to the series ``P(z) = sum_k (-1)^(k+1) z^k / (2k + 3)``; against
#: ``numpy.arctan`` the largest error on that interval is 4.4e-16, 9 units in the last place
#: (``tests/test_bake_kernels.py`` checks :func:`_angle` against ``numpy.arctan2``).
_ATAN_P = (-0.33333333333256987, 0.19999999982203043, -0.14285712845711665,
           0.11111053636467254, -0.0908960261715069, 0.07674200140399653,
           -0.06509586311864264, 0.05035419831218217, -0.02544895846987845)
_TAN_PI_8 = math.tan(math.pi / 8)
_TAN2_PI_8 = _TAN_PI_8 * _TAN_PI_8


@inline_kernel
def _atan_poly(z: float) -> float:
    """:data:`_ATAN_P`'s ``P(z)`` (``atan(t) = t + t^3 P(t^2)``, ``z = t^2 <= tan(pi / 8)^2``) by
    Estrin's scheme."""
    p0, p1, p2, p3, p4, p5, p6, p7, p8 = _ATAN_P
    z2 = z * z
    z4 = z2 * z2
    return (((p0 + p1 * z) + (p2 + p3 * z) * z2) + ((p4 + p5 * z) + (p6 + p7 * z) * z2) * z4
            + p8 * (z4 * z4))


@kernel
def _angle(y: float, x: float) -> float:
    """``atan2(y, x)`` for ``y >= 0``, in ``[0, pi]`` (an angle between two vectors from the
    length of their cross product and their dot product), to within 1e-15: the angle of
    ``(|x|, y)`` is brought within ``pi / 8`` of 0, ``pi / 4`` or ``pi / 2`` (one division) and
    :data:`_ATAN_P` evaluated by Estrin's scheme. Inlined, it costs a fifth of the C library's
    ``atan2`` call in the polygon integrals (Lambert's edge formula's four angles per point
    were half of :func:`polygon_irradiance`'s time)."""
    ax = abs(x)
    if y <= _TAN_PI_8 * ax:
        t = y / ax if ax > 0 else 0.0
        base = 0.0
    elif ax < _TAN_PI_8 * y:
        t = -ax / y
        base = 0.5 * math.pi
    else:
        t = (y - ax) / (y + ax)
        base = 0.25 * math.pi
    z = t * t
    r = base + (t + t * z * _atan_poly(z))
    return math.pi - r if x < 0 else r


@kernel
def _edge_sum(px: NDArray[np.float64], count: int, nx: float, ny: float, nz: float) -> float:
    """Lambert's edge formula, signed: ``sum_i theta_i (n . g_i)`` over the edges of the closed
    loop ``px[:count]`` (relative to the receiver, in its upper half-space); half its absolute
    value is the loop's cosine-weighted solid angle, and the sums of the loops bounding one
    planar region (an outline and its holes) add up to the region's."""
    total = 0.0
    for i in range(count):
        j = i + 1 if i + 1 < count else 0
        ax, ay, az = px[i, 0], px[i, 1], px[i, 2]
        bx, by, bz = px[j, 0], px[j, 1], px[j, 2]
        cx = ay * bz - az * by
        cy = az * bx - ax * bz
        cz = ax * by - ay * bx
        l2 = cx * cx + cy * cy + cz * cz
        if not l2 > 0:  # (a vertex at the receiver, or a degenerate edge: no area)
            continue
        d = ax * bx + ay * by + az * bz
        if l2 <= _TAN2_PI_8 * (d * d) and d > 0:
            # an edge that subtends at most pi / 8 (most do, away from the emitter):
            # theta / |c| = atan(t) / (t d) with t = |c| / d, _angle's polynomial in t^2:
            # no square root, one division
            inv = 1.0 / d
            z = l2 * (inv * inv)
            total += (1.0 + z * _atan_poly(z)) * inv * (cx * nx + cy * ny + cz * nz)
            continue
        lc = math.sqrt(l2)
        theta = _angle(lc, d)
        total += theta * (cx * nx + cy * ny + cz * nz) / lc
    return total


@kernel
def polygon_irradiance(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    outlines: EmitterOutlines,
) -> NDArray[np.float64]:
    """Unoccluded irradiance of uniformly emitting planar regions at surface points (exact).

    The regions are ``outlines`` (:class:`EmitterOutlines`). Region ``q`` is bounded by the
    closed loops ``group_loops[q] .. group_loops[q + 1] - 1``
    (an outline and its holes; loop ``l`` is ``loop_vertices[loop_start[l]:loop_start[l + 1]]``,
    counter-clockwise seen from the side ``group_normals[q]`` points to) and emits
    ``group_radiance[q] (3,)`` from that side. At a point ``points (n, 3)`` with unit
    ``normals (n, 3)`` in front of the region's plane, every loop is clipped to the point's upper
    half-space (Sutherland-Hodgman, which keeps a loop's signed edge sum right even when it is
    not convex) and the region's cosine-weighted solid angle is ``|sum of the loops' edge sums|
    / 2`` (Lambert's edge formula). A triangle is a region of one 3-vertex loop
    (:func:`emitter_irradiance`). Returns ``(n, 3)`` lux.
    """
    loop_vertices, loop_start, group_loops, group_normals, group_radiance = outlines
    n = points.shape[0]
    ng = group_normals.shape[0]
    out = np.zeros((n, 3))
    longest = 3
    for m in range(loop_start.shape[0] - 1):
        longest = max(longest, loop_start[m + 1] - loop_start[m])
    poly = np.empty((longest, 3))
    clipped = np.empty((2 * longest + 2, 3))
    for i in range(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        for q in range(ng):
            v0 = loop_start[group_loops[q]]
            side = (group_normals[q, 0] * (px - loop_vertices[v0, 0])
                    + group_normals[q, 1] * (py - loop_vertices[v0, 1])
                    + group_normals[q, 2] * (pz - loop_vertices[v0, 2]))
            if not side > 0:
                continue
            total = 0.0
            for m in range(group_loops[q], group_loops[q + 1]):
                s0, count = loop_start[m], loop_start[m + 1] - loop_start[m]
                above = 0
                for v in range(count):
                    x = loop_vertices[s0 + v, 0] - px
                    y = loop_vertices[s0 + v, 1] - py
                    z = loop_vertices[s0 + v, 2] - pz
                    poly[v, 0], poly[v, 1], poly[v, 2] = x, y, z
                    if x * nx + y * ny + z * nz >= 0:
                        above += 1
                if above == count:  # nothing to clip (what _clip_plane would return)
                    total += _edge_sum(poly, count, nx, ny, nz)
                elif above > 0:
                    k = _clip_plane(poly, count, nx, ny, nz, clipped)
                    if k >= 3:
                        total += _edge_sum(clipped, k, nx, ny, nz)
            f = 0.5 * abs(total)
            out[i, 0] += f * group_radiance[q, 0]
            out[i, 1] += f * group_radiance[q, 1]
            out[i, 2] += f * group_radiance[q, 2]
    return out


def emitter_irradiance(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    tri_vertices: NDArray[np.float64],
    tri_normals: NDArray[np.float64],
    tri_radiance: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Unoccluded irradiance of uniformly emitting triangles at surface points (exact):
    :func:`polygon_irradiance` with each triangle ``tri_vertices (E, 3, 3)`` a region of its own,
    emitting ``tri_radiance (E, 3)`` from its front (the side ``tri_normals (E, 3)`` points to,
    as wound). Returns ``(n, 3)`` lux."""
    e = len(tri_vertices)
    return polygon_irradiance(
        np.ascontiguousarray(points, dtype=np.float64),
        np.ascontiguousarray(normals, dtype=np.float64),
        EmitterOutlines(
            np.ascontiguousarray(np.asarray(tri_vertices, np.float64).reshape(-1, 3)),
            np.arange(0, 3 * e + 1, 3, dtype=np.int64), np.arange(e + 1, dtype=np.int64),
            np.ascontiguousarray(tri_normals, dtype=np.float64),
            np.ascontiguousarray(tri_radiance, dtype=np.float64)))


_ShadowRays = tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.float32],
                    NDArray[np.float32], NDArray[np.float64], NDArray[np.float64],
                    NDArray[np.bool_]]


@kernel
def _shadow_ray_arrays(cap: int) -> _ShadowRays:
    """Room for ``cap`` of :func:`emitter_shadow_rays`' rays (the last array: all finite)."""
    return (np.empty(cap, np.int64), np.empty((cap, 3), np.float32),
            np.empty((cap, 3), np.float32), np.empty(cap, np.float32), np.empty((cap, 3)),
            np.empty((cap, 3)), np.ones(1, np.bool_))


@kernel
def _first_rays(out: _ShadowRays, k: int) -> _ShadowRays:
    """The first ``k`` of :func:`_shadow_ray_arrays`' rays: the ones stored."""
    which, org, dirs, far, vis, occ, ok = out
    return which[:k], org[:k], dirs[:k], far[:k], vis[:k], occ[:k], ok


# inlined by numba: a call per sample passing six arrays cost 15 % of emitter_samples
@inline_kernel
def _emitter_shadow_ray(out: _ShadowRays, k: int, receivers: _Receivers, i: int,
                        sample: tuple[Vector, Vector], emission: _Emission, row: int,
                        weight: tuple[float, float], frame: tuple[float, NDArray[np.float64]]
                        ) -> int:
    """One sample of :func:`emitter_shadow_rays`: point ``i`` of ``receivers``
    ``(points, normals)``, the ``sample`` at ``q`` with normal ``qn`` (``(q, qn)``), radiance and
    control in row ``row`` of ``emission`` ``(radiance, control)``, ``weight``
    ``(inverse_pdf, 1 / L)``, ``frame`` ``(eps, centre)``; stored as ray ``k`` of ``out`` when it
    counts (``ok[0]`` cleared if it is not finite). Returns the next free ray."""
    which, org, dirs, far, vis, occ, ok = out
    points, normals = receivers
    q, qn = sample
    qx, qy, qz = q
    qnx, qny, qnz = qn
    radiance, control = emission
    inverse_pdf, inv_l = weight
    eps, centre = frame
    px, py, pz = points[i, 0], points[i, 1], points[i, 2]
    nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
    dx, dy, dz = qx - px, qy - py, qz - pz
    d2 = dx * dx + dy * dy + dz * dz
    if not d2 > 0:
        return k
    dist = math.sqrt(d2)
    wx, wy, wz = dx / dist, dy / dist, dz / dist
    cx = wx * nx + wy * ny + wz * nz
    cy = -(wx * qnx + wy * qny + wz * qnz)
    if not (cx > 0 and cy > 0):
        return k
    g = cx * cy / d2 * inverse_pdf * inv_l
    r0, r1, r2 = radiance[row, 0], radiance[row, 1], radiance[row, 2]
    c0, c1, c2 = control[row, 0], control[row, 1], control[row, 2]
    if max(r0, r1, r2, c0, c1, c2) <= 0:
        return k
    which[k] = i
    # the shadow ray runs between the two points each lifted eps off its surface (a ray
    # grazing the emitter's plane would hit it early in float32) and stops eps short
    ox, oy, oz = px + eps * nx, py + eps * ny, pz + eps * nz
    sx = qx + eps * qnx - ox
    sy = qy + eps * qny - oy
    sz = qz + eps * qnz - oz
    sl = math.sqrt(sx * sx + sy * sy + sz * sz)
    if not _embree_ray((org, dirs, far), k, (ox, oy, oz), (sx / sl, sy / sl, sz / sl), eps,
                       sl - eps, centre):
        ok[0] = False
    vis[k, 0], vis[k, 1], vis[k, 2] = g * (r0 - c0), g * (r1 - c1), g * (r2 - c2)
    occ[k, 0], occ[k, 1], occ[k, 2] = -g * c0, -g * c1, -g * c2
    return k + 1


@kernel
def emitter_shadow_rays(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    sample_points: NDArray[np.float64],
    sample_normals: NDArray[np.float64],
    sample_radiance: NDArray[np.float64],
    sample_control: NDArray[np.float64],
    inverse_pdf: NDArray[np.float64],
    eps: float,
    centre: NDArray[np.float64],
) -> _ShadowRays:
    """Next-event estimation toward points sampled on emitters: the shadow rays and what each
    contributes to the ratio estimator of :class:`probegrid.bake.emitters.Emitters` (or the
    control variate's correction, :func:`emitter_estimate`).

    Point ``i`` has ``L`` samples ``sample_points (n, L, 3)`` on emitting triangles (unit
    ``sample_normals``, front as wound), with radiance ``sample_radiance (n, L, 3)`` (textures
    applied), the control variate's radiance ``sample_control (n, L, 3)`` (the uniform radiance
    whose unoccluded integral is known exactly, :func:`emitter_irradiance`; 0 without one) and
    ``inverse_pdf (n, L)`` (area over the area density). A sample contributes
    ``g = cos_x cos_y / d^2 * inverse_pdf / L`` times ``(radiance - control)`` if its shadow ray
    is unoccluded and ``-control`` if it is occluded, so that

        E = exact unoccluded integral of the control + sum of contributions

    is unbiased, and exact when nothing occludes the emitters.

    Returns
    -------
    point : (k,) int64; origins, directions : (k, 3) float32; lengths : (k,) float32
        The shadow rays as Embree takes them (:func:`probegrid.raytrace.kernels._embree_ray`,
        re-centred on ``centre``,
        the tracer's; :class:`probegrid.raytrace.EmbreeRays`).
    visible, occluded : (k, 3) contributions (lux) for the two outcomes.
    ok : (1,) bool
        Whether every ray is finite in float32.
    """
    n, ns = sample_points.shape[0], sample_points.shape[1]
    out = _shadow_ray_arrays(n * ns)
    k = 0
    inv_l = 1.0 / ns
    receivers = (points, normals)
    emission = (sample_radiance.reshape(n * ns, 3), sample_control.reshape(n * ns, 3))
    frame = (eps, centre)
    for i in range(n):
        for s in range(ns):
            k = _emitter_shadow_ray(
                out, k, receivers, i,
                ((sample_points[i, s, 0], sample_points[i, s, 1], sample_points[i, s, 2]),
                 (sample_normals[i, s, 0], sample_normals[i, s, 1], sample_normals[i, s, 2])),
                emission, i * ns + s, (inverse_pdf[i, s], inv_l), frame)
    return _first_rays(out, k)


@kernel
def _polygon_solid_angle(px: NDArray[np.float64], count: int) -> float:
    """Solid angle of a planar convex polygon ``px[:count]`` (relative to the eye), as a fan
    of triangles (Van Oosterom & Strackee 1983)."""
    total = 0.0
    ax, ay, az = px[0, 0], px[0, 1], px[0, 2]
    la = math.sqrt(ax * ax + ay * ay + az * az)
    for i in range(1, count - 1):
        bx, by, bz = px[i, 0], px[i, 1], px[i, 2]
        cx, cy, cz = px[i + 1, 0], px[i + 1, 1], px[i + 1, 2]
        lb = math.sqrt(bx * bx + by * by + bz * bz)
        lc = math.sqrt(cx * cx + cy * cy + cz * cz)
        trip = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
        den = (la * lb * lc + (ax * bx + ay * by + az * bz) * lc
               + (ax * cx + ay * cy + az * cz) * lb + (bx * cx + by * cy + bz * cz) * la)
        total += 2.0 * _angle(abs(trip), den)
    return total


@kernel
def texel_emitter_coverage(
    origin: NDArray[np.float64],
    tri_vertices: NDArray[np.float64],
    tri_normals: NDArray[np.float64],
    n: int,
    axes: CubeAxes,
    capacity: int,
) -> tuple[int, NDArray[np.int64], NDArray[np.int64], NDArray[np.float64], NDArray[np.float64],
           NDArray[np.float64]]:
    """The exact solid angle of every (cube texel, emitting triangle) overlap seen from a point.

    Each triangle whose front faces ``origin (3,)`` is clipped to every face's frustum
    (``|x.U| <= x.N``, ``|x.V| <= x.N``), projected onto the face plane (straight edges stay
    straight), and clipped to each texel square of an ``n``-cube it touches (``axes``, the
    cube's, :data:`~probegrid.bake.kernels.cube.CUBE_AXES`); the piece's solid angle is the fan
    sum of :func:`_polygon_solid_angle`. Visibility is not tested here.

    Returns
    -------
    count : int
        Overlaps found (more than ``capacity`` means: call again with a larger one; only the
        first ``capacity`` are filled).
    texel : (capacity,) int64
        Flat texel index ``(face * n + row) * n + col``.
    triangle : (capacity,) int64
    solid_angle : (capacity,) float64
    direction : (capacity, 3) float64
        Unit direction of the piece's centroid.
    distance : (capacity,) float64
        Distance along it to the triangle's plane.
    """
    face_normals, face_u, face_v = axes
    ne = tri_vertices.shape[0]
    tex = np.empty(capacity, np.int64)
    tri = np.empty(capacity, np.int64)
    omega = np.empty(capacity)
    dirs = np.empty((capacity, 3))
    dist = np.empty(capacity)
    count = 0
    poly = np.empty((16, 3))
    tmp = np.empty((16, 3))
    uv = np.empty((16, 2))
    sq = np.empty((24, 2))
    sq2 = np.empty((24, 2))
    pts = np.empty((24, 3))
    half = 0.5 * n
    for e in range(ne):
        ox = tri_vertices[e, 0, 0] - origin[0]
        oy = tri_vertices[e, 0, 1] - origin[1]
        oz = tri_vertices[e, 0, 2] - origin[2]
        tn0, tn1, tn2 = tri_normals[e, 0], tri_normals[e, 1], tri_normals[e, 2]
        plane = -(tn0 * ox + tn1 * oy + tn2 * oz)  # > 0: the origin is in front
        if not plane > 0:
            continue
        for f in range(6):
            for v in range(3):
                for a in range(3):
                    poly[v, a] = tri_vertices[e, v, a] - origin[a]
            k = 3
            for side in range(4):
                sgn = 1.0 if side % 2 == 0 else -1.0
                if side < 2:
                    ax_ = face_normals[f, 0] + sgn * face_u[f, 0]
                    ay_ = face_normals[f, 1] + sgn * face_u[f, 1]
                    az_ = face_normals[f, 2] + sgn * face_u[f, 2]
                else:
                    ax_ = face_normals[f, 0] + sgn * face_v[f, 0]
                    ay_ = face_normals[f, 1] + sgn * face_v[f, 1]
                    az_ = face_normals[f, 2] + sgn * face_v[f, 2]
                k = _clip_plane(poly, k, ax_, ay_, az_, tmp)
                for j in range(k):
                    poly[j, 0], poly[j, 1], poly[j, 2] = tmp[j, 0], tmp[j, 1], tmp[j, 2]
                if k < 3:
                    break
            if k < 3:
                continue
            umin, umax, vmin, vmax = 1.0, -1.0, 1.0, -1.0
            ok = True
            for j in range(k):
                zz = (poly[j, 0] * face_normals[f, 0] + poly[j, 1] * face_normals[f, 1]
                      + poly[j, 2] * face_normals[f, 2])
                if not zz > 0:
                    ok = False
                    break
                uu = (poly[j, 0] * face_u[f, 0] + poly[j, 1] * face_u[f, 1]
                      + poly[j, 2] * face_u[f, 2]) / zz
                vv = (poly[j, 0] * face_v[f, 0] + poly[j, 1] * face_v[f, 1]
                      + poly[j, 2] * face_v[f, 2]) / zz
                uu = min(max(uu, -1.0), 1.0)
                vv = min(max(vv, -1.0), 1.0)
                uv[j, 0], uv[j, 1] = uu, vv
                umin, umax = min(umin, uu), max(umax, uu)
                vmin, vmax = min(vmin, vv), max(vmax, vv)
            if not ok:
                continue
            c0 = min(int(math.floor((umin + 1.0) * half)), n - 1)  # noqa: RUF046 (numba)
            c1 = min(int(math.floor((umax + 1.0) * half)), n - 1)  # noqa: RUF046 (numba)
            r0 = min(int(math.floor((vmin + 1.0) * half)), n - 1)  # noqa: RUF046 (numba)
            r1 = min(int(math.floor((vmax + 1.0) * half)), n - 1)  # noqa: RUF046 (numba)
            for row in range(r0, r1 + 1):
                for col in range(c0, c1 + 1):
                    u_lo = col / half - 1.0
                    u_hi = (col + 1) / half - 1.0
                    v_lo = row / half - 1.0
                    v_hi = (row + 1) / half - 1.0
                    m = k
                    for j in range(m):
                        sq[j, 0], sq[j, 1] = uv[j, 0], uv[j, 1]
                    for side in range(4):  # clip to the texel square
                        q = 0
                        for j in range(m):
                            jj = (j + 1) % m
                            if side == 0:
                                di, dj = sq[j, 0] - u_lo, sq[jj, 0] - u_lo
                            elif side == 1:
                                di, dj = u_hi - sq[j, 0], u_hi - sq[jj, 0]
                            elif side == 2:
                                di, dj = sq[j, 1] - v_lo, sq[jj, 1] - v_lo
                            else:
                                di, dj = v_hi - sq[j, 1], v_hi - sq[jj, 1]
                            if di >= 0:
                                sq2[q, 0], sq2[q, 1] = sq[j, 0], sq[j, 1]
                                q += 1
                            if (di >= 0) != (dj >= 0):
                                t = di / (di - dj)
                                sq2[q, 0] = sq[j, 0] + t * (sq[jj, 0] - sq[j, 0])
                                sq2[q, 1] = sq[j, 1] + t * (sq[jj, 1] - sq[j, 1])
                                q += 1
                        m = q
                        for j in range(m):
                            sq[j, 0], sq[j, 1] = sq2[j, 0], sq2[j, 1]
                        if m < 3:
                            break
                    if m < 3:
                        continue
                    # planar area (for the centroid) and the solid angle of the piece
                    area = 0.0
                    cu = 0.0
                    cv = 0.0
                    for j in range(m):
                        jj = (j + 1) % m
                        cr = sq[j, 0] * sq[jj, 1] - sq[jj, 0] * sq[j, 1]
                        area += cr
                        cu += (sq[j, 0] + sq[jj, 0]) * cr
                        cv += (sq[j, 1] + sq[jj, 1]) * cr
                    if area == 0.0:
                        continue
                    cu /= 3.0 * area
                    cv /= 3.0 * area
                    for j in range(m):
                        for a in range(3):
                            pts[j, a] = (face_normals[f, a] + sq[j, 0] * face_u[f, a]
                                         + sq[j, 1] * face_v[f, a])
                    om = _polygon_solid_angle(pts, m)
                    if not om > 0:
                        continue
                    if count < capacity:
                        dx = face_normals[f, 0] + cu * face_u[f, 0] + cv * face_v[f, 0]
                        dy = face_normals[f, 1] + cu * face_u[f, 1] + cv * face_v[f, 1]
                        dz = face_normals[f, 2] + cu * face_u[f, 2] + cv * face_v[f, 2]
                        dl = math.sqrt(dx * dx + dy * dy + dz * dz)
                        dx, dy, dz = dx / dl, dy / dl, dz / dl
                        tex[count] = (f * n + row) * n + col
                        tri[count] = e
                        omega[count] = om
                        dirs[count, 0], dirs[count, 1], dirs[count, 2] = dx, dy, dz
                        den = -(tn0 * dx + tn1 * dy + tn2 * dz)
                        dist[count] = plane / den if den > 0 else math.inf
                    count += 1
    return count, tex, tri, omega, dirs, dist


@kernel
def emitter_samples(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    random: NDArray[np.float64],
    selection: tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]],
    triangles: EmitterTriangles,
    eps: float,
    centre: NDArray[np.float64],
) -> _ShadowRays:
    """:func:`emitter_shadow_rays` of points sampled on untextured emitters, from uniform
    numbers: :meth:`probegrid.bake.emitters.Emitters.irradiance`'s choice of a triangle
    (drawn by ``random[..., 0]`` from the ``selection``'s alias table ``(accept, alias)``,
    :func:`~probegrid.bake.kernels.sampling.alias_draw`'s rule), its uniform point
    (``sqrt(r1) (1 - r2), sqrt(r1) r2`` as barycentrics ``u, v``; position ``(1 - u - v) a + u b + v c``) and radiance
    ``radiance[e]``, in one pass.

    ``random (n, L, 3)``; ``selection`` ``(accept, alias, inverse_pdf)``, ``inverse_pdf (E,)``
    area over the selection probability; ``triangles`` (:class:`EmitterTriangles`).
    Returns what :func:`emitter_shadow_rays` returns.
    """
    accept, alias, inverse_pdf = selection
    q, tri_normals, tri_radiance, tri_control = triangles
    n, ns = random.shape[0], random.shape[1]
    out = _shadow_ray_arrays(n * ns)
    k = 0
    inv_l = 1.0 / ns
    receivers = (points, normals)
    emission = (tri_radiance, tri_control)
    frame = (eps, centre)
    for i in range(n):
        for s in range(ns):
            e = _alias_pick(accept, alias, random[i, s, 0])
            r1 = math.sqrt(random[i, s, 1])
            w1 = r1 * (1.0 - random[i, s, 2])
            w2 = r1 * random[i, s, 2]
            w0 = 1.0 - w1 - w2
            k = _emitter_shadow_ray(
                out, k, receivers, i,
                ((w0 * q[e, 0, 0] + w1 * q[e, 1, 0] + w2 * q[e, 2, 0],
                  w0 * q[e, 0, 1] + w1 * q[e, 1, 1] + w2 * q[e, 2, 1],
                  w0 * q[e, 0, 2] + w1 * q[e, 1, 2] + w2 * q[e, 2, 2]),
                 (tri_normals[e, 0], tri_normals[e, 1], tri_normals[e, 2])),
                emission, e, (inverse_pdf[e], inv_l), frame)
    return _first_rays(out, k)


@kernel
def emitter_estimate(n: int, which: NDArray[np.int64], blocked: NDArray[np.bool_],
                     visible: NDArray[np.float64], occluded: NDArray[np.float64],
                     analytic: NDArray[np.float64]) -> NDArray[np.float64]:
    """The emitters' irradiance at ``n`` points from their shadow rays' outcomes
    (:func:`emitter_shadow_rays`; ray ``k`` belongs to point ``which[k]``): the plain estimate
    ``sum V g Le / (L p)`` when ``analytic`` is empty ``(0, 3)``; else the ratio estimator
    ``A * plain / sum g Lc / (L p)`` with ``A = analytic (n, 3)``, per channel, or
    ``A + plain`` where no sample saw the control (:class:`probegrid.bake.emitters.Emitters`).
    Returns ``(n, 3)`` lux."""
    plain = np.zeros((n, 3))
    whole = np.zeros((n, 3))
    for k in range(which.shape[0]):
        i = which[k]
        for c in range(3):
            if not blocked[k]:
                plain[i, c] += visible[k, c] - occluded[k, c]
            whole[i, c] += -occluded[k, c]
    if analytic.shape[0] == 0:
        return plain
    out = np.empty((n, 3))
    for i in range(n):
        for c in range(3):
            if whole[i, c] > 0.0:
                out[i, c] = analytic[i, c] * (plain[i, c] / whole[i, c])
            else:
                out[i, c] = analytic[i, c] + plain[i, c]
    return out


class EmitterClusters(NamedTuple):
    """Emitting triangles grouped into compact clusters, each bounded by a sphere, as
    :func:`cluster_samples` picks them (``K`` clusters,
    :func:`probegrid.bake.emitters.emitter_clusters`)."""

    #: (K, 3) float64 bounding spheres' centres.
    centre: NDArray[np.float64]
    #: (K,) float64 bounding spheres' radii.
    radius: NDArray[np.float64]
    #: (K,) float64 ``sum area * mean(radiance)`` of the cluster's triangles.
    power: NDArray[np.float64]
    #: (K, 3) float64 the axis of the cone holding the triangles' normals.
    axis: NDArray[np.float64]
    #: (K,) float64 the cosine of that cone's half-angle (-1: normals in every direction).
    spread: NDArray[np.float64]


@inline_kernel
def _cluster_importance(clusters: EmitterClusters, c: int, px: float, py: float, pz: float,
                        nx: float, ny: float, nz: float) -> float:
    """An upper-bound-shaped estimate of the irradiance cluster ``c`` gives a point ``p`` with
    normal ``n``: ``power / d^2`` times the largest receiver cosine over the cluster's bounding
    cap and the largest emitter cosine its normal cone allows (Estevez & Kulla 2018); 0 only
    where the cluster cannot light the point (its cap below the horizon, or every triangle
    facing away)."""
    centre, radius, power, axis, spread = clusters
    wx, wy, wz = centre[c, 0] - px, centre[c, 1] - py, centre[c, 2] - pz
    d2 = wx * wx + wy * wy + wz * wz
    r = radius[c]
    if d2 <= r * r:  # inside the bounding sphere: no direction can be ruled out
        return power[c] / max(r * r, 1e-300)
    d = math.sqrt(d2)
    wx, wy, wz = wx / d, wy / d, wz / d
    sin_c = r / d
    cos_c = math.sqrt(max(1.0 - sin_c * sin_c, 0.0))
    cos_a = wx * nx + wy * ny + wz * nz
    if cos_a >= cos_c:
        receiver = 1.0
    else:  # cos(a - theta_c): the cap's point nearest the normal
        receiver = cos_a * cos_c + math.sqrt(max(1.0 - cos_a * cos_a, 0.0)) * sin_c
        if receiver <= 0.0:
            return 0.0
    emitter = 1.0
    if spread[c] > -1.0:  # the triangles' normals within a cone: the side they face
        cos_b = -(wx * axis[c, 0] + wy * axis[c, 1] + wz * axis[c, 2])
        b = math.acos(min(max(cos_b, -1.0), 1.0))
        slack = b - math.acos(min(max(spread[c], -1.0), 1.0)) - math.asin(min(sin_c, 1.0))
        if slack >= 0.5 * math.pi:
            return 0.0
        emitter = math.cos(max(slack, 0.0))
    return power[c] * receiver * emitter / d2


@inline_kernel
def _cap_solid_angle(clusters: EmitterClusters, c: int, px: float, py: float, pz: float
                     ) -> tuple[float, float, float, float, float]:
    """The cone of directions from ``p`` toward cluster ``c``'s bounding sphere: its unit axis
    ``(x, y, z)``, the cosine of its half-angle (-1: the point is inside, every direction) and
    its solid angle ``2 pi (1 - cos)`` (computed without cancellation)."""
    centre, radius = clusters[0], clusters[1]
    wx, wy, wz = centre[c, 0] - px, centre[c, 1] - py, centre[c, 2] - pz
    d2 = wx * wx + wy * wy + wz * wz
    r = radius[c]
    if d2 <= r * r:
        return 0.0, 0.0, 1.0, -1.0, 4.0 * math.pi
    d = math.sqrt(d2)
    s2 = r * r / d2
    cos_c = math.sqrt(max(1.0 - s2, 0.0))
    return wx / d, wy / d, wz / d, cos_c, 2.0 * math.pi * s2 / (1.0 + cos_c)


@kernel
def cluster_samples(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    random: NDArray[np.float64],
    clusters: EmitterClusters,
    eps: float,
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Directions toward emitter clusters, for next-event estimation by solid angle
    (:meth:`probegrid.bake.emitters.Emitters.irradiance` when the emitters' outlines are too
    many edges for the exact integral).

    Point ``i`` (unit ``normals``, facing the lit side) draws ``L`` samples from
    ``random (n, L, 3)``: a cluster ``c`` with probability ``P(c)``, its
    :func:`_cluster_importance` over their sum (``random[..., 0]``), then a direction uniform
    in the cone of its bounding sphere (``random[..., 1:]``; the whole sphere of directions
    from inside it). The direction's density is the mixture over every cluster whose cone
    holds it, ``p(w) = sum_c P(c) [w in cone_c] / Omega_c``, so the estimate
    ``sum Le(w) cos(w) / (p(w) L)`` over the rays' first hits (an emitter's front, else 0) is
    unbiased, and for a sphere-like cluster nearly constant per sample: its cone is what the
    sphere covers, whatever its number of triangles.

    Returns
    -------
    point : (k,) int64
        The point each ray belongs to (samples below the horizon cast none).
    origins, directions : (k, 3) float64
        ``point + eps normal`` and the unit directions.
    weight : (k,) float64
        ``cos / (p(w) L)``: the ray's first hit's radiance times it is its contribution (lux).
    """
    n, ns = random.shape[0], random.shape[1]
    k_count = clusters[1].shape[0]
    which = np.empty(n * ns, np.int64)
    org = np.empty((n * ns, 3))
    dirs = np.empty((n * ns, 3))
    weight = np.empty(n * ns)
    cdf = np.empty(k_count)
    k = 0
    for i in range(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        total = 0.0
        for c in range(k_count):
            total += _cluster_importance(clusters, c, px, py, pz, nx, ny, nz)
            cdf[c] = total
        if not total > 0.0:
            continue
        for s in range(ns):
            target = random[i, s, 0] * total
            pick = k_count - 1
            for c in range(k_count):
                if target < cdf[c]:
                    pick = c
                    break
            ax, ay, az, cos_max, _ = _cap_solid_angle(clusters, pick, px, py, pz)
            r1, r2 = random[i, s, 1], random[i, s, 2]
            cos_t = 1.0 - r1 * (1.0 - cos_max)
            sin_t = math.sqrt(max(1.0 - cos_t * cos_t, 0.0))
            phi = 2.0 * math.pi * r2
            # an orthonormal frame around the cone's axis (Duff et al. 2017)
            sign = 1.0 if az >= 0.0 else -1.0
            a = -1.0 / (sign + az)
            b = ax * ay * a
            tx, ty, tz = 1.0 + sign * ax * ax * a, sign * b, -sign * ax
            bx, by, bz = b, sign + ay * ay * a, -ay
            cp, sp = math.cos(phi) * sin_t, math.sin(phi) * sin_t
            dx = tx * cp + bx * sp + ax * cos_t
            dy = ty * cp + by * sp + ay * cos_t
            dz = tz * cp + bz * sp + az * cos_t
            dl = math.sqrt(dx * dx + dy * dy + dz * dz)
            dx, dy, dz = dx / dl, dy / dl, dz / dl
            cos_r = dx * nx + dy * ny + dz * nz
            if not cos_r > 0.0:
                continue
            pdf = 0.0
            for c in range(k_count):
                pc = cdf[c] - (cdf[c - 1] if c > 0 else 0.0)
                if pc <= 0.0:
                    continue
                cx, cy, cz, cos_c, omega = _cap_solid_angle(clusters, c, px, py, pz)
                if c == pick or cos_c < -0.5 or dx * cx + dy * cy + dz * cz >= cos_c:
                    pdf += pc / (total * omega)
            which[k] = i
            org[k, 0], org[k, 1], org[k, 2] = px + eps * nx, py + eps * ny, pz + eps * nz
            dirs[k, 0], dirs[k, 1], dirs[k, 2] = dx, dy, dz
            weight[k] = cos_r / (pdf * ns)
            k += 1
    return which[:k], org[:k], dirs[:k], weight[:k]
