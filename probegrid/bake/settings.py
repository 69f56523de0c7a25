"""The bake's settings: everything that decides the bits of a store (stored in its manifest).

One pydantic model, :class:`BakeSettings`, with each option's default and bounds written once; the
CLI's ``probegrid bake`` options are generated from it and parse straight into it. It is the one
settings object of a bake: the stages, the record tracer and the replay read it.

What a bake derives from the size of its scene and grid rather than from an option -- how far
rays start off a surface and the distance a miss stands for -- is a :class:`TraceGeometry`,
computed once per bake by :meth:`BakeSettings.trace_geometry`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from probegrid._types import MapDType
from probegrid.bake.precision import map_dtype
from probegrid.core.cubemap import mip_sizes
from probegrid.core.lobes import level_roughness
from probegrid.store.manifest import ArraySpec

if TYPE_CHECKING:
    from probegrid.core.grid import GridSpec
    from probegrid.scene import Scene

__all__ = ["BakeSettings", "TraceGeometry", "store_arrays", "store_bytes"]


@dataclass(frozen=True)
class TraceGeometry:
    """The lengths of a bake's rays, from the extent of its scene and grid
    (:meth:`BakeSettings.trace_geometry`): not options, but what the options mean in that scene.

    Attributes
    ----------
    ray_offset : float
        Distance rays start off a surface (shadow, gather and emitter rays, metres).
    max_distance : float
        Distance recorded for misses in the visibility moments.
    """

    ray_offset: float = 1e-4
    max_distance: float = 1e3

    def __post_init__(self) -> None:
        if not (self.ray_offset > 0 and np.isfinite(self.ray_offset)):
            raise ValueError(f"ray_offset must be > 0, got {self.ray_offset}")
        if not (self.max_distance > 0 and np.isfinite(self.max_distance)):
            raise ValueError(f"max_distance must be > 0, got {self.max_distance}")


class BakeSettings(BaseModel):
    """Everything that decides the bits of a bake (stored in the manifest, checked on resume)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    face_size: int = Field(default=32, ge=2, le=512)
    samples: int = Field(default=1, ge=1, le=1024)
    seed: int = Field(default=0, ge=0)
    bounces: int | Literal["converge"] = Field(default="converge", union_mode="left_to_right")
    tolerance: float = Field(default=1e-3, gt=0, lt=1)
    max_bounces: int = Field(default=32, ge=1, le=256)
    light_samples: int = Field(default=2, ge=1, le=64)
    gather_samples: int = Field(default=2, ge=0, le=64)
    gather_depth: int = Field(default=2, ge=1, le=3)
    diffuse_size: int = Field(default=8, ge=1, le=128)
    specular_levels: int | None = Field(default=None, ge=1, le=10)
    moments_size: int = Field(default=8, ge=1, le=64)
    direct: bool = True
    store_incoming: bool = False
    invalid_threshold: float = Field(default=0.25, gt=0, le=1)
    enclosure: float = Field(default=0.5, ge=0, le=4)
    relocate: bool = True
    relocate_fraction: float = Field(default=0.45, ge=0, lt=0.5)
    ray_offset: float | None = Field(default=None, gt=0)
    batch_size: int = Field(default=8, ge=1, le=4096)
    dtype: MapDType = "float"  # map arrays as float32 or float16 (probegrid.bake.precision)
    # the SH field /sh interpolates (probegrid.bake.shfield): lattice steps per probe cell
    # (0: none) and the face size its points are traced at
    sh_field: float = Field(default=2.0, ge=0, le=4)
    sh_field_face_size: int = Field(default=8, ge=2, le=64)
    # rays per texel of the final view that reads the surface cache at its hits
    # (probegrid.bake.finalgather; 0: the probes keep the final pass's own view)
    final_gather: int = Field(default=0, ge=0, le=64)
    # the surface light cache's lattice spacing, scene units (probegrid.bake.surfacecache;
    # None: from the scene's surface, 0: no cache); never from the grid
    surface_cache_spacing: float | None = Field(default=None, ge=0, allow_inf_nan=False)

    @field_validator("bounces", mode="before")
    @classmethod
    def _bounces(cls, v: object) -> object:
        """An int 0..64, or "converge" (iterate until the estimated limit of the grid's energy
        changes by less than ``tolerance``, at most ``max_bounces``; probegrid.bake.converge); a
        numeric string is an int (from the CLI)."""
        if isinstance(v, str) and v.strip().lstrip("+").isdigit():
            v = int(v)
        if isinstance(v, bool) or (isinstance(v, int) and not 0 <= v <= 64):
            raise ValueError(f"bounces must be 0..64 or 'converge', got {v!r}")
        return v

    def gather_levels(self) -> int:
        """Gather levels the bake traces: ``gather_depth`` (0 without gather rays), at most the
        fixed bounce count (a level deeper than the bounces would carry no light)."""
        if self.gather_samples == 0:
            return 0
        return self.gather_depth if self.bounces == "converge" else min(self.gather_depth,
                                                                        int(self.bounces))

    def levels(self) -> int:
        """Specular mip levels (the full chain of ``face_size`` by default)."""
        return len(mip_sizes(self.face_size, self.specular_levels))

    @property
    def moments_face_size(self) -> int:
        """Face size of the stored visibility-moments cube: ``moments_size``, at most
        ``face_size``."""
        return min(self.moments_size, self.face_size)

    @property
    def environment_footprint(self) -> int:
        """Face size of the environment cube misses read (box-filtered to it,
        :meth:`probegrid.bake.environment.Environment.sampler`): the incoming cube's, whatever the
        samples per texel. A texel holds the mean radiance over its solid angle, and each of its
        rays that misses reads the environment at the texel's centre, where the cube holds the
        environment's mean over the texel, wherever in the texel the ray went: the texel mean
        keeps the environment's energy (measured on venice_sunset at 32^2: sunward irradiance
        exact, worst texel 1.1 %; a finer footprint of 64^2 with 4 samples: 3.3 %); more samples
        still resolve the edges of geometry inside the texel."""
        return self.face_size

    def trace_geometry(self, scene: Scene, grid: GridSpec) -> TraceGeometry:
        """The ray lengths of a bake of ``scene`` over ``grid``: ``ray_offset`` (the setting, else
        1e-5 of the extent of the scene and grid together) and twice that extent for misses.

        Raises ValueError when the moments cube cannot be traced: each of its texels bins whole
        texels of the incoming cube, so :attr:`moments_face_size` must divide ``face_size``.
        """
        m = self.moments_face_size
        if self.face_size % m:
            raise ValueError(f"moments_size {m} must divide face_size {self.face_size}")
        extent = float(np.linalg.norm(np.ptp(np.vstack([scene.bounds, grid.lo, grid.hi]), axis=0)))
        return TraceGeometry(ray_offset=self.ray_offset or max(extent, 1e-6) * 1e-5,
                             max_distance=max(extent, 1e-6) * 2.0)


def store_arrays(settings: BakeSettings) -> dict[str, ArraySpec]:
    """The arrays of a store baked with ``settings`` (name -> per-probe shape and dtype)."""
    n, d = settings.face_size, settings.diffuse_size
    m = settings.moments_face_size
    levels = settings.levels()
    md = map_dtype(settings.dtype)  # float32, or float16 with --dtype half
    arrays = {
        "sh": ArraySpec((9, 3), "float32", "radiance SH coefficients L_lm, index l(l+1)+m, RGB"),
        "diffuse": ArraySpec((6, d, d, 3), md, "diffuse cube: irradiance / pi"),
        "valid": ArraySpec((), "bool", "probe is not inside geometry"),
        "positions": ArraySpec((3,), "float64", "probe position (moved if relocated), world"),
        "moments": ArraySpec((6, m, m, 2), "float32",
                             "mean distance and mean squared distance per direction"),
        "backface_fraction": ArraySpec((), "float32", "fraction of rays hitting backfaces"),
        "sh_min": ArraySpec((3,), "float32", "minimum over the sphere of SH irradiance / pi"),
    }
    for k in range(levels):
        s = n >> k
        r = float(level_roughness(k, levels))
        arrays[f"specular_{k}"] = ArraySpec(
            (6, s, s, 3), md, f"GGX prefiltered radiance, roughness {r:.4g}"
        )
    if settings.store_incoming:
        arrays["incoming"] = ArraySpec((6, n, n, 3), md, "incoming radiance cube")
    return arrays


def store_bytes(settings: BakeSettings, n_probes: int, dtype: str | None = None) -> int:
    """Bytes of the store's arrays for ``n_probes`` probes (with ``dtype``, ``"float"`` or
    ``"half"``, instead of the settings')."""
    if dtype is not None:
        settings = settings.model_copy(update={"dtype": dtype})
    return sum(int(np.prod(spec.shape, dtype=np.int64)) * np.dtype(spec.dtype).itemsize
               for spec in store_arrays(settings).values()) * n_probes
