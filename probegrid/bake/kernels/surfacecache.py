"""The surface light cache's lookup: light stored on a lattice over each triangle, read at hits.

:func:`cache_lookup` interpolates, at ray hits given as a triangle and Embree's barycentrics
``(u, v)`` (the hit ``(1 - u - v) a + u b + v c``), the values stored at the vertices of a
regular barycentric lattice over the triangle (Yuksel et al., "Mesh colors", ACM TOG 29(2),
2010): triangle ``t`` of resolution ``r`` holds ``(r + 1)(r + 2) / 2`` vertices
``(i / r, j / r)``, ``i + j <= r``, row ``j`` after row ``j - 1`` (vertex ``(i, j)`` at
``j (r + 1) - j (j - 1) / 2 + i``; resolution 0: one vertex, the centroid, read
everywhere on the triangle), from its side's offset (the front; a double-sided
triangle's back from its own offset). A hit inside a lattice cell reads the cell's three
vertices linearly (the lower cell ``(i, j), (i + 1, j), (i, j + 1)`` or the upper
``(i + 1, j + 1), (i, j + 1), (i + 1, j)``): exact for light linear over the triangle.
:mod:`probegrid.bake.surfacecache` owns the layout and the reference (numpy) expression.
Floating point: :mod:`probegrid._jit`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import kernel

__all__ = ["cache_lookup"]


@kernel
def _vertex(r: int, i: int, j: int) -> int:
    """The row of lattice vertex ``(i, j)`` of a resolution-``r`` triangle."""
    return j * (r + 1) - (j * (j - 1)) // 2 + i


@kernel
def cache_lookup(prim: NDArray[np.int64], u: NDArray[np.float64], v: NDArray[np.float64],
                 directions: NDArray[np.float64], tri_normals: NDArray[np.float64],
                 lattice: NDArray[np.int64], values: NDArray[np.float32]
                 ) -> NDArray[np.float32]:
    """The cache's ``values (V, C)`` at hits ``prim (k,)`` (-1: a miss, 0 out), ``u, v (k,)``
    of rays along ``directions (k, 3)``: ``lattice (T, 3)`` holds per triangle its front's
    offset, its back's (-1: one-sided, 0 out) and its resolution; the side is the one the
    ray sees (``dot(normal as wound, direction) > 0``: the back). Returns ``(k, C)``."""
    k = prim.shape[0]
    c = values.shape[1]
    out = np.zeros((k, c), np.float32)
    for q in range(k):
        t = prim[q]
        if t < 0:
            continue
        d = (tri_normals[t, 0] * directions[q, 0] + tri_normals[t, 1] * directions[q, 1]
             + tri_normals[t, 2] * directions[q, 2])
        base = lattice[t, 1] if d > 0 else lattice[t, 0]
        if base < 0:
            continue
        r = lattice[t, 2]
        if r == 0:  # the centroid's value alone
            for ch in range(c):
                out[q, ch] = max(values[base, ch], 0.0)
            continue
        a = min(max(u[q], 0.0), 1.0) * r
        b = min(max(v[q], 0.0), 1.0) * r
        i = min(int(np.floor(a)), r - 1)
        j = min(int(np.floor(b)), r - 1)
        fa = a - i
        fb = b - j
        if i + j > r - 1:  # past the hypotenuse (rounding): the cell below it
            i = r - 1 - j
            fa = a - i
        if fa + fb <= 1.0 or i + j == r - 1:
            w0 = 1.0 - fa - fb
            v0 = _vertex(r, i, j)
            v1 = _vertex(r, i + 1, j)
            v2 = _vertex(r, i, j + 1)
            w1, w2 = fa, fb
        else:
            w0 = fa + fb - 1.0
            v0 = _vertex(r, i + 1, j + 1)
            v1 = _vertex(r, i, j + 1)
            v2 = _vertex(r, i + 1, j)
            w1, w2 = 1.0 - fa, 1.0 - fb
        for ch in range(c):
            x = (w0 * values[base + v0, ch] + w1 * values[base + v1, ch]
                 + w2 * values[base + v2, ch])
            out[q, ch] = max(x, 0.0)
    return out
