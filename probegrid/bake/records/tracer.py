"""Trace once: every ray of a batch of probes cast once, and what each bounce needs of it kept
as a record (:class:`RecordTracer`).

A bake's bounces differ only in the light its grid carries, never in its rays. So each probe's
rays are cast once (the primary rays, the shadow rays toward the punctual lights and toward
points sampled on the emitters and the environment at every hit, the probe's own rays toward the
lights and the emitter pieces of its direct view) and kept as the block's records
(:mod:`probegrid.bake.records.schema`): per ray its kind, emission, light and surface, and per
probe the correction of its direct view of the emitters (exact texel coverage) and the punctual
lights it sees (folded in at the end, :func:`probegrid.core.lights.splat_delta`).

Final gather
------------
Each front hit also casts ``gather_samples`` cosine-weighted rays (a gather level,
:func:`probegrid.bake.kernels.sampling.gather_rays`), traced once and lit as the probe's rays
are (punctual lights, one emitter and one environment sample at their hits; their misses and
emission count 0: the environment and the emitters reach the hit by sampling), and with
``gather_depth = 2`` (the default) each of their hits casts one more (a third level with 3).
(On the sample room against a path tracer: 1.59 % mean error with one level, 0.99 % with two,
for about 15 % more bake time; 0.77 % with three, for 1.4x the converged bake's CPU time: the
grid read at the deepest hits is what remains biased, up to 1.5 % bright for the probes by a
wall.) The probes' irradiance interpolated between them is then one reflection further from
what is seen: read at the hit itself, it is the irradiance where the probes stand, not where
the hit is (a ceiling above a floor's hot spot read a probe nearer the spot: 1.97x too bright;
``tests/test_bake.py``). ``gather_samples = 0`` reads the grid at the hit.

Random numbers come from counter-based streams, one per probe position and purpose
(:func:`probegrid.bake.kernels.sampling.stream_uniforms`): what a probe draws depends only on
its stream and the row, not on its batch or its index, so a block traced again gives the same
bits, and a probe at the same point of another grid draws the same numbers.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import frozen
from probegrid.bake.emitters import Emitters
from probegrid.bake.environment import Environment, EnvironmentLight
from probegrid.bake.kernels.grid import distance_moments, texel_means
from probegrid.bake.kernels.lights import light_rays, sum_unblocked
from probegrid.bake.kernels.sampling import gather_rays, stream_uniforms
from probegrid.bake.kernels.surfaces import HitRecords, scatter_divided, shade_hits
from probegrid.bake.records.schema import Level, RecordArrays, Records, gather_keys
from probegrid.bake.pattern import sample_pattern
from probegrid.bake.settings import BakeSettings, TraceGeometry
from probegrid.bake.view import ProbeView
from probegrid.core.cubemap import texel_directions
from probegrid.raytrace import EmbreeRays, RayTracer
from probegrid.scene import Scene

__all__ = ["SHADE_CHUNK", "Draw", "RecordTracer"]


#: Rays shaded together: every per-ray temporary of a chunk stays in cache-sized, reused memory
#: (a whole batch of probes at once spends much of its time in page faults). Each ray's result
#: does not depend on its chunk.
SHADE_CHUNK = 1 << 15
#: Fewest rays a chunk shaded on a thread of :attr:`RecordTracer.pool` holds.
MIN_SPLIT = 1024


#: Random numbers for given rows (a probe stream's rows, see RecordTracer.trace).
Draw = Callable[[NDArray[np.int64]], NDArray[np.float64]]


def _tint_rows(rec: Level, tint: NDArray[np.float64], rows: NDArray[np.int64],
               misses: NDArray[np.int64]) -> None:
    """Records of rays that passed tinted panes (``tint (k, 3)``, their weights): what a hit
    sends back (its emission and, through its albedo, what it reflects) and what a miss sees
    of the environment, multiplied by the weight; the punctual and emitted light a hit
    receives is reflected through the albedo, so it takes the weight there."""
    assert rec.albedo is not None and rec.emission is not None
    rec.albedo[rows] *= tint[rows]
    rec.emission[rows] *= tint[rows]
    if misses.size and rec.light_punctual is not None:
        rec.light_punctual[misses] *= tint[misses]


def _light_draw(draw: Callable[[int, int, int, NDArray[np.int64]], NDArray[np.float64]],
                purpose: int, per: int, samples: int) -> Draw | None:
    """The random numbers of ``samples`` light samples per ray (3 each:
    :meth:`RecordTracer.trace`'s ``draw`` of one purpose, ``per`` rays per probe) as a
    :data:`Draw` of ``(k, samples, 3)``; None for no sample."""
    if not samples:
        return None
    return lambda rows: draw(purpose, per, samples * 3, rows).reshape(-1, samples, 3)


def _stream_keys(seed: int, positions: NDArray[np.float64], purpose: int
                 ) -> NDArray[np.uint64]:
    """The keys of the probes' random streams for one purpose (independent of the sample
    pattern's): 64 bits of ``SeedSequence(seed, spawn_key=(x, y, z, purpose))`` each, ``x, y,
    z`` the probe's coordinates in units of :data:`STREAM_STEP` (rounded, as 64-bit two's
    complement), for :func:`probegrid.bake.kernels.sampling.stream_uniforms`. Keyed by where
    the probe stands, not by its index: a probe draws the same numbers in any grid that has a
    probe there (a grid extended by layers keeps its inner probes' bits wherever their light is
    the same; ``lo + 3 * step`` and ``lo' + 4 * step``, a rounding apart, are one point)."""
    q = np.round(np.asarray(positions, dtype=np.float64).reshape(-1, 3) / STREAM_STEP)
    q = np.clip(q, -2.0**62, 2.0**62).astype(np.int64).view(np.uint64)
    return np.array([np.random.SeedSequence(int(seed), spawn_key=(*map(int, b), purpose))
                     .generate_state(1, np.uint64)[0] for b in q], np.uint64)


#: The resolution of the positions that key the probes' random streams (metres, scene units):
#: 2^-20, about a micrometre.
STREAM_STEP = 2.0**-20


class RecordTracer:
    """Traces batches of probes into records (build once per worker: it owns the BVH).

    The settings say the probes' rays (``face_size``, ``samples``, ``seed``), their light
    (``light_samples``, ``direct``) and the gather levels (``gather_samples`` rays per hit,
    :meth:`~probegrid.bake.settings.BakeSettings.gather_levels` deep); ``geometry`` the rays'
    offset and the distance of a miss.
    """

    def __init__(self, scene: Scene, environment: Environment, settings: BakeSettings,
                 geometry: TraceGeometry, *, tracer: RayTracer | None = None) -> None:
        self.view = ProbeView(scene, environment, settings, geometry, tracer=tracer)
        self.scene = scene
        self.settings = settings
        self.geometry = geometry
        self.tracer = self.view.tracer
        self.emitters = Emitters.from_scene(scene)
        self.sky = EnvironmentLight(environment)
        levels = settings.gather_levels()
        self.light_samples = int(settings.light_samples)
        #: Gather rays per hit (0: the grid is read at the probes' own hits).
        self.gather_samples = int(settings.gather_samples) if levels else 0
        #: Gather levels traced when ``gather_samples`` is not 0.
        self.gather_depth = max(levels, 1)
        #: Threads that shade a level's chunks side by side (None: one after another; the
        #: kernels and Embree release the GIL). Each ray's result does not depend on its chunk.
        self.pool: ThreadPoolExecutor | None = None
        #: Which front hits ``(prim_id, t)`` sample the emitters and the environment (None:
        #: all; a probe traced at a point reads the others' from the surface cache).
        self.sample_where: Callable[[NDArray[np.int64], NDArray[np.float64]],
                                    NDArray[np.bool_]] | None = None

    def _shade(self, origins: NDArray[np.float64], dirs: NDArray[np.float64],
               draw_rows: NDArray[np.int64], draw_e: Draw | None, draw_s: Draw | None,
               rec: Level, t: NDArray[np.float64], *,
               sky_at_misses: NDArray[np.float64] | None) -> int:
        """Fills ``rec`` (:meth:`Level.empty`: misses) and ``t`` with the records and hit
        distances of one chunk of rays; returns the rays cast: the rays themselves and every
        shadow ray of their front hits (punctual lights; ``draw_e(rows) (k, L, 3)`` the random
        numbers of points on the emitters, ``draw_s`` of directions of the environment, None for
        none; ray ``i``'s are row ``draw_rows[i]``, drawn for the front hits only). A miss keeps
        the environment's radiance in the direction ``sky_at_misses[i]`` (what a probe sees:
        its texel's centre, where the environment box-filtered to the texels holds the texel's
        mean, wherever in the texel the ray went), else 0 for None (the environment reaches
        hits by sampling)."""
        geo = self.geometry
        rd = self.view
        eps = geo.ray_offset
        k = len(dirs)
        tint = None
        if self.tracer.tinted:  # the weights of the tinted panes the rays passed
            hits, tint = self.tracer.intersect_weighted(origins, dirs)
        else:
            hits = self.tracer.intersect(origins, dirs)
        rays = k
        sc = self.scene
        assert rec.light_punctual is not None and rec.light_emitters is not None
        # the records of the chunk in one pass: kind, distance, and at each front hit its
        # surface (the normal turned toward the ray: the side it sees is shaded; emission leaves
        # the front as wound only)
        rows, p, nrm, back_off = shade_hits(
            frozen(dirs), hits, (float(geo.max_distance), eps), sc.surface_tables,
            rd.double_sided,
            HitRecords(rec.kind, t, rec.position, rec.normal, rec.albedo, rec.emission))
        sc.apply_textures(hits.prim_id, hits.u, hits.v, rec.albedo, rec.emission, rows)
        if rec.primitive is not None and rec.barycentric is not None:  # (asked: Level.empty)
            rec.primitive[:] = hits.prim_id
            rec.barycentric[:, 0] = hits.u
            rec.barycentric[:, 1] = hits.v
        if sky_at_misses is not None and not rd.environment.is_black:
            miss = np.flatnonzero(rec.kind == 0)
            if miss.size:
                rec.light_punctual[miss] = rd.environment_view.radiance(sky_at_misses[miss])
        if tint is not None:  # what the ray brings back through the panes it passed
            _tint_rows(rec, tint, rows, np.flatnonzero(rec.kind == 0))
        if not rows.size:
            return rays
        which, s_org, s_dir, s_len, s_irr, ok = light_rays(p, nrm, rd.punctual_lights, eps,
                                                           self.tracer.centre)
        if len(which) and self.tracer.tinted:
            through = self.tracer.shadow_weights(EmbreeRays(s_org, s_dir, s_len), ok)
            rays += len(which)
            scatter_divided(rec.light_punctual, rows,
                            sum_unblocked(len(rows), which, ~np.any(through > 0, axis=1),
                                          s_irr * through), np.pi, False)
        elif len(which):
            occluded = self.tracer.occluded_rays(EmbreeRays(s_org, s_dir, s_len), ok)
            rays += len(which)
            scatter_divided(rec.light_punctual, rows,
                            sum_unblocked(len(rows), which, occluded, s_irr), np.pi, False)
        if self.sample_where is not None and (draw_e is not None or draw_s is not None):
            # the light sampled at some hits only (the others read it elsewhere)
            keep = self.sample_where(hits.prim_id[rows], hits.t[rows])
            rows, back_off, nrm = rows[keep], back_off[keep], nrm[keep]
            if rec.sampled is not None:
                rec.sampled[rows] = True
        # lit from a point offset short of the hit, back along the ray (shade_hits)
        if draw_e is not None and rows.size:
            e_e, r = self.emitters.irradiance(back_off, nrm, draw_e(draw_rows[rows]),
                                              self.tracer, eps)
            rays += r
            scatter_divided(rec.light_emitters, rows, e_e, np.pi, False)
        if draw_s is not None and rows.size:  # the environment as a light (not in the grid)
            e_s, r = self.sky.irradiance(back_off, nrm, draw_s(draw_rows[rows]), self.tracer,
                                         eps)
            rays += r
            scatter_divided(rec.light_emitters, rows, e_s, np.pi, True)
        return rays

    def _shade_all(self, origins: NDArray[np.float64], dirs: NDArray[np.float64],
                   draw_rows: NDArray[np.int64], draw_e: Draw | None, draw_s: Draw | None, *,
                   sky_at_misses: NDArray[np.float64] | None, hits: bool = False
                   ) -> tuple[Level, NDArray[np.float64], int]:
        """:meth:`_shade` of any number of rays, :data:`SHADE_CHUNK` at a time, into one set of
        records (with ``hits`` each ray's triangle and barycentrics too); ``sky_at_misses`` (a
        probe's ``(R, 3)`` table, ray ``i`` reading row ``i % R``) or None."""
        rec = Level.empty(len(dirs), hits=hits)
        t = np.empty(len(dirs))
        chunk = SHADE_CHUNK
        if self.pool is not None and len(dirs) >= 2 * MIN_SPLIT:  # one chunk per thread
            chunk = min(chunk, -(-len(dirs) // self.pool._max_workers))

        def shade(c0: int) -> int:
            sl = slice(c0, min(c0 + chunk, len(dirs)))
            sky = (None if sky_at_misses is None else
                   sky_at_misses[np.arange(sl.start, sl.stop) % len(sky_at_misses)])
            return self._shade(origins[sl], dirs[sl], draw_rows[sl], draw_e, draw_s,
                               rec.rows(sl), t[sl], sky_at_misses=sky)

        starts = range(0, len(dirs), chunk)  # chunks of rays, not rays
        if self.pool is not None and len(starts) > 1:
            rays = sum(self.pool.map(shade, starts))
        else:
            rays = sum(shade(c0) for c0 in starts)
        return rec, t, rays

    def _gather_level(self, draw: Any, rays_per_probe: int, purposes: tuple[int, int, int],
                      rows: NDArray[np.int64], above: Level, arriving: NDArray[np.float64],
                      parents: NDArray[np.int64], emitters: bool, sky: bool, *,
                      hits: bool = False) -> tuple[Level, NDArray[np.float64], int]:
        """One gather level: a cosine-weighted ray from each hit ``parents`` of the level
        ``above`` (records with ``position`` and ``normal``, the normal facing the side the ray
        ``arriving`` came from), lit as a probe's rays are (one emitter and one environment
        sample; misses and emission count 0). Its random numbers are rows ``rows`` of the
        probes' streams of ``purposes`` (directions, emitters, environment; ``rays_per_probe``
        primary rays of K gather rays each per probe, :meth:`trace`'s ``draw``; with ``hits``
        the records keep each ray's triangle and barycentrics). Returns the records, the
        directions and the rays cast."""
        eps = self.geometry.ray_offset
        kg = self.gather_samples
        per = rays_per_probe * kg
        assert above.position is not None and above.normal is not None
        org, dirs = gather_rays(above.position, above.normal, arriving, parents,
                                draw(purposes[0], per, 2, rows), eps)
        rec, _, rays = self._shade_all(org, dirs, rows,
                                       _light_draw(draw, purposes[1], per, int(emitters)),
                                       _light_draw(draw, purposes[2], per, int(sky)),
                                       sky_at_misses=None, hits=hits)
        return rec, dirs, rays

    def trace(self, positions: NDArray[np.float64], indices: NDArray[np.int64], *,
              hits: bool = False) -> tuple[RecordArrays, NDArray[np.float32], int]:
        """Cast every ray of probes at ``positions (B, 3)`` (linear ``indices``) once (with
        ``hits`` the probes' rays keep their triangles and barycentrics, :class:`Level`).

        Returns the records (their stored arrays, :meth:`Records.arrays`), the probes' distance
        moments ``(B, 6, m, m, 2)`` and the rays cast.
        """
        st = self.settings
        rd = self.view
        n, s, m = st.face_size, st.samples, st.moments_face_size
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        b = len(pos)
        pattern = sample_pattern(st)  # (every probe's: module docstring of bake.pattern)
        dirs = np.repeat(pattern[0].reshape(1, -1, 3), b, axis=0)  # (new, writable arrays:
        wts = np.repeat(pattern[1].reshape(1, -1), b, axis=0)  # one kernel signature)
        nr = dirs.shape[1]
        flat = dirs.reshape(-1, 3)
        origins = np.repeat(pos, nr, axis=0)
        eps = self.geometry.ray_offset
        ls = self.light_samples if len(self.emitters) else 0
        ks = 0 if self.sky.is_black else self.light_samples
        kg = self.gather_samples

        keys: dict[int, NDArray[np.uint64]] = {}

        def draw(purpose: int, per: int, width: int, rows: NDArray[np.int64]
                 ) -> NDArray[np.float64]:
            # rows of the probes' streams of one purpose, ``per`` rows of ``width`` numbers per
            # probe: row r of the batch is row r % per of probe r // per. What a probe draws
            # depends only on its stream and the row, not on its batch or the other rows
            if purpose not in keys:
                keys[purpose] = _stream_keys(st.seed, pos, purpose)
            return stream_uniforms(keys[purpose], per, rows, width)

        # a probe's misses see the environment at their texels' centres (_shade)
        centres = np.repeat(texel_directions(n).reshape(-1, 3), s, axis=0)  # (nr, 3)
        rec, t, rays = self._shade_all(origins, flat, np.arange(b * nr),
                                       _light_draw(draw, 1, nr, ls), _light_draw(draw, 2, nr, ks),
                                       sky_at_misses=centres, hits=hits)
        levels = [rec]
        if kg:
            # final gather (module docstring): kg rays from every front hit, one more from each
            # of their hits at depth 2; a bounce reads the grid at the deepest level's hits
            front = np.flatnonzero(rec.kind == 1)
            rows = np.repeat(front, kg) * kg + np.tile(np.arange(kg), len(front))
            parent_row = np.repeat(front, kg)  # each ray's parent in the level above
            above, arriving = rec, flat
            for depth in range(1, self.gather_depth + 1):
                level, g_dir, cast = self._gather_level(
                    draw, nr, (3 * depth, 3 * depth + 1, 3 * depth + 2), rows, above, arriving,
                    parent_row, bool(ls), bool(ks))
                rays += cast
                kept = level.keep(gather_keys(deepest=depth == self.gather_depth))
                kept.primary = parent_row.astype(np.int32)
                levels.append(kept)
                hit = np.flatnonzero(level.kind == 1)  # the next level's parents, one ray each
                rows, parent_row = rows[hit], hit
                above, arriving = level, g_dir
        back = rec.kind.reshape(b, nr) == 2
        moments = np.empty((b, 6, m, m, 2), dtype=np.float32)
        sa = rd.ray_solid_angles * wts
        tt = t.reshape(b, nr)
        for j in range(b):  # per probe: the reductions must not depend on the batch
            moments[j] = distance_moments(tt[j], sa[j], rd.moment_bins,
                                          6 * m * m).reshape(6, m, m, 2)
        # the probe's direct view of the emitters (exact texel coverage) replaces what its
        # rays saw of their emission; the punctual lights it sees are folded in at the end
        emission = rec.emission
        assert emission is not None
        view_tex, view_val, view_off = [], [], [0]
        texs, vals, offs, r = self.emitters.texel_views(pos, n, self.tracer, eps)
        rays += r
        for j in range(b):  # loop over probes, not rays
            tex, val = texs[offs[j]:offs[j + 1]], vals[offs[j]:offs[j + 1]]
            em = emission[j * nr:(j + 1) * nr]
            seen = em if s == 1 else texel_means(em, wts[j], s)
            delta = -np.asarray(seen, np.float64)
            delta[tex] += val
            keep = np.flatnonzero(np.any(delta != 0, axis=1))
            view_tex.append(keep)
            view_val.append(delta[keep])
            view_off.append(view_off[-1] + len(keep))
        l_dir, l_e, l_off = [np.zeros((0, 3))], [np.zeros((0, 3))], [0]
        if st.direct and self.scene.lights:
            ldirs, e_perp, visible, r = rd.visible_lights(pos)
            rays += r
            for j in range(b):
                li = np.flatnonzero(visible[j])
                l_dir.append(ldirs[j, li])
                l_e.append(e_perp[j, li])
                l_off.append(l_off[-1] + len(li))
        else:
            l_off = [0] * (b + 1)
        records = Records(
            probes=idx, rays_per_probe=nr, sky_sampled=bool(ks), levels=levels,
            backface_fraction=back.mean(axis=1),
            view_texel=np.concatenate(view_tex).astype(np.int64),
            view_value=np.concatenate(view_val).astype(np.float64).reshape(-1, 3),
            view_offsets=np.array(view_off, np.int64),
            lights_direction=np.concatenate(l_dir), lights_irradiance=np.concatenate(l_e),
            lights_offsets=np.array(l_off, np.int64))
        return records.arrays(), moments, rays
