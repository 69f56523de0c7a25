"""Where a bake's probes go: the default grid fitted to the scene's free space
(probegrid.bake.placement)."""

from __future__ import annotations

import numpy as np

from probegrid.bake.inside import inside_solid
from probegrid.bake.placement import grid_for
from probegrid.core.lights import PointLight
from probegrid.raytrace import RayTracer
from probegrid.scene import Material, SceneBuilder


def _room_on_a_slab():
    """An 8 x 3 x 8 room standing on a floor slab 1 unit thick that overhangs it."""
    b = SceneBuilder()
    m = b.add_material(Material.diffuse(0.5))
    b.add_box((-4, 0, -4), (4, 3, 4), material=m, inward=True)
    b.add_box((-4.5, -1.0, -4.5), (4.5, 0, 4.5), material=m)  # the slab, a closed solid
    b.add_light(PointLight((0.0, 2.5, 0.0), (1.0, 1.0, 1.0), 10.0))
    return b.build()


def test_the_default_grid_puts_no_probe_in_a_floor_slab():
    """With no --grid/--spacing the box is fitted to the free space: no probe inside the slab
    (the old default, 8 along the longest side at cell centres of the scene's bounds, put its
    lowest layer half a cell = 0.56 deep in it)."""
    scene = _room_on_a_slab()
    said = []
    g = grid_for(scene, say=said.append)
    p = g.positions()
    assert p[:, 1].min() > 0.0  # above the slab's top
    assert not inside_solid(RayTracer.from_scene(scene), scene, p).any()
    assert len(said) == 1 and f"default grid {g.label}" in said[0] and "free space" in said[0]
    # spacing: the longest side (9) / 8; two layers at least along every longer side
    step = 9 / 8
    extent = np.array([9.0, 3.0, 9.0])
    assert all(c >= 2 for c, e in zip(g.counts, extent, strict=True) if e > step)


def test_the_default_grid_has_two_layers_along_every_side_longer_than_the_spacing():
    """A flat room 8 x 1.2 x 0.5: spacing 1; the 1.2 side gets 2 layers (the old default,
    rint(8 e / longest) = 1, gave one), the 0.5 side one."""
    b = SceneBuilder()
    m = b.add_material(Material.diffuse(0.5))
    b.add_box((0, 0, 0), (8, 1.2, 0.5), material=m, inward=True)
    g = grid_for(b.build())
    assert g.counts == (8, 2, 1)
    np.testing.assert_allclose(np.unique(g.positions()[:, 1]), [0.3, 0.9])
    np.testing.assert_allclose(np.unique(g.positions()[:, 2]), [0.25])
