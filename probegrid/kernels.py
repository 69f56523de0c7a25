"""Compiled per-ray kernels of the bake (the one module that imports numba).

A bake handles every ray hit with the same short sequence of scalar steps: the hit's surface, its
shadow rays, the DDGI weights of the 8 probes around it (:mod:`probegrid.core.ddgi`, with a
seamless bilinear lookup of each probe's distance moments), and at every bounce the replay of
its record. Written as numpy array expressions these steps allocate a dozen ``(n, 8)`` and
``(n, 8, 3)`` temporaries per batch and cost many times the ray casting itself; here they are
one fused loop per hit, compiled by numba
(``cache=True``: compiled once per machine, then loaded from numba's cache). Kernels are pure
functions of arrays (they allocate their outputs, or fill arrays passed for that purpose) and
release the GIL.

Each kernel restates, step for step, an array expression that stays the reference and the
documentation of the maths; ``tests/test_kernels.py`` compares the two on random inputs:

* :func:`hit_probe_weights` -- :func:`probegrid.core.ddgi.probe_weights` with normals and
  moments, normalised (the trace-once weights, computed once per hit).
* :func:`hit_surfaces`, :func:`multiply_texture` -- :meth:`probegrid.scene.Scene.surface_at`'s
  barycentric interpolation and :func:`probegrid.scene.sample_texture`.
* :func:`light_rays` -- :func:`probegrid.core.lights.incident_many` and the choice of shadow
  rays; :func:`replay_radiance` -- a bounce's pass over the per-hit records.
* :func:`cube_sample_directions`, :func:`texel_means`, :func:`distance_moments`,
  :func:`split_hits` -- the render's sample pattern (:mod:`probegrid.core.cubemap`'s
  conversions), per-texel means, distance moments and the backface rule;
  :func:`shade_hits` -- :func:`split_hits` and :func:`hit_surfaces` in one pass into the records.
* :func:`embree_rays`, :func:`embree_hits` -- :class:`probegrid.raytrace.RayTracer`'s
  conversions to and from Embree's float32 rays (tested through the tracer). The shadow rays
  of :func:`light_rays`, :func:`emitter_samples` and :func:`environment_samples` are written
  as Embree takes them by the same rounding rule (:func:`_embree_ray`,
  :class:`probegrid.raytrace.EmbreeRays`): no float64 copy of them is made and converted.
* :func:`emitter_samples`, :func:`emitter_estimate`, :func:`environment_samples`,
  :func:`sum_unblocked`, :func:`cosine_directions`, :func:`gather_rays` -- the light sampled at
  hits (:class:`probegrid.bake.emitters.Emitters` and
  :class:`probegrid.bake.environment.EnvironmentLight` draw from alias tables,
  :func:`alias_table`, :func:`alias_draw`) and the final gather's rays.

Floating point: float64 throughout (float32 only where the data is, and the rays handed to
Embree), with FMA contraction and
reciprocal multiplication allowed (``fastmath={"contract", "arcp"}``; no other fast-math flag,
so nan and inf keep their meaning). Two functions of the C library are replaced where they
dominated a kernel, each tested against numpy to the last bits: :func:`_angle` (``atan2`` of
the polygon integrals) and :func:`_turn` (``cos`` and ``sin`` of the gather's azimuths). Results match the references to a few ulps, and a bake's
float32 outputs come out bit-identical to the pure-numpy bake's in practice.

Conventions are the owning modules' and are passed in, not restated: the cube faces' ``u``/``v``
axes (:data:`probegrid.core.cubemap.FACE_U`, :data:`~probegrid.core.cubemap.FACE_V`), the corner order
(:data:`probegrid.core.grid.CORNER_OFFSETS`), the SH basis constants
(:data:`probegrid.core.sh.BASIS_SCALE`) and the DDGI constants of :mod:`probegrid.core.ddgi`.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "alias_draw",
    "alias_table",
    "cosine_directions",
    "cube_sample_directions",
    "distance_moments",
    "embree_hits",
    "embree_rays",
    "emitter_estimate",
    "emitter_irradiance",
    "emitter_samples",
    "environment_samples",
    "gather_rays",
    "hit_surfaces",
    "light_rays",
    "mean_per_parent",
    "multiply_texture",
    "polygon_irradiance",
    "scatter_divided",
    "segment_rays",
    "shade_hits",
    "split_hits",
    "stream_uniforms",
    "sum_unblocked",
    "texel_means",
]

_JIT = {"nogil": True, "cache": True, "error_model": "numpy", "fastmath": {"contract", "arcp"}}


@numba.njit(**_JIT)
def _face_uv(dx: float, dy: float, dz: float, face_u: NDArray[np.float64],
             face_v: NDArray[np.float64]) -> tuple[int, float, float]:
    """:func:`probegrid.core.cubemap.direction_to_face_uv` of one direction (same tie rules)."""
    ax, ay, az = abs(dx), abs(dy), abs(dz)
    if ax >= ay and ax >= az:
        axis, comp = 0, dx
    elif ay >= az:
        axis, comp = 1, dy
    else:
        axis, comp = 2, dz
    face = 2 * axis + (1 if comp < 0 else 0)
    ma = abs(comp)
    if not ma > 0:
        ma = 1.0
    u = (dx * face_u[face, 0] + dy * face_u[face, 1] + dz * face_u[face, 2]) / ma
    v = (dx * face_v[face, 0] + dy * face_v[face, 1] + dz * face_v[face, 2]) / ma
    return face, min(max(u, -1.0), 1.0), min(max(v, -1.0), 1.0)


@numba.njit(**_JIT)
def _barycentric(values: NDArray[np.float64], a: int, b: int, c: int, w0: float, w1: float,
                 w2: float, k: int) -> float:
    """Component ``k`` of ``w0 values[a] + w1 values[b] + w2 values[c]`` (a point's vertex
    attribute, interpolated over its triangle)."""
    return w0 * values[a, k] + w1 * values[b, k] + w2 * values[c, k]


@numba.njit(**_JIT)
def _hit_side(tri_normals: NDArray[np.float64], t: int, dx: float, dy: float, dz: float,
              double_sided: NDArray[np.bool_]) -> tuple[int, float]:
    """The backface rule for a ray along ``d`` that hits triangle ``t``: kind 1 (front, or the
    back of a double-sided triangle) or 2 (the back of a one-sided triangle: black), and
    ``dot(normal as wound, d)`` (> 0: it sees the back, whose normal is turned toward it;
    < 0: it sees the front, the side that emits)."""
    d = tri_normals[t, 0] * dx + tri_normals[t, 1] * dy + tri_normals[t, 2] * dz
    return (2 if d > 0 and not double_sided[t] else 1), d


@numba.njit(**_JIT)
def hit_surfaces(
    prim: NDArray[np.int64],
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    vertices: NDArray[np.float64],
    triangles: NDArray[np.int64],
    tri_normals: NDArray[np.float64],
    material: NDArray[np.int64],
    base_color: NDArray[np.float64],
    emissive: NDArray[np.float64],
    colors: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Position, geometric normal, albedo and emission at barycentric points of triangles.

    :meth:`probegrid.scene.Scene.surface_at` without the textures (applied after, per
    material): ``position = (1 - u - v) a + u b + v c``; ``normal`` the triangle's unit normal
    as wound; ``albedo = baseColorFactor.rgb * COLOR_0.rgb`` (``colors`` interpolated like the
    position; an empty ``colors`` means none); ``emission = emissiveFactor``.

    Parameters
    ----------
    prim : (n,) int64 triangle indices; u, v : (n,) float64 barycentrics
    vertices (V, 3) float64, triangles (T, 3) int64, tri_normals (T, 3) float64,
    material (T,) int64, base_color (M, 3) and emissive (M, 3) float64,
    colors (V, >= 3) float64 or (0, 3)

    Returns
    -------
    position, normal, albedo, emission : (n, 3) float64
    """
    n = prim.shape[0]
    pos = np.empty((n, 3))
    nrm = np.empty((n, 3))
    alb = np.empty((n, 3))
    emi = np.empty((n, 3))
    has_colors = colors.shape[0] > 0
    for i in range(n):
        t = prim[i]
        w1, w2 = u[i], v[i]
        w0 = 1.0 - w1 - w2
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        m = material[t]
        for k in range(3):
            pos[i, k] = _barycentric(vertices, a, b, c, w0, w1, w2, k)
            nrm[i, k] = tri_normals[t, k]
            f = base_color[m, k]
            if has_colors:
                f *= _barycentric(colors, a, b, c, w0, w1, w2, k)
            alb[i, k] = f
            emi[i, k] = emissive[m, k]
    return pos, nrm, alb, emi


@numba.njit(**_JIT)
def light_rays(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    kind: NDArray[np.int64],
    light_pos: NDArray[np.float64],
    axis: NDArray[np.float64],
    power: NDArray[np.float64],
    light_range: NDArray[np.float64],
    angle_scale: NDArray[np.float64],
    angle_offset: NDArray[np.float64],
    eps: float,
    centre: NDArray[np.float64],
) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.float32], NDArray[np.float32],
           NDArray[np.float64], bool]:
    """The shadow rays of the punctual lights at surface points, and what each would deliver.

    :func:`probegrid.core.lights.incident_many` (kinds 0 point, 1 spot, 2 directional; the spec's
    range window ``clamp(1 - (d / range)^4, 0, 1) / d^2`` and spot cone
    ``saturate(cos * scale + offset)^2``) fused with the selection of
    :meth:`probegrid.bake.render.ProbeRenderer._visible_lights`: a (point, light) pair gets a shadow
    ray when the light delivers ``E_perp > 0`` and lies in front of the surface
    (``cos = dot(l, n) > 0``). The ray starts ``eps`` along the normal, with ``tmin = eps`` and
    ``tmax = distance - eps`` (inf for directional lights), and is written as Embree takes it
    (:func:`_embree_ray`, re-centred on ``centre``, the tracer's).

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
    n, nl = points.shape[0], kind.shape[0]
    cap = n * nl
    which = np.empty(cap, np.int64)
    org = np.empty((cap, 3), np.float32)
    dirs = np.empty((cap, 3), np.float32)
    far = np.empty(cap, np.float32)
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
            if not _embree_ray(org, dirs, far, k, px + eps * nx, py + eps * ny, pz + eps * nz,
                               lx, ly, lz, eps, dist - eps if dist < math.inf else math.inf,
                               centre):
                ok = False
            irr[k, 0], irr[k, 1], irr[k, 2] = cos * e0, cos * e1, cos * e2
            k += 1
    return which[:k], org[:k], dirs[:k], far[:k], irr[:k], ok


@numba.njit(**_JIT)
def _wrap(i: int, n: int, mode: int) -> int:
    """:func:`probegrid.scene._wrap_index` of one index: 0 repeat, 1 clamp, 2 mirror."""
    if mode == 0:
        return i % n
    if mode == 1:
        return min(max(i, 0), n - 1)
    m = i % (2 * n)
    return m if m < n else 2 * n - 1 - m


@numba.njit(**_JIT)
def multiply_texture(
    target: NDArray[np.float64],
    rows: NDArray[np.int64],
    prim: NDArray[np.int64],
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    triangles: NDArray[np.int64],
    uvs: NDArray[np.float64],
    texture: NDArray[np.float32],
    wrap_s: int,
    wrap_t: int,
) -> None:
    """Multiply ``target[rows] (k, 3)`` in place by a texture's RGB at the hits' UVs.

    :func:`probegrid.scene.sample_texture` (bilinear, texel centres at ``(col + 0.5) / W``,
    ``(row + 0.5) / H``, wrap modes 0 repeat, 1 clamp, 2 mirror) at the UV interpolated with
    barycentrics ``u[rows], v[rows]`` over triangle ``prim[rows]``; ``uvs`` empty means UV 0.
    """
    h, w = texture.shape[0], texture.shape[1]
    has_uv = uvs.shape[0] > 0
    for j in range(rows.shape[0]):
        i = rows[j]
        s, t = 0.0, 0.0
        if has_uv:
            tri = prim[i]
            w1, w2 = u[i], v[i]
            w0 = 1.0 - w1 - w2
            a, b, c = triangles[tri, 0], triangles[tri, 1], triangles[tri, 2]
            s = w0 * uvs[a, 0] + w1 * uvs[b, 0] + w2 * uvs[c, 0]
            t = w0 * uvs[a, 1] + w1 * uvs[b, 1] + w2 * uvs[c, 1]
        x = s * w - 0.5
        y = t * h - 0.5
        x0, y0 = math.floor(x), math.floor(y)
        fx, fy = x - x0, y - y0
        xi, yi = int(x0), int(y0)
        c0, c1 = _wrap(xi, w, wrap_s), _wrap(xi + 1, w, wrap_s)
        r0, r1 = _wrap(yi, h, wrap_t), _wrap(yi + 1, h, wrap_t)
        for k in range(3):
            top = texture[r0, c0, k] * (1.0 - fx) + texture[r0, c1, k] * fx
            bottom = texture[r1, c0, k] * (1.0 - fx) + texture[r1, c1, k] * fx
            target[i, k] *= top * (1.0 - fy) + bottom * fy


@numba.njit(**_JIT)
def cube_sample_directions(
    n: int,
    jitter: NDArray[np.float64],
    face_normals: NDArray[np.float64],
    face_u: NDArray[np.float64],
    face_v: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit directions of jittered samples in every texel of an ``n``-cube, and their weights.

    Sample ``k`` of texel ``(f, row, col)`` sits at continuous texel coordinates
    ``(col - 0.5 + jitter[k, 0], row - 0.5 + jitter[k, 1])`` (face coordinates
    ``(c + 0.5) 2 / n - 1``, :func:`probegrid.core.cubemap.texel_to_uv`); its direction is
    ``normal + u U + v V`` normalised and its weight the area element ``|d|^-3``, normalised
    over the texel's samples.

    Returns
    -------
    directions : (6, n, n, s, 3) float64
    weights : (6, n, n, s) float64
    """
    s = jitter.shape[0]
    d = np.empty((6, n, n, s, 3))
    wt = np.empty((6, n, n, s))
    scale = 2.0 / n
    for f in range(6):
        for row in range(n):
            for col in range(n):
                total = 0.0
                for k in range(s):
                    uu = (col - 0.5 + jitter[k, 0] + 0.5) * scale - 1.0
                    vv = (row - 0.5 + jitter[k, 1] + 0.5) * scale - 1.0
                    x = face_normals[f, 0] + uu * face_u[f, 0] + vv * face_v[f, 0]
                    y = face_normals[f, 1] + uu * face_u[f, 1] + vv * face_v[f, 1]
                    z = face_normals[f, 2] + uu * face_u[f, 2] + vv * face_v[f, 2]
                    norm = math.sqrt(x * x + y * y + z * z)
                    d[f, row, col, k, 0] = x / norm
                    d[f, row, col, k, 1] = y / norm
                    d[f, row, col, k, 2] = z / norm
                    a = 1.0 / (norm * norm * norm)
                    wt[f, row, col, k] = a
                    total += a
                for k in range(s):
                    wt[f, row, col, k] /= total
    return d, wt


@numba.njit(**_JIT)
def texel_means(radiance: NDArray[np.float32], weights: NDArray[np.float64],
                samples: int) -> NDArray[np.float32]:
    """Weighted mean radiance of each texel's rays.

    ``radiance (R, 3)`` float32 of rays stored texel by texel (``samples`` consecutive rays per
    texel) and their ``weights (R,)`` (summing to 1 over each texel's rays); returns
    ``(R / samples, 3)`` float32, summed in float64.
    """
    n = radiance.shape[0] // samples
    out = np.empty((n, 3), np.float32)
    for i in range(n):
        a0 = a1 = a2 = 0.0
        for k in range(i * samples, (i + 1) * samples):
            w = weights[k]
            a0 += w * radiance[k, 0]
            a1 += w * radiance[k, 1]
            a2 += w * radiance[k, 2]
        out[i, 0], out[i, 1], out[i, 2] = a0, a1, a2
    return out


@numba.njit(**_JIT)
def distance_moments(distance: NDArray[np.float64], solid_angle: NDArray[np.float64],
                     bins: NDArray[np.int64], n_bins: int) -> NDArray[np.float32]:
    """Solid-angle-weighted mean distance and mean squared distance per bin.

    ``distance (R,)`` of rays carrying ``solid_angle (R,)`` steradians, ``bins (R,)`` in
    ``[0, n_bins)``; returns ``(n_bins, 2)`` float32 (sums in float64; an empty bin is nan).
    """
    den = np.zeros(n_bins)
    mu = np.zeros(n_bins)
    m2 = np.zeros(n_bins)
    for k in range(distance.shape[0]):
        b = bins[k]
        a = solid_angle[k]
        t = distance[k]
        den[b] += a
        mu[b] += a * t
        m2[b] += a * t * t
    out = np.empty((n_bins, 2), np.float32)
    for b in range(n_bins):
        out[b, 0] = mu[b] / den[b]
        out[b, 1] = m2[b] / den[b]
    return out


@numba.njit(inline="always", **_JIT)
def _embree_ray(org: NDArray[np.float32], d32: NDArray[np.float32], far: NDArray[np.float32],
                k: int, ox: float, oy: float, oz: float, dx: float, dy: float, dz: float,
                lo: float, hi: float, centre: NDArray[np.float64]) -> bool:
    """Ray ``k`` as Embree takes it (:class:`probegrid.raytrace.EmbreeRays`): the origin
    ``(o - centre) + lo d`` in float64, rounded to float32 once, the direction rounded, the
    length ``hi - lo``. Returns whether the origin and direction are finite in float32. The one
    rounding rule of every ray cast (:func:`embree_rays`, :func:`light_rays`,
    :func:`emitter_samples`, :func:`environment_samples`, :func:`segment_rays`)."""
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


@numba.njit(**_JIT)
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
    one_o = origins.shape[0] == 1
    one_lo = tmin.shape[0] == 1
    one_hi = tmax.shape[0] == 1
    ok = True
    for i in range(m):
        io = 0 if one_o else i
        if not _embree_ray(org, d32, far, i, origins[io, 0], origins[io, 1], origins[io, 2],
                           directions[i, 0], directions[i, 1], directions[i, 2],
                           tmin[0] if one_lo else tmin[i], tmax[0] if one_hi else tmax[i],
                           centre):
            ok = False
    return org, d32, far, ok


@numba.njit(**_JIT)
def embree_hits(
    prim_id: NDArray[np.int32],
    tfar: NDArray[np.float32],
    u: NDArray[np.float32],
    v: NDArray[np.float32],
    tmin: NDArray[np.float64],
    start: int,
    prim_out: NDArray[np.int64],
    t_out: NDArray[np.float64],
    u_out: NDArray[np.float64],
    v_out: NDArray[np.float64],
) -> None:
    """Copy Embree's answers for rays ``start:start + m`` into the float64 / int64 outputs: the
    hit distance measured from the ray's origin (``tfar + tmin``; ``tmin (1 or n,)``), inf and
    barycentrics 0 for a miss (``prim_id < 0``)."""
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


@numba.njit(**_JIT)
def segment_rays(
    starts: NDArray[np.float64],
    ends: NDArray[np.float64],
    margin: float,
    centre: NDArray[np.float64],
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32], bool]:
    """Segments ``starts[k] -> ends[k]`` (``starts`` one row: shared) as Embree occlusion rays,
    ``margin`` left out at both ends (:meth:`probegrid.raytrace.RayTracer.segments_occluded`; the query side, not the bake).

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
    ok = True
    for i in range(m):
        j = 0 if one else i
        d0 = ends[i, 0] - starts[j, 0]
        d1 = ends[i, 1] - starts[j, 1]
        d2 = ends[i, 2] - starts[j, 2]
        lo = margin / max(math.sqrt(d0 * d0 + d1 * d1 + d2 * d2), 1e-30)
        if not _embree_ray(org, d32, far, i, starts[j, 0], starts[j, 1], starts[j, 2],
                           d0, d1, d2, lo, 1.0 - lo, centre):
            ok = False
        far[i] = np.float32(1.0 - 2.0 * lo)  # (the length as stated above, rounded once)
    return org, d32, far, ok
# ------------------------------------------------------------------------------ trace once
@numba.njit(**_JIT)
def hit_probe_weights(
    points: NDArray[np.float64],
    normals: NDArray[np.floating],
    rows: NDArray[np.int64],
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    step: NDArray[np.float64],
    counts: NDArray[np.int64],
    corner_offsets: NDArray[np.int64],
    valid: NDArray[np.bool_],
    positions: NDArray[np.float64],
    moments: NDArray[np.float32],
    moments_n: int,
    bias: float,
    face_u: NDArray[np.float64],
    face_v: NDArray[np.float64],
    normal_floor: float,
    min_weight: float,
    crush: float,
) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """The 8 probes around surface points ``rows`` of ``points (n, 3)`` (unit ``normals``) and
    their normalised DDGI weights (the other rows, misses say, stay 0).

    The weights of :func:`probegrid.core.ddgi.probe_weights` with normals and moments (the
    normal-facing term, the Chebyshev test on the seamless bilinear moments, the crush),
    divided by their sum. They depend only on the geometry and the probes' distance moments, never on the
    light, so a bake computes them once per hit and every bounce reuses them.

    Returns
    -------
    indices : (n, 8) int32
        Linear probe indices (corner order of :data:`probegrid.core.grid.CORNER_OFFSETS`).
    weights : (n, 8) float32
        Normalised weights; all 0 where no valid probe carries weight.
    """
    n_pts = points.shape[0]
    out_i = np.zeros((n_pts, 8), np.int32)
    out_w = np.zeros((n_pts, 8), np.float32)
    use_moments = moments.shape[0] > 0
    m = moments_n
    mb = m + 2
    texels = 6 * mb * mb
    half = 0.5 * m
    crush2 = crush * crush
    w = np.empty(8)
    base = np.empty(3, np.int64)
    frac = np.empty(3)
    cp = np.empty(3)
    for j in range(rows.shape[0]):
        i = rows[j]
        nx = np.float64(normals[i, 0])  # (float() keeps a float32)
        ny, nz = np.float64(normals[i, 1]), np.float64(normals[i, 2])
        big = max(abs(nx), abs(ny), abs(nz))
        if not big > 0:
            continue
        nx, ny, nz = nx / big, ny / big, nz / big
        nl = math.sqrt(nx * nx + ny * ny + nz * nz)
        nx, ny, nz = nx / nl, ny / nl, nz / nl
        for a in range(3):
            c = min(max(points[i, a], lo[a]), hi[a])
            cp[a] = c
            if counts[a] > 1:
                t = (c - lo[a]) / step[a]
                b = min(max(math.floor(t), 0.0), float(max(counts[a] - 2, 0)))
                base[a] = int(b)
                frac[a] = min(max(t - b, 0.0), 1.0)
            else:
                base[a] = 0
                frac[a] = 0.0
        qx, qy, qz = cp[0] + bias * nx, cp[1] + bias * ny, cp[2] + bias * nz
        total = 0.0
        for c in range(8):
            ii = min(base[0] + corner_offsets[c, 0], counts[0] - 1)
            jj = min(base[1] + corner_offsets[c, 1], counts[1] - 1)
            kk = min(base[2] + corner_offsets[c, 2], counts[2] - 1)
            p = (ii * counts[1] + jj) * counts[2] + kk
            out_i[i, c] = p
            tw = 1.0
            for a in range(3):
                f = frac[a]
                tw *= f if corner_offsets[c, a] == 1 else 1.0 - f
            if not valid[p]:
                tw *= 0.0
            if tw == 0.0:
                w[c] = 0.0
                continue
            ex = positions[p, 0] - cp[0]
            ey = positions[p, 1] - cp[1]
            ez = positions[p, 2] - cp[2]
            el = math.sqrt(ex * ex + ey * ey + ez * ez)
            if el > 1e-300:
                dot = (ex * nx + ey * ny + ez * nz) / el
            else:
                dot = 0.0
            s = ((dot + 1.0) * 0.5) ** 2 + normal_floor
            if use_moments:
                ox = qx - positions[p, 0]
                oy = qy - positions[p, 1]
                oz = qz - positions[p, 2]
                r = math.sqrt(ox * ox + oy * oy + oz * oz)
                face, u, v = _face_uv(ox, oy, oz, face_u, face_v)
                x = (u + 1.0) * half + 0.5
                y = (v + 1.0) * half + 0.5
                x0 = min(math.floor(x), float(m))
                y0 = min(math.floor(y), float(m))
                fx, fy = x - x0, y - y0
                gx, gy = 1.0 - fx, 1.0 - fy
                t0 = p * texels + (face * mb + int(y0)) * mb + int(x0)
                w00, w01, w10, w11 = gy * gx, gy * fx, fy * gx, fy * fx
                mean = (moments[t0, 0] * w00 + moments[t0 + 1, 0] * w01
                        + moments[t0 + mb, 0] * w10 + moments[t0 + mb + 1, 0] * w11)
                if not r <= mean:
                    mean_sq = (moments[t0, 1] * w00 + moments[t0 + 1, 1] * w01
                               + moments[t0 + mb, 1] * w10 + moments[t0 + mb + 1, 1] * w11)
                    var = abs(mean_sq - mean * mean)
                    excess = max(r - mean, 0.0)
                    den = var + excess * excess
                    if excess > 0:
                        cheb = var / den if den != 0 else math.nan
                    else:
                        cheb = 1.0
                    if math.isnan(cheb):
                        cheb = 0.0
                    s *= cheb * cheb * cheb
            s = max(s, min_weight)
            if s < crush:
                s = s * s * s / crush2
            tw *= s
            w[c] = tw
            total += tw
        if total <= 0:
            continue
        for c in range(8):
            out_w[i, c] = w[c] / total
    return out_i, out_w


@numba.njit(**_JIT)
def replay_radiance(
    kind: NDArray[np.uint8],
    emission: NDArray[np.float32],
    light_punctual: NDArray[np.float32],
    light_emitters: NDArray[np.float32],
    albedo: NDArray[np.float32],
    normals: NDArray[np.float32],
    indices: NDArray[np.int32],
    weights: NDArray[np.float32],
    cubes: NDArray[np.float32],
    cube_n: int,
    face_u: NDArray[np.float64],
    face_v: NDArray[np.float64],
    level: int,
    indirect: NDArray[np.float32],
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """One bounce of a probe's rays from their per-hit records (no ray is cast).

    Per ray, by ``kind`` (0 a miss, 1 a front hit, 2 a back hit):

    * a miss returns ``light_punctual`` (where a miss keeps the environment's radiance);
    * a back hit returns 0;
    * a front hit returns ``emission + albedo * lit`` with, at ``level`` 0,
      ``lit = light_punctual`` (the punctual lights' irradiance / pi) and, at higher levels,
      ``lit = light_punctual + light_emitters + sum_c weights[c] * G[indices[c]](normal)``:
      the emitters' irradiance / pi (next-event estimation) and the grid's bounced
      irradiance / pi, ``G`` each probe's bordered irradiance cube ``cubes`` (face ``cube_n``,
      :class:`probegrid.core.ddgi.BorderedCubes` layout ``(P * 6 (n + 2)^2, 3)``) read
      bilinearly at the normal; an empty ``cubes`` is a black grid. A non-empty ``indirect``
      ``(N, 3)`` (irradiance / pi gathered at each hit) takes the grid's place. An empty
      ``emission`` ``(0, 3)`` is no emission (``normals`` may be empty when no grid is read).

    Returns
    -------
    radiance : (N, 3) float32
        What the probe sees along each ray.
    bounced : (N, 3) float32
        The same without the emission of the surfaces hit: the light that the grid carries
        (reflected at least once, or the environment: the caller zeroes the misses when the
        environment is sampled at the hits instead).
    """
    nr = kind.shape[0]
    rad = np.zeros((nr, 3), np.float32)
    bnc = np.zeros((nr, 3), np.float32)
    has_emission = emission.shape[0] > 0
    use_indirect = level > 0 and indirect.shape[0] > 0
    use_grid = level > 0 and cubes.shape[0] > 0 and not use_indirect
    n = cube_n
    mb = n + 2
    texels = 6 * mb * mb
    half = 0.5 * n
    for i in range(nr):
        k = kind[i]
        if k == 2:
            continue
        if k == 0:
            for c in range(3):
                rad[i, c] = light_punctual[i, c]
                bnc[i, c] = light_punctual[i, c]
            continue
        l0 = np.float64(light_punctual[i, 0])
        l1 = np.float64(light_punctual[i, 1])
        l2 = np.float64(light_punctual[i, 2])
        if level > 0:
            l0 += light_emitters[i, 0]
            l1 += light_emitters[i, 1]
            l2 += light_emitters[i, 2]
        if use_indirect:
            l0 += indirect[i, 0]
            l1 += indirect[i, 1]
            l2 += indirect[i, 2]
        if use_grid:
            face, u, v = _face_uv(np.float64(normals[i, 0]), np.float64(normals[i, 1]),
                                  np.float64(normals[i, 2]), face_u, face_v)
            x = (u + 1.0) * half + 0.5
            y = (v + 1.0) * half + 0.5
            x0 = min(math.floor(x), float(n))
            y0 = min(math.floor(y), float(n))
            fx, fy = x - x0, y - y0
            gx, gy = 1.0 - fx, 1.0 - fy
            off = (face * mb + int(y0)) * mb + int(x0)
            w00, w01, w10, w11 = gy * gx, gy * fx, fy * gx, fy * fx
            for c in range(8):
                wc = np.float64(weights[i, c])
                if wc == 0.0:
                    continue
                t0 = indices[i, c] * texels + off
                l0 += wc * (cubes[t0, 0] * w00 + cubes[t0 + 1, 0] * w01
                            + cubes[t0 + mb, 0] * w10 + cubes[t0 + mb + 1, 0] * w11)
                l1 += wc * (cubes[t0, 1] * w00 + cubes[t0 + 1, 1] * w01
                            + cubes[t0 + mb, 1] * w10 + cubes[t0 + mb + 1, 1] * w11)
                l2 += wc * (cubes[t0, 2] * w00 + cubes[t0 + 1, 2] * w01
                            + cubes[t0 + mb, 2] * w10 + cubes[t0 + mb + 1, 2] * w11)
        b0 = albedo[i, 0] * l0
        b1 = albedo[i, 1] * l1
        b2 = albedo[i, 2] * l2
        bnc[i, 0], bnc[i, 1], bnc[i, 2] = b0, b1, b2
        if has_emission:
            rad[i, 0] = emission[i, 0] + b0
            rad[i, 1] = emission[i, 1] + b1
            rad[i, 2] = emission[i, 2] + b2
        else:
            rad[i, 0], rad[i, 1], rad[i, 2] = b0, b1, b2
    return rad, bnc


@numba.njit(**_JIT)
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
#: (``tests/test_kernels.py`` checks :func:`_angle` against ``numpy.arctan2``).
_ATAN_P = (-0.33333333333256987, 0.19999999982203043, -0.14285712845711665,
           0.11111053636467254, -0.0908960261715069, 0.07674200140399653,
           -0.06509586311864264, 0.05035419831218217, -0.02544895846987845)
_TAN_PI_8 = math.tan(math.pi / 8)
_TAN2_PI_8 = _TAN_PI_8 * _TAN_PI_8


@numba.njit(inline="always", **_JIT)
def _atan_poly(z: float) -> float:
    """:data:`_ATAN_P`'s ``P(z)`` (``atan(t) = t + t^3 P(t^2)``, ``z = t^2 <= tan(pi / 8)^2``) by
    Estrin's scheme."""
    p0, p1, p2, p3, p4, p5, p6, p7, p8 = _ATAN_P
    z2 = z * z
    z4 = z2 * z2
    return (((p0 + p1 * z) + (p2 + p3 * z) * z2) + ((p4 + p5 * z) + (p6 + p7 * z) * z2) * z4
            + p8 * (z4 * z4))


@numba.njit(**_JIT)
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


@numba.njit(**_JIT)
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


@numba.njit(**_JIT)
def polygon_irradiance(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    loop_vertices: NDArray[np.float64],
    loop_start: NDArray[np.int64],
    group_loops: NDArray[np.int64],
    group_normals: NDArray[np.float64],
    group_radiance: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Unoccluded irradiance of uniformly emitting planar regions at surface points (exact).

    Region ``q`` is bounded by the closed loops ``group_loops[q] .. group_loops[q + 1] - 1``
    (an outline and its holes; loop ``l`` is ``loop_vertices[loop_start[l]:loop_start[l + 1]]``,
    counter-clockwise seen from the side ``group_normals[q]`` points to) and emits
    ``group_radiance[q] (3,)`` from that side. At a point ``points (n, 3)`` with unit
    ``normals (n, 3)`` in front of the region's plane, every loop is clipped to the point's upper
    half-space (Sutherland-Hodgman, which keeps a loop's signed edge sum right even when it is
    not convex) and the region's cosine-weighted solid angle is ``|sum of the loops' edge sums|
    / 2`` (Lambert's edge formula). A triangle is a region of one 3-vertex loop
    (:func:`emitter_irradiance`). Returns ``(n, 3)`` lux.
    """
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
        np.ascontiguousarray(np.asarray(tri_vertices, np.float64).reshape(-1, 3)),
        np.arange(0, 3 * e + 1, 3, dtype=np.int64), np.arange(e + 1, dtype=np.int64),
        np.ascontiguousarray(tri_normals, dtype=np.float64),
        np.ascontiguousarray(tri_radiance, dtype=np.float64))


_ShadowRays = tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.float32],
                    NDArray[np.float32], NDArray[np.float64], NDArray[np.float64],
                    NDArray[np.bool_]]


@numba.njit(**_JIT)
def _shadow_ray_arrays(cap: int) -> _ShadowRays:
    """Room for ``cap`` of :func:`emitter_shadow_rays`' rays (the last array: all finite)."""
    return (np.empty(cap, np.int64), np.empty((cap, 3), np.float32),
            np.empty((cap, 3), np.float32), np.empty(cap, np.float32), np.empty((cap, 3)),
            np.empty((cap, 3)), np.ones(1, np.bool_))


@numba.njit(**_JIT)
def _first_rays(out: _ShadowRays, k: int) -> _ShadowRays:
    """The first ``k`` of :func:`_shadow_ray_arrays`' rays: the ones stored."""
    which, org, dirs, far, vis, occ, ok = out
    return which[:k], org[:k], dirs[:k], far[:k], vis[:k], occ[:k], ok


# inlined by numba: a call per sample passing six arrays cost 15 % of emitter_samples
@numba.njit(inline="always", **_JIT)
def _emitter_shadow_ray(points: NDArray[np.float64], normals: NDArray[np.float64], i: int,
                        qx: float, qy: float, qz: float, qnx: float, qny: float, qnz: float,
                        radiance: NDArray[np.float64], control: NDArray[np.float64], row: int,
                        inverse_pdf: float, inv_l: float, eps: float,
                        centre: NDArray[np.float64], k: int, which: NDArray[np.int64],
                        org: NDArray[np.float32], dirs: NDArray[np.float32],
                        far: NDArray[np.float32], vis: NDArray[np.float64],
                        occ: NDArray[np.float64], ok: NDArray[np.bool_]) -> int:
    """One sample of :func:`emitter_shadow_rays` (point ``i``, the sample at ``(qx, qy, qz)``
    with normal ``qn``, radiance and control in row ``row`` of ``radiance`` and ``control``,
    ``inv_l`` = 1 / L), stored as ray ``k`` when it counts (``ok[0]`` cleared if it is not
    finite); returns the next free ray."""
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
    if not _embree_ray(org, dirs, far, k, ox, oy, oz, sx / sl, sy / sl, sz / sl, eps, sl - eps,
                       centre):
        ok[0] = False
    vis[k, 0], vis[k, 1], vis[k, 2] = g * (r0 - c0), g * (r1 - c1), g * (r2 - c2)
    occ[k, 0], occ[k, 1], occ[k, 2] = -g * c0, -g * c1, -g * c2
    return k + 1


@numba.njit(**_JIT)
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
        The shadow rays as Embree takes them (:func:`_embree_ray`, re-centred on ``centre``,
        the tracer's; :class:`probegrid.raytrace.EmbreeRays`).
    visible, occluded : (k, 3) contributions (lux) for the two outcomes.
    ok : (1,) bool
        Whether every ray is finite in float32.
    """
    n, ns = sample_points.shape[0], sample_points.shape[1]
    out = _shadow_ray_arrays(n * ns)
    which, org, dirs, far, vis, occ, ok = out
    k = 0
    inv_l = 1.0 / ns
    rad = sample_radiance.reshape(n * ns, 3)
    ctl = sample_control.reshape(n * ns, 3)
    for i in range(n):
        for s in range(ns):
            k = _emitter_shadow_ray(
                points, normals, i, sample_points[i, s, 0], sample_points[i, s, 1],
                sample_points[i, s, 2], sample_normals[i, s, 0], sample_normals[i, s, 1],
                sample_normals[i, s, 2], rad, ctl, i * ns + s, inverse_pdf[i, s], inv_l, eps,
                centre, k, which, org, dirs, far, vis, occ, ok)
    return _first_rays(out, k)


@numba.njit(**_JIT)
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


@numba.njit(**_JIT)
def texel_emitter_coverage(
    origin: NDArray[np.float64],
    tri_vertices: NDArray[np.float64],
    tri_normals: NDArray[np.float64],
    n: int,
    face_normals: NDArray[np.float64],
    face_u: NDArray[np.float64],
    face_v: NDArray[np.float64],
    capacity: int,
) -> tuple[int, NDArray[np.int64], NDArray[np.int64], NDArray[np.float64], NDArray[np.float64],
           NDArray[np.float64]]:
    """The exact solid angle of every (cube texel, emitting triangle) overlap seen from a point.

    Each triangle whose front faces ``origin (3,)`` is clipped to every face's frustum
    (``|x.U| <= x.N``, ``|x.V| <= x.N``), projected onto the face plane (straight edges stay
    straight), and clipped to each texel square of an ``n``-cube it touches; the piece's solid
    angle is the fan sum of :func:`_polygon_solid_angle`. Visibility is not tested here.

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


@numba.njit(inline="always", **_JIT)
def _alias_pick(accept: NDArray[np.float64], alias: NDArray[np.int64], r: float) -> int:
    """One draw of :func:`alias_draw` (its rule, compiled): ``i = floor(r N)``, then ``i`` if
    ``frac(r N) < accept[i]`` else ``alias[i]``."""
    n = accept.shape[0]
    x = r * n  # the alias table's column, then its coin
    t = min(int(x), n - 1)
    if not x - t < accept[t]:
        t = alias[t]
    return t


@numba.njit(inline="always", **_JIT)
def _rotate(rotation: NDArray[np.float64], x: float, y: float, z: float
            ) -> tuple[float, float, float]:
    """``rotation (3, 3) @ (x, y, z)`` (pass ``rotation.T`` to turn back)."""
    return (rotation[0, 0] * x + rotation[0, 1] * y + rotation[0, 2] * z,
            rotation[1, 0] * x + rotation[1, 1] * y + rotation[1, 2] * z,
            rotation[2, 0] * x + rotation[2, 1] * y + rotation[2, 2] * z)


def alias_draw(accept: NDArray[np.float64], alias: NDArray[np.int64], random: ArrayLike
               ) -> NDArray[np.int64]:
    """The entries an :func:`alias_table` ``(accept, alias)`` draws for uniform ``random`` in
    [0, 1) (any shape): ``i = floor(r N)``, then ``i`` if ``frac(r N) < accept[i]`` else
    ``alias[i]`` -- the rule :func:`emitter_samples` and :func:`environment_samples` draw by
    (:func:`_alias_pick`)."""
    n = len(accept)
    x = np.asarray(random, dtype=np.float64) * n
    t = np.minimum(x.astype(np.int64), n - 1)
    return np.where(x - t < accept[t], t, alias[t])


@numba.njit(**_JIT)
def emitter_samples(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    random: NDArray[np.float64],
    accept: NDArray[np.float64],
    alias: NDArray[np.int64],
    inverse_pdf: NDArray[np.float64],
    tri_vertices: NDArray[np.float64],
    tri_normals: NDArray[np.float64],
    tri_radiance: NDArray[np.float64],
    tri_control: NDArray[np.float64],
    eps: float,
    centre: NDArray[np.float64],
) -> _ShadowRays:
    """:func:`emitter_shadow_rays` of points sampled on untextured emitters, from uniform
    numbers: :meth:`probegrid.bake.emitters.Emitters.irradiance`'s choice of a triangle
    (drawn by ``random[..., 0]`` from the selection's :func:`alias_table` ``(accept, alias)``,
    :func:`alias_draw`'s rule), its uniform point (``sqrt(r1) (1 - r2), sqrt(r1) r2`` as
    barycentrics ``u, v``; position ``(1 - u - v) a + u b + v c``) and radiance
    ``tri_radiance[e]``, in one pass.

    ``random (n, L, 3)``; ``inverse_pdf (E,)`` area over the selection probability;
    ``tri_vertices (E, 3, 3)``, ``tri_normals``, ``tri_radiance``, ``tri_control (E, 3)``.
    Returns what :func:`emitter_shadow_rays` returns.
    """
    n, ns = random.shape[0], random.shape[1]
    out = _shadow_ray_arrays(n * ns)
    which, org, dirs, far, vis, occ, ok = out
    k = 0
    inv_l = 1.0 / ns
    for i in range(n):
        for s in range(ns):
            e = _alias_pick(accept, alias, random[i, s, 0])
            r1 = math.sqrt(random[i, s, 1])
            w1 = r1 * (1.0 - random[i, s, 2])
            w2 = r1 * random[i, s, 2]
            w0 = 1.0 - w1 - w2
            q = tri_vertices
            k = _emitter_shadow_ray(
                points, normals, i, w0 * q[e, 0, 0] + w1 * q[e, 1, 0] + w2 * q[e, 2, 0],
                w0 * q[e, 0, 1] + w1 * q[e, 1, 1] + w2 * q[e, 2, 1],
                w0 * q[e, 0, 2] + w1 * q[e, 1, 2] + w2 * q[e, 2, 2], tri_normals[e, 0],
                tri_normals[e, 1], tri_normals[e, 2], tri_radiance, tri_control, e,
                inverse_pdf[e], inv_l, eps, centre, k, which, org, dirs, far, vis, occ, ok)
    return _first_rays(out, k)


@numba.njit(**_JIT)
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


@numba.njit(**_JIT)
def alias_table(prob: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Walker's alias table of a discrete distribution ``prob (N,)`` (summing to 1), built by
    Vose's method: entry ``i`` is kept with probability ``accept[i]`` and otherwise gives
    ``alias[i]``, so ``i = floor(r N)``, then ``i`` if ``frac(r N) < accept[i]`` else
    ``alias[i]`` draws index ``t`` with probability ``prob[t]`` from one uniform ``r`` in O(1)
    (:func:`environment_samples`; a zero-probability entry is never drawn)."""
    n = prob.shape[0]
    scaled = prob * n
    accept = np.ones(n)
    alias = np.arange(n)
    small = np.empty(n, np.int64)
    large = np.empty(n, np.int64)
    ns = 0
    nl = 0
    for i in range(n):
        if scaled[i] < 1.0:
            small[ns] = i
            ns += 1
        else:
            large[nl] = i
            nl += 1
    while ns > 0 and nl > 0:
        ns -= 1
        lo = small[ns]
        hi = large[nl - 1]
        accept[lo] = scaled[lo]
        alias[lo] = hi
        scaled[hi] = (scaled[hi] + scaled[lo]) - 1.0
        if scaled[hi] < 1.0:  # now short itself: the next one to be topped up
            nl -= 1
            small[ns] = hi
            ns += 1
    return accept, alias  # (entries left over are full up to rounding: accept 1)


@numba.njit(**_JIT)
def _environment_texel(dx: float, dy: float, dz: float, m: int, face_u: NDArray[np.float64],
                       face_v: NDArray[np.float64]) -> tuple[int, float]:
    """The texel of an ``m``-cube a unit direction (environment frame) falls in and
    ``(1 + u^2 + v^2)^(3/2)``, its density's texel-to-solid-angle factor."""
    face, u, v = _face_uv(dx, dy, dz, face_u, face_v)
    col = min(max(int((u + 1.0) * 0.5 * m), 0), m - 1)
    row = min(max(int((v + 1.0) * 0.5 * m), 0), m - 1)
    q = 1.0 + u * u + v * v
    return (face * m + row) * m + col, q * math.sqrt(q)


@numba.njit(**_JIT)
def environment_samples(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    random: NDArray[np.float64],
    accept: NDArray[np.float64],
    alias: NDArray[np.int64],
    prob: NDArray[np.float64],
    radiance: NDArray[np.float64],
    size: int,
    rotation: NDArray[np.float64],
    face_normals: NDArray[np.float64],
    face_u: NDArray[np.float64],
    face_v: NDArray[np.float64],
    mirrors: NDArray[np.int64],
    eps: float,
    centre: NDArray[np.float64],
) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.float32], NDArray[np.float32],
           NDArray[np.float64], bool]:
    """Directions drawn from a piecewise-constant environment cube, folded into the upper
    hemisphere of each normal, and their contributions
    (:class:`probegrid.bake.environment.EnvironmentLight`: ``sample_above`` and the estimator
    of ``irradiance`` before the shadow rays).

    A texel ``t`` of the ``size``-cube (flat ``(face, row, col)`` order) drawn with probability
    ``prob[t]`` from ``r0`` through its :func:`alias_table` ``(accept, alias)``, the point
    ``u = -1 + (col + r1) 2 / size``,
    ``v = -1 + (row + r2) 2 / size`` of its face square, the direction normalised and turned by
    ``rotation (3, 3)`` (environment frame to world): density
    ``p(w) = prob[t] (size^2 / 4) (1 + u^2 + v^2)^(3/2)``. A direction below the point's
    horizon is mirrored in its tangent plane, ``w - 2 (n . w) n`` (a reflection: it keeps solid
    angle), so every sample lands above it with density ``p(w) + p(mirror of w)``, and
    contributes ``radiance[texel of w] cos / (density L)`` and a shadow ray toward ``w``
    (unless ``cos = 0`` or the density is 0). Where the normal lies along an axis of the
    environment frame (floors, walls and ceilings, mostly) the mirror is the reflection in a
    coordinate plane, a symmetry of the cube: the mirror's texel is ``mirrors[axis, t]``
    (:func:`probegrid.core.cubemap.texel_permutation`, ``(3, 6 size^2)``) and its
    ``1 + u^2 + v^2`` is the sample's, with no lookup.

    ``points (n, 3)`` and their ``normals``, ``random (n, L, 3)``. Returns ``point (k,)``, the
    shadow rays from the points toward the directions (``tmin = eps``, no end) as Embree takes
    them (float32 ``origins``, ``directions (k, 3)`` and ``lengths (k,)``, :func:`_embree_ray`,
    re-centred on ``centre``, the tracer's), ``contribution (k, 3)`` of the samples that count
    and whether every ray is finite in float32.
    """
    n, ns = random.shape[0], random.shape[1]
    cap = n * ns
    which = np.empty(cap, np.int64)
    org = np.empty((cap, 3), np.float32)
    dirs = np.empty((cap, 3), np.float32)
    far = np.empty(cap, np.float32)
    contrib = np.empty((cap, 3))
    ok = True
    m = size
    mm = m * m
    step = 2.0 / m
    area = 0.25 * m * m
    # (the identity, an unrotated environment, is skipped: a sample costs a third less)
    rotated = not (rotation[0, 0] == 1.0 and rotation[1, 1] == 1.0 and rotation[2, 2] == 1.0)
    to_env = rotation.T  # world -> environment frame
    k = 0
    for i in range(n):
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        mx, my, mz = nx, ny, nz  # the normal in the environment frame
        if rotated:
            mx, my, mz = _rotate(to_env, nx, ny, nz)
        axis = -1  # the axis whose coordinate plane the mirror reflects in, if any
        if my == 0.0 and mz == 0.0:
            axis = 0
        elif mx == 0.0 and mz == 0.0:
            axis = 1
        elif mx == 0.0 and my == 0.0:
            axis = 2
        for s in range(ns):
            t = _alias_pick(accept, alias, random[i, s, 0])
            face = t // mm
            rest = t - face * mm
            row = rest // m
            col = rest - row * m
            u = -1.0 + (col + random[i, s, 1]) * step
            v = -1.0 + (row + random[i, s, 2]) * step
            q = 1.0 + u * u + v * v
            sq = math.sqrt(q)
            inv = 1.0 / sq
            wx = (face_normals[face, 0] + u * face_u[face, 0] + v * face_v[face, 0]) * inv
            wy = (face_normals[face, 1] + u * face_u[face, 1] + v * face_v[face, 1]) * inv
            wz = (face_normals[face, 2] + u * face_u[face, 2] + v * face_v[face, 2]) * inv
            if rotated:
                wx, wy, wz = _rotate(rotation, wx, wy, wz)
            cos = wx * nx + wy * ny + wz * nz
            if cos == 0.0 or math.isnan(cos):
                continue
            pdf = prob[t] * area * q * sq  # the drawn direction's density
            # its mirror in the tangent plane, in the environment frame (rotation^T)
            rx, ry, rz = wx - 2.0 * cos * nx, wy - 2.0 * cos * ny, wz - 2.0 * cos * nz
            if axis >= 0:
                tr, qr = mirrors[axis, t], q * sq
            else:
                ex, ey, ez = _rotate(to_env, rx, ry, rz) if rotated else (rx, ry, rz)
                tr, qr = _environment_texel(ex, ey, ez, m, face_u, face_v)
            pdf += prob[tr] * area * qr
            if cos < 0.0:  # below the horizon: the mirror is the sample
                wx, wy, wz, t, cos = rx, ry, rz, tr, -cos
            if not pdf > 0.0:
                continue
            w = cos / (pdf * ns)
            which[k] = i
            if not _embree_ray(org, dirs, far, k, points[i, 0], points[i, 1], points[i, 2],
                               wx, wy, wz, eps, math.inf, centre):
                ok = False
            contrib[k, 0] = radiance[t, 0] * w
            contrib[k, 1] = radiance[t, 1] * w
            contrib[k, 2] = radiance[t, 2] * w
            k += 1
    return which[:k], org[:k], dirs[:k], far[:k], contrib[:k], ok


@numba.njit(**_JIT)
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


@numba.njit(**_JIT)
def _turn(r: float) -> tuple[float, float]:
    """``(cos, sin)`` of the angle ``2 pi r`` for ``r`` in [0, 1), to within 2e-16: the quarter
    turn ``q = floor(4 r)`` is exact, the rest ``a = (4 r - q - 1/2) pi / 2`` lies within
    ``pi / 4`` of 0, where the Taylor series of ``sin a`` to ``a^15`` and of ``cos a`` to
    ``a^16`` are exact to 5e-17; then ``pi / 4 + a`` and the quarter turns are rotations.
    Costs a third of the C library's ``cos`` and ``sin`` (:func:`gather_rays`' azimuths)."""
    x = 4.0 * r
    q = min(int(x), 3)
    a = (x - q - 0.5) * (0.5 * math.pi)
    z = a * a
    sa = a * (1.0 + z * (-1.0 / 6 + z * (1.0 / 120 + z * (-1.0 / 5040 + z * (
        1.0 / 362880 + z * (-1.0 / 39916800 + z * (1.0 / 6227020800
                                                   - z / 1307674368000.0)))))))
    ca = 1.0 + z * (-0.5 + z * (1.0 / 24 + z * (-1.0 / 720 + z * (1.0 / 40320 + z * (
        -1.0 / 3628800 + z * (1.0 / 479001600 + z * (-1.0 / 87178291200
                                                     + z / 20922789888000.0)))))))
    h = math.sqrt(0.5)
    c, s = h * (ca - sa), h * (ca + sa)  # the angle pi / 4 + a
    if q == 0:
        return c, s
    if q == 1:
        return -s, c
    if q == 2:
        return -c, -s
    return s, -c


@numba.njit(**_JIT)
def _cosine_direction(nx: float, ny: float, nz: float, r0: float, r1: float
                      ) -> tuple[float, float, float]:
    """One cosine-weighted unit direction about the unit normal ``n`` (:func:`cosine_directions`)."""
    sign = 1.0 if nz >= 0.0 else -1.0
    a = -1.0 / (sign + nz)
    bb = nx * ny * a
    t1x, t1y, t1z = 1.0 + sign * nx * nx * a, sign * bb, -sign * nx
    t2x, t2y, t2z = bb, sign + ny * ny * a, -ny
    r = math.sqrt(r0)
    z = math.sqrt(max(1.0 - r0, 0.0))
    cp, sp = _turn(r1)  # the azimuth 2 pi r1
    c, s = r * cp, r * sp
    dx = c * t1x + s * t2x + z * nx
    dy = c * t1y + s * t2y + z * ny
    dz = c * t1z + s * t2z + z * nz
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    return dx / norm, dy / norm, dz / norm


@numba.njit(**_JIT)
def cosine_directions(normals: NDArray[np.float64], random: NDArray[np.float64]
                      ) -> NDArray[np.float64]:
    """Cosine-weighted unit directions about unit ``normals (n, 3)`` from uniform
    ``random (n, 2)`` (density ``cos / pi``): ``sqrt(r0)`` the sine of the polar angle,
    ``2 pi r1`` the azimuth, in the orthonormal basis of Duff et al., "Building an Orthonormal
    Basis, Revisited", JCGT 6(1), 2017. Returns ``(n, 3)``."""
    n = normals.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        out[i, 0], out[i, 1], out[i, 2] = _cosine_direction(
            normals[i, 0], normals[i, 1], normals[i, 2], random[i, 0], random[i, 1])
    return out


@numba.njit(**_JIT)
def gather_rays(positions: NDArray[np.float64], normals: NDArray[np.floating],
                arriving: NDArray[np.float64], parents: NDArray[np.int64],
                random: NDArray[np.float64], eps: float
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The final gather's rays from hits ``parents (k,)`` of a level (their ``positions``,
    unit ``normals`` facing the side the ray came from, and the ``arriving`` directions that
    found them): origins ``position - eps arriving + eps normal`` (off the surface and back
    along the ray: a hit on an edge of a closed room would start its rays in the next wall)
    and :func:`cosine_directions` about the normals from ``random (k, 2)``. Returns both
    ``(k, 3)``."""
    k = parents.shape[0]
    org = np.empty((k, 3))
    dirs = np.empty((k, 3))
    for j in range(k):
        i = parents[j]
        nx = np.float64(normals[i, 0])  # (float() keeps a float32)
        ny, nz = np.float64(normals[i, 1]), np.float64(normals[i, 2])
        for a in range(3):
            org[j, a] = positions[i, a] - eps * arriving[i, a] + eps * np.float64(normals[i, a])
        dirs[j, 0], dirs[j, 1], dirs[j, 2] = _cosine_direction(nx, ny, nz, random[j, 0],
                                                               random[j, 1])
    return org, dirs


@numba.njit(**_JIT)
def split_hits(
    directions: NDArray[np.float64],
    prim: NDArray[np.int64],
    tri_normals: NDArray[np.float64],
    double_sided: NDArray[np.bool_],
) -> tuple[NDArray[np.uint8], NDArray[np.int64], NDArray[np.bool_], NDArray[np.bool_]]:
    """Sort rays ``directions (k, 3)`` by what they hit (``prim (k,)``, -1 for a miss;
    ``tri_normals (T, 3)`` as wound): the backface rule (a ray that sees the back of a
    triangle that is not double-sided finds black).

    Returns ``kind (k,)`` uint8 (0 miss, 1 front hit, 2 the back of a one-sided triangle),
    the front hits' rays ``rows (f,)``, whether each sees its triangle's back (its normal is to
    be turned toward the ray, ``flip (f,)``) and whether it sees the front as wound
    (``dot(normal, direction) < 0``: the side that emits, ``emits (f,)``).
    """
    k = prim.shape[0]
    kind = np.zeros(k, np.uint8)
    rows = np.empty(k, np.int64)
    flip = np.empty(k, np.bool_)
    emits = np.empty(k, np.bool_)
    f = 0
    for i in range(k):
        t = prim[i]
        if t < 0:
            continue
        side, d = _hit_side(tri_normals, t, directions[i, 0], directions[i, 1],
                            directions[i, 2], double_sided)
        kind[i] = side
        if side == 2:
            continue
        rows[f] = i
        flip[f] = d > 0
        emits[f] = d < 0
        f += 1
    return kind, rows[:f], flip[:f], emits[:f]


@numba.njit(**_JIT)
def shade_hits(
    directions: NDArray[np.float64],
    prim: NDArray[np.int64],
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    t_hit: NDArray[np.float64],
    max_distance: float,
    eps: float,
    vertices: NDArray[np.float64],
    triangles: NDArray[np.int64],
    tri_normals: NDArray[np.float64],
    material: NDArray[np.int64],
    base_color: NDArray[np.float64],
    emissive: NDArray[np.float64],
    colors: NDArray[np.float64],
    double_sided: NDArray[np.bool_],
    kind: NDArray[np.uint8],
    distance: NDArray[np.float64],
    position: NDArray[np.float64],
    normal: NDArray[np.float32],
    albedo: NDArray[np.float32],
    emission: NDArray[np.float32],
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """:func:`split_hits` and :func:`hit_surfaces` of a chunk of rays in one pass, written into
    its records: ``kind (k,)``; ``distance (k,)`` the hit distance (``max_distance`` for a miss,
    at most ``max_distance``); and for each front hit its ``position``, its ``normal`` turned
    toward the ray, its ``albedo`` (without textures) and its ``emission`` (0 unless the ray
    sees the front as wound, the side that emits). Rows of misses and back hits are left as
    they are (the records start as zeros).

    Returns the front hits' rays ``rows (f,)`` and, for the light sampled at them, their
    positions and turned normals ``(f, 3)`` float64 and the points ``eps`` back along the ray
    from the hit ``(f, 3)`` (a hit exactly on an edge of a closed room would see the adjacent
    wall edge-on)."""
    k = prim.shape[0]
    rows = np.empty(k, np.int64)
    pts = np.empty((k, 3))
    nrm = np.empty((k, 3))
    back = np.empty((k, 3))
    has_colors = colors.shape[0] > 0
    f = 0
    for i in range(k):
        t = prim[i]
        if t < 0:
            kind[i] = 0
            distance[i] = max_distance
            continue
        distance[i] = min(t_hit[i], max_distance)
        side, d = _hit_side(tri_normals, t, directions[i, 0], directions[i, 1],
                            directions[i, 2], double_sided)
        kind[i] = side
        if side == 2:
            continue
        rows[f] = i
        sign = -1.0 if d > 0 else 1.0
        w1, w2 = u[i], v[i]
        w0 = 1.0 - w1 - w2
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        m = material[t]
        for j in range(3):
            pj = _barycentric(vertices, a, b, c, w0, w1, w2, j)
            nj = sign * tri_normals[t, j]
            pts[f, j] = pj
            nrm[f, j] = nj
            back[f, j] = pj - eps * directions[i, j]
            position[i, j] = pj
            normal[i, j] = nj
            al = base_color[m, j]
            if has_colors:
                al *= _barycentric(colors, a, b, c, w0, w1, w2, j)
            albedo[i, j] = al
            emission[i, j] = emissive[m, j] if d < 0 else 0.0
        f += 1
    return rows[:f], pts[:f], nrm[:f], back[:f]


@numba.njit(**_JIT)
def scatter_divided(out: NDArray[np.float32], rows: NDArray[np.int64],
                    values: NDArray[np.float64], divisor: float, add: bool) -> None:
    """``out[rows] = values / divisor`` (``+=`` when ``add``), ``values (len(rows), 3)``, the
    quotient in float64 rounded once to ``out``'s type."""
    for j in range(rows.shape[0]):
        i = rows[j]
        for c in range(3):
            x = values[j, c] / divisor
            if add:
                out[i, c] += x
            else:
                out[i, c] = x


#: SplitMix64's increment (the golden ratio in 64 bits) and its output mix's multipliers
#: (Steele, Lea and Flood, "Fast splittable pseudorandom number generators", OOPSLA 2014).
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)


@numba.njit(**_JIT)
def _splitmix(z: np.uint64) -> np.uint64:
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    return z ^ (z >> np.uint64(31))


@numba.njit(**_JIT)
def stream_uniforms(keys: NDArray[np.uint64], per_key: int, rows: NDArray[np.int64],
                    width: int) -> NDArray[np.float64]:
    """Uniform numbers in [0, 1) of counter-based streams, for the given rows only.

    Row ``r`` belongs to stream ``keys[r // per_key]`` (a probe's stream of one purpose) as its
    row ``j = r % per_key``; its ``width`` numbers are SplitMix64's outputs number
    ``j width .. j width + width - 1`` of that stream (state ``key + (c + 1) golden``, the
    output mix, the top 53 bits over ``2^53``). A number depends only on its key and counter,
    never on which other rows are drawn: a batch draws what its rays use and nothing else.
    Returns ``(len(rows), width)``.
    """
    out = np.empty((rows.shape[0], width))
    scale = 1.0 / 9007199254740992.0  # 2^-53
    q, lo = -1, 0
    key = np.uint64(0)
    for i in range(rows.shape[0]):
        r = rows[i]
        if not (q >= 0 and lo <= r < lo + per_key):  # (rows mostly come in order)
            q = r // per_key
            lo = q * per_key
            key = keys[q]
        base = np.uint64((r - lo) * width)
        for d in range(width):
            z = _splitmix(key + (base + np.uint64(d + 1)) * _GOLDEN)
            out[i, d] = np.int64(z >> np.uint64(11)) * scale
    return out


@numba.njit(**_JIT)
def mean_per_parent(parent: NDArray[np.int64], radiance: NDArray[np.float32], parents: int
                    ) -> NDArray[np.float32]:
    """The mean of ``radiance (k, 3)`` over the rows of each of ``parents`` parents
    (``parent (k,)`` each row's parent), summed in float64 in row order; 0 for a parent with
    no row. Returns ``(parents, 3)`` float32."""
    total = np.zeros((parents, 3))
    count = np.zeros(parents)
    for i in range(parent.shape[0]):
        p = parent[i]
        count[p] += 1.0
        total[p, 0] += radiance[i, 0]
        total[p, 1] += radiance[i, 1]
        total[p, 2] += radiance[i, 2]
    out = np.zeros((parents, 3), np.float32)
    for p in range(parents):
        if count[p] > 0:
            out[p, 0] = total[p, 0] / count[p]
            out[p, 1] = total[p, 1] / count[p]
            out[p, 2] = total[p, 2] / count[p]
    return out
