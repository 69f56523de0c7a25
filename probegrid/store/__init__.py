"""Grid stores: manifest models, the memory-mapped reader and the resumable writer.

``manifest`` (the format: names, array declarations, :class:`StoreManifest`), ``reader``
(:func:`open_store`, :class:`ProbeStore`) and ``writer`` (:class:`StoreWriter`, ``create_npy``).
"""

from probegrid._fs import directory_lock
from probegrid.errors import StoreError
from probegrid.store.manifest import (
    FORMAT_NAME,
    FORMAT_VERSION,
    SUPPORTED_FORMAT_VERSIONS,
    ArrayInfo,
    ArraySpec,
    BakeInputs,
    EnvironmentInput,
    SceneFile,
    SceneInput,
    StoreManifest,
    partial_path,
)
from probegrid.store.reader import ProbeStore, open_store, partial_progress, read_manifest
from probegrid.store.writer import StoreWriter, create_npy, keepable_scene

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
