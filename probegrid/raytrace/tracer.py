"""The Embree acceleration structure over one triangle soup (:class:`RayTracer`): closest hits,
occlusion of rays and of segments, built once per process.

Surfaces a ray may pass
-----------------------
A tracer built with a ``coverage`` (a scene's :class:`probegrid.scene.coverage.Coverage`:
cut-outs, partial coverage, thin transmission) decides at every hit on such a triangle whether
the ray stops there: it stops when ``xi < p``, ``p`` the coverage's stop probability at the
hit, ``xi`` a uniform number hashed from the ray's bits and the triangle (:func:`_uniforms`:
the same ray passes or stops the same way every time, in every process). A ray that passes is
cast again from just past the hit (``tmin`` = the hit's ``t`` plus :attr:`RayTracer.skip`
scene units, the origin staying where it was, so nothing in front is hit again), at most
:data:`MAX_LAYERS` times; a ray that still meets a cut-out surface after that stops there (a
bound on the work, not a model: it takes 64 stacked cut-outs). Embree's filter callbacks are
not reachable through embreex; this re-casting gives the same answer. :meth:`RayTracer.
transmittance` gives the expectation instead of a draw: the product of ``1 - p`` along a
segment (what a probe's single ray toward a punctual light uses).

Occlusion with a coverage first asks Embree's any-hit query of the opaque triangles only (one
call, as fast as without coverage), then walks the rays it left unblocked through the cut-out
triangles only, nearest first, until one stops the ray or the segment ends. Without a coverage
(or when every triangle is opaque) nothing of this runs and every answer is as before, bit for
bit.

This is the only module of the project that imports ``embreex``. Conventions (rays, barycentrics,
back faces, float32 precision, batches) are the package's, :mod:`probegrid.raytrace`.

Reference: Wald et al., "Embree: A Kernel Framework for Efficient CPU Ray Tracing", ACM TOG 33(4),
2014; embreex ``EmbreeScene.run`` (query ``INTERSECT`` with ``output=1`` returns ``primID``,
``u``, ``v``, ``tfar``; ``OCCLUDED`` returns the geometry id, -1 when unoccluded).
"""

from __future__ import annotations

import hashlib
import math
from typing import Final

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh
from numpy.typing import ArrayLike, NDArray

from probegrid._jit import frozen
from probegrid.raytrace.kernels import embree_hits, embree_rays, segment_rays
from probegrid.raytrace.rays import EmbreeRays, Hits

__all__ = ["RayTracer"]

_DEFAULT_CHUNK: Final[int] = 1 << 16
_MAX_CHUNK: Final[int] = 1 << 22

#: Surfaces a ray passes at most before it stops at the next one it may pass (module docstring).
MAX_LAYERS: Final[int] = 64

#: The step past a passed hit, as a share of the scene's bounding-box diagonal (about 150
#: float32 ulps of the re-centred coordinates: the next cast cannot find the same surface).
SKIP_SHARE: Final[float] = 1e-5


def _mix(h: NDArray[np.uint64]) -> NDArray[np.uint64]:
    """SplitMix64's finaliser (Steele, Lea, Flood 2014), element-wise."""
    h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return h ^ (h >> np.uint64(31))


def _uniforms(origins: NDArray, directions: NDArray, prim: NDArray[np.int64]
              ) -> NDArray[np.float64]:
    """A uniform number in [0, 1) per ray and triangle: SplitMix64 of the bits of the ray's
    origin and direction (``(k, 3)`` each, float64 or float32) and of the triangle ``prim``."""
    h = np.full(len(prim), 0x9E3779B97F4A7C15, dtype=np.uint64)
    with np.errstate(over="ignore"):
        for a in (origins, directions):
            bits = np.ascontiguousarray(a, np.float64).view(np.uint64)
            for k in range(3):
                h = _mix(h ^ bits[:, k])
        h = _mix(h ^ np.asarray(prim, np.int64).astype(np.uint64))
    return (h >> np.uint64(11)).astype(np.float64) * 2.0**-53


class RayTracer:
    """An Embree acceleration structure over one triangle soup, built once.

    Parameters
    ----------
    vertices : (V, 3) float
        World-space positions (finite).
    triangles : (T, 3) int
        Vertex indices, T >= 1.
    chunk_size : int
        Rays handed to Embree per call, at most 2^22 (bounds temporary memory, about 100 bytes
        per ray of a chunk; default 65536).
    coverage : Coverage or None
        What a ray may pass (module docstring): an object with ``cutout (T,) bool`` and
        ``stops(prim, u, v, xi) -> (k,) bool`` and ``stop_probability(prim, u, v)``
        (:class:`probegrid.scene.coverage.Coverage`).
        None: every triangle stops every ray.

    Attributes
    ----------
    vertices : (V, 3) float64, read-only
    triangles : (T, 3) int64, read-only
    normals : (T, 3) float64, read-only
        Unit geometric normals ``(b - a) x (c - a)``; zero for degenerate triangles.
    centre : (3,) float64, read-only
        The bounding box's centre, on which the float32 geometry and rays are re-centred
        (:class:`EmbreeRays`).
    skip : float
        The step past a hit a ray passes, in scene units (:data:`SKIP_SHARE` of the diagonal).
    """

    def __init__(
        self, vertices: ArrayLike, triangles: ArrayLike, *, chunk_size: int = _DEFAULT_CHUNK,
        coverage: object | None = None,
    ):
        v = np.array(vertices, dtype=np.float64)
        t = np.asarray(triangles)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise ValueError(f"vertices must have shape (V, 3) with V >= 1, got {v.shape}.")
        if not np.all(np.isfinite(v)):
            raise ValueError("vertices must be finite.")
        if t.ndim != 2 or t.shape[1] != 3 or len(t) == 0 or not np.issubdtype(t.dtype, np.integer):
            raise ValueError(
                f"triangles must be an integer array of shape (T, 3), T >= 1, got {t.shape}."
            )
        t = np.array(t, dtype=np.int64)
        if t.min() < 0 or t.max() >= len(v) or len(v) >= 2**31 or len(t) >= 2**31:
            raise ValueError(f"triangle indices must lie in [0, {len(v)}) and fit in int32.")
        if (
            not isinstance(chunk_size, (int, np.integer))
            or isinstance(chunk_size, bool)
            or not 1 <= chunk_size <= _MAX_CHUNK
        ):
            raise ValueError(
                f"chunk_size must be an integer in [1, {_MAX_CHUNK}], got {chunk_size!r}."
            )
        v.setflags(write=False)
        t.setflags(write=False)
        self.vertices: NDArray[np.float64] = v
        self.triangles: NDArray[np.int64] = t
        self.chunk_size = int(chunk_size)
        self.centre: NDArray[np.float64] = 0.5 * (v.min(axis=0) + v.max(axis=0))
        self.centre.setflags(write=False)
        p = v[t]
        n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        self.normals: NDArray[np.float64] = np.divide(
            n, length, out=np.zeros_like(n), where=length > 0
        )
        self.normals.setflags(write=False)
        self._scene = rtcore_scene.EmbreeScene()
        v32 = np.ascontiguousarray(v - self.centre, dtype=np.float32)
        TriangleMesh(scene=self._scene, vertices=v32,
                     indices=np.ascontiguousarray(t, dtype=np.int32))
        self.skip = SKIP_SHARE * max(float(np.linalg.norm(v.max(axis=0) - v.min(axis=0))),
                                     1e-30)
        self.coverage = None
        cut = (None if coverage is None
               else np.asarray(coverage.cutout, dtype=bool))  # type: ignore[attr-defined]
        if cut is not None and cut.shape != (len(t),):
            raise ValueError(f"coverage.cutout must have shape ({len(t)},), got {cut.shape}.")
        if cut is not None and cut.any():
            self.coverage = coverage
            self._cut = cut
            self._cut_ids = np.flatnonzero(cut)
            self._cut_scene = rtcore_scene.EmbreeScene()
            TriangleMesh(scene=self._cut_scene, vertices=v32,
                         indices=np.ascontiguousarray(t[cut], dtype=np.int32))
            self._opaque_scene = None
            if not cut.all():
                self._opaque_scene = rtcore_scene.EmbreeScene()
                TriangleMesh(scene=self._opaque_scene, vertices=v32,
                             indices=np.ascontiguousarray(t[~cut], dtype=np.int32))

    @classmethod
    def from_scene(cls, scene: object, *, chunk_size: int = _DEFAULT_CHUNK) -> RayTracer:
        """A tracer over ``scene.vertices`` and ``scene.triangles`` (a Scene of probegrid.scene),
        with its ``coverage`` (what a ray may pass; None: nothing)."""
        vertices, triangles = scene.vertices, scene.triangles  # type: ignore[attr-defined]
        return cls(vertices, triangles, chunk_size=chunk_size,
                   coverage=getattr(scene, "coverage", None))

    @classmethod
    def shared(cls, scene: object, *, chunk_size: int = _DEFAULT_CHUNK) -> RayTracer:
        """:meth:`from_scene`, reused while the geometry is the same: one BVH per process.

        A bake's stages each hand a worker the scene anew; the tracer of the last geometry seen
        (keyed by a SHA-256 of the vertex and index arrays) is kept, so the BVH is built once
        per worker process, not once per stage.
        """
        vertices, triangles = scene.vertices, scene.triangles  # type: ignore[attr-defined]
        h = hashlib.sha256(np.ascontiguousarray(vertices, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(triangles, dtype=np.int64).tobytes())
        coverage = getattr(scene, "coverage", None)
        key = (h.hexdigest(), chunk_size, None if coverage is None else coverage.key)
        cached = _SHARED.get(key)
        if cached is None:
            _SHARED.clear()
            cached = _SHARED[key] = cls(vertices, triangles, chunk_size=chunk_size,
                                        coverage=coverage)
        return cached

    def __reduce__(self) -> tuple:
        """Pickle as the arrays; the Embree scene is rebuilt on unpickling."""
        return (_rebuild, (self.vertices, self.triangles, self.chunk_size, self.coverage))

    def __repr__(self) -> str:
        return f"RayTracer({len(self.triangles)} triangles, {len(self.vertices)} vertices)"

    # -- argument handling ---------------------------------------------------------------

    def _rays(
        self, origins: ArrayLike, directions: ArrayLike, tmin: ArrayLike, tmax: ArrayLike
    ) -> tuple[tuple[int, ...], NDArray, NDArray, NDArray, NDArray]:
        """Broadcast ray arguments to ``n`` rays.

        Returns the batch shape, origins as ``(1, 3)`` (one shared origin) or ``(n, 3)``,
        directions ``(n, 3)`` C-contiguous float64, and tmin / tmax as 0-d or ``(n,)`` float64
        (shared values are not expanded, so the common cases stay cheap).
        """
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        if o.shape[-1:] != (3,) or d.shape[-1:] != (3,):
            raise ValueError(
                f"origins and directions must have shape (..., 3), got {o.shape} and {d.shape}."
            )
        lo = np.asarray(tmin, dtype=np.float64)
        hi = np.asarray(tmax, dtype=np.float64)
        try:
            shape = np.broadcast_shapes(o.shape[:-1], d.shape[:-1], lo.shape, hi.shape)
        except ValueError:
            raise ValueError(
                f"origins {o.shape}, directions {d.shape}, tmin {lo.shape} and tmax {hi.shape} "
                "do not broadcast together."
            ) from None
        if not (np.isfinite(lo).all() and np.all(lo >= 0)) or np.isnan(hi).any():
            raise ValueError("tmin must be finite and >= 0, and tmax must not be NaN.")
        n = math.prod(shape)
        o = o.reshape(1, 3) if o.size == 3 else np.broadcast_to(o, (*shape, 3)).reshape(n, 3)
        d = np.ascontiguousarray(np.broadcast_to(d, (*shape, 3)).reshape(n, 3))
        lo = lo.reshape(()) if lo.size == 1 else np.broadcast_to(lo, shape).reshape(n)
        hi = hi.reshape(()) if hi.size == 1 else np.broadcast_to(hi, shape).reshape(n)
        return shape, o, d, lo, hi

    def _embree_rays(
        self, o: NDArray, d: NDArray, lo: NDArray, hi: NDArray, s: int, e: int
    ) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
        """float32 origins (shifted to tmin, re-centred), directions and tfar of rays s:e.

        The shift and the re-centring are done in float64, each value rounded to float32 once
        (:func:`probegrid.raytrace.kernels.embree_rays`).
        """
        org, dir32, far, ok = embree_rays(*frozen((
            o if len(o) == 1 else o[s:e], d[s:e],
            lo.reshape(1) if lo.ndim == 0 else lo[s:e],
            hi.reshape(1) if hi.ndim == 0 else hi[s:e], self.centre)))
        if not ok:
            raise ValueError("ray origins and directions must be finite (and within float32).")
        # (tmax = inf stays inf; tmax <= tmin never hits)
        return org, dir32, far

    # -- queries -------------------------------------------------------------------------

    def intersect(
        self,
        origins: ArrayLike,
        directions: ArrayLike,
        *,
        tmin: ArrayLike = 0.0,
        tmax: ArrayLike = np.inf,
        weights: NDArray[np.float64] | None = None,
    ) -> Hits:
        """Closest hit of each ray ``origin + t direction``, ``tmin <= t <= tmax``
        (``weights``, ``(n, 3)`` for the ``n`` rays flattened: multiplied in place by what the
        rays pass, :meth:`intersect_weighted`).

        Parameters
        ----------
        origins, directions : (..., 3) float
            Broadcast against each other (e.g. one origin for many directions).
        tmin : float or (...) float
            Start of the ray segment, >= 0 (offset to step off the surface a ray leaves).
        tmax : float or (...) float
            End of the ray segment (inf by default).

        Returns
        -------
        Hits
            ``prim_id (...) int64`` (-1 = miss), ``t (...) float64`` (inf for a miss),
            ``u, v (...) float64`` barycentrics (0 for a miss).
        """
        shape, o, d, lo, hi = self._rays(origins, directions, tmin, tmax)
        n = len(d)
        prim = np.empty(n, np.int64)
        t = np.empty(n, np.float64)
        u = np.empty(n, np.float64)
        v = np.empty(n, np.float64)
        out = Hits(prim, t, u, v)
        for s in range(0, n, self.chunk_size):  # loop over chunks of rays, not rays
            e = min(s + self.chunk_size, n)
            org, dirs, far = self._embree_rays(o, d, lo, hi, s, e)
            res = self._scene.run(org, dirs, dists=far, output=1)
            embree_hits((res["primID"], res["tfar"], res["u"], res["v"]),
                        lo.reshape(1) if lo.ndim == 0 else lo, s, out)
        if self.coverage is not None:
            self._pass_through(o, d, hi, out, weights)
        return Hits(prim.reshape(shape), t.reshape(shape), u.reshape(shape), v.reshape(shape))

    @property
    def tinted(self) -> bool:
        """Whether a ray that passes a surface may carry a weight other than 1 (a tinted
        transmission: the ``tinted`` flag of :class:`probegrid.scene.coverage.Coverage`): the
        weighted queries (:meth:`intersect_weighted`, :meth:`shadow_weights`,
        :meth:`transmittance` with ``rgb``) then differ from the plain ones."""
        return bool(getattr(self.coverage, "tinted", False))

    def intersect_weighted(self, origins: ArrayLike, directions: ArrayLike, *,
                           tmin: ArrayLike = 0.0, tmax: ArrayLike = np.inf
                           ) -> tuple[Hits, NDArray[np.float64]]:
        """:meth:`intersect`, and the ``(..., 3)`` weight each ray carries to its hit (or
        miss): the product of the coverage's ``pass_weight`` over the surfaces it passed (1
        for none; module docstring of :mod:`probegrid.scene.coverage`)."""
        shape = np.broadcast_shapes(np.shape(origins)[:-1], np.shape(directions)[:-1],
                                    np.shape(tmin), np.shape(tmax))
        weights = np.ones((math.prod(shape), 3))
        hits = self.intersect(origins, directions, tmin=tmin, tmax=tmax, weights=weights)
        return hits, weights.reshape(*shape, 3)

    def _cast(self, scene: object, o: NDArray, d: NDArray, lo: NDArray, hi: NDArray,
              centre: NDArray[np.float64]) -> Hits:
        """Closest hits in ``scene`` (one of this tracer's Embree scenes) of rays ``o + t d``,
        ``lo <= t <= hi`` (``(k, 3)`` and ``(k,)`` float64, in the frame ``centre`` is the
        geometry's centre in), ``chunk_size`` at a time; ``prim_id`` as ``scene`` numbers its
        triangles."""
        n = len(d)
        out = Hits(np.empty(n, np.int64), np.empty(n), np.empty(n), np.empty(n))
        for s in range(0, n, self.chunk_size):  # loop over chunks of rays, not rays
            e = min(s + self.chunk_size, n)
            org, dirs, far, ok = embree_rays(o[s:e], d[s:e], lo[s:e], hi[s:e], centre)
            if not ok:
                raise ValueError("ray origins and directions must be finite (and within "
                                 "float32).")
            res = scene.run(org, dirs, dists=far, output=1)  # type: ignore[attr-defined]
            embree_hits((res["primID"], res["tfar"], res["u"], res["v"]), lo, s, out)
        return out

    def _stops(self, prim: NDArray[np.int64], hits: Hits, rows: NDArray[np.int64],
               o: NDArray, d: NDArray) -> NDArray[np.bool_]:
        """Whether rays ``rows`` stop at their hits on the (cut-out) triangles ``prim``."""
        if getattr(self.coverage, "stochastic", True):
            xi = _uniforms(o[rows] if len(o) > 1 else np.broadcast_to(o, (len(rows), 3)),
                           d[rows], prim)
        else:  # (every p is 0 or 1: no draw)
            xi = np.zeros(len(prim))
        stops = self.coverage.stops  # type: ignore[union-attr]
        return np.asarray(stops(prim, hits.u[rows], hits.v[rows], xi), dtype=bool)

    def _pass_through(self, o: NDArray, d: NDArray, hi: NDArray, out: Hits,
                      weights: NDArray[np.float64] | None = None) -> None:
        """Carry the closest hits ``out`` (of rays ``o + t d``, ``t <= hi``) past the cut-out
        surfaces the rays pass (module docstring), in place; ``weights (n, 3)`` multiplied by
        the weights of the surfaces passed."""
        n = len(d)
        his = np.broadcast_to(hi, (n,))
        cut = self._cut
        active = np.flatnonzero(out.prim_id >= 0)
        active = active[cut[out.prim_id[active]]]
        for _ in range(MAX_LAYERS):  # loop over layers of cut-out surfaces, not rays
            if not active.size:
                return
            go = active[~self._stops(out.prim_id[active], out, active, o, d)]
            if not go.size:
                return
            if weights is not None:
                weights[go] *= self.coverage.pass_weight(  # type: ignore[union-attr]
                    out.prim_id[go], out.u[go], out.v[go])
            og = o if len(o) == 1 else o[go]
            dg = d[go]
            lo = out.t[go] + self.skip / np.linalg.norm(dg, axis=1)
            again = self._cast(self._scene, np.ascontiguousarray(np.broadcast_to(og, dg.shape)),
                               dg, lo, np.ascontiguousarray(his[go]), self.centre)
            for a, b in zip(out, again):
                a[go] = b
            active = go[again.prim_id >= 0]
            active = active[cut[out.prim_id[active]]]

    def _occluded_embree(self, org: NDArray[np.float32], dirs: NDArray[np.float32],
                         far: NDArray[np.float32], weights: NDArray[np.float64] | None = None
                         ) -> NDArray[np.bool_]:
        """Occlusion of rays as Embree takes them, through the surfaces they may pass (module
        docstring): the opaque triangles' any-hit query, then the cut-out triangles nearest
        first (``weights (n, 3)`` multiplied by the weights of the surfaces passed)."""
        n = len(far)
        if self._opaque_scene is not None:
            blocked = self._opaque_scene.run(org, dirs, dists=far, query="OCCLUDED") >= 0
        else:
            blocked = np.zeros(n, dtype=bool)
        rows = np.flatnonzero(~blocked & (far > 0))
        if not rows.size:
            return blocked
        o = org[rows].astype(np.float64)
        d = dirs[rows].astype(np.float64)
        hi = far[rows].astype(np.float64)
        lo = np.zeros(len(rows))
        zero = np.zeros(3)
        alive = np.arange(len(rows))
        for _ in range(MAX_LAYERS):  # loop over layers of cut-out surfaces, not rays
            hits = self._cast(self._cut_scene, o[alive], d[alive], lo[alive], hi[alive], zero)
            hit = np.flatnonzero(hits.prim_id >= 0)
            if not hit.size:
                return blocked
            prim = self._cut_ids[hits.prim_id[hit]]
            local = Hits(hits.prim_id, hits.t, hits.u, hits.v)
            stop = self._stops(prim, local, hit, o[alive], d[alive])
            blocked[rows[alive[hit[stop]]]] = True
            go = hit[~stop]
            if weights is not None and go.size:
                weights[rows[alive[go]]] *= self.coverage.pass_weight(  # type: ignore[union-attr]
                    prim[~stop], hits.u[go], hits.v[go])
            lo[alive[go]] = hits.t[go] + self.skip / np.linalg.norm(d[alive[go]], axis=1)
            alive = alive[go]
            if not alive.size:
                return blocked
        blocked[rows[alive]] = True  # past MAX_LAYERS: stops at the next one (a bound)
        return blocked

    def occluded(
        self,
        origins: ArrayLike,
        directions: ArrayLike,
        tmax: ArrayLike,
        *,
        tmin: ArrayLike = 0.0,
    ) -> NDArray[np.bool_]:
        """Whether anything lies on each segment ``origin + t direction``, ``tmin <= t <= tmax``.

        Embree's any-hit query (faster than :meth:`intersect`). For a shadow ray toward a point
        light at distance ``d`` along a unit direction, pass ``tmax = d`` (minus an epsilon if the
        light sits on a surface) and ``tmin`` = a small offset off the shading point's surface.

        Returns
        -------
        (...) bool
        """
        shape, o, d, lo, hi = self._rays(origins, directions, tmin, tmax)
        n = len(d)
        out = np.empty(n, dtype=bool)
        for s in range(0, n, self.chunk_size):  # loop over chunks of rays, not rays
            e = min(s + self.chunk_size, n)
            org, dirs, far = self._embree_rays(o, d, lo, hi, s, e)
            if self.coverage is not None:
                out[s:e] = self._occluded_embree(org, dirs, far)
                continue
            out[s:e] = self._scene.run(org, dirs, dists=far, query="OCCLUDED") >= 0
        return out.reshape(shape)

    def occluded_rays(self, rays: EmbreeRays, ok: bool = True) -> NDArray[np.bool_]:
        """:meth:`occluded` of rays already as Embree takes them (:class:`EmbreeRays`, from
        this tracer's :attr:`centre`), ``chunk_size`` at a time; ``ok``: the flag their kernel
        returned, False when one is not finite in float32 (refused as :meth:`occluded` refuses
        it). Returns ``(k,) bool``."""
        if not ok:
            raise ValueError("ray origins and directions must be finite (and within float32).")
        org, dirs, far = rays  # (OCCLUDED leaves dists as they are: no copy, as segments_occluded)
        n = len(far)
        if self.coverage is not None:
            return self._occluded_chunks(org, dirs, far)
        if n <= self.chunk_size:  # the common case: one call
            return self._scene.run(org, dirs, dists=far, query="OCCLUDED") >= 0
        out = np.empty(n, dtype=bool)
        for s in range(0, n, self.chunk_size):  # loop over chunks of rays, not rays
            e = min(s + self.chunk_size, n)
            out[s:e] = self._scene.run(org[s:e], dirs[s:e], dists=far[s:e],
                                       query="OCCLUDED") >= 0
        return out

    def shadow_weights(self, rays: EmbreeRays, ok: bool = True) -> NDArray[np.float64]:
        """The ``(k, 3)`` light each shadow ray of :meth:`occluded_rays` lets through: 0 where
        it is occluded, else the product of the weights of the surfaces it passed (one draw
        per surface, as :meth:`occluded_rays`; 1 without a tinted coverage)."""
        if not ok:
            raise ValueError("ray origins and directions must be finite (and within float32).")
        org, dirs, far = rays
        if not self.tinted:
            return np.repeat((~self.occluded_rays(rays, ok)).astype(np.float64)[:, None], 3, 1)
        out = np.ones((len(far), 3))
        for s in range(0, len(far), self.chunk_size):  # loop over chunks of rays, not rays
            e = min(s + self.chunk_size, len(far))
            blocked = self._occluded_embree(org[s:e], dirs[s:e], far[s:e], out[s:e])
            out[s:e][blocked] = 0.0
        return out

    def occluded_weights(self, origins: ArrayLike, directions: ArrayLike, tmax: ArrayLike, *,
                         tmin: ArrayLike = 0.0) -> NDArray[np.float64]:
        """:meth:`shadow_weights` of the segments of :meth:`occluded`, ``(..., 3)``."""
        if not self.tinted:
            free = ~self.occluded(origins, directions, tmax, tmin=tmin)
            return np.repeat(free.astype(np.float64)[..., None], 3, -1)
        shape, o, d, lo, hi = self._rays(origins, directions, tmin, tmax)
        out = np.ones((len(d), 3))
        for s in range(0, len(d), self.chunk_size):  # loop over chunks of rays, not rays
            e = min(s + self.chunk_size, len(d))
            org, dirs, far = self._embree_rays(o, d, lo, hi, s, e)
            blocked = self._occluded_embree(org, dirs, far, out[s:e])
            out[s:e][blocked] = 0.0
        return out.reshape(*shape, 3)

    def transmittance(self, origins: ArrayLike, directions: ArrayLike, tmax: ArrayLike, *,
                      tmin: ArrayLike = 0.0, rgb: bool = False) -> NDArray[np.float64]:
        """The expected share of light that gets through each segment ``origin + t direction``,
        ``tmin <= t <= tmax``: 0 when an opaque triangle lies on it, else the product of
        ``1 - p`` over the surfaces it may pass (``p`` their stop probabilities, module
        docstring; 0 past :data:`MAX_LAYERS` of them). Without a coverage: ``1 - occluded``.
        For a probe's view of a punctual light: one ray would give all or nothing.

        With ``rgb``, ``(..., 3)``: each surface passes ``(1 - p) w`` per channel (its
        ``pass_weight`` ``w``: the light through a tinted pane takes its tint).

        Returns
        -------
        (...) float64 in [0, 1], or (..., 3) with ``rgb``
        """
        if self.coverage is None or (rgb and not self.tinted):
            plain = self.transmittance(origins, directions, tmax, tmin=tmin)
            return np.repeat(plain[..., None], 3, -1) if rgb else plain
        shape, o, d, lo, hi = self._rays(origins, directions, tmin, tmax)
        n = len(d)
        out = np.empty((n, 3) if rgb else n)
        for s in range(0, n, self.chunk_size):  # loop over chunks of rays, not rays
            e = min(s + self.chunk_size, n)
            org, dirs, far = self._embree_rays(o, d, lo, hi, s, e)
            out[s:e] = self._transmittance_embree(org, dirs, far, rgb)
        return out.reshape(*shape, 3) if rgb else out.reshape(shape)

    def _transmittance_embree(self, org: NDArray[np.float32], dirs: NDArray[np.float32],
                              far: NDArray[np.float32], rgb: bool = False
                              ) -> NDArray[np.float64]:
        """:meth:`transmittance` of rays as Embree takes them."""
        n = len(far)
        out = np.ones((n, 3) if rgb else n)
        if self._opaque_scene is not None:
            out[self._opaque_scene.run(org, dirs, dists=far, query="OCCLUDED") >= 0] = 0.0
        rows = np.flatnonzero((out.reshape(n, -1)[:, 0] > 0) & (far > 0))
        o = org[rows].astype(np.float64)
        d = dirs[rows].astype(np.float64)
        hi = far[rows].astype(np.float64)
        lo = np.zeros(len(rows))
        zero = np.zeros(3)
        alive = np.arange(len(rows))
        for _ in range(MAX_LAYERS):  # loop over layers of cut-out surfaces, not rays
            if not alive.size:
                return out
            hits = self._cast(self._cut_scene, o[alive], d[alive], lo[alive], hi[alive], zero)
            hit = np.flatnonzero(hits.prim_id >= 0)
            prim = self._cut_ids[hits.prim_id[hit]]
            p = self.coverage.stop_probability(  # type: ignore[union-attr]
                prim, hits.u[hit], hits.v[hit])
            if rgb:
                out[rows[alive[hit]]] *= (1.0 - p)[:, None] * self.coverage.pass_weight(
                    prim, hits.u[hit], hits.v[hit])  # type: ignore[union-attr]
            else:
                out[rows[alive[hit]]] *= 1.0 - p
            go = hit[p < 1.0]
            lo[alive[go]] = hits.t[go] + self.skip / np.linalg.norm(d[alive[go]], axis=1)
            alive = alive[go]
        out[rows[alive]] = 0.0  # past MAX_LAYERS (a bound)
        return out

    def _occluded_chunks(self, org: NDArray[np.float32], dirs: NDArray[np.float32],
                         far: NDArray[np.float32]) -> NDArray[np.bool_]:
        """:meth:`_occluded_embree`, ``chunk_size`` rays at a time."""
        out = np.empty(len(far), dtype=bool)
        for s in range(0, len(far), self.chunk_size):  # loop over chunks of rays, not rays
            e = min(s + self.chunk_size, len(far))
            out[s:e] = self._occluded_embree(org[s:e], dirs[s:e], far[s:e])
        return out

    def segments_occluded(
        self, starts: ArrayLike, ends: ArrayLike, *, margin: float = 0.0
    ) -> NDArray[np.bool_]:
        """Whether any triangle lies on each segment ``starts[k] -> ends[k]`` (visibility).

        The lean any-hit query of a probe field's exact visibility test (a few segments per
        point, microseconds each): the segments are re-centred and rounded to float32 in one
        compiled loop (:func:`probegrid.raytrace.kernels.segment_rays`; float64 first, as
        :meth:`occluded` does) and handed to Embree's ``OCCLUDED`` query directly,
        ``chunk_size`` at a time.

        Parameters
        ----------
        starts, ends : (k, 3) float
            Segment end points, finite; ``starts`` may be one point, ``(3,)`` or ``(1, 3)``,
            shared by every segment (a query point and its probes).
        margin : float
            Length (world units, >= 0) left out at *both* ends, so that a point lying on a
            surface, or a probe, does not occlude itself; a segment no longer than ``2 margin``
            is never occluded.

        Returns
        -------
        (k,) bool
        """
        a = np.asarray(starts, dtype=np.float64)
        b = np.asarray(ends, dtype=np.float64)
        if a.ndim == 1:
            a = a.reshape(1, -1)
        if b.ndim != 2 or b.shape[1:] != (3,) or a.shape not in (b.shape, (1, 3)):
            raise ValueError(f"starts and ends must have shape (k, 3) (starts also (3,) or "
                             f"(1, 3)), got {a.shape} and {b.shape}.")
        if not (math.isfinite(margin) and 0 <= margin < 1e30):
            raise ValueError(f"margin must be finite and >= 0, got {margin!r}.")
        org, dirs, far, ok = segment_rays(a, b, float(margin), self.centre)
        if not ok:
            raise ValueError("segment end points must be finite (and within float32).")
        if self.coverage is not None:
            return self._occluded_chunks(org, dirs, far)
        live = far > 0
        if live.all():
            if len(far) <= self.chunk_size:  # the common case: one call
                return self._scene.run(org, dirs, dists=far, query="OCCLUDED") >= 0
            idx = None
        else:
            org, dirs, far, idx = org[live], dirs[live], far[live], np.flatnonzero(live)
        hit = np.empty(len(far), dtype=bool)
        for s in range(0, len(far), self.chunk_size):  # loop over chunks of rays, not rays
            e = min(s + self.chunk_size, len(far))
            hit[s:e] = self._scene.run(org[s:e], dirs[s:e], dists=far[s:e],
                                       query="OCCLUDED") >= 0
        if idx is None:
            return hit
        out = np.zeros(len(b), dtype=bool)
        out[idx] = hit
        return out

    def backface(self, prim_id: ArrayLike, directions: ArrayLike) -> NDArray[np.bool_]:
        """Whether each hit is on the back of its triangle (``dot(normal, direction) > 0``).

        Parameters
        ----------
        prim_id : (...) int
            As returned by :meth:`intersect`; misses (-1) are never back faces.
        directions : (..., 3) float
            The rays' directions (broadcast with ``prim_id``).

        Returns
        -------
        (...) bool
        """
        pid = np.asarray(prim_id)
        if pid.size and not np.issubdtype(pid.dtype, np.integer):
            raise ValueError(f"prim_id must be integers, got dtype {pid.dtype}.")
        d = np.asarray(directions, dtype=np.float64)
        if d.shape[-1:] != (3,):
            raise ValueError(f"directions must have shape (..., 3), got {d.shape}.")
        if pid.size and pid.max(initial=-1) >= len(self.triangles):
            raise ValueError(f"prim_id must be -1 or a triangle index < {len(self.triangles)}.")
        hit = pid >= 0
        n = self.normals[np.where(hit, pid, 0)]
        return hit & (np.einsum("...i,...i->...", n, d) > 0)


#: The process's shared tracer (:meth:`RayTracer.shared`), at most one.
_SHARED: dict[tuple[str, int], RayTracer] = {}


def _rebuild(vertices: NDArray, triangles: NDArray, chunk_size: int,
             coverage: object | None = None) -> RayTracer:
    return RayTracer(vertices, triangles, chunk_size=chunk_size, coverage=coverage)
