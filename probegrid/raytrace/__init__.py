"""Batched ray casting against a triangle soup through Embree (the ``embreex`` binding).

:mod:`~probegrid.raytrace.tracer` is the only module of the project that imports ``embreex``;
no ray tracer of our own. The package holds the tracer (:class:`RayTracer`), the records of
rays it exchanges (:mod:`~probegrid.raytrace.rays`: :class:`Hits`, :class:`EmbreeRays`) and
its compiled conversions of rays to Embree's float32 (:mod:`~probegrid.raytrace.kernels`).

Conventions
-----------
* Rays are ``origin + t * direction`` for ``t in [tmin, tmax]``. Directions need not be unit
  length; ``t`` is measured in units of the given direction's length (so it is a distance when
  directions are unit vectors).
* ``prim_id`` is the triangle's row in the ``triangles`` array, ``-1`` for a miss (then
  ``t = inf`` and ``u = v = 0``).
* Barycentrics: the hit point is ``(1 - u - v) a + u b + v c`` for triangle ``(a, b, c)``
  (Embree's convention), matching :meth:`probegrid.scene.Scene.surface_at`.
* Back face: a hit is on the back of its triangle when the ray travels along the geometric
  normal ``(b - a) x (c - a)``, i.e. ``dot(normal, direction) > 0`` (the winding rule of
  :mod:`probegrid.scene`). Embree itself reports both sides (no culling).

Precision
---------
Embree works in float32. As trimesh's ``ray_pyembree`` does, the float64 geometry is re-centred
on its bounding-box centre before the cast, and ray origins get the same shift in float64, so the
float32 error is relative to the scene's extent, not to its distance from the world origin.
``tmin`` is applied by moving the origin to ``origin + tmin * direction`` in float64 (embreex
fixes Embree's ``tnear`` at 0) and adding ``tmin`` back to ``t``.

Batches and processes
---------------------
Any number of rays per call; they are passed to Embree in chunks of ``chunk_size`` to bound the
temporary float32 buffers. An Embree scene cannot be pickled, so a :class:`RayTracer` pickles as
its arrays and rebuilds its acceleration structure where it is unpickled: one per worker
process.

Reference: Wald et al., "Embree: A Kernel Framework for Efficient CPU Ray Tracing", ACM TOG 33(4),
2014; embreex ``EmbreeScene.run`` (query ``INTERSECT`` with ``output=1`` returns ``primID``,
``u``, ``v``, ``tfar``; ``OCCLUDED`` returns the geometry id, -1 when unoccluded).
"""

from probegrid.raytrace.rays import EmbreeRays, Hits
from probegrid.raytrace.tracer import RayTracer

__all__ = ["EmbreeRays", "Hits", "RayTracer"]
