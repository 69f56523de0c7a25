"""Grid stores: manifest models, the memory-mapped reader and the resumable writer.

``manifest`` (the format: names, array declarations, :class:`StoreManifest`), ``reader``
(:func:`open_store`, :class:`ProbeStore`) and ``writer`` (:class:`StoreWriter`, ``create_npy``);
``names``, the store's file and directory names alone; ``hashcache``, the files' verified
SHA-256s kept across processes. The names below are loaded on first use,
so that importing one submodule (``probegrid.store.names``) stays light.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from probegrid._fs import directory_lock as directory_lock
    from probegrid.errors import StoreError as StoreError
    from probegrid.store.manifest import FORMAT_NAME as FORMAT_NAME
    from probegrid.store.manifest import FORMAT_VERSION as FORMAT_VERSION
    from probegrid.store.manifest import SUPPORTED_FORMAT_VERSIONS as SUPPORTED_FORMAT_VERSIONS
    from probegrid.store.manifest import ArrayInfo as ArrayInfo
    from probegrid.store.manifest import ArraySpec as ArraySpec
    from probegrid.store.manifest import BakeInputs as BakeInputs
    from probegrid.store.manifest import EnvironmentInput as EnvironmentInput
    from probegrid.store.manifest import SceneFile as SceneFile
    from probegrid.store.manifest import SceneInput as SceneInput
    from probegrid.store.manifest import StoreManifest as StoreManifest
    from probegrid.store.manifest import partial_path as partial_path
    from probegrid.store.reader import ProbeStore as ProbeStore
    from probegrid.store.reader import open_store as open_store
    from probegrid.store.reader import partial_progress as partial_progress
    from probegrid.store.reader import read_manifest as read_manifest
    from probegrid.store.writer import StoreWriter as StoreWriter
    from probegrid.store.writer import create_npy as create_npy
    from probegrid.store.writer import keepable_scene as keepable_scene

#: name -> module that defines it (loaded on first use)
_PUBLIC: dict[str, str] = {
    "directory_lock": "probegrid._fs",
    "StoreError": "probegrid.errors",
    **dict.fromkeys(("FORMAT_NAME", "FORMAT_VERSION", "SUPPORTED_FORMAT_VERSIONS", "ArrayInfo",
                     "ArraySpec", "BakeInputs", "EnvironmentInput", "SceneFile", "SceneInput",
                     "StoreManifest", "partial_path"), "probegrid.store.manifest"),
    **dict.fromkeys(("ProbeStore", "open_store", "partial_progress", "read_manifest"),
                    "probegrid.store.reader"),
    **dict.fromkeys(("StoreWriter", "create_npy", "keepable_scene"), "probegrid.store.writer"),
}

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "SUPPORTED_FORMAT_VERSIONS",
    "ArrayInfo",
    "ArraySpec",
    "BakeInputs",
    "EnvironmentInput",
    "ProbeStore",
    "SceneFile",
    "SceneInput",
    "StoreError",
    "StoreManifest",
    "StoreWriter",
    "create_npy",
    "directory_lock",
    "keepable_scene",
    "open_store",
    "partial_path",
    "partial_progress",
    "read_manifest",
]


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name]), name)
        globals()[name] = value  # once
        return value
    raise AttributeError(f"module 'probegrid.store' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
