"""The grids a service instance serves: stores opened once at start-up, looked up by name.

A grid's *name* is its store directory's name without the ``.probes`` suffix
(``/data/atrium.probes`` is served as ``atrium``). Names are fixed when the app is built; a request
names a grid, it never names a file: the name is only a key of this registry, so nothing a client
sends becomes a path.

Each :class:`ServedGrid` keeps the open :class:`probegrid.store.ProbeStore` (read-only memory maps,
shared between worker processes through the page cache), its :class:`probegrid.query.ProbeField`
and the JSON-ready summary the ``/v1/grids`` routes return.

A store is checked when it is opened as ``probegrid export`` checks it
(:func:`probegrid.store.check.check_store`: manifest, array shapes, specular levels, no NaN or
infinity anywhere), so the service never answers with a value it would refuse to export.

A store replaced on disk while it is served (a new bake with ``--overwrite`` renames a new
directory into place) is noticed: at most every :data:`RECHECK_SECONDS` a request looks at the
store's ``manifest.json`` (device, inode, size, modification time); when it changed, a
background thread opens and checks the new store and then swaps it in with one assignment, so
a request is answered whole from the old store or whole from the new one, never from a mix.
A new store that fails its checks is not served (the old one stays, and ``/v1/grids/{grid}``
says why in ``replaced_on_disk``). ``content_hash`` (SHA-256 of the served ``manifest.json``,
which names the bake, its settings and creation time) says which bake is served; it is in the
``/v1/grids`` bodies and so in their ETags.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from probegrid.errors import StoreError
from probegrid.query import ProbeField
from probegrid.store import ProbeStore, open_store
from probegrid.store.check import check_store
from probegrid.store.manifest import store_name

__all__ = ["RECHECK_SECONDS", "GridRegistry", "ServedGrid", "grid_name"]

#: Seconds between two looks at a served store's ``manifest.json`` (see the module docstring).
RECHECK_SECONDS = 1.0
_log = logging.getLogger("probegrid.service")


def _signature(path: Path) -> tuple[int, ...] | None:
    """What identifies the store directory's manifest file on disk (None if it is gone)."""
    try:
        st = os.stat(path / "manifest.json")
    except OSError:
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)

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
    signature: tuple[int, ...] | None = None

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> ServedGrid:
        """Open a store, check it (:func:`~probegrid.store.check.check_store`) and describe it;
        StoreError or ValueError if it cannot be served.

        Every array is memory-mapped now, not on first use: a store replaced on disk is served
        whole from the old files, whose mappings stay valid, until the registry swaps the new
        one in (see the module docstring), never as a mix of old and new arrays.
        """
        name = grid_name(path)
        signature = _signature(Path(path))
        store = open_store(path)
        try:
            manifest_bytes = (Path(path) / "manifest.json").read_bytes()
        except OSError as exc:
            raise StoreError(f"{path}: cannot read manifest.json: {exc.strerror}") from None
        for array_name in store.names:
            store.arrays[array_name]
        check_store(store)
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
            "content_hash": hashlib.sha256(manifest_bytes).hexdigest(),
            "replaced_on_disk": None,
        }
        return cls(name=name, store=store, field=field, summary=summary, signature=signature)


@dataclass(eq=False)
class _Watch:
    """When a grid's store was last looked at on disk, and the reload under way, if any."""

    path: Path
    next_check: float = 0.0
    failed: tuple[tuple[int, ...] | None, str] | None = None
    reloading: threading.Thread | None = None
    lock: threading.Lock = field(default_factory=threading.Lock)


class GridRegistry(Mapping[str, ServedGrid]):
    """Name -> :class:`ServedGrid`; the names are fixed at construction, the grid behind a name
    is swapped for the new store when its directory is replaced on disk (module docstring)."""

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
        self._watch = {g.name: _Watch(Path(g.store.path)) for g in grids}

    @classmethod
    def open(cls, paths: Sequence[str | os.PathLike[str]]) -> GridRegistry:
        """Open every store; the first unservable one raises StoreError or ValueError."""
        return cls([ServedGrid.open(p) for p in paths])

    def __getitem__(self, name: str) -> ServedGrid:
        grid = self._grids[name]
        watch = self._watch[name]
        now = time.monotonic()
        if now >= watch.next_check:
            watch.next_check = now + RECHECK_SECONDS
            self._check(name, grid, watch)
        return self._grids[name]

    def _check(self, name: str, grid: ServedGrid, watch: _Watch) -> None:
        """Start a reload when the store's manifest on disk is not the served one."""
        signature = _signature(watch.path)
        if signature is None or signature == grid.signature:
            return
        if watch.failed is not None and watch.failed[0] == signature:
            return  # this replacement was refused already
        with watch.lock:
            if watch.reloading is not None and watch.reloading.is_alive():
                return
            watch.reloading = threading.Thread(target=self._reload, args=(name, watch),
                                               name=f"probegrid-reload-{name}", daemon=True)
            watch.reloading.start()

    def _reload(self, name: str, watch: _Watch) -> None:
        """Open and check the store now at the grid's path; swap it in, or say why not."""
        signature = _signature(watch.path)
        try:
            new = ServedGrid.open(watch.path)
        except (StoreError, ValueError, OSError) as exc:
            reason = str(exc).strip().splitlines()[0] if str(exc).strip() else repr(exc)
            watch.failed = (signature, reason)
            old = self._grids[name]
            summary = {**old.summary, "replaced_on_disk": (
                f"the store on disk was replaced by one that cannot be served ({reason}); "
                "still serving the bake opened before")}
            self._grids[name] = ServedGrid(name=old.name, store=old.store, field=old.field,
                                           summary=summary, signature=old.signature)
            _log.warning("grid %r: not serving the replaced store: %s", name, reason)
            return
        if new.name != name:  # pragma: no cover - same path, same name
            return
        watch.failed = None
        self._grids[name] = new  # one assignment: requests see the old grid or the new one
        _log.info("grid %r: serving the replaced store (content hash %s)", name,
                  new.summary["content_hash"][:16])

    def wait_for_reloads(self, timeout: float = 30.0) -> None:
        """Look at every store on disk now and wait for the reloads this starts (for tests and
        tools; requests never wait)."""
        for name, watch in self._watch.items():
            watch.next_check = 0.0
            self[name]
            thread = watch.reloading
            if thread is not None:
                thread.join(timeout)

    def __iter__(self) -> Iterator[str]:
        return iter(self._grids)

    def __len__(self) -> int:
        return len(self._grids)
