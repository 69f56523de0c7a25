"""Specular environment filters: the GGX prefiltered mip chain, Phong lobes, exact references.

Every filter here is a *zonal* convolution of the input radiance with a lobe centred on the
output texel's direction ``R`` (:mod:`probegrid.core.lobes`), normalised so that a constant
environment is returned unchanged::

    out[R] = sum_q K(R . w_q) L_q dOmega_q / sum_q K(R . w_q) dOmega_q

where ``q`` runs over source texels (centre ``w_q``, exact solid angle ``dOmega_q``,
:func:`probegrid.core.cubemap.texel_solid_angles`): the midpoint rule on the piecewise-constant input,
normalised by the same discrete sum (a ratio estimator, so constants are exact and energy is
conserved to quadrature accuracy).

GGX chain (:func:`ggx_prefilter`)
---------------------------------
Level ``k`` of ``levels`` has face size ``n >> k`` (or ``size >> k``) and perceptual roughness
``r = k / (levels - 1)``, ``alpha = r^2``; the kernel is :func:`probegrid.core.lobes.ggx_kernel`
(the split-sum ``n = v = r`` prefilter of Karis 2013). Level 0 is the input unchanged (a copy; a
box/solid-angle resample when ``size`` differs from the input).

``method="tiered"`` (default): for input cubes up to :data:`DENSE_CHAIN_MAX` (128^2) every level
is the dense sum over every input texel, computed through the cube's 48 symmetries
(:func:`symmetric_zonal_sums`: the kernel is evaluated for 1/48 of the outputs, float32 BLAS
applies it to the 48 permuted copies of the input at once, and a block of outputs reads only
the input texels within 90 degrees of it). That is the reference itself (to float32 rounding:
relative 2e-6) at ~0.3 s CPU for a 128^2 chain; ``probegrid filter`` computes its diffuse map in
the same pass. Larger cubes, whose dense sums would cost ``(n / 128)^4`` times more, take a
deterministic, *sparse multi-resolution* evaluation of that sum (no random or quasi-random
samples), described below. Why not importance sampling with filtered lookups
(Krivanek & Colbert 2008, Filament's ``roughnessFilter``)? It is kept as ``method="fis"`` and
measured (128^2 chains, ``benchmarks/bench_filter.py``): at 256 Hammersley samples it takes
~1.1 s for 2-8 % RMS relative error on venice and 45-130 % on studio (64 samples: 0.3 s, 6-28 %
on venice); a seamless trilinear lookup costs ~300 ns in numpy. The tiered sum takes 0.42-0.46 s
cold / 0.23 s warm on one thread for 0.2-0.3 % (venice) and 1.5 % (studio). It applies the same
idea -- coarser mips where the lobe is smooth -- deterministically:

* Pieces. The GGX lobe has long tails (the energy beyond half-angle ``p`` is
  ``a^2 / (a^2 + tan^2 p)``: ~4 % beyond 12 degrees at ``r = 1/7``), so it cannot be truncated,
  and a dense product with the full-resolution input costs ``6 n_k^2 x 6 n^2`` pairs. The kernel
  is split with smooth radial windows into pieces ``K = sum_t K (W_t - W_{t-1})``; ``W_t`` is 1
  for ``theta < rho_t / 2``, 0 beyond ``rho_t``, a smoothstep (in the chord ``|R - w|``) between.
  Piece ``t`` lives in ``rho_t / 4 <= theta <= rho_t`` and is summed over mip ``s_t = s_0 + t``
  of the input (:func:`probegrid.core.cubemap.downsample`), whose texel is ``rho_t / beta``:
  ``rho_t = beta (2 / m_t) (1 + u^2 + v^2)^(-3/4)`` for mip face size ``m_t``, scaled by the
  local texel size at the output's face position ``(u, v)`` so that every piece sees about
  ``pi beta^2`` texels (``beta = 6``) also near cube corners. ``s_0`` is the coarsest mip whose
  texel is at most ``HWHM / gamma`` (HWHM ~= 1.29 alpha; ``gamma = 3``, clamped to the input).
  The chain ends with a *dense* piece ``K (1 - W_last)`` over a whole mip once
  ``(6 g^2)(6 m^2) <= dense_pairs`` (2e7; mips up to 64^2). A level is instead *one* dense
  stage over the finest mip ``m <= 128`` (no coarser than ``s_0``) whose ``36 g^2 m^2`` pairs fit
  ``level_pairs`` (7e8, scaled by ``(128 / n)^2`` above 128^2): exact over the input texels, or
  first-order over a mip's moments. For a 128^2 chain that makes levels 2-7 exact dense sums
  (levels 3-7 of a 256^2 chain dense over mips), so their error is the source's own (chains of
  128^2 and smaller cubes are now wholly dense, above); level 1 of the tiered sum is at 3.4 x
  (venice) and 9.7 x (studio) the 128^2 source's floor. The dense stages are
  built in float32 row chunks (:func:`_dense_level_stage`; a 128^2 chain peaks at ~240 MB).
* First-order moments. A coarse texel stands for the input texels it covers, whose exact
  positions matter when one is much brighter (a sun). Each mip texel carries ``P = sum L dOmega``
  and the first moment ``M = sum L dOmega (w_i - w_q)`` (built exactly from the input), and a
  piece ``f = K W`` contributes ``f(c_q) P_q + f'(c_q) R . M_q`` -- the first-order Taylor
  expansion of ``f`` about the texel centre (a dipole term, as in fast multipole methods). This
  cut the error next to the sun by about 2 x. Input texels are the reference's midpoint nodes
  and have no moment.
* Output grids. A piece over mip ``m`` is evaluated on a grid of ``2 m`` (at most the level's
  size) and interpolated (seamless bilinear, :class:`probegrid.core.sampling.CubeSampler`): its sum
  is smooth on the scale of its window. Numerators and the normaliser (the same sum for the
  constant 1, pure geometry) are interpolated separately and divided at the end, so constants
  stay exact.
* Plans. The weights depend only on geometry, so they are computed once per (input size, level
  size, alpha, beta, gamma) into padded *plans* (:func:`ggx_tier_plan`, ``lru_cache``,
  read-only arrays) and reused: a probe grid filters many cubes of one size. They are computed
  only for a fundamental domain of the 48 cube symmetries
  (:func:`probegrid.core.cubemap.symmetry_group`: signed axis permutations, which map texel
  centres onto texel centres and keep angles and solid angles): the texels
  ``i <= j <= (n - 1) / 2`` of face +X, 1/48 of the outputs. Every other output reuses its
  representative's row with permuted source indices. Candidate source texels of a windowed piece
  are found with tiles and bounding cones before the exact test.
* Applying a plan gathers ``(P, M)`` rows and contracts them with the weights, chunked over
  outputs (temporaries ~32 MB); dense pieces instead permute the whole mip once per symmetry
  and use one matrix product. BLAS is limited to one thread during the call (its spin-waiting
  made runs on the shared 2-core machine 2-10 x slower); ``workers`` threads can filter
  levels concurrently.

Accuracy of the tiered sum against :func:`reference_convolution` (every input texel, float64)
on the real HDRs, measured on a 128^2 chain forced through it (``benchmarks/bench_filter.py``):
level 1 RMS relative error ~2e-3 (venice) and ~1.4e-2 (studio's small bright softboxes), max 7 %
next to the brightest sources; whole-level dense stages are exact over their source texels.
Filament's cmgen at 1024 samples: 2-8 % (venice) and 8-80 % (studio) RMS. Time (one thread,
cold, CPU): ~1.9 s for a 256^2 chain. Memory: the cached plans plus chunked temporaries (the
symmetries of the chain's texels by index arithmetic, :func:`_chain_permute`, not a 100 MB
table at 256^2); :func:`clear_caches` drops the cached geometry. The dense chain of a 128^2
cube holds the 48 permuted copies of the input (57 MB) while it runs.
Tests: constant, linear (analytic lobe mean), near-delta and real-HDR inputs against the
reference, symmetry.

``method="exact"`` is the dense float64 sum over every input texel (slow, for references).

Phong (:func:`phong_filter`, :func:`phong_chain`)
--------------------------------------------------
The normalised cosine-power lobe ``max(0, R . w)^P``, summed exactly over every input texel
(dense, float64, chunked): no approximation beyond the midpoint rule.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Literal, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._types import GGXMethod
from probegrid.core import lobes
from probegrid.core.arrays import one_blas_thread
from probegrid.core.cubemap import (
    _symmetry_face_table,
    check_cube,
    mip_sizes,
    symmetry_permutations,
    texel_directions,
    texel_solid_angles,
    texel_uv,
)
from probegrid.core.sampling import CubeSampler, mip_chain, resample

__all__ = [
    "GGXMethod",
    "PlanStage",
    "clear_caches",
    "ggx_filter",
    "ggx_prefilter",
    "ggx_tier_plan",
    "hammersley",
    "phong_chain",
    "phong_filter",
    "reference_convolution",
    "zonal_convolution",
]


#: Temporaries of the dense sums are kept near this many bytes.
_CHUNK_BYTES = 32 * 2**20
#: GGX half width at half maximum is about this many times alpha (small alpha).
_HWHM_PER_ALPHA = 1.29
#: A piece summed over mip m is evaluated on a grid of this many times m, then interpolated.
_GRID_PER_MIP = 2
#: Largest mip face size summed whole by a dense stage (its 48 permuted copies are gathered,
#: in chunks of _CHUNK_BYTES).
_DENSE_MAX_MIP = 128
#: A level is one dense stage over the finest mip with at most this many (output, source) pairs.
_DENSE_PAIRS = 700_000_000


# --------------------------------------------------------------------------------------------
# Dense (exact) zonal convolution


def zonal_convolution(
    faces: ArrayLike,
    kernel: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    size: int,
    *,
    normalize: bool = True,
    chunk_bytes: int = _CHUNK_BYTES,
) -> NDArray[np.float64]:
    """Dense zonal convolution over every source texel (float64, midpoint rule).

    ``out[R] = sum_q kernel(R . w_q) L_q dOmega_q``, divided by ``sum_q kernel(R . w_q)
    dOmega_q`` when ``normalize``.

    Parameters
    ----------
    faces : (6, n, n, C) float
        Source radiance.
    kernel : callable
        Maps an array of cosines ``R . w`` (float64, any shape) to kernel values (1/sr).
    size : int
        Output face size.
    normalize : bool
        Divide by the discrete kernel integral (constant in, constant out).
    chunk_bytes : int
        Output texels are processed in chunks whose ``(rows, 6 n^2)`` float64 temporaries take
        about this many bytes (memory bound: ~3 such arrays).

    Returns
    -------
    (6, size, size, C) float64
    """
    src = check_cube(faces, name="faces")
    _check_size(size, "size")
    n, c = src.shape[1], src.shape[3]
    ds = texel_directions(n).reshape(-1, 3)
    om = texel_solid_angles(n).reshape(-1)
    lw = np.concatenate([src.reshape(-1, c).astype(np.float64) * om[:, None], om[:, None]], 1)
    do = texel_directions(size).reshape(-1, 3)
    out = np.empty((do.shape[0], c), dtype=np.float64)
    rows = max(1, int(chunk_bytes) // (8 * ds.shape[0]))
    for i in range(0, do.shape[0], rows):
        k = kernel(do[i:i + rows] @ ds.T)
        r = k @ lw
        if normalize:
            out[i:i + rows] = r[:, :c] / r[:, c:]
        else:
            out[i:i + rows] = r[:, :c]
    return out.reshape(6, size, size, c)


def _ggx_kernel_fast(alpha: float) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
    """``lobes.ggx_kernel`` at ``alpha`` evaluated in place (:func:`lobes.ggx_kernel_inplace`)."""
    a = float(alpha)
    return lambda c: lobes.ggx_kernel_inplace(c, a)


def reference_convolution(faces: ArrayLike, alpha: float, size: int) -> NDArray[np.float64]:
    """Brute-force GGX prefilter: every source texel, float64 (the converged reference).

    Parameters
    ----------
    faces : (6, n, n, C) float
    alpha : float
        GGX alpha (> 0).
    size : int
        Output face size.

    Returns
    -------
    (6, size, size, C) float64
        The normalised sum of the module docstring with ``K = lobes.ggx_kernel``. Cost
        ``36 size^2 n^2`` kernel evaluations (~30 s for 64^2 from 128^2); memory is chunked.
    """
    a = float(alpha)
    if not (np.isfinite(a) and a > 0):
        raise ValueError(f"alpha must be a finite number > 0, got {alpha!r}.")
    return zonal_convolution(faces, _ggx_kernel_fast(a), size)


# --------------------------------------------------------------------------------------------
# Phong


def phong_filter(faces: ArrayLike, exponent: float, size: int) -> NDArray[np.float32]:
    """Normalised cosine-power (Phong) filter, exact over every source texel.

    Parameters
    ----------
    faces : (6, n, n, C) float
    exponent : float
        ``P >= 0``; ``K = max(0, R . w)^P`` (:func:`probegrid.core.lobes.phong_kernel`).
    size : int
        Output face size.

    Returns
    -------
    (6, size, size, C) float32
        ``sum K L dOmega / sum K dOmega``. For ``P`` so large that the lobe is narrower than a
        source texel the result tends to the nearest texels (the sum stays well defined: the
        kernel is evaluated as ``exp(P log c)`` relative to the row's largest cosine).
    """
    p = float(exponent)
    if not (np.isfinite(p) and p >= 0):
        raise ValueError(f"exponent must be a finite number >= 0, got {exponent!r}.")

    def k(c: NDArray[np.float64]) -> NDArray[np.float64]:
        # Scale each row by its largest cosine^P so huge exponents do not underflow to 0/0;
        # the normalisation cancels the per-row factor.
        cmax = np.max(c, axis=1, keepdims=True)
        np.maximum(c, 0.0, out=c)
        with np.errstate(divide="ignore"):
            np.log(c, out=c)
        c -= np.log(np.maximum(cmax, 1e-300))
        c *= p
        return np.exp(c, out=c)

    if p == 0:
        return zonal_convolution(faces, lambda c: (c > 0).astype(np.float64), size).astype(
            np.float32)
    return zonal_convolution(faces, k, size).astype(np.float32)


def phong_chain(faces: ArrayLike, exponents: Sequence[float], *, size: int | None = None
                ) -> list[NDArray[np.float32]]:
    """:func:`phong_filter` for several exponents, level ``k`` at face size ``size >> k``.

    Parameters
    ----------
    faces : (6, n, n, C) float
    exponents : sequence of float
        One exponent per level (e.g. decreasing, sharpest first).
    size : int, optional
        Face size of level 0 (default ``n``); must allow ``len(exponents)`` halvings.

    Returns
    -------
    list of (6, size >> k, size >> k, C) float32
    """
    src = check_cube(faces, name="faces")
    base = src.shape[1] if size is None else size
    sizes = mip_sizes(base, len(exponents)) if len(exponents) else []
    return [phong_filter(src, e, s) for e, s in zip(exponents, sizes)]


# --------------------------------------------------------------------------------------------
# Tiered GGX plan


def _check_size(n: int, name: str) -> None:
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
        raise ValueError(f"{name} must be a positive integer, got {n!r}.")


@lru_cache(maxsize=16)
def _fundamental_domain(g: int) -> tuple[NDArray[np.intp], NDArray[np.int32], NDArray[np.int32]]:
    """A fundamental domain of the cube symmetries on the texels of a ``g``-cube.

    Returns
    -------
    rows : (F,) intp
        Flat indices (face 0) of the texels ``i <= j <= (g - 1) / 2`` (row ``i``, column
        ``j``) of face +X, an eighth of the face (about ``g^2 / 8`` texels, 1/48 of the cube):
        every texel of the cube is the image of one of them under some symmetry.
    owner_sym, owner_row : (6 g^2,) int32
        For every texel ``o``: a symmetry ``k`` and a position ``r`` in ``rows`` with
        ``perm[k, rows[r]] == o``.
    """
    i, j = np.meshgrid(np.arange(g), np.arange(g), indexing="ij")
    rows = np.flatnonzero((i <= j) & (2 * j <= g - 1))
    perm = symmetry_permutations(g)
    owner_sym = np.full(6 * g * g, -1, dtype=np.int32)
    owner_row = np.full(6 * g * g, -1, dtype=np.int32)
    for k in range(47, -1, -1):  # identity last, so face 0's own texels keep k = 0
        owner_sym[perm[k, rows]] = k
        owner_row[perm[k, rows]] = np.arange(rows.size)
    if np.any(owner_sym < 0):
        raise AssertionError("the fundamental domain does not cover the cube")  # pragma: no cover
    for a in (rows, owner_sym, owner_row):
        a.setflags(write=False)
    return rows, owner_sym, owner_row


def _tiles(dirs: NDArray[np.float64], b: int) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                                       NDArray[np.intp]]:
    """Group an ``(F, m, m, 3)`` direction grid into ``b x b`` tiles.

    Returns tile centres ``(T, 3)``, tile radii ``(T,)`` (largest angle from the centre to a
    member's centre) and member flat indices ``(T, b * b)``.
    """
    f, m = dirs.shape[0], dirs.shape[1]
    idx = np.arange(f * m * m).reshape(f, m // b, b, m // b, b).transpose(0, 1, 3, 2, 4)
    idx = idx.reshape(-1, b * b)
    mem = dirs.reshape(-1, 3)[idx]
    cen = mem.sum(axis=1)
    cen /= np.linalg.norm(cen, axis=1, keepdims=True)
    cosr = np.min(np.einsum("tkd,td->tk", mem, cen), axis=1)
    return cen, np.arccos(np.clip(cosr, -1.0, 1.0)), idx


def _compact_rows(mask: NDArray[np.bool_]) -> tuple[NDArray[np.intp], NDArray[np.intp],
                                                   NDArray[np.intp], int]:
    """Where to move each row's selected entries so they come first.

    Returns ``rr, cc`` (the selected entries, row-major), ``slot`` (their new column) and the
    compacted width (largest row count).
    """
    rr, cc = np.nonzero(mask)
    counts = np.bincount(rr, minlength=mask.shape[0])
    start = np.cumsum(counts) - counts
    slot = np.arange(rr.size) - start[rr]
    return rr, cc, slot, int(counts.max()) if counts.size else 0


def _cap_pairs(g: int, rows: NDArray[np.intp], m: int, rho: NDArray[np.float64] | None
               ) -> tuple[NDArray[np.bool_], NDArray[np.intp], NDArray[np.float64]]:
    """Source texels within angle ``rho`` of some output texels (all texels when None).

    Parameters
    ----------
    g : int
        Output face size.
    rows : (P,) intp
        The output texels: flat indices into face 0 of the ``g``-cube.
    m : int
        Source face size.
    rho : (P,) float64 or None
        Cap radius of each output (radians).

    Returns
    -------
    valid : (P, K) bool
        Which entries are real (the rest is padding).
    q : (P, K) intp
        Source flat index (``< 6 m^2``).
    c : (P, K) float64
        Cosine between output and source directions (padding: -1).
    """
    grid = texel_directions(g)[0]
    src = texel_directions(m)
    od = grid.reshape(-1, 3)[rows]
    sd = src.reshape(-1, 3)
    if rho is None:
        c = od @ sd.T
        q = np.broadcast_to(np.arange(sd.shape[0]), c.shape)
        return np.ones(c.shape, dtype=bool), q, c
    bo = 2 if g % 2 == 0 else 1
    bs = 4 if m % 4 == 0 else (2 if m % 2 == 0 else 1)
    co, ro, io = _tiles(grid[None], bo)
    # Only the output tiles holding a requested texel; rho of the others is irrelevant (0).
    rho_all = np.zeros(g * g)
    rho_all[rows] = rho
    wanted = np.zeros(g * g, dtype=bool)
    wanted[rows] = True
    pick = np.flatnonzero(wanted[io].any(axis=1))
    co, ro, io = co[pick], ro[pick], io[pick]
    cs, rs, is_ = _tiles(src, bs)
    # Tile pairs whose bounding cones come within rho: (To, Kc) candidate source tiles.
    reach = np.minimum(rho_all[io].max(axis=1) + ro + rs.max(), np.pi)
    cos_reach = np.cos(reach).astype(np.float32)
    cs_t = np.ascontiguousarray(cs.T, dtype=np.float32)
    co32 = co.astype(np.float32)
    found = []
    step = max(1, _CHUNK_BYTES // (8 * cs.shape[0]))               # bounded (To, Ts) blocks
    for t0 in range(0, co.shape[0], step):
        rr, cc, slot, _ = _compact_rows(co32[t0:t0 + step] @ cs_t >= cos_reach[t0:t0 + step, None])
        found.append((rr + t0, cc, slot))
    kc = max(int(f[2].max()) + 1 if f[2].size else 0 for f in found)
    cand = np.zeros((co.shape[0], kc), dtype=np.intp)
    cvalid = np.zeros((co.shape[0], kc), dtype=bool)
    for rr, cc, slot in found:
        cand[rr, slot] = cc
        cvalid[rr, slot] = True
    # Every output of a tile tests the members of the tile's candidates exactly (float32 is
    # enough for the test: a misclassified entry sits at the window's edge, where it is 0).
    qs = is_[cand].reshape(co.shape[0], -1)                        # (To, Kc bs^2)
    grid32 = grid.reshape(-1, 3).astype(np.float32)
    c32 = np.matmul(grid32[io], sd.astype(np.float32)[qs].transpose(0, 2, 1))  # (To, bo^2, N)
    cmin = np.cos(np.minimum(rho_all, np.pi)).astype(np.float32)
    cmin[~wanted] = 2.0                                            # nothing for other texels
    keep = c32 >= cmin[io][:, :, None]
    keep &= np.repeat(cvalid, bs * bs, axis=1)[:, None, :]
    keep = keep.reshape(-1, qs.shape[1])                           # rows in tile order
    rr, cc, slot, width = _compact_rows(keep)
    valid = np.zeros((keep.shape[0], width), dtype=bool)
    q = np.zeros((keep.shape[0], width), dtype=np.intp)
    valid[rr, slot] = True
    q[rr, slot] = qs[rr // (bo * bo), cc]
    where = np.empty(g * g, dtype=np.intp)                         # flat index -> tile row
    where[io.reshape(-1)] = np.arange(io.size)
    valid, q = valid[where[rows]], q[where[rows]]
    ck = np.einsum("rd,rkd->rk", od, sd[q])                        # exact cosines, float64
    ck[~valid] = -1.0
    return valid, q, ck


def _window(chord: NDArray[np.float64], rho: NDArray[np.float64]) -> NDArray[np.float64]:
    """Radial window of angular radius ``rho`` (broadcast against ``chord``), in terms of the
    chord ``|R - w|``: 1 for ``theta <= rho / 2``, 0 for ``theta >= rho``, a smoothstep in the
    chord between."""
    r = np.minimum(rho, np.pi)
    c1 = 2.0 * np.sin(0.5 * r)
    c0 = 2.0 * np.sin(0.25 * r)
    x = np.clip((c1 - chord) / (c1 - c0), 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _window_dc(chord: NDArray[np.float64], rho: NDArray[np.float64]) -> NDArray[np.float64]:
    """Derivative of :func:`_window` with respect to the cosine ``c`` (``chord^2 = 2 - 2c``)."""
    r = np.minimum(rho, np.pi)
    c1 = 2.0 * np.sin(0.5 * r)
    c0 = 2.0 * np.sin(0.25 * r)
    x = np.clip((c1 - chord) / (c1 - c0), 0.0, 1.0)
    return 6.0 * x * (1.0 - x) / ((c1 - c0) * np.maximum(chord, 1e-12))


def _tier_schedule(n: int, size: int, alpha: float, beta: float, gamma: float,
                   dense_pairs: int, level_pairs: int) -> list[tuple[int, float | None, int]]:
    """Pieces of the kernel: (source mip level, window radius or None for the dense rest,
    output grid size). A piece whose mip is coarser than half the output is evaluated on a grid
    twice the mip's size and interpolated (its sum is smooth on the scale of its window)."""
    src_levels = mip_sizes(n)
    hwhm = min(_HWHM_PER_ALPHA * alpha, 1.0)
    s0 = 0
    while s0 + 1 < len(src_levels) and 2.0 / src_levels[s0 + 1] <= hwhm / gamma:
        s0 += 1
    # A finer dense sum is used when it fits the budget (cheap outputs, e.g. the 1 x 1 level).
    for s, m in enumerate(src_levels[:s0 + 1]):
        if 36 * size * size * m * m <= level_pairs and m <= _DENSE_MAX_MIP:
            return [(s, None, size)]
    tiers: list[tuple[int, float | None, int]] = []
    for s in range(s0, len(src_levels)):
        m = src_levels[s]
        g = min(size, _GRID_PER_MIP * m)
        rho = beta * 2.0 / m
        if 36 * g * g * m * m <= dense_pairs or rho >= np.pi or s == len(src_levels) - 1:
            tiers.append((s, None, g))
            break
        tiers.append((s, rho, g))
    return tiers


@dataclass(frozen=True, eq=False)
class PlanStage:
    """One stage of a :func:`ggx_tier_plan`: the pieces summed on one output grid.

    Rows are the fundamental-domain texels of face +X of the ``grid``-cube
    (:func:`_fundamental_domain`); every other output texel reuses its representative's row
    with the source columns mapped by the cube symmetry relating them.

    Attributes
    ----------
    grid : int
        Output face size of the stage (interpolated to the level's size when smaller).
    weights : (F, 2, K) float32
        ``f(c_q)`` and ``f'(c_q)`` per row and entry (padding 0).
    columns : (F, K) int32 or None
        Sparse stages: flat indices into the concatenated mip chain. None for a dense stage,
        whose ``K`` entries are all ``6 m^2`` texels of mip ``level`` in order.
    level : int
        Source mip level of a dense stage; for a sparse stage 0 when every entry is an input
        texel (no moments: only ``P`` is gathered) and -1 otherwise.
    norm : (F,) float64
        The same first-order sum for the constant 1 (pure geometry): the normaliser.
    """

    grid: int
    weights: NDArray[np.float32]
    columns: NDArray[np.int32] | None
    level: int
    norm: NDArray[np.float64]


def _ggx_kernel_and_slope(c: NDArray[np.float64], alpha: float
                          ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``lobes.ggx_kernel(c)`` and its derivative with respect to ``c`` (0 for ``c <= 0``)."""
    a2 = alpha * alpha
    slope = 0.5 * (a2 - 1.0)
    scale = a2 / (4.0 * np.pi)
    cp = np.maximum(c, 0.0)
    t = cp * slope + (slope + 1.0)
    k = scale * cp / (t * t)
    dk = np.where(c > 0, scale * (t - 2.0 * slope * cp) / (t * t * t), 0.0)
    return k, dk


@lru_cache(maxsize=32)
def ggx_tier_plan(n: int, size: int, alpha: float, *, beta: float = 6.0, gamma: float = 3.0,
                  dense_pairs: int = 20_000_000, level_pairs: int = _DENSE_PAIRS
                  ) -> tuple[PlanStage, ...]:
    """Weights of the tiered GGX filter (geometry only; cached, read-only arrays).

    Parameters
    ----------
    n : int
        Input face size (a power of two).
    size : int
        Output face size.
    alpha : float
        GGX alpha > 0.
    beta : float
        Window radius of each piece in texels of its mip level.
    gamma : float
        Finest piece's texels per kernel half width (HWHM).
    dense_pairs : int
        A mip is summed whole (a dense stage) once ``(6 g^2) (6 m^2)`` is at most this.
    level_pairs : int
        The whole level is one dense stage over the finest mip (up to 128^2) with at most
        ``level_pairs (128 / n)^2`` pairs (for ``n > 128``): exact over the input texels, or
        first-order over a mip's moments.

    Returns
    -------
    tuple of PlanStage
        Sparse stages (capped pieces, merged per output grid) and dense stages; see
        :class:`PlanStage` and :func:`ggx_prefilter` for how they are applied.
    """
    _check_size(n, "n")
    _check_size(size, "size")
    if n & (n - 1):
        raise ValueError(f"the tiered GGX filter needs a power-of-two input size, got {n}.")
    a = float(alpha)
    if not (np.isfinite(a) and a > 0):
        raise ValueError(f"alpha must be a finite number > 0, got {alpha!r}.")
    src_levels = mip_sizes(n)
    offsets = np.cumsum([0] + [6 * m * m for m in src_levels[:-1]])
    geo = _geometric_pyramid(n)                                    # (total, 4): Omega, m
    sparse: dict[int, list[tuple[NDArray, ...]]] = {}
    stages: list[PlanStage] = []
    prev_rho: float | None = None
    # the whole-level budget shrinks with the cube (its stages are held in the plan cache)
    budget = int(level_pairs * min(1.0, (128 / n) ** 2))
    schedule = _tier_schedule(n, size, a, beta, gamma, dense_pairs, budget)
    if len(schedule) == 1 and schedule[0][1] is None:  # the whole level is one dense stage
        s, _, g = schedule[0]
        m = src_levels[s]
        return (_dense_level_stage(g, m, s, a, geo[offsets[s]:offsets[s] + 6 * m * m]),)
    for s, rho, g in schedule:
        m = src_levels[s]
        fund = _fundamental_domain(g)[0]
        # The window radius follows the local texel size (1 + u^2 + v^2)^(-3/4) of the output's
        # position, so every piece sees about pi beta^2 texels also near the cube corners.
        u, v = texel_uv(g)
        scale = ((1.0 + u * u + v * v) ** -0.75).reshape(-1)[fund][:, None]
        rho_o = None if rho is None else rho * scale
        prev_o = None if prev_rho is None else prev_rho * scale
        valid, q, c = _cap_pairs(g, fund, m, None if rho_o is None else rho_o[:, 0])
        chord = np.sqrt(np.maximum(2.0 - 2.0 * c, 0.0))
        k, dk = _ggx_kernel_and_slope(c, a)
        piece = np.ones_like(c) if rho_o is None else _window(chord, rho_o)
        dpiece = np.zeros_like(c) if rho_o is None else _window_dc(chord, rho_o)
        if prev_o is not None:
            piece -= _window(chord, prev_o)
            dpiece -= _window_dc(chord, prev_o)
        w0 = k * piece
        w1 = dk * piece + k * dpiece
        w0[~valid] = 0.0
        w1[~valid] = 0.0
        if s == 0:
            w1[:] = 0.0  # input texels are points of the midpoint rule: no sub-texel moments
        rdir = texel_directions(g)[0].reshape(-1, 3)[fund]
        if rho is None:
            stages.append(_make_stage(g, w0, w1, None, s, geo[offsets[s]:offsets[s] + 6 * m * m],
                                      rdir))
        else:
            sparse.setdefault(g, []).append((w0, w1, q + offsets[s], valid))
        prev_rho = rho
    for g in sorted(sparse, reverse=True):
        parts = sparse[g]
        w0, w1, q, ok = (np.concatenate([x[i] for x in parts], axis=1) for i in range(4))
        rdir = texel_directions(g)[0].reshape(-1, 3)[_fundamental_domain(g)[0]]
        on_input = q < 6 * n * n
        # Entries on the input texels have no moments: a separate stage gathers only P there.
        for sel, level in ((on_input, 0), (~on_input, -1)):
            rr, cc, slot, width = _compact_rows(sel & ok & ((w0 != 0) | (w1 != 0)))
            if width == 0:
                continue
            packed = [np.zeros((w0.shape[0], width), dtype=x.dtype) for x in (w0, w1, q)]
            for o, x in zip(packed, (w0, w1, q)):
                o[rr, slot] = x[rr, cc]
            stages.append(_make_stage(g, packed[0], packed[1], packed[2].astype(np.int32),
                                      level, geo, rdir))
    return tuple(sorted(stages, key=lambda st: -st.grid))


def _dense_level_stage(g: int, m: int, s: int, alpha: float, geo: NDArray[np.float64]
                       ) -> PlanStage:
    """A whole level as one dense stage over mip ``s`` (face ``m``): the same weights as the
    general path (``f = K``, no window), built in row chunks straight into float32 so that
    stages of millions of pairs need no full-size float64 temporaries."""
    fund = _fundamental_domain(g)[0]
    od = texel_directions(g)[0].reshape(-1, 3)[fund]
    sd = texel_directions(m).reshape(-1, 3)
    ww = np.empty((len(fund), 1 if s == 0 else 2, len(sd)), dtype=np.float32)  # no moments on 0
    norm = np.empty(len(fund))
    rows = max(1, _CHUNK_BYTES // (8 * 4 * len(sd)))
    for i in range(0, len(fund), rows):
        k, dk = _ggx_kernel_and_slope(od[i:i + rows] @ sd.T, alpha)
        if s == 0:
            dk[:] = 0.0  # input texels are points of the midpoint rule: no sub-texel moments
        norm[i:i + rows] = k @ geo[:, 0] + np.einsum("rk,rk->r", dk, od[i:i + rows] @ geo[:, 1:].T)
        ww[i:i + rows, 0] = k
        if s > 0:
            ww[i:i + rows, 1] = dk
    ww.setflags(write=False)
    norm.setflags(write=False)
    return PlanStage(grid=g, weights=ww, columns=None, level=s, norm=norm)


def _make_stage(g: int, w0: NDArray[np.float64], w1: NDArray[np.float64],
                cols: NDArray[np.int32] | None, level: int, geo: NDArray[np.float64],
                rdir: NDArray[np.float64]) -> PlanStage:
    """Pack a stage and compute its normaliser from the geometric moments ``geo``."""
    gq = geo[None] if cols is None else np.take(geo, cols, axis=0)    # (F or 1, K, 4)
    norm = np.einsum("rk,rk->r", w0, np.broadcast_to(gq[..., 0], w0.shape))
    norm += np.einsum("rk,rk->r", w1, np.einsum("rkd,rd->rk", np.broadcast_to(
        gq[..., 1:], (*w1.shape, 3)), rdir))
    ww = np.stack([w0, w1], axis=1).astype(np.float32)
    for arr in (ww, norm) + (() if cols is None else (cols,)):
        arr.setflags(write=False)
    return PlanStage(grid=g, weights=ww, columns=cols, level=level, norm=norm)


@lru_cache(maxsize=8)
def _geometric_pyramid(n: int) -> NDArray[np.float64]:
    """``[Omega_q, m_q]`` of every mip texel (levels concatenated): (total, 4) float64, with
    ``m_q = sum_i dOmega_i (w_i - w_q)`` over the input texels it covers. Read-only."""
    out = _moment_pyramid(np.ones((6, n, n, 1), dtype=np.float32), dtype=np.float64)
    out.setflags(write=False)
    return out


@lru_cache(maxsize=2)
def _chain_layout(n: int) -> tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.int32]]:
    """The symmetries of the concatenated mip chain of an ``n``-cube in three small tables
    (read-only), from which :func:`_chain_permute` composes where symmetry ``k`` sends chain
    row ``q`` (texel ``(i, j)`` of face ``f`` of level ``l``):

    * ``face (total,)``: ``6 l + f`` of each row;
    * ``moves (48 * 6 L,)``: for ``(k, 6 l + f)``, ``8 x`` the first row of the face ``f'`` that
      ``k`` moves face ``f`` onto, plus which of the 8 moves of a square ``k`` applies;
    * ``within (8, total)``: each move's image of each row within its face,
      ``source_row * m + source_column`` (sources ``j, i, m - 1 - j, m - 1 - i``,
      :func:`probegrid.core.cubemap._texel_maps`).

    About 36 bytes per chain row (19 MB at 256^2), where the table of every symmetry of every
    row takes 192 (100 MB)."""
    sizes = mip_sizes(n)
    table = _symmetry_face_table()                                 # (48, 6): g', col, row src
    pairs, which = np.unique(table[..., 2] * 4 + table[..., 1], return_inverse=True)
    which = which.reshape(48, 6)
    assert len(pairs) <= 8  # (the dihedral group of the square)
    total = sum(6 * m * m for m in sizes)
    face = np.empty(total, dtype=np.int32)
    within = np.zeros((8, total), dtype=np.int32)
    moves = np.empty((48, 6 * len(sizes)), dtype=np.int32)
    off = 0
    for level, m in enumerate(sizes):
        rows = slice(off, off + 6 * m * m)
        f, i, j = np.meshgrid(np.arange(6), np.arange(m), np.arange(m), indexing="ij")
        face[rows] = (6 * level + f).reshape(-1)
        sources = (j, i, m - 1 - j, m - 1 - i)
        for d, pair in enumerate(pairs):
            within[d, rows] = (sources[pair // 4] * m + sources[pair % 4]).reshape(-1)
        moves[:, 6 * level:6 * level + 6] = (off + table[..., 0] * m * m) * 8 + which
        off += 6 * m * m
    out = (face, moves.reshape(-1), within)
    for x in out:
        x.setflags(write=False)
    return out


def _chain_permute(n: int, sym: NDArray[np.integer], q: NDArray[np.integer]
                   ) -> NDArray[np.int32]:
    """:func:`symmetry_permutations` of the concatenated mip chain of an ``n``-cube: where
    symmetry ``sym`` sends chain row ``q`` (broadcast), composed from :func:`_chain_layout`'s
    tables (int32)."""
    face, moves, within = _chain_layout(n)
    q = np.asarray(q)
    key = np.take(face, q) + np.asarray(sym, dtype=np.int32) * np.int32(len(moves) // 48)
    move = np.take(moves, key)
    del key
    out = move >> 3
    move &= 7
    move *= np.int32(within.shape[1])
    move += q
    out += np.take(within, move)
    return out


def _moment_pyramid(src: NDArray[np.float32], dtype: type = np.float32) -> NDArray:
    """Zeroth and first moments of every mip texel, from the input texels.

    For mip texel ``q`` (centre ``w_q``) covering input texels ``i``:
    ``P_q = sum_i L_i dOmega_i`` and ``M_q = sum_i L_i dOmega_i (w_i - w_q)`` per channel (``M``
    is 0 on level 0). Built level by level from the 2 x 2 children ``j`` (float64):
    ``P = sum_j P_j`` and ``M = sum_j (M_j + P_j (w_j - w_q))``. Returns ``(total, 4 C)`` rows
    ``[P (C), M_x (C), M_y (C), M_z (C)]`` for the levels ``0, 1, ...`` concatenated (each
    face-major).
    """
    n, c = src.shape[1], src.shape[3]
    sizes = mip_sizes(n)
    total = sum(6 * m * m for m in sizes)
    out = np.empty((total, 4 * c), dtype=dtype)
    p = src.astype(np.float64) * texel_solid_angles(n)[..., None]   # (6, m, m, C)
    mom = np.zeros((6, n, n, 3, c))
    out[:6 * n * n, :c] = p.reshape(-1, c)
    out[:6 * n * n, c:] = 0.0
    off = 6 * n * n
    for m in sizes[1:]:
        child_w = texel_directions(2 * m).reshape(6, m, 2, m, 2, 3, 1)
        pc = p.reshape(6, m, 2, m, 2, 1, c)
        mom = (mom.reshape(6, m, 2, m, 2, 3, c) + pc * child_w).sum(axis=(2, 4))
        p = p.reshape(6, m, 2, m, 2, c).sum(axis=(2, 4))
        mom -= texel_directions(m)[..., :, None] * p[..., None, :]
        out[off:off + 6 * m * m, :c] = p.reshape(-1, c)
        out[off:off + 6 * m * m, c:] = mom.reshape(-1, 3 * c)
        off += 6 * m * m
    return out


def _apply_plan(pyramid: NDArray[np.float32], n: int, stages: tuple[PlanStage, ...],
                size: int) -> NDArray[np.float32]:
    """Evaluate a plan: ``sum_q f(c_q) P_q + f'(c_q) R . M_q`` per channel (the first-order
    Taylor expansion of ``f`` about each mip texel's centre), divided by the plan's normaliser;
    coarse stages are interpolated (seamless bilinear) before the division.

    Output texel ``o = S_k(r)`` of fundamental texel ``r`` uses row ``r`` with every source
    texel ``q'`` replaced by ``S_k(q')``. Sparse stages gather per entry; dense stages instead
    permute the whole source mip once per symmetry and multiply (BLAS)."""
    c = pyramid.shape[1] // 4
    src_levels = mip_sizes(n)
    offsets = np.cumsum([0] + [6 * m * m for m in src_levels[:-1]])
    acc = np.zeros((6, size, size, c + 1), dtype=np.float64)
    p_only: NDArray[np.float32] | None = None
    for st in stages:
        g = st.grid
        fund, owner_sym, owner_row = _fundamental_domain(g)
        dirs = texel_directions(g).reshape(-1, 3)
        part = np.empty((6 * g * g, c + 1), dtype=np.float64)
        part[:, c] = st.norm[owner_row]
        if st.columns is None and 6 * g * g >= 48:
            # Dense stage, many outputs: permute the source mip once per symmetry, multiply.
            m = src_levels[st.level]
            block = pyramid[offsets[st.level]:offsets[st.level] + 6 * m * m]
            src_perm = symmetry_permutations(m)
            out_perm = symmetry_permutations(g)
            w0 = np.ascontiguousarray(st.weights[:, 0])
            w1 = np.ascontiguousarray(st.weights[:, 1]) if st.level > 0 else w0
            bp = np.ascontiguousarray(block[:, :c])
            bm = np.ascontiguousarray(block[:, c:])
            ks = max(1, _CHUNK_BYTES // (16 * c * 6 * m * m))       # symmetries per product
            for k0 in range(0, 48, ks):
                sp = src_perm[k0:k0 + ks].T                        # (6 m^2, ks)
                kk = sp.shape[1]
                o = out_perm[k0:k0 + ks, fund].T                   # (F, ks)
                y0 = (w0 @ np.take(bp, sp, axis=0).reshape(sp.shape[0], -1)).reshape(-1, kk, c)
                if st.level > 0:  # level 0 has no moments
                    y1 = (w1 @ np.take(bm, sp, axis=0).reshape(sp.shape[0], -1))
                    y0 += np.einsum("fkd,fkdc->fkc", dirs[o], y1.reshape(-1, kk, 3, c))
                part[o, :c] = y0
        elif st.columns is None:
            # Dense stage, few outputs (6 g^2 < 48): scatter each output's row of weights to the
            # source texels its symmetry maps them to (a (6 g^2, 6 m^2) matrix per moment), then
            # multiply the source mip as it is (cheaper than gathering it once per output).
            m = src_levels[st.level]
            rows_m = 6 * m * m
            base = offsets[st.level] + np.arange(rows_m)
            idx = (_chain_permute(n, owner_sym[:, None], base[None, :])
                   - offsets[st.level])                            # (6 g^2, 6 m^2)
            out_rows = np.arange(6 * g * g)[:, None]
            block = pyramid[offsets[st.level]:offsets[st.level] + rows_m]
            w0 = np.zeros((6 * g * g, rows_m), dtype=np.float32)
            w0[out_rows, idx] = st.weights[owner_row, 0]
            y = w0 @ block[:, :c]                                  # (6 g^2, C)
            if st.level > 0:  # level 0 has no moments
                w1 = np.zeros((6 * g * g, rows_m), dtype=np.float32)
                w1[out_rows, idx] = st.weights[owner_row, 1]
                mom = (w1 @ block[:, c:]).reshape(-1, 3, c)        # (6 g^2, 3, C)
                y = y + np.einsum("rd,rdc->rc", dirs, mom)
            part[:, :c] = y
        else:
            ww, cols = st.weights, st.columns
            chunk = max(1, _CHUNK_BYTES // (4 * 4 * c * max(ww.shape[2], 1)))
            if st.level == 0 and p_only is None:
                p_only = np.ascontiguousarray(pyramid[:, :c])
            for i in range(0, 6 * g * g, chunk):
                fr = owner_row[i:i + chunk]
                idx = _chain_permute(n, owner_sym[i:i + chunk][:, None], cols[fr])
                if st.level == 0:                                  # input texels: P only
                    x = np.take(p_only, idx, axis=0)               # (r, K, C)
                    part[i:i + chunk, :c] = np.matmul(ww[fr, :1], x)[:, 0]
                    continue
                x = np.take(pyramid, idx, axis=0)                  # (r, K, 4 C)
                y = np.matmul(ww[fr], x)                           # (r, 2, 4 C)
                mom = y[:, 1, c:].reshape(-1, 3, c)
                part[i:i + chunk, :c] = y[:, 0, :c] + np.einsum("rd,rdc->rc",
                                                                 dirs[i:i + chunk], mom)
        part = part.reshape(6, g, g, c + 1)
        if g == size:
            acc += part
        else:
            acc += CubeSampler(part.astype(np.float32)).bilinear(texel_directions(size))
    return (acc[..., :c] / acc[..., c:]).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Dense sums over every input texel, through the cube's symmetries


#: Largest input face size whose whole chain :func:`ggx_prefilter` sums densely (every level
#: exact over every input texel, :func:`symmetric_zonal_sums`).
DENSE_CHAIN_MAX = 128
#: Output rows (fundamental-domain texels) per block of :func:`symmetric_zonal_sums`, and
#: input texels per kernel tile (a tile's temporaries stay in cache: ~6 MB).
_ZONAL_ROWS = 128
_ZONAL_COLUMNS = 4096
#: Far-field option of :func:`symmetric_zonal_sums`: beyond ``_FAR_ALPHAS`` alpha of a GGX
#: block's cone, where the kernel has fallen below ``16 / _FAR_ALPHAS^4`` (4e-5) of its peak,
#: input texels are summed merged ``_FAR_MERGE``^2 at a time. (Not the clamped cosine: merged
#: texels across its horizon moved a 32^2 diffuse map by 0.015 % mean, 2 % at a texel beside
#: the studio HDR's lamps, where the dense sum is within 0.007 % of the converged map.)
_FAR_MERGE = 2
_FAR_ALPHAS = 25.0
#: ... and beyond ``_FAR_TEXELS`` merged texels' widths, where the kernel (~ 1 / angle^4 there)
#: varies by less than 20 % across one (a 64^2 input merges only beyond 56 degrees).
_FAR_TEXELS = 20.0


@dataclass(frozen=True)
class ZonalOutput:
    """One output of :func:`symmetric_zonal_sums`.

    Attributes
    ----------
    size : int
        Output face size.
    kind : {"ggx", "cosine"}
        ``"ggx"``: the normalised GGX prefilter at ``alpha`` (:func:`reference_convolution`);
        ``"cosine"``: ``sum_q max(0, n . w_q) / pi L_q dOmega_q``, irradiance / pi
        (:func:`probegrid.core.diffuse.diffuse_exact`), not normalised.
    alpha : float
        GGX alpha (``"ggx"`` only).
    """

    size: int
    kind: Literal["ggx", "cosine"] = "ggx"
    alpha: float = 0.0


def _zonal_kernel(c: NDArray[np.float64], out: ZonalOutput) -> NDArray[np.float32]:
    """Kernel values (float32) of a block of float64 cosines (overwritten)."""
    if out.kind == "cosine":
        k = c.astype(np.float32)
        np.maximum(k, 0.0, out=k)
        k *= np.float32(1.0 / np.pi)
        return k
    # K = alpha^2 / (4 pi) c / t^2, t = ((1 - c) + alpha^2 (1 + c)) / 2 (lobes.ggx_kernel):
    # 1 - c is formed in float64, so the peak (1 - c ~ alpha^2) keeps float32 precision
    a2 = out.alpha * out.alpha
    np.clip(c, 0.0, 1.0, out=c)
    k = c.astype(np.float32)
    np.subtract(1.0, c, out=c)
    t = c.astype(np.float32)
    t *= np.float32(0.5 * (1.0 - a2))
    t += np.float32(a2)                                   # (1 - c)/2 (1 - a^2) + a^2 = t
    t *= t
    k /= t
    k *= np.float32(a2 / (4.0 * np.pi))
    return k


def prepare_zonal_sums(n: int, outputs: Sequence[ZonalOutput]) -> None:
    """Build the input-independent tables :func:`symmetric_zonal_sums` reads for an ``n``-cube
    and these outputs (the symmetry permutations, fundamental domains, texel directions and
    solid angles; cached per process), so that a caller can make them in one thread while the
    input is still being read or resampled in another. Calling it is optional."""
    _check_size(n, "cube size")
    symmetry_permutations(n)
    texel_solid_angles(n)
    texel_directions(n)
    for o in outputs:
        _check_size(o.size, "output size")
        _fundamental_domain(o.size)
        texel_directions(o.size)


def _merge_rows(x: NDArray[np.float32], n: int, merge: int) -> NDArray[np.float32]:
    """Rows ``(6 n^2, K)`` of an ``n``-cube's texels summed over ``merge x merge`` blocks:
    ``(6 m^2, K)``, ``m = n / merge``, in the merged cube's texel order."""
    m = n // merge
    return x.reshape(6, m, merge, m, merge, -1).sum(axis=(2, 4)).reshape(6 * m * m, -1)


def symmetric_zonal_sums(faces: ArrayLike, outputs: Sequence[ZonalOutput], *,
                         workers: int = 1, far_field: bool = False
                         ) -> list[NDArray[np.float32]]:
    """Zonal sums over every input texel (the midpoint rule on the input, as
    :func:`zonal_convolution`), computed once per cube symmetry class.

    A zonal sum at output direction ``S R`` (``S`` one of the 48 cube symmetries,
    :func:`probegrid.core.cubemap.symmetry_permutations`) equals the sum at ``R`` over the input
    permuted by ``S``. So the kernel is evaluated only for the fundamental-domain outputs
    (:func:`_fundamental_domain`, 1/48 of them) against every input texel (float64 cosines,
    float32 kernel values), and one matrix product per tile (float32 BLAS, sums accumulated in
    float32) applies it to the 48 permuted copies of ``L dOmega`` side by side (one more to
    ``dOmega``: the normaliser). A block of rows reads only the input texels within 90 degrees
    of its cone (both kernels vanish beyond). Cost: ``6 n^2 48 C`` floats for the permuted input
    and at most ``2 F 6 n^2 (48 C + 1)`` flops for ``F`` rows: a 128^2 chain (levels 64^2 ..
    1^2, 715 rows) and a 32^2 diffuse map (136 rows) take ~0.4 s CPU here. The results equal
    :func:`reference_convolution` and :func:`probegrid.core.diffuse.diffuse_exact` to float32
    rounding of the weights and sums (relative 2e-6).

    Parameters
    ----------
    faces : (6, n, n, C) float, finite
    outputs : sequence of ZonalOutput
    workers : int
        Threads sharing the row blocks (BLAS is limited to one thread meanwhile).
    far_field : bool
        Sum the far field of narrow GGX lobes over merged texels: beyond ``_FAR_ALPHAS`` alpha
        of a block's cone, ``2 x 2`` input texels become one (their ``L dOmega`` summed, at
        their solid-angle-weighted mean direction); the near field stays over every input
        texel. For a 128^2 chain that is level 1 (alpha 0.02), 60 % of the work, at 0.6 of its
        cost; the error it adds (1e-6 mean, 2e-3 at worst relative to the dense sum on the
        bundled HDRs) is far below the 128^2 input's own (``benchmarks/bench_filter_cli.py``
        prints every level against the dense sum's floor, ``tests/test_specular.py`` bounds
        it).

    Returns
    -------
    list of (6, size, size, C) float32, one per output.
    """
    src = check_cube(faces, name="faces")
    if not np.all(np.isfinite(src)):
        raise ValueError("faces must be finite (no nan or inf radiance).")
    for o in outputs:
        _check_size(o.size, "output size")
        if o.kind not in ("ggx", "cosine"):
            raise ValueError(f"output kind must be 'ggx' or 'cosine', got {o.kind!r}.")
        if o.kind == "ggx" and not (np.isfinite(o.alpha) and o.alpha > 0):
            raise ValueError(f"alpha must be a finite number > 0, got {o.alpha!r}.")
    if not isinstance(workers, (int, np.integer)) or isinstance(workers, bool) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}.")
    n, c = src.shape[1], src.shape[3]
    perm = symmetry_permutations(n)                                # (48, 6 n^2)
    om = texel_solid_angles(n).reshape(-1)
    lw = src.reshape(-1, c) * om[:, None].astype(np.float32)
    # column block k of row q holds L dOmega at S_k(q) (gathered by the threads, a share each)
    x = np.empty((6 * n * n, 48, c), dtype=np.float32)
    shares = np.linspace(0, 6 * n * n, workers + 1).astype(np.intp)

    def gather(part: int) -> None:
        q0, q1 = shares[part], shares[part + 1]
        np.take(lw, perm.T[q0:q1], axis=0, out=x[q0:q1])

    om32 = om.astype(np.float32)
    sd = texel_directions(n).reshape(-1, 3)
    results = [np.empty((6 * o.size * o.size, c), dtype=np.float32) for o in outputs]

    def far_field_of(o: ZonalOutput) -> tuple[float, int] | None:
        """(angle beyond a block's cone, merge factor) of an output's far field, or None."""
        f = _FAR_MERGE
        if not far_field or o.kind != "ggx" or n % f or n < 4 * f:
            return None
        angle = max(_FAR_ALPHAS * o.alpha, _FAR_TEXELS * f * 0.5 * np.pi / n)
        return (angle, f) if angle < 0.5 * np.pi else None

    jobs = []
    for i, o in enumerate(outputs):
        fund = _fundamental_domain(o.size)[0]
        for r0 in range(0, len(fund), _ZONAL_ROWS):
            jobs.append((i, fund[r0:r0 + _ZONAL_ROWS]))
    # merged texels per factor: members, dOmega summed, mean direction, the cone test's margin
    # (half a merged texel's diagonal, at most) and, once gathered, L dOmega summed
    merged: dict[int, dict[str, Any]] = {}
    for f in sorted({ff[1] for o in outputs if (ff := far_field_of(o)) is not None}):
        m = n // f
        members = np.arange(6 * n * n).reshape(6, m, f, m, f).transpose(0, 1, 3, 2, 4).reshape(
            6 * m * m, f * f)
        dirs = (sd[members] * om[members][..., None]).sum(axis=1)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        reach = float(np.arccos(np.clip(np.einsum("ij,ij->i", sd[members[:, 0]], dirs),
                                        -1.0, 1.0)).max())
        merged[f] = {"members": members, "om32": om[members].sum(axis=1).astype(np.float32),
                     "dirs": dirs, "reach": reach}

    def run(job: tuple[int, NDArray[np.intp]]) -> None:
        i, rows = job
        o = outputs[i]
        od = texel_directions(o.size)[0].reshape(-1, 3)[rows]
        # both kernels vanish for R . w <= 0: only the input texels within 90 degrees of some
        # row (of the cone holding the block's rows) take part
        axis = od.sum(axis=0)
        axis /= np.linalg.norm(axis)
        spread = float(np.arccos(np.clip((od @ axis).min(), -1.0, 1.0)))
        horizon = -np.sin(min(spread, 0.5 * np.pi)) - 1e-12
        far = far_field_of(o)
        y = np.zeros((len(rows), 48 * c), dtype=np.float32)       # (r, 48 C)
        norm = np.zeros(len(rows), dtype=np.float32)
        if far is None:
            near = np.flatnonzero(sd @ axis > horizon)
        else:  # the merged texels beyond the near cone, the input's own within it
            angle, mg = far[0], merged[far[1]]
            cos_far = mg["dirs"] @ axis
            inner = cos_far > np.cos(min(spread + angle + mg["reach"], np.pi))
            outer = np.flatnonzero(~inner & (cos_far > horizon - np.sin(mg["reach"])))
            near = mg["members"][inner].reshape(-1)
            near = np.sort(near[sd[near] @ axis > horizon])
            for q0 in range(0, len(outer), _ZONAL_COLUMNS):
                q = outer[q0:q0 + _ZONAL_COLUMNS]
                k = _zonal_kernel(od @ mg["dirs"][q].T, o)
                y += k @ np.take(mg["x"], q, axis=0)
                norm += k @ mg["om32"][q]
        for q0 in range(0, len(near), _ZONAL_COLUMNS):
            q = near[q0:q0 + _ZONAL_COLUMNS]
            k = _zonal_kernel(od @ sd[q].T, o)
            y += k @ np.take(x, q, axis=0)
            norm += k @ om32[q]
        vals = y.reshape(-1, 48, c)
        if o.kind == "ggx":
            vals /= norm[:, None, None]
        targets = symmetry_permutations(o.size)[:, rows].T         # (r, 48)
        results[i][targets] = vals                                 # (texels on mirror planes
        # are written by several symmetries, with the same value)

    def merge_rows() -> None:
        for f, mg in merged.items():
            mg["x"] = _merge_rows(x, n, f)

    with one_blas_thread():
        if workers == 1:
            gather(0)
            x = x.reshape(6 * n * n, 48 * c)
            merge_rows()
            for job in jobs:
                run(job)
        else:
            with ThreadPoolExecutor(max_workers=workers) as pool:
                list(pool.map(gather, range(workers)))
                x = x.reshape(6 * n * n, 48 * c)
                merge_rows()
                list(pool.map(run, jobs))
    return [r.reshape(6, o.size, o.size, c) for r, o in zip(results, outputs)]


def hammersley(count: int) -> NDArray[np.float64]:
    """The Hammersley point set ``(i / N, radical_inverse_2(i))``: (N, 2) float64 in [0, 1)."""
    i = np.arange(count, dtype=np.uint64)
    bits = i.copy()
    rev = np.zeros(count, dtype=np.uint64)
    for _ in range(32):  # 32 bits of the van der Corput sequence
        rev = (rev << np.uint64(1)) | (bits & np.uint64(1))
        bits >>= np.uint64(1)
    return np.stack([i / count, rev.astype(np.float64) / 2.0**32], axis=1)


def _ggx_fis(sampler: CubeSampler, n: int, alpha: float, size: int, samples: int,
             bias: float) -> NDArray[np.float32]:
    """Filtered importance sampling of one GGX level (Krivanek & Colbert 2008; Karis 2013).

    One fixed Hammersley set of ``samples`` half vectors ``h ~ D(h) (n.h)`` is shared by all
    texels and rotated into each texel's frame (``n = v = R``); ``l = 2 (v.h) h - v``, weight
    ``n.l`` (the GGX importance-sampling estimator of the kernel), looked up trilinearly at
    ``lod = 0.5 log2(Omega_s / Omega_p) + bias`` with ``Omega_s = 1 / (N pdf)``,
    ``pdf = D / 4`` and ``Omega_p = 4 pi / (6 n^2)``; the sum is divided by the sum of the
    weights.
    """
    u = hammersley(samples)
    a2 = alpha * alpha
    c2 = (1.0 - u[:, 1]) / (1.0 + (a2 - 1.0) * u[:, 1])
    ch, sh_ = np.sqrt(c2), np.sqrt(np.maximum(1.0 - c2, 0.0))
    phi = 2.0 * np.pi * u[:, 0]
    hx, hy = sh_ * np.cos(phi), sh_ * np.sin(phi)
    local = np.stack([2.0 * ch * hx, 2.0 * ch * hy, 2.0 * c2 - 1.0], axis=1)   # l, v = +z
    keep = local[:, 2] > 0
    local, ch = local[keep], ch[keep]
    weight = local[:, 2] / local[:, 2].sum()
    pdf = lobes.ggx_ndf(ch, alpha) / 4.0
    omega_p = 4.0 * np.pi / (6.0 * n * n)
    lod = np.clip(0.5 * np.log2(1.0 / (samples * pdf * omega_p)) + bias, 0.0,
                  sampler.num_levels - 1).astype(np.float32)
    d = texel_directions(size).reshape(-1, 3)
    up = np.where(np.abs(d[:, 2:3]) < 0.999, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t = np.cross(up, d)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(d, t)
    frame = np.stack([t, b, d], axis=1).astype(np.float32)                 # rows T, B, N
    local32 = local.astype(np.float32)
    out = np.empty((d.shape[0], sampler.channels), dtype=np.float32)
    rows = max(1, _CHUNK_BYTES // (4 * 8 * local.shape[0]))
    for i in range(0, d.shape[0], rows):
        dirs = np.einsum("sj,rjk->rsk", local32, frame[i:i + rows])       # (r, S, 3)
        vals = sampler.trilinear(dirs, lod)                                # (r, S, C)
        out[i:i + rows] = np.einsum("s,rsc->rc", weight.astype(np.float32), vals)
    return out.reshape(6, size, size, -1)


def ggx_prefilter(
    faces: ArrayLike,
    *,
    levels: int | None = None,
    size: int | None = None,
    method: GGXMethod = "tiered",
    beta: float = 6.0,
    gamma: float = 3.0,
    workers: int = 1,
    samples: int | None = None,
    lod_bias: float = 1.0,
) -> list[NDArray[np.float32]]:
    """GGX prefiltered specular mip chain (split-sum, ``n = v = r``).

    Parameters
    ----------
    faces : (6, n, n, C) float
        Input radiance; ``n`` a power of two for ``method="tiered"``.
    levels : int, optional
        Number of levels (default: down to 1 x 1). Level ``k`` has perceptual roughness
        ``k / (levels - 1)``.
    size : int, optional
        Face size of level 0 (default ``n``); level ``k`` has ``size >> k``.
    method : {"tiered", "fis", "exact"}
        ``"tiered"``: the dense sum through the cube's symmetries for ``n <=``
        :data:`DENSE_CHAIN_MAX`, else the sparse multi-resolution sum (module docstring);
        ``"fis"``: filtered
        importance sampling with ``samples`` Hammersley samples (for comparison: noisier and
        slower at equal accuracy, see the module docstring); ``"exact"``: dense float64 sum over
        every input texel (:func:`reference_convolution`; slow).
    beta, gamma : float
        Accuracy parameters of ``"tiered"`` (see :func:`ggx_tier_plan`).
    workers : int
        Threads (``"tiered"``): sharing the dense sums' blocks of rows, or filtering levels of
        the sparse sum concurrently (level 1 is about half the work, so 2 is the useful
        maximum). Default 1 (a probe grid is parallel at a higher level).
    samples : int, optional
        ``"fis"`` only (default 256): samples per texel (a level gets the same set).
    lod_bias : float
        ``"fis"`` only: added to the lookup's mip level (1.0 = Filament's ``K = 4``).

    Returns
    -------
    list of (6, size >> k, size >> k, C) float32
        Level 0 is a copy of the input (or its antialiased resize when ``size != n``).
    """
    if method not in get_args(GGXMethod):
        raise ValueError(f"method must be one of {get_args(GGXMethod)}, got {method!r}.")
    src = check_cube(faces, name="faces")
    if not np.all(np.isfinite(src)):
        raise ValueError("faces must be finite (no nan or inf radiance).")
    n = src.shape[1]
    base = n if size is None else size
    _check_size(base, "size")
    sizes = mip_sizes(base, levels)
    if method == "tiered" and n & (n - 1):
        raise ValueError(f"method 'tiered' needs a power-of-two input face size, got {n}.")
    if not (beta >= 1 and gamma > 0):
        raise ValueError(f"beta must be >= 1 and gamma > 0, got {beta!r} and {gamma!r}.")
    if not isinstance(workers, (int, np.integer)) or isinstance(workers, bool) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}.")
    if samples is not None and method != "fis":
        raise ValueError(f"samples applies to method 'fis' only, not {method!r}.")
    if samples is not None and (not isinstance(samples, (int, np.integer)) or samples < 1):
        raise ValueError(f"samples must be a positive integer, got {samples!r}.")
    if base == n:
        out = [src.copy()]
    else:
        out = [resample(src, base)]
    if len(sizes) == 1:
        return out
    if method in ("exact", "fis"):
        if method == "fis":
            sampler = CubeSampler(mip_chain(src) if n & (n - 1) == 0 else [src])
        for k, s in enumerate(sizes[1:], start=1):
            alpha = float(lobes.roughness_to_alpha(lobes.level_roughness(k, len(sizes))))
            if method == "exact":
                out.append(reference_convolution(src, alpha, s).astype(np.float32))
            else:
                out.append(_ggx_fis(sampler, n, alpha, s, samples or 256, float(lod_bias)))
        return out
    if n <= DENSE_CHAIN_MAX:  # every level exact, through the cube's symmetries
        out += symmetric_zonal_sums(
            src, [ZonalOutput(s, "ggx", float(lobes.roughness_to_alpha(
                lobes.level_roughness(k, len(sizes))))) for k, s in enumerate(sizes) if k],
            workers=int(workers))
        return out
    # The tiered path makes many small and medium BLAS calls; a second BLAS thread buys nothing
    # there and, on a loaded machine, its spin-waiting made runs 2-10x slower (measured), so
    # BLAS is limited to one thread for the duration of the call; ``workers`` threads filter
    # different levels instead (numpy releases the GIL in the gathers and products).
    with one_blas_thread():
        pyramid = _moment_pyramid(src)
        _chain_layout(n)  # shared caches, built once before any thread needs them
        _geometric_pyramid(n)

        def level(k: int) -> NDArray[np.float32]:
            s = sizes[k]
            alpha = float(lobes.roughness_to_alpha(lobes.level_roughness(k, len(sizes))))
            stages = ggx_tier_plan(n, s, alpha, beta=float(beta), gamma=float(gamma))
            return _apply_plan(pyramid, n, stages, s)

        if workers == 1:
            out += [level(k) for k in range(1, len(sizes))]
        else:
            with ThreadPoolExecutor(max_workers=workers) as pool:
                out += list(pool.map(level, range(1, len(sizes))))
    return out


def clear_caches() -> None:
    """Drop the cached geometry of the tiered filter (plans, symmetry tables: ~150 MB after a
    256^2 chain); the next call rebuilds what it needs."""
    for f in (ggx_tier_plan, _chain_layout, _geometric_pyramid, symmetry_permutations,
              _fundamental_domain):
        f.cache_clear()


def ggx_filter(faces: ArrayLike, alpha: float, size: int, *, beta: float = 6.0,
               gamma: float = 3.0) -> NDArray[np.float32]:
    """One GGX-prefiltered cube at any ``alpha`` (the tiered sum of :func:`ggx_prefilter`).

    Parameters
    ----------
    faces : (6, n, n, C) float
        Input radiance, ``n`` a power of two, finite.
    alpha : float
        GGX alpha > 0 (``roughness ** 2``).
    size : int
        Output face size.
    beta, gamma : float
        Accuracy parameters (:func:`ggx_tier_plan`).

    Returns
    -------
    (6, size, size, C) float32
    """
    src = check_cube(faces, name="faces")
    if not np.all(np.isfinite(src)):
        raise ValueError("faces must be finite (no nan or inf radiance).")
    n = src.shape[1]
    if n & (n - 1):
        raise ValueError(f"the tiered GGX filter needs a power-of-two input size, got {n}.")
    with one_blas_thread():
        stages = ggx_tier_plan(n, size, float(alpha), beta=float(beta), gamma=float(gamma))
        return _apply_plan(_moment_pyramid(src), n, stages, size)
