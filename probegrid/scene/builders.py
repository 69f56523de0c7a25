"""Scenes built in code: quads, boxes and a small builder (the tests' and samples' scenes).

World frame glTF (right-handed, +Y up, metres). Triangles wind counter-clockwise seen from the
side their normal points to.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.core.lights import Light
from probegrid.scene.model import _LIGHT_TYPES, Material, Scene, SceneError

__all__ = ['SceneBuilder', 'box_mesh', 'box_scene', 'quad_mesh']


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

