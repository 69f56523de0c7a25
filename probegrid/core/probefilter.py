"""A bake's per-probe filters as one cached matrix: the exact diffuse map and GGX chain.

Every probe of a bake goes through the same linear filters at the same face size ``n``:

* the diffuse map (irradiance / pi, :mod:`probegrid.core.diffuse`): ``out[n_o] = sum_q max(0, n_o . w_q)
  / pi L_q dOmega_q``, exactly :func:`probegrid.core.diffuse.diffuse_exact`;
* GGX level ``k >= 1`` of the specular chain (:mod:`probegrid.core.specular`, face ``n >> k``,
  perceptual roughness ``k / (levels - 1)``, ``alpha = r^2``): ``out[R] = sum_q K(R . w_q) L_q
  dOmega_q / sum_q K(R . w_q) dOmega_q`` with ``K`` = :func:`probegrid.core.lobes.ggx_kernel`, exactly
  :func:`probegrid.core.specular.reference_convolution` (``ggx_prefilter(method="exact")``). Level 0 is
  the cube itself.

Both are sums over every input texel ``q`` (centre ``w_q``, exact solid angle ``dOmega_q``), i.e.
rows of one fixed ``(rows, 6 n^2)`` matrix. For the small faces of probes it pays to compute that
matrix once per process (float64, each row's GGX weights normalised in float64, then rounded to
float32; read-only, ``lru_cache``) and to filter ``G`` probes with one matrix product against their
``(6 n^2, 3 G)`` texels (BLAS sgemm). Measured at ``n = 32`` (8^2 diffuse, 6 levels) on this
project's 2-core machine: about 1 ms per probe in groups of 8, against about 3.7 ms for
:func:`~probegrid.core.diffuse.diffuse_exact` plus the tiered :func:`~probegrid.core.specular.ggx_prefilter`
-- and exact (the references themselves, to float32 rounding of the weights and sums) where the
tiered sum approximates the reference to a few 1e-3. A constant cube comes out constant to float32
rounding (the GGX rows sum to 1).

Memory: ``(6 d^2 + sum_k 6 (n >> k)^2) x 6 n^2 x 4`` bytes: 60 MB at ``n = 32`` with ``d = 8`` and the
full chain, 3.8 MB at 16. Larger faces keep the per-call filters (a 64^2 matrix would take about
1 GB): :func:`supported` says which.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core import lobes
from probegrid.core.arrays import one_blas_thread
from probegrid.core.cubemap import check_cube, mip_sizes, texel_directions, texel_solid_angles

__all__ = ["MATRIX_VERSION", "MAX_FACE", "describe", "filter_cube", "filter_matrix",
           "filter_matrix_shape", "filter_sizes", "supported"]

#: Largest input face size filtered through the cached matrix.
MAX_FACE = 32

#: Bumped whenever :func:`filter_matrix` would return other bits (keys the per-machine cache).
MATRIX_VERSION = 1

#: Rows of the matrix computed together (bounded float64 temporaries: rows x 6 n^2 x 8 bytes).
_ROWS = 256


def supported(n: int, diffuse_size: int) -> bool:
    """Whether an ``n``-cube with a ``diffuse_size`` diffuse map goes through the matrix."""
    return 1 <= n <= MAX_FACE and 1 <= diffuse_size <= MAX_FACE


def describe(n: int, diffuse_size: int) -> dict[str, str]:
    """How a bake with face size ``n`` filters its probes (for the store's manifest)."""
    if supported(n, diffuse_size):
        how = "exact sum over every incoming texel (one cached float32 matrix, probegrid.core.probefilter)"
        return {"diffuse": how, "specular": how}
    return {"diffuse": "exact sum over every incoming texel (probegrid.core.diffuse.diffuse_exact)",
            "specular": "tiered multi-resolution sum (probegrid.core.specular.ggx_prefilter)"}


def filter_sizes(n: int, diffuse_size: int, levels: int) -> tuple[int, ...]:
    """Face sizes of the matrix's row blocks: ``(diffuse_size, n >> 1, ..., n >> (levels - 1))``
    (the GGX chain's sizes after level 0)."""
    return (int(diffuse_size), *mip_sizes(n, levels)[1:])


def filter_matrix_shape(n: int, diffuse_size: int, levels: int) -> tuple[int, int]:
    """Shape of :func:`filter_matrix`'s matrix: its rows (every output texel, face-major) and
    columns (the ``n``-cube's texels)."""
    return (sum(6 * s * s for s in filter_sizes(n, diffuse_size, levels)), 6 * int(n) * int(n))


@lru_cache(maxsize=2)
def filter_matrix(n: int, diffuse_size: int, levels: int) -> tuple[NDArray[np.float32],
                                                                     tuple[int, ...]]:
    """The diffuse and GGX rows for ``n``-cubes; cached, read-only.

    Returns
    -------
    matrix : (6 d^2 + sum_k 6 s_k^2, 6 n^2) float32
        Rows: the ``d = diffuse_size`` diffuse map, then GGX levels ``k = 1 .. levels - 1``
        (face ``s_k = n >> k``), each face-major ``(6, s, s)``. Columns: the input texels,
        face-major.
    sizes : tuple of int
        ``(d, s_1, ..., s_{levels-1})``.
    """
    if not supported(n, diffuse_size):
        raise ValueError(f"the filter matrix is for faces up to {MAX_FACE}, got input {n} and "
                         f"diffuse {diffuse_size}.")
    chain = mip_sizes(n, levels)
    sizes = filter_sizes(n, diffuse_size, levels)
    w = texel_directions(n).reshape(-1, 3)
    om = texel_solid_angles(n).reshape(-1)
    rows = filter_matrix_shape(n, diffuse_size, levels)[0]
    out = np.empty((rows, w.shape[0]), dtype=np.float32)
    r0 = 0
    for k, s in enumerate(sizes):
        d = texel_directions(s).reshape(-1, 3)
        alpha = (0.0 if k == 0 else
                 float(lobes.roughness_to_alpha(lobes.level_roughness(k, len(chain)))))
        for i in range(0, len(d), _ROWS):  # chunks of output texels (bounded temporaries)
            c = d[i:i + _ROWS] @ w.T                                   # (r, 6 n^2) cosines
            if k == 0:
                np.maximum(c, 0.0, out=c)
                c *= om / np.pi
            else:
                lobes.ggx_kernel_inplace(c, alpha)
                c *= om
                c /= c.sum(axis=1, keepdims=True)
            out[r0 + i:r0 + i + len(c)] = c
        r0 += len(d)
    out.setflags(write=False)
    return out, sizes


def filter_cube(faces: ArrayLike, diffuse_size: int, levels: int, *,
                matrix: NDArray[np.float32] | None = None
                ) -> tuple[NDArray[np.float32], list[NDArray[np.float32]]]:
    """Diffuse map and GGX chain of ``faces (6, n, n, C)`` (finite, ``n <= MAX_FACE``).

    The channels may be many probes' RGB side by side: each output channel depends only on the
    same input channel, so ``C = 3 G`` filters ``G`` probes in one product.

    Returns
    -------
    diffuse : (6, d, d, C) float32
        Irradiance / pi (:func:`probegrid.core.diffuse.diffuse_exact`).
    chain : list of (6, n >> k, n >> k, C) float32, k = 0 .. levels - 1
        Level 0 is a copy of the input; the others as
        :func:`probegrid.core.specular.reference_convolution`.

    ``matrix``: :func:`filter_matrix`'s matrix for these sizes when the caller already has it
    (e.g. read from a per-machine cache); computed (and kept per process) otherwise.
    """
    src = check_cube(faces, name="faces")
    if not np.all(np.isfinite(src)):
        raise ValueError("faces must be finite (no nan or inf radiance).")
    n, c = src.shape[1], src.shape[3]
    sizes = filter_sizes(n, int(diffuse_size), int(levels))
    if matrix is None:
        matrix = filter_matrix(n, int(diffuse_size), int(levels))[0]
    elif matrix.shape != (shape := filter_matrix_shape(n, int(diffuse_size), int(levels))):
        raise ValueError(f"the filter matrix has shape {matrix.shape}, expected {shape}")
    with one_blas_thread():  # workers are processes (cf. specular)
        y = matrix @ np.ascontiguousarray(src.reshape(-1, c), dtype=np.float32)
    parts = []
    r0 = 0
    for s in sizes:
        parts.append(np.ascontiguousarray(y[r0:r0 + 6 * s * s].reshape(6, s, s, c)))
        r0 += 6 * s * s
    return parts[0], [src.copy(), *parts[1:]]
