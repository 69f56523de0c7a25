"""The cube map's conversions, compiled: a direction's face and ``(u, v)``, and a probe's
jittered sample directions of every texel.

* :func:`_face_uv` -- :func:`probegrid.core.cubemap.direction_to_face_uv` of one direction (the
  same tie rules), the lookup of the grid's and the environment's kernels;
* :func:`cube_sample_directions` -- a probe's sample pattern
  (:func:`probegrid.bake.pattern.sample_pattern`, :func:`probegrid.core.cubemap.texel_to_uv`'s
  conversions).

The faces' axes reach every kernel as one :class:`CubeAxes` (:data:`CUBE_AXES`, the arrays of
:mod:`probegrid.core.cubemap`), passed at run time. Floating point: :mod:`probegrid._jit`.
"""

from __future__ import annotations

import math
from typing import Final, NamedTuple

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import kernel
from probegrid.core.cubemap import FACE_NORMALS, FACE_U, FACE_V

__all__ = ["CUBE_AXES", "CubeAxes", "cube_sample_directions"]


class CubeAxes(NamedTuple):
    """The six faces' axes, ``(6, 3)`` float64 each, in face order."""

    #: Each face's outward normal.
    normals: NDArray[np.float64]
    #: Each face's ``u`` axis.
    u: NDArray[np.float64]
    #: Each face's ``v`` axis.
    v: NDArray[np.float64]


#: The faces' axes of :mod:`probegrid.core.cubemap`, as the kernels take them.
CUBE_AXES: Final[CubeAxes] = CubeAxes(FACE_NORMALS, FACE_U, FACE_V)


@kernel
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


@kernel
def cube_sample_directions(
    n: int,
    jitter: NDArray[np.float64],
    axes: CubeAxes,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit directions of jittered samples in every texel of an ``n``-cube, and their weights.

    ``jitter (T, s, 2)`` holds the samples' positions inside their texels, in ``[0, 1)^2``: one
    set for every texel (``T = 1``) or one per texel (``T = 6 n^2``, texel ``(f, row, col)``'s
    at ``(f n + row) n + col``). Sample ``k`` of texel ``(f, row, col)`` sits at continuous
    texel coordinates ``(col - 0.5 + jitter[t, k, 0], row - 0.5 + jitter[t, k, 1])`` (face
    coordinates ``(c + 0.5) 2 / n - 1``, :func:`probegrid.core.cubemap.texel_to_uv`); its
    direction is ``normal + u U + v V`` normalised (``axes``, :data:`CUBE_AXES`) and its weight
    the area element ``|d|^-3``, normalised over the texel's samples.

    Returns
    -------
    directions : (6, n, n, s, 3) float64
    weights : (6, n, n, s) float64
    """
    face_normals, face_u, face_v = axes
    s = jitter.shape[1]
    per_texel = jitter.shape[0] > 1
    d = np.empty((6, n, n, s, 3))
    wt = np.empty((6, n, n, s))
    scale = 2.0 / n
    for f in range(6):
        for row in range(n):
            for col in range(n):
                t = (f * n + row) * n + col if per_texel else 0
                total = 0.0
                for k in range(s):
                    uu = (col - 0.5 + jitter[t, k, 0] + 0.5) * scale - 1.0
                    vv = (row - 0.5 + jitter[t, k, 1] + 0.5) * scale - 1.0
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
