"""Tests of probegrid.raytrace: analytic hits on known quads, segments (tmin/tmax), occlusion,
back faces, broadcasting, chunking, pickling, and agreement with Scene.surface_at."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

from probegrid.raytrace import RayTracer
from probegrid.scene import box_scene, load_gltf, quad_mesh


def _quad_tracer(offset: float = 0.0) -> RayTracer:
    """The quad z = 0, x in [0, 2], y in [0, 1] (shifted by ``offset`` on every axis), facing +Z."""
    v, t, _ = quad_mesh((offset, offset, offset), (2.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    return RayTracer(v, t)


@pytest.mark.parametrize("offset", [0.0, 1.0e4])
def test_hit_at_analytic_t_and_barycentrics(offset: float) -> None:
    rt = _quad_tracer(offset)
    rng = np.random.default_rng(1)
    s = rng.uniform(0.01, 0.99, 200)  # along edge_u (x / 2)
    w = rng.uniform(0.01, 0.99, 200)  # along edge_v (y)
    target = np.stack([2 * s, w, np.zeros_like(s)], axis=1) + offset
    origins = target + np.array([0.3, -0.2, 5.0])
    directions = 2.0 * (target - origins)  # not unit: t is in units of |direction|
    hits = rt.intersect(origins, directions)
    np.testing.assert_allclose(hits.t, 0.5, rtol=2e-6)
    # triangle 0 = (c, c + eu, c + eu + ev), triangle 1 = (c, c + eu + ev, c + ev):
    # p = c + s eu + w ev gives (u, v) = (s - w, w) in 0 and (s, w - s) in 1
    first = s >= w
    np.testing.assert_array_equal(hits.prim_id, np.where(first, 0, 1))
    np.testing.assert_allclose(hits.u, np.where(first, s - w, s), atol=2e-6)
    np.testing.assert_allclose(hits.v, np.where(first, w, w - s), atol=2e-6)
    assert hits.t.dtype == np.float64 and hits.prim_id.dtype == np.int64


def test_misses_and_segments() -> None:
    rt = _quad_tracer()
    o = np.array([[1.0, 0.5, 1.0], [5.0, 5.0, 1.0], [1.0, 0.5, 1.0], [1.0, 0.5, 1.0]])
    d = np.array([[0, 0, -1.0], [0, 0, -1.0], [0, 0, 1.0], [0, 0, -1.0]])
    hits = rt.intersect(o, d, tmax=np.array([np.inf, np.inf, np.inf, 0.999]))
    np.testing.assert_array_equal(hits.prim_id, [hits.prim_id[0], -1, -1, -1])
    assert hits.prim_id[0] in (0, 1)
    np.testing.assert_allclose(hits.t, [1.0, np.inf, np.inf, np.inf])
    np.testing.assert_array_equal(hits.u[1:], 0.0)
    np.testing.assert_array_equal(hits.v[1:], 0.0)
    # tmin past the surface: miss; tmin before it: hit, with t measured from the true origin
    assert rt.intersect(o[0], d[0], tmin=1.001).prim_id == -1
    h = rt.intersect(o[0], d[0], tmin=0.5)
    assert h.prim_id >= 0 and h.t == pytest.approx(1.0, abs=1e-6)
    # per-ray tmin and tmax, one shared origin
    h = rt.intersect(o[0], d[[0, 0, 0]], tmin=[0.0, 0.9, 1.1], tmax=[2.0, 1.05, 2.0])
    np.testing.assert_array_equal(h.prim_id >= 0, [True, True, False])
    np.testing.assert_allclose(h.t[:2], 1.0, atol=1e-6)
    np.testing.assert_array_equal(
        rt.occluded(o[0], d[[0, 0, 0]], [0.95, 1.05, 2.0], tmin=[0.0, 0.0, 1.1]),
        [False, True, False],
    )


def test_two_walls_tmin_selects_second() -> None:
    v1, t1, _ = quad_mesh((-1, -1, 0), (2, 0, 0), (0, 2, 0))
    v2, t2, _ = quad_mesh((-1, -1, -3), (2, 0, 0), (0, 2, 0))
    rt = RayTracer(np.concatenate([v1, v2]), np.concatenate([t1, t2 + 4]))
    h = rt.intersect([0.1, 0.2, 1.0], [0, 0, -1], tmin=1.0 + 1e-4)
    assert h.prim_id in (2, 3) and h.t == pytest.approx(4.0, abs=1e-5)


def test_occlusion_before_and_after_wall() -> None:
    rt = _quad_tracer()
    o = np.array([1.0, 0.5, 2.0])
    d = np.array([0.0, 0.0, -1.0])
    tmax = np.array([1.0, 1.9, 1.999, 2.001, 2.5, np.inf])
    np.testing.assert_array_equal(rt.occluded(o, d, tmax), [False, False, False, True, True, True])
    # a segment starting past the wall is not occluded
    assert not rt.occluded(o, d, 10.0, tmin=2.01)
    # a ray beside the quad is never occluded
    assert not rt.occluded([3.0, 0.5, 2.0], d, np.inf)


def test_backface() -> None:
    rt = _quad_tracer()  # faces +Z
    o = np.array([[1.0, 0.5, 1.0], [1.0, 0.5, -1.0], [9.0, 9.0, 1.0]])
    d = np.array([[0, 0, -1.0], [0, 0, 1.0], [0, 0, -1.0]])
    h = rt.intersect(o, d)
    np.testing.assert_array_equal(h.prim_id >= 0, [True, True, False])
    np.testing.assert_array_equal(rt.backface(h.prim_id, d), [False, True, False])
    with pytest.raises(ValueError):
        rt.backface(np.array([5]), d[:1])


def test_inward_box_has_no_backfaces_inside_and_only_backfaces_outside() -> None:
    s = box_scene((-1, -1, -1), (1, 1, 1), albedo=0.5)
    rt = RayTracer.from_scene(s)
    rng = np.random.default_rng(3)
    d = rng.normal(size=(2000, 3))
    inside = rt.intersect(np.zeros(3), d)
    assert np.all(inside.prim_id >= 0) and not rt.backface(inside.prim_id, d).any()
    # rays from outside aimed at the box centre hit the outside = the back of inward walls
    origins = 5.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    outside = rt.intersect(origins, -d)
    assert np.all(outside.prim_id >= 0) and rt.backface(outside.prim_id, -d).all()


def test_broadcasting_and_empty_batches() -> None:
    rt = _quad_tracer()
    rng = np.random.default_rng(2)
    d = rng.normal(size=(4, 5, 3))
    d[..., 2] = -np.abs(d[..., 2]) - 1.0
    h = rt.intersect([1.0, 0.5, 1.0], d, tmax=np.full((4, 5), 100.0))
    assert h.prim_id.shape == h.t.shape == h.u.shape == h.v.shape == (4, 5)
    flat = rt.intersect(np.tile([1.0, 0.5, 1.0], (20, 1)), d.reshape(20, 3))
    np.testing.assert_array_equal(h.prim_id.reshape(-1), flat.prim_id)
    np.testing.assert_array_equal(h.t.reshape(-1), flat.t)
    assert rt.occluded([1.0, 0.5, 1.0], d, 100.0).shape == (4, 5)
    e = rt.intersect(np.zeros((0, 3)), np.zeros((0, 3)))
    assert e.prim_id.shape == (0,) and rt.occluded(
        np.zeros((0, 3)), np.zeros((0, 3)), 1.0
    ).shape == (0,)


def test_chunking_is_invisible(real_data: Path) -> None:
    s = load_gltf(real_data / "gltf" / "CornellBox.glb")
    rng = np.random.default_rng(4)
    o = rng.uniform(s.bounds[0] + 1, s.bounds[1] - 1, (1000, 3))
    d = rng.normal(size=(1000, 3))
    a = RayTracer.from_scene(s).intersect(o, d, tmin=0.01)
    b = RayTracer.from_scene(s, chunk_size=7).intersect(o, d, tmin=0.01)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(
        RayTracer.from_scene(s).occluded(o, d, 300.0),
        RayTracer.from_scene(s, chunk_size=13).occluded(o, d, 300.0),
    )


def test_rays_as_embree_takes_them_are_occluded_as_the_float64_rays(real_data: Path) -> None:
    """occluded_rays of rays a kernel wrote as Embree takes them (raytrace.kernels.embree_rays,
    the rounding rule of the bake's shadow-ray kernels) answers as occluded does for the same
    float64 rays, chunked or not, with and without an end; a kernel's not-finite flag is
    refused with occluded's error."""
    from probegrid.raytrace import EmbreeRays
    from probegrid.raytrace.kernels import embree_rays

    s = load_gltf(real_data / "gltf" / "CornellBox.glb")
    rng = np.random.default_rng(5)
    o = rng.uniform(s.bounds[0] + 1, s.bounds[1] - 1, (2000, 3))
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tmax = np.where(rng.random(2000) < 0.2, np.inf, rng.uniform(0.1, 300.0, 2000))
    for chunk in (65536, 13):
        rt = RayTracer.from_scene(s, chunk_size=chunk)
        org, dirs, far, ok = embree_rays(o, d, np.array([0.01]), tmax, rt.centre)
        rays = EmbreeRays(org, dirs, far)
        kept = far.copy()
        got = rt.occluded_rays(rays, ok)
        np.testing.assert_array_equal(got, rt.occluded(o, d, tmax, tmin=0.01))
        assert 0.2 < got.mean() < 0.95
        np.testing.assert_array_equal(rays.lengths, kept)  # the caller's rays are left as given
    with pytest.raises(ValueError, match="finite"):
        rt.occluded_rays(rays, False)
    assert rt.occluded_rays(EmbreeRays(org[:0], dirs[:0], far[:0])).shape == (0,)


def test_pickle_rebuilds(real_data: Path) -> None:
    s = load_gltf(real_data / "gltf" / "Cubes.glb")
    rt = RayTracer.from_scene(s)
    blob = pickle.dumps(rt)
    assert len(blob) < 20_000  # arrays only, no acceleration structure
    rt2 = pickle.loads(blob)
    rng = np.random.default_rng(5)
    d = rng.normal(size=(500, 3))
    a, b = rt.intersect([0.0, 1.0, 0.0], d), rt2.intersect([0.0, 1.0, 0.0], d)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)


def test_hits_agree_with_surface_positions(real_data: Path) -> None:
    s = load_gltf(real_data / "gltf" / "CornellBox.glb")
    rt = RayTracer.from_scene(s)
    rng = np.random.default_rng(6)
    o = rng.uniform(s.bounds[0] + 5, s.bounds[1] - 5, (5000, 3))
    d = rng.normal(size=(5000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    h = rt.intersect(o, d)
    hit = h.prim_id >= 0
    assert 0.5 < hit.mean() < 1.0  # the box is open at +Z
    surf = s.surface_at(h.prim_id[hit], h.u[hit], h.v[hit])
    # 555 mm scene in float32: positions agree to ~1e-4 of the extent
    np.testing.assert_allclose(o[hit] + h.t[hit, None] * d[hit], surf.position, atol=0.05)
    # rays leaving through the open front (+Z) are the misses
    assert np.all(d[~hit, 2] > 0)


def test_bad_arguments() -> None:
    rt = _quad_tracer()
    with pytest.raises(ValueError):
        rt.intersect([[np.nan, 0, 0]], [[0, 0, 1.0]])
    with pytest.raises(ValueError):
        rt.intersect([[0, 0, 0]], [[0, 0, 1.0]], tmin=-1.0)
    with pytest.raises(ValueError):
        rt.intersect(np.zeros((3, 2)), np.zeros((3, 2)))
    with pytest.raises(ValueError):
        rt.intersect(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError):
        RayTracer(np.zeros((3, 3)), np.zeros((0, 3), int))
    with pytest.raises(ValueError):
        RayTracer([[0, 0, 0], [1, 0, 0], [0, np.inf, 0]], [[0, 1, 2]])
    with pytest.raises(ValueError):
        RayTracer([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]])


def test_shared_tracer_is_reused_per_geometry() -> None:
    from probegrid.raytrace import RayTracer
    from probegrid.scene import box_scene

    a = box_scene((-1, -1, -1), (1, 1, 1), albedo=0.5)
    again = box_scene((-1, -1, -1), (1, 1, 1), albedo=0.9)  # same geometry, another object
    t1 = RayTracer.shared(a)
    assert RayTracer.shared(again) is t1
    t2 = RayTracer.shared(box_scene((-2, -1, -1), (1, 1, 1), albedo=0.5))
    assert t2 is not t1
    hit = t2.intersect(np.zeros(3), np.array([-1.0, 0.0, 0.0]))
    assert hit.t == pytest.approx(2.0)  # the new geometry's BVH, not the cached one
