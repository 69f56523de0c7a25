"""A versioned per-user cache of computed arrays (the DFG table, the bake's probe filter), under
the XDG cache directory.

Some arrays are identical on every run -- the split-sum DFG table depends only on its size and
quadrature, the bake's per-probe filter matrix only on the face sizes and level count -- so they
are computed once per machine and read back afterwards. Files live in
``$XDG_CACHE_HOME/probegrid/v1/`` (``~/.cache/probegrid/v1/`` when the variable is unset), named
by what computed them and a hash of every argument, the cache format version and numpy's
version (:func:`cached_array`). A cached array holds exactly the bits the computation returned
(``.npy``, no conversion), is written through a temporary file and ``os.replace`` (never
half-written), and is checked on reading (dtype, shape, finite); a file that fails the check,
cannot be read or cannot be written is recomputed silently, so the cache never changes a result
and never makes a run fail. Delete the directory to clear it.

To fill the cache ahead of time (e.g. in a container image)::

    python -m probegrid.usercache            # the filter's default 128^2 DFG table
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from probegrid._fs import CACHE_ENV, user_cache_root

__all__ = ["CACHE_ENV", "CACHE_VERSION", "cache_dir", "cached_array", "dfg_lut",
           "probe_filter_matrix"]

#: Bumped when the layout of the cache or any cached computation changes.
CACHE_VERSION = 1



def cache_dir() -> Path:
    """``$PROBEGRID_CACHE_DIR/v<CACHE_VERSION>`` when that is set, else
    ``$XDG_CACHE_HOME/probegrid/v<CACHE_VERSION>`` (``~/.cache`` when unset or relative):
    :func:`probegrid._fs.user_cache_root`."""
    return user_cache_root() / f"v{CACHE_VERSION}"


def cached_array(name: str, key: dict[str, object], compute: Callable[[], NDArray],
                 *, dtype: np.dtype | type, shape: tuple[int, ...],
                 mapped: bool = False) -> NDArray:
    """The array ``compute()`` returns, read from the cache when an equal key was stored.

    Parameters
    ----------
    name : str
        What computes it (part of the file name).
    key : dict
        Every argument the result depends on (JSON-serialisable).
    compute : callable
        Returns the array (of ``dtype`` and ``shape``).
    dtype, shape
        What a valid cached file must hold.
    mapped : bool
        Memory-map the cached file instead of reading it (large arrays: no copy, and the
        processes of one machine share its pages).

    Returns
    -------
    ndarray
        Read-only when it came from the cache or was just stored.
    """
    full = {"name": name, "cache": CACHE_VERSION, "numpy": np.__version__, **key}
    digest = hashlib.sha256(json.dumps(full, sort_keys=True).encode()).hexdigest()[:20]
    path = cache_dir() / f"{name}-{digest}.npy"
    try:
        arr = np.load(path, allow_pickle=False, mmap_mode="r" if mapped else None)
        arr = arr.view(np.ndarray)  # (a memmap's pages, as a plain array)
        if arr.dtype == np.dtype(dtype) and arr.shape == shape and np.all(np.isfinite(arr)):
            arr.setflags(write=False)
            return arr
    except (OSError, ValueError, EOFError):
        pass
    arr = compute()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
        with open(tmp, "wb") as fh:
            np.save(fh, arr, allow_pickle=False)
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only or full cache directory: the result is still returned
    return arr


def dfg_lut(size: int = 128, *, samples: int = 64) -> NDArray[np.float32]:
    """:func:`probegrid.core.dfg.dfg_lut` through the cache (the same bits; ~1 s saved per run)."""
    from probegrid.core import dfg

    return cached_array("dfg_lut", {"size": int(size), "samples": int(samples),
                                    "algorithm": "probegrid.dfg.dfg_lut v1"},
                        lambda: dfg.dfg_lut(size, samples=samples),
                        dtype=np.float32, shape=(int(size), int(size), 2))


@lru_cache(maxsize=2)
def probe_filter_matrix(n: int, diffuse_size: int, levels: int) -> NDArray[np.float32]:
    """:func:`probegrid.core.probefilter.filter_matrix`'s matrix through the cache (the same
    bits; about 1 s saved per bake worker at faces 32), memory-mapped (read-only; the workers of
    a machine share its pages) and kept per process."""
    from probegrid.core import probefilter

    shape = probefilter.filter_matrix_shape(n, diffuse_size, levels)
    return cached_array("probe_filter", {"n": int(n), "diffuse_size": int(diffuse_size),
                                         "levels": int(levels),
                                         "version": probefilter.MATRIX_VERSION},
                        lambda: probefilter.filter_matrix(n, diffuse_size, levels)[0],
                        dtype=np.float32, shape=shape, mapped=True)


if __name__ == "__main__":  # pragma: no cover - a convenience command
    for s in (128,):
        dfg_lut(s)
    print(f"filled {cache_dir()}")
