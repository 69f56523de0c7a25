"""Emissive triangles as lights: next-event estimation at hits and the exact direct view.

A triangle whose material has a non-zero ``emissive`` factor emits radiance ``Le`` (times its
emissive texture) from its **front**, the side its winding's normal points to -- whatever the
material's ``doubleSided`` flag, as a path tracer's area light does (a panel just under a
ceiling lights the room, not the ceiling behind it).

Light at surface points (:meth:`Emitters.irradiance`)
-----------------------------------------------------
The irradiance a surface point receives directly from the emitters is estimated by explicit
light sampling, scaled to the exact unoccluded integral (a ratio estimator, as Heitz et al.):

    E = A * [sum_i V_i g_i Le_i / p_i] / [sum_i g_i Lc_i / p_i],

with ``A`` the exact unoccluded irradiance of the emitters at their uniform radiance ``Lc``
(the emitters' outlines clipped to the point's upper half-space and integrated by Lambert's edge
formula, :func:`probegrid.bake.kernels.emitters.polygon_irradiance`; coplanar triangles of one
radiance are merged into their outlines first, :func:`emitter_outlines`, so a quad costs one
clipped 4-gon, not two triangles, and a fan-tessellated disc its rim), ``L`` points sampled on
the emitters (a triangle picked in proportion to its power ``area * mean(Le)``, a uniform point
on it), ``g = cos_x cos_y / d^2``, ``V`` the shadow ray's visibility and ``p`` the area
density. It is
exact wherever nothing occludes the emitters (the ratio is 1: a furnace box is exact) and
wherever everything does (0), never negative, and biased only in penumbrae, where it
is consistent. (An additive control variate, ``A + sum [V (Le - Lc) - (1 - V) Lc] g / (L p)``,
is unbiased but goes negative in shadows; clamped at 0, it made the Cornell box's shadowed
probes 4-6 % too bright against a path tracer: 6.0 % worst probe, 2.7 % with this estimator.)
Where no sample sees the control (all on the point's own plane) the control variate's
estimate is used. In a scene whose emitters' outlines have more than :data:`MAX_ANALYTIC` edges
``A`` is left out: plain next-event estimation, ``sum V g Le / (L p)``. Unlike light that reaches hits
through a probe grid, this does not depend on the grid's resolution (a small bright panel
lights its walls as a path tracer's next-event estimation does).

What a probe sees of the emitters (:meth:`Emitters.texel_view`)
---------------------------------------------------------------
A probe's rays leave through texel centres (or a few jittered points), and would catch a panel
smaller than a texel whole or not at all. Instead, each emitting triangle facing the probe is
clipped to every cube texel it overlaps (on the face plane, where its edges stay straight) and
the exact solid angle of each piece is computed
(:func:`probegrid.bake.kernels.emitters.texel_emitter_coverage`, on sub-texels,
:data:`VIEW_SUBDIVISION` per texel side); one shadow ray toward each piece's centroid gives its
visibility. A texel's emission is then
``sum Le * Omega_piece * V / Omega_texel``: a panel keeps its exact energy whatever its size,
and the texel's own rays supply the rest (the light reflected by the surfaces they hit).

References: J. Arvo, "Analytic Methods for Simulated Light Transport", 1995 (Lambert's edge
formula); Van Oosterom & Strackee, IEEE Trans. Biomed. Eng. 30 (1983) (triangle solid angle);
E. Heitz et al., "Combining Analytic Direct Illumination and Stochastic Shadows", 2018 (the
the ratio estimator of unoccluded light and stochastic shadows).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from probegrid.bake.kernels.cube import CUBE_AXES
from probegrid.bake.kernels.emitters import (
    EmitterOutlines,
    EmitterTriangles,
    emitter_estimate,
    emitter_samples,
    emitter_shadow_rays,
    polygon_irradiance,
    texel_emitter_coverage,
)
from probegrid.bake.kernels.sampling import alias_draw, alias_table
from probegrid.core.arrays import sum_rows
from probegrid.core.cubemap import texel_solid_angles
from probegrid.raytrace import EmbreeRays, RayTracer
from probegrid.scene import Scene

__all__ = ["MAX_ANALYTIC", "VIEW_SUBDIVISION", "Emitters", "emitter_outlines"]

#: Sub-texels per texel side whose pieces of the emitters get their own visibility ray.
VIEW_SUBDIVISION = 4

#: Edges of the emitters' outlines (:func:`emitter_outlines`) up to which the exact unoccluded
#: integral is used at every hit (its cost grows with them; above, plain next-event estimation).
MAX_ANALYTIC = 768

#: Emitting triangles above which their outlines are not even looked for (plain next-event
#: estimation): chaining edges is set-up work per process, bounded here.
MAX_OUTLINED = 16384


def emitter_outlines(vertices: NDArray[np.float64], normals: NDArray[np.float64],
                     radiance: NDArray[np.float64]) -> EmitterOutlines:
    """Uniformly emitting triangles as planar regions bounded by closed loops, the input of
    :func:`probegrid.bake.kernels.emitters.polygon_irradiance` (same integral, fewer edges).

    Triangles ``vertices (E, 3, 3)`` (unit ``normals (E, 3)`` as wound) with the same
    ``radiance (E, 3)`` (bit for bit) and the same plane (normal and offset within 1e-9 of the
    scene's size) form one region; within it, an edge two triangles share in opposite
    directions (same corner positions, bit for bit) is interior and cancels, and the remaining
    directed edges are chained into closed loops (outlines, holes). Triangles that only look
    alike stay apart, which costs edges, never accuracy.

    Returns the :class:`~probegrid.bake.kernels.emitters.EmitterOutlines`
    ``loop_vertices (V, 3)``, ``loop_start (L + 1,)``, ``group_loops (G + 1,)``,
    ``group_normals (G, 3)`` and ``group_radiance (G, 3)``.
    """
    v = np.asarray(vertices, np.float64).reshape(-1, 3, 3)
    nrm = np.asarray(normals, np.float64).reshape(-1, 3)
    rad = np.asarray(radiance, np.float64).reshape(-1, 3)
    scale = max(float(np.abs(v).max()) if v.size else 0.0, 1e-300)
    offset = np.einsum("ij,ij->i", nrm, v[:, 0]) / scale
    key = np.column_stack([np.round(nrm * 1e9), np.round(offset * 1e9), rad])
    _, group_of = np.unique(key, axis=0, return_inverse=True)
    group_of = group_of.reshape(-1)
    loops: list[NDArray[np.float64]] = []
    group_loops, g_normals, g_radiance = [0], [], []
    for g in range(int(group_of.max()) + 1 if len(v) else 0):  # loop over planar regions
        tris = v[group_of == g]
        corners, index = np.unique(tris.reshape(-1, 3), axis=0, return_inverse=True)
        index = index.reshape(-1, 3)
        edges = np.concatenate([index[:, [0, 1]], index[:, [1, 2]], index[:, [2, 0]]])
        count: dict[tuple[int, int], int] = {}
        for a, b in edges.tolist():  # loop over the region's edges (setup, not rays)
            if count.get((b, a), 0) > 0:
                count[(b, a)] -= 1  # shared in opposite directions: interior
            else:
                count[(a, b)] = count.get((a, b), 0) + 1
        leaving: dict[int, list[int]] = {}
        for (a, b), k in count.items():
            leaving.setdefault(a, []).extend([b] * k)
        for start in sorted(leaving):  # chain the boundary edges into closed loops
            while leaving[start]:
                loop, at = [start], leaving[start].pop()
                while at != start:
                    loop.append(at)
                    at = leaving[at].pop()
                loops.append(corners[loop])
        group_loops.append(len(loops))
        first = np.flatnonzero(group_of == g)[0]
        g_normals.append(nrm[first])
        g_radiance.append(rad[first])
    starts = np.cumsum([0] + [len(lp) for lp in loops]).astype(np.int64)
    return EmitterOutlines(
        np.ascontiguousarray(np.concatenate(loops) if loops else np.zeros((0, 3))),
        starts, np.array(group_loops, np.int64),
        np.ascontiguousarray(np.reshape(g_normals, (-1, 3)), dtype=np.float64),
        np.ascontiguousarray(np.reshape(g_radiance, (-1, 3)), dtype=np.float64))


@dataclass(frozen=True, eq=False)
class Emitters:
    """The emitting triangles of a scene and how to sample them.

    Attributes
    ----------
    scene : Scene
    triangles : (E,) int64
        Indices of the triangles with a non-zero emissive factor.
    """

    scene: Scene
    triangles: NDArray[np.int64]

    @classmethod
    def from_scene(cls, scene: Scene) -> Emitters:
        emis = scene.surface_tables.emissive
        tri = np.flatnonzero((emis[scene.material].max(axis=1) > 0)
                             & (scene.triangle_areas > 0)).astype(np.int64)
        return cls(scene, tri)

    def __len__(self) -> int:
        return len(self.triangles)

    @cached_property
    def vertices(self) -> NDArray[np.float64]:
        """(E, 3, 3) float64 corners."""
        return np.ascontiguousarray(self.scene.vertices[self.scene.triangles[self.triangles]],
                                    dtype=np.float64)

    @cached_property
    def normals(self) -> NDArray[np.float64]:
        """(E, 3) float64 unit normals as wound (the emitting side)."""
        return np.ascontiguousarray(self.scene.triangle_normals[self.triangles])

    @cached_property
    def factor(self) -> NDArray[np.float64]:
        """(E, 3) emissive factor (the radiance without textures)."""
        return np.ascontiguousarray(self.scene.surface_tables.emissive[self.scene.material[
            self.triangles]])

    @cached_property
    def textured(self) -> NDArray[np.bool_]:
        """(E,) the triangle's emission has a texture."""
        flags = np.array([m.emissive_texture is not None for m in self.scene.materials], bool)
        return flags[self.scene.material[self.triangles]]

    @cached_property
    def outlines(self) -> EmitterOutlines:
        """The emitters at their uniform radiance (the factor) as :func:`emitter_outlines`."""
        return emitter_outlines(self.vertices, self.normals, self.factor)

    @cached_property
    def analytic(self) -> bool:
        """Whether the exact unoccluded integral (the ratio estimator's scale) is used: some
        emitters (at most :data:`MAX_OUTLINED` triangles), their outlines at most
        :data:`MAX_ANALYTIC` edges."""
        return 0 < len(self) <= MAX_OUTLINED and len(self.outlines[0]) <= MAX_ANALYTIC

    @cached_property
    def control(self) -> NDArray[np.float64]:
        """(E, 3) the control variate's uniform radiance (the factor; 0 without one)."""
        if not self.analytic:
            return np.zeros((len(self), 3))
        return self.factor

    @cached_property
    def _selection(self) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
        """The triangles' selection in proportion to their power ``area * mean(factor)``: its
        alias table ``(accept, alias)`` (:func:`probegrid.bake.kernels.sampling.alias_table`) and
        ``area / probability`` per triangle."""
        area = self.scene.triangle_areas[self.triangles]
        power = area * self.factor.mean(axis=1)
        prob = power / power.sum()
        accept, alias = alias_table(prob)
        return accept, alias, area / prob

    # -- light at surface points -----------------------------------------------------------
    def irradiance(self, points: NDArray[np.float64], normals: NDArray[np.float64],
                   random: NDArray[np.float64], tracer: RayTracer, eps: float
                   ) -> tuple[NDArray[np.float64], int]:
        """Direct irradiance (lux, RGB) from the emitters at ``points (n, 3)`` with unit
        ``normals (n, 3)`` facing the side that is lit, from ``random (n, L, 3)`` uniform
        numbers in [0, 1) (L light samples per point). Returns ``(n, 3)`` and rays cast."""
        n = len(points)
        out = np.zeros((n, 3))
        if n == 0 or len(self) == 0:
            return out, 0
        analytic = (polygon_irradiance(points, normals, self.outlines) if self.analytic
                    else np.zeros((0, 3)))
        accept, alias, inv_pdf = self._selection
        if self.textured.any():  # the points' radiance through the textures
            e = alias_draw(accept, alias, random[..., 0])
            r1 = np.sqrt(random[..., 1])
            bu, bv = r1 * (1.0 - random[..., 2]), r1 * random[..., 2]
            surf = self.scene.surface_at(self.triangles[e], bu, bv)
            rays = emitter_shadow_rays(
                points, normals, np.ascontiguousarray(surf.position),
                np.ascontiguousarray(self.normals[e]), np.ascontiguousarray(surf.emission),
                np.ascontiguousarray(self.control[e]), np.ascontiguousarray(inv_pdf[e]), eps,
                tracer.centre)
        else:  # the same, in one compiled pass
            rays = emitter_samples(points, normals, np.ascontiguousarray(random),
                                   (accept, alias, inv_pdf),
                                   EmitterTriangles(self.vertices, self.normals, self.factor,
                                                    self.control), eps, tracer.centre)
        which, org, dirs, lengths, vis, occ, ok = rays
        blocked = (tracer.occluded_rays(EmbreeRays(org, dirs, lengths), bool(ok[0]))
                   if len(which) else np.zeros(0, np.bool_))
        # with the exact unoccluded integral: it, scaled by the samples' visible share (ratio
        # estimator); where no sample saw the control (all on the point's own plane, say), the
        # control variate's estimate, A + sum of the contributions
        return emitter_estimate(n, which, blocked, vis, occ, analytic), len(which)

    # -- what a probe sees -----------------------------------------------------------------
    def texel_view(self, origin: NDArray[np.float64], n: int, tracer: RayTracer, eps: float
                   ) -> tuple[NDArray[np.int64], NDArray[np.float64], int]:
        """The emitters' mean radiance over the texels of an ``n``-cube at ``origin (3,)``.

        Returns the flat texel indices ``(k,)`` that see some emitter (unique, sorted), their
        mean emitted radiance ``(k, 3)`` (exact solid-angle coverage, one shadow ray per
        sub-texel and triangle piece for visibility, :data:`VIEW_SUBDIVISION`) and the rays
        cast.
        """
        if len(self) == 0:
            return np.zeros(0, np.int64), np.zeros((0, 3)), 0
        o = np.ascontiguousarray(origin, dtype=np.float64)
        # pieces of sub-texels (VIEW_SUBDIVISION^2 per texel), each with its own shadow ray:
        # an occluder's edge across a texel is resolved to a sub-texel; the coverage stays exact.
        # Emitters that would need more than 4 rays per texel of the whole cube get 1 per piece.
        for sub in (VIEW_SUBDIVISION, 1):
            m = n * sub
            limit = 24 * n * n if sub > 1 else np.inf
            cap = 24 * n * n  # (room for what the sub-texel pass keeps: one call, not two)
            while True:
                count, tex, tri, omega, dirs, dist = texel_emitter_coverage(
                    o, self.vertices, self.normals, m, CUBE_AXES, cap)
                if count <= cap or count > limit:
                    break
                cap = count
            if count <= min(cap, limit):
                break
        tex, tri, omega, dirs, dist = (tex[:count], tri[:count], omega[:count], dirs[:count],
                                       dist[:count])
        if count == 0:
            return np.zeros(0, np.int64), np.zeros((0, 3)), 0
        if sub > 1:  # sub-texel (face, row, col) of the m-cube -> texel of the n-cube
            face, rest = np.divmod(tex, m * m)
            row, col = np.divmod(rest, m)
            tex = (face * n + row // sub) * n + col // sub
        ok = np.isfinite(dist) & (dist > 2 * eps)
        visible = np.zeros(count, bool)
        if ok.any():
            visible[ok] = ~tracer.occluded(np.broadcast_to(o, (int(ok.sum()), 3)), dirs[ok],
                                           dist[ok] * (1 - 1e-4) - eps, tmin=eps)
        radiance = self.factor[tri].copy()
        if self.textured.any():
            sel = np.flatnonzero(self.textured[tri] & visible)
            if sel.size:
                radiance[sel] = self._radiance_at(tri[sel], o + dist[sel, None] * dirs[sel])
        sa = texel_solid_angles(n).reshape(-1)
        value = radiance * (omega * visible / sa[tex])[:, None]
        uniq, inv = np.unique(tex, return_inverse=True)
        return uniq, sum_rows(inv, value, len(uniq)), int(ok.sum())

    def _radiance_at(self, e: NDArray[np.int64], points: NDArray[np.float64]
                     ) -> NDArray[np.float64]:
        """Emitted radiance (textures applied) at points on emitter triangles ``e``."""
        v = self.vertices[e]
        a, b, c = v[:, 0], v[:, 1], v[:, 2]
        e1, e2, d = b - a, c - a, points - a
        d11 = np.einsum("ij,ij->i", e1, e1)
        d12 = np.einsum("ij,ij->i", e1, e2)
        d22 = np.einsum("ij,ij->i", e2, e2)
        p1 = np.einsum("ij,ij->i", d, e1)
        p2 = np.einsum("ij,ij->i", d, e2)
        den = d11 * d22 - d12 * d12
        bu = np.clip((d22 * p1 - d12 * p2) / den, 0.0, 1.0)
        bv = np.clip((d11 * p2 - d12 * p1) / den, 0.0, 1.0)
        return self.scene.surface_at(self.triangles[e], bu, bv).emission
