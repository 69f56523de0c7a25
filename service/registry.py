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
infinity anywhere) after :func:`probegrid.store.open_store` has checked that every file is a
regular file inside the store (no link followed) with the size and SHA-256 the manifest records,
so the service never answers with a value it would refuse to export, nor with bytes from outside
the store. The arrays and the scene copy are read into memory at open (``load=True``: the
store's size per process, 207 MiB for a 16x8x16 grid of 32^2 faces), not mapped: a file
truncated or rewritten in place under the server can then neither crash it (SIGBUS on a mapped
page that is gone) nor change what it serves behind its back.

A store changed on disk while it is served (a new bake with ``--overwrite`` renames a new
directory into place; a copy lands file by file, manifest first; a file is rewritten in place)
is noticed: at most every :data:`RECHECK_SECONDS` a request looks at the store directory's
entries (``os.scandir``: name, inode, size, modification time of each, no reading); when they
changed, a background thread opens and checks the store as it now is and then swaps it in with
one assignment, so a request is answered whole from the old store or whole from the new one,
never from a mix. A store deleted under the server is served on from memory, and
``/healthz`` says so (:meth:`GridRegistry.problems`). A store that fails its checks (a half-landed copy fails its hashes) is not
served: the old one stays, ``/v1/grids/{grid}`` says why in ``replaced_on_disk``, and the store
is opened again on the next change of its entries, so a copy that completes is picked up.
``content_hash`` (SHA-256 of the served ``manifest.json``, which records every file's hash, the
bake, its settings and creation time) is the served store's content identity: it is in the
``/v1/grids`` bodies, and every response made from the store and kept (``/probes``, the
three.js export) is kept on the :class:`ServedGrid` it was made from, so it goes with it.
"""

from __future__ import annotations

import logging
import os
import re
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from probegrid.errors import StoreError
from probegrid.query import ProbeField
from probegrid.store import ProbeStore, open_store
from probegrid.store.check import check_store
from probegrid.store.manifest import store_name

__all__ = ["RECHECK_SECONDS", "GridRegistry", "ServedGrid", "grid_name"]

#: Seconds between two looks at a served store's directory (see the module docstring).
RECHECK_SECONDS = 1.0
_log = logging.getLogger("probegrid.service")
T = TypeVar("T")


def _signature(path: Path) -> tuple[tuple[object, ...], ...] | None:
    """What identifies the store directory's content on disk without reading it: the
    directory's and each entry's inode, size and modification time (None if it is gone)."""
    try:
        top = os.stat(path)
        with os.scandir(path) as entries:
            rows = []
            for e in entries:
                st = e.stat(follow_symlinks=False)
                rows.append((e.name, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns))
    except OSError:
        return None
    return ((top.st_dev, top.st_ino), *sorted(rows))


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
    signature: tuple[tuple[object, ...], ...] | None = None
    #: The store's scene copy (read and checked at open), None if it keeps none.
    scene: bytes | None = None
    #: Responses made from this store and kept (see :meth:`kept`), by key.
    responses: dict[str, Any] = field(default_factory=dict, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def kept(self, key: str, make: Callable[[], T]) -> T:
        """``make()``, made once per served store and kept with it: a store replaced on disk
        is a new :class:`ServedGrid`, so nothing made from the old one is served for it."""
        done = self.responses.get(key)
        if done is None:
            with self._lock:
                done = self.responses.get(key)
                if done is None:
                    done = self.responses[key] = make()
        return done

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> ServedGrid:
        """Open a store, check it (:func:`~probegrid.store.check.check_store`) and describe it;
        StoreError or ValueError if it cannot be served.

        Every array and the scene copy are read into memory now (see the module docstring):
        the old store is served whole until the registry swaps the new one in, never as a mix
        of old and new files. StoreError too when the directory changed while it was read.
        """
        name = grid_name(path)
        signature = _signature(Path(path))
        store = open_store(path, load=True)
        scene = store.scene_bytes()
        if _signature(Path(path)) != signature:
            raise StoreError(f"{path} changed while it was opened")
        check_store(store)
        field = ProbeField(store)
        for lattice in ("probes", "field"):  # found now, not by the first query
            field.clear_cells(lattice)
        if field.sh_field is not None:
            field._gradient_table("deringed")
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
            "content_hash": store.manifest_sha256,
            "replaced_on_disk": None,
        }
        return cls(name=name, store=store, field=field, summary=summary, signature=signature,
                   scene=scene)


@dataclass(eq=False)
class _Watch:
    """When a grid's store was last looked at on disk, and the reload under way, if any."""

    path: Path
    next_check: float = 0.0
    failed: tuple[tuple[tuple[object, ...], ...] | None, str] | None = None
    gone: bool = False  # the store directory was not there at the last look
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
        watch.gone = signature is None
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
            if _signature(watch.path) != signature:  # still landing: look again on next check
                return
            reason = str(exc).strip().splitlines()[0] if str(exc).strip() else repr(exc)
            watch.failed = (signature, reason)
            old = self._grids[name]
            summary = {**old.summary, "replaced_on_disk": (
                f"the store on disk was replaced by one that cannot be served ({reason}); "
                "still serving the bake opened before")}
            self._grids[name] = ServedGrid(name=old.name, store=old.store, field=old.field,
                                           summary=summary, signature=old.signature,
                                           scene=old.scene, responses=old.responses)
            _log.warning("grid %r: not serving the replaced store: %s", name, reason)
            return
        if new.name != name:  # pragma: no cover - same path, same name
            return
        watch.failed = None
        self._grids[name] = new  # one assignment: requests see the old grid or the new one
        _log.info("grid %r: serving the replaced store (content hash %s)", name,
                  new.summary["content_hash"][:16])

    def problems(self) -> dict[str, str]:
        """Grid name -> why the served copy is not the store on disk: its directory is gone
        (deleted under the server), or it was replaced by a store that cannot be served. Empty
        when every served store is the one on disk. Looks at the disk as requests do (at most
        every :data:`RECHECK_SECONDS`); the copy read into memory is served either way."""
        out: dict[str, str] = {}
        for name, watch in self._watch.items():
            self[name]
            if watch.gone:
                out[name] = ("the store was deleted from disk; serving the copy read into memory "
                             "until a store is back at its path")
            elif watch.failed is not None:
                out[name] = (f"the store on disk was replaced by one that cannot be served "
                             f"({watch.failed[1]}); serving the copy read before")
        return out

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
