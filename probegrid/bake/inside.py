"""Inside or outside: is a point inside a closed solid of the scene, whatever its materials?

A probe inside a solid sees only the inside of its walls; its light leaks through them into the
grid and the queries beside the solid. glTF's ``doubleSided`` says how a surface is *shaded*,
not which side of it is matter: a closed cube exported from Blender is double-sided, and its
inside shows no back face to the renderer. This module decides from the geometry's **authored
winding** (the face normals as wound, ``doubleSided`` ignored), with fallbacks for meshes whose
winding cannot be trusted.

Method
------
1. **Topology, once per scene** (:class:`SolidIndex`). Vertices are welded by exact position
   (glTF exports split vertices along normal and UV seams), degenerate triangles dropped, and the
   triangles joined across their shared edges into connected components (a union-find with
   orientation parity, Kruskal-style: each edge shared by exactly two triangles says whether
   they are wound alike). A component is

   * **closed and orientable**: every edge is shared by exactly two of its triangles and the
     parities agree (no Moebius twist). Its consistent orientation is made outward by the sign
     of its enclosed volume (divergence theorem, ``V = sum a . (b x c) / 6``). If its authored
     faces agree with the outward orientation for more than half its area, it is a **solid**
     (matter inside: a cube, a slab), else a **shell** (air inside: a room modelled with inward
     faces). A consistently wound mesh is thus read exactly as authored; an inconsistently wound
     one (a few flipped faces) as its majority says -- the fallback for inconsistent winding.
   * a closed **double-sided** component read as a solid that holds a source of light (a
     punctual light, or a point just in front of an emissive triangle of another component,
     tested as in 2.) is read as a shell instead: light does not shine from inside matter, and
     a room modelled from a cube without flipping its normals, double-sided so that it renders
     either way (a common export), is a room -- the fallback for rooms wound inside out.
   * **open, non-manifold or non-orientable**: its winding says nothing about an inside. Its
     single-sided triangles keep their authored back (the RTXGI-style back-face test of the
     classifier); its double-sided ones have no back -- the fallback for open meshes, where the
     classifier's enclosure test (every ray hits within half a cell) still catches a probe shut
     in a small cavity.

2. **The test, per point** (:func:`inside_solid`): ``DIRECTIONS`` rays (a spherical Fibonacci
   set, tilted off the axes) from the point, their nearest hits through Embree. A ray votes
   "inside" when its nearest hit is on the back of its triangle's *effective* orientation (the
   solid's outward normal, the shell's inward one, a single-sided open triangle's authored one).
   From inside a closed solid every ray meets its back first, so the vote is unanimous up to
   rays lost at edges in float32; a point outside every solid gets no vote from solids. A point
   is inside when more than half the rays vote so (a majority, robust to the odd lost ray and to
   another object's faces poking into the solid).

The classifier (:func:`probegrid.bake.stages.classify_task`) marks such a probe invalid, and its
relocation tries the nearby lattice of points with the same test, so a probe inside a slab is
moved out when a free point lies within the allowed distance; an invalid probe has zero weight
in every bounce's indirect lookup and in every query.

References: Jacobson, Kavan and Sorkine-Hornung, "Robust Inside-Outside Segmentation using
Generalized Winding Numbers", SIGGRAPH 2013 (why authored orientation, not parity, decides, and
why open meshes need a fallback); Majercik et al., "Dynamic Diffuse Global Illumination with
Ray-Traced Irradiance Fields", JCGT 8(2), 2019 (the back-face classifier); Keinert et al.,
"Spherical Fibonacci Mapping", SIGGRAPH Asia 2015.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray

from probegrid._jit import strict_kernel
from probegrid.raytrace import RayTracer
from probegrid.scene import Scene

__all__ = ["DIRECTIONS", "SolidIndex", "inside_solid", "solid_index", "vote_directions"]

#: Rays per point of the inside test.
DIRECTIONS: Final[int] = 64
#: Fraction of a point's rays that must vote "inside" (a strict majority).
MAJORITY: Final[float] = 0.5

#: A closed component enclosing less than ``THIN * extent * area`` (the scene's diagonal, the
#: component's area) is a doubled surface, not a solid: open.
THIN: Final[float] = 1e-6

#: Component kinds of :attr:`SolidIndex.kind`.
OPEN, SOLID, SHELL = 0, 1, 2


def vote_directions(n: int = DIRECTIONS) -> NDArray[np.float64]:
    """``(n, 3)`` unit directions, a spherical Fibonacci set rotated off the coordinate axes (so
    no ray runs along an axis-aligned wall or through a box's edges by construction)."""
    k = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    # a fixed rotation by irrational-ish angles about two axes
    a, b = 0.5 * np.sqrt(2.0) - 0.1, np.sqrt(3.0) / 5.0
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    return d @ (ry @ rx).T


@strict_kernel
def _find(parent: NDArray[np.int64], parity: NDArray[np.int8], x: int) -> tuple[int, int]:
    """Root of ``x`` and ``x``'s orientation parity relative to it; compresses the path."""
    root, p = x, 0
    while parent[root] != root:
        p ^= parity[root]
        root = parent[root]
    # second pass: point every node of the path at the root, with its parity to the root
    y, py = x, p
    while parent[y] != y:
        nxt, step = parent[y], parity[y]
        parent[y] = root
        parity[y] = py
        py ^= step
        y = nxt
    return root, p


@strict_kernel
def _union_parity(n: int, fa: NDArray[np.int64], fb: NDArray[np.int64],
                  rel: NDArray[np.int8]) -> tuple[NDArray[np.int64], NDArray[np.int8],
                                                  NDArray[np.bool_]]:
    """Components of ``n`` faces joined by edges ``(fa, fb)`` that require
    ``flip[fb] = flip[fa] xor rel``; returns each face's root, its flip relative to the root,
    and per root whether the constraints contradict (a non-orientable component)."""
    parent = np.arange(n)
    parity = np.zeros(n, np.int8)
    conflict = np.zeros(n, np.bool_)
    for e in range(len(fa)):  # loop over shared edges (topology, once per scene)
        ra, pa = _find(parent, parity, fa[e])
        rb, pb = _find(parent, parity, fb[e])
        if ra == rb:
            if (pa ^ pb) != rel[e]:
                conflict[ra] = True
        else:
            parent[rb] = ra
            parity[rb] = pa ^ pb ^ rel[e]
            conflict[ra] = conflict[ra] or conflict[rb]
    roots = np.empty(n, np.int64)
    flips = np.empty(n, np.int8)
    for f in range(n):
        roots[f], flips[f] = _find(parent, parity, f)
    bad = np.zeros(n, np.bool_)
    for f in range(n):
        bad[f] = conflict[roots[f]]
    return roots, flips, bad


@dataclass(frozen=True, eq=False)
class SolidIndex:
    """What the inside test knows of a scene's triangles (see the module docstring).

    Attributes
    ----------
    component : (T,) int64
        Component label of each triangle (-1 for a degenerate one).
    kind : (T,) int8
        OPEN, SOLID or SHELL: the kind of the triangle's component.
    sided : (T,) bool
        The triangle has a back for the inside test (closed orientable component, or a
        single-sided material).
    normals : (T, 3) float64
        Effective unit normals, pointing out of the matter: out of a solid, into the air a shell
        encloses; the authored normals of open triangles.
    """

    component: NDArray[np.int64]
    kind: NDArray[np.int8]
    sided: NDArray[np.bool_]
    normals: NDArray[np.float64]

    @property
    def solids(self) -> int:
        """Number of closed components read as solids."""
        return int(np.unique(self.component[self.kind == SOLID]).size)

    @classmethod
    def build(cls, scene: Scene, tracer: RayTracer | None = None) -> SolidIndex:
        """The index of ``scene`` (``tracer``: its ray tracer, for the light-source
        fallback; built when needed)."""
        tris = np.asarray(scene.triangles, dtype=np.int64)
        verts = np.asarray(scene.vertices, dtype=np.float64)
        t = len(tris)
        # weld vertices at identical positions
        _, weld = np.unique(verts, axis=0, return_inverse=True)
        w = weld.reshape(-1)[tris]  # (T, 3) welded ids
        ok = (w[:, 0] != w[:, 1]) & (w[:, 1] != w[:, 2]) & (w[:, 0] != w[:, 2])
        ok &= scene.triangle_areas > 0
        faces = np.flatnonzero(ok)
        # directed edges (a -> b) of every usable face
        a = w[faces][:, [0, 1, 2]].reshape(-1)
        b = w[faces][:, [1, 2, 0]].reshape(-1)
        owner = np.repeat(faces, 3)
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        key = lo * (int(w.max()) + 1) + hi
        order = np.argsort(key, kind="stable")
        key, owner, fwd = key[order], owner[order], (a < b)[order]
        first = np.r_[True, key[1:] != key[:-1]]
        starts = np.flatnonzero(first)
        counts = np.diff(np.r_[starts, len(key)])
        # a face touching an edge not shared by exactly two faces makes its component open
        boundary = np.zeros(t, bool)
        boundary[owner[np.repeat(counts != 2, counts)]] = True
        pair = starts[counts == 2]
        fa, fb = owner[pair], owner[pair + 1]
        # same direction along the shared edge: wound oppositely, one must flip
        rel = (fwd[pair] == fwd[pair + 1]).astype(np.int8)
        roots, flips, conflict = _union_parity(t, fa, fb, rel)
        roots[~ok] = -1
        # a component is closed when none of its faces touches a boundary edge
        open_root = np.zeros(t, bool)
        open_root[roots[boundary & ok]] = True
        open_root[roots[conflict & ok]] = True
        closed = ok & ~open_root[np.maximum(roots, 0)]
        # outward orientation of each closed component: sign of its volume as oriented by the
        # parities (flip 1 = wound against the component's root)
        p = verts[tris] - 0.5 * (verts.min(axis=0) + verts.max(axis=0))
        vol = np.einsum("ti,ti->t", p[:, 0], np.cross(p[:, 1], p[:, 2])) / 6.0
        s = np.where(flips == 1, -1.0, 1.0)
        comp_vol = np.bincount(np.maximum(roots, 0), weights=np.where(closed, s * vol, 0.0),
                               minlength=t)
        area = np.asarray(scene.triangle_areas, dtype=np.float64)
        # a closed surface enclosing (almost) no volume -- a plane doubled back to back -- has
        # no inside: open
        comp_area = np.bincount(np.maximum(roots, 0), weights=np.where(closed, area, 0.0),
                                minlength=t)
        extent = float(np.linalg.norm(np.ptp(verts, axis=0)))
        thin = np.abs(comp_vol) <= THIN * extent * comp_area
        closed &= ~thin[np.maximum(roots, 0)]
        # per face: does the authored winding agree with the outward one?
        outward_flip = comp_vol[np.maximum(roots, 0)] < 0  # the root's orientation points in
        agrees = (flips == 1) == outward_flip
        agree_area = np.bincount(np.maximum(roots, 0), weights=np.where(closed & agrees, area, 0),
                                 minlength=t)
        total_area = np.bincount(np.maximum(roots, 0), weights=np.where(closed, area, 0),
                                 minlength=t)
        is_solid = (agree_area > 0.5 * total_area)[np.maximum(roots, 0)]
        kind = np.where(closed, np.where(is_solid, SOLID, SHELL), OPEN).astype(np.int8)
        # effective normal: the authored one, flipped where the component's reading disagrees
        # (solid: faces pointing into the matter; shell: faces pointing out of the room)
        flip = closed & np.where(is_solid, ~agrees, agrees)
        normals = np.asarray(scene.triangle_normals, dtype=np.float64) * np.where(
            flip, -1.0, 1.0)[:, None]
        sided = closed | ~np.asarray(scene.double_sided, dtype=bool)
        sided &= ok
        index = cls(roots, kind, sided, normals)
        two_sided = np.asarray(scene.double_sided, dtype=bool)
        solid_faces = kind == SOLID
        if solid_faces.any() and two_sided[solid_faces].any():
            points, source = _light_points(scene, roots)
            if len(points):
                lit = index._solids_around(tracer or RayTracer.shared(scene), points, source)
                # a double-sided solid (every face double-sided) holding a light: a room
                all_two = np.bincount(np.maximum(roots, 0), weights=(~two_sided & closed),
                                      minlength=t) == 0
                turn = closed & np.isin(roots, lit) & all_two[np.maximum(roots, 0)]
                kind[turn] = SHELL
                normals[turn] *= -1.0
        for arr in (roots, kind, sided, normals):
            arr.setflags(write=False)
        return index

    def _solids_around(self, tracer: RayTracer, points: NDArray[np.float64],
                       source: NDArray[np.int64]) -> NDArray[np.int64]:
        """Components (labels) of the solids that hold any of ``points (L, 3)`` (more than
        half of a point's rays meet the back of that component's faces first), other than the
        point's ``source`` component (an emitter's own solid)."""
        d = vote_directions(DIRECTIONS)
        dirs = np.tile(d, (len(points), 1))
        prim = tracer.intersect(np.repeat(points, len(d), axis=0), dirs).prim_id
        tri = np.maximum(prim, 0)
        back = ((prim >= 0) & (self.kind[tri] == SOLID)
                & (np.einsum("ni,ni->n", self.normals[tri], dirs) > 0))
        comp = np.where(back, self.component[tri], -1).reshape(len(points), len(d))
        lab = np.sort(comp, axis=1)  # per point: the majority label, if any, is the median
        major = lab[:, len(d) // 2]
        votes = (comp == major[:, None]).sum(axis=1)
        return np.unique(major[(major >= 0) & (major != source)
                               & (votes > MAJORITY * len(d))])


#: Most emissive triangles whose fronts are tested as light sources (the most powerful ones).
MAX_EMITTER_POINTS: Final[int] = 256


def _light_points(scene: Scene, component: NDArray[np.int64]
                  ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Points where light starts: punctual lights (not directional) and, just in front of
    each of the :data:`MAX_EMITTER_POINTS` most powerful emissive triangles, its centroid (on
    both sides of a double-sided one); ``(L, 3)``, and the component each comes from (-2 for
    a punctual light)."""
    pts = [np.asarray(li.position, dtype=np.float64) for li in scene.lights
           if hasattr(li, "position")]
    src = [-2] * len(pts)
    emis = np.stack([m.emissive for m in scene.materials])[np.asarray(scene.material)]
    power = emis.max(axis=1) * np.asarray(scene.triangle_areas)
    power[component < 0] = 0
    hot = np.flatnonzero(power > 0)
    hot = hot[np.argsort(-power[hot], kind="stable")][:MAX_EMITTER_POINTS]
    if hot.size:
        v = np.asarray(scene.vertices, dtype=np.float64)
        extent = float(np.linalg.norm(np.ptp(v, axis=0))) or 1.0
        c = v[np.asarray(scene.triangles)[hot]].mean(axis=1)
        n = np.asarray(scene.triangle_normals)[hot]
        eps = 1e-4 * extent
        pts.extend(c + eps * n)
        two = np.asarray(scene.double_sided)[hot]
        pts.extend(c[two] - eps * n[two])
        src.extend(component[hot])
        src.extend(component[hot[two]])
    return np.array(pts, dtype=np.float64).reshape(-1, 3), np.array(src, dtype=np.int64)


_INDEX: weakref.WeakKeyDictionary[Scene, SolidIndex] = weakref.WeakKeyDictionary()


def solid_index(scene: Scene, tracer: RayTracer | None = None) -> SolidIndex:
    """The scene's :class:`SolidIndex`, built once per scene object (per process)."""
    idx = _INDEX.get(scene)
    if idx is None:
        idx = _INDEX[scene] = SolidIndex.build(scene, tracer)
    return idx


def inside_votes(tracer: RayTracer, scene: Scene, points: NDArray[np.float64], *,
                 directions: int = DIRECTIONS) -> NDArray[np.float64]:
    """Fraction of ``directions`` rays from each of ``points (P, 3)`` whose nearest hit is the
    back of a sided triangle (its effective orientation); ``(P,)`` float64."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros(0)
    idx = solid_index(scene, tracer)
    d = vote_directions(directions)
    dirs = np.tile(d, (len(pts), 1))
    hits = tracer.intersect(np.repeat(pts, len(d), axis=0), dirs)
    prim = hits.prim_id
    tri = np.maximum(prim, 0)
    back = (prim >= 0) & idx.sided[tri] & (np.einsum("ni,ni->n", idx.normals[tri], dirs) > 0)
    return back.reshape(len(pts), len(d)).mean(axis=1)


def inside_solid(tracer: RayTracer, scene: Scene, points: NDArray[np.float64], *,
                 directions: int = DIRECTIONS) -> NDArray[np.bool_]:
    """Whether each of ``points (P, 3)`` is inside a solid of ``scene`` (the module docstring:
    more than half of ``directions`` rays meet the back of a sided triangle first); ``(P,)``."""
    return inside_votes(tracer, scene, points, directions=directions) > MAJORITY
