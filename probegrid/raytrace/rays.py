"""The records of rays the tracer exchanges: closest hits (:class:`Hits`) and rays already
as Embree takes them (:class:`EmbreeRays`, written by compiled kernels by the one rounding rule
of :func:`probegrid.raytrace.kernels._embree_ray`).

Both are named tuples of arrays, so compiled kernels take and fill them as they are.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

__all__ = ["EmbreeRays", "Hits"]


class Hits(NamedTuple):
    """Closest hits of a batch of rays (see :meth:`RayTracer.intersect`)."""

    prim_id: NDArray[np.int64]
    t: NDArray[np.float64]
    u: NDArray[np.float64]
    v: NDArray[np.float64]


class EmbreeRays(NamedTuple):
    """Rays already as Embree takes them (:meth:`RayTracer.occluded_rays`): written by the
    compiled kernels that make them (:func:`probegrid.raytrace.kernels._embree_ray`, the one
    rounding rule, the same as :meth:`RayTracer.occluded`'s), so no float64 copy is made and
    converted.

    ``origins (k, 3) float32``: ``(origin - tracer.centre) + tmin direction`` in float64,
    rounded once; ``directions (k, 3) float32``; ``lengths (k,) float32``: ``tmax - tmin``
    (inf: no end)."""

    origins: NDArray[np.float32]
    directions: NDArray[np.float32]
    lengths: NDArray[np.float32]
