"""The environment sampled as a light at hits, compiled.

* :func:`environment_samples` -- :class:`probegrid.bake.environment.EnvironmentLight`'s
  ``sample_above`` and the estimator of its ``irradiance`` before the shadow rays, in one pass
  (``tests/test_bake_kernels.py`` compares it with the numpy sampler); the shadow rays' outcomes
  are summed by :func:`probegrid.bake.kernels.lights.sum_unblocked`.

The environment reaches the kernel as one :class:`SkyTable`. Texels are drawn by the alias rule
of :func:`probegrid.bake.kernels.sampling._alias_pick`; shadow rays are written as Embree takes
them (:func:`probegrid.raytrace.kernels._embree_ray`). Floating point: :mod:`probegrid._jit`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import inline_kernel, kernel
from probegrid.bake.kernels.cube import CubeAxes, _face_uv
from probegrid.bake.kernels.sampling import _alias_pick
from probegrid.raytrace.kernels import _embree_ray

__all__ = ["SkyTable", "environment_samples"]


class SkyTable(NamedTuple):
    """A piecewise-constant environment cube as :func:`environment_samples` draws from it."""

    #: (6 size^2,) float64 and int64: the texels' alias table.
    accept: NDArray[np.float64]
    alias: NDArray[np.int64]
    #: (6 size^2,) float64 each texel's probability.
    prob: NDArray[np.float64]
    #: (6 size^2, 3) float64 each texel's radiance.
    radiance: NDArray[np.float64]
    #: The cube's face size.
    size: int
    #: (3, 3) float64 environment frame to world.
    rotation: NDArray[np.float64]
    #: (3, 6 size^2) int64 each texel's mirror in the three coordinate planes
    #: (:func:`probegrid.core.cubemap.texel_permutation`).
    mirrors: NDArray[np.int64]


@inline_kernel
def _rotate(rotation: NDArray[np.float64], x: float, y: float, z: float
            ) -> tuple[float, float, float]:
    """``rotation (3, 3) @ (x, y, z)`` (pass ``rotation.T`` to turn back)."""
    return (rotation[0, 0] * x + rotation[0, 1] * y + rotation[0, 2] * z,
            rotation[1, 0] * x + rotation[1, 1] * y + rotation[1, 2] * z,
            rotation[2, 0] * x + rotation[2, 1] * y + rotation[2, 2] * z)


@kernel
def _environment_texel(dx: float, dy: float, dz: float, m: int, face_u: NDArray[np.float64],
                       face_v: NDArray[np.float64]) -> tuple[int, float]:
    """The texel of an ``m``-cube a unit direction (environment frame) falls in and
    ``(1 + u^2 + v^2)^(3/2)``, its density's texel-to-solid-angle factor."""
    face, u, v = _face_uv(dx, dy, dz, face_u, face_v)
    col = min(max(int((u + 1.0) * 0.5 * m), 0), m - 1)
    row = min(max(int((v + 1.0) * 0.5 * m), 0), m - 1)
    q = 1.0 + u * u + v * v
    return (face * m + row) * m + col, q * math.sqrt(q)


@kernel
def environment_samples(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    random: NDArray[np.float64],
    sky: SkyTable,
    axes: CubeAxes,
    eps: float,
    centre: NDArray[np.float64],
) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.float32], NDArray[np.float32],
           NDArray[np.float64], bool]:
    """Directions drawn from a piecewise-constant environment cube, folded into the upper
    hemisphere of each normal, and their contributions
    (:class:`probegrid.bake.environment.EnvironmentLight`: ``sample_above`` and the estimator
    of ``irradiance`` before the shadow rays).

    The environment is ``sky`` (:class:`SkyTable`), the cube's axes ``axes``
    (:data:`~probegrid.bake.kernels.cube.CUBE_AXES`). A texel ``t`` of the ``size``-cube (flat
    ``(face, row, col)`` order) drawn with probability ``prob[t]`` from ``r0`` through its alias
    table ``(accept, alias)`` (:func:`~probegrid.bake.kernels.sampling.alias_table`), the point
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
    them (float32 ``origins``, ``directions (k, 3)`` and ``lengths (k,)``,
    :func:`probegrid.raytrace.kernels._embree_ray`, re-centred on ``centre``, the tracer's),
    ``contribution (k, 3)`` of the samples that count and whether every ray is finite in
    float32.
    """
    accept, alias, prob, radiance, size, rotation, mirrors = sky
    face_normals, face_u, face_v = axes
    n, ns = random.shape[0], random.shape[1]
    cap = n * ns
    which = np.empty(cap, np.int64)
    org = np.empty((cap, 3), np.float32)
    dirs = np.empty((cap, 3), np.float32)
    far = np.empty(cap, np.float32)
    rays = (org, dirs, far)
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
            if not _embree_ray(rays, k, (points[i, 0], points[i, 1], points[i, 2]),
                               (wx, wy, wz), eps, math.inf, centre):
                ok = False
            contrib[k, 0] = radiance[t, 0] * w
            contrib[k, 1] = radiance[t, 1] * w
            contrib[k, 2] = radiance[t, 2] * w
            k += 1
    return which[:k], org[:k], dirs[:k], far[:k], contrib[:k], ok
