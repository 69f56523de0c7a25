"""Checks that a grid store holds what its readers need, beyond :func:`open_store`'s.

:func:`open_store` checks the manifest's schema and each array file's header and size.
:func:`map_arrays` checks what ``probegrid export`` and the service read: the ``sh`` ``(9, 3)``
and ``diffuse`` ``(6, n, n, 3)`` arrays present, every map array ``(6, n, n, 3)`` per probe, and
the specular levels exactly ``specular_0 .. specular_<n-1>`` halving in size (level ``k`` has
roughness ``k / (n - 1)``, so a gap would mislabel every level). :func:`nonfinite_counts`
counts NaN and infinities per floating-point array, reading the memory maps in bounded chunks;
:func:`check_store` runs both and raises :class:`~probegrid.errors.StoreError` (one line) on
any failure: the service calls it when it opens a store, so it never answers with a NaN.
"""

from __future__ import annotations

import re
from collections.abc import Iterable

import numpy as np

from probegrid.errors import StoreError
from probegrid.store.reader import ProbeStore

__all__ = ["check_store", "map_arrays", "nonfinite_counts", "specular_levels"]

_SPECULAR_RE = re.compile(r"^specular_(0|[1-9][0-9]*)$")
#: Bytes of an array read at once by :func:`nonfinite_counts`.
CHUNK_BYTES = 64 * 2**20


def specular_levels(store: ProbeStore) -> list[int]:
    """The levels ``0 .. n-1`` of the store's ``specular_<k>`` arrays (``[]`` if none).

    Raises ``StoreError`` unless they are exactly ``specular_0 .. specular_<n-1>``, each
    ``(P, 6, s_k, s_k, 3)`` with ``s_k = s_0 >> k``.
    """
    names = [n for n in store.names if n.startswith("specular_")]
    bad = [n for n in names if not _SPECULAR_RE.match(n)]
    if bad:
        raise StoreError(f"{store.path}: array {bad[0]!r} is not a specular level "
                         "(specular_<k>); the store is damaged")
    levels = sorted(int(n.removeprefix("specular_")) for n in names)
    if levels != list(range(len(levels))):
        raise StoreError(f"{store.path}: specular levels {levels} are not 0..{len(levels) - 1} "
                         "(level k has roughness k/(levels-1)); the store is damaged")
    if levels:
        s0 = _cube_size(store, "specular_0")
        for k in levels[1:]:
            s = s0 >> k
            _check_shape(store, f"specular_{k}", (6, s, s, 3) if s >= 1 else
                         f"no such level (level 0 is {s0}^2: at most {s0.bit_length()} levels)")
    return levels


def _check_shape(store: ProbeStore, name: str, want: tuple[int, ...] | str) -> None:
    """StoreError unless array ``name`` has per-probe shape ``want`` (a str: never right, the
    words say what was expected)."""
    shape = tuple(store.manifest.arrays[name].shape[1:])
    if shape != want:
        raise StoreError(f"{store.path}: array {name!r} has per-probe shape {shape}, expected "
                         f"{want}; the store is damaged")


def _cube_size(store: ProbeStore, name: str) -> int:
    """Face size ``n`` of array ``name``; StoreError unless it holds ``(6, n, n, 3)`` per probe."""
    shape = tuple(store.manifest.arrays[name].shape[1:])
    n = shape[1] if len(shape) == 4 else 0
    _check_shape(store, name, (6, n, n, 3) if n else "(6, n, n, 3)")
    return n


def map_arrays(store: ProbeStore) -> list[tuple[str, str, int | None]]:
    """``(array, kind, specular level)`` of every map export writes, after checking that the
    store has them in the shapes it needs (``sh`` and ``diffuse`` are required)."""
    missing = [n for n in ("sh", "diffuse") if n not in store.names]
    if missing:
        raise StoreError(f"{store.path} has no {' or '.join(repr(n) for n in missing)} array; "
                         "export needs both (the store is damaged or not a baked store)")
    _check_shape(store, "sh", (9, 3))
    maps: list[tuple[str, str, int | None]] = [("diffuse", "diffuse", None)]
    maps += [(f"specular_{k}", "specular", k) for k in specular_levels(store)]
    if "incoming" in store.names:
        maps.append(("incoming", "incoming", None))
    for name, _, _ in maps:
        _cube_size(store, name)
    if "positions" in store.names:
        _check_shape(store, "positions", (3,))
    return maps


def nonfinite_counts(store: ProbeStore, names: Iterable[str] | None = None) -> dict[str, int]:
    """Number of NaN and infinite values of each floating-point array (all by default) that
    has any; read in chunks of about :data:`CHUNK_BYTES`."""
    counts: dict[str, int] = {}
    for name in store.names if names is None else names:
        a = store[name]
        if not np.issubdtype(a.dtype, np.floating) or a.size == 0:
            continue
        per_probe = max(1, a.nbytes // max(1, a.shape[0]))
        step = max(1, CHUNK_BYTES // per_probe)
        bad = 0
        for start in range(0, a.shape[0], step):
            bad += int(a.size // a.shape[0] * min(step, a.shape[0] - start)
                       - np.count_nonzero(np.isfinite(a[start:start + step])))
        if bad:
            counts[name] = bad
    return counts


def check_store(store: ProbeStore) -> None:
    """:func:`map_arrays` and no non-finite value in any array; StoreError (one line) if not."""
    map_arrays(store)
    bad = nonfinite_counts(store)
    if bad:
        where = ", ".join(f"{count} in {name!r}" for name, count in bad.items())
        raise StoreError(f"{store.path} holds non-finite values (NaN or inf): {where}; the "
                         "store is damaged")
