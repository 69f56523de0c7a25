"""Probes traced at any point against a converged grid: what a probe baked there would hold.

Between the probes of a grid, a blend of the 8 surrounding probes' maps is an overlay of views
from 8 places: a mirror level shows a small light up to 8 times, and the diffuse map carries the
light of wherever the probes stand. :class:`PointTracer` instead renders a probe at the query
point with the bake's own estimator -- its texel rays, the direct light sampled at every hit
(punctual lights, the emitters' exact view and samples, the environment), the final gather and,
at the gather's deepest hits, the converged grid read through the surrounding probes'
irradiance cubes (:class:`probegrid.bake.records.RecordTracer`,
:func:`probegrid.bake.records.replay.replay` with ``final=True``) -- and filters its incoming
cube into the diffuse map and the GGX chain with the bake's filter
(:func:`probegrid.core.probefilter.filter_cube`). The parallax of everything the point sees is
then exact; only the light reflected more than ``gather_depth`` times still comes from the grid.

A bake's surface light cache (:mod:`probegrid.bake.surfacecache`) makes the trace cheap: with
it the probe's rays alone are cast, and each hit reads the light reflected at least once (and,
where the lattice is coarser than a mirror texel or with ``direct="cache"``, the emitters' and
the environment's) from the cache instead of gathering it -- a fifth of the shading points.
:data:`POINT_PRESETS` names the choices the service offers (``quality=``); ``"reference"`` keeps
the bake's gather at every hit. The rays are shaded, and the filter's product made, on a shared
pool of two threads (:func:`shared_pool`).

What it needs of a bake is what the final pass read (:mod:`probegrid.bake.extras`: the
environment, the grid's irradiance cubes and the bordered distance moments, stored as extras),
the scene and the bake's settings; :meth:`PointTracer.from_store` builds it from a store that
has them. The grid's arrays stay memory-mapped (a query reads the 8 probes around each hit); a
tracer holds the scene's tables, the emitters' and the environment's (at most ``6 x 64^2``
texels and the probes' face size), and the probes' validity and positions (25 bytes a probe).

A point's random streams are keyed by the bake's seed and the point's coordinates (the same
point gives the same bits), so two nearby points draw independent noise, of the bake's level
at a probe.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._types import TraceQuality, choices
from probegrid.bake.environment import LIGHT_SIZE, Environment
from probegrid.bake.records import (
    GridData,
    RecordTracer,
    all_hit_weights,
    gather_depth,
    grid_level_read,
    hit_weights,
)
from probegrid.bake.records.replay import replay, visible_probe
from probegrid.bake.settings import BakeSettings, TraceGeometry
from probegrid.bake.surfacecache import LATTICE_EXTRA, LIGHT_EXTRA, SurfaceCache
from probegrid.core import probefilter
from probegrid.core.sampling import resample
from probegrid.raytrace import RayTracer
from probegrid.scene import Scene

__all__ = ["ENVIRONMENT_EXTRA", "GRID_EXTRA", "MOMENTS_EXTRA", "POINT_PRESETS", "PointMaps",
           "PointSettings", "PointTracer", "environment_extra", "trace_support"]

#: The store extra holding the environment a bake's rays saw (unrotated, unscaled cube).
ENVIRONMENT_EXTRA = "environment"
#: The store extra holding the grid's irradiance cubes the bake's final pass read (bordered).
GRID_EXTRA = "grid_irradiance"
#: The store extra holding the probes' distance moments with their seamless border.
MOMENTS_EXTRA = "moments_bordered"


def environment_extra(environment: Environment, face_size: int) -> NDArray[np.float32] | None:
    """The environment cube a store keeps for :class:`PointTracer` (None for a constant
    colour, which the manifest describes): the cube box-filtered to the finest size the bake
    reads it at -- the light sampler's (:data:`probegrid.bake.environment.LIGHT_SIZE`) or the
    probes' texels (``face_size``), at most its own -- without rotation and intensity (the
    manifest's ``bake.environment`` states them)."""
    if environment.faces is None:
        return None
    n = int(environment.faces.shape[1])
    size = min(n, max(LIGHT_SIZE, int(face_size)))
    faces = environment.faces if size == n else resample(environment.faces, size)
    return np.ascontiguousarray(faces, dtype=np.float32)


@dataclass(frozen=True)
class PointSettings:
    """How a point is traced: the bake's settings by default (``None`` keeps the bake's).

    Attributes
    ----------
    indirect : "cache", "gather" or None
        Where the light reflected at least once comes from at the rays' hits: read from the
        store's surface cache (:mod:`probegrid.bake.surfacecache`), or gathered there with
        the bake's estimator (gather rays reading the grid); None: the cache when the store
        has one.
    direct : "sample" or "cache"
        The emitters' and the environment's direct light at the hits: sampled with shadow
        rays (sharp shadows in the mirror level), or read from the surface cache too (no
        shadow ray but the punctual lights'; needs the cache). The punctual lights' is always
        exact.
    gather_samples : int or None
        Gather rays per front hit (at least 1 for a bake with gather rays: its grid's cubes
        are of the size gather hits read), when gathering.
    gather_depth : int or None
        Gather levels (at most the bake's), when gathering.
    light_samples : int or None
        Emitter and environment samples per hit.
    face_size : int or None
        Texel rays per face (the bake's face size by default; lower for SH only, which
        needs about 8).
    """

    indirect: Literal["cache", "gather"] | None = None
    direct: Literal["sample", "cache"] = "sample"
    gather_samples: int | None = None
    gather_depth: int | None = None
    light_samples: int | None = None
    face_size: int | None = None

    @classmethod
    def preset(cls, name: str) -> PointSettings:
        """The settings of a preset of :data:`POINT_PRESETS`."""
        if name not in POINT_PRESETS:
            raise ValueError(f"quality must be one of {', '.join(POINT_PRESETS)}, got "
                             f"{name[:32]!r}.")
        return POINT_PRESETS[name]


#: The traced answers a service offers (``/maps?quality=``): ``accurate`` (the surface
#: cache's indirect light, direct light sampled at every hit: the default), ``fast`` (the
#: cache's direct light too; a store without a cache gathers with 1 ray, 1 level and 1 light
#: sample) and ``reference`` (the bake's own estimator: gather rays at every hit, no cache).
POINT_PRESETS: dict[str, PointSettings] = {}


POINT_PRESETS.update(accurate=PointSettings(), fast=PointSettings(direct="cache"),
                     reference=PointSettings(indirect="gather"))
assert tuple(POINT_PRESETS) == choices(TraceQuality)


@dataclass(frozen=True)
class PointMaps:
    """What a probe at a point holds: its incoming cube, diffuse map and GGX chain, and the
    fraction of its rays that met a back face (over the bake's ``invalid_threshold``: the
    point is inside a solid, where no probe would be valid)."""

    incoming: NDArray[np.float32]
    diffuse: NDArray[np.float32]
    specular: tuple[NDArray[np.float32], ...]
    backface_fraction: float = 0.0


def trace_support(manifest: Any, extras: set[str], has_scene: bool) -> str | None:
    """Why a store cannot be traced at points (None: it can): its bake's settings, the
    environment it saw, the grid its final pass read and its scene must all be there."""
    bake = getattr(manifest, "bake", None) or {}
    if "settings" not in bake or "render" not in bake:
        return "the store records no bake settings"
    if not has_scene:
        return "the store keeps no scene file"
    if GRID_EXTRA not in extras or MOMENTS_EXTRA not in extras:
        return "the store keeps no grid irradiance (baked before it was stored)"
    env = bake.get("environment") or {}
    if env.get("type") == "cube" and ENVIRONMENT_EXTRA not in extras:
        return "the store keeps no environment cube"
    if "bounces" not in (getattr(manifest, "quality", None) or {}):
        return "the store records no final bounce level"
    return None


#: Threads a point's rays are shaded on by default: the machine's cores, at most 2 (the
#: service's requests share them).
DEFAULT_THREADS = min(2, os.cpu_count() or 1)
_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def _forget_pools() -> None:
    """A forked child has none of its parent's threads: it starts its own pools."""
    global _POOLS_LOCK
    _POOLS.clear()
    _POOLS_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pools)


def shared_pool(threads: int | None) -> ThreadPoolExecutor | None:
    """The process's pool of ``threads`` threads (None: :data:`DEFAULT_THREADS`) that every
    tracer shades its rays on, or None for one thread."""
    n = DEFAULT_THREADS if threads is None else int(threads)
    if n < 2:
        return None
    with _POOLS_LOCK:
        if n not in _POOLS:
            _POOLS[n] = ThreadPoolExecutor(n, thread_name_prefix="probegrid-point")
        return _POOLS[n]


class PointTracer:
    """Traces probes at arbitrary points of one bake (build once: it owns the BVH and the
    emitters' and environment's tables).

    Parameters
    ----------
    scene, environment
        What the bake traced.
    settings : BakeSettings
        The bake's (face size, samples, seed, light and gather samples, ...), with the gather
        and light samples the queries use.
    geometry : TraceGeometry
        The bake's ray lengths (ray offset, miss distance).
    grid_data : GridData
        The grid the final pass read (bordered moments and irradiance cubes).
    level : int
        The final pass's bounce level.
    diffuse_size, specular_levels : int
        The maps' sizes (the store's).
    cache : SurfaceCache or None
        The store's surface cache: the rays' hits read the light reflected at least once from
        it (None: gathered there, the bake's estimator).
    direct : "sample" or "cache"
        With a cache, whether the hits' emitter and environment light is sampled or read:
        ``"sample"`` samples it at the hits where the lattice is coarser than a texel of the
        probe's mirror level (distance under ``spacing x 2 n / pi``, ``n`` the face size: a
        lattice cell seen larger than a texel's 90 / n degrees) and reads the cache beyond.
    threads : int or None
        Threads the rays are shaded on (:func:`shared_pool`; None: :data:`DEFAULT_THREADS`).
    """

    def __init__(self, scene: Scene, environment: Environment, settings: BakeSettings,
                 geometry: TraceGeometry, grid_data: GridData, *, level: int, diffuse_size: int,
                 specular_levels: int, tracer: RayTracer | None = None,
                 cache: SurfaceCache | None = None, direct: str = "sample",
                 threads: int | None = None) -> None:
        self.settings = settings
        self.level = int(level)
        #: The surface cache the rays' hits read their indirect light from (None: gathered).
        self.cache = cache
        #: Whether the hits read the emitters' and environment's direct light from the cache.
        self.direct_cached = cache is not None and direct == "cache"
        self.records = RecordTracer(scene, environment, settings, geometry, tracer=tracer)
        self.records.pool = shared_pool(threads)
        if self.direct_cached:  # no emitter or environment sample at the hits
            self.records.light_samples = 0
        elif cache is not None:  # sampled where the lattice is coarser than a texel
            self.records.sample_where = self.samples_direct
        # the hits' probes tested for visibility by the scene's tracer, as the bake tests them
        self.data = dataclasses.replace(grid_data, tracer=self.records.tracer)
        self.diffuse_size = int(diffuse_size)
        self.specular_levels = int(specular_levels)
        n = settings.face_size
        self._matrix: Any = None
        self._dense = probefilter.supported(n, self.diffuse_size)

    @classmethod
    def from_store(cls, store: Any, scene: Scene, *, tracer: RayTracer | None = None,
                   settings: PointSettings | None = None, threads: int | None = None
                   ) -> PointTracer:
        """The tracer of a store's bake (:func:`trace_support` must say it can) and ``scene``,
        the scene it baked; ``settings`` may lower the bake's gather and light samples."""
        why = trace_support(store.manifest, set(store.manifest.extras), True)
        if why is not None:
            raise ValueError(f"store {store.path.name} cannot be traced at points: {why}.")
        bake = store.manifest.bake
        st = bake["settings"]
        rd = bake["render"]
        try:
            baked = BakeSettings.model_validate(st)
        except ValueError:
            raise ValueError(f"store {store.path.name} cannot be traced at points: its bake "
                             "settings are not this version's.") from None
        geometry = TraceGeometry(ray_offset=float(rd["ray_offset"]),
                                 max_distance=float(rd["max_distance"]))
        env_d = bake.get("environment") or {}
        if env_d.get("type") == "cube":
            env = Environment(faces=np.asarray(store.arrays[ENVIRONMENT_EXTRA], np.float32),
                              intensity=float(env_d.get("intensity", 1.0)),
                              rotation=float(env_d.get("rotation_rad", 0.0)))
        else:
            env = Environment(color=np.asarray(env_d.get("color", (0.0, 0.0, 0.0))),
                              intensity=float(env_d.get("intensity", 1.0)))
        level = int(store.manifest.quality["bounces"])
        ps = settings or PointSettings()
        has_cache = LATTICE_EXTRA in store.manifest.extras and LIGHT_EXTRA in store.manifest.extras
        if ps.indirect == "cache" and not has_cache:
            raise ValueError(f"store {store.path.name} keeps no surface cache (baked before "
                             "it was stored).")
        use_cache = has_cache and ps.indirect != "gather"
        if ps.direct == "cache" and not use_cache:  # a store without a cache: a cheap gather
            ps = PointSettings(indirect="gather", gather_samples=1, gather_depth=1,
                               light_samples=1)
        # the bake's gather levels (BakeSettings.gather_levels): the grid's irradiance cubes
        # are of the size its hits read them at, so a query keeps gather rays if it had them
        depth = baked.gather_levels()
        # the final pass read a grid or none (its stored cubes are zeros)
        reads = grid_level_read(level, depth) >= 0
        gather = baked.gather_samples if ps.gather_samples is None else ps.gather_samples
        if depth and gather < 1:
            raise ValueError("a bake with gather rays is traced with at least 1 gather sample.")
        if depth and ps.gather_depth is not None:
            if not 1 <= ps.gather_depth <= depth:
                raise ValueError(f"gather_depth must be 1..{depth} for this store.")
            depth = ps.gather_depth
        # the bordered grid the final pass read, memory-mapped: what a query reads of it is
        # the 8 probes around each hit, so the service's memory does not grow with the grid
        moments = np.asarray(store.arrays[MOMENTS_EXTRA])
        grid_cubes = np.asarray(store.arrays[GRID_EXTRA])
        data = GridData(store.grid, np.array(store.arrays["valid"], dtype=bool),
                        np.asarray(store.arrays["positions"], dtype=np.float64),
                        moments.reshape(-1, moments.shape[-1]), moments.shape[2] - 2,
                        grid_cubes.reshape(-1, 3) if reads else None)
        # the record tracer reads its light and gather samples from the settings: the bake's,
        # lowered where ``settings`` asks (gather_levels() then gives ``depth``)
        queried = baked.model_copy(update={
            "face_size": baked.face_size if ps.face_size is None else int(ps.face_size),
            "light_samples": (baked.light_samples if ps.light_samples is None
                              else int(ps.light_samples)),
            "gather_samples": gather if depth and not use_cache else 0,
            "gather_depth": max(depth, 1)})
        cache = None
        if use_cache:  # memory-mapped (or in memory) as the store holds it
            cache = SurfaceCache(scene, np.asarray(store.arrays[LATTICE_EXTRA]),
                                 np.asarray(store.arrays[LIGHT_EXTRA]))
        return cls(scene, env, queried, geometry, data, level=level,
                   diffuse_size=baked.diffuse_size, specular_levels=baked.levels(),
                   tracer=tracer, cache=cache, direct=ps.direct, threads=threads)

    def samples_direct(self, prim: NDArray[np.int64], t: NDArray[np.float64]
                       ) -> NDArray[np.bool_]:
        """Which hits (triangles ``prim`` at distances ``t``) sample the emitters' and the
        environment's light (the others read the cache's): those nearer than ``spacing 2 n /
        pi`` (``n`` the face size), where a lattice cell looks larger than a mirror texel."""
        assert self.cache is not None
        return t < self.cache.spacing[prim] * (self.settings.face_size * 2.0 / np.pi)

    @staticmethod
    def point_index(point: NDArray[np.float64]) -> int:
        """The random streams' index of a point: 62 bits of a hash of its coordinates."""
        h = hashlib.sha256(np.ascontiguousarray(point, dtype="<f8").tobytes()).digest()
        return int.from_bytes(h[:8], "little") >> 2

    def incoming(self, points: ArrayLike) -> NDArray[np.float32]:
        """``(B, 6, n, n, 3)`` incoming cubes of probes at ``points (B, 3)``."""
        return self._incoming(points)[0]

    def _incoming(self, points: ArrayLike) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
        """:meth:`incoming` and each point's backface fraction."""
        pos = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if not np.isfinite(pos).all():
            raise ValueError("points must be finite.")
        idx = np.array([self.point_index(p) for p in pos], dtype=np.int64)
        if self.cache is not None:
            return self._incoming_cached(pos, idx)
        rec, _, _ = self.records.trace(pos, idx)
        cubes = None
        if self.level > 0 and self.data.cubes is not None:
            rec = dict(rec)
            # a hit that sees none of its cell's probes reads the probe the point sees
            near = visible_probe(pos, self.data.grid, self.data.valid, self.data.positions,
                                 self.records.tracer)
            rec.update(all_hit_weights(rec, self.data, stand_in=near))
            if gather_depth(rec) and self.level >= 2:
                rec["weight_index"], rec["weight"] = hit_weights(rec, self.data, stand_in=near)
            cubes = self.data.cubes
        back = np.asarray(rec["backface_fraction"], np.float64)
        cube, _ = replay(rec, self.settings, self.level, cubes, final=True, positions=pos)
        return cube, back

    def _incoming_cached(self, pos: NDArray[np.float64], idx: NDArray[np.int64]
                         ) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
        """:meth:`_incoming` with the hits' indirect light (and with ``direct="cache"`` the
        emitters' and environment's) read from the surface cache: the probes' rays only."""
        assert self.cache is not None
        rec, _, _ = self.records.trace(pos, idx, hits=True)
        nrm = np.asarray(rec["normal"], np.float64)
        # the side a ray sees: its normal is turned toward it (against the ray)
        light = self.cache.lookup(rec["primitive"], rec["barycentric"][:, 0],
                                  rec["barycentric"][:, 1], -nrm)
        if self.direct_cached:
            indirect = light[:, 0] + light[:, 1]
        else:  # the cache's direct light where the hit did not sample it (far hits)
            cached = ~np.asarray(rec["sampled"], bool)
            indirect = light[:, 0] + np.where(cached[:, None], light[:, 1], 0.0)
        back = np.asarray(rec["backface_fraction"], np.float64)
        cube, _ = replay(rec, self.settings, self.level, None, final=True,
                         indirect=np.ascontiguousarray(indirect))
        return cube, back

    def maps(self, point: ArrayLike) -> PointMaps:
        """The incoming cube, diffuse map and GGX chain of a probe at one point."""
        cube, back = self._incoming(np.asarray(point, dtype=np.float64).reshape(1, 3))
        return self.filter(cube[0], backface_fraction=float(back[0]))

    def filter(self, cube: NDArray[np.float32], *, backface_fraction: float = 0.0
               ) -> PointMaps:
        """A probe's maps from its incoming cube ``(6, n, n, 3)``, as the bake filters them."""
        from probegrid import usercache
        from probegrid.core import diffuse, specular

        n = self.settings.face_size
        if self._dense:
            if self._matrix is None:
                self._matrix = usercache.probe_filter_matrix(n, self.diffuse_size,
                                                             self.specular_levels)
            d, chain = probefilter.filter_cube(cube, self.diffuse_size, self.specular_levels,
                                               matrix=self._matrix, pool=self.records.pool)
        else:
            d = diffuse.diffuse_exact(cube, self.diffuse_size)
            chain = specular.ggx_prefilter(cube, levels=self.specular_levels)
        return PointMaps(cube, np.asarray(d, np.float32),
                         tuple(np.asarray(c, np.float32) for c in chain), backface_fraction)

