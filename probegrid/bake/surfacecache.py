"""The surface light cache: the light arriving at the scene's surfaces, stored at bake time so
that a probe traced at any point (:class:`probegrid.bake.point.PointTracer`) reads it where its
rays hit instead of gathering it there.

A probe's ray that hits a surface returns ``emission + albedo * (direct + indirect)``, both
irradiance / pi at the hit. The bake computes the indirect part by final gather (cosine rays from
the hit, lit at theirs, one more level below, the converged grid read at the deepest hits:
:mod:`probegrid.bake.records.tracer`); that is four fifths of a traced point's rays and their
shadow rays. It is a smooth function of the point on the surface, the same for every query point,
so the bake stores it once, as Lumen's surface cache (Wright et al., "Lumen: Real-time Global
Illumination in Unreal Engine 5", SIGGRAPH 2022 course) and SEED's surfels (Halen et al.,
"Global Illumination Based on Surfels", SIGGRAPH 2021 course) do at run time: here at the
vertices of a barycentric lattice over each triangle (mesh colors, Yuksel et al. 2010; the
layout and lookup are :func:`probegrid.bake.kernels.surfacecache.cache_lookup`), both sides of a
double-sided triangle. Each vertex holds

* ``indirect``: the light reflected at least once, gathered exactly as the bake gathers it at a
  probe's hit -- :data:`CACHE_GATHER` cosine rays instead of ``gather_samples``, each lit as the
  bake lights gather rays, the same gather levels below, the converged grid read at the deepest
  hits (:func:`bake_surface_cache`; a deepest hit that sees none of its cell's probes reads
  the probe its vertex sees, nothing where it sees none, as a probe's hit reads the probe
  itself); so a query reading it computes the bake's estimator with the hit's gather
  averaged over many more rays and interpolated over the lattice;
* ``direct``: the emitters' and the environment's direct light, :data:`CACHE_LIGHT_SAMPLES`
  samples each, read by a query at the hits where a lattice cell looks smaller than a mirror texel, or
  everywhere (``PointSettings.direct="cache"``); the punctual lights' is always exact at the
  hits (one shadow ray per light).

The lattice's spacing is the same on every triangle (each triangle's resolution is its longest
edge over the spacing rounded down, 0 -- the centroid alone -- to :data:`MAX_RESOLUTION`) and
depends on the scene and the probes' face size, never on the grid (:func:`plan_lattice`): the
bake's ``surface_cache_spacing`` (scene units; 0: no cache), or by default the finest spacing whose
lattice has at most one vertex a triangle side plus :data:`CACHE_TEXEL_VERTICES` per texel of
a probe's face (``8 n^2``: about ``sqrt(A) / 2n`` over a surface of area ``A`` made of
triangles longer than the spacing, a lattice cell seen from across a room about a mirror
texel). So probes added anywhere leave the lattice as it was, and its light changes only as
the grid its deepest gather hits read does (probes added outside the walls: 0.02 % on the
sunlit hall's traced points, ``benchmarks/bench_leaks.py``). Either way at
most :data:`MAX_VERTICES` (48 MB in the store): a finer spacing is coarsened to fit, and a
scene with more triangle sides than that stores no cache (its queries gather). A bake's final
gather (:mod:`probegrid.bake.finalgather`) plans a finer lattice, those vertices per texel and
per ray of its view, and iterates its light on itself (:func:`_iterate`). The manifest
states the spacing, the vertices and why (``quality.surface_cache``). Lattice vertices stand a
hair inside their triangle (:data:`INSET`), so that no gather ray starts on the edge of a
concave corner.

The cache's random numbers are one counter-based stream per purpose
(:func:`probegrid.bake.kernels.sampling.stream_uniforms`) keyed by the bake's seed and
:data:`CACHE_STREAM`, a row per vertex and ray: a bake's cache is the same bits whatever its
chunks, which are shaded on :data:`THREADS` threads (the cache runs in the bake's own process
after the probes' passes, which had every core).
"""

from __future__ import annotations

import dataclasses
import math
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import frozen
from probegrid.bake.environment import Environment
from probegrid.bake.kernels.grid import mean_per_parent
from probegrid.bake.kernels.surfacecache import cache_lookup
from probegrid.bake.records.replay import (
    GridData,
    _level_weights,
    _replay_level,
    irradiance_size,
    visible_probe,
)
from probegrid.bake.records.schema import Level, gather_keys
from probegrid.bake.records.tracer import STREAM_STEP, RecordTracer, _stream_keys
from probegrid.bake.settings import BakeSettings, TraceGeometry
from probegrid.core.ddgi import DEFAULT_NORMAL_BIAS
from probegrid.raytrace import RayTracer
from probegrid.scene import Scene

__all__ = ["CACHE_GATHER", "CACHE_LIGHT_SAMPLES", "CACHE_TEXEL_VERTICES", "LATTICE_EXTRA",
           "LIGHT_EXTRA", "LatticePlan", "SurfaceCache", "bake_surface_cache", "lattice_positions",
           "lattice_resolutions", "plan_lattice"]

#: The store extra of the lattice: per triangle its front's first vertex, its back's (-1 for a
#: one-sided triangle) and its resolution, ``(T, 3) int64``.
LATTICE_EXTRA = "surface_lattice"
#: The store extra of the light at the lattice's vertices, ``(V, 2, 3) float32``: irradiance / pi
#: of the light reflected at least once (``[:, 0]``) and of the emitters' and environment's
#: direct light (``[:, 1]``).
LIGHT_EXTRA = "surface_light"

#: Cosine-weighted gather rays per lattice vertex (the bake's hits cast ``gather_samples``),
#: stratified 16 x 16: a vertex's reflected light within 3-4 % (median; 7 % with 8 x 8 strata),
#: whose noise a point traced a few centimetres off a wall sees as patches of its rough GGX
#: levels (docs/benchmarks.md).
CACHE_GATHER = 256
#: Emitter and environment samples per lattice vertex for its direct light.
CACHE_LIGHT_SAMPLES = 16
#: The default lattice's vertices beyond one a triangle side, per texel of a probe's face
#: (:func:`plan_lattice`): ``8 n^2`` spread over a surface of area ``A`` are a spacing of about
#: ``sqrt(A) / 2n``, in a cube room of side ``L`` (``A = 6 L^2``) ``1.2 L / n``: a cell seen
#: from across the room about a mirror texel (``pi L / 2n``). 8 192 vertices at faces 32.
CACHE_TEXEL_VERTICES = 8
#: Largest lattice resolution of a triangle (edges over the spacing).
MAX_RESOLUTION = 64
#: Largest number of lattice vertices (24 bytes each in the store).
MAX_VERTICES = 1 << 21
#: Lattice vertices stand this fraction of the way from the triangle's edge to its centroid.
INSET = 1e-3
#: Where the cache's random streams are keyed (streams are keyed by position,
#: :func:`probegrid.bake.records.tracer._stream_keys`): the far corner of the keys' range,
#: -4.4e12 m on each axis, beyond every probe and query point (the service takes |x| <= 1e12).
CACHE_STREAM = np.full((1, 3), -(2.0**62) * STREAM_STEP)
#: Vertices shaded together.
CHUNK = 4096
#: Threads the chunks are shaded on: the machine's cores, at most 2 (the probes' passes run
#: on every core; the cache runs after them, in the bake's own process).
THREADS = min(2, os.cpu_count() or 1)


def lattice_counts(res: NDArray[np.int64]) -> NDArray[np.int64]:
    """Vertices of a lattice of resolution ``res``: ``(r + 1)(r + 2) / 2`` (one, the
    centroid, for 0)."""
    r = np.asarray(res, np.int64)
    return (r + 1) * (r + 2) // 2


def longest_edges(scene: Scene) -> NDArray[np.float64]:
    """Each triangle's longest edge."""
    v = np.asarray(scene.vertices, np.float64)[np.asarray(scene.triangles)]
    return np.max(np.linalg.norm(v - np.roll(v, 1, axis=1), axis=2), axis=1)


def lattice_resolutions(scene: Scene, vertices: int) -> NDArray[np.int64] | None:
    """Each triangle's resolution for at most ``vertices`` lattice vertices in all (both sides
    of double-sided triangles counted): its longest edge over one spacing, rounded down, the
    finest spacing that fits (bisection), 0 (the centroid alone) to :data:`MAX_RESOLUTION`;
    None when one vertex a side is already too many (a scene of more triangles than the
    budget: no cache)."""
    edge = longest_edges(scene)
    sides = 1 + np.asarray(scene.double_sided, np.int64)

    def res(h: float) -> NDArray[np.int64]:
        return _resolutions(edge, h)

    if int(np.sum(sides)) > vertices:
        return None
    lo, hi = 1e-9 * max(float(edge.max()), 1e-9), 2.0 * max(float(edge.max()), 1e-9)
    for _ in range(60):  # bisection on the spacing, in log
        h = math.sqrt(lo * hi)
        if int(np.sum(sides * lattice_counts(res(h)))) > vertices:
            lo = h
        else:
            hi = h
    return res(hi)


@dataclasses.dataclass(frozen=True)
class LatticePlan:
    """The lattice of a scene's surface cache (:func:`plan_lattice`).

    Attributes
    ----------
    resolutions : (T,) int64 array or None
        Each triangle's resolution (None: no cache).
    spacing : float
        The lattice's spacing, scene units (0: no cache).
    vertices : int
        Its vertices, both sides of double-sided triangles counted.
    reason : str
        Why this spacing (one sentence, for the manifest).
    """

    resolutions: NDArray[np.int64] | None
    spacing: float
    vertices: int
    reason: str

    def manifest(self) -> dict[str, Any]:
        """What the manifest's ``quality.surface_cache`` states."""
        coarser = 0 if self.resolutions is None else int(np.sum(self.resolutions
                                                                == MAX_RESOLUTION))
        return {"spacing": self.spacing, "vertices": self.vertices,
                "triangles_at_max_resolution": coarser, "reason": self.reason}


def _resolutions(edge: NDArray[np.float64], h: float) -> NDArray[np.int64]:
    return np.clip(np.floor(edge / h), 0, MAX_RESOLUTION).astype(np.int64)


def _spacing_of(scene: Scene, res: NDArray[np.int64]) -> float:
    """The spacing a lattice of resolutions ``res`` states: the coarsest it is the lattice of
    (the least longest edge over its resolution; with the centroids alone, the longest
    edge)."""
    edge = longest_edges(scene)
    on = res > 0
    return float(np.min(edge[on] / res[on])) if on.any() else float(np.max(edge, initial=0.0))


def plan_lattice(scene: Scene, spacing: float | None = None, *, face_size: int = 32,
                 rays: int = 1, max_vertices: int | None = None) -> LatticePlan:
    """The surface cache's lattice of ``scene`` at ``spacing`` (scene units; 0: none; None: the
    default, the finest with at most one vertex a triangle side plus
    :data:`CACHE_TEXEL_VERTICES` per texel of a probe's face, ``face_size`` texels a side, and
    per ray a texel of the view that reads the cache, ``rays``: a final gather's,
    :mod:`probegrid.bake.finalgather`), at most ``max_vertices`` vertices (None:
    :data:`MAX_VERTICES`; a finer spacing coarsened to fit; a scene of more triangle sides than
    that: none). The scene, the probes' texels and the rays that read it decide it, never the
    grid."""
    sides = 1 + np.asarray(scene.double_sided, np.int64)
    n_sides = int(np.sum(sides))
    area = float(np.sum(triangle_areas(scene) * sides))
    max_vertices = MAX_VERTICES if max_vertices is None else int(max_vertices)
    if spacing is not None and spacing <= 0:
        return LatticePlan(None, 0.0, 0, "surface_cache_spacing 0: no surface cache")
    if n_sides > max_vertices:
        return LatticePlan(None, 0.0, 0, f"{n_sides} triangle sides, more than the cache's "
                           f"{max_vertices} vertices: no surface cache")
    cap = f"at most {max_vertices} vertices ({max_vertices * 24 >> 20} MB)"
    if spacing is None:
        extra = CACHE_TEXEL_VERTICES * int(face_size) ** 2 * int(rays)
        res = lattice_resolutions(scene, min(max_vertices, n_sides + extra))
        assert res is not None
        per = "" if rays == 1 else f" and per ray of a final gather of {rays}"
        why = (f"the default: the finest spacing with at most one vertex a triangle side plus "
               f"{CACHE_TEXEL_VERTICES} per texel of a face of {face_size}^2{per} ({extra}) over "
               f"the scene's {area:.6g} square units of surface ({n_sides} triangle sides), "
               f"whatever the grid")
        h = _spacing_of(scene, res)
    else:
        res = _resolutions(longest_edges(scene), float(spacing))
        why = f"surface_cache_spacing {spacing:g}"
        h = float(spacing)
        if int(np.sum(sides * lattice_counts(res))) > max_vertices:
            res = lattice_resolutions(scene, max_vertices)
            assert res is not None
            h = _spacing_of(scene, res)
            why += f", coarsened to {cap}"
    vertices = int(np.sum(sides * lattice_counts(res)))
    return LatticePlan(res, h, vertices, why)


def triangle_areas(scene: Scene) -> NDArray[np.float64]:
    """Each triangle's area."""
    v = np.asarray(scene.vertices, np.float64)[np.asarray(scene.triangles)]
    return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)


def lattice_layout(scene: Scene, res: NDArray[np.int64]) -> NDArray[np.int64]:
    """The ``(T, 3)`` lattice table (:data:`LATTICE_EXTRA`) of resolutions ``res``."""
    counts = lattice_counts(res)
    sides = 1 + np.asarray(scene.double_sided, np.int64)
    start = np.concatenate([[0], np.cumsum(sides * counts)[:-1]]).astype(np.int64)
    back = np.where(sides == 2, start + counts, -1)
    return np.stack([start, back, res], axis=1).astype(np.int64)


def lattice_positions(scene: Scene, lattice: NDArray[np.int64]
                      ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Positions and unit normals (the side's: a back's is flipped) ``(V, 3)`` of every lattice
    vertex, each a fraction :data:`INSET` of the way toward its triangle's centroid."""
    tri = np.asarray(scene.vertices, np.float64)[np.asarray(scene.triangles)]
    nrm = np.asarray(scene.triangle_normals, np.float64)
    res = lattice[:, 2]
    total = int(np.sum(lattice_counts(res) * (1 + (lattice[:, 1] >= 0))))
    pos = np.empty((total, 3))
    out_n = np.empty((total, 3))
    for r in np.unique(res):  # loop over resolutions (at most MAX_RESOLUTION), not vertices
        ts = np.flatnonzero(res == r)
        j, i = np.divmod(np.arange((r + 1) * (r + 1)), r + 1)
        keep = i + j <= r  # row j after row j - 1: the layout of cache_lookup
        bu, bv = (i[keep] / r, j[keep] / r) if r else (np.full(1, 1 / 3), np.full(1, 1 / 3))
        bary = np.stack([1.0 - bu - bv, bu, bv], axis=1)
        bary = (1.0 - INSET) * bary + INSET / 3.0
        pts = np.einsum("mk,tkc->tmc", bary, tri[ts])  # (T_r, m, 3)
        m = bary.shape[0]
        for side, col in ((1.0, 0), (-1.0, 1)):  # front, then back
            on = lattice[ts, col] >= 0
            rows = lattice[ts[on], col][:, None] + np.arange(m)[None, :]
            pos[rows] = pts[on]
            out_n[rows] = side * nrm[ts[on]][:, None, :]
    return pos, out_n


class SurfaceCache:
    """A store's surface cache (:data:`LATTICE_EXTRA`, :data:`LIGHT_EXTRA`; memory-mapped as
    stored) read at ray hits."""

    def __init__(self, scene: Scene, lattice: NDArray[np.int64], light: NDArray[np.float32]
                 ) -> None:
        self.lattice = np.ascontiguousarray(lattice, np.int64)
        self.light = light.reshape(len(light), -1)
        self.normals = np.ascontiguousarray(scene.triangle_normals, np.float64)
        if len(self.lattice) != len(self.normals):
            raise ValueError("the surface cache is not of this scene (triangle count).")
        #: Each triangle's lattice spacing: its longest edge over its resolution (the whole
        #: edge for resolution 0).
        self.spacing = longest_edges(scene) / np.maximum(self.lattice[:, 2], 1)

    def lookup(self, prim: NDArray[np.int64], u: NDArray[np.float64], v: NDArray[np.float64],
               directions: NDArray[np.float64]) -> NDArray[np.float32]:
        """Indirect and direct irradiance / pi ``(k, 2, 3)`` at hits of rays along
        ``directions (k, 3)`` (``prim`` -1: a miss, zeros)."""
        out = cache_lookup(np.ascontiguousarray(prim, np.int64), np.ascontiguousarray(u),
                           np.ascontiguousarray(v), np.ascontiguousarray(directions),
                           self.normals, self.lattice, self.light)
        return out.reshape(len(out), 2, 3)


def bake_surface_cache(scene: Scene, environment: Environment, settings: BakeSettings,
                       geometry: TraceGeometry, data: GridData, *, level: int,
                       plan: LatticePlan | None = None, tracer: RayTracer | None = None,
                       iterations: int = 0, gather: int = CACHE_GATHER
                       ) -> tuple[NDArray[np.int64], NDArray[np.float32], int] | None:
    """The lattice table, the light at its vertices (module docstring) and the rays cast, for
    a bake of ``settings`` whose final pass, at bounce ``level``, read ``data`` (``cubes`` the
    grid's bordered irradiance, None for none), over the lattice of ``plan`` (None: the
    settings', :func:`plan_lattice`; None returned: no cache), ``gather`` first gather rays a
    vertex (stratified over a square grid when a square). ``iterations``: that indirect light
    then gathered again that many times by the same first gather rays, their hits reading the
    cache itself instead of the levels below and the grid (:func:`_iterate`; when the rays'
    hits fit in :data:`ITERATE_MAX_RAYS`)."""
    if plan is None:
        plan = plan_lattice(scene, settings.surface_cache_spacing,
                            face_size=settings.face_size)
    res = plan.resolutions
    if res is None:
        return None
    lattice = lattice_layout(scene, res)
    pos, nrm = lattice_positions(scene, lattice)
    depth = settings.gather_levels()
    st = settings.model_copy(update={"gather_samples": gather if depth else 0,
                                     "gather_depth": max(depth, 1)})
    rt = RecordTracer(scene, environment, st, geometry, tracer=tracer)
    if iterations:  # (a final gather's finer cache: the bake's workers wait meanwhile)
        from probegrid.bake.point import shared_pool

        rt.pool = shared_pool(None)  # the rays shaded on two threads, the same bits
    # the gather hits' probes tested for visibility by the scene's tracer, as the bake's are
    data = dataclasses.replace(data, tracer=rt.tracer)
    eps = geometry.ray_offset
    total = len(pos)
    light = np.zeros((total, 2, 3), np.float32)
    # every purpose's stream keys made before the chunks run (on threads: none writes them)
    keys = {purpose: _stream_keys(settings.seed, CACHE_STREAM, purpose)
            for purpose in range(1, 3 * max(depth, 1) + 3)}

    def draw(purpose: int, per: int, width: int, rows: NDArray[np.int64]) -> NDArray[np.float64]:
        u = np.asarray(_draw_rows(keys[purpose], per, rows, width))
        if purpose == 3:  # a vertex's first gather rays: stratified over the unit square
            u = stratified(u, rows % gather, gather)
        return u

    ls = CACHE_LIGHT_SAMPLES if len(rt.emitters) else 0
    ks = 0 if rt.sky.is_black else CACHE_LIGHT_SAMPLES
    kg = rt.gather_samples
    g = irradiance_size(depth > 0)
    grid = data.cubes if data.cubes is not None else np.zeros((0, 3), np.float32)
    empty = np.zeros((0, 3), np.float32)
    keep_hits = iterations > 0 and kg > 0 and level >= 1 and total * kg <= ITERATE_MAX_RAYS
    # the first gather level, when iterated: each chunk's (appended by any thread; each chunk
    # writes its own vertices in _iterate, so their order does not matter)
    first: list[tuple[Level, NDArray[np.int64]]] = []
    bias = DEFAULT_NORMAL_BIAS * data.grid.smallest_cell()

    # at most CHUNK vertices a chunk, at least one chunk per thread
    chunk = max(1, min(CHUNK, -(-total // THREADS)))

    def shade(v0: int) -> int:
        """The light of vertices ``v0`` to ``v0 + chunk`` (written to ``light``); rays cast."""
        v1 = min(v0 + chunk, total)
        k = v1 - v0
        p = pos[v0:v1]
        n = nrm[v0:v1]
        rays = 0
        # direct light of the emitters and the environment, from just off the surface
        off = p + eps * n
        if ls:
            e, r = rt.emitters.irradiance(off, n, draw(1, total, 3 * ls, np.arange(v0, v1))
                                          .reshape(k, ls, 3), rt.tracer, eps)
            light[v0:v1, 1] += (e / np.pi).astype(np.float32)
            rays += r
        if ks:
            e, r = rt.sky.irradiance(off, n, draw(2, total, 3 * ks, np.arange(v0, v1))
                                     .reshape(k, ks, 3), rt.tracer, eps)
            light[v0:v1, 1] += (e / np.pi).astype(np.float32)
            rays += r
        if not kg or level < 1:
            return rays
        # the gather: the vertices as front hits seen from straight above
        above = Level(kind=np.ones(k, np.uint8), position=p, normal=n.astype(np.float32))
        arriving = -n
        front = np.arange(k)
        rows = (v0 + np.repeat(front, kg)) * kg + np.tile(np.arange(kg), k)
        parent_row = np.repeat(front, kg)
        owner = parent_row  # each record's vertex
        levels: list[Level] = [above]
        for d in range(1, depth + 1):
            lv, g_dir, cast = rt._gather_level(draw, total, (3 * d, 3 * d + 1, 3 * d + 2),
                                               rows, above, arriving, parent_row, bool(ls),
                                               bool(ks), hits=keep_hits and d == 1)
            rays += cast
            if keep_hits and d == 1:  # what _iterate reads of them (73 bytes a ray)
                first.append((lv.keep(ITERATE_KEYS), v0 + parent_row))
            kept = lv.keep(gather_keys(deepest=d == depth))
            kept.primary = parent_row.astype(np.int32)
            levels.append(kept)
            hit = np.flatnonzero(lv.kind == 1)
            if d < depth:
                rows, parent_row, owner = rows[hit], hit, owner[hit]
            above, arriving = lv, g_dir
        deepest = levels[depth]
        if grid.shape[0]:
            # a deepest hit that sees none of its cell's probes reads the probe its vertex
            # sees (nothing where it sees none), as a probe's hits read the probe: never the
            # moments' soft weights, which can favour a probe beyond a wall (with probes
            # added there, the light behind a cabinet changed 4x)
            seen = visible_probe(p + bias * n, data.grid, data.valid, data.positions,
                                 rt.tracer)
            deepest.weight_index, deepest.weight = _level_weights(deepest, data, seen[owner])
        below = empty
        for d in range(depth, 0, -1):  # deepest first, as the bake's replay
            parents = len(levels[d - 1].kind)
            if level - d < 0:
                below = np.zeros((parents, 3), np.float32)
                continue
            _, reflected = _replay_level(levels[d], d, level - d,
                                         grid if d == depth else empty, below, g)
            primary = levels[d].primary
            assert primary is not None
            below = mean_per_parent(*frozen((primary, reflected)), parents)
        light[v0:v1, 0] = below
        return rays

    # chunks of vertices, not vertices, on THREADS threads (Embree and the kernels release the
    # GIL; each chunk's numbers depend only on its vertices: the same bits on any thread)
    starts = range(0, total, chunk)
    if THREADS > 1 and len(starts) > 1:
        with ThreadPoolExecutor(THREADS, thread_name_prefix="probegrid-cache") as pool:
            rays = sum(pool.map(shade, starts))
    else:
        rays = sum(shade(v0) for v0 in starts)
    if keep_hits:
        _iterate(SurfaceCache(scene, lattice, light), light, first, level - 1, g, iterations)
    return lattice, light, rays


#: Most first-level gather rays whose hits :func:`bake_surface_cache` keeps to iterate the
#: cache (73 bytes each: 300 MB; 65,536 vertices of 64 rays). A larger cache is not iterated.
ITERATE_MAX_RAYS = 1 << 22
#: What the iteration keeps of a first gather level's records.
ITERATE_KEYS = ("kind", "light_punctual", "light_emitters", "albedo", "normal", "primitive",
                "barycentric")


def _iterate(cache: SurfaceCache, light: NDArray[np.float32],
             first: list[tuple[Level, NDArray[np.int64]]], level: int, g: int,
             iterations: int) -> None:
    """Gather the cache's indirect light (``light[:, 0]`` of ``light (V, 2, 3)``, which
    ``cache`` reads, in place) ``iterations``
    times more from the kept first gather level ``first`` (each chunk's records, with their
    triangles and barycentrics, and each ray's vertex): a ray's hit reflects its own direct
    light (punctual, emitters and environment, as sampled when it was traced) and the cache's
    indirect light there, at bounce ``level``, and a vertex takes the mean over its rays.

    A fixed point of the gather on the lattice (a radiosity iteration): the light reflected
    more than ``gather_depth`` times comes from the surfaces themselves instead of the probes'
    irradiance read at the deepest hits, which is biased where the probes stand in open space
    and the hits by walls (the sunlit hall of ``benchmarks/scenes.py``: 3-8 % bright). Each
    iteration leaves the previous error times about the scene's albedo; the first starts from
    the gathered (grid-read) estimate."""
    total = len(light)
    empty = np.zeros((0, 3), np.float32)
    for _ in range(iterations):  # loop over iterations, each a pass over every kept ray
        new = np.zeros((total, 3), np.float32)
        for lv, vertex in first:  # loop over chunks of vertices
            assert lv.primitive is not None and lv.barycentric is not None
            assert lv.normal is not None
            # the side a ray sees: its normal is turned toward it
            below = cache.lookup(lv.primitive, lv.barycentric[:, 0], lv.barycentric[:, 1],
                                 -np.asarray(lv.normal, np.float64))[:, 0]
            _, reflected = _replay_level(lv.keep(gather_keys(deepest=False)), 1, level, empty,
                                         np.ascontiguousarray(below, np.float32), g)
            lo, hi = int(vertex.min()), int(vertex.max()) + 1
            new[lo:hi] = mean_per_parent(*frozen(((vertex - lo).astype(np.int32), reflected)),
                                         hi - lo)
        light[:, 0] = new


def stratified(u: NDArray[np.float64], k: NDArray[np.int64], count: int) -> NDArray[np.float64]:
    """Uniform pairs ``u (n, 2)`` of sample ``k`` of ``count`` moved into stratum ``k`` of a
    ``sqrt(count)``-square grid over the unit square (unchanged unless ``count`` is a square):
    each vertex's gather rays then cover the cosine lobe evenly (the cosine map of
    :func:`probegrid.bake.kernels.sampling.gather_rays` keeps the strata's equal measure)."""
    s = math.isqrt(count)
    if s * s != count or s < 2:
        return u
    out = np.empty_like(u)
    out[:, 0] = (k // s + u[:, 0]) / s
    out[:, 1] = (k % s + u[:, 1]) / s
    return out


def _draw_rows(keys: NDArray[np.uint64], per: int, rows: NDArray[np.int64], width: int
               ) -> Any:
    from probegrid.bake.kernels.sampling import stream_uniforms

    return stream_uniforms(keys, max(int(per), int(rows.max(initial=0)) + 1), rows, width)
