"""Clear cells (probegrid.core.clearcells): the triangle-box test against an exact clipping
reference, the flags against segments cast through Embree, and the weights of the exact
visibility test unchanged when the clear cells skip their segments."""

from __future__ import annotations

import numpy as np
import pytest

from probegrid.core.clearcells import clear_cells, triangles_overlap_boxes
from probegrid.core.ddgi import probe_weights
from probegrid.core.grid import GridSpec
from probegrid.raytrace import RayTracer
from probegrid.scene import box_mesh, quad_mesh


def _clipped_area(tri: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether the triangle meets the closed box: the polygon clipped by the box's 6 half
    spaces (Sutherland-Hodgman) is not empty (an independent exact reference)."""
    poly = [np.asarray(v, dtype=np.float64) for v in tri]
    for axis in range(3):
        for bound, sign in ((lo[axis], 1.0), (hi[axis], -1.0)):
            out = []
            for k in range(len(poly)):
                a, b = poly[k], poly[(k + 1) % len(poly)]
                da, db = sign * (a[axis] - bound), sign * (b[axis] - bound)
                if da >= 0:
                    out.append(a)
                if (da >= 0) != (db >= 0):
                    out.append(a + (b - a) * (da / (da - db)))
            poly = out
            if not poly:
                return False
    return True


def test_triangle_box_overlap_equals_polygon_clipping():
    rng = np.random.default_rng(4)
    k = 3000
    tri = rng.uniform(-1.0, 1.0, (k, 3, 3)) * rng.uniform(0.3, 1.5, (k, 1, 1))
    tri += rng.uniform(-1.0, 0.5, (k, 1, 3))
    lo = rng.uniform(-1.0, 0.0, (k, 3))
    hi = lo + rng.uniform(0.1, 1.0, (k, 3))
    got = triangles_overlap_boxes(tri, lo, hi)
    want = np.array([_clipped_area(tri[i], lo[i], hi[i]) for i in range(k)])
    boxes_meet = np.all((tri.min(axis=1) <= hi) & (tri.max(axis=1) >= lo), axis=1)
    assert want.mean() > 0.15 and (boxes_meet & ~want).mean() > 0.1  # the hard cases too
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    plane_cuts = (np.abs(np.sum(normal * (tri[:, 0] - centre), axis=1))
                  <= np.sum(np.abs(normal) * half, axis=1))
    assert (boxes_meet & plane_cuts & ~want).sum() > 20  # only an edge product separates them
    # (a triangle grazing a box within rounding may go either way; none does here)
    assert np.array_equal(got, want)


def test_a_triangle_through_a_box_with_no_vertex_or_edge_inside_it_overlaps():
    # a big triangle whose plane cuts the box's middle: only the normal axis can decide
    tri = np.array([[[-10.0, -10.0, 0.1], [10.0, -10.0, 0.1], [0.0, 20.0, 0.1]]])
    assert triangles_overlap_boxes(tri, [[-1, -1, -1]], [[1, 1, 1]])[0]
    assert not triangles_overlap_boxes(tri + [0, 0, 1.2], [[-1, -1, -1]], [[1, 1, 1]])[0]


def _room() -> tuple[np.ndarray, np.ndarray]:
    """A closed room 4 x 3 x 4 with a wall across it (a doorway) and a tilted panel."""
    parts = [box_mesh((-2.0, 0.0, -2.0), (2.0, 3.0, 2.0), inward=True)[:2],
             quad_mesh((0.3, 0.0, -2.0), (0.0, 0.0, 2.5), (0.0, 3.0, 0.0))[:2],
             quad_mesh((-1.5, 1.0, 0.5), (1.0, 0.6, 0.0), (0.0, 0.3, 1.0))[:2]]
    vs, ts, base = [], [], 0
    for v, t in parts:
        vs.append(np.asarray(v, np.float64))
        ts.append(np.asarray(t) + base)
        base += len(v)
    return np.concatenate(vs), np.concatenate(ts)


@pytest.fixture(scope="module")
def room():
    v, t = _room()
    grid = GridSpec.from_counts((-1.9, 0.1, -1.9), (1.9, 2.9, 1.9), (9, 7, 9))
    return v, t, grid, RayTracer(v.astype(np.float32), t.astype(np.int32))


def test_clear_cells_see_their_corners_and_the_others_touch_a_triangle(room):
    v, t, grid, tracer = room
    clear = clear_cells(grid, v, t)
    assert 0.5 < clear.fraction < 0.95  # the wall and the panel cut some cells
    rng = np.random.default_rng(5)
    bases = np.flatnonzero(clear.clear)
    for base in bases[::3]:  # random segments inside the clear box: none is occluded
        a = clear.lo[base] + rng.random((20, 3)) * (clear.hi[base] - clear.lo[base])
        b = clear.lo[base] + rng.random((20, 3)) * (clear.hi[base] - clear.lo[base])
        assert not tracer.segments_occluded(a, b).any()
    tri = v[t]
    for flags, lo, hi in ((clear.clear, clear.lo, clear.hi),
                          (clear.block_clear, clear.block_lo, clear.block_hi)):
        n = np.array(grid.counts)
        ijk = grid.probe_ijk(np.arange(grid.n_probes))
        for base in np.flatnonzero(np.all(ijk <= n - 2, axis=1))[::3]:  # the reference
            touched = any(_clipped_area(tri[k], lo[base], hi[base]) for k in range(len(t)))
            assert flags[base] == (not touched), base


def test_weights_with_clear_cells_equal_the_full_segment_test(room):
    v, t, grid, tracer = room
    rng = np.random.default_rng(6)
    moved = grid.positions() + rng.normal(scale=0.05, size=(grid.n_probes, 3))
    valid = rng.random(grid.n_probes) > 0.05
    occluded = lambda a, b: tracer.segments_occluded(a, b, margin=1e-4)  # noqa: E731
    pts = grid.lo - 0.2 + rng.random((3000, 3)) * (grid.hi - grid.lo + 0.4)
    nrm = rng.normal(size=(3000, 3))
    skipped = 0
    for positions in (None, moved):
        clear = clear_cells(grid, v, t, positions=positions)
        for normals in (None, nrm):
            kw = dict(valid=valid, normals=normals, probe_positions=positions, normal_bias=0.3,
                      occluded=occluded, extrapolate=0.25, facing=False)
            full = probe_weights(grid, pts, **kw)
            fast = probe_weights(grid, pts, clear=clear, **kw)
            assert np.array_equal(full.weights, fast.weights)
            assert np.array_equal(full.unlit, fast.unlit)
            plain = probe_weights(grid, pts, **{**kw, "occluded": None})
            assert (plain.weights != full.weights).any(axis=1).sum() > 100  # walls do hide
            for i in range(0, 3000, 11):  # the single-point path
                one = {**kw, "normals": None if normals is None else normals[i]}
                a = probe_weights(grid, pts[i], **one)
                b = probe_weights(grid, pts[i], clear=clear, **one)
                assert np.array_equal(a.weights, b.weights) and a.unlit[0] == b.unlit[0]
            start = pts if normals is None else pts + 0.3 * grid.smallest_cell() * (
                normals / np.linalg.norm(normals, axis=1, keepdims=True))
            skipped += int(clear.contains(full.indices[:, 0], start).sum())
    assert skipped > 0.5 * 4 * 3000  # most points cast no segment


def test_clear_cells_check_their_input():
    grid = GridSpec.from_counts((0, 0, 0), (1, 1, 1), (2, 2, 2))
    v = np.zeros((3, 3))
    with pytest.raises(ValueError, match="index"):
        clear_cells(grid, v, [[0, 1, 3]])
    with pytest.raises(ValueError, match="positions"):
        clear_cells(grid, v, [[0, 1, 2]], positions=np.zeros((7, 3)))
    with pytest.raises(ValueError, match="pad"):
        clear_cells(grid, v, [[0, 1, 2]], pad=-1.0)
    empty = clear_cells(grid, v[:0], np.zeros((0, 3), int))
    assert empty.clear[0] and empty.clear.sum() == 1 and empty.fraction == 1.0
