"""The record format of a block of probes: what the trace-once pass keeps of every ray.

A block's records have two forms that share their arrays (converting copies nothing):

* typed: :class:`Records`, the block, with one :class:`Level` per level of rays (the probes'
  own rays, then each gather level), what the tracer fills and the replay reads;
* stored: :data:`RecordArrays`, a flat mapping of named arrays, what crosses process and
  storage boundaries (one ``.npy`` per name in a block's directory,
  :mod:`probegrid.bake.records.storage`; the driver adds and drops arrays by name). A level's
  field ``name`` is stored as ``prefix + name`` with the level's prefix of
  :data:`LEVEL_PREFIXES`; the per-probe arrays under their own names. These names are the
  record files' and are stated here only.

Per ray, a level holds (:class:`Level`): ``kind`` (0 a miss, 1 a front hit, 2 a back hit),
``emission`` (the probes' rays only), ``light_punctual``, ``light_emitters``, ``albedo``,
``position`` and ``normal`` (the probes' rays, and the deepest gather level until its probe
weights are known), ``primary`` (a gather ray's parent row in the level above) and, once
computed, ``weight_index`` and ``weight`` (the 8 probes a hit reads the grid through). What a
gather level keeps is :func:`gather_keys`; :func:`record_bytes` is the bake's estimate of it
all.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "LEVEL_PREFIXES",
    "RECORD_KEYS",
    "Level",
    "RecordArrays",
    "Records",
    "gather_depth",
    "gather_keys",
    "has_hit_weights",
    "record_bytes",
    "select_probes",
    "stored_name",
    "weighted_positions",
]

#: The stored form of a block's records: its arrays by name (the record files' names).
RecordArrays = dict[str, NDArray[Any]]

#: What the probes' own rays keep, per ray.
RECORD_KEYS: Final = ("kind", "emission", "light_punctual", "light_emitters", "albedo",
                      "position", "normal")

#: Name prefix of each level's stored arrays: the probes' rays, then each gather level (the rays
#: of level ``d`` name their parent hit of level ``d - 1`` in ``prefix + "primary"``).
LEVEL_PREFIXES: Final = ("", "gather_", "gather2_", "gather3_")


def gather_keys(*, deepest: bool) -> tuple[str, ...]:
    """What a gather level keeps of its records: no emission (its hits' emission counts 0: the
    emitters reach the hit above by sampling), and positions and normals only at the deepest
    level, whose hits read the grid (the positions until their probe weights are known,
    :func:`weighted_positions`)."""
    keep = ("kind", "light_punctual", "light_emitters", "albedo")
    return keep + ("position", "normal") if deepest else keep


def stored_name(depth: int, field: str) -> str:
    """The stored name of field ``field`` of level ``depth``."""
    return LEVEL_PREFIXES[depth] + field


@dataclass(eq=False)
class Level:
    """One level's per-ray records (``k`` rays); a field the level does not keep is None."""

    #: (k,) uint8: 0 a miss, 1 a front hit, 2 a back hit (black).
    kind: NDArray[np.uint8]
    #: (k, 3) float32 the radiance the surface emits toward the ray (front of an emitter only).
    emission: NDArray[np.float32] | None = None
    #: (k, 3) float32: for a miss the environment's radiance; for a hit the punctual lights'
    #: shadowed irradiance / pi.
    light_punctual: NDArray[np.float32] | None = None
    #: (k, 3) float32 the direct irradiance / pi of the emitters and the environment sampled at
    #: the hit.
    light_emitters: NDArray[np.float32] | None = None
    #: (k, 3) float32.
    albedo: NDArray[np.float32] | None = None
    #: (k, 3) float64 the hit.
    position: NDArray[np.float64] | None = None
    #: (k, 3) float32 the normal turned toward the ray.
    normal: NDArray[np.float32] | None = None
    #: (k,) int32 each gather ray's parent row in the level above.
    primary: NDArray[np.int32] | None = None
    #: (k, 8) int32 and float32: the probes a hit reads the grid through, and their weights.
    weight_index: NDArray[np.int32] | None = None
    weight: NDArray[np.float32] | None = None
    #: (k,) int64 the triangle hit (-1: a miss) and (k, 2) float64 Embree's barycentrics
    #: ``(u, v)`` there: kept only when asked (:meth:`empty` ``hits=True``; a probe traced at a
    #: point reads the surface cache there, :mod:`probegrid.bake.surfacecache`).
    primitive: NDArray[np.int64] | None = None
    barycentric: NDArray[np.float64] | None = None
    #: (k,) bool: whether the hit sampled the emitters and the environment (kept with
    #: ``primitive``; the record tracer's ``sample_where``).
    sampled: NDArray[np.bool_] | None = None

    @classmethod
    def empty(cls, k: int, *, hits: bool = False) -> Level:
        """The records (:data:`RECORD_KEYS`) of ``k`` rays: misses (with ``hits`` their
        ``primitive`` and ``barycentric`` too)."""
        return cls(kind=np.zeros(k, np.uint8),
                   primitive=np.full(k, -1, np.int64) if hits else None,
                   barycentric=np.zeros((k, 2)) if hits else None,
                   sampled=np.zeros(k, bool) if hits else None,
                   emission=np.zeros((k, 3), np.float32),
                   light_punctual=np.zeros((k, 3), np.float32),
                   light_emitters=np.zeros((k, 3), np.float32),
                   albedo=np.zeros((k, 3), np.float32),
                   position=np.zeros((k, 3), np.float64),
                   normal=np.zeros((k, 3), np.float32))

    def fields(self) -> dict[str, NDArray[Any]]:
        """The arrays the level holds, by field name."""
        return {f.name: v for f in dataclasses.fields(self)
                if (v := getattr(self, f.name)) is not None}

    def rows(self, rows: slice | NDArray[np.int64]) -> Level:
        """The level's records of ``rows`` (a slice: views), every array it holds."""
        return Level(**{name: v[rows] for name, v in self.fields().items()})

    def keep(self, names: tuple[str, ...]) -> Level:
        """The level with only the arrays ``names`` (the same arrays)."""
        return Level(**{name: v for name, v in self.fields().items() if name in names})

    @classmethod
    def read(cls, arrays: Mapping[str, NDArray[Any]], depth: int) -> Level:
        """Level ``depth`` of a block's stored arrays."""
        names = [f.name for f in dataclasses.fields(cls)]
        return cls(**{name: arrays.get(stored_name(depth, name)) for name in names})

    def stored(self, depth: int) -> RecordArrays:
        """The level's arrays under their stored names, as level ``depth``."""
        return {stored_name(depth, name): v for name, v in self.fields().items()}


@dataclass(eq=False)
class Records:
    """A block's records: its probes, their levels of rays and their per-probe corrections."""

    #: (B,) int64 the probes' linear indices, ascending.
    probes: NDArray[np.int64]
    #: The rays of each probe (its rays are rows ``j * rays_per_probe ...`` of level 0).
    rays_per_probe: int
    #: Whether the environment is sampled as a light at the hits (then the grid does not carry
    #: what the probes' misses see of it).
    sky_sampled: bool
    #: The probes' rays, then each gather level.
    levels: list[Level]
    #: (B,) float64 the fraction of each probe's rays that hit a back face.
    backface_fraction: NDArray[np.float64]
    #: The probes' direct view of the emitters: texels ``(V,)`` int64 and corrections
    #: ``(V, 3)`` float64, probe ``j``'s at ``view_offsets[j]:view_offsets[j + 1]``.
    view_texel: NDArray[np.int64]
    view_value: NDArray[np.float64]
    view_offsets: NDArray[np.int64]
    #: The punctual lights each probe sees: directions and irradiance ``(L, 3)``, probe ``j``'s
    #: at ``lights_offsets[j]:lights_offsets[j + 1]``.
    lights_direction: NDArray[np.float64]
    lights_irradiance: NDArray[np.float64]
    lights_offsets: NDArray[np.int64]

    @property
    def depth(self) -> int:
        """The gather levels the records hold (0: none)."""
        return len(self.levels) - 1

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, NDArray[Any]]) -> Records:
        """The typed view of a block's stored arrays (no copy)."""
        return cls(
            probes=arrays["probes"], rays_per_probe=int(arrays["rays_per_probe"]),
            sky_sampled=bool(arrays.get("sky_sampled", False)),
            levels=[Level.read(arrays, d) for d in range(gather_depth(arrays) + 1)],
            backface_fraction=arrays["backface_fraction"],
            view_texel=arrays["view_texel"], view_value=arrays["view_value"],
            view_offsets=arrays["view_offsets"], lights_direction=arrays["lights_direction"],
            lights_irradiance=arrays["lights_irradiance"],
            lights_offsets=arrays["lights_offsets"])

    def arrays(self) -> RecordArrays:
        """The stored form (the same arrays)."""
        out: RecordArrays = {}
        for d, level in enumerate(self.levels):
            out.update(level.stored(d))
        out.update(view_texel=self.view_texel, view_value=self.view_value,
                   view_offsets=self.view_offsets, lights_direction=self.lights_direction,
                   lights_irradiance=self.lights_irradiance,
                   lights_offsets=self.lights_offsets,
                   backface_fraction=self.backface_fraction, probes=self.probes,
                   rays_per_probe=np.array(self.rays_per_probe),
                   sky_sampled=np.array(self.sky_sampled))
        return out

    def select(self, probes: NDArray[np.int64]) -> Records | None:
        """The records of ``probes`` (a subset of the block's, in order), or None if absent."""
        have = self.probes
        rows = np.searchsorted(have, probes)
        if np.any(rows >= len(have)) or not np.array_equal(
                have[np.minimum(rows, len(have) - 1)], probes):
            return None
        r = self.rays_per_probe
        kept = (rows[:, None] * r + np.arange(r)[None, :]).reshape(-1)
        levels = [self.levels[0].rows(kept)]
        parents = len(self.levels[0].kind)
        for level in self.levels[1:]:  # each level's rays of kept parents
            assert level.primary is not None
            new_row = np.full(parents, -1, np.int64)
            new_row[kept] = np.arange(len(kept))
            mapped = new_row[level.primary]
            rows_k = np.flatnonzero(mapped >= 0)
            picked = level.keep(tuple(n for n in level.fields() if n != "primary")).rows(rows_k)
            picked.primary = mapped[rows_k].astype(np.int32)
            levels.append(picked)
            kept, parents = rows_k, len(level.kind)
        view_sel, view_offsets = _select_ranges(self.view_offsets, rows)
        lights_sel, lights_offsets = _select_ranges(self.lights_offsets, rows)
        return Records(
            probes=probes, rays_per_probe=r, sky_sampled=self.sky_sampled, levels=levels,
            backface_fraction=self.backface_fraction[rows],
            view_texel=self.view_texel[view_sel], view_value=self.view_value[view_sel],
            view_offsets=view_offsets, lights_direction=self.lights_direction[lights_sel],
            lights_irradiance=self.lights_irradiance[lights_sel], lights_offsets=lights_offsets)


def _select_ranges(offsets: NDArray[np.int64], rows: NDArray[np.int64]
                   ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The entries of probes ``rows`` of a per-probe ragged array (``offsets``) and their new
    offsets."""
    parts = [np.arange(offsets[i], offsets[i + 1]) for i in rows]
    sel = np.concatenate(parts) if parts else np.zeros(0, np.int64)
    counts = np.array([len(p) for p in parts], np.int64)
    return sel, np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)


def gather_depth(arrays: Mapping[str, NDArray[Any]]) -> int:
    """Gather levels a block's stored arrays hold: 0 (none), 1 (``gather_*``), 2 (``gather2_*``
    too) or 3 (``gather3_*`` too)."""
    return sum(1 for d in range(1, len(LEVEL_PREFIXES)) if stored_name(d, "primary") in arrays)


def select_probes(arrays: RecordArrays, probes: NDArray[np.int64]) -> RecordArrays | None:
    """The stored records of ``probes`` (a subset of the block's, in order; the block itself
    when they are all of it), or None if absent (:meth:`Records.select`)."""
    if np.array_equal(arrays["probes"], probes):
        return arrays
    picked = Records.from_arrays(arrays).select(probes)
    return None if picked is None else picked.arrays()


def weighted_positions(arrays: Mapping[str, NDArray[Any]]) -> tuple[str, ...]:
    """The stored positions no pass reads once the hits' probe weights are known: the deepest
    gather level's (the probes' own hits keep theirs: the final view weighs them again)."""
    depth = gather_depth(arrays)
    return (stored_name(depth, "position"),) if depth else ()


def has_hit_weights(arrays: Mapping[str, NDArray[Any]]) -> bool:
    """Whether the hits' probe weights were already added to a block's stored arrays."""
    return stored_name(gather_depth(arrays), "weight_index") in arrays


def record_bytes(primary: int, gather_samples: int, depth: int) -> int:
    """Bytes the records of ``primary`` probe rays take at most (every ray a front hit, every
    gather level full), their probe weights included: the probes' rays keep every
    :data:`RECORD_KEYS` array; each gather level (``gather_samples`` rays per primary ray)
    what :func:`gather_keys` keeps plus its 32-bit parent rows; the level whose hits read the
    grid also its weights (8 int32 probes and 8 float32 weights)."""
    size = {k: v.itemsize * (v.shape[1] if v.ndim > 1 else 1)
            for k, v in Level.empty(1).fields().items()}
    weights = 8 * (4 + 4)
    total = primary * sum(size[k] for k in RECORD_KEYS)
    if depth == 0 or gather_samples == 0:
        return total + primary * weights
    for d in range(1, depth + 1):
        deepest = d == depth
        per_ray = (sum(size[k] for k in gather_keys(deepest=deepest)) + 4
                   + (weights if deepest else 0))
        total += primary * gather_samples * per_ray
    return total
