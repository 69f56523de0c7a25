"""The checks of a bake's inputs that need no scene: each done here, once, for every caller.

:func:`check_bake_inputs` refuses, with a one-line error, an output that is not a store name
(``NAME.probes``), a store that exists without ``overwrite``, settings whose specular chain
does not fit the face size, and a scene file that cannot be kept in the store. :func:`bake`
(:mod:`probegrid.bake.driver`) runs it before any work; ``probegrid bake``
(:mod:`probegrid.jobs.bake`) runs it before it starts worker processes or loads the scene, and
prints its errors as they are. Importing this module is cheap (no numba, no Embree).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

from probegrid.store.manifest import check_store_name

if TYPE_CHECKING:
    from probegrid.bake.settings import BakeSettings

__all__ = ["check_bake_inputs"]


def check_bake_inputs(out: str | os.PathLike[str], *, settings: BakeSettings,
                      overwrite: bool = False,
                      scene_file: str | os.PathLike[str] | None = None) -> Path:
    """Refuse a bake into ``out`` that cannot go ahead; returns ``out`` as a Path.

    Raises ValueError for a name that is not ``NAME.probes``, for an existing store without
    ``overwrite`` and for ``settings`` that do not hold together
    (:meth:`~probegrid.bake.settings.BakeSettings.levels`), and
    :class:`~probegrid.errors.StoreError` for a ``scene_file`` that is not a readable glTF file
    (:func:`probegrid.store.writer.keepable_scene`).
    """
    path = check_store_name(out)
    if path.exists() and not overwrite:
        raise ValueError(f"{path} exists; pass --overwrite to replace it")
    settings.levels()
    if scene_file is not None:
        from probegrid.store.writer import keepable_scene

        keepable_scene(scene_file)  # readable glTF, checked before any work
    return path
