"""Small array helpers the numerical modules share.

:func:`sum_rows` adds up rows of values by an index (the per-channel ``np.bincount`` that
gathers shadow-ray contributions onto their shading points, rays onto their parent hits or
texels onto blocks): float64 sums in the values' order, so the bits do not depend on how the
work was split. :func:`one_blas_thread` limits BLAS to one thread for a block of small
products (threads would only spin).
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from threadpoolctl import ThreadpoolController

__all__ = ["one_blas_thread", "sum_rows"]


@lru_cache(maxsize=1)
def _controller() -> ThreadpoolController:
    """The process's thread pools, found once (each ``threadpool_limits`` call scans the loaded
    libraries again: about 1.5 ms)."""
    return ThreadpoolController()


def one_blas_thread() -> AbstractContextManager[Any]:
    """A context in which BLAS uses one thread (``threadpool_limits(1, "blas")``; the pools
    of the libraries loaded when first called, numpy's BLAS among them)."""
    return _controller().limit(limits=1, user_api="blas")


def sum_rows(index: ArrayLike, values: ArrayLike, n: int) -> NDArray[np.float64]:
    """``out[i] = sum of values[k] over k with index[k] == i``.

    Parameters
    ----------
    index : (k,) int, in ``[0, n)``
    values : (k, C) float
    n : int
        Rows of the result.

    Returns
    -------
    (n, C) float64
    """
    v = np.asarray(values)
    out = np.empty((int(n), v.shape[1]))
    for c in range(v.shape[1]):  # per column: one bincount each
        out[:, c] = np.bincount(index, weights=v[:, c], minlength=int(n))
    return out
