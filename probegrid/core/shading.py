"""Offline shading with probe maps: normal transforms, reflection, classic and split-sum shading.

Two shading formulas, evaluated per pixel / vertex on arrays (what a shader would do):

* Classic cube-map lighting (Bloom, "Cube Map Lighting", 2004)::

      out = albedo * Diffuse[N] + gloss * Specular[R(N)]

  ``Diffuse`` holds irradiance / pi (see :mod:`probegrid.core.cubemap`), ``Specular`` a (Phong- or
  GGX-) prefiltered or unfiltered radiance map. Without a view vector, ``Specular`` is looked up at
  ``N`` itself: the seed's "no view" case, where the map is a function of the normal only (e.g. a
  Phong map of lights around an object rendered without a camera position).

* Split-sum image-based lighting (Karis 2013, as the Khronos glTF Sample Viewer does it)::

      s   = F0 * A + B                                   (A, B) = DFG(N . V, roughness)
      out = albedo * (1 - s) * Diffuse[N] + s * Prefiltered[R, lod = roughness (levels - 1)]

  where ``albedo`` is the Lambertian colour (glTF: ``baseColor (1 - metallic)``) and ``F0`` the
  normal-incidence reflectance (glTF: ``mix(0.04, baseColor, metallic)``). The diffuse term is
  *reduced by the specular energy* ``s`` (``reduce_diffuse=True``, the default): light reflected
  by the specular layer is not also scattered diffusely, as the glTF Sample Viewer's
  ``k_D = diffuseColor (1 - F0 A - B)``. So a white furnace (constant environment ``L``,
  albedo 1) returns exactly ``L`` for every ``F0``, roughness and view. We do *not* apply the
  Sample Viewer's further refinements (roughness-dependent Fresnel ``max(1 - r, F0)`` and
  Fdez-Aguera's multiple-scattering term); ``reduce_diffuse=False`` gives the plain sum
  ``albedo Diffuse[N] + s Prefiltered``.

Vectors
-------
* ``N`` normals in world space (the maps' frame, glTF: right-handed, +Y up). They need *not* be
  unit: cube-map lookups are invariant to the length of the direction (the sampler projects on
  the major axis), the "implicit normalisation" the seed relies on. Formulas that need a unit
  normal (reflection, ``N . V``) normalise a copy.
* ``V`` points *from the surface to the eye* (not necessarily unit). The reflection is
  ``R = 2 (N . V) N - V`` with ``N`` normalised, so ``|R| = |V|`` (directions only matter).
* :func:`transform_normals` takes normals from object or rest (skinning) pose space to world
  space with the inverse-transpose of the 3 x 3 linear part, without renormalising.

Everything broadcasts over leading axes: normals, views, albedo and ``F0`` are ``(..., 3)``
(albedo and ``F0`` ``(..., C)`` for ``C``-channel maps), roughness and gloss ``(...)``. Results are
``(..., C)`` float32 (cube texel precision). Non-finite or zero normals raise ``ValueError``.

References
----------
* C. Bloom, "Cube Map Lighting", 2004.
* B. Karis, "Real Shading in Unreal Engine 4", SIGGRAPH 2013 course notes (split sum, DFG LUT).
* Khronos glTF Sample Viewer, ``ibl.glsl`` (diffuse reduced by ``1 - F0 A - B``).
* C. Fdez-Aguera, "A Multiple-Scattering Microfacet Model for Real-Time Image-based Lighting",
  JCGT 8(1), 2019 (the refinement not applied here).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core.cubemap import CubeMap
from probegrid.core.dfg import dfg_lookup
from probegrid.core.lobes import roughness_to_lod
from probegrid.core.sampling import CubeSampler

__all__ = [
    "reflect",
    "shade_classic",
    "shade_split_sum",
    "transform_normals",
    "unit_vectors",
]

CubeLike = CubeMap | ArrayLike | Sequence[ArrayLike]


def _vectors(value: ArrayLike, name: str, *, nonzero: bool = False) -> NDArray[np.float64]:
    a = np.asarray(value, dtype=np.float64)
    if a.shape[-1:] != (3,):
        raise ValueError(f"{name} must have shape (..., 3), got {a.shape}.")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite.")
    if nonzero and np.any(np.all(a == 0, axis=-1)):
        raise ValueError(f"{name} must be non-zero vectors.")
    return a


def _finite(value: ArrayLike, name: str) -> NDArray[np.float64]:
    a = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite.")
    return a


def unit_vectors(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rows scaled to unit length; scaled by their largest component first, so vectors with
    tiny (1e-200) or huge components normalise instead of under- or overflowing."""
    scale = np.max(np.abs(v), axis=-1, keepdims=True)
    s = v / np.where(scale > 0, scale, 1.0)
    return s / np.linalg.norm(s, axis=-1, keepdims=True)


def transform_normals(normals: ArrayLike, matrix: ArrayLike) -> NDArray[np.float64]:
    """Transform normals with the inverse-transpose of a matrix's 3 x 3 linear part.

    A surface transformed by ``M`` has normals ``M^-T n``: tangents ``t`` map to ``M t`` and
    ``(M^-T n) . (M t) = n . t = 0``. Mirroring matrices (``det M < 0``) are handled (the cofactor
    shortcut ``det(M) M^-T`` would flip them). The result is *not* renormalised: cube lookups
    normalise implicitly, and :func:`reflect` / the shaders normalise where needed.

    Parameters
    ----------
    normals : (..., 3) float
        Normals in object or rest-pose space.
    matrix : (..., 3, 3) or (..., 4, 4) float
        Object-to-world (or skinning) matrix, column-vector convention (``world = M @ p``); a
        4 x 4 affine matrix's upper-left 3 x 3 block is used. Leading axes broadcast against
        ``normals`` (one matrix per normal for skinning).

    Returns
    -------
    (..., 3) float64
        World-space normals ``M^-T n``.
    """
    n = _vectors(normals, "normals")
    m = _finite(matrix, "matrix")
    if m.ndim < 2 or m.shape[-2:] not in ((3, 3), (4, 4)):
        raise ValueError(f"matrix must have shape (..., 3, 3) or (..., 4, 4), got {m.shape}.")
    m3 = m[..., :3, :3]
    try:
        inv = np.linalg.inv(m3)
    except np.linalg.LinAlgError:
        raise ValueError("matrix is singular: it has no inverse-transpose for normals.") from None
    if not np.all(np.isfinite(inv)):
        raise ValueError("matrix is singular: it has no inverse-transpose for normals.")
    return np.einsum("...ji,...j->...i", inv, n)


def reflect(views: ArrayLike, normals: ArrayLike) -> NDArray[np.float64]:
    """Mirror reflection of the view vector: ``R = 2 (N . V) N - V`` with ``N`` normalised.

    Parameters
    ----------
    views : (..., 3) float
        ``V``, from the surface point *to the eye*; any length (``|R| = |V|``).
    normals : (..., 3) float
        ``N``, any non-zero length.

    Returns
    -------
    (..., 3) float64
        ``R``, pointing away from the surface (the direction to look up in a specular map).
    """
    v = _vectors(views, "views")
    n = unit_vectors(_vectors(normals, "normals", nonzero=True))
    return 2.0 * np.einsum("...i,...i->...", n, v)[..., None] * n - v


def _sampler(cube: CubeLike, name: str) -> CubeSampler:
    try:
        return CubeSampler(cube)
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from None


def _map_samplers(
    diffuse: CubeLike, specular: CubeLike, specular_name: str
) -> tuple[CubeSampler, CubeSampler]:
    """Samplers of the diffuse and the specular map, checked to have the same channels."""
    d_s, s_s = _sampler(diffuse, "diffuse"), _sampler(specular, specular_name)
    if d_s.channels != s_s.channels:
        raise ValueError(
            f"diffuse and specular maps must have the same channels, got {d_s.channels} "
            f"and {s_s.channels}."
        )
    return d_s, s_s


def _channels(value: ArrayLike, name: str, c: int) -> NDArray[np.float64]:
    a = _finite(value, name)
    if a.ndim == 0 or a.shape[-1] not in (1, c):
        raise ValueError(f"{name} must have shape (..., {c}) (or (..., 1)), got {a.shape}.")
    return a


def _batch(*shapes: tuple[int, ...]) -> tuple[int, ...]:
    try:
        return np.broadcast_shapes(*shapes)
    except ValueError:
        raise ValueError(
            "the leading axes of the inputs do not broadcast: "
            + ", ".join(str(s) for s in shapes)
            + "."
        ) from None


def shade_classic(
    normals: ArrayLike,
    *,
    diffuse: CubeLike,
    specular: CubeLike,
    albedo: ArrayLike,
    gloss: ArrayLike,
    views: ArrayLike | None = None,
) -> NDArray[np.float32]:
    """Bloom's cube-map lighting: ``albedo * Diffuse[N] + gloss * Specular[R(N)]``.

    Parameters
    ----------
    normals : (..., 3) float
        World-space normals, any non-zero length (the lookups normalise implicitly).
    diffuse : CubeMap or (6, n, n, C) array
        Diffuse map (irradiance / pi); level 0 is sampled, seamless bilinear.
    specular : CubeMap or (6, m, m, C) array
        Specular map; level 0 is sampled, seamless bilinear.
    albedo : (..., C) float
        Diffuse colour.
    gloss : (...) float
        Specular weight (the seed keeps it in the normal map's alpha).
    views : (..., 3) float or None
        Surface-to-eye vectors. ``None``: look ``Specular`` up at ``N`` (no view, see the module
        docstring); otherwise at ``R = reflect(views, normals)``.

    Returns
    -------
    (..., C) float32
    """
    n = _vectors(normals, "normals", nonzero=True)
    d_s, s_s = _map_samplers(diffuse, specular, "specular")
    c = d_s.channels
    alb = _channels(albedo, "albedo", c)
    g = _finite(gloss, "gloss")
    v = None if views is None else _vectors(views, "views")
    shapes = [n.shape[:-1], alb.shape[:-1], g.shape] + ([] if v is None else [v.shape[:-1]])
    lead = _batch(*shapes)
    n = np.broadcast_to(n, (*lead, 3))
    spec_dir = n if v is None else reflect(np.broadcast_to(v, (*lead, 3)), n)
    out = alb * d_s.bilinear(n) + g[..., None] * s_s.bilinear(spec_dir)
    return out.astype(np.float32)


def shade_split_sum(
    normals: ArrayLike,
    views: ArrayLike,
    *,
    albedo: ArrayLike,
    roughness: ArrayLike,
    f0: ArrayLike,
    diffuse: CubeLike,
    specular_levels: CubeLike,
    dfg: ArrayLike,
    reduce_diffuse: bool = True,
) -> NDArray[np.float32]:
    """Split-sum image-based lighting with a diffuse map, a GGX prefiltered chain and a DFG LUT.

    ``s = F0 A + B`` with ``(A, B) = dfg_lookup(dfg, max(N . V, 0), roughness)``;
    ``out = albedo (1 - s) Diffuse[N] + s Prefiltered[R, roughness (levels - 1)]`` (without the
    ``(1 - s)`` when ``reduce_diffuse`` is false). See the module docstring.

    Parameters
    ----------
    normals : (..., 3) float
        World-space normals, any non-zero length.
    views : (..., 3) float
        Surface-to-eye vectors, any non-zero length.
    albedo : (..., C) float
        Lambertian colour.
    roughness : (...) float in [0, 1]
        Perceptual roughness (glTF), ``alpha = roughness^2``.
    f0 : (..., C) float
        Reflectance at normal incidence.
    diffuse : CubeMap or (6, n, n, C) array
        Diffuse map (irradiance / pi), level 0 sampled bilinearly.
    specular_levels : CubeMap or sequence of (6, n_k, n_k, C) arrays
        GGX prefiltered chain, level ``k`` at roughness ``k / (levels - 1)``; sampled trilinearly
        at ``lod = roughness (levels - 1)``.
    dfg : array
        A LUT from :func:`probegrid.core.dfg.dfg_lut`.
    reduce_diffuse : bool
        Scale the diffuse term by ``1 - s`` (glTF Sample Viewer behaviour, default).

    Returns
    -------
    (..., C) float32
    """
    n = _vectors(normals, "normals", nonzero=True)
    v = _vectors(views, "views", nonzero=True)
    d_s, s_s = _map_samplers(diffuse, specular_levels, "specular_levels")
    c = d_s.channels
    alb = _channels(albedo, "albedo", c)
    spec_f0 = _channels(f0, "f0", c)
    r = _finite(roughness, "roughness")
    if np.any((r < 0) | (r > 1)):
        raise ValueError("roughness must lie in [0, 1].")
    lead = _batch(n.shape[:-1], v.shape[:-1], alb.shape[:-1], spec_f0.shape[:-1], r.shape)
    n = np.broadcast_to(n, (*lead, 3))
    v = np.broadcast_to(v, (*lead, 3))
    r = np.broadcast_to(r, lead)
    n_dot_v = np.clip(np.einsum("...i,...i->...", unit_vectors(n), unit_vectors(v)), 0.0, 1.0)
    ab = np.asarray(dfg_lookup(dfg, n_dot_v, r), dtype=np.float64)
    s = spec_f0 * ab[..., 0:1] + ab[..., 1:2]
    prefiltered = s_s.trilinear(reflect(v, n), roughness_to_lod(r, s_s.num_levels))
    kd = alb * (1.0 - s) if reduce_diffuse else alb
    out = kd * d_s.bilinear(n) + s * prefiltered
    return out.astype(np.float32)
