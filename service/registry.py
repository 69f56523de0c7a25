"""The grids a service instance serves: stores opened once at start-up, looked up by name.

A grid's *name* is its store directory's name without the ``.probes`` suffix
(``/data/atrium.probes`` is served as ``atrium``). Names are fixed when the app is built; a request
names a grid, it never names a file: the name is only a key of this registry, so nothing a client
sends becomes a path.

Each :class:`ServedGrid` keeps the open :class:`probegrid.store.ProbeStore` (read-only memory maps,
shared between worker processes through the page cache), its :class:`probegrid.core.ddgi.ProbeField`
and the JSON-ready summary the ``/v1/grids`` routes return.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from probegrid.query import ProbeField
from probegrid.store import ProbeStore, open_store
from probegrid.store.manifest import store_name

__all__ = ["GridRegistry", "ServedGrid", "grid_name"]

_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


def grid_name(path: str | os.PathLike[str]) -> str:
    """The name a store is served under: its directory name without ``.probes``.

    Raises ValueError when that name is empty or has characters other than letters, digits,
    ``.``, ``_`` and ``-`` (at most 128, starting with a letter or digit).
    """
    name = Path(path).name
    name = store_name(name)
    if not _NAME_RE.match(name):
        raise ValueError(
            f"cannot serve {str(path)!r}: a grid name must be 1-128 letters, digits, '.', '_' or "
            f"'-' starting with a letter or digit, got {name!r}."
        )
    return name


@dataclass(frozen=True, eq=False)
class ServedGrid:
    """One served grid.

    Attributes
    ----------
    name : str
    store : ProbeStore
    field : ProbeField
    summary : dict
        JSON-ready description (see :class:`service.schemas.GridSummary`).
    """

    name: str
    store: ProbeStore
    field: ProbeField
    summary: dict[str, Any]

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> ServedGrid:
        """Open a store and describe it; StoreError or ValueError if it cannot be served.

        Every array is memory-mapped now, not on first use: a store replaced on disk while the
        service runs (a new bake with ``--overwrite`` renames a new directory into place) is
        still served whole from the old files, whose mappings stay valid, never as a mix of
        old and new arrays. Serving the new store takes a restart.
        """
        name = grid_name(path)
        store = open_store(path)
        for array_name in store.names:
            store.arrays[array_name]
        field = ProbeField(store)
        arrays = store.manifest.arrays
        valid = int(np.count_nonzero(store.arrays["valid"])) if "valid" in arrays else None
        grid = store.grid
        sizes = {
            kind: [field.map_size(kind, k) for k in range(field.map_levels(kind))]
            for kind in field.kinds
        }
        summary = {
            "name": name,
            "counts": list(grid.counts),
            "bounds_min": list(grid.bounds_min),
            "bounds_max": list(grid.bounds_max),
            "spacing": grid.spacing.tolist(),
            "probes": grid.n_probes,
            "valid_probes": grid.n_probes if valid is None else valid,
            "kinds": list(field.kinds),
            "map_sizes": sizes,
            "specular_levels": field.specular_levels,
            "visibility": "moments" in arrays,
            "scene_hash": store.manifest.scene_hash,
            "created": store.manifest.created.isoformat(),
        }
        return cls(name=name, store=store, field=field, summary=summary)


class GridRegistry(Mapping[str, ServedGrid]):
    """Name -> :class:`ServedGrid`, immutable after construction."""

    def __init__(self, grids: Sequence[ServedGrid]) -> None:
        by_name: dict[str, ServedGrid] = {}
        for g in grids:
            if g.name in by_name:
                raise ValueError(
                    f"two stores would be served as {g.name!r} ({by_name[g.name].store.path} and "
                    f"{g.store.path}); rename one of the directories."
                )
            by_name[g.name] = g
        self._grids = by_name

    @classmethod
    def open(cls, paths: Sequence[str | os.PathLike[str]]) -> GridRegistry:
        """Open every store; the first unservable one raises StoreError or ValueError."""
        return cls([ServedGrid.open(p) for p in paths])

    def __getitem__(self, name: str) -> ServedGrid:
        return self._grids[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._grids)

    def __len__(self) -> int:
        return len(self._grids)
