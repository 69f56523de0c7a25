"""Scenes for the probe baker: world-space triangles, glTF materials and punctual lights.

A :class:`Scene` is what the baker needs to shade a ray hit: one flat triangle soup in world space
(every mesh instance already transformed by its node's world matrix), a material index per
triangle, per-vertex UVs and colours, the list of :class:`Material` s and the punctual lights of
:mod:`probegrid.lights`. Scenes come from glTF 2.0 files (:func:`load_gltf`) or from Python
(:meth:`Scene.from_arrays`, :class:`SceneBuilder`, :func:`box_scene`). This is the only module of
the project that imports ``trimesh``.

Conventions
-----------
* World frame: glTF's, kept as is -- right-handed, +Y up, -Z forward, in the file's units (glTF
  says metres; ``CornellBox.glb`` is in millimetres and is *not* rescaled).
* Winding: a triangle ``(a, b, c)`` faces the side of its geometric normal
  ``normalize((b - a) x (c - a))`` (counter-clockwise seen from the front, glTF's front face).
  A mesh instanced under a node whose world matrix has a negative determinant is re-wound
  (glTF 2.0 spec, "Transformations": a negative determinant makes the winding clockwise), so the
  rule above holds for every triangle of a :class:`Scene`.
* Barycentrics: a point of triangle ``(a, b, c)`` is ``(1 - u - v) a + u b + v c`` (Embree's
  and Moller-Trumbore's ``u, v``).
* UVs are glTF's: ``(0, 0)`` is the upper-left corner of the image, ``v`` grows downward. trimesh
  flips ``v`` on load ("origin lower-left"); :func:`load_gltf` flips it back.
* Colours are linear Rec.709 RGB. ``baseColorTexture`` and ``emissiveTexture`` are sRGB-encoded
  (glTF spec, "Metallic-Roughness Material") and are decoded to linear once on load with the
  exact sRGB EOTF (IEC 61966-2-1); alpha stays linear. Textures are filtered bilinearly in
  linear space, wrapping as the texture's sampler says (default REPEAT), like a GPU with an
  sRGB texture format.
* Shading albedo = ``baseColorFactor.rgb * baseColorTexture.rgb * COLOR_0.rgb`` (glTF: COLOR_0
  "acts as an additional linear multiplier to base color"). Emission (radiance, cd/m^2 in the
  photometric reading of :mod:`probegrid.lights`) = ``emissiveFactor *
  KHR_materials_emissive_strength.emissiveStrength * emissiveTexture.rgb``.
* Lights (``KHR_lights_punctual``): position = the node's world translation, direction = the
  node's world matrix applied to -Z (normalised); point/spot intensity in candela, directional in
  lux, ``range`` kept; see :mod:`probegrid.lights` for units and falloff.

Not supported (stated rather than guessed): textures on ``TEXCOORD_1`` or higher (rejected
with a :class:`SceneError`), ``KHR_texture_transform`` (ignored), alpha modes and
metallic/roughness (the baker treats every surface as opaque Lambertian), morph targets and
skins (the bind pose is used), points and lines (ignored). A file whose ``extensionsRequired``
names anything but ``KHR_lights_punctual`` and ``KHR_materials_emissive_strength`` is refused,
as the glTF specification asks of a loader.

References: glTF 2.0 specification (Khronos, 2021); KHR_lights_punctual and
KHR_materials_emissive_strength extension specifications; IEC 61966-2-1 (sRGB).
"""

from __future__ import annotations

import base64
import copy
import dataclasses
import hashlib
import io
import json
import math
import signal
import struct
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Final, Literal, NamedTuple, get_args
from urllib.parse import unquote

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.kernels import hit_surfaces, multiply_texture
from probegrid.lights import DirectionalLight, Light, PointLight, SpotLight

__all__ = [
    "Material",
    "Scene",
    "SceneBuilder",
    "SceneError",
    "Surface",
    "Wrap",
    "box_mesh",
    "box_scene",
    "load_gltf",
    "quad_mesh",
    "sample_texture",
    "srgb_to_linear",
]

Wrap = Literal["repeat", "clamp", "mirror"]
_WRAPS: Final[tuple[str, ...]] = get_args(Wrap)
#: glTF sampler wrap codes (OpenGL enums) -> our names.
_GL_WRAP: Final[dict[int, str]] = {10497: "repeat", 33071: "clamp", 33648: "mirror"}
_LIGHT_TYPES: Final = (PointLight, SpotLight, DirectionalLight)
#: Extensions a file may list in ``extensionsRequired`` (glTF: refuse files needing others).
_SUPPORTED_EXTENSIONS: Final[frozenset[str]] = frozenset(
    {"KHR_lights_punctual", "KHR_materials_emissive_strength"}
)
#: Prefix given to material names before trimesh sees the file, to map its materials back.
_TAG: Final[str] = "__probegrid_material_"
_GLB_MAGIC: Final[bytes] = b"glTF"
_CHUNK_JSON: Final[int] = 0x4E4F534A
_CHUNK_BIN: Final[int] = 0x004E4942


class SceneError(ValueError):
    """A scene that cannot be used (missing or broken file, bad geometry); one-line message."""


# --------------------------------------------------------------------------------------------
# colour and texture helpers
# --------------------------------------------------------------------------------------------


def srgb_to_linear(values: ArrayLike) -> NDArray[np.float64]:
    """Decode sRGB-encoded values in [0, 1] to linear (IEC 61966-2-1 EOTF).

    ``c / 12.92`` for ``c <= 0.04045``, else ``((c + 0.055) / 1.055) ** 2.4``.
    """
    c = np.asarray(values, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4)


def _wrap_index(i: NDArray[np.int64], n: int, mode: str) -> NDArray[np.int64]:
    if mode == "repeat":
        return np.mod(i, n)
    if mode == "clamp":
        return np.clip(i, 0, n - 1)
    m = np.mod(i, 2 * n)  # mirror: period 2n, second half reflected
    return np.where(m < n, m, 2 * n - 1 - m)


def _check_wrap(wrap: Sequence[str]) -> tuple[str, str]:
    w = tuple(wrap)
    if len(w) != 2 or any(x not in _WRAPS for x in w):
        raise ValueError(f"wrap must be two of {', '.join(_WRAPS)} (s, t), got {wrap!r}.")
    return w  # type: ignore[return-value]


def sample_texture(
    texture: ArrayLike, uv: ArrayLike, *, wrap: Sequence[Wrap] = ("repeat", "repeat")
) -> NDArray[np.float64]:
    """Bilinear texture lookup with GPU texel-centre conventions.

    Parameters
    ----------
    texture : (H, W, C) float
        Row 0 is the top of the image (glTF ``v = 0``).
    uv : (..., 2) float
        glTF texture coordinates: ``u`` to the right, ``v`` downward, ``[0, 1]`` over the image;
        texel ``(row, col)`` has its centre at ``((col + 0.5) / W, (row + 0.5) / H)``.
    wrap : (2,) of {"repeat", "clamp", "mirror"}
        Wrap mode along ``u`` (wrapS) and ``v`` (wrapT); glTF's default sampler repeats.

    Returns
    -------
    (..., C) float64
    """
    tex = np.asarray(texture)
    if tex.ndim != 3 or tex.shape[0] < 1 or tex.shape[1] < 1:
        raise ValueError(f"texture must have shape (H, W, C), got {tex.shape}.")
    ws, wt = _check_wrap(wrap)
    coords = np.asarray(uv, dtype=np.float64)
    if coords.shape[-1:] != (2,):
        raise ValueError(f"uv must have shape (..., 2), got {coords.shape}.")
    if not np.all(np.isfinite(coords)):
        raise ValueError("uv must be finite.")
    h, w = tex.shape[:2]
    x = coords[..., 0] * w - 0.5
    y = coords[..., 1] * h - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    xi = x0.astype(np.int64)
    yi = y0.astype(np.int64)
    c0, c1 = _wrap_index(xi, w, ws), _wrap_index(xi + 1, w, ws)
    r0, r1 = _wrap_index(yi, h, wt), _wrap_index(yi + 1, h, wt)
    top = tex[r0, c0] * (1.0 - fx) + tex[r0, c1] * fx
    bottom = tex[r1, c0] * (1.0 - fx) + tex[r1, c1] * fx
    return np.asarray(top * (1.0 - fy) + bottom * fy, dtype=np.float64)


def _readonly(a: NDArray) -> NDArray:
    a.setflags(write=False)
    return a


# --------------------------------------------------------------------------------------------
# materials and scenes
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Material:
    """A glTF material reduced to what a Lambertian light bake uses.

    Attributes
    ----------
    base_color : (4,) float64
        Linear RGBA ``baseColorFactor`` (a 3-vector gets alpha 1). glTF default ``(1, 1, 1, 1)``.
    base_color_texture : (H, W, 4) float32 or None
        ``baseColorTexture``, decoded to linear RGB (alpha linear as stored).
    emissive : (3,) float64
        ``emissiveFactor * emissiveStrength``, linear RGB radiance. glTF default 0.
    emissive_texture : (H, W, 3) float32 or None
        ``emissiveTexture``, decoded to linear RGB.
    double_sided : bool
        glTF ``doubleSided`` (default False: the back of a triangle is not a surface).
    name : str
        For messages only; not part of :meth:`Scene.content_hash`.
    base_color_wrap, emissive_wrap : (2,) of {"repeat", "clamp", "mirror"}
        The textures' sampler wrap modes along u and v.
    """

    base_color: NDArray[np.float64] = field(default_factory=lambda: np.ones(4))
    base_color_texture: NDArray[np.float32] | None = None
    emissive: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    emissive_texture: NDArray[np.float32] | None = None
    double_sided: bool = False
    name: str = ""
    base_color_wrap: tuple[Wrap, Wrap] = ("repeat", "repeat")
    emissive_wrap: tuple[Wrap, Wrap] = ("repeat", "repeat")

    def __post_init__(self) -> None:
        bc = np.array(self.base_color, dtype=np.float64).reshape(-1)
        if bc.shape == (3,):
            bc = np.append(bc, 1.0)
        if bc.shape != (4,) or not np.all(np.isfinite(bc)) or np.any(bc < 0):
            raise ValueError(
                f"base_color must be 3 or 4 finite non-negative numbers, got {self.base_color!r}."
            )
        em = np.array(self.emissive, dtype=np.float64)
        if em.ndim == 0:
            em = np.full(3, float(em))
        if em.shape != (3,) or not np.all(np.isfinite(em)) or np.any(em < 0):
            raise ValueError(
                f"emissive must be 3 finite non-negative numbers, got {self.emissive!r}."
            )
        object.__setattr__(self, "base_color", _readonly(bc))
        object.__setattr__(self, "emissive", _readonly(em))
        for name, channels in (("base_color_texture", 4), ("emissive_texture", 3)):
            tex = getattr(self, name)
            if tex is None:
                continue
            t = np.array(tex, dtype=np.float32)
            if t.ndim != 3 or t.shape[2] != channels or t.shape[0] < 1 or t.shape[1] < 1:
                raise ValueError(f"{name} must have shape (H, W, {channels}), got {t.shape}.")
            if not np.all(np.isfinite(t)):
                raise ValueError(f"{name} must be finite.")
            object.__setattr__(self, name, _readonly(t))
        object.__setattr__(self, "double_sided", bool(self.double_sided))
        object.__setattr__(self, "base_color_wrap", _check_wrap(self.base_color_wrap))
        object.__setattr__(self, "emissive_wrap", _check_wrap(self.emissive_wrap))

    @classmethod
    def diffuse(
        cls, albedo: ArrayLike, *, emission: ArrayLike = 0.0, double_sided: bool = False
    ) -> Material:
        """An untextured material: ``albedo`` (scalar or RGB) and ``emission`` (scalar or RGB)."""
        a = np.broadcast_to(np.asarray(albedo, dtype=np.float64), (3,))
        e = np.broadcast_to(np.asarray(emission, dtype=np.float64), (3,))
        return cls(base_color=a, emissive=e, double_sided=double_sided)

    def _hash_into(self, h: hashlib._Hash) -> None:
        _hash_array(h, self.base_color, "<f8")
        _hash_array(h, self.emissive, "<f8")
        for tex in (self.base_color_texture, self.emissive_texture):
            _hash_array(h, tex, "<f4")
        h.update(json.dumps([self.double_sided, self.base_color_wrap, self.emissive_wrap]).encode())


def _hash_array(h: hashlib._Hash, a: NDArray | None, dtype: str) -> None:
    if a is None:
        h.update(b"None;")
        return
    c = np.ascontiguousarray(a, dtype=np.dtype(dtype))
    h.update(f"{dtype}{c.shape};".encode())
    h.update(c.tobytes())


class Surface(NamedTuple):
    """Shading data at surface points (see :meth:`Scene.surface_at`)."""

    position: NDArray[np.float64]
    normal: NDArray[np.float64]
    albedo: NDArray[np.float64]
    emission: NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Scene:
    """World-space triangles with materials and punctual lights (immutable).

    Attributes
    ----------
    vertices : (V, 3) float64
        World-space positions, finite.
    triangles : (T, 3) int64
        Vertex indices, wound so the geometric normal faces the front (module docstring). T >= 1.
    material : (T,) int64
        Index into ``materials`` of each triangle.
    materials : tuple of Material
    uvs : (V, 2) float64 or None
        glTF texture coordinates (``TEXCOORD_0``); vertices without them hold 0.
    colors : (V, 4) float64 or None
        Linear RGBA vertex colours (``COLOR_0``); vertices without them hold 1.
    lights : tuple of PointLight, SpotLight, DirectionalLight
    name : str
        For messages only; not part of :meth:`content_hash`.

    Invalid data raises :class:`SceneError` (a ``ValueError``).
    """

    vertices: NDArray[np.float64]
    triangles: NDArray[np.int64]
    material: NDArray[np.int64]
    materials: tuple[Material, ...]
    uvs: NDArray[np.float64] | None = None
    colors: NDArray[np.float64] | None = None
    lights: tuple[Light, ...] = ()
    name: str = ""

    def __post_init__(self) -> None:
        v = np.array(self.vertices, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3:
            raise SceneError(f"vertices must have shape (V, 3), got {v.shape}.")
        bad = ~np.all(np.isfinite(v), axis=1)
        if np.any(bad):
            raise SceneError(
                f"scene {self.name!r} has {int(bad.sum())} vertices with NaN or infinite "
                "coordinates."
            )
        t = np.asarray(self.triangles)
        if t.size == 0:
            raise SceneError(f"scene {self.name!r} has no triangles.")
        if t.ndim != 2 or t.shape[1] != 3 or not np.issubdtype(t.dtype, np.integer):
            raise SceneError(
                f"triangles must be integer vertex indices of shape (T, 3), got {t.dtype} "
                f"{t.shape}."
            )
        t = np.array(t, dtype=np.int64)
        if t.min() < 0 or t.max() >= len(v):
            raise SceneError(
                f"triangle vertex indices must be in [0, {len(v)}), got "
                f"[{int(t.min())}, {int(t.max())}]."
            )
        mats = tuple(self.materials)
        if not mats or not all(isinstance(m, Material) for m in mats):
            raise SceneError("materials must be a non-empty sequence of Material.")
        m = np.array(self.material, dtype=np.int64).reshape(-1)
        if m.shape != (len(t),):
            raise SceneError(f"material must have shape ({len(t)},), got {m.shape}.")
        if m.min() < 0 or m.max() >= len(mats):
            raise SceneError(f"material indices must be in [0, {len(mats)}).")
        for name, width, fill in (("uvs", 2, 0.0), ("colors", 4, 1.0)):
            a = getattr(self, name)
            if a is None:
                continue
            a = np.array(a, dtype=np.float64)
            if name == "colors" and a.ndim == 2 and a.shape[1] == 3:
                a = np.concatenate([a, np.full((len(a), 1), fill)], axis=1)
            if a.shape != (len(v), width):
                raise SceneError(f"{name} must have shape ({len(v)}, {width}), got {a.shape}.")
            if not np.all(np.isfinite(a)):
                raise SceneError(f"{name} must be finite.")
            object.__setattr__(self, name, _readonly(a))
        lights = tuple(self.lights)
        for light in lights:
            if not isinstance(light, _LIGHT_TYPES):
                raise SceneError(
                    f"lights must be PointLight, SpotLight or DirectionalLight, got {light!r}."
                )
        object.__setattr__(self, "vertices", _readonly(v))
        object.__setattr__(self, "triangles", _readonly(t))
        object.__setattr__(self, "material", _readonly(m))
        object.__setattr__(self, "materials", mats)
        object.__setattr__(self, "lights", lights)

    # -- construction ----------------------------------------------------------------------

    @classmethod
    def from_arrays(
        cls,
        vertices: ArrayLike,
        triangles: ArrayLike,
        *,
        material: ArrayLike | None = None,
        materials: Sequence[Material] | None = None,
        uvs: ArrayLike | None = None,
        colors: ArrayLike | None = None,
        lights: Sequence[Light] = (),
        name: str = "",
    ) -> Scene:
        """A scene from arrays; by default one material (glTF's default: white, single-sided).

        Parameters
        ----------
        vertices : (V, 3) float
        triangles : (T, 3) int
        material : (T,) int, optional
            Material index per triangle (default 0 everywhere).
        materials : sequence of Material, optional
        uvs : (V, 2) float, optional
        colors : (V, 3) or (V, 4) float, optional
        lights : sequence of lights
        name : str
        """
        mats = tuple(materials) if materials is not None else (Material(),)
        t = np.asarray(triangles)
        n_tri = t.shape[0] if t.ndim == 2 else 0
        m = np.zeros(n_tri, np.int64) if material is None else material
        return cls(
            vertices=vertices,  # type: ignore[arg-type]
            triangles=t,  # type: ignore[arg-type]
            material=m,  # type: ignore[arg-type]
            materials=mats,
            uvs=uvs,  # type: ignore[arg-type]
            colors=colors,  # type: ignore[arg-type]
            lights=tuple(lights),
            name=name,
        )

    # -- derived data ----------------------------------------------------------------------

    @property
    def n_triangles(self) -> int:
        """Number of triangles T."""
        return len(self.triangles)

    @cached_property
    def bounds(self) -> NDArray[np.float64]:
        """(2, 3) float64: min and max corner of the vertices used by triangles."""
        used = self.vertices[np.unique(self.triangles)]
        return _readonly(np.stack([used.min(axis=0), used.max(axis=0)]))

    @cached_property
    def triangle_normals(self) -> NDArray[np.float64]:
        """(T, 3) float64: unit geometric normals as wound; zero for degenerate triangles."""
        p = self.vertices[self.triangles]
        n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return _readonly(np.divide(n, length, out=np.zeros_like(n), where=length > 0))

    @cached_property
    def triangle_areas(self) -> NDArray[np.float64]:
        """(T,) float64 triangle areas, in squared scene units."""
        p = self.vertices[self.triangles]
        return _readonly(
            0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        )

    @cached_property
    def double_sided(self) -> NDArray[np.bool_]:
        """(T,) bool: the material of each triangle is double-sided."""
        flags = np.array([m.double_sided for m in self.materials], dtype=bool)
        return _readonly(flags[self.material])

    @cached_property
    def _factor_tables(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        base = np.stack([m.base_color[:3] for m in self.materials])
        emis = np.stack([m.emissive for m in self.materials])
        return _readonly(base), _readonly(emis)

    def content_hash(self) -> str:
        """SHA-256 (hex) of the geometry, materials and lights: equal scenes hash equal.

        Covers vertices, triangles, material indices, UVs, colours, every material's factors,
        textures, sidedness and wrap modes, and every light's type and parameters, all in a
        fixed little-endian encoding; ``name`` fields are excluded. Stable across runs and
        machines.
        """
        h = hashlib.sha256(b"probegrid-scene-v1;")
        _hash_array(h, self.vertices, "<f8")
        _hash_array(h, self.triangles, "<i8")
        _hash_array(h, self.material, "<i8")
        _hash_array(h, self.uvs, "<f8")
        _hash_array(h, self.colors, "<f8")
        h.update(f"materials{len(self.materials)};".encode())
        for m in self.materials:
            m._hash_into(h)
        for light in self.lights:
            record = [type(light).__name__] + [
                [f.name, getattr(light, f.name)] for f in dataclasses.fields(light)
            ]
            h.update(json.dumps(record).encode())
        return h.hexdigest()

    # -- shading -----------------------------------------------------------------------------

    @cached_property
    def _kernel_tables(self) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Contiguous vertices, triangles, normals and material indices for the kernels."""
        return (np.ascontiguousarray(self.vertices, dtype=np.float64),
                np.ascontiguousarray(self.triangles, dtype=np.int64),
                np.ascontiguousarray(self.triangle_normals, dtype=np.float64),
                np.ascontiguousarray(self.material, dtype=np.int64))

    @cached_property
    def _kernel_colors(self) -> NDArray[np.float64]:
        if self.colors is None:
            return np.zeros((0, 3))
        return np.ascontiguousarray(self.colors[:, :3], dtype=np.float64)

    @cached_property
    def _kernel_uvs(self) -> NDArray[np.float64]:
        if self.uvs is None:
            return np.zeros((0, 2))
        return np.ascontiguousarray(self.uvs, dtype=np.float64)

    @cached_property
    def _textured_materials(self) -> NDArray[np.int64]:
        return np.array([i for i, m in enumerate(self.materials)
                         if m.base_color_texture is not None or m.emissive_texture is not None],
                        dtype=np.int64)

    def _apply_textures(self, pid: NDArray[np.int64], u: NDArray[np.float64],
                        v: NDArray[np.float64], albedo: NDArray[np.float64],
                        emission: NDArray[np.float64]) -> None:
        """Multiply ``albedo``/``emission (n, 3)`` in place by the textures sampled at the
        interpolated UV of the hits (:func:`sample_texture`'s bilinear filter and wrap modes,
        compiled as :func:`probegrid.kernels.multiply_texture`)."""
        if not self._textured_materials.size or not pid.size:
            return
        mat = self.material[pid]
        tris, uvs = self._kernel_tables[1], self._kernel_uvs
        for i in self._textured_materials:  # loop over textured materials, not hits
            sel = np.flatnonzero(mat == i)
            if not sel.size:
                continue
            m = self.materials[int(i)]
            for tex, wrap, target in ((m.base_color_texture, m.base_color_wrap, albedo),
                                      (m.emissive_texture, m.emissive_wrap, emission)):
                if tex is not None:
                    multiply_texture(target, sel, pid, u, v, tris, uvs,
                                     np.ascontiguousarray(tex, dtype=np.float32),
                                     _WRAPS.index(wrap[0]), _WRAPS.index(wrap[1]))

    def surface_at(self, prim_ids: ArrayLike, u: ArrayLike, v: ArrayLike) -> Surface:
        """Position, geometric normal, albedo and emission at barycentric points of triangles.

        Parameters
        ----------
        prim_ids : (...) int
            Triangle indices in ``[0, T)`` (filter out misses first).
        u, v : (...) float
            Barycentrics: the point is ``(1 - u - v) a + u b + v c``; broadcast with prim_ids.

        Returns
        -------
        Surface
            ``position (..., 3)`` float64 world position; ``normal (..., 3)`` unit geometric
            normal as wound; ``albedo (..., 3)`` linear shading albedo
            ``baseColor.rgb * texture.rgb * COLOR_0.rgb``; ``emission (..., 3)`` emitted
            radiance ``emissive * emissiveTexture.rgb``. Textures are sampled bilinearly at the
            interpolated UV with the material's wrap modes.
        """
        pid, uu, vv = np.broadcast_arrays(
            np.asarray(prim_ids), np.asarray(u, np.float64), np.asarray(v, np.float64)
        )
        if pid.size and not np.issubdtype(pid.dtype, np.integer):
            raise ValueError(f"prim_ids must be integers, got dtype {pid.dtype}.")
        shape = pid.shape
        pid = pid.reshape(-1).astype(np.int64)
        uu = uu.reshape(-1)
        vv = vv.reshape(-1)
        if pid.size and (pid.min() < 0 or pid.max() >= self.n_triangles):
            raise ValueError(
                f"prim_ids must be triangle indices in [0, {self.n_triangles}); filter misses "
                "(-1) out first."
            )
        base, emis = self._factor_tables
        position, normal, albedo, emission = hit_surfaces(
            pid, np.ascontiguousarray(uu), np.ascontiguousarray(vv), *self._kernel_tables,
            base, emis, self._kernel_colors)
        self._apply_textures(pid, uu, vv, albedo, emission)
        return Surface(
            position.reshape(*shape, 3),
            normal.reshape(*shape, 3),
            albedo.reshape(*shape, 3),
            emission.reshape(*shape, 3),
        )


# --------------------------------------------------------------------------------------------
# building scenes from Python
# --------------------------------------------------------------------------------------------


def quad_mesh(
    corner: ArrayLike, edge_u: ArrayLike, edge_v: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
    """A parallelogram ``corner + s edge_u + t edge_v``, ``s, t in [0, 1]``, as two triangles.

    The front faces ``edge_u x edge_v``. UVs run ``(s, 1 - t)`` (image upright when the quad is
    seen from the front with ``edge_v`` up).

    Returns
    -------
    vertices : (4, 3) float64
    triangles : (2, 3) int64
    uvs : (4, 2) float64
    """
    c = np.asarray(corner, dtype=np.float64)
    eu = np.asarray(edge_u, dtype=np.float64)
    ev = np.asarray(edge_v, dtype=np.float64)
    for name, a in (("corner", c), ("edge_u", eu), ("edge_v", ev)):
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be a finite 3-vector, got {a!r}.")
    verts = np.stack([c, c + eu, c + eu + ev, c + ev])
    tris = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)
    uvs = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])
    return verts, tris, uvs


def box_mesh(
    lo: ArrayLike, hi: ArrayLike, *, inward: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
    """An axis-aligned box as 6 quads (24 vertices, 12 triangles).

    Faces are in the order -X, +X, -Y, +Y, -Z, +Z; each faces outward, or into the box when
    ``inward`` (a room or furnace seen from inside).

    Returns
    -------
    vertices : (24, 3) float64
    triangles : (12, 3) int64
    uvs : (24, 2) float64
    """
    a = np.asarray(lo, dtype=np.float64)
    b = np.asarray(hi, dtype=np.float64)
    if a.shape != (3,) or b.shape != (3,) or not np.all(np.isfinite(a) & np.isfinite(b)):
        raise ValueError("lo and hi must be finite 3-vectors.")
    if not np.all(b > a):
        raise ValueError(f"hi must exceed lo on every axis, got lo={a}, hi={b}.")
    d = b - a
    ex, ey, ez = np.diag(d)
    # (corner, edge_u, edge_v) with edge_u x edge_v pointing outward.
    faces = [
        (a, ez, ey),  # -X
        (a + ex, ey, ez),  # +X
        (a, ex, ez),  # -Y
        (a + ey, ez, ex),  # +Y
        (a, ey, ex),  # -Z
        (a + ez, ex, ey),  # +Z
    ]
    vs, ts, us = [], [], []
    for k, (c, eu, ev) in enumerate(faces):
        if inward:
            eu, ev = ev, eu
        v, t, uv = quad_mesh(c, eu, ev)
        vs.append(v)
        ts.append(t + 4 * k)
        us.append(uv)
    return np.concatenate(vs), np.concatenate(ts), np.concatenate(us)


class SceneBuilder:
    """Accumulates meshes, materials and lights, then builds a :class:`Scene`.

    Example::

        b = SceneBuilder()
        wall = b.add_material(Material.diffuse(0.8))
        b.add_box((-1, 0, -1), (1, 2, 1), material=wall, inward=True)
        b.add_light(PointLight((0, 1, 0), (1, 1, 1), 10.0))
        scene = b.build()
    """

    def __init__(self) -> None:
        self._materials: list[Material] = []
        self._vertices: list[NDArray[np.float64]] = []
        self._triangles: list[NDArray[np.int64]] = []
        self._material: list[NDArray[np.int64]] = []
        self._uvs: list[NDArray[np.float64]] = []
        self._lights: list[Light] = []
        self._count = 0

    def add_material(self, material: Material) -> int:
        """Register a material; returns its index."""
        if not isinstance(material, Material):
            raise TypeError(f"expected a Material, got {material!r}.")
        self._materials.append(material)
        return len(self._materials) - 1

    def add_triangles(
        self,
        vertices: ArrayLike,
        triangles: ArrayLike,
        *,
        material: int,
        uvs: ArrayLike | None = None,
    ) -> None:
        """Add a triangle mesh (indices local to ``vertices``) with one material."""
        v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        if not 0 <= material < len(self._materials):
            raise ValueError(
                f"material {material} has not been added (have {len(self._materials)})."
            )
        uv = np.zeros((len(v), 2)) if uvs is None else np.asarray(uvs, np.float64).reshape(-1, 2)
        if len(uv) != len(v):
            raise ValueError(f"uvs must have one row per vertex ({len(v)}), got {len(uv)}.")
        self._vertices.append(v)
        self._triangles.append(t + self._count)
        self._material.append(np.full(len(t), material, np.int64))
        self._uvs.append(uv)
        self._count += len(v)

    def add_quad(
        self, corner: ArrayLike, edge_u: ArrayLike, edge_v: ArrayLike, *, material: int
    ) -> None:
        """Add a parallelogram facing ``edge_u x edge_v`` (see :func:`quad_mesh`)."""
        v, t, uv = quad_mesh(corner, edge_u, edge_v)
        self.add_triangles(v, t, material=material, uvs=uv)

    def add_box(self, lo: ArrayLike, hi: ArrayLike, *, material: int, inward: bool = False) -> None:
        """Add an axis-aligned box facing outward, or inward (see :func:`box_mesh`)."""
        v, t, uv = box_mesh(lo, hi, inward=inward)
        self.add_triangles(v, t, material=material, uvs=uv)

    def add_light(self, light: Light) -> None:
        """Add a punctual light."""
        if not isinstance(light, _LIGHT_TYPES):
            raise TypeError(f"expected a PointLight, SpotLight or DirectionalLight, got {light!r}.")
        self._lights.append(light)

    def build(self, *, name: str = "") -> Scene:
        """The scene built so far (raises :class:`SceneError` if it has no triangles)."""
        if not self._triangles:
            raise SceneError(f"scene {name!r} has no triangles.")
        return Scene(
            vertices=np.concatenate(self._vertices),
            triangles=np.concatenate(self._triangles),
            material=np.concatenate(self._material),
            materials=tuple(self._materials),
            uvs=np.concatenate(self._uvs),
            lights=tuple(self._lights),
            name=name,
        )


def box_scene(
    lo: ArrayLike,
    hi: ArrayLike,
    *,
    albedo: ArrayLike,
    emission: ArrayLike = 0.0,
    inward: bool = True,
    double_sided: bool = False,
    lights: Sequence[Light] = (),
) -> Scene:
    """A closed axis-aligned box whose six walls share one diffuse material (a furnace).

    Parameters
    ----------
    lo, hi : (3,) float
        Opposite corners.
    albedo, emission : float or (3,) float
        Linear albedo and emitted radiance of every wall.
    inward : bool
        Walls face into the box (default: a probe inside sees front faces).
    double_sided : bool
        Material sidedness.
    lights : sequence of lights
    """
    b = SceneBuilder()
    mat = b.add_material(Material.diffuse(albedo, emission=emission, double_sided=double_sided))
    b.add_box(lo, hi, material=mat, inward=inward)
    for light in lights:
        b.add_light(light)
    return b.build(name="box")


# --------------------------------------------------------------------------------------------
# glTF loading
# --------------------------------------------------------------------------------------------


def _parse_glb(data: bytes, name: str) -> tuple[dict, bytes | None]:
    """(JSON header, BIN chunk or None) of a binary glTF; checks the container's lengths."""
    if len(data) < 12 or data[:4] != _GLB_MAGIC:
        raise SceneError(f"{name} is not a binary glTF file (bad magic).")
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2:
        raise SceneError(f"{name} is binary glTF version {version}; only version 2 is supported.")
    if length > len(data):
        raise SceneError(f"{name} is truncated: header says {length} bytes, file has {len(data)}.")
    header, binary, offset = None, None, 12
    while offset < length:
        if offset + 8 > length:
            raise SceneError(f"{name} is truncated inside a chunk header at byte {offset}.")
        chunk_len, chunk_type = struct.unpack_from("<II", data, offset)
        start, end = offset + 8, offset + 8 + chunk_len
        if end > length:
            raise SceneError(f"{name} is truncated: a chunk runs past the end of the file.")
        if header is None:
            if chunk_type != _CHUNK_JSON:
                raise SceneError(f"{name}: the first chunk of a .glb must be JSON.")
            try:
                header = json.loads(data[start:end].decode("utf-8"))
            except (UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise SceneError(f"{name} has an unreadable JSON chunk ({exc}).") from None
        elif chunk_type == _CHUNK_BIN and binary is None:
            binary = data[start:end]
        offset = end
    if not isinstance(header, dict):
        raise SceneError(f"{name} has no JSON chunk.")
    return header, binary


def _build_glb(header: dict, binary: bytes | None) -> bytes:
    """A binary glTF container (spec section "Binary glTF Layout")."""
    js = json.dumps(header, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    chunks = struct.pack("<II", len(js), _CHUNK_JSON) + js
    if binary is not None:
        b = binary + b"\x00" * (-len(binary) % 4)
        chunks += struct.pack("<II", len(b), _CHUNK_BIN) + b
    return _GLB_MAGIC + struct.pack("<II", 2, 12 + len(chunks)) + chunks


def _uri_bytes(uri: str, base: Path, what: str) -> bytes:
    """Bytes of a glTF URI: a data URI or a path relative to the .gltf file."""
    if uri.startswith("data:"):
        try:
            return base64.b64decode(uri.split(",", 1)[1], validate=False)
        except (IndexError, ValueError) as exc:
            raise SceneError(f"{what} has a malformed data URI ({exc}).") from None
    target = base / unquote(uri)
    if not target.is_file():
        raise SceneError(f"{what} not found: {target}")
    return target.read_bytes()


def _check_nodes(header: dict, name: str) -> None:
    """The node hierarchy must be a forest (glTF 2.0, 3.5.3): valid child indices, at most one
    parent per node, no cycles."""
    nodes = header.get("nodes", [])
    parent: dict[int, int] = {}
    for i, node in enumerate(nodes):
        for c in node.get("children", []):
            if not isinstance(c, int) or not 0 <= c < len(nodes):
                raise SceneError(f"{name}: node {i} has a child {c!r} that is not a node index.")
            if c in parent or c == i:
                raise SceneError(f"{name}: node {c} has more than one parent or is its own child "
                                 "(the node hierarchy must be a tree).")
            parent[c] = i
    for start in range(len(nodes)):  # walk up from every node: a cycle never reaches a root
        seen, n = set(), start
        while n in parent:
            if n in seen:
                raise SceneError(f"{name}: the node hierarchy has a cycle through node {n}.")
            seen.add(n)
            n = parent[n]


def _check_buffers(header: dict, binary: bytes | None, base: Path, name: str) -> None:
    """Every buffer exists and holds its declared byteLength (catches truncated files)."""
    for i, buf in enumerate(header.get("buffers", [])):
        need = int(buf.get("byteLength", 0))
        if "uri" in buf:
            have = len(_uri_bytes(buf["uri"], base, f"{name}: buffer {i} ({buf['uri']})"))
        elif i == 0 and binary is not None:
            have = len(binary)
        else:
            raise SceneError(f"{name}: buffer {i} has no data (no uri and no .glb BIN chunk).")
        if have < need:
            raise SceneError(f"{name}: buffer {i} is truncated ({have} of {need} bytes).")


def _node_world_matrices(header: dict, name: str) -> dict[int, NDArray[np.float64]]:
    """World matrix (4x4, column vectors) of every node reachable from the default scene."""
    nodes = header.get("nodes", [])
    scenes = header.get("scenes", [])
    if not scenes:
        return {}
    roots = scenes[int(header.get("scene", 0))].get("nodes", [])
    world: dict[int, NDArray[np.float64]] = {}
    stack = [(int(r), np.eye(4)) for r in roots]
    while stack:  # loop over scene-graph nodes (not rays or pixels)
        i, parent = stack.pop()
        if i in world or not 0 <= i < len(nodes):
            raise SceneError(f"{name}: node {i} is out of range or reached twice (not a tree).")
        node = nodes[i]
        if "matrix" in node:
            local = np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T
        else:
            t = np.array(node.get("translation", [0, 0, 0]), dtype=np.float64)
            x, y, z, w = np.array(node.get("rotation", [0, 0, 0, 1]), dtype=np.float64)
            s = np.array(node.get("scale", [1, 1, 1]), dtype=np.float64)
            rot = np.array(
                [
                    [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
                ]
            )
            local = np.eye(4)
            local[:3, :3] = rot * s[None, :]
            local[:3, 3] = t
        if not np.all(np.isfinite(local)):
            raise SceneError(f"{name}: node {i} has a non-finite transform.")
        world[i] = parent @ local
        stack.extend((int(c), world[i]) for c in node.get("children", []))
    return world


def _parse_lights(header: dict, name: str) -> tuple[Light, ...]:
    """KHR_lights_punctual lights placed by the default scene's nodes, in node order."""
    defs = header.get("extensions", {}).get("KHR_lights_punctual", {}).get("lights", [])
    if not defs:
        return ()
    world = _node_world_matrices(header, name)
    lights: list[Light] = []
    for i in sorted(world):
        ext = header["nodes"][i].get("extensions", {}).get("KHR_lights_punctual")
        if ext is None:
            continue
        k = int(ext["light"])
        if not 0 <= k < len(defs):
            raise SceneError(f"{name}: node {i} refers to missing light {k}.")
        d = defs[k]
        m = world[i]
        position = m[:3, 3]
        direction = m[:3, :3] @ np.array([0.0, 0.0, -1.0])
        color = d.get("color", [1.0, 1.0, 1.0])
        intensity = d.get("intensity", 1.0)
        kind = d.get("type")
        try:
            if kind == "point":
                lights.append(PointLight(position, color, intensity, range=d.get("range")))
            elif kind == "spot":
                spot = d.get("spot", {})
                lights.append(
                    SpotLight(
                        position,
                        direction,
                        color,
                        intensity,
                        range=d.get("range"),
                        inner_cone_angle=spot.get("innerConeAngle", 0.0),
                        outer_cone_angle=spot.get("outerConeAngle", math.pi / 4),
                    )
                )
            elif kind == "directional":
                lights.append(DirectionalLight(direction, color, intensity))
            else:
                raise SceneError(
                    f"{name}: light {k} has type {kind!r}; expected point, spot or directional."
                )
        except SceneError:
            raise
        except (ValueError, TypeError) as exc:
            raise SceneError(f"{name}: light {k} ({kind}) is invalid: {exc}") from None
    return tuple(lights)


def _texture_array(image: object, channels: int, what: str) -> NDArray[np.float32]:
    """A PIL image (as trimesh decoded it) -> (H, W, channels) float32 linear RGB(A)."""
    try:
        a = np.asarray(image)
        if a.dtype == np.uint16 or a.dtype == np.int32:  # 16-bit greyscale PNG modes
            a = np.clip(a.astype(np.float64) / 65535.0, 0.0, 1.0)
            a = np.repeat(a[..., None], 3, axis=-1) if a.ndim == 2 else a
            if channels == 4:
                a = np.concatenate([a[..., :3], np.ones_like(a[..., :1])], axis=-1)
        else:
            mode = "RGBA" if channels == 4 else "RGB"
            rgb = image.convert(mode)  # type: ignore[attr-defined]
            a = np.asarray(rgb, dtype=np.float64) / 255.0
    except (OSError, ValueError, SyntaxError) as exc:
        raise SceneError(f"{what} could not be decoded ({exc}).") from None
    out = np.array(a[..., :channels], dtype=np.float64)
    out[..., :3] = srgb_to_linear(out[..., :3])
    return out.astype(np.float32)


def _texture_info(
    header: dict, info: dict | None, mat_name: str, slot: str
) -> tuple[str, tuple[str, str]] | None:
    """(image description, wrap modes) of a textureInfo, after validating what we support."""
    if info is None:
        return None
    if int(info.get("texCoord", 0)) != 0:
        raise SceneError(
            f"material {mat_name!r}: {slot} uses TEXCOORD_{info['texCoord']}; only TEXCOORD_0 "
            "is supported."
        )
    try:
        tex = header["textures"][int(info["index"])]
        sampler = header.get("samplers", [])[tex["sampler"]] if "sampler" in tex else {}
        source = tex.get("source")
        image = header["images"][source] if source is not None else {}
    except (KeyError, IndexError, TypeError):
        raise SceneError(f"material {mat_name!r}: {slot} refers to a missing texture.") from None
    desc = image.get("uri", f"bufferView {image.get('bufferView')}")
    if isinstance(desc, str) and desc.startswith("data:"):
        desc = "embedded data URI"
    wrap = tuple(_GL_WRAP.get(int(sampler.get(k, 10497)), "repeat") for k in ("wrapS", "wrapT"))
    return f"{slot} of material {mat_name!r} (image {desc})", wrap  # type: ignore[return-value]


def _material_from_json(header: dict, index: int, tm_material: object | None) -> Material:
    """Material ``index`` of the glTF JSON; texture pixels come from trimesh's decoded images."""
    mj = header["materials"][index]
    mname = str(mj.get("name", f"#{index}"))
    pbr = mj.get("pbrMetallicRoughness", {})
    strength = mj.get("extensions", {}).get("KHR_materials_emissive_strength", {})
    emissive = np.array(mj.get("emissiveFactor", [0.0, 0.0, 0.0]), dtype=np.float64)
    emissive = emissive * float(strength.get("emissiveStrength", 1.0))
    textures: dict[str, NDArray[np.float32] | None] = {}
    wraps: dict[str, tuple[str, str]] = {}
    for slot, info, attr, channels in (
        ("baseColorTexture", pbr.get("baseColorTexture"), "baseColorTexture", 4),
        ("emissiveTexture", mj.get("emissiveTexture"), "emissiveTexture", 3),
    ):
        found = _texture_info(header, info, mname, slot)
        textures[slot] = None
        wraps[slot] = ("repeat", "repeat")
        if found is None or tm_material is None:
            continue
        what, wraps[slot] = found
        image = getattr(tm_material, attr, None)
        if image is None:
            raise SceneError(f"{what} is missing or could not be decoded.")
        textures[slot] = _texture_array(image, channels, what)
    try:
        return Material(
            base_color=pbr.get("baseColorFactor", [1.0, 1.0, 1.0, 1.0]),
            base_color_texture=textures["baseColorTexture"],
            emissive=emissive,
            emissive_texture=textures["emissiveTexture"],
            double_sided=bool(mj.get("doubleSided", False)),
            name=mname,
            base_color_wrap=wraps["baseColorTexture"],  # type: ignore[arg-type]
            emissive_wrap=wraps["emissiveTexture"],  # type: ignore[arg-type]
        )
    except ValueError as exc:
        raise SceneError(f"material {mname!r} is invalid: {exc}") from None


def _vertex_colors(raw: NDArray) -> NDArray[np.float64]:
    """COLOR_0 accessor data -> (V, 4) float64; integer types are normalized (glTF spec)."""
    a = np.asarray(raw)
    if np.issubdtype(a.dtype, np.integer):
        a = a.astype(np.float64) / float(np.iinfo(a.dtype).max)
    a = np.asarray(a, dtype=np.float64).reshape(len(a), -1)
    if a.shape[1] == 3:
        a = np.concatenate([a, np.ones((len(a), 1))], axis=1)
    return a[:, :4]


def load_gltf(path: str | Path) -> Scene:
    """Load a glTF 2.0 scene (.gltf or .glb) into world space.

    trimesh reads the meshes, the node hierarchy and the images; factors, samplers, the
    emissive-strength extension and ``KHR_lights_punctual`` (which trimesh ignores) are read
    from the glTF JSON (trimesh stores ``baseColorFactor`` as 8-bit, losing precision). Every
    primitive of every mesh node of the default scene becomes triangles in world space; points
    and lines are skipped. Primitives without a material get glTF's default material.

    Parameters
    ----------
    path : str or Path
        A ``.gltf`` (with its buffers and images beside it, or embedded as data URIs) or ``.glb``.

    Returns
    -------
    Scene

    Raises
    ------
    SceneError
        Missing or unreadable file, truncated .glb or buffer, missing or undecodable texture,
        non-finite vertices, no triangles, unsupported features (see module docstring).
    """
    p = Path(path)
    label = p.name
    suffix = p.suffix.lower()
    if suffix not in (".gltf", ".glb"):
        raise SceneError(f"{label}: expected a .gltf or .glb file, got suffix {p.suffix!r}.")
    if not p.is_file():
        raise SceneError(f"scene file not found: {p}")
    data = p.read_bytes()
    try:
        return _load_gltf_data(p, data)
    except SceneError:
        raise
    except (AttributeError, TypeError, KeyError, IndexError, ValueError, RecursionError) as exc:
        # JSON of the wrong shape ("asset": "2.0", "materials": [5], a node cycle, ...)
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SceneError(f"{label} is not a well-formed glTF 2.0 scene ({msg}).") from None


def _load_gltf_data(p: Path, data: bytes) -> Scene:
    """:func:`load_gltf` of the file's bytes (its errors of malformed JSON not yet caught)."""
    label, suffix = p.name, p.suffix.lower()
    if suffix == ".glb":
        header, binary = _parse_glb(data, label)
    else:
        binary = None
        try:
            header = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise SceneError(f"{label} is not valid glTF JSON ({exc}).") from None
        if not isinstance(header, dict):
            raise SceneError(f"{label} is not a glTF JSON object.")
    version = str(header.get("asset", {}).get("version", ""))
    if not version.startswith("2."):
        raise SceneError(f"{label} is glTF version {version or '?'}; only 2.x is supported.")
    unsupported = sorted(set(header.get("extensionsRequired", [])) - _SUPPORTED_EXTENSIONS)
    if unsupported:
        raise SceneError(f"{label} requires unsupported glTF extensions: {', '.join(unsupported)}.")
    _check_buffers(header, binary, p.parent, label)
    _check_nodes(header, label)
    for i, img in enumerate(header.get("images", [])):
        if "uri" in img and not str(img["uri"]).startswith("data:"):
            _uri_bytes(img["uri"], p.parent, f"{label}: image {i} ({img['uri']})")

    # Tag material names so trimesh's materials map back to their glTF indices.
    tagged = copy.deepcopy(header)
    for i, m in enumerate(tagged.get("materials", [])):
        m["name"] = f"{_TAG}{i}"
    tm_scene = _trimesh_load(tagged, binary, p, label)

    n_json_mats = len(header.get("materials", []))
    tm_materials: dict[int, object] = {}
    instances = []
    order = list(tm_scene.geometry.keys())
    for node in tm_scene.graph.nodes_geometry:
        matrix, geom_name = tm_scene.graph[node]
        geom = tm_scene.geometry[geom_name]
        if not hasattr(geom, "faces") or len(geom.faces) == 0:
            continue  # points, lines
        instances.append((order.index(geom_name), np.asarray(matrix, np.float64).tobytes(), geom))
    instances.sort(key=lambda item: (item[0], item[1]))  # deterministic (graph order is not)

    verts, tris, mats, uvs, cols = [], [], [], [], []
    any_uv = any_col = False
    count = 0
    for _, mbytes, geom in instances:
        m = np.frombuffer(mbytes, dtype=np.float64).reshape(4, 4)
        v = np.asarray(geom.vertices, dtype=np.float64) @ m[:3, :3].T + m[:3, 3]
        f = np.asarray(geom.faces, dtype=np.int64)
        if np.linalg.det(m[:3, :3]) < 0:
            f = f[:, [0, 2, 1]]
        visual = geom.visual
        material = getattr(visual, "material", None)
        mname = getattr(material, "name", None)
        if isinstance(mname, str) and mname.startswith(_TAG):
            idx = int(mname[len(_TAG) :])
            tm_materials.setdefault(idx, material)
        else:
            idx = n_json_mats  # glTF default material
        uv = getattr(visual, "uv", None)
        if uv is not None and len(uv) == len(v):
            uv = np.asarray(uv, dtype=np.float64) * [1.0, -1.0] + [0.0, 1.0]  # undo trimesh flip
            any_uv = True
        else:
            uv = np.zeros((len(v), 2))
        attrs = getattr(visual, "vertex_attributes", {}) or {}
        col = attrs.get("color") if hasattr(attrs, "get") else None
        if col is not None and len(col) == len(v):
            col = _vertex_colors(col)
            any_col = True
        else:
            col = np.ones((len(v), 4))
        verts.append(v)
        tris.append(f + count)
        mats.append(np.full(len(f), idx, np.int64))
        uvs.append(uv)
        cols.append(col)
        count += len(v)
    if not tris:
        raise SceneError(f"{label} has no triangles in its default scene.")

    materials = [_material_from_json(header, i, tm_materials.get(i)) for i in range(n_json_mats)]
    material = np.concatenate(mats)
    if np.any(material == n_json_mats):
        materials.append(Material(name="glTF default"))
    return Scene(
        vertices=np.concatenate(verts),
        triangles=np.concatenate(tris),
        material=material,
        materials=tuple(materials),
        uvs=np.concatenate(uvs) if any_uv else None,
        colors=np.concatenate(cols) if any_col else None,
        lights=_parse_lights(header, label),
        name=label,
    )


def _trimesh_load(header: dict, binary: bytes | None, path: Path, label: str):
    """trimesh.Scene of a (re-encoded) glTF; any trimesh failure becomes a SceneError.

    trimesh's loader catches ``BaseException`` around format handlers, which would swallow a
    Ctrl-C (or the CLI's SIGTERM, turned into KeyboardInterrupt) arriving during the load; in
    the main thread, SIGINT and SIGTERM are held during the call and delivered to their own
    handlers right after it (loading takes a fraction of a second).
    """
    import trimesh

    def load():
        if binary is not None or path.suffix.lower() == ".glb":
            return trimesh.load_scene(
                io.BytesIO(_build_glb(header, binary)), file_type="glb", process=False
            )
        resolver = trimesh.resolvers.FilePathResolver(str(path))
        return trimesh.load_scene(
            io.BytesIO(json.dumps(header).encode("utf-8")),
            file_type="gltf",
            resolver=resolver,
            process=False,
        )

    try:
        with _signals_held():
            return load()
    except SceneError:
        raise
    except Exception as exc:  # noqa: BLE001 -- trimesh raises arbitrary types on bad accessors
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SceneError(f"{label} could not be read by trimesh: {msg}") from None


@contextmanager
def _signals_held() -> Iterator[None]:
    """Hold SIGINT and SIGTERM for the duration, then deliver those that arrived to the
    handlers in place before (main thread only; elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    sigs = (signal.SIGINT, signal.SIGTERM)
    previous = {sig: signal.getsignal(sig) for sig in sigs}
    for sig in sigs:
        signal.signal(sig, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        for sig in sigs:
            handler = previous[sig]
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        for sig in dict.fromkeys(held):
            signal.raise_signal(sig)
