"""Leak-free probe queries: a wall between a lit and a dark room, a room's
corner, the exact point-to-probe segment test and the fallback of stores without triangles
(probegrid.query, probegrid.core.ddgi, probegrid.raytrace, probegrid.bake.extras)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from probegrid.bake.driver import BakeSettings, bake
from probegrid.core.grid import GridSpec
from probegrid.core.lights import PointLight
from probegrid.query import ProbeField
from probegrid.raytrace import RayTracer
from probegrid.scene import Material, SceneBuilder
from probegrid.store import open_store

FAST = {"face_size": 8, "diffuse_size": 4, "moments_size": 4, "batch_size": 64, "bounces": 1}

#: Room A (lit) x in [0, 1.9], room B (dark) x in [2.1, 4], both 2 high and deep; a 0.2 thick
#: wall between them. Double-sided walls (Blender's usual export): the probes outside the rooms
#: are valid.
WALL_A, WALL_B = 1.9, 2.1
#: Probes at x = -0.25, 0.25, ..., 4.25 (none in the wall), y and z = -0.25 .. 2.25: a layer
#: outside the rooms all round.
GRID = GridSpec.from_counts((-0.25, -0.25, -0.25), (4.25, 2.25, 2.25), (10, 6, 6))


def two_rooms():
    b = SceneBuilder()
    wall = b.add_material(Material.diffuse(0.5, double_sided=True))
    b.add_box((0.0, 0.0, 0.0), (WALL_A, 2.0, 2.0), material=wall, inward=True)
    b.add_box((WALL_B, 0.0, 0.0), (4.0, 2.0, 2.0), material=wall, inward=True)
    b.add_light(PointLight((1.0, 1.2, 1.0), (1.0, 1.0, 1.0), 5.0))
    return b.build(name="two rooms")


@pytest.fixture(scope="module")
def stores(tmp_path_factory) -> dict[str, Path]:
    """The two rooms baked once (with triangles) and the same store without its extras (the
    format-1 layout: what every store was before), to compare the old behaviour."""
    root = tmp_path_factory.mktemp("rooms")
    report = bake(two_rooms(), GRID, root / "rooms.probes", settings=BakeSettings(**FAST))
    new = report.store.path
    old = root / "old.probes"
    shutil.copytree(new, old)
    doc = (old / "manifest.json").read_text()
    import json

    m = json.loads(doc)
    for name in m.pop("extras"):
        (old / f"{name}.npy").unlink()
    m["format_version"] = 1
    (old / "manifest.json").write_text(json.dumps(m))
    return {"new": new, "old": old}


@pytest.fixture(scope="module")
def field(stores) -> ProbeField:
    return ProbeField(open_store(stores["new"]))


@pytest.fixture(scope="module")
def old_field(stores) -> ProbeField:
    return ProbeField(open_store(stores["old"]))


def _lit_probes(field: ProbeField) -> np.ndarray:
    """The probes inside room A."""
    pos = np.asarray(field.store["positions"])
    return np.all((pos > 0) & (pos < [WALL_A, 2.0, 2.0]), axis=1)


def _room_b_probes(field: ProbeField) -> np.ndarray:
    pos = np.asarray(field.store["positions"])
    return np.all((pos > [WALL_B, 0, 0]) & (pos < [4.0, 2.0, 2.0]), axis=1)


def _weight_on(w, mask) -> np.ndarray:
    """Per point, the total weight on the probes selected by ``mask (P,)``."""
    return np.sum(w.weights * mask[w.indices], axis=1)


def test_store_keeps_the_scene_and_the_baked_rooms_are_as_built(field, stores):
    s = field.store
    assert s.manifest.format_version == 2
    # (and what a probe traced at a point reads: the grid the final pass read, bordered moments,
    # the surface light cache, and the SH field /sh interpolates; a black environment is stated
    # in the manifest, not stored)
    assert set(s.extras) == {"sh_deringed", "sh_window", "scene_vertices", "scene_triangles",
                             "grid_irradiance", "moments_bordered", "surface_lattice",
                             "surface_light", "sh_field", "sh_field_raw", "sh_field_valid",
                             "sh_field_lattice"}
    scene = two_rooms()
    np.testing.assert_array_equal(s["scene_vertices"], scene.vertices.astype(np.float32))
    np.testing.assert_array_equal(s["scene_triangles"], scene.triangles)
    assert np.all(s["valid"])  # double-sided walls: the probes outside the rooms are valid
    lit, dark = _lit_probes(field), _room_b_probes(field)
    assert lit.sum() == dark.sum() == 4 * 4 * 4
    sh = np.asarray(s["sh"], np.float64)
    assert np.all(sh[lit][:, 0] > 0)
    assert field.visibility_test(normal=False) == "segments"
    assert ProbeField(open_store(stores["old"])).visibility_test(normal=False) == "none"


def test_wall_gives_the_dark_side_no_weight_from_the_lit_probes(field, old_field):
    lit = _lit_probes(field)
    rng = np.random.default_rng(3)
    # points in room B within half a cell of the wall (between the probe layers x = 1.75 and
    # 2.25, so the lit layer has trilinear weight 0.1 .. 0.3), and on the wall's face in B
    pts = np.column_stack([rng.uniform(WALL_B + 1e-3, 2.2, 64), rng.uniform(0.05, 1.95, 64),
                           rng.uniform(0.05, 1.95, 64)])
    normals = np.tile([1.0, 0.0, 0.0], (64, 1))
    for nrm in (None, normals):
        w = field.weights(pts, normals=nrm)
        assert w.visibility == "segments"
        assert not w.unlit.any()
        np.testing.assert_array_equal(_weight_on(w, lit), 0.0)
        np.testing.assert_allclose(_weight_on(w, _room_b_probes(field)), 1.0, rtol=0, atol=1e-15)
        np.testing.assert_allclose(w.weights.sum(axis=1), 1.0, atol=1e-14)
        old = old_field.weights(pts, normals=nrm)
        assert old.visibility == ("none" if nrm is None else "moments")
        # what the old weights leaked: up to 30 % without a normal, a little with one
        assert _weight_on(old, lit).max() > (0.05 if nrm is None else 0.0)
    # in room A, the lit probes still light points near the same wall; room B's do not
    pa = pts - [2 * (WALL_B - WALL_A) + 0.02, 0, 0]
    w = field.weights(pa, normals=-normals)
    np.testing.assert_allclose(_weight_on(w, lit), 1.0, rtol=0, atol=1e-15)
    assert np.all(field.sh(w, kind="raw")[:, 0] > 0)


def test_corner_query_takes_under_one_percent_from_outside_the_room(field, old_field):
    lit = _lit_probes(field)  # room A's probes; room B's are outside it
    # room A's floor corners at the wall, and the wall's bottom edge
    # room A's corners (at the wall and at the outside walls, floor and ceiling) and the
    # wall's bottom edge, each with
    # the normals of the surfaces that meet there (pointing into the room)
    e = 0.01
    cases = [
        ((WALL_A - e, e, e), [(0, 1, 0), (-1, 0, 0), (0, 0, 1)]),
        ((WALL_A - e, e, 2 - e), [(0, 1, 0), (-1, 0, 0), (0, 0, -1)]),
        ((WALL_A - e, 2 - e, e), [(0, -1, 0), (-1, 0, 0), (0, 0, 1)]),
        ((e, e, e), [(0, 1, 0), (1, 0, 0), (0, 0, 1)]),
        ((e, 2 - e, 2 - e), [(0, -1, 0), (1, 0, 0), (0, 0, -1)]),
        ((WALL_A - 2 * e, 2 * e, 1.0), [(0, 1, 0), (-1, 0, 0)]),
    ]
    pts = np.array([p for p, normals in cases for _ in normals], dtype=np.float64)
    nrm = np.array([n for _, normals in cases for n in normals], dtype=np.float64)
    w = field.weights(pts, normals=nrm)
    outside = _weight_on(w, ~lit)
    assert outside.max() < 0.01, outside
    assert not w.unlit.any()
    old = old_field.weights(pts, normals=nrm)
    assert _weight_on(old, ~lit).max() > 0.5  # the old weights fail this


def test_segment_test_equals_a_brute_force_ray_cast(field):
    """The weights' visibility is exactly Embree's closest hit before the probe, checked
    against RayTracer.intersect on random points of both rooms and the wall."""
    rng = np.random.default_rng(7)
    pts = rng.uniform([0.02, 0.02, 0.02], [3.98, 1.98, 1.98], (300, 3))
    w0 = field.weights(pts)
    tracer = RayTracer(two_rooms().vertices, two_rooms().triangles)
    pos = np.asarray(field.store["positions"])
    valid = np.asarray(field.store["valid"])
    idx, _, _ = GRID.corners(pts)
    ends = pos[idx]  # (n, 8, 3)
    d = ends - pts[:, None]
    dist = np.linalg.norm(d, axis=-1)
    hits = tracer.intersect(np.repeat(pts, 8, axis=0), (d / dist[..., None]).reshape(-1, 3))
    seen = (hits.t.reshape(-1, 8) >= dist - 1e-6) & valid[idx]
    np.testing.assert_array_equal(w0.weights > 0, seen & (w0.weights > 0))
    # every corner that carries trilinear weight and is seen keeps it
    tri = GRID.corners(pts)[1]
    np.testing.assert_array_equal(w0.weights > 0, seen & (tri > 0))


def test_segments_occluded_matches_intersect_and_respects_the_margin():
    scene = two_rooms()
    tracer = RayTracer(scene.vertices, scene.triangles)
    a = np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [3.0, 1.0, 1.0], [1.0, 1.0, 1.0],
                  [1.0, 1.0, 1.0]])
    b = np.array([[3.0, 1.0, 1.0], [1.5, 1.5, 1.5], [3.5, 0.5, 1.0], [WALL_A, 1.0, 1.0],
                  [1.0, 1.0, 1.0]])
    got = tracer.segments_occluded(a, b, margin=1e-6)
    assert got.tolist() == [True, False, False, False, False]
    # a segment ending exactly on the wall touches it (no margin) or not (margin)
    assert tracer.segments_occluded(a[3:4], b[3:4]).tolist() == [True]
    with pytest.raises(ValueError, match="shape"):
        tracer.segments_occluded(a, b[:2])
    with pytest.raises(ValueError, match="finite"):
        tracer.segments_occluded(a[:1], [[np.nan, 0, 0]])


def test_the_response_says_which_test_and_the_old_store_keeps_its_weights(field, old_field):
    p = np.array([[1.0, 1.0, 1.0], [2.6, 0.4, 1.2]])
    n = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    assert field.weights(p).visibility == "segments"
    assert field.weights(p[:1]).visibility == "segments"  # the one-point path too
    assert old_field.weights(p).visibility == "none"
    assert old_field.weights(p, normals=n).visibility == "moments"
    # far from walls nothing is hidden: the same weights as the old store's, to rounding
    np.testing.assert_allclose(field.weights(p).weights, old_field.weights(p).weights,
                               rtol=0, atol=1e-15)


def test_baked_store_keeps_raw_and_deringed_sh(field, old_field):
    """Every probe's stored deringed SH has irradiance >= 0 over a dense sphere sampling (as
    float32, as stored), equals the raw SH where that already held, and records its window;
    a store without them (format 1) is deringed the same way when queried."""
    from probegrid.core import sh as shm

    s = field.store
    raw = np.asarray(s["sh"], np.float64)
    der = np.asarray(s["sh_deringed"], np.float64)
    window = np.asarray(s["sh_window"], np.float64)
    k = np.arange(20000) + 0.5
    y = 1 - 2 * k / k.size
    phi = k * np.pi * (3 - np.sqrt(5))
    dirs = np.column_stack([np.sqrt(1 - y * y) * np.cos(phi), y, np.sqrt(1 - y * y) * np.sin(phi)])
    basis = shm.sh_basis(dirs) * shm.A_HAT

    def dense_min(c):
        return (basis @ np.moveaxis(c, 1, 0).reshape(9, -1)).min(axis=0).reshape(len(c), 3)

    raw_min, der_min = dense_min(raw), dense_min(der)
    ok = np.all(raw_min >= 0, axis=1)
    # (no probe of these rooms rings: the ones above the roof that did saw the lit inside
    # through the boxes' edges, where rays through their texel centres slipped between two
    # triangles; rays anywhere in their texels do not. tests/test_dering.py rings.)
    assert np.all(der_min >= 0)
    np.testing.assert_array_equal(der[ok], raw[ok])
    np.testing.assert_array_equal(window[ok], 1.0)
    np.testing.assert_allclose(der, raw * window[:, shm.BAND_OF][:, :, None], rtol=1e-6,
                               atol=1e-7 * np.abs(raw).max())
    # queries: deringed by default, raw on request; the old store derings on first use
    w = field.weights(np.array([[1.0, 1.0, 1.0]]))
    assert field.sh_source() == "store" and old_field.sh_source() == "computed"
    np.testing.assert_allclose(old_field.sh(w), field.sh(w), rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(field.sh(w, kind="raw"), old_field.sh(w, kind="raw"))
    with pytest.raises(ValueError, match="sh kind"):
        field.sh(w, kind="ringing")


def test_segment_rays_kernel_restates_its_array_expression():
    from probegrid.raytrace.kernels import segment_rays

    rng = np.random.default_rng(11)
    a = rng.uniform(-5, 5, (200, 3))
    b = rng.uniform(-5, 5, (200, 3))
    b[:3] = a[:3]  # zero-length segments
    centre = np.array([0.3, -1.0, 2.0])
    margin = 1e-3
    for starts in (a, a[:1]):
        org, dirs, far, ok = segment_rays(starts, b, margin, centre)
        d = b - starts
        lo = margin / np.maximum(np.linalg.norm(d, axis=1), 1e-30)
        assert ok
        np.testing.assert_allclose(org, ((starts - centre) + lo[:, None] * d).astype(np.float32),
                                   rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(dirs, d.astype(np.float32))
        np.testing.assert_allclose(far, (1 - 2 * lo).astype(np.float32), rtol=1e-6)
    assert np.all(segment_rays(a, b, margin, centre)[2][:3] < 0)  # never occluded
    assert not segment_rays(np.array([[np.inf, 0, 0]]), b[:1], margin, centre)[3]


def test_store_extras_are_written_atomically_and_checked(tmp_path):
    from probe_stores import GRID as LGRID
    from probe_stores import linear_arrays

    from probegrid.core.conventions import conventions
    from probegrid.store import ArraySpec, StoreError, StoreWriter

    arrays = linear_arrays(LGRID)
    specs = {k: ArraySpec(shape=a.shape[1:], dtype=a.dtype.str) for k, a in arrays.items()}
    w = StoreWriter.create(tmp_path / "x.probes", arrays=specs, grid=LGRID,
                           conventions=conventions(), scene_hash="x")
    with pytest.raises(StoreError, match="not written"):
        w.add_extra("scene_vertices", np.zeros((3, 3), np.float32))
    w.write(np.arange(LGRID.n_probes), arrays)
    with pytest.raises(ValueError, match="name of one of the store's arrays"):
        w.add_extra("sh", np.zeros((3, 3)))
    w.add_extra("scene_vertices", np.ones((3, 3), np.float32), description="first")
    w.add_extra("scene_vertices", np.full((4, 3), 2.0, np.float32))  # replaced
    assert not list(w.partial_path.glob(".*.tmp"))
    store = w.finish(quality={})
    assert store.manifest.format_version == 2 and store.extras == ["scene_vertices"]
    np.testing.assert_array_equal(store["scene_vertices"], np.full((4, 3), 2.0))
    assert "scene_vertices" not in store.names  # the per-probe arrays stay apart
    (store.path / "scene_vertices.npy").write_bytes(b"broken")
    with pytest.raises(StoreError, match="scene_vertices.npy is not a valid .npy"):
        open_store(store.path)
