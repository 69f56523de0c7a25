"""Inside is inside: probes inside closed solids are invalid whatever the
material's double-sidedness, by the authored winding (probegrid.bake.inside), with fallbacks for
inconsistently wound and open meshes; relocation moves probes out; invalid probes give no light."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from probegrid.bake.driver import BakeSettings, bake
from probegrid.bake.inside import OPEN, SHELL, SOLID, SolidIndex, inside_solid, inside_votes
from probegrid.core.grid import GridSpec
from probegrid.core.lights import PointLight
from probegrid.raytrace import RayTracer
from probegrid.scene import Material, Scene, SceneBuilder
from probegrid.scene.builders import box_mesh

FAST = {"face_size": 8, "diffuse_size": 4, "moments_size": 4, "batch_size": 16}
TWO_SIDED = dataclasses.replace(Material.diffuse(0.5), double_sided=True)


def _room_with_cube(cube_lo=(-1, -1, -1), cube_hi=(1, 1, 1), *, cube=TWO_SIDED):
    b = SceneBuilder()
    room = b.add_material(Material.diffuse(0.5))
    solid = b.add_material(cube)
    b.add_box((-3, -3, -3), (3, 3, 3), material=room, inward=True)
    b.add_box(cube_lo, cube_hi, material=solid)
    b.add_light(PointLight((2.0, 2.5, 0.0), (1.0, 1.0, 1.0), 20.0))
    return b.build()


def _in_box(p, lo, hi):
    return np.all((p > np.asarray(lo)) & (p < np.asarray(hi)), axis=1)


@pytest.mark.slow
def test_a_double_sided_cube_larger_than_a_cell_invalidates_every_probe_inside_and_none_outside(
        tmp_path):
    """Cube 2 units wide, cells 1 unit: the 8 probes inside sit half a cell from its walls
    (the old enclosure test, every ray within half a cell, never fired; the back-face test sees
    no back on a double-sided material). Relocation may move a probe at most 0.45 of a cell, so
    none can leave: all 8 stay invalid; all 208 outside stay valid."""
    scene = _room_with_cube()
    grid = GridSpec.from_counts((-2.5,) * 3, (2.5,) * 3, (6, 6, 6))
    s = bake(scene, grid, tmp_path / "c.probes",
             settings=BakeSettings(bounces=0, **FAST)).store
    inside = _in_box(grid.positions(), (-1,) * 3, (1,) * 3)
    assert inside.sum() == 8
    valid = np.asarray(s["valid"])
    assert not valid[inside].any()
    assert valid[~inside].all()
    assert s.manifest.quality["invalid_probes"] == 8


def test_relocation_moves_a_probe_out_of_a_double_sided_solid(tmp_path):
    """A probe 0.2 inside a double-sided wall 1.6 thick, cell 2 (may move 0.9): moved out, to a
    point outside the solid; with --no-relocate it stays invalid."""
    scene = _room_with_cube((-0.8, -2.9, -2.9), (0.8, 2.9, 2.9))
    grid = GridSpec.from_counts((0.6, 0, 0), (2.6, 0, 0), (2, 1, 1))
    moved = bake(scene, grid, tmp_path / "m.probes",
                 settings=BakeSettings(bounces=0, **FAST)).store
    p = np.asarray(moved["positions"])
    assert moved["valid"].tolist() == [True, True]
    assert p[0, 0] > 0.8 and np.abs(p[0] - (0.6, 0, 0)).max() <= 0.9 + 1e-12
    assert moved.manifest.quality["relocated_probes"] == 1
    kept = bake(scene, grid, tmp_path / "k.probes",
                settings=BakeSettings(bounces=0, relocate=False, **FAST)).store
    assert kept["valid"].tolist() == [False, True]


def _scene_of(vertices, triangles, double_sided=True):
    mat = dataclasses.replace(Material.diffuse(0.5), double_sided=double_sided)
    return Scene.from_arrays(vertices, triangles, materials=[mat])


def test_topology_reads_solids_shells_and_open_meshes():
    v, t, _ = box_mesh((0, 0, 0), (1, 1, 1))
    solid = SolidIndex.build(_scene_of(v, t))
    assert (solid.kind == SOLID).all() and solid.sided.all() and solid.solids == 1
    v2, t2, _ = box_mesh((0, 0, 0), (1, 1, 1), inward=True)
    assert (SolidIndex.build(_scene_of(v2, t2)).kind == SHELL).all()
    # a box without its top: open; double-sided, so no back for the test, single-sided keeps
    # its authored back (the classifier's back-face test)
    open_box = SolidIndex.build(_scene_of(v, t[[0, 1, 2, 3, 4, 5, 8, 9, 10, 11]]))
    assert (open_box.kind == OPEN).all() and not open_box.sided.any()
    single = SolidIndex.build(_scene_of(v, t[:10], double_sided=False))
    assert single.sided.all()
    # a quad doubled back to back is closed and orientable but encloses nothing: open
    q = t[:2]
    assert (SolidIndex.build(_scene_of(v, np.vstack([q, q[:, ::-1]]))).kind == OPEN).all()
    # effective normals of a solid point out of it: the +X face's normal is +X
    centres = v[t].mean(axis=1)
    px = np.flatnonzero(np.isclose(centres[:, 0], 1.0))
    np.testing.assert_allclose(solid.normals[px], [[1, 0, 0]] * len(px))


def test_inconsistent_winding_falls_back_to_the_majority():
    """A closed cube with one face (2 triangles) flipped is still a solid with outward effective
    normals; a room with one flipped wall is still a shell: points inside the cube are inside
    (every ray), points in the room are not."""
    v, t, _ = box_mesh((-1, -1, -1), (1, 1, 1))
    bad = t.copy()
    bad[2:4] = bad[2:4, ::-1]  # the +X face (quads -X, +X, ...) wound inward
    scene = _scene_of(v, bad)
    idx = SolidIndex.build(scene)
    assert (idx.kind == SOLID).all()
    outward = SolidIndex.build(_scene_of(v, t)).normals
    np.testing.assert_allclose(idx.normals, outward)
    tracer = RayTracer.from_scene(scene)
    pts = np.array([[0.0, 0, 0], [0.9, 0.9, -0.9], [0.95, 0, 0], [1.5, 0, 0], [0, 3, 0]])
    assert inside_solid(tracer, scene, pts).tolist() == [True, True, True, False, False]
    np.testing.assert_allclose(inside_votes(tracer, scene, pts[:3]), 1.0)

    rv, rt, _ = box_mesh((-3, -3, -3), (3, 3, 3), inward=True)
    rt = rt.copy()
    rt[0:2] = rt[0:2, ::-1]
    room = _scene_of(rv, rt)
    assert (SolidIndex.build(room).kind == SHELL).all()
    inner = np.array([[0.0, 0, 0], [2.9, 0, 0], [-2.9, 2.9, 0]])
    assert not inside_solid(RayTracer.from_scene(room), room, inner).any()


def test_the_winding_not_the_sidedness_decides():
    """The same closed cube, single- or double-sided: the same verdict at every point of a
    lattice through it (inside exactly when strictly inside the cube)."""
    g = np.linspace(-1.9, 1.9, 9)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    expected = _in_box(pts, (-1,) * 3, (1,) * 3)
    for double_sided in (False, True):
        scene = _room_with_cube(cube=dataclasses.replace(Material.diffuse(0.5),
                                                         double_sided=double_sided))
        got = inside_solid(RayTracer.from_scene(scene), scene, pts)
        assert np.array_equal(got, expected), double_sided


def test_invalid_probes_give_no_light_to_a_bounce():
    """The bounce lookup (the trace-once weights of every hit, probegrid.bake.records) gives an
    invalid probe zero weight: whatever light it holds, no surface point reads any of it."""
    from probegrid.bake.records import GridData, hit_weights

    grid = GridSpec.from_counts((0, 0, 0), (1, 1, 1), (2, 2, 2))
    rng = np.random.default_rng(3)
    valid = np.ones(8, bool)
    valid[[1, 6]] = False
    pts = rng.uniform(0.1, 0.9, (50, 3))
    nrm = rng.normal(size=(50, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    data = GridData(grid, valid, grid.positions(), np.zeros((0, 2), np.float32), 0, None)
    rec = {"kind": np.ones(50, np.uint8), "position": pts, "normal": nrm.astype(np.float32)}
    idx, w = hit_weights(rec, data)
    assert np.all(w[np.isin(idx, [1, 6])] == 0)  # the invalid probes carry nothing
    assert np.all(w.sum(axis=1) > 0.99)  # and the valid ones carry it all
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-6)


@pytest.mark.parametrize("n", [16, 64])
def test_votes_are_fractions_of_the_directions(n):
    scene = _room_with_cube()
    tracer = RayTracer.from_scene(scene)
    v = inside_votes(tracer, scene, np.array([[0.0, 0, 0], [2.0, 2, 2]]), directions=n)
    assert v[0] == 1.0 and v[1] == 0.0


def test_a_double_sided_room_wound_inside_out_around_its_light_stays_a_room():
    """A room modelled from a cube without flipping its normals, double-sided (it renders
    either way): by its winding a solid, but it holds the scene's light, and light does not
    shine from inside matter: a room. A double-sided solid cube beside the light stays solid,
    and so does a glowing (emissive, double-sided) cube: its own light does not count."""
    b = SceneBuilder()
    two = b.add_material(TWO_SIDED)
    glow = b.add_material(dataclasses.replace(Material.diffuse(0.5, emission=3.0),
                                              double_sided=True))
    b.add_box((-3, -3, -3), (3, 3, 3), material=two)  # outward normals
    b.add_box((-2, -2, -2), (-1, -1, -1), material=two)
    b.add_box((1, 1, 1), (2, 2, 2), material=glow)
    b.add_light(PointLight((0.0, 2.0, 0.0), (1.0, 1.0, 1.0), 10.0))
    scene = b.build()
    idx = SolidIndex.build(scene)
    assert idx.kind.tolist() == [SHELL] * 12 + [SOLID] * 24
    pts = np.array([[0.0, 0, 0], [2.5, -2.5, 2.5], [-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]])
    assert inside_solid(RayTracer.from_scene(scene), scene, pts).tolist() == [
        False, False, True, True]
    # without the light the big cube is what its winding says: a solid
    plain = _scene_of(*box_mesh((-3, -3, -3), (3, 3, 3))[:2])
    assert (SolidIndex.build(plain).kind == SOLID).all()
