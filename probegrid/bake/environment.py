"""The distant environment a bake's missed rays see: an HDR cube or a constant colour.

A ray that leaves the scene returns ``intensity * Env[R_y(-rotation) d]``: the environment is
rotated by ``rotation`` radians about +Y with the right-hand rule (a positive quarter turn
moves what the image shows toward +Z to +X), then scaled. A constant environment returns its
colour in every direction; the default environment is black.

A ray stands for the solid angle of its texel, so :meth:`Environment.sampler` can look the cube
up *prefiltered to that footprint*: the cube box-filtered over solid angle
(:func:`probegrid.core.sampling.resample`) to the face size whose texels match the rays', then sampled
bilinearly. A point lookup in a 256^2 sky from 32^2-texel rays would
see a sun smaller than a texel in full or not at all (measured on venice_sunset at 32^2, one ray
per texel: -12 % of the sunward irradiance, 15 % worst texel; prefiltered: 0.2 %).

The environment as a light (:class:`EnvironmentLight`)
-----------------------------------------------------
Surface points are lit by the environment through explicit sampling, as they are by the
emitters: directions are drawn from the environment itself (a texel of its
:data:`LIGHT_SIZE`-face box-filtered cube picked in proportion to ``luminance * solid angle``
through an alias table (:func:`probegrid.bake.kernels.sampling.alias_table`),
a uniform point in that texel's face square), each tested by a shadow ray, and

    E = (1 / L) sum_i L_i max(0, n . w_i) V_i / p(w_i),

with ``p(w) = P_texel (m^2 / 4) (1 + u^2 + v^2)^(3/2)`` the density over solid angle of a point
uniform on the texel's ``(2/m)^2`` square of the face plane. A direction drawn below the
point's horizon is mirrored in its tangent plane (:meth:`EnvironmentLight.sample_above`), so
that every sample can light the point: the density of a folded direction is
``p(w) + p(mirror of w)`` (a mirror keeps solid angle). Half of the sample room's draws fell
below the horizon and were lost before. The estimator is unbiased for the
piecewise-constant environment and non-negative; a sun falls on its few texels, so a hit in the
sun or in a shadow is found with the first samples. The light a window lets into a room then
depends on where each hit is, not on the probes it would otherwise be read from (a sun patch on
a floor, interpolated between probes that stand in and out of it, made the sample room's
sky-lit probes 1.56x too bright).

Radiance is linear Rec.709 RGB in the scene's photometric units (cd/m^2).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.bake.kernels.cube import CUBE_AXES
from probegrid.bake.kernels.environment import SkyTable, environment_samples
from probegrid.bake.kernels.lights import sum_unblocked
from probegrid.bake.kernels.sampling import alias_draw, alias_table
from probegrid.core.color import luminance
from probegrid.core.cubemap import (
    FACE_NORMALS,
    FACE_U,
    FACE_V,
    check_cube,
    direction_to_face_uv,
    texel_permutation,
    texel_solid_angles,
)
from probegrid.core.sampling import CubeSampler, resample
from probegrid.core.sh import rotation_y
from probegrid.raytrace import EmbreeRays, RayTracer

__all__ = ["LIGHT_SIZE", "Environment", "EnvironmentLight"]

#: Face size of the box-filtered environment cube that hits sample as a light (at most).
LIGHT_SIZE = 64


@dataclass(frozen=True, eq=False)
class Environment:
    """Radiance arriving from infinitely far away.

    Attributes
    ----------
    faces : (6, n, n, 3) float32 or None
        A cube map (see :mod:`probegrid.core.cubemap`), or None for a constant colour.
    color : (3,) float64
        The constant radiance when ``faces`` is None (default black).
    intensity : float
        Multiplies the radiance.
    rotation : float
        Radians about +Y (right-handed).
    """

    faces: NDArray[np.float32] | None = None
    color: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    intensity: float = 1.0
    rotation: float = 0.0

    def __post_init__(self) -> None:
        if self.faces is not None:
            f = check_cube(self.faces, name="environment")
            if f.shape[3] != 3:
                raise ValueError(f"an environment cube needs 3 channels, got {f.shape[3]}")
            if not np.isfinite(f).all():
                raise ValueError("the environment has non-finite texels")
            object.__setattr__(self, "faces", f)
        c = np.broadcast_to(np.asarray(self.color, dtype=np.float64), (3,)).copy()
        if not np.isfinite(c).all() or (c < 0).any():
            raise ValueError(f"environment colour must be 3 finite values >= 0, got {self.color!r}")
        object.__setattr__(self, "color", c)
        if not np.isfinite(self.intensity) or self.intensity < 0:
            raise ValueError(f"environment intensity must be finite and >= 0, got {self.intensity}")
        if not np.isfinite(self.rotation):
            raise ValueError(f"environment rotation must be finite, got {self.rotation}")

    @property
    def is_black(self) -> bool:
        return self.intensity == 0 or (self.faces is None and not self.color.any())

    def sampler(self, footprint: int | None = None) -> _EnvSampler:
        """A fast evaluator (builds the seamless sampler once).

        ``footprint``: face size of a cube whose texels have the solid angle one lookup stands
        for; the environment is box-filtered down to it when it is finer (None: as stored).
        """
        return _EnvSampler(self, footprint)

    def lookup_size(self, footprint: int | None) -> int | None:
        """Face size of the cube :meth:`sampler` samples for ``footprint`` (None: constant)."""
        if self.faces is None:
            return None
        n = int(self.faces.shape[1])
        return n if footprint is None else min(n, int(footprint))

    def describe(self) -> dict[str, object]:
        """JSON-ready description for manifests."""
        if self.faces is None:
            return {"type": "constant", "color": self.color.tolist(), "intensity": self.intensity}
        return {
            "type": "cube",
            "face_size": int(self.faces.shape[1]),
            "intensity": self.intensity,
            "rotation_rad": self.rotation,
        }


class _EnvSampler:
    def __init__(self, env: Environment, footprint: int | None = None) -> None:
        if footprint is not None and (not isinstance(footprint, (int, np.integer))
                                      or footprint < 1):
            raise ValueError(f"footprint must be a positive integer, got {footprint!r}")
        self._env = env
        self._sampler = None
        if env.faces is not None:
            size = env.lookup_size(footprint)
            faces = env.faces if size == env.faces.shape[1] else resample(env.faces, size)
            self._sampler = CubeSampler([faces])
        self._inverse = rotation_y(-env.rotation)

    def radiance(self, directions: ArrayLike) -> NDArray[np.float32]:
        """Radiance for world directions ``(..., 3)``, returns ``(..., 3)`` float32."""
        d = np.asarray(directions, dtype=np.float64)
        env = self._env
        if self._sampler is None:
            out = np.broadcast_to((env.color * env.intensity).astype(np.float32), d.shape)
            return np.array(out)
        if env.rotation:
            d = d @ self._inverse.T
        out = self._sampler.bilinear(d)
        if env.intensity != 1.0:
            out = out * np.float32(env.intensity)
        return out


class EnvironmentLight:
    """The environment sampled as a light at surface points (module docstring).

    ``size``: face size of the piecewise-constant cube sampled (the environment box-filtered
    down to it when finer; a constant colour is a 1-texel cube).
    """

    def __init__(self, env: Environment, size: int = LIGHT_SIZE) -> None:
        if env.faces is None:
            m = 1
            faces = np.broadcast_to(env.color, (6, 1, 1, 3)).astype(np.float64)
        else:
            m = min(int(env.faces.shape[1]), int(size))
            faces = env.faces if m == env.faces.shape[1] else resample(env.faces, m)
            faces = np.asarray(faces, dtype=np.float64)
        radiance = faces.reshape(-1, 3) * float(env.intensity)
        power = np.maximum(luminance(radiance), 0.0) * texel_solid_angles(m).reshape(-1)
        total = float(power.sum())
        self.size = m
        self.radiance = radiance
        self.is_black = not total > 0.0
        prob = power / total if total > 0 else power
        self._prob = prob
        self._accept, self._alias = alias_table(prob)
        # the texels' mirrors in the three coordinate planes of the environment frame (the
        # reflection negating axis a: environment_samples' mirror for normals along it)
        self._mirrors = np.stack([texel_permutation(np.diag([-1.0 if i == a else 1.0
                                                             for i in range(3)]), m)
                                  for a in range(3)])
        # environment frame -> world
        self._rotation = rotation_y(env.rotation) if env.rotation else None
        self._to_world = np.eye(3) if self._rotation is None else self._rotation  # (kernel's)
        self._table = SkyTable(self._accept, self._alias, prob, radiance, m, self._to_world,
                               self._mirrors)

    def sample(self, random: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                            NDArray[np.float64],
                                                            NDArray[np.float64]]:
        """Directions drawn from the environment for uniform ``random (..., 3)`` in [0, 1).

        Returns unit world directions ``(..., 3)``, their radiance ``(..., 3)`` and their
        density over solid angle ``(...)``.
        """
        r = np.asarray(random, dtype=np.float64)
        m = self.size
        t = alias_draw(self._accept, self._alias, r[..., 0])
        face, rest = np.divmod(t, m * m)
        row, col = np.divmod(rest, m)
        u = -1.0 + (col + r[..., 1]) * (2.0 / m)
        v = -1.0 + (row + r[..., 2]) * (2.0 / m)
        d = (FACE_NORMALS[face] + u[..., None] * FACE_U[face] + v[..., None] * FACE_V[face])
        q = 1.0 + u * u + v * v
        d /= np.sqrt(q)[..., None]
        pdf = self._density(t, q ** 1.5)
        if self._rotation is not None:
            d = d @ self._rotation.T
        return d, self.radiance[t], pdf

    def _texels(self, directions: NDArray[np.float64]
                ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """The sampled cube's texels at unit world ``directions (..., 3)`` (flat index) and
        ``(1 + u^2 + v^2)^(3/2)`` there
        (:func:`probegrid.bake.kernels.environment._environment_texel`)."""
        d = np.asarray(directions, dtype=np.float64)
        if self._rotation is not None:
            d = d @ self._rotation  # world -> environment frame
        m = self.size
        face, u, v = direction_to_face_uv(d)
        col = np.clip(((u + 1.0) * 0.5 * m).astype(np.int64), 0, m - 1)
        row = np.clip(((v + 1.0) * 0.5 * m).astype(np.int64), 0, m - 1)
        return (face * m + row) * m + col, (1.0 + u * u + v * v) ** 1.5

    def _density(self, texels: NDArray[np.int64], factor: NDArray[np.float64]
                 ) -> NDArray[np.float64]:
        """:meth:`sample`'s density over solid angle in ``texels`` at points whose
        ``(1 + u^2 + v^2)^(3/2)`` is ``factor``: ``P_texel (m^2 / 4) factor``."""
        return self._prob[texels] * (0.25 * self.size * self.size) * factor

    def sample_above(self, random: NDArray[np.float64], normals: NDArray[np.float64]
                     ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """:meth:`sample`'s directions folded into the upper hemisphere of ``normals (n, 3)``
        (``random (n, L, 3)``): one below the horizon is mirrored in the tangent plane,
        ``w - 2 (n . w) n``. Returns the directions ``(n, L, 3)``, the environment's radiance
        there and their density ``p(w) + p(mirror of w)`` (the mirror keeps solid angle; 0 for a
        direction in the tangent plane, which contributes nothing)."""
        d, rad, pdf = self.sample(random)
        nrm = np.asarray(normals, dtype=np.float64)[:, None, :]
        cos = np.sum(d * nrm, axis=-1, keepdims=True)
        mirror = d - 2.0 * cos * nrm
        t, factor = self._texels(mirror)
        total = pdf + self._density(t, factor)
        below = cos < 0
        up = np.where(below, mirror, d)
        rad = np.where(below, self.radiance[t], rad)
        return up, rad, np.where(cos[..., 0] == 0, 0.0, total)

    def irradiance(self, points: NDArray[np.float64], normals: NDArray[np.float64],
                   random: NDArray[np.float64], tracer: RayTracer, eps: float
                   ) -> tuple[NDArray[np.float64], int]:
        """Direct irradiance (lux, RGB) from the environment at ``points (n, 3)`` with unit
        ``normals (n, 3)``, from ``random (n, L, 3)`` uniform numbers (L samples per point).
        Returns ``(n, 3)`` and the shadow rays cast (:meth:`sample_above` and the estimator in
        one compiled pass, :func:`probegrid.bake.kernels.environment.environment_samples`)."""
        n = len(points)
        out = np.zeros((n, 3))
        if n == 0 or self.is_black:
            return out, 0
        which, org, dirs, lengths, contrib, ok = environment_samples(
            np.asarray(points, dtype=np.float64), np.asarray(normals, dtype=np.float64),
            np.ascontiguousarray(random, np.float64), self._table, CUBE_AXES, float(eps),
            tracer.centre)
        if not which.size:
            return out, 0
        if tracer.tinted:  # through tinted panes: each ray's weights
            through = tracer.shadow_weights(EmbreeRays(org, dirs, lengths), ok)
            return (sum_unblocked(n, which, ~np.any(through > 0, axis=1), contrib * through),
                    len(which))
        blocked = tracer.occluded_rays(EmbreeRays(org, dirs, lengths), ok)
        return sum_unblocked(n, which, blocked, contrib), len(which)
