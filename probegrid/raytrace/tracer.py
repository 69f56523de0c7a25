"""The Embree acceleration structure over one triangle soup (:class:`RayTracer`): closest hits,
occlusion of rays and of segments, built once per process.

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

    Attributes
    ----------
    vertices : (V, 3) float64, read-only
    triangles : (T, 3) int64, read-only
    normals : (T, 3) float64, read-only
        Unit geometric normals ``(b - a) x (c - a)``; zero for degenerate triangles.
    centre : (3,) float64, read-only
        The bounding box's centre, on which the float32 geometry and rays are re-centred
        (:class:`EmbreeRays`).
    """

    def __init__(
        self, vertices: ArrayLike, triangles: ArrayLike, *, chunk_size: int = _DEFAULT_CHUNK
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
        TriangleMesh(
            scene=self._scene,
            vertices=np.ascontiguousarray(v - self.centre, dtype=np.float32),
            indices=np.ascontiguousarray(t, dtype=np.int32),
        )

    @classmethod
    def from_scene(cls, scene: object, *, chunk_size: int = _DEFAULT_CHUNK) -> RayTracer:
        """A tracer over ``scene.vertices`` and ``scene.triangles`` (a Scene of probegrid.scene)."""
        vertices, triangles = scene.vertices, scene.triangles  # type: ignore[attr-defined]
        return cls(vertices, triangles, chunk_size=chunk_size)

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
        key = (h.hexdigest(), chunk_size)
        cached = _SHARED.get(key)
        if cached is None:
            _SHARED.clear()
            cached = _SHARED[key] = cls(vertices, triangles, chunk_size=chunk_size)
        return cached

    def __reduce__(self) -> tuple:
        """Pickle as the arrays; the Embree scene is rebuilt on unpickling."""
        return (_rebuild, (self.vertices, self.triangles, self.chunk_size))

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
    ) -> Hits:
        """Closest hit of each ray ``origin + t direction``, ``tmin <= t <= tmax``.

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
        return Hits(prim.reshape(shape), t.reshape(shape), u.reshape(shape), v.reshape(shape))

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
        if n <= self.chunk_size:  # the common case: one call
            return self._scene.run(org, dirs, dists=far, query="OCCLUDED") >= 0
        out = np.empty(n, dtype=bool)
        for s in range(0, n, self.chunk_size):  # loop over chunks of rays, not rays
            e = min(s + self.chunk_size, n)
            out[s:e] = self._scene.run(org[s:e], dirs[s:e], dists=far[s:e],
                                       query="OCCLUDED") >= 0
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


def _rebuild(vertices: NDArray, triangles: NDArray, chunk_size: int) -> RayTracer:
    return RayTracer(vertices, triangles, chunk_size=chunk_size)
