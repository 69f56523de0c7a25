"""The surface light cache (probegrid.bake.surfacecache) and the traced answer's presets.

The lattice lookup reproduces light linear over a triangle exactly; a furnace box (every wall
emitting ``Le`` with albedo ``rho``) has the analytic cache ``rho Le / (1 - rho)`` (light
reflected at least once) and ``Le`` (the emitters' direct light) at every vertex, and a probe
traced anywhere inside reads ``Le / (1 - rho)`` whichever preset answers; a panel room's traced
point agrees with a probe baked there (the cache against the bake's own gather). Then the
presets through ``ProbeField``, the service (422 on a bad value) and the client, and the
incoming cube traced for a store that keeps none.
"""

from __future__ import annotations

import asyncio
import io

import httpx
import numpy as np
import pytest

from probegrid.bake import BakeSettings, bake
from probegrid.bake.environment import Environment
from probegrid.bake.kernels.surfacecache import cache_lookup
from probegrid.bake.point import POINT_PRESETS, PointSettings, PointTracer
from probegrid.bake.surfacecache import (
    INSET,
    LATTICE_EXTRA,
    LIGHT_EXTRA,
    lattice_counts,
    lattice_layout,
    lattice_positions,
    lattice_resolutions,
)
from probegrid.core.grid import GridSpec
from probegrid.query import ProbeField
from probegrid.scene import SceneBuilder, Material, box_scene
from test_point_maps import room_store  # noqa: F401  (the sample room, its glTF kept)

FAST = {"face_size": 8, "diffuse_size": 4, "moments_size": 4, "batch_size": 4}


def _two_triangles(double: bool):
    b = SceneBuilder()
    m = b.add_material(Material(base_color=(0.5, 0.5, 0.5), double_sided=double))
    b.add_quad((0.0, 0.0, 0.0), (2.0, 0.0, 0.0), (0.0, 0.0, 1.0), material=m)
    return b.build()


@pytest.mark.parametrize("double", [False, True])
def test_the_lattice_reads_light_linear_over_a_triangle_exactly(double):
    """Values linear in the position at every lattice vertex come back exactly (to float32)
    anywhere on the triangle, per side; a one-sided triangle's back and a miss read 0."""
    scene = _two_triangles(double)
    res = lattice_resolutions(scene, 200)
    assert res is not None and res.min() >= 1
    lattice = lattice_layout(scene, res)
    pos, nrm = lattice_positions(scene, lattice)
    total = int(np.sum(lattice_counts(res) * (1 + double)))
    assert len(pos) == total <= 200
    # front: a linear function of the position; back: another
    front = np.where(np.einsum("vc,c->v", nrm, scene.triangle_normals[0]) > 0, 1.0, 0.0)
    values = np.stack([1.0 + pos @ [0.3, 0.0, 0.7], 5.0 - pos @ [0.1, 0.0, 0.2],
                       2.0 + 0.0 * pos[:, 0], 0.5 + pos @ [1.0, 0.0, 0.0],
                       0.5 + 0.0 * pos[:, 0], 0.5 + 0.0 * pos[:, 0]], axis=1)
    values[:, 3:] *= (1.0 - front)[:, None]  # the back's channels
    values[:, :3] *= front[:, None]
    rng = np.random.default_rng(1)
    k = 500
    prim = rng.integers(0, scene.n_triangles, k)
    u, v = rng.random((2, k))
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    tri = np.asarray(scene.vertices)[np.asarray(scene.triangles)[prim]]
    p = (1 - u - v)[:, None] * tri[:, 0] + u[:, None] * tri[:, 1] + v[:, None] * tri[:, 2]
    # the vertices stand INSET of the way toward the centroid: so does what they give back
    c = tri.mean(axis=1)
    p = c + (1.0 - INSET) * (p - c)
    for side in (1.0, -1.0):  # rays from above the front, then from behind
        dirs = -side * np.asarray(scene.triangle_normals)[prim]
        got = cache_lookup(prim.astype(np.int64), u, v, dirs,
                           np.asarray(scene.triangle_normals, np.float64), lattice,
                           values.astype(np.float32))
        if side > 0:
            expect = np.stack([1.0 + p @ [0.3, 0.0, 0.7], 5.0 - p @ [0.1, 0.0, 0.2],
                               np.full(k, 2.0)], axis=1)
            np.testing.assert_allclose(got[:, :3], expect, rtol=2e-6, atol=2e-6)
            np.testing.assert_array_equal(got[:, 3:], 0.0)
        elif double:
            np.testing.assert_allclose(got[:, 3], 0.5 + p[:, 0], rtol=2e-6)
        else:  # the back of a one-sided triangle: none
            np.testing.assert_array_equal(got, 0.0)
    miss = cache_lookup(np.array([-1]), np.zeros(1), np.zeros(1), np.array([[0.0, -1.0, 0.0]]),
                        np.asarray(scene.triangle_normals, np.float64), lattice,
                        values.astype(np.float32))
    np.testing.assert_array_equal(miss, 0.0)


def test_a_budget_below_one_vertex_per_triangle_side_gives_no_lattice():
    scene = _two_triangles(True)
    assert lattice_resolutions(scene, 3) is None  # 2 triangles, 2 sides each
    res = lattice_resolutions(scene, 4)
    assert res is not None and list(res) == [0, 0]  # the centroids alone
    assert lattice_positions(scene, lattice_layout(scene, res))[0].shape == (4, 3)


@pytest.fixture(scope="module")
def furnace(tmp_path_factory):
    rho, le = 0.5, 2.0
    scene = box_scene((-1, -1, -1), (1, 1, 1), albedo=rho, emission=le, inward=True)
    grid = GridSpec.from_counts((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), (2, 1, 1))
    # (a spacing over the longest edge: one vertex a triangle side, the coarse lattice the
    # direct light's distance rule is tested on)
    store = bake(scene, grid, tmp_path_factory.mktemp("furnace") / "f.probes",
                 settings=BakeSettings(bounces="converge", surface_cache_spacing=4.0,
                                       **FAST)).store
    return scene, store, rho, le


def test_the_furnace_cache_holds_the_reflected_and_the_emitted_light(furnace):
    """Every vertex of a converged furnace box: light reflected at least once
    ``rho Le / (1 - rho)``, the emitters' direct light ``Le`` (irradiance / pi)."""
    scene, store, rho, le = furnace
    assert {LATTICE_EXTRA, LIGHT_EXTRA} <= set(store.manifest.extras)
    light = np.asarray(store[LIGHT_EXTRA], np.float64)
    lattice = np.asarray(store[LATTICE_EXTRA])
    assert lattice.shape == (scene.n_triangles, 3) and light.shape[1:] == (2, 3)
    assert store.manifest.quality["surface_cache_rays"] > 0
    # the gather converges to the grid's limit (to the furnace test's tolerance, 1e-3) with
    # the noise of the direct samples' and gather rays' none: every ray sees the same
    np.testing.assert_allclose(light[:, 0], rho * le / (1 - rho), rtol=2e-3)
    np.testing.assert_allclose(light[:, 1], le, rtol=1e-4)


@pytest.mark.parametrize("quality", list(POINT_PRESETS))
def test_every_preset_reads_the_furnace_limit_anywhere(furnace, quality):
    scene, store, rho, le = furnace
    tracer = PointTracer.from_store(store, scene, settings=PointSettings.preset(quality))
    assert (tracer.cache is not None) == (quality != "reference")
    assert tracer.direct_cached == (quality == "fast")
    maps = tracer.maps(np.array([0.31, -0.62, 0.17]))
    np.testing.assert_allclose(maps.incoming, le / (1 - rho), rtol=2e-3)
    np.testing.assert_allclose(maps.diffuse, le / (1 - rho), rtol=3e-3)


def test_accurate_samples_the_direct_light_where_the_lattice_is_coarser_than_a_texel(furnace):
    """The accurate preset samples the emitters at the hits nearer than ``spacing 2 n / pi``
    (a lattice cell seen larger than a mirror texel) and reads the cache's direct light beyond:
    both give the furnace's ``Le`` (the traced cube above), and the rule is the distance's."""
    scene, store, rho, le = furnace
    tracer = PointTracer.from_store(store, scene)
    tracer.cache.spacing = tracer.cache.spacing / 8  # (a finer lattice: some hits are far)
    p = np.array([0.9, -0.9, 0.9])  # by a corner: near and far walls
    rec, _, _ = tracer.records.trace(p[None], np.array([7]), hits=True)
    front = rec["kind"] == 1
    dist = np.linalg.norm(rec["position"] - p, axis=1)
    reach = tracer.cache.spacing[rec["primitive"]] * 8 * 2 / np.pi
    sampled = rec["sampled"]
    assert 0 < sampled[front].mean() < 1
    clear = front & (np.abs(dist - reach) > 1e-6 * reach)
    np.testing.assert_array_equal(sampled[clear], dist[clear] < reach[clear])
    np.testing.assert_allclose(tracer.maps(p).incoming, le / (1 - rho), rtol=2e-3)


def test_the_presets_are_checked():
    with pytest.raises(ValueError, match="quality must be one of accurate, fast, reference"):
        PointSettings.preset("best")
    assert PointSettings.preset("fast").direct == "cache"
    assert PointSettings.preset("reference").indirect == "gather"


def test_a_store_without_a_cache_gathers_and_fast_lowers_the_gather(furnace, tmp_path):
    import json
    import shutil

    scene, store, rho, le = furnace
    copy = tmp_path / "old.probes"
    shutil.copytree(store.path, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    del manifest["extras"][LATTICE_EXTRA], manifest["extras"][LIGHT_EXTRA]
    (copy / "manifest.json").write_text(json.dumps(manifest))
    from probegrid.store import open_store

    old = open_store(copy)
    accurate = PointTracer.from_store(old, scene)
    assert accurate.cache is None and accurate.records.gather_samples == 2
    fast = PointTracer.from_store(old, scene, settings=PointSettings.preset("fast"))
    assert fast.cache is None and fast.records.gather_samples == 1
    assert fast.records.gather_depth == 1 and fast.records.light_samples == 1
    with pytest.raises(ValueError, match="keeps no surface cache"):
        PointTracer.from_store(old, scene, settings=PointSettings(indirect="cache"))


def test_threads_do_not_change_a_traced_point(furnace):
    """The rays shaded on two threads, in two chunks: each ray's record is its own."""
    from probegrid.bake.records import tracer as rt

    scene, store, _, _ = furnace
    one = PointTracer.from_store(store, scene, threads=1)
    two = PointTracer.from_store(store, scene, threads=2)
    p = np.array([0.1, 0.2, -0.3])
    old = rt.MIN_SPLIT
    rt.MIN_SPLIT = 16  # (the cubes of faces 8 are 384 rays)
    try:
        np.testing.assert_array_equal(two.incoming(p[None]), one.incoming(p[None]))
    finally:
        rt.MIN_SPLIT = old


# ------------------------------------------------------------------------------ the service
def test_the_service_answers_each_preset_and_refuses_a_bad_one(room_store):
    from service.main import create_app

    app = create_app([room_store.path])
    point = {"x": "0.1", "y": "1.2", "z": "-0.3"}
    field = ProbeField(room_store)
    assert "incoming" in field.kinds and "incoming" not in room_store.names
    p = np.array([0.1, 1.2, -0.3])

    async def fetch():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            url = "/v1/grids/room/maps/"
            return [await c.get(url + "diffuse", params={**point, "quality": q})
                    for q in ("fast", "reference")] + [
                await c.get(url + "diffuse", params=point),
                await c.get(url + "diffuse", params={**point, "quality": "best"}),
                await c.get(url + "diffuse", params={**point, "quality": ""}),
                await c.get(url + "incoming", params=point),
                await c.get(url + "incoming", params={**point, "method": "blend"}),
                await c.get(url + "incoming", params={**point, "level": "1"})]

    fast, ref, default, bad, empty, incoming, blend_in, level_in = asyncio.run(fetch())
    for r, q in ((fast, "fast"), (ref, "reference"), (default, "accurate")):
        assert r.status_code == 200 and r.headers["x-probegrid-quality"] == q
        np.testing.assert_array_equal(np.load(io.BytesIO(r.content)),
                                      field.point_maps(p, quality=q).diffuse)
    assert bad.status_code == 422 and "quality" in bad.text
    assert empty.status_code == 422
    assert incoming.status_code == 200
    np.testing.assert_array_equal(np.load(io.BytesIO(incoming.content)),
                                  field.point_maps(p, quality="accurate").incoming)
    assert blend_in.status_code == 422 and "traced" in blend_in.json()["message"]
    assert level_in.status_code == 422


def test_the_client_passes_the_quality_through():
    from probegrid.client import ProbeGridClient
    from probegrid.errors import ProbegridError

    call = ProbeGridClient._map_call("g", (0.0, 1.0, 2.0), None, "diffuse", 0, "trace", "fast")
    assert call.params["quality"] == "fast"
    assert "quality" not in ProbeGridClient._map_call("g", (0.0, 1.0, 2.0), None, "diffuse",
                                                      0).params
    with pytest.raises(ProbegridError, match="quality must be one of"):
        ProbeGridClient._map_call("g", (0.0, 1.0, 2.0), None, "diffuse", 0, "trace", "best")


def test_the_lattice_is_the_scenes_whatever_the_grid(tmp_path):
    """The same closed room baked with 2 probes inside, then with those 2 and 10 more outside
    its walls: the cache's lattice is the same (the scene's and the faces' alone; it followed
    the probe count) and so is its light (the probes outside, behind the walls, are not read
    at the gathers' deepest hits inside)."""
    from probegrid.core.lights import PointLight

    scene = box_scene((-2, 0, -2), (2, 3, 2), albedo=0.5, emission=0.0, inward=True,
                      lights=(PointLight((0.3, 2.0, 0.2), (1.0, 0.9, 0.8), 20.0),))
    inner = GridSpec.from_counts((-1.0, 1.5, 0.0), (1.0, 1.5, 0.0), (2, 1, 1))
    # x = -3, -1, 1, 3 and y = -1.5, 1.5, 4.5: all but the two inner probes outside
    outer = GridSpec.from_counts((-3.0, -1.5, 0.0), (3.0, 4.5, 0.0), (4, 3, 1))
    st = BakeSettings(bounces=2, relocate=False, sh_field=0, **FAST)
    alone = bake(scene, inner, tmp_path / "alone.probes", settings=st).store
    ext = bake(scene, outer, tmp_path / "ext.probes", settings=st).store
    np.testing.assert_array_equal(ext[LATTICE_EXTRA], alone[LATTICE_EXTRA])
    plan = alone.manifest.quality["surface_cache"]
    assert plan == ext.manifest.quality["surface_cache"]
    res = np.asarray(alone[LATTICE_EXTRA])[:, 2]
    # the default: 8 vertices a texel of a face of 8^2 beyond one a side (12 triangles)
    assert 12 + 8 * 64 - 2 * 12 < int(np.sum(lattice_counts(res))) <= 12 + 8 * 64
    assert plan["vertices"] == int(np.sum(lattice_counts(res)))
    assert "whatever the grid" in plan["reason"]
    a = np.asarray(alone[LIGHT_EXTRA], np.float64)
    b = np.asarray(ext[LIGHT_EXTRA], np.float64)
    np.testing.assert_array_equal(b[:, 1], a[:, 1])  # the direct light: the scene's alone
    # (measured 1.4e-5: the deepest hits' reads weigh the probes outside ~0)
    assert np.abs(b[:, 0] - a[:, 0]).sum() <= 1e-4 * np.abs(a[:, 0]).sum()


def test_the_spacing_option_and_the_cap(monkeypatch):
    """``surface_cache_spacing``: that spacing (a triangle's resolution its longest edge over
    it), 0 none; finer than :data:`MAX_VERTICES` allows, coarsened to fit; the manifest's
    entry says which and why."""
    from probegrid.bake import surfacecache as sc

    scene = box_scene((0, 0, 0), (4, 2, 2), albedo=0.5)  # longest edges 4.47 and 2.83
    p = sc.plan_lattice(scene, 0.5)
    assert sorted(set(p.resolutions.tolist())) == [5, 8]
    assert p.vertices == int(np.sum(lattice_counts(p.resolutions)))
    assert p.manifest()["reason"] == "surface_cache_spacing 0.5" and p.spacing == 0.5
    none = sc.plan_lattice(scene, 0.0)
    assert none.resolutions is None and none.vertices == 0
    monkeypatch.setattr(sc, "MAX_VERTICES", 200)
    capped = sc.plan_lattice(scene, 0.01)
    assert capped.vertices <= 200 < sc.plan_lattice(scene, 0.5).vertices + 100
    assert "coarsened to at most 200 vertices" in capped.reason and capped.spacing > 0.5 / 2
    with pytest.raises(ValueError):
        BakeSettings(surface_cache_spacing=-1.0)


def test_each_vertex_gathers_its_reflected_light_to_a_few_percent(tmp_path, monkeypatch):
    """A room lit by a small bright panel (the light reflected at least once comes from a few
    bright patches): the cache's reflected light at its vertices is within 3 % (median) of
    the same vertices gathered with 4x more rays (:data:`CACHE_GATHER`: 2.4 % here, 3.7 %
    with the former 8 x 8 strata; on the Cornell box 3.5 % against 7 % of a 1024-ray gather),
    whose noise a point traced a few centimetres off a wall sees as patches of its rough GGX
    levels."""
    import probegrid.bake.surfacecache as sc
    from probegrid.bake.settings import TraceGeometry

    b = SceneBuilder()
    wall = b.add_material(Material(base_color=(0.6, 0.6, 0.6)))
    lamp = b.add_material(Material(base_color=(0.0, 0.0, 0.0), emissive=(40.0, 40.0, 40.0)))
    b.add_box((-1.0, 0.0, -0.5), (1.0, 1.0, 0.5), material=wall, inward=True)
    b.add_box((-0.3, 0.0, -0.2), (0.1, 0.4, 0.2), material=wall)
    b.add_quad((0.45, 0.97, -0.1), (0.2, 0, 0), (0, 0, 0.2), material=lamp)
    scene = b.build()
    store = bake(scene, GridSpec.from_counts((-0.6, 0.6, 0.0), (0.6, 0.6, 0.0), (2, 1, 1)),
                 tmp_path / "p.probes", settings=BakeSettings(bounces=4, **FAST)).store
    light = np.asarray(store[LIGHT_EXTRA], np.float64)
    tracer = PointTracer.from_store(store, scene)
    baked = BakeSettings.model_validate(store.manifest.bake["settings"])
    rd = store.manifest.bake["render"]
    geometry = TraceGeometry(ray_offset=rd["ray_offset"], max_distance=rd["max_distance"])
    monkeypatch.setattr(sc, "CACHE_GATHER", 4 * sc.CACHE_GATHER)
    lattice, dense, _ = sc.bake_surface_cache(scene, Environment(), baked, geometry,
                                              tracer.data, level=tracer.level)
    np.testing.assert_array_equal(lattice, store[LATTICE_EXTRA])
    got, ref = light[:, 0].mean(axis=1), dense[:, 0].astype(np.float64).mean(axis=1)
    lit = ref > 1e-3 * ref.max()
    assert lit.mean() > 0.5
    err = np.abs(got[lit] / ref[lit] - 1.0)
    assert np.median(err) < 0.03, np.median(err)


def test_threads_and_chunks_do_not_change_the_cache(furnace, monkeypatch):
    """A lit panel over a floor (light that varies over the lattice) gathered against the
    furnace's grid: its vertices shaded in one chunk on one thread, or in chunks of 37 on two,
    give the same bits and rays."""
    from probegrid.bake import surfacecache as sc
    from probegrid.bake.environment import Environment
    from probegrid.bake.records import GridData
    from probegrid.bake.settings import TraceGeometry

    _, store, _, _ = furnace
    b = SceneBuilder()
    lamp = b.add_material(Material(base_color=(0.5, 0.5, 0.5, 1.0), emissive=(3.0, 2.0, 1.0)))
    grey = b.add_material(Material.diffuse(0.5))
    b.add_quad((-0.3, 0.9, -0.3), (0.6, 0, 0), (0, 0, 0.6), material=lamp)  # faces -Y
    b.add_quad((-1, -0.9, -1), (0, 0, 2), (2, 0, 0), material=grey)  # the floor, faces +Y
    b.add_quad((-1, -0.9, -1), (2, 0, 0), (0, 1.8, 0), material=grey)  # a wall, faces +Z
    scene = b.build()
    mom = np.asarray(store["moments_bordered"])
    cubes = np.asarray(store["grid_irradiance"])
    data = GridData(store.grid, np.asarray(store["valid"], bool),
                    np.asarray(store["positions"], np.float64), mom.reshape(-1, mom.shape[-1]),
                    mom.shape[2] - 2, cubes.reshape(-1, 3))
    geometry = TraceGeometry(ray_offset=1e-4, max_distance=100.0)

    def cache(threads: int, chunk: int):
        monkeypatch.setattr(sc, "THREADS", threads)
        monkeypatch.setattr(sc, "CHUNK", chunk)
        got = sc.bake_surface_cache(scene, Environment(), BakeSettings(**FAST), geometry, data,
                                    level=2, plan=sc.plan_lattice(scene, 0.15))
        assert got is not None
        return got

    lattice, one, rays = cache(1, 4096)
    lattice2, two, rays2 = cache(2, 37)
    assert len(one) > 4 * 37 and rays2 == rays
    assert one[:, 0].std() > 0.05 * one[:, 0].mean() > 0  # (the light varies)
    np.testing.assert_array_equal(lattice2, lattice)
    np.testing.assert_array_equal(two, one)
