"""The bake's kernels at ray hits: the backface rule and the records pass.

* :func:`split_hits` -- the backface rule (:func:`_hit_side`): misses, front hits and the backs
  of one-sided triangles, which find black;
* :func:`shade_hits` -- :func:`split_hits` and :func:`probegrid.scene.kernels.hit_surfaces` in
  one pass into a chunk's records (:class:`HitRecords`), with the points the light is sampled
  at;
* :func:`scatter_divided` -- a chunk's irradiance divided by pi into its records' rows.

``tests/test_bake_kernels.py`` compares them with the kernels and expressions they fuse.
Floating point: :mod:`probegrid._jit`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import kernel
from probegrid.raytrace.rays import Hits
from probegrid.scene.kernels import SurfaceTables, _barycentric

__all__ = ["HitRecords", "scatter_divided", "shade_hits", "split_hits"]


class HitRecords(NamedTuple):
    """The per-ray records :func:`shade_hits` fills (``k`` rays)."""

    #: (k,) uint8: 0 miss, 1 front hit, 2 the back of a one-sided triangle.
    kind: NDArray[np.uint8]
    #: (k,) float64 hit distance.
    distance: NDArray[np.float64]
    #: (k, 3) position of each front hit.
    position: NDArray[np.float64]
    #: (k, 3) float32 normal turned toward the ray.
    normal: NDArray[np.float32]
    #: (k, 3) float32 albedo, without textures.
    albedo: NDArray[np.float32]
    #: (k, 3) float32 emission toward the ray.
    emission: NDArray[np.float32]


@kernel
def _hit_side(tri_normals: NDArray[np.float64], t: int, dx: float, dy: float, dz: float,
              double_sided: NDArray[np.bool_]) -> tuple[int, float]:
    """The backface rule for a ray along ``d`` that hits triangle ``t``: kind 1 (front, or the
    back of a double-sided triangle) or 2 (the back of a one-sided triangle: black), and
    ``dot(normal as wound, d)`` (> 0: it sees the back, whose normal is turned toward it;
    < 0: it sees the front, the side that emits)."""
    d = tri_normals[t, 0] * dx + tri_normals[t, 1] * dy + tri_normals[t, 2] * dz
    return (2 if d > 0 and not double_sided[t] else 1), d


@kernel
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


@kernel
def shade_hits(
    directions: NDArray[np.float64],
    hits: Hits,
    limits: tuple[float, float],
    surfaces: SurfaceTables,
    double_sided: NDArray[np.bool_],
    records: HitRecords,
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """:func:`split_hits` and :func:`probegrid.scene.kernels.hit_surfaces` of a chunk of rays
    (``directions (k, 3)``, the tracer's ``hits``) in one pass, written into its ``records``
    (:class:`HitRecords`): ``kind (k,)``; ``distance (k,)`` the hit distance (``max_distance``
    for a miss, at most ``max_distance``; ``limits = (max_distance, eps)``); and for each front
    hit its ``position``, its ``normal`` turned toward the ray, its ``albedo`` (without
    textures) and its ``emission`` (0 unless the ray sees the front as wound, the side that
    emits). ``surfaces`` is the scene's, ``double_sided (T,)`` whose backs reflect too.
    Rows of misses and back hits are left as they are (the records start as zeros).

    Returns the front hits' rays ``rows (f,)`` and, for the light sampled at them, their
    positions and turned normals ``(f, 3)`` float64 and the points ``eps`` back along the ray
    from the hit ``(f, 3)`` (a hit exactly on an edge of a closed room would see the adjacent
    wall edge-on)."""
    prim, t_hit, u, v = hits
    max_distance, eps = limits
    vertices, triangles, tri_normals, material, base_color, emissive, colors = surfaces
    kind, distance, position, normal, albedo, emission = records
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


@kernel
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
