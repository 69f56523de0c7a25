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

Radiance is linear Rec.709 RGB in the scene's photometric units (cd/m^2).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core.cubemap import check_cube
from probegrid.core.sampling import CubeSampler, resample
from probegrid.core.sh import rotation_y

__all__ = ["Environment"]


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
