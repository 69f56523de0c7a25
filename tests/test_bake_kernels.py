"""The compiled bake kernels (:mod:`probegrid.bake.kernels`) against the numpy expressions they
restate."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from meshes import triangle_soup

from probegrid.core.grid import GridSpec


def _field(rng: np.random.Generator, counts=(4, 3, 5), moments=True, invalid=0.2,
           moved=True) -> SimpleNamespace:
    """A random grid's probes: validity, (moved) positions and distance moments."""
    grid = GridSpec(bounds_min=(-1.0, 0.0, -2.0), bounds_max=(2.0, 1.5, 1.0), counts=counts)
    p = grid.n_probes
    pos = grid.positions().reshape(-1, 3)
    if moved:
        pos = pos + rng.uniform(-0.1, 0.1, pos.shape)
    m = None
    if moments:
        mean = rng.uniform(0.05, 2.0, (p, 6, 4, 4))
        m2 = mean**2 + rng.uniform(0.0, 0.3, mean.shape)
        m = np.stack([mean, m2], axis=-1).astype(np.float32)
    return SimpleNamespace(grid=grid, valid=rng.random(p) >= invalid, positions=pos, moments=m)


def _pattern_reference(n: int, jitter: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sample pattern in numpy array expressions (cubemap's own conversions)."""
    from probegrid.core.cubemap import face_uv_to_direction, texel_to_uv

    k = np.arange(n, dtype=np.float64)
    j = np.broadcast_to(jitter, (6 * n * n,) + jitter.shape[1:]).reshape(6, n, n, -1, 2)
    u = texel_to_uv(k[None, None, :, None] - 0.5 + j[..., 0], n)
    v = texel_to_uv(k[None, :, None, None] - 0.5 + j[..., 1], n)
    d = face_uv_to_direction(np.arange(6)[:, None, None, None], u, v)
    norm = np.linalg.norm(d, axis=-1)
    w = norm**-3
    return d / norm[..., None], w / w.sum(axis=-1, keepdims=True)


@pytest.mark.parametrize("samples", [1, 5])
def test_sample_pattern_kernel_matches_numpy(samples: int) -> None:
    from probegrid.bake.pattern import _jitter, sample_pattern
    from probegrid.bake.settings import BakeSettings

    st = BakeSettings(face_size=8, samples=samples, seed=3, moments_size=8)
    d, w = sample_pattern(st)
    rd, rw = _pattern_reference(8, _jitter(st.face_size, st.samples, st.seed))
    np.testing.assert_allclose(d, rd, rtol=0, atol=1e-15)
    np.testing.assert_allclose(w, rw, rtol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-15)
    # one set of positions for every texel (T = 1) is the same kernel's other form
    from probegrid.bake.kernels.cube import CUBE_AXES, cube_sample_directions

    shared = np.array([[[0.25, 0.75]] * samples])
    d1, w1 = cube_sample_directions(8, shared, CUBE_AXES)
    rd1, rw1 = _pattern_reference(8, shared)
    np.testing.assert_allclose(d1, rd1, rtol=0, atol=1e-15)
    np.testing.assert_allclose(w1, rw1, rtol=1e-14)


def test_texel_means_and_distance_moments_match_numpy() -> None:
    from probegrid.bake.kernels.grid import distance_moments, texel_means

    rng = np.random.default_rng(2)
    s, texels = 5, 96
    rad = rng.random((texels * s, 3)).astype(np.float32)
    w = rng.random((texels, s))
    w /= w.sum(axis=1, keepdims=True)
    ref = (rad.reshape(texels, s, 3) * w[..., None]).sum(axis=1, dtype=np.float64)
    np.testing.assert_allclose(texel_means(rad, w.reshape(-1), s), ref, rtol=1e-6)

    t = rng.uniform(0.1, 9.0, texels * s)
    sa = rng.uniform(0.01, 0.02, texels * s)
    bins = rng.integers(0, 12, texels * s)
    bins[:12] = np.arange(12)
    got = distance_moments(t, sa, bins, 12)
    den = np.bincount(bins, weights=sa, minlength=12)
    np.testing.assert_allclose(got[:, 0], np.bincount(bins, sa * t, 12) / den, rtol=1e-6)
    np.testing.assert_allclose(got[:, 1], np.bincount(bins, sa * t * t, 12) / den, rtol=1e-6)


def test_split_hits_sorts_misses_fronts_and_one_sided_backs() -> None:
    from probegrid.bake.kernels.surfaces import split_hits

    tri_n = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])  # triangle 1 is double-sided
    dirs = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [9.0, 9.0, 9.0], [0.0, 1.0, 0.0],
                     [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
    prim = np.array([0, 0, -1, 1, 1, 0])
    kind, rows, flip, emits = split_hits(dirs, prim, tri_n, np.array([False, True]))
    assert kind.tolist() == [1, 2, 0, 1, 1, 1]  # the back of one-sided triangle 0 is black
    assert rows.tolist() == [0, 3, 4, 5]
    assert flip.tolist() == [False, True, False, False]  # turned toward the ray
    assert emits.tolist() == [True, False, True, False]  # (edge-on: neither flipped nor lit)


def _assert_embree_rays(rays, origins, directions, tmin, tmax, centre) -> None:
    """Rays written as Embree takes them (raytrace.EmbreeRays: float32, re-centred on
    ``centre``, moved to ``tmin``) are the float64 rays ``origins + t directions``,
    ``tmin <= t <= tmax``, to float32 rounding."""
    org, dirs, length = rays
    assert org.dtype == dirs.dtype == length.dtype == np.float32
    want = (origins - centre) + np.reshape(tmin, (-1, 1)) * directions
    np.testing.assert_allclose(org, want, rtol=0, atol=4e-7 * max(1.0, np.abs(want).max()))
    np.testing.assert_allclose(dirs, directions, rtol=0, atol=1e-7)
    np.testing.assert_allclose(length, np.broadcast_to(tmax - tmin, length.shape), rtol=1e-6)


def test_light_rays_match_incident_many() -> None:
    """The shadow-ray set-up equals lights.incident_many plus the renderer's selection rule."""
    from probegrid.bake.kernels.lights import PunctualLights, light_rays
    from probegrid.core.lights import (
        DirectionalLight,
        PointLight,
        SpotLight,
        incident_many,
    )

    lights = [
        PointLight((0.0, 2.0, 0.0), (1.0, 0.8, 0.6), 40.0, range=3.0),
        SpotLight((1.0, 1.5, -1.0), (0.0, -1.0, 0.2), (0.2, 0.4, 1.0), 80.0, range=None,
                  inner_cone_angle=0.3, outer_cone_angle=0.7),
        DirectionalLight((0.3, -1.0, 0.1), (1.0, 1.0, 1.0), 3.0),
    ]
    rng = np.random.default_rng(4)
    n = 3000
    pts = rng.uniform(-2.5, 2.5, (n, 3))
    pts[0] = lights[0].position  # at the light: no direction, no light
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    eps = 1e-3
    centre = np.array([0.3, -0.2, 0.5])
    which, org, dirs, length, irr, ok = light_rays(pts, nrm, PunctualLights.of(lights), eps,
                                                   centre)
    assert ok

    d_ref, e_ref, dist_ref = incident_many(lights, pts)
    cos = np.einsum("pli,pi->pl", d_ref, nrm)
    lit = (e_ref.max(axis=-1) > 0) & (cos > 0)
    pi, li = np.nonzero(lit)  # the same (point, light) order as the kernel's loops
    assert len(which) == len(pi) > n // 4
    np.testing.assert_array_equal(which, pi)
    ref_tmax = np.where(np.isfinite(dist_ref[pi, li]), dist_ref[pi, li] - eps, np.inf)
    _assert_embree_rays((org, dirs, length), pts[pi] + eps * nrm[pi], d_ref[pi, li], eps,
                        ref_tmax, centre)
    np.testing.assert_allclose(irr, cos[pi, li, None] * e_ref[pi, li], rtol=1e-12, atol=1e-300)
    assert not lit[0, 0]  # at the light: neither the reference nor the kernel lights it


def test_shade_hits_is_split_hits_then_hit_surfaces() -> None:
    """The fused records pass against the two kernels it fuses: kinds, distances, the front
    hits' surfaces (normals turned toward the ray, emission from the front only, albedo and
    emission rounded to the records' float32), and the points eps back along the ray."""
    from probegrid.bake.kernels.surfaces import HitRecords, shade_hits, split_hits
    from probegrid.raytrace import Hits
    from probegrid.scene.kernels import SurfaceTables, hit_surfaces

    rng = np.random.default_rng(16)
    verts, tris, nrm, material = triangle_soup(rng)
    base, emis = rng.random((3, 3)), rng.random((3, 3))
    colors = np.ascontiguousarray(rng.random((30, 3)))
    double = rng.random(40) < 0.5
    n = 600
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    prim = np.where(rng.random(n) < 0.2, -1, rng.integers(0, 40, n)).astype(np.int64)
    u = rng.random(n)
    v = rng.random(n) * (1 - u)
    t_hit = np.where(prim < 0, np.inf, rng.uniform(0.0, 30.0, n))
    eps = 1e-4
    kind = np.full(n, 7, np.uint8)
    dist = np.empty(n)
    rec = {k: np.zeros((n, 3), np.float64 if k == "position" else np.float32)
           for k in ("position", "normal", "albedo", "emission")}
    surfaces = SurfaceTables(verts, tris, nrm, material, base, emis, colors)
    rows, pts, turned, back = shade_hits(
        dirs, Hits(prim, t_hit, u, v), (20.0, eps), surfaces, double,
        HitRecords(kind, dist, rec["position"], rec["normal"], rec["albedo"], rec["emission"]))
    kind_r, rows_r, flip, emits = split_hits(dirs, prim, nrm, double)
    np.testing.assert_array_equal(kind, kind_r)
    np.testing.assert_array_equal(rows, rows_r)
    assert 0 < len(rows) < n and (kind == 2).any()
    np.testing.assert_array_equal(dist, np.where(prim < 0, 20.0, np.minimum(t_hit, 20.0)))
    pos, nn, alb, em = hit_surfaces(prim[rows], u[rows], v[rows], surfaces)
    nn[flip] *= -1.0
    em[~emits] = 0.0
    np.testing.assert_array_equal(pts, pos)
    np.testing.assert_array_equal(turned, nn)
    np.testing.assert_array_equal(back, pos - eps * dirs[rows])
    for name, want in (("position", pos), ("normal", nn), ("albedo", alb), ("emission", em)):
        expect = np.zeros_like(rec[name])
        expect[rows] = want
        np.testing.assert_array_equal(rec[name], expect)


@pytest.mark.parametrize("counts", [(4, 3, 5), (2, 1, 1)])
def test_hit_probe_weights_match_probe_weights(counts) -> None:
    """The trace-once weights are :func:`probegrid.core.ddgi.probe_weights`' (normals and
    moments), stored normalised in float32."""
    from probegrid.bake.records import GridData, hit_weights
    from probegrid.core.ddgi import BorderedCubes, probe_weights

    rng = np.random.default_rng(3)
    field = _field(rng, counts=counts)
    n = 3000
    pts = rng.uniform((-1.3, -0.2, -2.3), (2.3, 1.7, 1.3), (n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    mom = BorderedCubes(field.moments)
    data = GridData(field.grid, field.valid, field.positions, mom.data, mom.n, None)
    kind = rng.choice(np.array([0, 1, 1, 1, 2], np.uint8), n)  # misses and back hits: none
    rec = {"kind": kind, "position": pts, "normal": nrm.astype(np.float32)}
    idx, w = hit_weights(rec, data)
    ref = probe_weights(field.grid, pts, valid=field.valid,
                        normals=nrm.astype(np.float32).astype(np.float64),
                        probe_positions=field.positions, moments=mom)
    front = kind == 1
    np.testing.assert_array_equal(idx[front], ref.indices[front])
    np.testing.assert_allclose(w[front], ref.weights[front], rtol=1e-6, atol=1e-7)
    assert not idx[~front].any() and not w[~front].any()


def test_replay_kernel_matches_numpy() -> None:
    """One bounce from records: ``emission + albedo * (lp + le + sum_c w_c G_c(n))`` with the
    bilinear bordered-cube lookup of :class:`probegrid.core.ddgi.BorderedCubes`, or with the
    gathered irradiance in the grid's place."""
    from probegrid.bake.kernels.cube import CUBE_AXES
    from probegrid.bake.kernels.grid import ReplayRecords, replay_radiance
    from probegrid.core.ddgi import BorderedCubes

    rng = np.random.default_rng(5)
    n, p, g = 2000, 7, 4
    kind = rng.integers(0, 3, n).astype(np.uint8)
    f32 = lambda *s: rng.random(s).astype(np.float32)
    em, lp, le, alb = f32(n, 3), f32(n, 3), f32(n, 3), f32(n, 3)
    nrm = rng.normal(size=(n, 3))
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)).astype(np.float32)
    idx = rng.integers(0, p, (n, 8)).astype(np.int32)
    w = f32(n, 8)
    cubes = BorderedCubes(rng.random((p, 6, g, g, 3)))
    gathered = f32(n, 3)
    none = np.zeros((0, 3), np.float32)
    for level, indirect in ((0, none), (2, none), (0, gathered), (2, gathered)):
        rad, bnc = replay_radiance(ReplayRecords(kind, em, lp, le, alb, nrm, idx, w),
                                   (cubes.data, g), CUBE_AXES, level, indirect)
        grid = np.zeros((n, 3))
        if level and len(indirect):  # gathered irradiance takes the grid's place
            grid = indirect.astype(np.float64)
        elif level:
            for c in range(8):
                grid += w[:, c, None] * cubes.lookup(idx[:, c], nrm.astype(np.float64))
        lit = lp + (le + grid if level else 0)
        ref_b = np.where((kind == 1)[:, None], alb * lit, np.where((kind == 0)[:, None], lp, 0))
        ref_r = ref_b + np.where((kind == 1)[:, None], em, 0)
        np.testing.assert_allclose(bnc, ref_b, rtol=1e-5)
        np.testing.assert_allclose(rad, ref_r, rtol=1e-5)


def test_angle_is_atan2_to_the_last_bits() -> None:
    """bake.kernels.emitters._angle (the polygon integrals' atan2 for y >= 0) against
    numpy.arctan2 over 24 decades of both arguments, both signs of x, the reduction's branch
    points and the zeros: within 1e-15 and 16 units in the last place everywhere, exact at 0,
    pi / 2 and pi."""
    import numba

    from probegrid.bake.kernels.emitters import _TAN_PI_8, _angle

    @numba.njit
    def angles(y, x):
        out = np.empty(y.shape[0])
        for i in range(y.shape[0]):
            out[i] = _angle(y[i], x[i])
        return out

    rng = np.random.default_rng(3)
    n = 400_000
    y = np.abs(rng.normal(size=n)) * 10.0 ** rng.uniform(-12, 12, n)
    x = rng.normal(size=n) * 10.0 ** rng.uniform(-12, 12, n)
    t = _TAN_PI_8
    edge_y = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1e-300, 1.0, t, 1.0, t, 1.0, 1.0, 2.0])
    edge_x = np.array([1.0, -1.0, 0.0, 0.0, -0.0, 1.0, -1e-300, 1.0, t, -1.0, 1.0, -1.0, 3.0])
    y, x = np.concatenate([y, edge_y]), np.concatenate([x, edge_x])
    got, ref = angles(y, x), np.arctan2(y, x)
    assert np.abs(got - ref).max() <= 1e-15
    assert np.all(np.abs(got - ref) <= 16 * np.spacing(np.maximum(ref, 1e-300)))
    assert angles(np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, -1.0])).tolist() == [
        0.0, np.pi / 2, np.pi]


def test_turn_is_cos_and_sin_of_the_azimuth() -> None:
    """bake.kernels.sampling._turn (the gather's azimuths) against numpy's cos and sin of
    2 pi r: within 1e-15 over 10^6 uniform numbers, the quarter turns and the ends of [0, 1)."""
    import numba

    from probegrid.bake.kernels.sampling import _turn

    @numba.njit
    def turns(r):
        out = np.empty((r.shape[0], 2))
        for i in range(r.shape[0]):
            out[i, 0], out[i, 1] = _turn(r[i])
        return out

    r = np.concatenate([np.random.default_rng(4).random(1_000_000),
                        [0.0, 0.125, 0.25, 0.5, 0.75, 1 - 2.0**-53, 1e-300]])
    got = turns(r)
    assert np.abs(got[:, 0] - np.cos(2 * np.pi * r)).max() <= 1e-15
    assert np.abs(got[:, 1] - np.sin(2 * np.pi * r)).max() <= 1e-15


def test_emitter_irradiance_is_the_exact_form_factor() -> None:
    """Lambert's edge formula against the closed form of a parallel rectangle (near: edges
    wider than pi/8, through the arctangent; far: narrower, through its series in t^2 alone),
    and a triangle crossing the receiver's horizon (clipped) against a fine quadrature."""
    from probegrid.bake.kernels.emitters import emitter_irradiance

    a, b = 1.3, 0.7  # rectangle centred above the point, facing down
    for c in (0.2, 0.9, 3.0, 40.0):
        v = np.array([[-a / 2, c, -b / 2], [a / 2, c, -b / 2], [a / 2, c, b / 2],
                      [-a / 2, c, b / 2]])
        tris = np.array([v[[0, 2, 1]], v[[0, 3, 2]]])
        nrm = np.tile([0.0, -1.0, 0.0], (2, 1))
        e = emitter_irradiance(np.zeros((1, 3)), np.array([[0.0, 1.0, 0.0]]), tris, nrm,
                               np.ones((2, 3)))
        x, y = a / 2 / c, b / 2 / c
        ff = 4 * (x / np.hypot(1, x) * np.arctan(y / np.hypot(1, x))
                  + y / np.hypot(1, y) * np.arctan(x / np.hypot(1, y))) / (2 * np.pi)
        np.testing.assert_allclose(e[0], np.pi * ff, rtol=1e-12)
    # a vertical triangle beside a tilted receiver: quadrature of cos_x cos_y / d^2 dA
    tri = np.array([[[1.0, -0.5, -0.5], [1.0, 0.8, -0.5], [1.0, -0.5, 0.9]]])
    tn = np.array([[-1.0, 0.0, 0.0]])
    rn = np.array([[0.3, 0.8, 0.0]]) / np.hypot(0.3, 0.8)
    got = emitter_irradiance(np.zeros((1, 3)), rn, tri, tn, np.ones((1, 3)))[0, 0]
    k = 1500
    s, t = np.meshgrid((np.arange(k) + 0.5) / k, (np.arange(k) + 0.5) / k)
    inside = s + t < 1
    pts = tri[0, 0] + s[inside, None] * (tri[0, 1] - tri[0, 0]) + t[inside, None] * (
        tri[0, 2] - tri[0, 0])
    d2 = np.sum(pts**2, axis=1)
    cx = np.maximum(pts @ rn[0], 0) / np.sqrt(d2)
    cy = pts[:, 0] / np.sqrt(d2)
    area = 0.5 * 1.3 * 1.4
    ref = np.sum(cx * cy / d2) * area / inside.sum()
    assert got == pytest.approx(ref, rel=2e-3)
    assert 0 < got < np.pi


def test_texel_coverage_adds_up_to_the_triangle_solid_angle() -> None:
    """The pieces of a triangle clipped to every texel it covers (across cube faces) add up to
    its solid angle (Van Oosterom-Strackee), each piece inside its texel."""
    from probegrid.bake.kernels.cube import CUBE_AXES
    from probegrid.bake.kernels.emitters import texel_emitter_coverage
    from probegrid.core.cubemap import texel_solid_angles

    rng = np.random.default_rng(11)
    for _ in range(5):
        tri = rng.normal(size=(1, 3, 3)) * 2
        nrm = np.cross(tri[0, 1] - tri[0, 0], tri[0, 2] - tri[0, 0])
        nrm /= np.linalg.norm(nrm)
        if np.dot(nrm, tri[0, 0]) > 0:  # make it face the origin
            tri = tri[:, ::-1].copy()
            nrm = -nrm
        a, b, c = tri[0]
        la, lb, lc = (np.linalg.norm(x) for x in (a, b, c))
        ref = 2 * np.arctan2(abs(np.dot(a, np.cross(b, c))),
                             la * lb * lc + np.dot(a, b) * lc + np.dot(a, c) * lb
                             + np.dot(b, c) * la)
        count, tex, _, om, dirs, dist = texel_emitter_coverage(
            np.zeros(3), tri, nrm[None], 8, CUBE_AXES, 4096)
        assert 0 < count <= 4096
        assert om[:count].sum() == pytest.approx(ref, rel=1e-10)
        assert np.all(om[:count] <= texel_solid_angles(8).reshape(-1)[tex[:count]] * (1 + 1e-9))
        hit = dist[:count, None] * dirs[:count]
        np.testing.assert_allclose((hit - a) @ nrm, 0, atol=1e-9)


def test_cosine_directions_match_numpy() -> None:
    """The compiled cosine-weighted directions against the array expression (Duff et al.'s
    basis), and their distribution: mean cosine 2/3, uniform azimuth."""
    from probegrid.bake.kernels.sampling import cosine_directions

    rng = np.random.default_rng(4)
    nrm = rng.normal(size=(3000, 3))
    nrm[:5] = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0], [0, 0, -1 + 1e-12]]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    r = rng.random((3000, 2))
    nx, ny, nz = nrm.T
    sign = np.where(nz >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + nz)
    bb = nx * ny * a
    t1 = np.stack([1.0 + sign * nx * nx * a, sign * bb, -sign * nx], axis=1)
    t2 = np.stack([bb, sign + ny * ny * a, -ny], axis=1)
    rad, phi = np.sqrt(r[:, 0]), 2 * np.pi * r[:, 1]
    d = ((rad * np.cos(phi))[:, None] * t1 + (rad * np.sin(phi))[:, None] * t2
         + np.sqrt(1 - r[:, 0])[:, None] * nrm)
    want = d / np.linalg.norm(d, axis=1, keepdims=True)
    got = cosine_directions(nrm, r)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-14)
    cos = np.einsum("ij,ij->i", got, nrm)
    assert cos.min() >= 0 and abs(cos.mean() - 2 / 3) < 0.01


def test_alias_table_draws_each_entry_with_its_probability() -> None:
    """Walker's alias table (Vose): the probability it gives each entry, accept / N plus the
    refused shares aliased to it, is the distribution's; zero-probability entries (a black
    ground) are never drawn, also on a fine sweep of the uniform."""
    from probegrid.bake.kernels.sampling import alias_draw, alias_table

    rng = np.random.default_rng(21)
    for prob in (rng.gamma(0.3, 1.0, 6 * 64 * 64), np.r_[np.zeros(7), 1.0, np.zeros(3)],
                 np.full(5, 0.2)):
        prob = prob / prob.sum()
        accept, alias = alias_table(prob)
        n = len(prob)
        got = accept / n
        np.add.at(got, alias, (1.0 - accept) / n)
        np.testing.assert_allclose(got, prob, rtol=0, atol=1e-15)
        u = (np.arange(1_000_000) + 0.5) / 1_000_000
        t = alias_draw(accept, alias, u)
        assert np.all(prob[t] > 0)
        # a fine sweep of the uniform lands on each entry as often as its probability, to one
        # sweep step per piece of a column it owns (its own and those aliased to it)
        pieces = 1 + np.bincount(alias[accept < 1], minlength=n)
        assert np.all(np.abs(np.bincount(t, minlength=n) / len(u) - prob) <= pieces / len(u))


def test_gather_rays_start_off_their_parents_and_follow_the_cosine() -> None:
    """The gather's rays from chosen parent hits: origins ``p - eps arriving + eps n`` and the
    cosine directions about the parents' (float32) normals, row by row."""
    from probegrid.bake.kernels.sampling import cosine_directions, gather_rays

    rng = np.random.default_rng(14)
    m = 200
    pos = rng.normal(size=(m, 3))
    nrm = rng.normal(size=(m, 3))
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)).astype(np.float32)
    arriving = rng.normal(size=(m, 3))
    parents = rng.integers(0, m, 500)
    r = rng.random((500, 2))
    org, dirs = gather_rays(pos, nrm, arriving, parents, r, 1e-3)
    n64 = nrm.astype(np.float64)[parents]
    np.testing.assert_allclose(org, pos[parents] - 1e-3 * arriving[parents] + 1e-3 * n64,
                               rtol=0, atol=1e-15)
    np.testing.assert_allclose(dirs, cosine_directions(n64, r), rtol=0, atol=1e-15)


@pytest.mark.parametrize("rotation", [0.7, 0.0])
def test_environment_samples_match_the_numpy_sampler(rotation: float) -> None:
    """The compiled environment samples are EnvironmentLight.sample_above's directions with
    the estimator's contributions radiance cos / (p L), for a rotated sky and an unrotated
    one, with normals along the axes (the mirror by texel permutation) among others."""
    from probegrid.bake.environment import Environment, EnvironmentLight
    from probegrid.bake.kernels.cube import CUBE_AXES
    from probegrid.bake.kernels.environment import SkyTable, environment_samples

    rng = np.random.default_rng(6)
    faces = (rng.random((6, 8, 8, 3)) ** 3).astype(np.float32)
    faces[3] = 0.0  # a black ground: zero-probability texels
    light = EnvironmentLight(Environment(faces=faces, intensity=2.0, rotation=rotation), 8)
    n, ls = 400, 3
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm[::3] = np.repeat(np.vstack([np.eye(3), -np.eye(3)]), 23, axis=0)[:len(nrm[::3])]
    r = rng.random((n, ls, 3))
    pts = rng.normal(size=(n, 3))
    centre = np.array([-0.4, 0.1, 0.9])
    sky = SkyTable(light._accept, light._alias, light._prob, light.radiance, light.size,
                   light._to_world, light._mirrors)
    which, org, dirs, length, contrib, ok = environment_samples(pts, nrm, r, sky, CUBE_AXES,
                                                                1e-3, centre)
    assert ok
    d, rad, pdf = light.sample_above(r, nrm)
    cos = np.einsum("nlk,nk->nl", d, nrm)
    i, k = np.nonzero((cos > 0) & (pdf > 0))
    assert len(i) > 0.95 * n * ls  # (draws below the horizon are folded above it, not lost)
    np.testing.assert_array_equal(which, i)
    _assert_embree_rays((org, dirs, length), pts[i], d[i, k], 1e-3, np.inf, centre)
    np.testing.assert_allclose(contrib, rad[i, k] * (cos[i, k] / (pdf[i, k] * ls))[:, None],
                               rtol=1e-12)


def test_emitter_samples_match_surface_sampling() -> None:
    """The fused emitter sampling against choosing triangles with alias_draw, points through
    Scene.surface_at and emitter_shadow_rays; the estimate against sum_rows."""
    from probegrid.bake.emitters import Emitters
    from probegrid.core.arrays import sum_rows
    from probegrid.bake.kernels.emitters import (
        EmitterTriangles,
        emitter_estimate,
        emitter_samples,
        emitter_shadow_rays,
    )
    from probegrid.bake.kernels.lights import sum_unblocked
    from probegrid.bake.kernels.sampling import alias_draw
    from probegrid.scene import Material, SceneBuilder

    b = SceneBuilder()
    hot = b.add_material(Material(emissive=(3.0, 2.0, 1.0)))
    warm = b.add_material(Material(emissive=(0.5, 1.0, 0.2)))
    b.add_quad((-0.5, 2, -0.5), (1, 0, 0), (0, 0, 1), material=hot)
    b.add_quad((2, 0, -1), (0, 0, 2), (0, 1.5, 0), material=warm)
    em = Emitters.from_scene(b.build())
    rng = np.random.default_rng(8)
    n, ls = 300, 2
    pts = rng.uniform(-1, 1, (n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    r = rng.random((n, ls, 3))
    accept, alias, inv_pdf = em._selection
    centre = np.array([0.2, 1.0, -0.3])
    got = emitter_samples(pts, nrm, r, (accept, alias, inv_pdf),
                          EmitterTriangles(em.vertices, em.normals, em.factor, em.control), 1e-4,
                          centre)
    e = alias_draw(accept, alias, r[..., 0])
    r1 = np.sqrt(r[..., 1])
    surf = em.scene.surface_at(em.triangles[e], r1 * (1 - r[..., 2]), r1 * r[..., 2])
    want = emitter_shadow_rays(pts, nrm, np.ascontiguousarray(surf.position),
                               np.ascontiguousarray(em.normals[e]),
                               np.ascontiguousarray(surf.emission),
                               np.ascontiguousarray(em.control[e]),
                               np.ascontiguousarray(inv_pdf[e]), 1e-4, centre)
    assert len(got[0]) > n // 2
    assert got[6][0] and want[6][0]  # every ray finite
    for g, w in zip(got[:6], want[:6], strict=True):  # (float32 rays: one rounding apart)
        np.testing.assert_allclose(g, w, rtol=1e-13 if g.dtype == np.float64 else 1e-6,
                                   atol=1e-15 if g.dtype == np.float64 else 1e-6)
    which, org, dirs, length, vis, occ, _ = got
    # each ray leaves its point eps off the surface, a unit direction toward an emitter
    _assert_embree_rays((org, dirs, length), pts[which] + 1e-4 * nrm[which],
                        dirs.astype(np.float64), 1e-4, 1e-4 + length.astype(np.float64), centre)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, rtol=1e-6)
    assert np.all(np.einsum("ki,ki->k", dirs, nrm[which]) > 0) and np.all(length > 0)
    blocked = rng.random(len(which)) < 0.3
    plain = sum_rows(which, np.where(blocked[:, None], 0.0, vis - occ), n)
    whole = sum_rows(which, -occ, n)
    a = rng.uniform(0.5, 2.0, (n, 3))
    ok = whole > 0
    ratio = np.where(ok, a * np.divide(plain, whole, out=np.zeros_like(plain), where=ok),
                     a + plain)
    np.testing.assert_allclose(emitter_estimate(n, which, blocked, vis, occ, a), ratio,
                               rtol=1e-13)
    np.testing.assert_allclose(emitter_estimate(n, which, blocked, vis, occ, np.zeros((0, 3))),
                               plain, rtol=1e-13, atol=1e-300)
    np.testing.assert_allclose(sum_unblocked(n, which, blocked, vis),
                               sum_rows(which, np.where(blocked[:, None], 0.0, vis), n),
                               rtol=1e-13, atol=1e-300)


@pytest.mark.parametrize("samples,planes", [(1, True), (2, False)])
def test_smooth_texels_matches_numpy(samples: int, planes: bool) -> None:
    """The edge-aware Gaussian over a window of texels, against the same sums written as
    array expressions over every pair of rays of a face."""
    from probegrid.bake.kernels.texels import Smoothing, TexelHits, smooth_texels

    rng = np.random.default_rng(5)
    n, b = 6, 2
    per = 6 * n * n * samples
    nr = b * per
    value = rng.random((nr, 3))
    weight = rng.random(nr) * (rng.random(nr) > 0.2)
    normal = np.zeros((nr, 3), np.float32)
    normal[np.arange(nr), rng.integers(0, 2, nr)] = 1.0  # two surfaces' worth of normals
    position = rng.normal(size=(nr, 3))
    origin = rng.normal(size=(b, 3)) if planes else np.zeros((0, 3))
    sm = Smoothing(radius=2, sigma=1.5, same_normal=0.9, same_plane=0.3)
    got = smooth_texels(TexelHits(value, weight, position, normal, origin), n, samples, sm)

    ray = np.arange(nr)
    probe, texel = ray // per, (ray % per) // samples
    face, row, col = texel // (n * n), (texel % (n * n)) // n, texel % n
    dr, dc = row[:, None] - row[None, :], col[:, None] - col[None, :]
    same = ((probe[:, None] == probe[None, :]) & (face[:, None] == face[None, :])
            & (np.abs(dr) <= sm.radius) & (np.abs(dc) <= sm.radius)
            & (normal @ normal.T >= sm.same_normal))
    if planes:
        off = np.abs(np.einsum("ijk,ik->ij", position[None, :] - position[:, None], normal))
        reach = sm.same_plane * np.linalg.norm(position - origin[probe], axis=1)
        same &= off <= reach[:, None]
    g = np.exp(-(dr**2 + dc**2) / (2 * sm.sigma**2)) * same * weight[None, :]
    want = np.where(weight[:, None] > 0, (g @ value) / np.maximum(g.sum(axis=1), 1e-300)[:, None],
                    value)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
