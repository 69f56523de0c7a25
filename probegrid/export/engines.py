"""Probe grids packed the way engines sample them: three.js' ``LightProbeGrid`` SH atlas and
Bevy's ``IrradianceVolume`` ambient cubes; filling invalid probes first.

Pure functions on grid-shaped numpy arrays (``(nx, ny, nz, ...)``, probe ``(i, j, k)`` at
``bounds_min + (i, j, k) * spacing``); no I/O. Every layout below was read from the engine's own
source, not from its documentation:

three.js (``examples/jsm/lighting/LightProbeGridWebGL.js`` and
``src/renderers/shaders/ShaderChunk/lightprobes_pars_fragment.glsl.js``, three r187)
    One RGBA 3D texture of width ``nx``, height ``ny`` and depth ``7 (nz + 2)``: seven
    sub-volumes stacked along z, sub-volume ``t`` in slices ``t (nz + 2) + 1 .. t (nz + 2) + nz``
    with one padding slice at each end copying its first and last data slice. The 27 SH floats
    ``c0.rgb .. c8.rgb`` are packed four per texel in order: ``t = 0: (c0.rgb, c1.r)``, ``1:
    (c1.gb, c2.rg)``, ``2: (c2.b, c3.rgb)``, ``3: (c4.rgb, c5.r)``, ``4: (c5.gb, c6.rg)``, ``5:
    (c6.b, c7.rgb)``, ``6: (c8.rgb, 0)``. The coefficients are *radiance* ``L_lm`` in the world
    frame with three's basis (index ``l(l+1)+m``, ``0.282095``, ``0.488603 y/z/x``, ``1.092548
    xy``, ...: the same basis and sign as probegrid's, no Condon-Shortley phase; three projects
    its CubeCamera renders with ``textureCube(env, dir)`` and evaluates the same ``dir``); the
    shader turns them into irradiance with ``0.886227 c0 + 2 * 0.511664 (c1 y + c2 z + c3 x) +
    ...`` (= ``A_l Y_lm``), then the Lambert BRDF divides by pi. The volume is centred at the
    object's position with ``width = nx * cell`` etc.: three places probe ``i`` at the centre of
    cell ``i`` (``min + (i + 0.5) size / n``), so a corner-inclusive probegrid lattice maps to a
    three volume grown by half a cell on each side.

Bevy (``crates/bevy_pbr/src/light_probe/irradiance_volume.wesl``)
    One 3D texture of ``(nx, 2 ny, 3 nz)`` texels (width, height, depth) holding an *ambient
    cube* per probe (Valve's basis, the shader blends ``rgb_x N.x^2 + rgb_y N.y^2 + rgb_z
    N.z^2``): slab ``a`` of ``nz`` slices for axis x, y, z (``uvw + (0, 0, a / 3)``), and within
    it rows ``0 .. ny - 1`` for the *positive* direction and ``ny .. 2 ny - 1`` for the negative
    one -- the shader adds ``0.5`` to ``v`` when ``N < 0`` ("the bottom half of each cube slice
    is the negative part"). Texel ``(i, j, k)`` of a slab is sampled at the unit-cube point
    ``(i + 0.5) / nx - 0.5`` (the shader's ``(unit_pos + 0.5) * resolution`` clamped to texel
    centres), so the volume's transform is translation = box centre, scale = ``counts * cell``.
    The values are multiplied by the diffuse colour with no 1/pi: they are irradiance / pi,
    probegrid's diffuse map read along the six axes (Bevy's frame is glTF's: right-handed, +Y
    up; the volume is sampled with world-space normals, unflipped).

Cube maps (environment and per-probe maps) are stored in the OpenGL/Vulkan/KTX2 face table, so a
raw ``texture(cube, world_dir)`` in glTF's world frame (the glTF Sample Viewer's lookup) returns
``world_dir``'s light. Engines that treat cube maps as left-handed mirror the lookup: three.js
samples ``(-x, y, z)`` for a ``CubeTexture`` (``flipEnvMap = -1`` in ``PMREMGenerator.js`` and
the envmap shader chunks), Bevy samples ``(x, y, -z)`` (``compute_cubemap_sample_dir`` in
``environment_map.wesl``: "Cubemaps are left-handed, so we negate the Z coordinate").
:func:`mirror_cube` writes a cube for those lookups (``CUBE_MIRROR`` names the axis).

Invalid probes (inside geometry) hold meaningless light and engines have no validity test, so
:func:`fill_invalid` replaces each with the mean of its valid face neighbours, growing outward
from the valid ones until every probe has a value.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core.cubemap import direction_to_texel, texel_directions

__all__ = [
    "CUBE_MIRROR",
    "ambient_cube",
    "bevy_transform",
    "bevy_volume",
    "fill_invalid",
    "mirror_cube",
    "threejs_atlas",
    "threejs_placement",
    "threejs_unpack",
]

#: The axis each consumer's cube lookup mirrors (None: the raw OpenGL/KTX2 lookup).
CUBE_MIRROR: dict[str, int | None] = {"gltf": None, "threejs": 0, "bevy": 2}

#: Padding slices at each end of a three.js sub-volume (``ATLAS_PADDING``).
THREEJS_PADDING = 1


def fill_invalid(values: ArrayLike, valid: ArrayLike) -> tuple[NDArray[np.float32], int]:
    """Replace invalid probes by the mean of their valid face neighbours, repeatedly.

    Parameters
    ----------
    values : (nx, ny, nz, ...) array
    valid : (nx, ny, nz) bool

    Returns
    -------
    (filled, count)
        ``filled`` float32 with every probe holding a value (valid probes unchanged); ``count``
        the number of probes filled. Each pass fills the invalid probes that touch a valid or
        already-filled probe (the mean of those of its up to six face neighbours that have
        values), so a probe ``d`` steps from the nearest valid one is filled in pass ``d``. The
        work is proportional to the number of invalid probes (index arrays over them only).
        Raises ValueError when no probe is valid.
    """
    out = np.array(values, dtype=np.float32, copy=True)
    have = np.array(valid, dtype=bool, copy=True).reshape(-1)
    dims = np.array(out.shape[:3])
    if have.size != int(np.prod(dims)) or np.shape(valid) != out.shape[:3]:
        raise ValueError(f"valid has shape {np.shape(valid)}, values {out.shape}: they must "
                         "match on (nx, ny, nz)")
    if not have.any():
        raise ValueError("every probe is invalid (inside geometry); nothing to fill from")
    flat = out.reshape(have.size, -1)
    todo = np.flatnonzero(~have)
    count = int(todo.size)
    steps = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    while todo.size:
        ijk = np.stack(np.unravel_index(todo, tuple(dims)), axis=-1)  # (M, 3)
        nb = ijk[:, None, :] + steps[None]  # (M, 6, 3)
        inside = np.all((nb >= 0) & (nb < dims), axis=-1)
        idx = np.ravel_multi_index(tuple(np.clip(nb, 0, dims - 1).transpose(2, 0, 1)),
                                   tuple(dims))
        ok = inside & have[idx]
        n = ok.sum(axis=1)
        sel = n > 0
        vals = np.where(ok[sel][..., None], flat[idx[sel]], 0.0).sum(axis=1, dtype=np.float64)
        flat[todo[sel]] = (vals / n[sel][:, None]).astype(np.float32)
        have[todo[sel]] = True
        todo = todo[~sel]
    return out, count


def threejs_atlas(sh: ArrayLike) -> NDArray[np.float32]:
    """``(nx, ny, nz, 9, 3)`` radiance SH -> the ``(7 (nz + 2), ny, nx, 4)`` RGBA atlas (z
    slices, rows, texels: the order of a KTX2 3D texture and of three's ``Data3DTexture``)."""
    c = np.asarray(sh, dtype=np.float32)
    if c.ndim != 5 or c.shape[3:] != (9, 3):
        raise ValueError(f"SH grid must be (nx, ny, nz, 9, 3), got shape {c.shape}")
    nx, ny, nz = c.shape[:3]
    flat = np.zeros((nx, ny, nz, 28), dtype=np.float32)
    flat[..., :27] = c.reshape(nx, ny, nz, 27)  # c0.rgb, c1.rgb, ..., c8.rgb, then 0
    packed = flat.reshape(nx, ny, nz, 7, 4).transpose(3, 2, 1, 0, 4)  # (7, nz, ny, nx, 4)
    padded = np.concatenate([packed[:, :1], packed, packed[:, -1:]], axis=1)
    return np.ascontiguousarray(padded.reshape(7 * (nz + 2), ny, nx, 4))


def threejs_unpack(atlas: ArrayLike, nz: int) -> NDArray[np.float32]:
    """Inverse of :func:`threejs_atlas` (the data slices only): ``(nx, ny, nz, 9, 3)``."""
    a = np.asarray(atlas, dtype=np.float32)
    depth, ny, nx, _ = a.shape
    if depth != 7 * (nz + 2):
        raise ValueError(f"atlas depth {depth} is not 7 (nz + 2) for nz = {nz}")
    sub = a.reshape(7, nz + 2, ny, nx, 4)[:, 1:-1]  # (7, nz, ny, nx, 4)
    flat = sub.transpose(3, 2, 1, 0, 4).reshape(nx, ny, nz, 28)
    return np.ascontiguousarray(flat[..., :27].reshape(nx, ny, nz, 9, 3))


def ambient_cube(diffuse: ArrayLike) -> NDArray[np.float32]:
    """``(..., 6, n, n, 3)`` diffuse cubes -> ``(..., 6, 3)`` their values toward +X, -X, +Y,
    -Y, +Z, -Z: what a bilinear ``texture(cube, axis)`` returns, i.e. the face's centre texel
    (odd n) or the mean of its four central texels (even n)."""
    d = np.asarray(diffuse, dtype=np.float32)
    if d.ndim < 4 or d.shape[-4] != 6 or d.shape[-3] != d.shape[-2] or d.shape[-1] != 3:
        raise ValueError(f"diffuse cubes must be (..., 6, n, n, 3), got shape {d.shape}")
    n = d.shape[-2]
    lo, hi = (n - 1) // 2, n // 2 + 1
    centre = d[..., lo:hi, lo:hi, :].astype(np.float64)
    return centre.mean(axis=(-3, -2)).astype(np.float32)


def bevy_volume(ambient: ArrayLike) -> NDArray[np.float32]:
    """``(nx, ny, nz, 6, 3)`` ambient cubes (+X, -X, +Y, -Y, +Z, -Z) -> Bevy's ``(3 nz, 2 ny,
    nx, 3)`` texels (z slices, rows, texels): slab ``a`` = axis, top rows the positive side."""
    a = np.asarray(ambient, dtype=np.float32)
    if a.ndim != 5 or a.shape[3:] != (6, 3):
        raise ValueError(f"ambient cubes must be (nx, ny, nz, 6, 3), got shape {a.shape}")
    nx, ny, nz = a.shape[:3]
    # (axis, sign, nz, ny, nx, 3): sign 0 = positive (rows 0..ny-1), 1 = negative
    s = a.reshape(nx, ny, nz, 3, 2, 3).transpose(3, 2, 4, 1, 0, 5)
    return np.ascontiguousarray(s.reshape(3 * nz, 2 * ny, nx, 3))


def _cell(grid: Any) -> NDArray[np.float64]:
    """Cell size per axis (1 where a single-probe axis has an empty extent)."""
    cell = np.asarray(grid.cell_size, dtype=np.float64)
    return np.where(cell > 0, cell, 1.0)


def threejs_placement(grid: Any) -> dict[str, list[float] | list[int]]:
    """Where a three.js ``LightProbeGrid(width, height, depth, nx, ny, nz)`` must sit so that its
    probes land on the store's: ``position`` = box centre, ``size`` = counts * cell, and the
    ``min``/``max`` the shader's ``probesMin``/``probesMax`` then hold."""
    lo, hi = np.asarray(grid.lo), np.asarray(grid.hi)
    centre = 0.5 * (lo + hi)
    size = np.asarray(grid.counts, dtype=np.float64) * _cell(grid)
    return {"position": centre.tolist(), "size": size.tolist(),
            "resolution": [int(n) for n in grid.counts],
            "min": (centre - 0.5 * size).tolist(), "max": (centre + 0.5 * size).tolist()}


def bevy_transform(grid: Any) -> dict[str, list[float]]:
    """The ``Transform`` of Bevy's ``LightProbe`` entity that samples the store's probes at the
    volume's cell centres: translation = box centre, scale = counts * cell, no rotation."""
    lo, hi = np.asarray(grid.lo), np.asarray(grid.hi)
    size = np.asarray(grid.counts, dtype=np.float64) * _cell(grid)
    return {"translation": (0.5 * (lo + hi)).tolist(), "rotation_xyzw": [0.0, 0.0, 0.0, 1.0],
            "scale": size.tolist()}


@lru_cache(maxsize=32)
def _mirror_index(n: int, axis: int) -> tuple[NDArray[np.intp], ...]:
    d = np.array(texel_directions(n, normalized=False))
    d[..., axis] = -d[..., axis]
    return direction_to_texel(d, n)  # texel centres map onto texel centres exactly


def mirror_cube(faces: ArrayLike, axis: int | None) -> NDArray[np.float32]:
    """``(..., 6, n, n, C)`` cubes -> the cubes ``c'`` with ``c'(d) = c(M d)``, ``M`` mirroring
    ``axis`` (0 = x, 1 = y, 2 = z; None returns the input): a consumer that looks up ``M w``
    for world direction ``w`` then reads ``c(w)``. A reflection maps texel centres onto texel
    centres, so this is an exact permutation of texels (no resampling)."""
    c = np.asarray(faces, dtype=np.float32)
    if axis is None:
        return c
    if c.ndim < 4 or c.shape[-4] != 6 or c.shape[-3] != c.shape[-2]:
        raise ValueError(f"cubes must be (..., 6, n, n, C), got shape {c.shape}")
    f, r, col = _mirror_index(int(c.shape[-2]), int(axis))
    return np.ascontiguousarray(c[..., f, r, col, :])
