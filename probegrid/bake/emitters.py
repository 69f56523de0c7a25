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
estimate is used. Unlike light that reaches hits through a probe grid, this does not depend on
the grid's resolution (a small bright panel lights its walls as a path tracer's next-event
estimation does).

Emitters of many triangles (:meth:`Emitters.sampling`)
------------------------------------------------------
In a scene whose emitters' outlines have more than :data:`MAX_ANALYTIC` edges (a tessellated
sphere, a tube), ``A`` would cost too much per hit. The emitting triangles are then grouped into
at most :data:`MAX_CLUSTERS` compact clusters (:func:`emitter_clusters`: connected pieces,
split along their longest axis while much longer than thick) and each sample draws a cluster in
proportion to a bound of what it gives the point (power over distance squared, the receiver's
and the emitters' cosines over the cluster's bounding sphere: a light-tree's importance) and a
direction uniform in the cone of that sphere; the ray's first hit supplies ``Le`` (visibility
included). The estimator ``sum Le cos / (p L)``, ``p`` the mixture density over every cone that
holds the direction, is unbiased, and nearly constant per sample for a sphere-like cluster,
whatever its triangles (area sampling of a 5,120-triangle icosphere drew half its samples on
the far side and a few next to the point: a texel of a probe carried 67 % of its light).

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
    EmitterClusters,
    EmitterOutlines,
    EmitterTriangles,
    emitter_estimate,
    emitter_samples,
    cluster_samples,
    emitter_shadow_rays,
    polygon_irradiance,
    texel_emitter_coverage,
)
from probegrid.bake.kernels.sampling import alias_draw, alias_table
from probegrid.core.arrays import sum_rows
from probegrid.core.cubemap import texel_solid_angles
from probegrid.raytrace import EmbreeRays, RayTracer
from probegrid.scene import Scene

__all__ = ["CLUSTER_ELONGATION", "MAX_ANALYTIC", "MAX_CLUSTERS", "VIEW_SUBDIVISION", "Emitters",
           "emitter_clusters", "emitter_outlines"]

#: Sub-texels per texel side whose pieces of the emitters get their own visibility ray.
VIEW_SUBDIVISION = 4

#: Edges of the emitters' outlines (:func:`emitter_outlines`) up to which the exact unoccluded
#: integral is used at every hit (its cost grows with them; above, plain next-event estimation).
MAX_ANALYTIC = 768

#: Emitting triangles above which their outlines are not even looked for (sampled by
#: clusters): chaining edges is set-up work per process, bounded here.
MAX_OUTLINED = 16384

#: Most clusters the emitters are sampled through without the exact integral (each sample
#: weighs every cluster: the cost per hit grows with them).
MAX_CLUSTERS = 64

#: A cluster is split while its bounding sphere's radius exceeds this many times the radius of
#: a sphere of its area (1 for a sphere, 2 for a flat disc, large for a thin tube).
CLUSTER_ELONGATION = 2.5


def emitter_clusters(vertices: NDArray[np.float64], normals: NDArray[np.float64],
                     power: NDArray[np.float64]) -> EmitterClusters:
    """Emitting triangles ``vertices (E, 3, 3)`` (unit ``normals (E, 3)``, ``power (E,)`` =
    area times mean radiance) as at most :data:`MAX_CLUSTERS` compact clusters, the input of
    :func:`probegrid.bake.kernels.emitters.cluster_samples`.

    The clusters start as the triangles' connected pieces (corners shared bit for bit; all
    triangles as one cluster when there are more pieces than :data:`MAX_CLUSTERS`); the
    most elongated cluster (bounding radius over the radius of a sphere of its area, above
    :data:`CLUSTER_ELONGATION`) is split at the median of its triangles' centroids along its
    box's longest axis, until none is or there are :data:`MAX_CLUSTERS`. Each cluster keeps its
    bounding sphere (the box's centre, the farthest corner), its power and the cone of its
    normals (the area-weighted mean normal and the widest angle from it; -1 when they point
    every way, as a sphere's).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    v = np.asarray(vertices, np.float64).reshape(-1, 3, 3)
    e = len(v)
    corners, index = np.unique(v.reshape(-1, 3), axis=0, return_inverse=True)
    index = index.reshape(e, 3)
    graph = coo_matrix((np.ones(3 * e), (np.repeat(np.arange(e), 3), e + index.reshape(-1))),
                       shape=(e + len(corners), e + len(corners)))
    pieces, label = connected_components(graph, directed=False)
    label = label[:e]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    groups = ([np.flatnonzero(label == g) for g in range(pieces)] if pieces <= MAX_CLUSTERS
              else [np.arange(e)])

    def sphere(t: NDArray[np.int64]) -> tuple[NDArray[np.float64], float, float]:
        pts = v[t].reshape(-1, 3)
        centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
        radius = float(np.sqrt(((pts - centre) ** 2).sum(axis=1).max()))
        excess = radius / max(np.sqrt(area[t].sum() / (4 * np.pi)), 1e-300)
        return centre, radius, excess

    spheres = [sphere(t) for t in groups]
    while len(groups) < MAX_CLUSTERS:  # loop over splits (a few dozen), not triangles
        worst = max(range(len(groups)), key=lambda j: spheres[j][2])
        t = groups[worst]
        if spheres[worst][2] <= CLUSTER_ELONGATION or len(t) < 2:
            break
        mid = v[t].mean(axis=1)
        axis = int(np.argmax(np.ptp(mid, axis=0)))
        order = np.argsort(mid[:, axis], kind="stable")
        halves = (t[order[:len(t) // 2]], t[order[len(t) // 2:]])
        groups[worst:worst + 1] = halves
        spheres[worst:worst + 1] = [sphere(h) for h in halves]
    k = len(groups)
    out = EmitterClusters(np.zeros((k, 3)), np.zeros(k), np.zeros(k), np.zeros((k, 3)),
                          -np.ones(k))
    nrm = np.asarray(normals, np.float64).reshape(-1, 3)
    for j, t in enumerate(groups):  # loop over clusters
        out.centre[j], out.radius[j] = spheres[j][0], spheres[j][1]
        out.power[j] = float(np.asarray(power)[t].sum())
        mean = (nrm[t] * area[t, None]).sum(axis=0)
        length = float(np.linalg.norm(mean))
        if length > 1e-3 * max(float(area[t].sum()), 1e-300):
            out.axis[j] = mean / length
            out.spread[j] = float(max((nrm[t] @ out.axis[j]).min(), -1.0))
            if out.spread[j] <= 0.0:  # a cone wider than a hemisphere bounds nothing useful
                out.spread[j] = -1.0
    return out


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
    def covered(self) -> NDArray[np.bool_]:
        """(E,) the triangle's material does not stop every ray (alpha MASK or BLEND,
        transmission): it emits only where, and as much as, a ray hitting it stops
        (:meth:`probegrid.scene.coverage.Coverage.stop_probability`)."""
        cov = self.scene.coverage
        if cov is None:
            return np.zeros(len(self), bool)
        return np.asarray(cov.cutout)[self.triangles]

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
    def clusters(self) -> EmitterClusters:
        """The emitters as :func:`emitter_clusters` (sampled by solid angle when not
        :attr:`analytic`)."""
        area = self.scene.triangle_areas[self.triangles]
        return emitter_clusters(self.vertices, self.normals, area * self.factor.mean(axis=1))

    @cached_property
    def slot(self) -> NDArray[np.int64]:
        """(T,) each scene triangle's row among the emitters, -1 for the others."""
        out = np.full(self.scene.n_triangles, -1, np.int64)
        out[self.triangles] = np.arange(len(self))
        return out

    def sampling(self) -> str:
        """How the light of the emitters is sampled at hits, in words (the bake's summary)."""
        if len(self) == 0:
            return "no emitters"
        if self.analytic:
            return (f"{len(self)} emitting triangles: exact unoccluded integral over "
                    f"{len(self.outlines[0])} outline edges, shadowed by sampled rays")
        return (f"{len(self)} emitting triangles (over the exact integral's {MAX_ANALYTIC} "
                f"outline edges or {MAX_OUTLINED} triangles): sampled by solid angle over "
                f"{len(self.clusters.radius)} clusters, no exact integral")

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
        if not self.analytic:
            return self._cluster_irradiance(points, normals, random, tracer, eps)
        analytic = polygon_irradiance(points, normals, self.outlines)
        accept, alias, inv_pdf = self._selection
        if self.textured.any() or self.covered.any():  # the points' radiance, textures and
            e = alias_draw(accept, alias, random[..., 0])  # coverage applied
            r1 = np.sqrt(random[..., 1])
            bu, bv = r1 * (1.0 - random[..., 2]), r1 * random[..., 2]
            surf = self.scene.surface_at(self.triangles[e], bu, bv)
            emission = surf.emission
            if self.covered.any():
                emission = emission * self._coverage(e, bu, bv)[..., None]
            rays = emitter_shadow_rays(
                points, normals, np.ascontiguousarray(surf.position),
                np.ascontiguousarray(self.normals[e]), np.ascontiguousarray(emission),
                np.ascontiguousarray(self.control[e]), np.ascontiguousarray(inv_pdf[e]), eps,
                tracer.centre)
        else:  # the same, in one compiled pass
            rays = emitter_samples(points, normals, np.ascontiguousarray(random),
                                   (accept, alias, inv_pdf),
                                   EmitterTriangles(self.vertices, self.normals, self.factor,
                                                    self.control), eps, tracer.centre)
        which, org, dirs, lengths, vis, occ, ok = rays
        if len(which) and tracer.tinted:  # through tinted panes: the visible term weighted
            through = tracer.shadow_weights(EmbreeRays(org, dirs, lengths), bool(ok[0]))
            blocked = ~np.any(through > 0, axis=1)
            vis = through * (vis - occ) + occ  # (the estimator adds vis - occ where unblocked)
        else:
            blocked = (tracer.occluded_rays(EmbreeRays(org, dirs, lengths), bool(ok[0]))
                       if len(which) else np.zeros(0, np.bool_))
        # with the exact unoccluded integral: it, scaled by the samples' visible share (ratio
        # estimator); where no sample saw the control (all on the point's own plane, say), the
        # control variate's estimate, A + sum of the contributions
        return emitter_estimate(n, which, blocked, vis, occ, analytic), len(which)

    def _cluster_irradiance(self, points: NDArray[np.float64], normals: NDArray[np.float64],
                            random: NDArray[np.float64], tracer: RayTracer, eps: float
                            ) -> tuple[NDArray[np.float64], int]:
        """:meth:`irradiance` by solid angle toward the :attr:`clusters`
        (:func:`~probegrid.bake.kernels.emitters.cluster_samples`): each ray's first hit, the
        front of an emitter, gives its radiance (textures applied) times the ray's weight."""
        which, org, dirs, weight = cluster_samples(
            np.ascontiguousarray(points, dtype=np.float64),
            np.ascontiguousarray(normals, dtype=np.float64),
            np.ascontiguousarray(random, dtype=np.float64), self.clusters, eps)
        out = np.zeros((len(points), 3))
        if not len(which):
            return out, 0
        tint = None
        if tracer.tinted:
            hits, tint = tracer.intersect_weighted(org, dirs, tmin=eps)
        else:
            hits = tracer.intersect(org, dirs, tmin=eps)
        prim = hits.prim_id
        slot = np.where(prim >= 0, self.slot[np.maximum(prim, 0)], -1)
        lit = np.flatnonzero(slot >= 0)
        front = np.einsum("ij,ij->i", self.normals[slot[lit]], dirs[lit]) < 0
        lit, e = lit[front], slot[lit[front]]
        radiance = self.factor[e].copy()
        tex = np.flatnonzero(self.textured[e])
        if tex.size:
            radiance[tex] = self.scene.surface_at(self.triangles[e[tex]], hits.u[lit[tex]],
                                                  hits.v[lit[tex]]).emission
        if tint is not None:
            radiance *= tint[lit]
        # (a cut-out or blended emitter: the ray passed where it does not cover, as any ray)
        return sum_rows(which[lit], radiance * weight[lit, None], len(points)), len(which)

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
        through = None
        if ok.any() and tracer.tinted:  # (through tinted panes: their weights)
            through = np.zeros((count, 3))
            through[ok] = tracer.occluded_weights(np.broadcast_to(o, (int(ok.sum()), 3)),
                                                  dirs[ok], dist[ok] * (1 - 1e-4) - eps,
                                                  tmin=eps)
            visible = np.any(through > 0, axis=1)
        elif ok.any():
            visible[ok] = ~tracer.occluded(np.broadcast_to(o, (int(ok.sum()), 3)), dirs[ok],
                                           dist[ok] * (1 - 1e-4) - eps, tmin=eps)
        radiance = self.factor[tri].copy()
        if self.textured.any() or self.covered.any():
            sel = np.flatnonzero((self.textured[tri] | self.covered[tri]) & visible)
            if sel.size:
                radiance[sel] = self._radiance_at(tri[sel], o + dist[sel, None] * dirs[sel])
        if through is not None:
            radiance *= through
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
        emission = self.scene.surface_at(self.triangles[e], bu, bv).emission
        if self.covered.any():
            emission = emission * self._coverage(e, bu, bv)[:, None]
        return emission

    def _coverage(self, e: NDArray[np.int64], bu: NDArray[np.float64],
                  bv: NDArray[np.float64]) -> NDArray[np.float64]:
        """The share of emitters ``e`` (any shape) that emits at barycentrics ``bu, bv``: the
        coverage's stop probability (what a ray hitting it there sees of its emission; 1 for
        an emitter that stops every ray)."""
        shape = np.shape(e)
        e = np.asarray(e).reshape(-1)
        out = np.ones(len(e))
        rows = np.flatnonzero(self.covered[e])
        cov = self.scene.coverage
        if rows.size and cov is not None:
            out[rows] = cov.stop_probability(self.triangles[e[rows]],
                                             np.asarray(bu, np.float64).reshape(-1)[rows],
                                             np.asarray(bv, np.float64).reshape(-1)[rows])
        return out.reshape(shape)
