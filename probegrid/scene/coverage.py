"""What stops a ray where it hits a surface: glTF's alpha modes and thin transmission.

A ray that hits a triangle stops there with a probability ``p`` (the model every ray of the
bake follows, primary, shadow and gather rays alike; the tracer draws it,
:meth:`probegrid.raytrace.RayTracer.intersect`):

* ``OPAQUE``: ``p = 1``;
* ``MASK``: ``p = 1`` where alpha >= ``alphaCutoff``, ``p = 0`` (a hole) elsewhere (glTF 2.0,
  "Alpha Coverage"): a cut-out leaf or fence passes light exactly through its holes;
* ``BLEND``: ``p = alpha`` -- stochastic transparency (Enderton et al. 2010): alpha is the
  share of the surface that covers the pixel, so the expected light through it is
  ``(1 - alpha)`` times what lies behind, and the expected light it reflects ``alpha`` times
  its own;
* ``KHR_materials_transmission`` (thin-walled: no volume, no refraction): ``p`` is multiplied
  by ``1 - T``, ``T = transmissionFactor * transmissionTexture.r`` (the texture linear, read
  through its own coordinates). The extension's thin-walled surface is
  ``mix(diffuse, specular_btdf * baseColor, T)``: it reflects ``1 - T`` of its diffuse light
  and passes ``T`` of the light behind it straight, **multiplied by the base colour**
  ``c = baseColorFactor.rgb * baseColorTexture.rgb * COLOR_0.rgb`` per channel. A ray that
  passes a surface therefore carries the weight ``w = ((1 - a) + a T c) / ((1 - a) + a T)``
  (``a`` the alpha share above: the light through the holes is untinted, through the glass
  tinted), so that the expected light through is ``(1 - a) + a T c`` per channel
  (:meth:`Coverage.pass_weight`; the tracer multiplies a ray's weights along it,
  ``RayTracer.intersect(weights=...)``, ``shadow_weights``, ``transmittance(rgb=True)``).
  The specular lobe (the btdf's roughness, the Fresnel term) is not modelled: a pane of
  ``T = 1`` and white base colour passes everything.

Alpha is ``baseColorFactor.a * baseColorTexture.a * COLOR_0.a`` (glTF 2.0), the texture read
through its :class:`~probegrid.scene.textures.TexCoord` with its sampler's wrap modes.

A ray's uniform number ``xi`` in ``[0, 1)`` (the tracer's: a hash of the ray and the
triangle, so the same ray passes or stops the same way every time) decides: the ray stops
when ``xi < p``. MASK and OPAQUE need none. Where one ray stands for all the light (a probe's
view of a punctual light), the tracer takes the expectation instead, the product of
``1 - p`` along the ray (:meth:`probegrid.raytrace.RayTracer.transmittance`).

Reference: glTF 2.0 specification, 3.9.4 "Alpha Coverage"; KHR_materials_transmission;
Enderton, Sintorn, Shirley, Luebke, "Stochastic Transparency", I3D 2010.
"""

from __future__ import annotations

import hashlib
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import frozen
from probegrid.scene.kernels import multiply_texture
from probegrid.scene.textures import _WRAPS

if TYPE_CHECKING:
    from probegrid.scene.model import Scene
    from probegrid.scene.textures import TexCoord

__all__ = ["Coverage"]


class Coverage:
    """The coverage of a scene's triangles (module docstring), for the tracer.

    Attributes
    ----------
    cutout : (T,) bool, read-only
        The triangles a ray may pass (a material that is not opaque or transmits).
    stochastic : bool
        Whether some material draws (BLEND, transmission): else every hit's ``p`` is 0 or 1
        and a ray needs no random number.
    key : str
        A hash of what decides coverage (materials' modes, factors, alpha textures and their
        coordinates, the vertex alphas): two scenes with the same key pass the same rays.
    tinted : bool
        Whether a ray that passes some surface may carry a weight other than 1 (a transmitting
        material whose base colour is not white, or is textured, or vertex colours): else the
        weights need not be kept.
    """

    def __init__(self, scene: Scene) -> None:
        self._scene = scene
        mats = scene.materials
        flags = np.array([not m.stops_every_ray for m in mats], dtype=bool)
        #: Whether a hit may need a draw (BLEND or transmission); else ``p`` is 0 or 1.
        self.stochastic = any(m.alpha_mode == "BLEND" or m.transmission > 0 for m in mats)
        self.cutout: NDArray[np.bool_] = flags[scene.material]
        self.cutout.setflags(write=False)
        # per material, what every hit reads (indexed by the hits' materials)
        self._alpha = np.array([m.base_color[3] for m in mats])
        self._mode = np.array([("OPAQUE", "MASK", "BLEND").index(m.alpha_mode) for m in mats])
        self._cutoff = np.array([m.alpha_cutoff for m in mats])
        self._transmission = np.array([m.transmission for m in mats])
        self._transmission_textured = [i for i, m in enumerate(mats)
                                       if m.transmission_texture is not None
                                       and m.transmission > 0]
        self.tinted = any(m.transmission > 0 and (
            np.any(m.base_color[:3] != 1.0) or m.base_color_texture is not None
            or scene.colors is not None) for m in mats)
        h = hashlib.sha256(b"probegrid-coverage-v1;")
        h.update(np.ascontiguousarray(scene.material, "<i8").tobytes())
        for m in mats:
            h.update(repr((m.alpha_mode, m.alpha_cutoff, m.transmission, float(m.base_color[3]),
                           tuple(m.base_color_uv), m.base_color_wrap)).encode())
            if m.base_color_texture is not None and m.alpha_mode != "OPAQUE":
                h.update(np.ascontiguousarray(m.base_color_texture[..., 3], "<f4").tobytes())
        if scene.colors is not None:
            h.update(np.ascontiguousarray(scene.colors[:, 3], "<f8").tobytes())
        for a in (scene.uvs, *scene.extra_uvs):
            if a is not None:
                h.update(np.ascontiguousarray(a, "<f8").tobytes())
        for m in mats:  # (a scene without transmission textures keys as before)
            if m.transmission_texture is not None:
                h.update(repr((tuple(m.transmission_uv), m.transmission_wrap)).encode())
                h.update(np.ascontiguousarray(m.transmission_texture, "<f4").tobytes())
        if self.tinted:
            for m in mats:
                h.update(np.ascontiguousarray(m.base_color[:3], "<f8").tobytes())
                if m.base_color_texture is not None:
                    h.update(np.ascontiguousarray(m.base_color_texture[..., :3], "<f4").tobytes())
            if scene.colors is not None:
                h.update(np.ascontiguousarray(scene.colors[:, :3], "<f8").tobytes())
        self.key = h.hexdigest()

    def alpha(self, prim: NDArray[np.int64], u: NDArray[np.float64],
              v: NDArray[np.float64]) -> NDArray[np.float64]:
        """Alpha ``baseColorFactor.a * baseColorTexture.a * COLOR_0.a`` at barycentric points
        ``(1 - u - v) a + u b + v c`` of triangles ``prim`` (each ``(k,)``)."""
        sc = self._scene
        prim = np.ascontiguousarray(prim, np.int64)
        u = np.ascontiguousarray(u, np.float64)
        v = np.ascontiguousarray(v, np.float64)
        mat = sc.material[prim]
        out = self._alpha[mat]
        if sc.colors is not None:
            tri = sc.triangles[prim]
            col = sc.colors[:, 3]
            out *= (1.0 - u - v) * col[tri[:, 0]] + u * col[tri[:, 1]] + v * col[tri[:, 2]]
        hit = np.flatnonzero(np.bincount(mat, minlength=len(sc.materials)))
        for i in hit:  # loop over the materials hit, not over hits
            m = sc.materials[int(i)]
            if m.base_color_texture is not None and m.alpha_mode != "OPAQUE":
                self._multiply(out, prim, u, v, mat == i, m.base_color_texture,
                               m.base_color_uv, m.base_color_wrap, 3)
        return out

    def transmission(self, prim: NDArray[np.int64], u: NDArray[np.float64],
                     v: NDArray[np.float64]) -> NDArray[np.float64]:
        """``T = transmissionFactor * transmissionTexture.r`` at barycentric points of
        triangles ``prim`` (each ``(k,)``)."""
        sc = self._scene
        prim = np.ascontiguousarray(prim, np.int64)
        mat = sc.material[prim]
        out = self._transmission[mat]
        if self._transmission_textured:
            u = np.ascontiguousarray(u, np.float64)
            v = np.ascontiguousarray(v, np.float64)
            for i in self._transmission_textured:  # loop over transmitting materials, not hits
                m = sc.materials[i]
                self._multiply(out, prim, u, v, mat == i, m.transmission_texture,
                               m.transmission_uv, m.transmission_wrap, 0)
        return out

    def _multiply(self, out: NDArray[np.float64], prim: NDArray[np.int64],
                  u: NDArray[np.float64], v: NDArray[np.float64], rows: NDArray[np.bool_],
                  texture: NDArray[np.float32], texcoord: TexCoord, wrap: tuple[str, str],
                  channel: int) -> None:
        """``out (k,)`` at the hits ``rows`` (a mask) multiplied in place by ``channel`` of a
        material's ``texture``, read through its texture coordinates ``texcoord`` (set and
        transform) with its ``wrap`` modes."""
        at = np.flatnonzero(rows)
        if not at.size:
            return
        sc = self._scene
        uvs, xform = sc.kernel_texcoords(texcoord)
        multiply_texture(out.reshape(-1, 1), at, *frozen((
            (prim, u, v), np.ascontiguousarray(sc.triangles, np.int64), uvs,
            np.asarray(texture, np.float32))),
            (_WRAPS.index(wrap[0]), _WRAPS.index(wrap[1])), frozen(xform), channel)

    def _shares(self, prim: NDArray[np.int64], u: NDArray[np.float64], v: NDArray[np.float64]
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(a, T)``: the alpha share that covers (1 opaque, 0 or 1 MASK, alpha BLEND) and the
        transmission, at the hits."""
        sc = self._scene
        mat = sc.material[np.asarray(prim, np.int64)]
        modes = self._mode[mat]
        a = np.ones(len(mat))
        alpha_rows = modes != 0
        if alpha_rows.any():
            al = self.alpha(np.asarray(prim)[alpha_rows], np.asarray(u)[alpha_rows],
                            np.asarray(v)[alpha_rows])
            cutoff = self._cutoff[mat[alpha_rows]]
            a[alpha_rows] = np.where(modes[alpha_rows] == 1, (al >= cutoff).astype(np.float64),
                                     np.clip(al, 0.0, 1.0))
        return a, self.transmission(prim, u, v)

    def stop_probability(self, prim: NDArray[np.int64], u: NDArray[np.float64],
                         v: NDArray[np.float64]) -> NDArray[np.float64]:
        """``p``, the probability that a ray hitting triangle ``prim`` at ``(u, v)`` stops
        there (module docstring), ``(k,)`` in [0, 1]."""
        a, t = self._shares(prim, u, v)
        return a * (1.0 - t)

    def pass_weight(self, prim: NDArray[np.int64], u: NDArray[np.float64],
                    v: NDArray[np.float64]) -> NDArray[np.float64]:
        """``w (k, 3)``, the weight a ray that passes triangle ``prim`` at ``(u, v)`` carries
        on: ``((1 - a) + a T c) / ((1 - a) + a T)`` (module docstring; 1 where nothing
        passes)."""
        a, t = self._shares(prim, u, v)
        c = self._scene.surface_at(np.asarray(prim, np.int64), u, v).albedo
        q = (1.0 - a) + a * t
        through = (1.0 - a)[:, None] + (a * t)[:, None] * c
        return np.divide(through, q[:, None], out=np.ones_like(through), where=q[:, None] > 0)

    def stops(self, prim: NDArray[np.int64], u: NDArray[np.float64], v: NDArray[np.float64],
              xi: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether rays hitting triangles ``prim`` at ``(u, v)`` with uniform numbers ``xi``
        stop there: ``xi < p`` (``(k,)`` bool)."""
        return np.asarray(xi) < self.stop_probability(prim, u, v)
