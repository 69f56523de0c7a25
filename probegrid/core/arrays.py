"""Small array helpers the numerical modules share.

:func:`sum_rows` adds up rows of values by an index (the per-channel ``np.bincount`` that
gathers shadow-ray contributions onto their shading points, rays onto their parent hits or
texels onto blocks): float64 sums in the values' order, so the bits do not depend on how the
work was split.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["sum_rows"]


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
