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
rows of one fixed matrix over the ``6 n^2`` input texels. Their weights depend only on the angle
between the output and the input direction, so the symmetry of the cube that carries face 0 onto
face ``f`` (:func:`probegrid.core.cubemap.face_symmetries`, a signed permutation of the axes)
carries face 0's rows onto face ``f``'s: ``row(f, r)[q] = row(0, r)[pi_f^-1(q)]`` with
``pi_f`` the texel permutation of that symmetry (:func:`probegrid.core.cubemap.texel_permutation`).
So only face 0's rows are kept (float64, each row's GGX weights normalised in float64, then
rounded to float32; computed once per process, read-only, ``lru_cache``), and ``G`` probes are
filtered by one matrix product of those rows against their texels gathered six ways,
``(6 n^2, 6 x 3 G)`` (BLAS sgemm): face ``f``'s outputs are face 0's rows applied to the input
permuted by ``pi_f``. Measured at ``n = 32`` (8^2 diffuse, 6 levels) on this project's 2-core
machine, a group of 8 probes: 13 ms with the full six-face matrix, which streamed 60 MB per
group and was bound by memory, 8.3 ms with face 0's rows (10 MB; the same flops), against about
30 ms for :func:`~probegrid.core.diffuse.diffuse_exact` plus the tiered
:func:`~probegrid.core.specular.ggx_prefilter` -- and exact (the references themselves, to
float32 rounding of the weights and sums) where the tiered sum approximates the reference to a
few 1e-3. A constant cube comes out constant to float32 rounding (the GGX rows sum to 1).

Memory: ``(d^2 + sum_k (n >> k)^2) x 6 n^2 x 4`` bytes: 10 MB at ``n = 32`` with ``d = 8`` and the
full chain, 0.6 MB at 16. Larger faces keep the per-call filters (a 64^2 matrix would take about
170 MB): :func:`supported` says which.
"""

from __future__ import annotations

from concurrent.futures import Executor
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core import lobes
from probegrid.core.arrays import one_blas_thread
from probegrid.core.cubemap import (
    check_cube,
    face_symmetries,
    mip_sizes,
    texel_directions,
    texel_permutation,
    texel_solid_angles,
)

__all__ = ["MATRIX_VERSION", "MAX_FACE", "describe", "filter_cube", "filter_matrix",
           "filter_matrix_shape", "filter_sizes", "supported"]

#: Largest input face size filtered through the cached matrix.
MAX_FACE = 32

#: Bumped whenever :func:`filter_matrix` would return other bits (keys the per-machine cache).
MATRIX_VERSION = 2  # 2: face 0's rows alone (the others by symmetry)

#: Rows of the matrix computed together (bounded float64 temporaries: rows x 6 n^2 x 8 bytes).
_ROWS = 256


def supported(n: int, diffuse_size: int) -> bool:
    """Whether an ``n``-cube with a ``diffuse_size`` diffuse map goes through the matrix."""
    return 1 <= n <= MAX_FACE and 1 <= diffuse_size <= MAX_FACE


def describe(n: int, diffuse_size: int) -> dict[str, str]:
    """How a bake with face size ``n`` filters its probes (for the store's manifest)."""
    if supported(n, diffuse_size):
        how = ("exact sum over every incoming texel (one cached float32 matrix of face 0's rows,"
               " the other faces by the cube's symmetry, probegrid.core.probefilter)")
        return {"diffuse": how, "specular": how}
    return {"diffuse": "exact sum over every incoming texel (probegrid.core.diffuse.diffuse_exact)",
            "specular": "tiered multi-resolution sum (probegrid.core.specular.ggx_prefilter)"}


def filter_sizes(n: int, diffuse_size: int, levels: int) -> tuple[int, ...]:
    """Face sizes of the matrix's row blocks: ``(diffuse_size, n >> 1, ..., n >> (levels - 1))``
    (the GGX chain's sizes after level 0)."""
    return (int(diffuse_size), *mip_sizes(n, levels)[1:])


def filter_matrix_shape(n: int, diffuse_size: int, levels: int) -> tuple[int, int]:
    """Shape of :func:`filter_matrix`'s matrix: its rows (face 0's output texels of every
    block) and columns (the ``n``-cube's texels)."""
    return (sum(s * s for s in filter_sizes(n, diffuse_size, levels)), 6 * int(n) * int(n))


@lru_cache(maxsize=2)
def filter_matrix(n: int, diffuse_size: int, levels: int) -> tuple[NDArray[np.float32],
                                                                     tuple[int, ...]]:
    """Face 0's diffuse and GGX rows for ``n``-cubes; cached, read-only.

    Returns
    -------
    matrix : (d^2 + sum_k s_k^2, 6 n^2) float32
        Rows: face 0 (``+X``) of the ``d = diffuse_size`` diffuse map, then of GGX levels
        ``k = 1 .. levels - 1`` (face ``s_k = n >> k``), each ``(s, s)`` row-major. Columns:
        the input texels, face-major. The other faces' rows are these after
        :func:`_face_gathers` (module docstring).
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
        d = texel_directions(s)[0].reshape(-1, 3)  # face 0's output texels
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


@lru_cache(maxsize=4)
def _face_gathers(n: int) -> NDArray[np.int64]:
    """``(6 n^2, 6)`` input rows that give face ``f``'s outputs from face 0's rows: column
    ``f`` is the texel permutation of the symmetry carrying face 0 onto face ``f``."""
    out = np.stack([texel_permutation(s, n) for s in face_symmetries()], axis=1)
    out.setflags(write=False)
    return out


def filter_cube(faces: ArrayLike, diffuse_size: int, levels: int, *,
                matrix: NDArray[np.float32] | None = None, pool: Executor | None = None
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
    ``pool``: threads that each multiply a block of the matrix's rows (one cube's product
    split over cores: the same sums, equal to float32 rounding).
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
    # face f's outputs: face 0's rows applied to the input permuted by face f's symmetry
    gathered = np.ascontiguousarray(src.reshape(-1, c), dtype=np.float32)[_face_gathers(n)]
    rhs = gathered.reshape(-1, 6 * c)
    with one_blas_thread():  # workers are processes (cf. specular)
        if pool is None:
            y = (matrix @ rhs).reshape(-1, 6, c)
        else:  # row blocks side by side (numpy releases the GIL in the product)
            workers = max(1, int(getattr(pool, "_max_workers", 2)))
            cut = np.linspace(0, matrix.shape[0], workers + 1).astype(int)
            blocks = list(pool.map(lambda i: matrix[cut[i]:cut[i + 1]] @ rhs, range(workers)))
            y = np.concatenate(blocks).reshape(-1, 6, c)
    parts = []
    r0 = 0
    for s in sizes:  # (s, s, face, C) rows -> (face, s, s, C)
        block = y[r0:r0 + s * s].reshape(s, s, 6, c)
        parts.append(np.ascontiguousarray(block.transpose(2, 0, 1, 3)))
        r0 += s * s
    return parts[0], [src.copy(), *parts[1:]]
