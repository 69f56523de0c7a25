"""Cube-map conventions, texel geometry and the cube-map type.

This module *owns* the project's cube-map conventions; every other module imports them from here.

Face order and orientation
--------------------------
Faces are stored in the order ``+X, -X, +Y, -Y, +Z, -Z`` (index 0-5), the order of OpenGL's
``GL_TEXTURE_CUBE_MAP_POSITIVE_X + i``, Vulkan's array layers and KTX/KTX2 files. A face is an
``(n, n, C)`` array whose row 0 is the *top* row of the image. Within a face, ``u`` runs left to
right and ``v`` top to bottom, both in ``[-1, 1]`` with texel centres at::

    u = 2 * (col + 0.5) / n - 1        v = 2 * (row + 0.5) / n - 1

and the (unnormalised) direction of a point ``(u, v)`` of each face is the OpenGL / Vulkan / KTX2
table::

    +X: ( 1, -v, -u)      -X: (-1, -v,  u)
    +Y: ( u,  1,  v)      -Y: ( u, -1, -v)
    +Z: ( u, -v,  1)      -Z: (-u, -v, -1)

Laid out as a horizontal cross (as :mod:`probegrid.core.layouts` writes it)::

            +----+
            | +Y |
       +----+----+----+----+
       | -X | +Z | +X | -Z |
       +----+----+----+----+
            | -Y |
            +----+

Directions are in the glTF world frame (right-handed, +Y up, -Z forward), so a GPU lookup
``texture(cube, world_dir)`` of an uploaded cube returns what was stored for ``world_dir``.

Texels
------
Cube arrays are ``(6, n, n, C)`` float32 (linear scene-referred Rec.709 RGB for ``C = 3``).
Geometry (directions, solid angles) is float64. The exact solid angle of the patch
``[u0, u1] x [v0, v1]`` of a face is ``F(u1, v1) - F(u0, v1) - F(u1, v0) + F(u0, v0)`` with
``F(x, y) = atan2(x y, sqrt(x^2 + y^2 + 1))``, the integral of the area element
``(1 + u^2 + v^2)^(-3/2) du dv`` of the unit cube projected onto the sphere (Girard; see also
Driscoll, "Cubemap texel solid angle", 2012). The 6 n^2 solid angles sum to 4 pi.

Symmetries
----------
The 48 symmetries of the cube (signed axis permutations, :func:`symmetry_group`) map the cube
onto itself and texel centres onto texel centres, keeping angles and solid angles; each one
permutes the texels of a cube (:func:`symmetry_permutations`, :func:`texel_permutation`) by index
arithmetic. Filters whose weights depend only on angles compute a fundamental domain and reuse it
through them (:mod:`probegrid.core.probefilter` with :func:`face_symmetries`,
:mod:`probegrid.core.specular` with the whole group).

Mip levels halve the face size (``n >> level``); a mip of a cube is the solid-angle-weighted mean
of the 2 x 2 texels it covers, i.e. the mean radiance over the coarse texel's solid angle.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import lru_cache
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "FACE_NAMES",
    "FACE_NORMALS",
    "FACE_U",
    "FACE_V",
    "CubeMap",
    "check_cube",
    "direction_to_face",
    "direction_to_face_uv",
    "direction_to_texel",
    "downsample",
    "face_symmetries",
    "face_uv_to_direction",
    "mip_sizes",
    "normalization_cube",
    "solid_angle_corner",
    "solid_angle_integral",
    "symmetry_group",
    "symmetry_permutations",
    "texel_directions",
    "texel_permutation",
    "texel_solid_angles",
    "texel_to_uv",
    "texel_uv",
    "uv_to_texel",
]

#: Face names in storage order.
FACE_NAMES: Final[tuple[str, ...]] = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")

#: ``direction(face, u, v) = FACE_NORMALS[face] + u * FACE_U[face] + v * FACE_V[face]``.
#: (6, 3) float64; the three rows of each face are orthonormal.
FACE_NORMALS: Final[NDArray[np.float64]] = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64
)
FACE_U: Final[NDArray[np.float64]] = np.array(
    [[0, 0, -1], [0, 0, 1], [1, 0, 0], [1, 0, 0], [1, 0, 0], [-1, 0, 0]], dtype=np.float64
)
FACE_V: Final[NDArray[np.float64]] = np.array(
    [[0, -1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1], [0, -1, 0], [0, -1, 0]], dtype=np.float64
)
for _a in (FACE_NORMALS, FACE_U, FACE_V):
    _a.setflags(write=False)


def face_uv_to_direction(face: ArrayLike, u: ArrayLike, v: ArrayLike) -> NDArray[np.float64]:
    """Unnormalised direction of face coordinates.

    Parameters
    ----------
    face : (...) int
        Face index 0-5.
    u, v : (...) float
        Face coordinates, ``[-1, 1]`` on the face (values outside extend the face plane).

    Returns
    -------
    (..., 3) float64
        ``FACE_NORMALS[face] + u FACE_U[face] + v FACE_V[face]``; its largest component is 1 in
        magnitude when ``|u|, |v| <= 1``.
    """
    f = np.asarray(face, dtype=np.intp)
    uu = np.asarray(u, dtype=np.float64)[..., None]
    vv = np.asarray(v, dtype=np.float64)[..., None]
    return FACE_NORMALS[f] + uu * FACE_U[f] + vv * FACE_V[f]


def _major_axis(d: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """The face of each direction ``d (..., 3)`` (its major axis and sign; ties go to X, then
    Y, then Z) and the direction's component along that axis."""
    if d.shape[-1:] != (3,):
        raise ValueError(f"directions must have shape (..., 3), got {d.shape}")
    a = np.abs(d)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    is_x = (a[..., 0] >= a[..., 1]) & (a[..., 0] >= a[..., 2])
    is_y = ~is_x & (a[..., 1] >= a[..., 2])
    axis = np.where(is_x, 0, np.where(is_y, 1, 2))
    comp = np.where(is_x, x, np.where(is_y, y, z))
    return (2 * axis + (comp < 0)).astype(np.intp), comp


def direction_to_face(directions: ArrayLike) -> NDArray[np.intp]:
    """The face a direction lands on (:func:`direction_to_face_uv`'s face alone): the face of
    its major axis and sign, ties to X, then Y, then Z; the zero vector maps to +X."""
    return _major_axis(np.asarray(directions, dtype=np.float64))[0]


def direction_to_face_uv(
    directions: ArrayLike,
) -> tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.float64]]:
    """Face and face coordinates a direction lands on (the GPU's cube-map face selection).

    The face is the one of the major axis; ties go to X, then Y, then Z. Directions need not be
    normalised; the zero vector maps to +X, (0, 0).

    Parameters
    ----------
    directions : (..., 3) float

    Returns
    -------
    face : (...) intp
    u, v : (...) float64 in [-1, 1]
    """
    d = np.asarray(directions, dtype=np.float64)
    face, comp = _major_axis(d)
    ma = np.abs(comp)
    ma = np.where(ma > 0, ma, 1.0)
    u = np.einsum("...i,...i->...", d, FACE_U[face]) / ma
    v = np.einsum("...i,...i->...", d, FACE_V[face]) / ma
    return face, np.clip(u, -1.0, 1.0), np.clip(v, -1.0, 1.0)


def uv_to_texel(uv: ArrayLike, n: int) -> NDArray[np.float64]:
    """Continuous texel coordinate (column for ``u``, row for ``v``) of a face coordinate.

    Texel ``k``'s centre is at ``k``; the face spans ``[-0.5, n - 0.5]``.
    """
    return (np.asarray(uv, dtype=np.float64) + 1.0) * (0.5 * n) - 0.5


def texel_to_uv(k: ArrayLike, n: int) -> NDArray[np.float64]:
    """Face coordinate of a (continuous) texel coordinate; inverse of :func:`uv_to_texel`."""
    return (np.asarray(k, dtype=np.float64) + 0.5) * (2.0 / n) - 1.0


def direction_to_texel(
    directions: ArrayLike, n: int
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """Face, row and column of the texel of an ``n x n``-face cube containing each direction.

    Parameters
    ----------
    directions : (..., 3) float
    n : int
        Face size in texels.

    Returns
    -------
    face, row, col : (...) intp
    """
    _check_size(n)
    face, u, v = direction_to_face_uv(directions)
    col = np.clip(np.floor((u + 1.0) * (0.5 * n)), 0, n - 1).astype(np.intp)
    row = np.clip(np.floor((v + 1.0) * (0.5 * n)), 0, n - 1).astype(np.intp)
    return face, row, col


@lru_cache(maxsize=1)
def symmetry_group() -> NDArray[np.float64]:
    """The 48 symmetries of the cube (signed 3 x 3 permutation matrices), identity first.

    Each maps the cube onto itself and, because texel centres are symmetric on a face
    (``-u_k = u_{n-1-k}``), texel centres onto texel centres; it preserves angles and solid
    angles (:func:`symmetry_permutations`). (48, 3, 3) float64, read-only.
    """
    mats = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            m = np.zeros((3, 3))
            m[np.arange(3), perm] = np.where(np.array(signs) == 0, 1.0, -1.0)
            mats.append(m)
    out = np.stack(mats)
    out.setflags(write=False)
    return out


@lru_cache(maxsize=1)
def _symmetry_face_table() -> NDArray[np.intp]:
    """How each cube symmetry moves each face: ``(48, 6, 3)`` rows ``[g', column source,
    row source]``, a source 0-3 meaning ``j, i, n - 1 - j, n - 1 - i`` of texel ``(i, j)`` (row,
    column). ``S`` maps face ``g`` onto the face ``g'`` with normal ``S N_g`` and ``(u, v)`` onto
    ``(+-u or +-v, +-v or +-u)``; ``-u`` of column ``j`` is column ``n - 1 - j``."""
    group = symmetry_group()
    table = np.empty((48, 6, 3), dtype=np.intp)
    for k in range(48):
        m = group[k]
        for g in range(6):
            ng, ug, vg = m @ FACE_NORMALS[g], m @ FACE_U[g], m @ FACE_V[g]
            g2 = int(np.argmax(FACE_NORMALS @ ng))
            table[k, g, 0] = g2
            for t, axis in ((1, FACE_U[g2]), (2, FACE_V[g2])):  # u' = (S U_g).U_g' u + ...
                a, c = float(ug @ axis), float(vg @ axis)
                table[k, g, t] = (0 if a != 0 else 1) + (0 if (a if a != 0 else c) > 0 else 2)
    table.setflags(write=False)
    return table


def _texel_maps(table: NDArray[np.intp], n: int, dtype: type) -> NDArray[np.integer]:
    """Flat texel indices ``(..., 6, n, n)`` of rows ``(..., 6, 3)`` of
    :func:`_symmetry_face_table`: texel ``(g, i, j)`` goes to ``(g', source 2, source 1)``."""
    i, j = np.meshgrid(np.arange(n, dtype=dtype), np.arange(n, dtype=dtype), indexing="ij")
    sources = np.stack([j, i, n - 1 - j, n - 1 - i])              # (4, n, n)
    return ((table[..., 0, None, None].astype(dtype) * n + sources[table[..., 2]]) * n
            + sources[table[..., 1]])


@lru_cache(maxsize=16)
def symmetry_permutations(n: int) -> NDArray[np.int32]:
    """Where each cube symmetry sends each texel of an ``n``-cube.

    ``perm[k, q]``: flat index (face-major ``(face, row, col)``) of the texel whose centre is
    ``S_k w_q``, for the 48 symmetries ``S_k`` of :func:`symmetry_group`; by index arithmetic
    (each symmetry moves whole faces and flips or swaps their rows and columns). (48, 6 n^2)
    int32, read-only.
    """
    _check_size(n)
    perm = _texel_maps(_symmetry_face_table(), n, np.int32).reshape(48, -1)
    perm.setflags(write=False)
    return perm


@lru_cache(maxsize=1)
def face_symmetries() -> NDArray[np.float64]:
    """The symmetries of the cube that carry face 0 (``+X``) onto each face, frame and all.

    Returns
    -------
    (6, 3, 3) float64, read-only
        ``S[f]`` maps face 0's normal, ``u`` and ``v`` axes onto face ``f``'s
        (``S[f] @ FACE_NORMALS[0] = FACE_NORMALS[f]``, likewise ``FACE_U``, ``FACE_V``): a
        signed permutation matrix (a rotation or a reflection, one of :func:`symmetry_group`),
        so it maps the texel ``(0, row, col)`` of any cube onto the texel ``(f, row, col)`` and
        the texel grid onto itself (:func:`texel_permutation`). A filter whose weights depend
        only on the angle between directions acts on face ``f`` as it acts on face 0 after
        ``S[f]`` (:mod:`probegrid.core.probefilter`).
    """
    frames = np.stack([FACE_NORMALS, FACE_U, FACE_V], axis=-1)  # (6, 3, 3): columns n, u, v
    out = np.einsum("fij,kj->fik", frames, frames[0])  # frames[f] @ frames[0].T
    out.setflags(write=False)
    return out


def texel_permutation(symmetry: ArrayLike, n: int) -> NDArray[np.int64]:
    """Where a symmetry of the cube sends each texel of an ``n``-cube.

    ``symmetry``: a ``(3, 3)`` signed permutation matrix ``S``. Returns ``(6 n^2,)`` int64:
    entry ``c`` is the flat index (face-major ``(face, row, col)``) of the texel whose centre is
    ``S`` applied to texel ``c``'s centre (the row of :func:`symmetry_permutations` of ``S``,
    computed alone). Raises ``ValueError`` when ``S`` is not a signed permutation (it would not
    map texels onto texels).
    """
    s = np.asarray(symmetry, dtype=np.float64)
    if (s.shape != (3, 3) or not np.all(np.isin(s, (-1.0, 0.0, 1.0)))
            or not np.array_equal(np.abs(s).sum(axis=0), np.ones(3))
            or not np.array_equal(np.abs(s).sum(axis=1), np.ones(3))):
        raise ValueError(f"a symmetry of the cube is a signed permutation matrix, got {s!r}")
    _check_size(n)
    k = int(np.flatnonzero(np.all(symmetry_group() == s, axis=(1, 2)))[0])
    return _texel_maps(_symmetry_face_table()[k], n, np.int64).reshape(-1)


def _check_size(n: int) -> None:
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
        raise ValueError(f"cube face size must be a positive integer, got {n!r}")


def texel_uv(n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Face coordinates of the texel centres of an ``n x n`` face.

    Returns
    -------
    u, v : (n, n) float64, indexed ``[row, col]``
    """
    _check_size(n)
    c = texel_to_uv(np.arange(n), n)
    u, v = np.meshgrid(c, c, indexing="xy")
    return u, v


@lru_cache(maxsize=16)
def _texel_directions(n: int, normalized: bool) -> NDArray[np.float64]:
    u, v = texel_uv(n)
    d = face_uv_to_direction(np.arange(6)[:, None, None], u[None], v[None])
    if normalized:
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
    d.setflags(write=False)
    return d


def texel_directions(n: int, *, normalized: bool = True) -> NDArray[np.float64]:
    """Directions of the texel centres of a cube with ``n x n`` faces.

    Returns
    -------
    (6, n, n, 3) float64, read-only (cached)
        Unit vectors when ``normalized`` (default), else points on the cube ``max|.| = 1``.
    """
    _check_size(n)
    return _texel_directions(int(n), bool(normalized))


def solid_angle_corner(x: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
    """``F(x, y) = atan2(x y, sqrt(x^2 + y^2 + 1))``: the solid angle of the face patch
    ``[0, x] x [0, y]`` (signed), so a patch ``[u0, u1] x [v0, v1]`` subtends
    ``F(u1, v1) - F(u0, v1) - F(u1, v0) + F(u0, v0)`` (module docstring)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    return np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))


@lru_cache(maxsize=16)
def _texel_solid_angles(n: int) -> NDArray[np.float64]:
    e = np.linspace(-1.0, 1.0, n + 1)
    x0, y0 = np.meshgrid(e[:-1], e[:-1], indexing="xy")
    x1, y1 = np.meshgrid(e[1:], e[1:], indexing="xy")
    w = (
        solid_angle_corner(x1, y1)
        - solid_angle_corner(x0, y1)
        - solid_angle_corner(x1, y0)
        + solid_angle_corner(x0, y0)
    )
    out = np.broadcast_to(w, (6, n, n)).copy()
    out.setflags(write=False)
    return out


def texel_solid_angles(n: int) -> NDArray[np.float64]:
    """Exact solid angle of every texel of a cube with ``n x n`` faces.

    Returns
    -------
    (6, n, n) float64, read-only (cached), steradians; sums to 4 pi.
    """
    _check_size(n)
    return _texel_solid_angles(int(n))


def solid_angle_integral(faces: ArrayLike) -> NDArray[np.float64]:
    """``integral L dw`` of a cube over the sphere, per channel (exact texel solid angles).

    Parameters
    ----------
    faces : (6, n, n, C) float

    Returns
    -------
    (C,) float64
        For a radiance cube, the irradiance it would deliver to a sphere's worth of normals
        divided by pi; a constant cube of value L gives ``4 pi L``.
    """
    a = check_cube(faces)
    return np.einsum("fij,fijc->c", texel_solid_angles(a.shape[1]), a, dtype=np.float64)


def normalization_cube(n: int, *, encoded: bool = False) -> NDArray[np.float32]:
    """A normalisation cube map: each texel holds the unit direction of its centre.

    Parameters
    ----------
    n : int
        Face size.
    encoded : bool
        If true, store ``0.5 * d + 0.5`` (the classic RGB8-friendly encoding, ``_bx2`` in
        ps.1.x shaders) instead of ``d``.

    Returns
    -------
    (6, n, n, 3) float32
    """
    d = texel_directions(n).astype(np.float32)
    return (0.5 * d + 0.5).astype(np.float32) if encoded else d


def check_cube(faces: ArrayLike, *, name: str = "cube") -> NDArray[np.float32]:
    """Validate a cube array and return it as float32 ``(6, n, n, C)``.

    Raises ``ValueError`` with a one-line message for a wrong shape.
    """
    a = np.asarray(faces)
    if a.ndim == 3:
        a = a[..., None]
    if a.ndim != 4 or a.shape[0] != 6 or a.shape[1] != a.shape[2] or a.shape[1] < 1:
        raise ValueError(f"{name} must have shape (6, n, n, C), got {a.shape}")
    return np.asarray(a, dtype=np.float32)


def downsample(faces: ArrayLike) -> NDArray[np.float32]:
    """One mip step: each ``2 x 2`` block becomes its solid-angle-weighted mean.

    Parameters
    ----------
    faces : (6, n, n, C) float, n even

    Returns
    -------
    (6, n // 2, n // 2, C) float32
    """
    a = check_cube(faces)
    n = a.shape[1]
    if n % 2:
        raise ValueError(f"cannot halve an odd face size {n}")
    w = texel_solid_angles(n)[..., None]
    h = n // 2
    num = (a.astype(np.float64) * w).reshape(6, h, 2, h, 2, -1).sum(axis=(2, 4))
    den = w.reshape(6, h, 2, h, 2, 1).sum(axis=(2, 4))
    return (num / den).astype(np.float32)


def mip_sizes(n: int, levels: int | None = None) -> list[int]:
    """Face sizes of a mip chain: ``n, n/2, ..., 1`` (``levels`` of them if given).

    ``n`` must be a power of two for a full chain; ``levels`` may not exceed ``log2(n) + 1``.
    """
    _check_size(n)
    full = int(np.log2(n)) + 1 if (n & (n - 1)) == 0 else None
    if levels is None:
        if full is None:
            raise ValueError(f"a full mip chain needs a power-of-two face size, got {n}")
        levels = full
    if levels < 1:
        raise ValueError(f"levels must be >= 1, got {levels}")
    sizes = [n >> k for k in range(levels)]
    if sizes[-1] < 1 or any(s * 2 != p for p, s in itertools.pairwise(sizes)):
        raise ValueError(f"face size {n} cannot be halved {levels - 1} times")
    return sizes


@dataclass(frozen=True, eq=False)
class CubeMap:
    """A cube map with an optional mip chain.

    Attributes
    ----------
    levels : tuple of (6, n_k, n_k, C) float32
        ``levels[k]`` has face size ``n >> k``. Level 0 is the full-resolution cube.
    kind : str
        What it holds: ``"incoming"`` (radiance), ``"diffuse"`` (irradiance / pi),
        ``"specular"`` (GGX prefiltered radiance, level ``k`` at perceptual roughness
        ``k / (len(levels) - 1)``), or ``"other"``.
    """

    levels: tuple[NDArray[np.float32], ...]
    kind: str = "other"

    def __post_init__(self) -> None:
        if not self.levels:
            raise ValueError("a CubeMap needs at least one level")
        lv = tuple(check_cube(a, name=f"level {k}") for k, a in enumerate(self.levels))
        n, c = lv[0].shape[1], lv[0].shape[3]
        for k, a in enumerate(lv):
            if a.shape != (6, max(n >> k, 1), max(n >> k, 1), c) or (n >> k) < 1:
                raise ValueError(
                    f"level {k} must have shape {(6, n >> k, n >> k, c)}, got {a.shape}"
                )
        object.__setattr__(self, "levels", lv)

    def __repr__(self) -> str:
        """One line: kind, face size, levels, channels and dtype (not every texel)."""
        a = self.levels[0]
        return (f"CubeMap(kind={self.kind!r}, size={a.shape[1]}, levels={len(self.levels)}, "
                f"channels={a.shape[3]}, dtype={a.dtype})")

    @classmethod
    def from_faces(cls, faces: ArrayLike, *, kind: str = "other", mips: bool = False) -> CubeMap:
        """Wrap one cube array, optionally with its full box-filtered mip chain."""
        a = check_cube(faces)
        levels = [a]
        if mips:
            for _ in mip_sizes(a.shape[1])[1:]:
                levels.append(downsample(levels[-1]))
        return cls(tuple(levels), kind=kind)

    @property
    def faces(self) -> NDArray[np.float32]:
        """Level 0, ``(6, n, n, C)``."""
        return self.levels[0]

    @property
    def size(self) -> int:
        """Face size of level 0."""
        return int(self.levels[0].shape[1])

    @property
    def channels(self) -> int:
        return int(self.levels[0].shape[3])

    @property
    def num_levels(self) -> int:
        return len(self.levels)

    def roughness(self, level: int) -> float:
        """Perceptual roughness of a specular level: ``level / (levels - 1)`` (glTF)."""
        if not 0 <= level < self.num_levels:
            raise ValueError(f"level {level} out of range 0..{self.num_levels - 1}")
        return level / (self.num_levels - 1) if self.num_levels > 1 else 0.0
