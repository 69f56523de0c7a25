"""Compiled surface lookups of the scene: a hit's interpolated surface and its textures.

Each kernel restates, step for step, an array expression that stays the reference and the
documentation of the maths (``tests/test_scene_kernels.py`` compares the two on random inputs):

* :func:`hit_surfaces` -- :meth:`probegrid.scene.Scene.surface_at`'s barycentric interpolation
  (without the textures);
* :func:`multiply_texture` -- :func:`probegrid.scene.sample_texture` (bilinear, glTF wrap
  modes) at a hit's texture coordinates, mapped by the texture's
  :class:`~probegrid.scene.textures.TexCoord`.

:func:`_barycentric` (a vertex attribute interpolated over its triangle) is the one scalar step
of both, and of the bake's records pass (:func:`probegrid.bake.kernels.surfaces.shade_hits`).

A scene's arrays reach the kernels as one :class:`SurfaceTables` (``Scene.surface_tables``).
Floating point: the rules of :mod:`probegrid._jit`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import kernel

__all__ = ["SurfaceTables", "hit_surfaces", "multiply_texture"]


class SurfaceTables(NamedTuple):
    """A scene's triangles and material factors as the kernels read them (contiguous)."""

    #: (V, 3) float64 positions.
    vertices: NDArray[np.float64]
    #: (T, 3) int64 vertex indices.
    triangles: NDArray[np.int64]
    #: (T, 3) float64 unit normals as wound.
    tri_normals: NDArray[np.float64]
    #: (T,) int64 material indices.
    material: NDArray[np.int64]
    #: (M, 3) float64 ``baseColorFactor.rgb``.
    base_color: NDArray[np.float64]
    #: (M, 3) float64 ``emissiveFactor`` (times the strength).
    emissive: NDArray[np.float64]
    #: (V, >= 3) float64 ``COLOR_0``, or (0, 3): none.
    colors: NDArray[np.float64]


@kernel
def _barycentric(values: NDArray[np.float64], a: int, b: int, c: int, w0: float, w1: float,
                 w2: float, k: int) -> float:
    """Component ``k`` of ``w0 values[a] + w1 values[b] + w2 values[c]`` (a point's vertex
    attribute, interpolated over its triangle)."""
    return w0 * values[a, k] + w1 * values[b, k] + w2 * values[c, k]


@kernel
def hit_surfaces(
    prim: NDArray[np.int64],
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    surfaces: SurfaceTables,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Position, geometric normal, albedo and emission at barycentric points of triangles.

    :meth:`probegrid.scene.Scene.surface_at` without the textures (applied after, per
    material): ``position = (1 - u - v) a + u b + v c``; ``normal`` the triangle's unit normal
    as wound; ``albedo = baseColorFactor.rgb * COLOR_0.rgb`` (``colors`` interpolated like the
    position; an empty ``colors`` means none); ``emission = emissiveFactor``.

    Parameters
    ----------
    prim : (n,) int64 triangle indices; u, v : (n,) float64 barycentrics
    surfaces : the scene's :class:`SurfaceTables`

    Returns
    -------
    position, normal, albedo, emission : (n, 3) float64
    """
    vertices, triangles, tri_normals, material, base_color, emissive, colors = surfaces
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


@kernel
def _wrap(i: int, n: int, mode: int) -> int:
    """:func:`probegrid.scene.textures._wrap_index` of one index: 0 repeat, 1 clamp,
    2 mirror."""
    if mode == 0:
        return i % n
    if mode == 1:
        return min(max(i, 0), n - 1)
    m = i % (2 * n)
    return m if m < n else 2 * n - 1 - m


@kernel
def multiply_texture(
    target: NDArray[np.float64],
    rows: NDArray[np.int64],
    hits: tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]],
    triangles: NDArray[np.int64],
    uvs: NDArray[np.float64],
    texture: NDArray[np.float32],
    wrap: tuple[int, int],
    xform: NDArray[np.float64],
    first: int,
) -> None:
    """Multiply ``target[rows] (k, C)`` in place by channels ``first`` to ``first + C - 1`` of a
    texture at the hits' UVs (its RGB: ``first`` 0, C 3; its alpha: ``first`` 3, C 1).

    :func:`probegrid.scene.sample_texture` (bilinear, texel centres at ``(col + 0.5) / W``,
    ``(row + 0.5) / H``, wrap modes ``(s, t)`` 0 repeat, 1 clamp, 2 mirror) at the UV
    interpolated with barycentrics ``u[rows], v[rows]`` over triangle ``prim[rows]`` (``hits``
    is ``(prim, u, v)``) and mapped by ``xform`` (the texture's
    :class:`~probegrid.scene.textures.TexCoord` matrix, or empty for none); ``uvs`` empty
    means UV 0.
    """
    prim, u, v = hits
    wrap_s, wrap_t = wrap
    h, w = texture.shape[0], texture.shape[1]
    has_uv = uvs.shape[0] > 0
    mapped = xform.shape[0] == 6
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
        if mapped:
            s, t = (xform[0] * s + xform[1] * t + xform[2],
                    xform[3] * s + xform[4] * t + xform[5])
        x = s * w - 0.5
        y = t * h - 0.5
        x0, y0 = math.floor(x), math.floor(y)
        fx, fy = x - x0, y - y0
        xi, yi = int(x0), int(y0)
        c0, c1 = _wrap(xi, w, wrap_s), _wrap(xi + 1, w, wrap_s)
        r0, r1 = _wrap(yi, h, wrap_t), _wrap(yi + 1, h, wrap_t)
        for k in range(target.shape[1]):
            q = first + k
            top = texture[r0, c0, q] * (1.0 - fx) + texture[r0, c1, q] * fx
            bottom = texture[r1, c0, q] * (1.0 - fx) + texture[r1, c1, q] * fx
            target[i, k] *= top * (1.0 - fy) + bottom * fy
