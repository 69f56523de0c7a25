"""Scenes built in code for the accuracy benchmarks: a sunlit building and emissive spheres.

World frame glTF (right-handed, +Y up, metres). Each builder returns a probegrid
:class:`~probegrid.scene.Scene` (and an :class:`~probegrid.bake.environment.Environment` where
the scene has a sky) that Mitsuba 3 converts with the same physics
(``benchmarks/mitsuba_reference.py``).

* :func:`sunlit_building`: a closed hall (10 x 4 x 8 m inside, 20 cm thick walls and roof,
  each a solid slab) on an open ground plane, lit by a strong sun through two roof skylights
  whose openings are crossed by thin mullions (sharp stripes of sunlight on the floor and
  walls), and a blue sky. Most of the hall sees only indirect light; the skylights' patches
  see the sun. :func:`building_interior_points` gives 36 probe positions inside the hall.
* :func:`emissive_spheres`: a closed grey room lit only by four emissive icospheres of
  thousands of triangles each (no punctual light, no sky).
"""

from __future__ import annotations

import numpy as np
import trimesh
from numpy.typing import NDArray

from probegrid.bake.environment import Environment
from probegrid.core.lights import DirectionalLight
from probegrid.scene import Material, Scene
from probegrid.scene.builders import SceneBuilder

__all__ = [
    "BUILDING_INSIDE",
    "building_interior_points",
    "emissive_spheres",
    "sunlit_building",
]

#: The hall's inside: (lo, hi) corners, metres.
BUILDING_INSIDE = (np.array([-5.0, 0.0, -4.0]), np.array([5.0, 4.0, 4.0]))
_WALL = 0.2
_SKYLIGHTS = ((-3.0, -1.0), (1.0, 3.0))  # x ranges of the two openings
_SKYLIGHT_Z = (-1.5, 1.5)
_MULLION = 0.05  # width of a bar across an opening
_MULLION_PITCH = 0.5


def sunlit_building(*, sun_lux: float = 40.0, sky: float = 1.0) -> tuple[Scene, Environment]:
    """The sunlit hall and its sky (see the module docstring).

    Parameters
    ----------
    sun_lux : float
        The sun's illuminance at normal incidence (the sky's irradiance on the ground is
        ``pi * sky`` times its colour's mean, about 3 for ``sky=1``).
    sky : float
        The sky's constant radiance scale (colour (0.55, 0.7, 1.0)).
    """
    lo, hi = BUILDING_INSIDE
    w = _WALL
    b = SceneBuilder()
    ground = b.add_material(Material.diffuse((0.35, 0.32, 0.28)))
    wall = b.add_material(Material.diffuse((0.75, 0.72, 0.68)))
    floor = b.add_material(Material.diffuse((0.55, 0.40, 0.30)))
    roof = b.add_material(Material.diffuse(0.6))
    furniture = b.add_material(Material.diffuse((0.3, 0.5, 0.7)))

    # Ground outside (faces up), and the hall's floor as its own quad a millimetre above it.
    b.add_quad((-30.0, 0.0, 30.0), (60.0, 0.0, 0.0), (0.0, 0.0, -60.0), material=ground)
    b.add_quad((lo[0], 0.001, hi[2]), (hi[0] - lo[0], 0.0, 0.0), (0.0, 0.0, lo[2] - hi[2]),
               material=floor)
    # Four walls, each a closed slab.
    b.add_box((lo[0] - w, 0.0, lo[2] - w), (lo[0], hi[1], hi[2] + w), material=wall)
    b.add_box((hi[0], 0.0, lo[2] - w), (hi[0] + w, hi[1], hi[2] + w), material=wall)
    b.add_box((lo[0], 0.0, lo[2] - w), (hi[0], hi[1], lo[2]), material=wall)
    b.add_box((lo[0], 0.0, hi[2]), (hi[0], hi[1], hi[2] + w), material=wall)
    # The roof: slabs around two openings, thin mullions across each opening.
    y0, y1 = hi[1], hi[1] + w
    xs = [lo[0] - w, _SKYLIGHTS[0][0], _SKYLIGHTS[0][1], _SKYLIGHTS[1][0], _SKYLIGHTS[1][1],
          hi[0] + w]
    for k in range(len(xs) - 1):
        x0, x1 = xs[k], xs[k + 1]
        if k in (1, 3):  # an opening's x range: slabs before and after it along z
            b.add_box((x0, y0, lo[2] - w), (x1, y1, _SKYLIGHT_Z[0]), material=roof)
            b.add_box((x0, y0, _SKYLIGHT_Z[1]), (x1, y1, hi[2] + w), material=roof)
            for xm in np.arange(x0 + _MULLION_PITCH, x1 - 1e-9, _MULLION_PITCH):
                b.add_box((xm - _MULLION / 2, y0, _SKYLIGHT_Z[0]),
                          (xm + _MULLION / 2, y1, _SKYLIGHT_Z[1]), material=roof)
        else:
            b.add_box((x0, y0, lo[2] - w), (x1, y1, hi[2] + w), material=roof)
    # A table-sized block and a cabinet against a wall.
    b.add_box((-1.0, 0.001, 1.8), (0.6, 0.8, 2.8), material=furniture)
    b.add_box((3.6, 0.001, -3.6), (4.6, 2.0, -2.4), material=furniture)
    b.add_light(DirectionalLight((0.35, -0.85, 0.2), (1.0, 0.95, 0.85), sun_lux))
    env = Environment(color=np.array([0.55, 0.7, 1.0]), intensity=sky)
    return b.build(name="sunlit_building"), env


def building_interior_points() -> NDArray[np.float64]:
    """36 probe positions inside the hall (a 4 x 3 x 3 lattice, clear of walls and furniture).

    Returns
    -------
    (36, 3) float64, x fastest, then y, then z.
    """
    xs = np.array([-3.75, -1.25, 1.25, 3.75])
    ys = np.array([1.0, 2.0, 3.0])
    zs = np.array([-2.4, 0.0, 2.4]) * 1.0
    z, y, x = np.meshgrid(zs, ys, xs, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)


def emissive_spheres(*, subdivisions: int = 4, radiance: float = 8.0) -> Scene:
    """A 6 x 3 x 6 m grey room lit only by four emissive spheres (radius 0.25 m).

    ``subdivisions=4`` gives 5,120 triangles per sphere (20,480 emitting triangles).
    """
    b = SceneBuilder()
    room = b.add_material(Material.diffuse(0.6))
    colours = ((1.0, 0.85, 0.7), (0.7, 0.85, 1.0), (1.0, 1.0, 1.0), (0.9, 1.0, 0.8))
    b.add_box((-3.0, 0.0, -3.0), (3.0, 3.0, 3.0), material=room, inward=True)
    m = trimesh.creation.icosphere(subdivisions=subdivisions)  # (unit radius, outward)
    v, f = np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)
    centres = ((-1.6, 2.3, -1.6), (1.6, 2.3, -1.6), (-1.6, 0.6, 1.6), (1.6, 1.5, 1.6))
    for centre, colour in zip(centres, colours):
        mat = b.add_material(Material.diffuse(0.0, emission=np.asarray(colour) * radiance))
        b.add_triangles(v * 0.25 + np.asarray(centre), f, material=mat)
    return b.build(name="emissive_spheres")
