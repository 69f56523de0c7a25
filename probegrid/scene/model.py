"""The scene model the baker shades: world-space triangles, glTF materials and punctual lights.

A :class:`Scene` is what the baker needs to shade a ray hit: one flat triangle soup in world space
(every mesh instance already transformed by its node's world matrix), a material index per
triangle, per-vertex UVs and colours, the list of :class:`Material` s and the punctual lights of
:mod:`probegrid.core.lights`. Scenes come from glTF 2.0 files (:func:`probegrid.scene.load_gltf`)
or from Python (:meth:`Scene.from_arrays`, :mod:`probegrid.scene.builders`).

Conventions
-----------
* World frame: glTF's, kept as is -- right-handed, +Y up, -Z forward, in the scene's units.
* Winding: a triangle ``(a, b, c)`` faces the side of its geometric normal
  ``normalize((b - a) x (c - a))`` (counter-clockwise seen from the front, glTF's front face).
* Barycentrics: a point of triangle ``(a, b, c)`` is ``(1 - u - v) a + u b + v c`` (Embree's
  and Moller-Trumbore's ``u, v``).
* Colours are linear Rec.709 RGB; textures are filtered bilinearly in linear space
  (:mod:`probegrid.scene.textures`).
* Shading albedo = ``base_color.rgb * base_color_texture.rgb * vertex colour.rgb``; emission
  (radiance, cd/m^2 in the photometric reading of :mod:`probegrid.core.lights`) =
  ``emissive * emissive_strength * emissive_texture.rgb``. Every surface is Lambertian.
* Each texture reads its own set of texture coordinates through its own affine map
  (:class:`~probegrid.scene.textures.TexCoord`: glTF ``texCoord`` and ``KHR_texture_transform``).
* What stops a ray (:mod:`probegrid.scene.coverage`): glTF's alpha modes (``MASK`` with its
  cutoff: a hole; ``BLEND``: alpha is the probability that a ray stops) and thin transmission
  (``KHR_materials_transmission``: a ray passes with probability ``transmission`` (times its
  texture's R), carrying the base colour's tint). Alpha is
  ``baseColorFactor.a * baseColorTexture.a * COLOR_0.a``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Final, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._jit import frozen
from probegrid.core.lights import DirectionalLight, Light, PointLight, SpotLight
from probegrid.errors import SceneError
from probegrid.scene.coverage import Coverage
from probegrid.scene.kernels import SurfaceTables, hit_surfaces, multiply_texture
from probegrid.scene.textures import _WRAPS, TexCoord, Wrap, _check_texcoord, _check_wrap

__all__ = ['ALPHA_MODES', 'Material', 'Scene', 'SceneError', 'Surface']

_LIGHT_TYPES: Final = (PointLight, SpotLight, DirectionalLight)

#: glTF's alpha modes.
ALPHA_MODES: Final = ("OPAQUE", "MASK", "BLEND")


def _readonly(a: NDArray) -> NDArray:
    a.setflags(write=False)
    return a


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
    alpha_mode : {"OPAQUE", "MASK", "BLEND"}
        glTF ``alphaMode`` (:mod:`probegrid.scene.coverage` for what each does to a ray).
    alpha_cutoff : float
        glTF ``alphaCutoff`` of ``MASK`` (default 0.5): alpha below it is a hole.
    transmission : float in [0, 1]
        ``KHR_materials_transmission``'s ``transmissionFactor`` (thin: a ray passes with
        probability ``transmission`` times the texture's, unbent, tinted by the base colour,
        :mod:`probegrid.scene.coverage`).
    transmission_texture : (H, W, 1) float32 or None
        ``transmissionTexture``'s R channel (linear, in [0, 1]), multiplying ``transmission``.
    base_color_uv, emissive_uv, transmission_uv : TexCoord
        The coordinates each texture reads (set and ``KHR_texture_transform``).
    transmission_wrap : (2,) of {"repeat", "clamp", "mirror"}
    """

    base_color: NDArray[np.float64] = field(default_factory=lambda: np.ones(4))
    base_color_texture: NDArray[np.float32] | None = None
    emissive: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    emissive_texture: NDArray[np.float32] | None = None
    double_sided: bool = False
    name: str = ""
    base_color_wrap: tuple[Wrap, Wrap] = ("repeat", "repeat")
    emissive_wrap: tuple[Wrap, Wrap] = ("repeat", "repeat")
    alpha_mode: str = "OPAQUE"
    alpha_cutoff: float = 0.5
    transmission: float = 0.0
    base_color_uv: TexCoord = TexCoord()
    emissive_uv: TexCoord = TexCoord()
    transmission_texture: NDArray[np.float32] | None = None
    transmission_wrap: tuple[Wrap, Wrap] = ("repeat", "repeat")
    transmission_uv: TexCoord = TexCoord()

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
        for name, channels in (("base_color_texture", 4), ("emissive_texture", 3),
                               ("transmission_texture", 1)):
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
        object.__setattr__(self, "transmission_wrap", _check_wrap(self.transmission_wrap))
        if self.alpha_mode not in ALPHA_MODES:
            raise ValueError(f"alpha_mode must be one of {', '.join(ALPHA_MODES)}, got "
                             f"{self.alpha_mode!r}.")
        for name in ("alpha_cutoff", "transmission"):
            x = float(getattr(self, name))
            if not (np.isfinite(x) and x >= 0) or (name == "transmission" and x > 1):
                raise ValueError(f"{name} must be a finite number >= 0"
                                 + (" and <= 1" if name == "transmission" else "")
                                 + f", got {getattr(self, name)!r}.")
            object.__setattr__(self, name, x)
        object.__setattr__(self, "base_color_uv", _check_texcoord(self.base_color_uv))
        object.__setattr__(self, "emissive_uv", _check_texcoord(self.emissive_uv))
        object.__setattr__(self, "transmission_uv", _check_texcoord(self.transmission_uv))
        if self.transmission_texture is not None and (
                self.transmission_texture.min() < 0 or self.transmission_texture.max() > 1):
            raise ValueError("transmission_texture must be in [0, 1].")

    @property
    def stops_every_ray(self) -> bool:
        """Opaque: no hole, no partial coverage, no transmission (every ray that hits stops)."""
        return self.alpha_mode == "OPAQUE" and self.transmission == 0.0

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
        extra = [self.alpha_mode, self.alpha_cutoff, self.transmission,
                 list(self.base_color_uv), list(self.emissive_uv)]
        if extra != ["OPAQUE", 0.5, 0.0, list(TexCoord()), list(TexCoord())]:
            h.update(json.dumps(extra).encode())  # (a scene without them hashes as before)
        if self.transmission_texture is not None:
            _hash_array(h, self.transmission_texture, "<f4")
            h.update(json.dumps([self.transmission_wrap, list(self.transmission_uv)]).encode())


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
    extra_uvs : tuple of (V, 2) float64
        The further sets ``TEXCOORD_1``, ``TEXCOORD_2``, ... (a texture's ``TexCoord.index``
        ``n`` reads ``extra_uvs[n - 1]``); vertices without them hold 0.
    colors : (V, 4) float64 or None
        Linear RGBA vertex colours (``COLOR_0``); vertices without them hold 1.
    lights : tuple of PointLight, SpotLight, DirectionalLight
    name : str
        For messages only; not part of :meth:`content_hash`.
    unhonoured : tuple of str
        What the file the scene came from uses that the bake does not honour (the glTF
        loader's list: metallic-roughness, sheen, ...); for messages and the store's manifest,
        not part of :meth:`content_hash`.

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
    extra_uvs: tuple[NDArray[np.float64], ...] = ()
    unhonoured: tuple[str, ...] = ()

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
        extra = []
        for k, a in enumerate(self.extra_uvs):
            a = np.array(a, dtype=np.float64)
            if a.shape != (len(v), 2) or not np.all(np.isfinite(a)):
                raise SceneError(f"TEXCOORD_{k + 1} must be finite, of shape ({len(v)}, 2), got "
                                 f"{a.shape}.")
            extra.append(_readonly(a))
        object.__setattr__(self, "extra_uvs", tuple(extra))
        object.__setattr__(self, "unhonoured", tuple(str(x) for x in self.unhonoured))
        used = {m.base_color_uv.index for m in mats if m.base_color_texture is not None}
        used |= {m.emissive_uv.index for m in mats if m.emissive_texture is not None}
        used |= {m.transmission_uv.index for m in mats if m.transmission_texture is not None}
        if used and max(used) > len(extra):
            raise SceneError(f"a texture reads TEXCOORD_{max(used)}, which the scene does not "
                             "have.")
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
        extra_uvs: Sequence[ArrayLike] = (),
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
        extra_uvs : sequence of (V, 2) float
            ``TEXCOORD_1`` and further sets.
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
            extra_uvs=tuple(extra_uvs),  # type: ignore[arg-type]
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
        for a in self.extra_uvs:  # (none: the hash of a scene without them, as before)
            _hash_array(h, a, "<f8")
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
    def surface_tables(self) -> SurfaceTables:
        """The triangles and material factors as the compiled kernels read them
        (:class:`probegrid.scene.kernels.SurfaceTables`: contiguous, read-only, built once)."""
        base, emis = self._factor_tables
        return frozen(SurfaceTables(*self._kernel_tables, base, emis, self._kernel_colors))

    @cached_property
    def _kernel_uvs(self) -> NDArray[np.float64]:
        if self.uvs is None:
            return np.zeros((0, 2))
        return np.ascontiguousarray(self.uvs, dtype=np.float64)

    def kernel_texcoords(self, tc: TexCoord) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The kernels' ``uvs`` (contiguous; empty: UV 0) and ``xform`` (empty: identity) of a
        texture's :class:`~probegrid.scene.textures.TexCoord`."""
        uvs = (self._kernel_uvs if tc.index == 0
               else np.ascontiguousarray(self.extra_uvs[tc.index - 1]))
        return uvs, (np.zeros(0) if tc.is_identity else np.array(tc.matrix, np.float64))

    @cached_property
    def coverage(self) -> Coverage | None:
        """What stops a ray at each triangle (:class:`probegrid.scene.coverage.Coverage`), or
        None when every material stops every ray (opaque, no transmission)."""
        if all(m.stops_every_ray for m in self.materials):
            return None
        return Coverage(self)

    @cached_property
    def _textured_materials(self) -> NDArray[np.int64]:
        return np.array([i for i, m in enumerate(self.materials)
                         if m.base_color_texture is not None or m.emissive_texture is not None],
                        dtype=np.int64)

    def apply_textures(self, pid: NDArray[np.int64], u: NDArray[np.float64],
                        v: NDArray[np.float64], albedo: NDArray[Any],
                        emission: NDArray[Any], rows: NDArray[np.int64] | None = None
                        ) -> None:
        """Multiply ``albedo``/``emission (n, 3)`` in place by the textures sampled at the
        interpolated UV of the hits (:func:`sample_texture`'s bilinear filter and wrap modes,
        compiled as :func:`probegrid.scene.kernels.multiply_texture`); only ``rows`` of them when
        given (the other entries of ``pid``, misses say, are not read)."""
        if not self._textured_materials.size or not pid.size:
            return
        hit = np.arange(len(pid)) if rows is None else np.asarray(rows, np.int64)
        mat = self.material[pid[hit]]
        tris = self._kernel_tables[1]
        for i in self._textured_materials:  # loop over textured materials, not hits
            sel = hit[mat == i]
            if not sel.size:
                continue
            m = self.materials[int(i)]
            for tex, wrap, tc, target in (
                    (m.base_color_texture, m.base_color_wrap, m.base_color_uv, albedo),
                    (m.emissive_texture, m.emissive_wrap, m.emissive_uv, emission)):
                if tex is not None:
                    uvs, xform = self.kernel_texcoords(tc)
                    multiply_texture(target, sel, *frozen((
                        (pid, u, v), tris, uvs, np.asarray(tex, dtype=np.float32))),
                        (_WRAPS.index(wrap[0]), _WRAPS.index(wrap[1])), frozen(xform), 0)

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
        position, normal, albedo, emission = hit_surfaces(
            pid, np.ascontiguousarray(uu), np.ascontiguousarray(vv), self.surface_tables)
        self.apply_textures(pid, uu, vv, albedo, emission)
        return Surface(
            position.reshape(*shape, 3),
            normal.reshape(*shape, 3),
            albedo.reshape(*shape, 3),
            emission.reshape(*shape, 3),
        )

