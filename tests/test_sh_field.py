"""The SH field (``probegrid.bake.shfield``): what ``/sh`` interpolates near walls.

* Analytic: a store whose probes and SH field hold the same SH, affine (or quadratic) in the
  position. Between the outermost probes and the walls (more than a quarter cell outside the
  probes' box) the probes' blend is clamped; the field reaches the walls, so it reproduces an
  affine field exactly and a quadratic one within trilinear interpolation's bound
  (``h^2 / 8 |f''|`` per axis).
* The service: ``/sh`` answers from the field (``source: "field"``, lattice points with their
  positions), ``source=probes`` keeps the probes' blend, a bad ``source`` is a 422; the bake's
  options refuse bad values.
* A real bake (``slow``): the field's lattice is what the bake traced -- SH of probes traced at
  its points (:class:`probegrid.bake.point.PointTracer`, the ground truth generator) with the
  preset the field uses, reading the store's surface cache at the rays' hits -- and at
  points near the walls the field is closer to the SH traced at the point than the probes'
  blend; giving the surface normal never makes a point's answer worse.
"""

from __future__ import annotations

import asyncio
import dataclasses
from pathlib import Path

import httpx
import numpy as np
import pytest
from probe_stores import GRID, linear_arrays

from probegrid.bake.shfield import (
    FIELD_QUALITY,
    SH_FIELD_EXTRAS,
    field_lattice,
    field_settings,
    lattice_from_extra,
)
from probegrid.core.conventions import conventions
from probegrid.core.grid import GridSpec
from probegrid.query import ProbeField
from probegrid.store import ArraySpec, StoreWriter, open_store

#: The cells' box of :data:`probe_stores.GRID` (probes at 0..2 x 0..1 x 0..2, spacing 1).
BOX_LO, BOX_HI = np.array([-0.5, -0.5, -0.5]), np.array([2.5, 1.5, 2.5])


def affine_sh(p: np.ndarray) -> np.ndarray:
    """(n, 9, 3) SH affine in the position (a DC term that stays positive in the box)."""
    c = np.arange(27, dtype=np.float64).reshape(9, 3) / 27.0
    g = np.stack([np.cos(np.arange(27) + a).reshape(9, 3) for a in range(3)])
    return 4.0 + c + np.einsum("ni,i...->n...", p, g)


def quadratic_sh(p: np.ndarray) -> np.ndarray:
    """:func:`affine_sh` plus ``x^2`` in every coefficient (second derivative 2 along x)."""
    return affine_sh(p) + (p[:, 0] ** 2)[:, None, None]


def field_store(path: Path, sh_of, *, refine: float = 2.0,
                valid: np.ndarray | None = None) -> ProbeField:
    """A store of :data:`GRID` whose probes' SH and SH field are ``sh_of(positions)`` (the
    field's points ``valid``, default all)."""
    arrays = linear_arrays(GRID)
    arrays["sh"] = sh_of(GRID.positions()).astype(np.float32)
    specs = {name: ArraySpec(shape=a.shape[1:], dtype=a.dtype.str, description=name)
             for name, a in arrays.items()}
    writer = StoreWriter.create(path, arrays=specs, grid=GRID, conventions=conventions(),
                                scene_hash="synthetic-field", bake={"synthetic": True})
    writer.write(np.arange(GRID.n_probes), arrays)
    writer.add_extra("sh_deringed", arrays["sh"])
    lattice = field_lattice(GRID, refine)
    values = sh_of(lattice.positions()).astype(np.float32)
    writer.add_extra("sh_field_lattice", np.array([lattice.bounds_min, lattice.bounds_max,
                                                   lattice.counts], np.float64))
    writer.add_extra("sh_field", values)
    writer.add_extra("sh_field_raw", values)
    writer.add_extra("sh_field_valid", np.ones(lattice.n_probes, bool) if valid is None
                     else np.asarray(valid, bool))
    writer.finish(quality={"invalid_probes": 0})
    return ProbeField(open_store(path))


def near_wall_points() -> np.ndarray:
    """Points between the outermost probe layers and the walls (0.3 to 0.45 cell outside the
    probes' box, beyond the quarter cell the probes' blend extrapolates), and inside ones."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(BOX_LO + 0.05, BOX_HI - 0.05, (64, 3))
    side = rng.integers(0, 2, 64)
    pts[:, 0] = np.where(side == 0, rng.uniform(-0.45, -0.3, 64), rng.uniform(2.3, 2.45, 64))
    return pts


def test_lattice_reaches_the_walls():
    lattice = field_lattice(GRID, 2.0)
    assert lattice.counts == (7, 5, 7)
    step = (BOX_HI - BOX_LO) / (np.array(lattice.counts) - 1)
    np.testing.assert_allclose(lattice.bounds_min, BOX_LO + 0.1 * step)
    np.testing.assert_allclose(lattice.bounds_max, BOX_HI - 0.1 * step)
    assert lattice_from_extra(np.array([lattice.bounds_min, lattice.bounds_max,
                                        lattice.counts])) == lattice
    assert field_lattice(GridSpec.from_counts((0, 0, 0), (0, 1, 1), (1, 2, 2)), 1.0).counts \
        == (2, 3, 3)
    with pytest.raises(ValueError, match="refine"):
        field_lattice(GRID, 0.0)


def test_field_interpolates_where_the_probes_clamp(tmp_path):
    f = field_store(tmp_path / "affine.probes", affine_sh)
    pts = near_wall_points()
    truth = affine_sh(pts)
    got, w, used = f.sh_at(pts)
    assert used == "field" and w.points.shape == pts.shape
    probes, _, old = f.sh_at(pts, source="probes")
    assert old == "probes"
    scale = np.abs(truth).max()
    # the field is exact for an affine SH (float32 storage), the probes' blend is not
    assert np.abs(got - truth).max() <= 1e-5 * scale
    assert np.abs(probes - truth).max(axis=(1, 2)).min() > 0.005 * scale  # (>= 0.05 x 1)


def test_field_interpolates_a_quadratic_within_the_bound(tmp_path):
    f = field_store(tmp_path / "quad.probes", quadratic_sh)
    lattice = f.sh_field[0]
    pts = near_wall_points()
    truth = quadratic_sh(pts)
    got = f.sh_at(pts)[0]
    probes = f.sh_at(pts, source="probes")[0]
    hx = lattice.spacing[0]
    bound = hx**2 / 8 * 2.0  # trilinear interpolation of x^2: at most h^2/8 |f''|
    err = np.abs(got - truth).max(axis=(1, 2))
    old = np.abs(probes - truth).max(axis=(1, 2))
    print(f"\nquadratic SH near walls: field worst {err.max():.4f} (bound {bound:.4f}), "
          f"probes' blend worst {old.max():.4f}, median {np.median(old):.4f}")
    assert err.max() <= bound * (1 + 1e-5) + 1e-5
    assert np.median(old) > 4 * bound


def get_all(store: Path, *urls: str) -> list[httpx.Response]:
    """GET ``urls`` from the service's app serving ``store`` (in process)."""
    from service.main import create_app

    app = create_app([store])

    async def fetch() -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            return [await c.get(u) for u in urls]

    return asyncio.run(fetch())


def test_service_answers_from_the_field(tmp_path):
    field_store(tmp_path / "g.probes", affine_sh)
    p = (2.4, 0.5, 1.0)
    at = "/v1/grids/g/sh?x=2.4&y=0.5&z=1.0"
    # (the last: a query string FastAPI decodes, past the fast path)
    doc, old, bad, bad_slow = get_all(tmp_path / "g.probes", at, at + "&source=probes",
                                      at + "&source=lattice", at + "&source=%6Cattice")
    doc, old = doc.json(), old.json()
    assert doc["source"] == "field" and doc["sh_source"] == "store"
    np.testing.assert_allclose(doc["coefficients"], affine_sh(np.array([p]))[0], rtol=1e-5)
    lattice = field_lattice(GRID, 2.0)
    for u in doc["probes"]:
        assert u["position"] == pytest.approx(lattice.positions()[u["index"]].tolist())
    assert abs(sum(u["weight"] for u in doc["probes"]) - 1) < 1e-9
    assert old["source"] == "probes" and old["flags"]["outside"]
    assert all(u.get("position") is None for u in old["probes"])
    for r in (bad, bad_slow):
        assert r.status_code == 422 and "source" in r.text


def test_a_store_without_the_field_answers_with_the_probes(tmp_path):
    from probe_stores import linear_store

    f = ProbeField(linear_store(tmp_path / "lin.probes"))
    assert f.sh_field is None
    c, w, used = f.sh_at([[0.5, 0.5, 0.5]])
    assert used == "probes"
    np.testing.assert_array_equal(c, f.sh(f.weights([[0.5, 0.5, 0.5]])))
    with pytest.raises(ValueError, match="source"):
        f.sh_at([[0.5, 0.5, 0.5]], source="lattice")


def test_bake_options_are_checked():
    from pydantic import ValidationError

    from probegrid.bake import BakeSettings

    for bad in ({"sh_field": -1}, {"sh_field": 5}, {"sh_field_face_size": 1},
                {"sh_field": float("nan")}):
        with pytest.raises(ValidationError):
            BakeSettings(**bad)
    assert BakeSettings().sh_field == 2 and BakeSettings().sh_field_face_size == 8


# ---------------------------------------------------------------------------- a real bake
@pytest.fixture(scope="module")
def baked(tmp_path_factory, real_data):
    """The CornellBox, 2 x 2 x 2 probes, one bounce, with its SH field and no surface cache
    (``surface_cache_spacing=0``); the scene too."""
    return _bake_cornell(tmp_path_factory, real_data, face_size=8, surface_cache_spacing=0.0)


@pytest.fixture(scope="module")
def baked_cached(tmp_path_factory, real_data):
    """:func:`baked` at faces 16 with the default surface cache."""
    return _bake_cornell(tmp_path_factory, real_data, face_size=16)


def _bake_cornell(tmp_path_factory, real_data, *, face_size: int,
                  surface_cache_spacing: float | None = None):
    from probegrid.bake import BakeSettings, bake
    from probegrid.bake.placement import grid_for
    from probegrid.scene import load_gltf

    glb = real_data / "gltf" / "CornellBox.glb"
    scene = load_gltf(glb)
    out = tmp_path_factory.mktemp("field") / "cornell.probes"
    bake(scene, grid_for(scene, grid="2x2x2"), out, scene_file=glb,
         settings=BakeSettings(face_size=face_size, bounces=1, diffuse_size=4,
                               surface_cache_spacing=surface_cache_spacing))
    return ProbeField(open_store(out), scene=scene), scene


def surface_points(scene, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points 1 to 3 % of the box's size off the box's walls (its largest triangles),
    with the walls' normals (into the box)."""
    rng = np.random.default_rng(seed)
    v = np.asarray(scene.vertices, np.float64)[np.asarray(scene.triangles)]
    lo, hi = np.asarray(scene.bounds, np.float64)
    cross = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    walls = area > 0.5 * area.max()
    tri = rng.choice(np.flatnonzero(walls), size=n, p=area[walls] / area[walls].sum())
    a, b = rng.random((2, n, 1))
    flip = (a + b) > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    p = v[tri, 0] + a * (v[tri, 1] - v[tri, 0]) + b * (v[tri, 2] - v[tri, 0])
    nrm = cross[tri] / np.linalg.norm(cross[tri], axis=1, keepdims=True)
    nrm *= np.sign(np.einsum("ni,ni->n", 0.5 * (lo + hi) - p, nrm))[:, None]  # into the box
    return p + nrm * rng.uniform(0.01, 0.03, (n, 1)) * float(np.max(hi - lo)), nrm


def irradiance_error(a: np.ndarray, ref: np.ndarray, n: np.ndarray) -> np.ndarray:
    """``sum |E_a(n) - E_ref(n)| / sum E_ref(n)`` over RGB, per point."""
    from probegrid.core.sh.clampedcosine import irradiance

    ea = np.array([irradiance(a[i], n[i][None])[0] for i in range(len(n))])
    er = np.array([irradiance(ref[i], n[i][None])[0] for i in range(len(n))])
    return np.abs(ea - er).sum(axis=1) / np.abs(er).sum(axis=1)


@pytest.mark.slow
@pytest.mark.parametrize("store", ["baked", "baked_cached"])
def test_baked_field_is_traced_sh_at_its_lattice(store, request):
    from probegrid.bake.point import PointSettings, PointTracer
    from probegrid.core.sh.projection import project_cube

    f, scene = request.getfixturevalue(store)
    assert set(SH_FIELD_EXTRAS) <= set(f.store.manifest.extras)
    lattice, valid, _ = f.sh_field
    assert lattice == field_lattice(f.grid, 2.0) and lattice.counts == (5, 5, 5)
    raw = np.asarray(f.store.arrays["sh_field_raw"])
    some = np.array([0, 31, 62, 124])
    has_cache = {"surface_lattice", "surface_light"} <= set(f.store.manifest.extras)
    assert has_cache == (store == "baked_cached")
    # with a surface cache its points are traced as the service's preset traces a point,
    # the rays' hits reading the cache (no gather); without one, with the bake's gather
    settings = field_settings(has_cache, 8)
    if has_cache:
        assert settings == dataclasses.replace(PointSettings.preset(FIELD_QUALITY), face_size=8)
        assert settings.indirect != "gather"
        # (the bake's gather at every hit gives other numbers: 100x beyond the tolerance of
        # the match below)
        gathered = PointTracer.from_store(f.store, scene, settings=field_settings(False, 8))
        other = np.array([project_cube(c) for c in gathered.incoming(lattice.positions()[some])])
        assert np.abs(other - raw[some]).max() > 1e-3 * np.abs(raw[some]).max()
    else:
        assert settings == PointSettings(indirect="gather", face_size=8)
    tracer = PointTracer.from_store(f.store, scene, settings=settings)
    assert (tracer.cache is not None) == has_cache
    expected = np.array([project_cube(c) for c in tracer.incoming(lattice.positions()[some])])
    np.testing.assert_allclose(raw[some], expected, rtol=1e-5, atol=1e-6 * np.abs(raw).max())
    # the probes' region is stored by the same arrays as before (the field is extras only)
    assert "sh_field" not in f.store.manifest.arrays


@pytest.mark.slow
def test_near_walls_the_field_beats_the_probes_and_the_normal_never_hurts(baked):
    from probegrid.bake.point import PointSettings, PointTracer
    from probegrid.core.sh.projection import project_cube

    f, scene = baked
    pts, nrm = surface_points(scene, 24)
    # the reference: SH of probes traced at the points themselves (finer: face 16)
    tracer = PointTracer.from_store(f.store, scene, settings=PointSettings(face_size=16))
    ref = np.array([project_cube(c) for c in tracer.incoming(pts)])
    field_n = irradiance_error(f.sh_at(pts, normals=nrm)[0], ref, nrm)
    field_0 = irradiance_error(f.sh_at(pts)[0], ref, nrm)
    probes = irradiance_error(f.sh_at(pts, normals=nrm, source="probes")[0], ref, nrm)
    print(f"\nE(n) error near the Cornell box's walls, 2x2x2 probes: probes' blend mean "
          f"{100 * probes.mean():.1f} % worst {100 * probes.max():.1f} %; SH field mean "
          f"{100 * field_n.mean():.1f} % worst {100 * field_n.max():.1f} % (without the normal "
          f"{100 * field_0.mean():.1f} / {100 * field_0.max():.1f} %)")
    assert field_n.mean() < 0.5 * probes.mean()
    assert field_n.max() < probes.max()
    assert np.all(field_n <= field_0 + 1e-9)  # per point: the normal never makes it worse
    # the service's /sh answers the same
    p, n = pts[0].tolist(), nrm[0].tolist()
    doc = get_all(f.store.path, f"/v1/grids/cornell/sh?x={p[0]!r}&y={p[1]!r}&z={p[2]!r}"
                                f"&nx={n[0]!r}&ny={n[1]!r}&nz={n[2]!r}")[0].json()
    assert doc["source"] == "field"
    np.testing.assert_allclose(doc["coefficients"], f.sh_at(p, normals=n)[0][0], rtol=1e-12)
