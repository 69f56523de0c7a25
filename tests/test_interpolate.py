"""Tests of probe blending at arbitrary positions (probegrid.core.ddgi)."""

from __future__ import annotations

import numpy as np
import pytest
from probe_stores import GRID, linear_arrays, linear_shapes, linear_store, linear_values

from probegrid.core.cubemap import CubeMap
from probegrid.core.ddgi import CRUSH_THRESHOLD, _probe_bilinear, blend, blend_lookup, probe_weights
from probegrid.core.dfg import dfg_lut
from probegrid.core.grid import GridSpec
from probegrid.core.sampling import CubeSampler
from probegrid.core.shading import shade_split_sum
from probegrid.query import ProbeField

RNG_SEED = 20240611


@pytest.fixture(scope="module")
def field(tmp_path_factory) -> ProbeField:
    return ProbeField(linear_store(tmp_path_factory.mktemp("interp") / "linear.probes"))


def _inside(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return GRID.lo + rng.random((n, 3)) * (GRID.hi - GRID.lo)


# ------------------------------------------------------------------------------ exactness
def test_linear_field_is_reproduced_exactly_inside_cells(field):
    pts = _inside(200)
    w = field.weights(pts)
    assert not w.outside.any() and not w.unlit.any()
    np.testing.assert_allclose(w.weights.sum(axis=1), 1.0, rtol=0, atol=1e-14)
    shapes = linear_shapes()
    np.testing.assert_allclose(field.sh(w, kind="raw"), linear_values("sh", shapes["sh"], pts),
                               rtol=0, atol=1e-12)
    for kind, name in (("diffuse", "diffuse"), ("incoming", "incoming")):
        got = field.cube(w, kind)
        assert got.dtype == np.float32 and got.shape == (200, *shapes[name])
        np.testing.assert_allclose(got, linear_values(name, shapes[name], pts), rtol=0, atol=1e-5)
    for k in range(field.specular_levels):
        got = field.cube(w, "specular", level=k)
        want = linear_values(f"specular_{k}", shapes[f"specular_{k}"], pts)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)


def test_probe_positions_give_the_probe_values(field):
    pos = GRID.positions()
    w = field.weights(pos)
    got = field.sh(w, kind="raw")
    np.testing.assert_array_equal(got, field.store.arrays["sh"][:].astype(np.float64))


def test_cubemap_bundles_every_specular_level(field):
    w = field.weights([0.5, 0.5, 0.5])
    (cm,) = field.cubemap(w, "specular")
    assert isinstance(cm, CubeMap) and cm.kind == "specular"
    assert cm.num_levels == field.specular_levels == 4
    assert [lv.shape[1] for lv in cm.levels] == [8, 4, 2, 1]
    assert field.kinds == ("diffuse", "specular", "incoming")


# ------------------------------------------------------------------------------ validity
def test_invalid_probes_get_zero_weight_and_the_rest_renormalise():
    valid = np.ones(GRID.n_probes, bool)
    centre = np.array([[0.5, 0.5, 0.5]])  # trilinear 1/8 on every corner of cell (0, 0, 0)
    idx = GRID.corner_indices(centre)[0]
    valid[idx[[0, 5]]] = False
    w = probe_weights(GRID, centre, valid=valid)
    np.testing.assert_allclose(w.weights[0, [0, 5]], 0.0)
    np.testing.assert_allclose(np.delete(w.weights[0], [0, 5]), 1.0 / 6.0, rtol=1e-15)
    # an affine field over the valid probes is no longer exact, but it is their weighted mean
    values = np.arange(GRID.n_probes, dtype=np.float64)[:, None]
    assert blend(values, w)[0, 0] == pytest.approx(np.mean(np.delete(idx, [0, 5])))


def test_all_corners_invalid_is_flagged_unlit():
    valid = np.ones(GRID.n_probes, bool)
    pts = np.array([[0.5, 0.5, 0.5], [1.5, 0.5, 1.5]])
    valid[GRID.corner_indices(pts[0])] = False
    w = probe_weights(GRID, pts, valid=valid)
    assert w.unlit.tolist() == [True, False]
    assert np.all(w.weights[0] == 0) and w.weights[1].sum() == pytest.approx(1.0)
    assert np.all(blend(np.ones((GRID.n_probes, 2)), w)[0] == 0)


def test_invalid_probe_data_never_leaks_into_the_blend():
    arrays = linear_arrays()
    valid = arrays["valid"].copy()
    valid[0] = False
    sh = arrays["sh"].astype(np.float64)
    sh[0] = np.nan  # whatever an invalid probe holds must not matter
    w = probe_weights(GRID, [[0.25, 0.25, 0.25]], valid=valid)
    assert np.isfinite(blend(sh, w)).all()


# ------------------------------------------------------------------------------ DDGI weights
LINE = GridSpec.from_counts((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (2, 1, 1))


def _per_probe(w) -> np.ndarray:
    """(n, P) weight of each probe of LINE (corners repeat probe 0 on its single-probe axes)."""
    out = np.zeros((len(w), LINE.n_probes))
    for i in range(len(w)):
        out[i] = np.bincount(w.indices[i], weights=w.weights[i], minlength=LINE.n_probes)
    return out


def _moments(mean: np.ndarray, mean_sq: np.ndarray, m: int = 2) -> np.ndarray:
    out = np.empty((len(mean), 6, m, m, 2), np.float64)
    out[..., 0] = np.asarray(mean)[:, None, None, None]
    out[..., 1] = np.asarray(mean_sq)[:, None, None, None]
    return out


def test_wall_between_probes_removes_that_probes_weight():
    p = [[0.5, 0.0, 0.0]]
    n = [[-1.0, 0.0, 0.0]]  # the surface faces probe 0 at x = 0
    open_ = _moments([100.0, 100.0], [100.0**2 + 1, 100.0**2 + 1])
    w_open = probe_weights(LINE, p, normals=n, moments=open_)
    assert _per_probe(w_open)[0, 0] > 0.8  # facing term 1.2 vs 0.2
    # probe 0 sees a surface at distance 0.1 in every direction (variance 0): a wall
    wall = _moments([0.1, 100.0], [0.01, 100.0**2 + 1])
    w = probe_weights(LINE, p, normals=n, moments=wall)
    assert _per_probe(w)[0, 0] < 1e-12
    assert _per_probe(w)[0, 1] == pytest.approx(1.0, abs=1e-12)


def test_ddgi_weights_match_the_stated_formula():
    p = [[0.5, 0.0, 0.0]]
    n = [[-1.0, 0.0, 0.0]]
    # probe 0: mean 0.4, variance 0.01, point at r = 0.5 -> Chebyshev 0.01 / 0.02 = 0.5, cubed
    m = _moments([0.4, 100.0], [0.16 + 0.01, 100.0**2 + 1])
    w = probe_weights(LINE, p, normals=n, moments=m, normal_bias=0.0)
    s0 = 1.2 * 0.5**3  # facing ((1 + 1) / 2)^2 + 0.2 = 1.2
    assert s0 < CRUSH_THRESHOLD
    s0 = s0**3 / CRUSH_THRESHOLD**2  # crushed
    s1 = 0.2  # facing away: ((-1 + 1) / 2)^2 + 0.2
    np.testing.assert_allclose(_per_probe(w)[0], [s0 / (s0 + s1), s1 / (s0 + s1)], rtol=1e-12)
    # the normal bias moves the tested point by 0.1 cell along n, to r = 0.4 = mean: visible
    w_b = probe_weights(LINE, p, normals=n, moments=m, normal_bias=0.1)
    np.testing.assert_allclose(_per_probe(w_b)[0], [1.2 / 1.4, 0.2 / 1.4], rtol=1e-12)


def test_normal_term_without_moments_and_with_moved_probes():
    p = [[0.5, 0.0, 0.0]]
    n = [[0.0, 1.0, 0.0]]  # perpendicular to both probe directions: equal terms 0.45
    w = probe_weights(LINE, p, normals=n)
    np.testing.assert_allclose(_per_probe(w)[0], 0.5)
    moved = np.array([[0.5, 1.0, 0.0], [1.0, 0.0, 0.0]])  # probe 0 moved straight above p
    w = probe_weights(LINE, p, normals=n, probe_positions=moved)
    np.testing.assert_allclose(_per_probe(w)[0], [1.2 / 1.65, 0.45 / 1.65], rtol=1e-12)


def _random_field(seed: int):
    rng = np.random.default_rng(seed)
    grid = GridSpec.from_counts((0.0, 0.0, 0.0), (2.0, 2.0, 2.0), (3, 3, 3))
    values = rng.normal(size=(grid.n_probes, 5))
    mean = rng.uniform(0.3, 2.0, size=(grid.n_probes, 6, 3, 3))
    var = rng.uniform(0.01, 0.2, size=mean.shape)
    moments = np.stack([mean, mean**2 + var], axis=-1)
    valid = np.ones(grid.n_probes, bool)
    valid[4] = False
    return grid, values, moments, valid


def test_no_popping_weights_are_continuous_along_a_line():
    """Max jump between neighbouring samples shrinks with the step: no discontinuity anywhere,
    including at cell boundaries and where the probe directions cross cube-face edges."""
    grid, values, moments, valid = _random_field(1)
    a, b = np.array([0.05, 0.3, 0.2]), np.array([1.95, 1.7, 1.9])
    normal = np.array([[0.3, 0.8, -0.5]])

    def max_jump(steps: int) -> float:
        t = np.linspace(0.0, 1.0, steps)[:, None]
        pts = a + t * (b - a)
        w = probe_weights(grid, pts, valid=valid, normals=np.repeat(normal, steps, 0),
                          moments=moments)
        f = blend(values, w)
        return float(np.abs(np.diff(f, axis=0)).max())

    coarse, fine = max_jump(2001), max_jump(20001)
    assert fine < 0.2 * coarse, (coarse, fine)  # Lipschitz: ~0.1; a jump would stay put


def test_continuity_across_a_cell_face_exactly():
    grid, values, moments, valid = _random_field(2)
    eps = 1e-9
    pts = np.array([[1.0 - eps, 0.7, 1.3], [1.0 + eps, 0.7, 1.3]])
    nrm = np.array([[0.2, -0.9, 0.4]] * 2)
    w = probe_weights(grid, pts, valid=valid, normals=nrm, moments=moments)
    f = blend(values, w)
    np.testing.assert_allclose(f[0], f[1], atol=1e-6)
    # the two points lie in different cells: different corner sets, same blended result
    assert not np.array_equal(w.indices[0], w.indices[1])


# ------------------------------------------------------------------------------ clamping
def test_outside_points_are_clamped_and_flagged(field):
    pts = np.array([[-1.0, 0.5, 0.5], [3.0, 2.0, -4.0], [1.0, 0.5, 1.0]])
    valid = np.asarray(field.store.arrays["valid"], bool)
    w = probe_weights(field.grid, pts, valid=valid)  # the default: clamped onto the box
    assert w.outside.tolist() == [True, True, False]
    np.testing.assert_array_equal(w.points, [[0.0, 0.5, 0.5], [2.0, 1.0, 0.0], [1.0, 0.5, 1.0]])
    inside = probe_weights(field.grid, w.points, valid=valid)
    np.testing.assert_array_equal(w.weights, inside.weights)
    np.testing.assert_allclose(field.sh(w, kind="raw"), linear_values("sh", (9, 3), w.points),
                               atol=1e-12)


def test_queries_extrapolate_a_quarter_cell_beyond_the_box(field):
    """SH varying linearly in space: a point up to a quarter cell outside the probes' box gets
    the exact extrapolated SH (clamping gives the box face's); farther out, the SH a quarter
    cell out (the grid's cells are 1 wide)."""
    pts = np.array([[-0.2, 0.5, 0.5], [2.1, 1.15, -0.25], [-1.0, 0.5, 0.5], [3.0, 2.0, -4.0],
                    [1.0, 0.5, 1.0]])
    w = field.weights(pts)
    assert w.outside.tolist() == [True, True, True, True, False]
    np.testing.assert_allclose(w.points, [[-0.2, 0.5, 0.5], [2.1, 1.15, -0.25],
                                          [-0.25, 0.5, 0.5], [2.25, 1.25, -0.25], [1.0, 0.5, 1.0]],
                               atol=1e-15)
    assert (w.weights < 0).any()
    np.testing.assert_allclose(w.weights.sum(axis=1), 1.0, atol=1e-12)
    exact = linear_values("sh", (9, 3), w.points)
    np.testing.assert_allclose(field.sh(w, kind="raw"), exact, atol=1e-12)
    clamped = probe_weights(field.grid, pts[:2],
                            valid=np.asarray(field.store.arrays["valid"], bool))
    assert np.abs(field.sh(clamped, kind="raw") - exact[:2]).max() > 1e-3
    rng = np.random.default_rng(5)
    more = rng.uniform(-0.6, 2.6, (64, 3)) * [1.0, 0.5, 1.0]
    many = field.weights(more, normals=rng.normal(size=(64, 3)))
    for i, q in enumerate(np.concatenate([pts, more])):  # the single-point path: the same
        one = field.weights(q) if i < len(pts) else field.weights(q, normals=None)
        ref = w if i < len(pts) else field.weights(more)
        k = i if i < len(pts) else i - len(pts)
        np.testing.assert_allclose(one.weights, ref.weights[k:k + 1], atol=1e-14)
        np.testing.assert_allclose(one.points, ref.points[k:k + 1], atol=1e-14)
    np.testing.assert_allclose(many.weights, field.weights(more).weights, atol=1e-14)
    # the maps' blend clamps onto the box
    _, wm, used = field.cube_at(pts[0], "diffuse", method="blend")
    assert used == "blend"
    np.testing.assert_array_equal(wm.points, [[0.0, 0.5, 0.5]])
    assert (wm.weights >= 0).all()


# ------------------------------------------------------------------------------ lookups
def test_probe_lookup_is_the_seamless_cube_sampler():
    rng = np.random.default_rng(3)
    cubes = rng.normal(size=(4, 6, 5, 5, 2)).astype(np.float32)
    d = rng.normal(size=(600, 3))
    d[:100] = np.sign(d[:100])  # cube corners
    d[100:200, 0] = np.sign(d[100:200, 0]) * np.abs(d[100:200, 1])  # face edges
    probes = rng.integers(0, 4, size=600)
    got = _probe_bilinear(cubes, probes, d)
    for p in range(4):
        sel = probes == p
        want = CubeSampler(cubes[p]).bilinear(d[sel])
        np.testing.assert_allclose(got[sel], want, rtol=1e-5, atol=1e-5)


def test_blend_lookup_equals_lookup_of_the_blended_cube(field):
    pts = _inside(12, seed=4)
    w = field.weights(pts, normals=np.tile([0.0, 1.0, 0.0], (12, 1)))
    rng = np.random.default_rng(4)
    d = rng.normal(size=(12, 3))
    lod = rng.uniform(0, 3, size=12)
    levels = [field.store.arrays[f"specular_{k}"] for k in range(4)]
    got = blend_lookup(levels, w, d, lod=lod)
    blended = [field.cube(w, "specular", level=k) for k in range(4)]
    for i in range(12):
        want = CubeSampler([lv[i] for lv in blended]).trilinear(d[i], lod[i])
        np.testing.assert_allclose(got[i], want, rtol=1e-5, atol=1e-4)


def test_shade_equals_split_sum_on_the_blended_maps(field):
    n = 6
    rng = np.random.default_rng(5)
    pts = _inside(n, seed=5)
    nrm = rng.normal(size=(n, 3))
    views = rng.normal(size=(n, 3))
    albedo = rng.uniform(0, 1, size=(n, 3))
    f0 = np.array([0.04, 0.04, 0.04])
    rough = rng.uniform(0, 1, size=n)
    lut = dfg_lut(16, samples=8)
    rgb, _ = field.shade(pts, nrm, views, albedo=albedo, roughness=rough, f0=f0, dfg=lut)
    assert rgb.shape == (n, 3) and rgb.dtype == np.float32
    for i in range(n):
        wi = field.weights(pts[i], normals=nrm[i])
        spec = [field.cube(wi, "specular", level=k)[0] for k in range(4)]
        want = shade_split_sum(nrm[i], views[i], albedo=albedo[i], roughness=rough[i], f0=f0,
                               diffuse=field.cube(wi, "diffuse")[0], specular_levels=spec, dfg=lut)
        np.testing.assert_allclose(rgb[i], want, rtol=2e-5, atol=2e-4)


# ------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"points": [[np.nan, 0.0, 0.0]]}, "finite"),
        ({"points": [[np.inf, 0.0, 0.0]]}, "finite"),
        ({"points": [[0.0, 0.0]]}, "shape"),
        ({"points": [[0.0, 0.0, 0.0]], "normals": [[0.0, 0.0, 0.0]]}, "non-zero"),
        ({"points": [[0.0, 0.0, 0.0]], "normals": [[1.0, 0.0, 0.0]] * 2}, "one row per point"),
        ({"points": [[0.0, 0.0, 0.0]], "normal_bias": -1.0}, "normal_bias"),
    ],
)
def test_bad_arguments_raise_value_error(kwargs, match):
    with pytest.raises(ValueError, match=match):
        probe_weights(GRID, **kwargs)


def test_bad_kind_and_level_raise_value_error(field):
    w = field.weights([0.5, 0.5, 0.5])
    with pytest.raises(ValueError, match="0..3"):
        field.cube(w, "specular", level=4)
    with pytest.raises(ValueError, match="no 'phong' maps"):
        field.cube(w, "phong")  # type: ignore[arg-type]


def test_huge_normals_and_points_stay_finite(field):
    w = field.weights([[1e300, -1e300, 0.5]], normals=[[1e300, 1e300, 0.0]])
    assert w.outside[0] and np.isfinite(w.weights).all()
    assert w.weights.sum() == pytest.approx(1.0)


def test_many_points_are_chunked_with_identical_results():
    grid, _, moments, valid = _random_field(6)
    rng = np.random.default_rng(6)
    n = 9000  # more than one chunk of points
    pts = rng.uniform(-0.2, 2.2, size=(n, 3))
    nrm = rng.normal(size=(n, 3))
    w = probe_weights(grid, pts, valid=valid, normals=nrm, moments=moments)
    assert w.weights.shape == (n, 8) and w.outside.shape == (n,)
    some = np.r_[0:5, 8190:8196, n - 5:n]
    part = probe_weights(grid, pts[some], valid=valid, normals=nrm[some], moments=moments)
    np.testing.assert_array_equal(w.weights[some], part.weights)
    np.testing.assert_array_equal(w.indices[some], part.indices)
    empty = probe_weights(grid, np.zeros((0, 3)))
    assert empty.weights.shape == (0, 8) and len(empty) == 0


def test_moments_of_the_wrong_shape_raise_value_error():
    with pytest.raises(ValueError, match=r"\(P, 6, m, m, 2\)"):
        probe_weights(LINE, [[0.5, 0.0, 0.0]], normals=[[1.0, 0.0, 0.0]],
                      moments=np.zeros((2, 6, 2, 3, 2)))


def test_bordered_cubes_lookup_matches_the_seamless_filter():
    from probegrid.core.ddgi import BorderedCubes, _probe_bilinear

    rng = np.random.default_rng(5)
    cubes = rng.random((7, 6, 4, 4, 2)).astype(np.float32)
    probes = rng.integers(0, 7, 5000)
    dirs = rng.normal(size=(5000, 3))
    dirs[:8] = [[1, 1, 1], [-1, 1, 1], [1, -1, 1], [1, 1, -1], [1, 0, 0], [0, 1e-9, 1],
                [1, 1, 0], [0, -1, 1]]  # corners, centres and edges
    expected = _probe_bilinear(cubes, probes, dirs)
    got = BorderedCubes(cubes).lookup(probes, dirs)
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6)


# ------------------------------------------------------------------------------ one point
SCALAR_GRIDS = [
    GRID,
    GridSpec.from_counts((-1.5, 0.2, -3.0), (2.25, 0.2, 5.0), (3, 1, 5)),
    GridSpec.from_counts((0.1, 0.2, 0.3), (0.7, 1.9, 3.3), (2, 7, 1)),
    GridSpec.from_counts((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (1, 1, 1)),
]


def _edge_points(grid: GridSpec, n: int, seed: int) -> np.ndarray:
    """Random points in and around the box, plus probes, box corners, faces and -0.0."""
    rng = np.random.default_rng(seed)
    lo, hi = grid.lo, grid.hi
    pts = lo - 1.0 + rng.random((n, 3)) * (hi - lo + 2.0)
    pts[:40] = grid.positions()[rng.integers(0, grid.n_probes, 40)]
    pts[40:60] = np.where(rng.random((20, 3)) < 0.5, lo, hi)
    pts[60:70, 0] = -0.0
    pts[70:80] = [1e300, -1e300, 0.5]
    return pts


@pytest.mark.parametrize("grid", SCALAR_GRIDS, ids=[g.label for g in SCALAR_GRIDS])
def test_one_point_scalar_path_equals_the_vectorised_one(grid):
    """probe_weights of a single point (pure-Python path) gives the vectorised path's indices,
    weights, clamped point and flags exactly (equal floats; a zero may differ in sign)."""
    pts = _edge_points(grid, 600, seed=grid.n_probes)
    rng = np.random.default_rng(1)
    for valid in (None, rng.random(grid.n_probes) < 0.6):
        many = probe_weights(grid, pts, valid=valid)
        for k, p in enumerate(pts):
            one = probe_weights(grid, p, valid=valid)
            for name in ("indices", "weights", "points", "outside", "unlit"):
                np.testing.assert_array_equal(getattr(one, name)[0], getattr(many, name)[k],
                                              err_msg=f"{name} at {p}")
        idx, w, out = grid.corners(pts)
        for k, p in enumerate(pts[:100]):
            i1, w1, o1 = grid.point_corners(*p.tolist())
            assert i1 == idx[k].tolist() and w1 == w[k].tolist() and o1 == out[k]


@pytest.mark.parametrize("grid", SCALAR_GRIDS, ids=[g.label for g in SCALAR_GRIDS])
def test_one_point_with_a_normal_scalar_path_equals_the_vectorised_one(grid):
    """With a normal (and no moments: the exact segment test replaces them), the single-point
    path gives the vectorised path's indices and flags exactly and its weights to rounding,
    with moved probes and invalid ones."""
    pts = _edge_points(grid, 300, seed=grid.n_probes + 1)[:80]
    pts = np.clip(pts, -1e6, 1e6)
    rng = np.random.default_rng(2)
    normals = rng.normal(size=(len(pts), 3))
    moved = grid.positions() + rng.normal(scale=0.1, size=(grid.n_probes, 3))
    for valid, pos in ((None, None), (rng.random(grid.n_probes) < 0.6, moved)):
        many = probe_weights(grid, pts, valid=valid, normals=normals, probe_positions=pos)
        for k, p in enumerate(pts):
            one = probe_weights(grid, p, valid=valid, normals=normals[k], probe_positions=pos)
            np.testing.assert_array_equal(one.indices[0], many.indices[k])
            np.testing.assert_array_equal(one.unlit[0], many.unlit[k])
            np.testing.assert_allclose(one.weights[0], many.weights[k], rtol=1e-12, atol=1e-300)


def test_blend_of_a_batch_equals_the_blend_of_each_point(field):
    pts = _edge_points(GRID, 100, seed=3)
    w = field.weights(pts)
    batch_sh, batch_cube = field.sh(w), field.cube(w, "specular", level=1)
    for k, p in enumerate(pts):
        one = field.weights(p)
        np.testing.assert_array_equal(field.sh(one)[0], batch_sh[k])
        np.testing.assert_array_equal(field.cube(one, "specular", level=1)[0], batch_cube[k])


def test_a_query_normal_does_not_reweight_toward_the_probes_it_faces(field):
    """SH varying linearly in space (the light the probes in front of the surface see differs
    from the light behind): DDGI's normal-facing term moves the blend toward the probes the
    normal faces, off the exact value; the query's weights with a normal keep the trilinear
    blend (the normal only biases the visibility test), which is exact."""
    pts = np.array([[0.5, 0.5, 0.5], [1.3, 0.2, 1.7]])
    nrm = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 1.0]])
    exact = linear_values("sh", (9, 3), pts)
    with_n = field.weights(pts, normals=nrm)
    np.testing.assert_allclose(field.sh(with_n, kind="raw"), exact, atol=1e-12)
    np.testing.assert_allclose(with_n.weights, field.weights(pts).weights, atol=1e-15)
    one = field.weights(pts[0], normals=nrm[0])  # the single-point path
    np.testing.assert_allclose(one.weights, with_n.weights[:1], atol=1e-15)
    valid = np.asarray(field.store.arrays["valid"], bool)
    ddgi = probe_weights(field.grid, pts, valid=valid, normals=nrm, facing=True)
    assert np.abs(field.sh(ddgi, kind="raw") - exact).max() > 1e-2


def test_extrapolation_with_an_invalid_or_hidden_probe_keeps_weights_non_negative():
    """A negative extrapolation weight needs every probe it reads: with an invalid probe in
    the extrapolation the point is clamped; with a hidden one (segment test) the positive part
    of the weights is kept, renormalised."""
    grid = GridSpec.from_counts((0.0, 0.0, 0.0), (2.0, 1.0, 1.0), (3, 2, 2))
    p = np.array([[-0.2, 0.5, 0.5]])  # outside on -x: probes at x = 1 get negative weights
    free = probe_weights(grid, p, extrapolate=0.25)
    np.testing.assert_allclose(free.weights.sum(), 1.0)
    neg = free.weights[0] < 0
    assert neg.sum() == 4
    xyz = grid.positions()
    valid = np.ones(len(xyz), bool)
    valid[free.indices[0][neg][0]] = False
    w = probe_weights(grid, p, valid=valid, extrapolate=0.25)
    np.testing.assert_array_equal(w.weights, probe_weights(grid, p, valid=valid).weights)
    np.testing.assert_array_equal(w.points, [[0.0, 0.5, 0.5]])
    hide = free.indices[0][neg][0]

    def occluded(starts, ends):
        return np.all(np.isclose(ends, xyz[hide]), axis=1)

    for pts in (p, np.repeat(p, 2, axis=0)):  # the single-point and the vectorised paths
        h = probe_weights(grid, pts, extrapolate=0.25, occluded=occluded)
        assert (h.weights >= 0).all()
        np.testing.assert_allclose(h.weights.sum(axis=1), 1.0)
        expect = np.maximum(free.weights[0], 0.0)
        expect[free.indices[0] == hide] = 0.0
        np.testing.assert_allclose(h.weights[0], expect / expect.sum(), atol=1e-15)
