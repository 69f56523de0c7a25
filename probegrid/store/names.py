"""The file and directory names of a grid store, and nothing else (no import beyond typing).

Defined here, apart from the format's models (:mod:`probegrid.store.manifest`, which re-exports
them), so that a command that only has to recognise a store's directory, as ``probegrid filter``
checking its output location, reads them without loading the manifest models (pydantic).
"""

from __future__ import annotations

from typing import Final

__all__ = [
    "DONE_FILE",
    "MANIFEST_FILE",
    "PARTIAL_SUFFIX",
    "PLAN_FILE",
    "STORE_DIR_SUFFIXES",
    "STORE_SUFFIX",
    "WORK_SUFFIX",
]

MANIFEST_FILE: Final = "manifest.json"


PLAN_FILE: Final = "_bake.json"  # partial directories only


DONE_FILE: Final = "_done.npy"  # partial directories only


PARTIAL_SUFFIX: Final = ".partial"

#: A finished store's directory name ends in this (the one ``.probes`` naming rule).
STORE_SUFFIX: Final = ".probes"
#: A bake's own working directory beside the store (``NAME.probes.work``).
WORK_SUFFIX: Final = ".work"
#: Every directory name a store or a bake of one uses; no other output may be written there.
STORE_DIR_SUFFIXES: Final = (STORE_SUFFIX, STORE_SUFFIX + PARTIAL_SUFFIX,
                             STORE_SUFFIX + WORK_SUFFIX)
