"""What a bake adds to its store once every probe is written: deringed SH and the scene.

:func:`write_store_extras` is the one place that writes the store's extras (format 2, see
:mod:`probegrid.store.manifest`); the bake driver calls it just before publishing the store:

``sh_deringed (P, 9, 3) float32``
    Each probe's radiance SH windowed so that its irradiance is non-negative over the whole
    sphere (:func:`probegrid.core.sh.dering.dering`); equal to ``sh`` where that already holds.
``sh_window (P, 3) float32``
    The band factors ``(1, h_1, h_2)`` of each probe's window (``(1, 1, 1)``: not windowed).
``scene_vertices (V, 3) float32``, ``scene_triangles (T, 3) int32``
    The scene's triangle soup, so that queries can test the visibility between a point and the
    surrounding probes exactly (:class:`probegrid.query.ProbeField`). float32 is what Embree
    traces anyway; 12 bytes per vertex and per triangle.

The windows are chosen from the float32 ``sh`` as stored (so "already non-negative" is decided
on the values a reader sees), with :data:`probegrid.core.sh.dering.DEFAULT_MARGIN` of headroom for
the float32 rounding of the deringed coefficients.
"""

from __future__ import annotations

import numpy as np

from probegrid.core.sh.dering import dering
from probegrid.scene import Scene
from probegrid.store import StoreWriter

__all__ = ["write_store_extras"]


def write_store_extras(writer: StoreWriter, scene: Scene) -> None:
    """Add ``sh_deringed``, ``sh_window``, ``scene_vertices`` and ``scene_triangles`` to the
    finished-but-unpublished store of ``writer`` (every probe written); see the module
    docstring. Idempotent: a resumed bake writes the same extras again."""
    raw = np.asarray(writer.array("sh"), dtype=np.float64)
    deringed, window, _ = dering(raw)
    writer.add_extra("sh_deringed", deringed.astype(np.float32),
                     description="radiance SH windowed per probe so that its irradiance is "
                                 "non-negative over the sphere (equal to sh where it was)")
    writer.add_extra("sh_window", window.astype(np.float32),
                     description="band factors (1, h1, h2) of each probe's deringing window")
    writer.add_extra("scene_vertices", np.asarray(scene.vertices, dtype=np.float32),
                     description="scene triangle vertices, world (for exact query visibility)")
    writer.add_extra("scene_triangles", np.asarray(scene.triangles, dtype=np.int32),
                     description="scene triangles: vertex indices into scene_vertices")
