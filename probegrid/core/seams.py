"""Cube-map edge topology: bordered faces, seam averaging and seam export modes.

A cube map is six separate square textures, but the sphere they tile has no edges. Filtering
that treats each face on its own (clamping at face edges) makes visible seams, and so does a GPU
without ``TEXTURE_CUBE_MAP_SEAMLESS``. This module provides the array math that ties the faces
together; :mod:`probegrid.core.sampling` builds seamless filtering on it.

Bordered layout
---------------
``add_border`` returns ``(6, n + 2, n + 2, C)``: each face with a one-texel border continued from
its neighbours. Bordered index ``(r', c')`` holds real texel ``(r' - 1, c' - 1)`` of the same face
when ``1 <= r', c' <= n``. A *border* texel is a virtual texel of the face's extended plane;
its source is found geometrically, with no hand-written edge table:

* Its centre has face coordinates ``(u, v)`` with one of them ``-1 - 1/n`` or ``1 + 1/n``
  (:func:`probegrid.core.cubemap.texel_to_uv` of index ``-1`` or ``n``). Its direction
  ``face_uv_to_direction(face, u, v)`` is projected with ``direction_to_face_uv`` onto the
  neighbouring face and the texel containing it is taken (floor).
* This lands exactly on the neighbour's edge texel. Proof, for the top border of +Z (all 24
  edges are the same up to the cube's symmetries): column ``c`` has ``u = (2c + 1 - n) / n`` and
  ``v = -1 - 1/n``, direction ``(u, 1 + 1/n, 1)``; the major axis is ``+Y`` with
  ``|y| = (n + 1) / n``, so on +Y ``u' = (2c + 1 - n) / (n + 1)`` and ``v' = n / (n + 1)``.
  The texel row is ``floor((v' + 1) n / 2) = floor(n - n / (2 (n + 1))) = n - 1`` (the edge row),
  and the column is ``floor((u' + 1) n / 2) = floor((c + 1) n / (n + 1))
  = c + floor(1 - (c + 1) / (n + 1)) = c``, because ``0 < (c + 1) / (n + 1) < 1``. Neither value
  is ever within ``1 / (2 (n + 1))`` of an integer, so rounding cannot change the floor.
  (``tests/test_seams.py`` checks adjacency and symmetry for every ``n`` up to 64.)
* The four corner border texels lie diagonally off the cube corner, where three faces meet and
  no single neighbour texel exists. Each is the *average of the three real corner texels* meeting
  at that cube corner (the face's own corner texel and the two neighbours' edge-end texels), the
  seed of Bloom's "cube map lighting" seam fix. Bilinear filtering over such a border is
  continuous across edges *and* at the corners: at the exact cube corner all three faces give the
  mean of the three corner texels.

Seam export modes
-----------------
``SeamMode``: ``"none"`` (faces as they are), ``"average"`` (:func:`average_seams`: texels that
touch across an edge are replaced by their mean, corner texels by the mean of the three at the
corner, so a non-seamless sampler that clamps to edge shows no discontinuity) and ``"border"``
(:func:`add_border`: ``(n + 2)``-sized faces for a renderer that samples the inner
``[1/(n+2), (n+1)/(n+2)]`` uv range, as in padded texture-atlas layouts).

References
----------
* J. Blinn and M. Newell, "Texture and reflection in computer generated images", 1976.
* C. Bloom, "Cube map lighting", 2000 (averaging corner texels over the three faces).
* T. Scheuermann and J. Isidoro, "Cubemap filtering with CubeMapGen", GDC 2005 (edge fixup).
* OpenGL 4.6 section 8.13.1, ``TEXTURE_CUBE_MAP_SEAMLESS`` (which leaves corners undefined).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache
from typing import Final, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._types import SeamMode
from probegrid.core.cubemap import (
    check_cube,
    direction_to_face_uv,
    face_uv_to_direction,
    texel_to_uv,
)

__all__ = [
    "SEAM_MODES",
    "SeamMode",
    "add_border",
    "apply_seam_mode",
    "average_seams",
    "border_sources",
    "seam_score",
]

#: The allowed seam export modes, in the order of :data:`SeamMode`.
SEAM_MODES: Final[tuple[str, ...]] = get_args(SeamMode)


def _check_size(n: int) -> int:
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
        raise ValueError(f"The cube face size must be a positive integer, got {n!r}.")
    return int(n)


def _readonly(*arrays: NDArray) -> None:
    for a in arrays:
        a.setflags(write=False)


def _virtual_sources(
    face: NDArray[np.intp], rb: NDArray[np.intp], cb: NDArray[np.intp], n: int
) -> NDArray[np.intp]:
    """Real texel ``(face, row, col)`` (K, 3) under the centre of each edge border texel
    ``(face, rb, cb)`` (bordered indices), by projection (see the module docstring)."""
    u = texel_to_uv(cb - 1, n)
    v = texel_to_uv(rb - 1, n)
    g, gu, gv = direction_to_face_uv(face_uv_to_direction(face, u, v))
    col = np.floor((gu + 1.0) * (0.5 * n)).astype(np.intp)
    row = np.floor((gv + 1.0) * (0.5 * n)).astype(np.intp)
    return np.stack([g, row, col], axis=-1)


@lru_cache(maxsize=32)
def _ring(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """The border ring of every face, O(n) memory.

    Returns
    -------
    edge_pos : (6 * 4n, 3) intp
        ``(face, r', c')`` of the edge border texels, face-major then raster order.
    edge_src : (6 * 4n, 3) intp
        The real ``(face, row, col)`` each copies.
    corner_pos : (24, 3) intp
        ``(face, r', c')`` of the corner border texels, same order.
    corner_src : (24, 3, 3) intp
        The three real texels each averages: the face's own corner texel, then the texels across
        the row edge and across the column edge.
    """
    m = n + 2
    line = np.arange(1, m - 1)
    last = m - 1
    # one face's edge border positions in raster order: top row, side columns, bottom row
    er = np.concatenate([np.zeros(n, np.intp), np.repeat(line, 2), np.full(n, last)])
    ec = np.concatenate([line, np.tile([0, last], n), line])
    edge_pos = np.stack([np.repeat(np.arange(6), er.size), np.tile(er, 6), np.tile(ec, 6)], -1)
    edge_src = _virtual_sources(*edge_pos.T, n)

    cr = np.array([0, 0, last, last])
    cc = np.array([0, last, 0, last])
    corner_pos = np.stack([np.repeat(np.arange(6), 4), np.tile(cr, 6), np.tile(cc, 6)], -1)
    f, rb, cb = corner_pos.T
    ri = np.where(rb == 0, 1, m - 2)  # the adjacent real row / column, bordered indices
    ci = np.where(cb == 0, 1, m - 2)
    own = np.stack([f, ri - 1, ci - 1], axis=-1)
    corner_src = np.stack(
        [own, _virtual_sources(f, rb, ci, n), _virtual_sources(f, ri, cb, n)], axis=1
    )
    out = (edge_pos, edge_src, corner_pos, corner_src)
    _readonly(*out)
    return out


def _build_border_sources(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    m = n + 2
    shape = (6, m, m, 3)
    face = np.broadcast_to(np.arange(6)[:, None, None, None], shape).copy()
    row = np.broadcast_to((np.arange(m) - 1)[None, :, None, None], shape).copy()
    col = np.broadcast_to((np.arange(m) - 1)[None, None, :, None], shape).copy()
    edge_pos, edge_src, corner_pos, corner_src = _ring(n)
    for out, j in ((face, 0), (row, 1), (col, 2)):
        out[tuple(edge_pos.T)] = edge_src[:, j, None]
        out[tuple(corner_pos.T)] = corner_src[:, :, j]
    _readonly(face, row, col)
    return face, row, col


_border_sources_cached = lru_cache(maxsize=8)(_build_border_sources)

#: border_sources() caches its (large: 72 (n + 2)^2 bytes) tables only up to this face size.
_BORDER_SOURCES_CACHE_MAX: Final = 256


def border_sources(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """Which real texel each texel of the bordered layout copies.

    Parameters
    ----------
    n : int
        Face size of the real cube (``n >= 1``).

    Returns
    -------
    face, row, col : (6, n + 2, n + 2, 3) intp, read-only (cached for ``n <= 256``)
        For bordered texel ``[f, r', c']`` the last axis lists the real texels
        ``(face[.., j], row[.., j], col[.., j])`` whose average it holds: three distinct corner
        texels for the 4 corner border texels of each face, three copies of one texel for every
        other (interior or edge-border) texel. Interior texels copy ``(f, r' - 1, c' - 1)``.
    """
    n = _check_size(n)
    if n <= _BORDER_SOURCES_CACHE_MAX:
        return _border_sources_cached(n)
    return _build_border_sources(n)


@lru_cache(maxsize=32)
def _ring_indices(
    n: int,
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """Flat indices for :func:`add_border`.

    Returns ``edge_dst`` (E,) into the flattened bordered cube ``6 (n+2)^2``, ``edge_src`` (E,)
    into the flattened real cube ``6 n^2``, ``corner_dst`` (24,) and ``corner_src`` (24, 3),
    each triple sorted so that equal corners sum in the same order.
    """
    m = n + 2
    edge_pos, edge_src, corner_pos, corner_src = _ring(n)

    def dst(p: NDArray[np.intp]) -> NDArray[np.intp]:
        return (p[..., 0] * m + p[..., 1]) * m + p[..., 2]

    def src(p: NDArray[np.intp]) -> NDArray[np.intp]:
        return (p[..., 0] * n + p[..., 1]) * n + p[..., 2]

    out = (dst(edge_pos), src(edge_src), dst(corner_pos), np.sort(src(corner_src), axis=-1))
    _readonly(*out)
    return out


def _inner_of_edge(n: int) -> NDArray[np.intp]:
    """(E,) flat index into ``6 n^2`` of the real texel just inside each edge border texel."""
    edge_pos = _ring(n)[0]
    f, r, c = edge_pos.T
    return (f * n + np.clip(r, 1, n) - 1) * n + np.clip(c, 1, n) - 1


def add_border(faces: ArrayLike) -> NDArray[np.float32]:
    """Faces with a one-texel border continued from their neighbours (the ``"border"`` mode).

    Parameters
    ----------
    faces : (6, n, n, C) float (or (6, n, n))

    Returns
    -------
    (6, n + 2, n + 2, C) float32
        ``out[:, 1:-1, 1:-1] == faces``; an edge border texel equals the neighbour face's texel
        across the edge; a corner border texel is the mean of the three real texels at that cube
        corner (computed in float64).
    """
    a = check_cube(faces)
    n, c = a.shape[1], a.shape[3]
    edge_dst, edge_src, corner_dst, corner_src = _ring_indices(n)
    out = np.empty((6, n + 2, n + 2, c), dtype=np.float32)
    out[:, 1:-1, 1:-1] = a
    flat_out = out.reshape(-1, c)
    flat_in = a.reshape(-1, c)
    flat_out[edge_dst] = flat_in[edge_src]
    flat_out[corner_dst] = _class_mean(flat_in, corner_src)
    return out


def _class_mean(flat: NDArray[np.float32], members: NDArray[np.intp]) -> NDArray[np.float32]:
    """Mean of ``flat[members]`` over the last index axis, summed in a fixed order in float64.

    ``members`` (K, m) -> (K, C) float32. Rows holding the same (sorted) members give bit-equal
    results.
    """
    acc = flat[members[:, 0]].astype(np.float64)
    for j in range(1, members.shape[1]):
        acc += flat[members[:, j]]
    return (acc / members.shape[1]).astype(np.float32)


@lru_cache(maxsize=32)
def _seam_classes(n: int) -> tuple[tuple[NDArray[np.intp], NDArray[np.intp]], ...]:
    """Groups of real texels that touch across face edges, as flat indices into ``6 n^2``.

    Returns ``((targets, members), ...)``: ``targets`` (K,) and ``members`` (K, m) sorted, with
    ``targets[i] in members[i]``. For ``n >= 2``: pairs for edge texels that are not at a corner,
    triples for corner texels. For ``n = 1`` every face touches every adjacent face and the
    transitive closure is the whole cube: one class of 6.
    """
    if n == 1:
        t = np.arange(6)
        out: tuple[tuple[NDArray[np.intp], NDArray[np.intp]], ...] = (
            (t, np.broadcast_to(t, (6, 6)).copy()),
        )
    else:
        m = n + 2
        edge_pos = _ring(n)[0]
        _, edge_src, corner_dst, corner_src = _ring_indices(n)
        inner = _inner_of_edge(n)
        along = np.where((edge_pos[:, 1] == 0) | (edge_pos[:, 1] == m - 1),
                         edge_pos[:, 2], edge_pos[:, 1])
        keep = (along >= 2) & (along <= m - 3)  # inner texel is not a corner texel
        pairs = np.sort(np.stack([inner[keep], edge_src[keep]], axis=-1), axis=-1)
        f_c, rem = np.divmod(corner_dst, m * m)
        r_c, c_c = np.divmod(rem, m)
        corner_tgt = (f_c * n + np.clip(r_c, 1, n) - 1) * n + np.clip(c_c, 1, n) - 1
        out = ((inner[keep], pairs), (corner_tgt, corner_src.copy()))
    for t, mem in out:
        _readonly(t, mem)
    return out


def average_seams(faces: ArrayLike) -> NDArray[np.float32]:
    """Make texels that touch across face edges equal (the ``"average"`` export mode).

    Parameters
    ----------
    faces : (6, n, n, C) float (or (6, n, n))

    Returns
    -------
    (6, n, n, C) float32
        Each non-corner edge texel and the texel across the edge both become their mean; the
        three corner texels meeting at a cube corner all become their mean; interior texels are
        unchanged. Every pair of texels touching across an edge is then bit-equal. For ``n = 1``
        every face touches four others, so all six texels become the cube's mean.
    """
    a = check_cube(faces)
    n, c = a.shape[1], a.shape[3]
    out = a.copy()
    flat_in = a.reshape(-1, c)
    flat_out = out.reshape(-1, c)
    for targets, members in _seam_classes(n):
        flat_out[targets] = _class_mean(flat_in, members)
    return out


def apply_seam_mode(levels: Sequence[ArrayLike], mode: SeamMode) -> list[NDArray[np.float32]]:
    """Apply a seam export mode to every level of a mip chain.

    Parameters
    ----------
    levels : sequence of (6, n_k, n_k, C) float
    mode : {"none", "average", "border"}
        See the module docstring. ``"none"`` returns float32 copies.

    Returns
    -------
    list of (6, n_k, n_k, C) float32, or (6, n_k + 2, n_k + 2, C) for ``"border"``.
    """
    if mode not in SEAM_MODES:
        raise ValueError(f"Unknown seam mode {mode!r}; expected one of {', '.join(SEAM_MODES)}.")
    if isinstance(levels, np.ndarray):
        # ValueError, the project's one exception type for bad arguments.
        raise ValueError(  # noqa: TRY004
            "levels must be a sequence of cube arrays, not a single array."
        )
    if mode == "average":
        return [average_seams(a) for a in levels]
    if mode == "border":
        return [add_border(a) for a in levels]
    return [check_cube(a, name=f"level {k}").copy() for k, a in enumerate(levels)]


def seam_score(faces: ArrayLike) -> float:
    """Seam visibility: mean ``|a - b|`` over texels ``a, b`` adjacent across face edges,
    divided by the mean absolute texel value.

    Parameters
    ----------
    faces : (6, n, n, C) float

    Returns
    -------
    float
        Dimensionless, >= 0 (nan if the cube holds nan); 0 after :func:`average_seams` and for
        an all-zero or constant cube. A smooth environment gives about the texel-to-texel
        variation inside faces, so compare scores of the same image before and after a seam
        treatment.
    """
    a = check_cube(faces)
    n, c = a.shape[1], a.shape[3]
    flat = a.reshape(-1, c)
    i, j = _inner_of_edge(n), _ring_indices(n)[1]
    diff = float(np.mean(np.abs(flat[i].astype(np.float64) - flat[j])))
    scale = float(np.mean(np.abs(flat), dtype=np.float64))
    if scale == 0.0:  # an all-zero cube (then diff is 0 too)
        return 0.0
    return diff / scale
