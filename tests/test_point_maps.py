"""Maps at a point between probes: a probe traced there (probegrid.bake.point) against the blend.

A room lit by one small emissive panel, two probes, a query point between them: the traced
probe sees one panel, of its exact solid angle, in its direction, and agrees with a probe baked
at that point; the blend of the two probes shows two half-bright copies. Then the store's
extras the tracer needs, the fallback of stores without them, the service's ``method`` and the
client's.
"""

from __future__ import annotations

import asyncio
import threading

import httpx
import numpy as np
import pytest

from probegrid.bake import BakeSettings, bake
from probegrid.bake.environment import LIGHT_SIZE, Environment
from probegrid.bake.point import ENVIRONMENT_EXTRA, GRID_EXTRA, PointTracer
from probegrid.core.cubemap import texel_directions, texel_solid_angles
from probegrid.core.grid import GridSpec
from probegrid.core.sampling import resample
from probegrid.query import ProbeField
from probegrid.scene import Material, SceneBuilder, load_gltf
from probegrid.store import open_store

LE = 40.0  # the panel's radiance
PANEL = (0.15, 0.97, 0.0)  # its centre, facing -Y
SIDE = 0.2
POINT = np.array([0.0, 0.45, 0.0])
SETTINGS = {"face_size": 16, "diffuse_size": 4, "moments_size": 4, "bounces": 4,
            "store_incoming": True, "batch_size": 4}


def _panel_room():
    b = SceneBuilder()
    wall = b.add_material(Material(base_color=(0.2, 0.2, 0.2)))
    lamp = b.add_material(Material(base_color=(0.0, 0.0, 0.0), emissive=(LE, LE, LE)))
    b.add_box((-1.0, 0.0, -0.5), (1.0, 1.0, 0.5), material=wall, inward=True)
    x, y, z = PANEL
    b.add_quad((x - SIDE / 2, y, z - SIDE / 2), (SIDE, 0, 0), (0, 0, SIDE), material=lamp)
    return b.build()


def _solid_angle(point, corners) -> float:
    """Exact solid angle of a planar quad seen from ``point`` (two triangles, Van Oosterom and
    Strackee's formula)."""
    total = 0.0
    for tri in ((0, 1, 2), (0, 2, 3)):
        r = [np.asarray(corners[i], float) - point for i in tri]
        n = [np.linalg.norm(v) for v in r]
        num = abs(np.dot(r[0], np.cross(r[1], r[2])))
        den = (n[0] * n[1] * n[2] + np.dot(r[0], r[1]) * n[2] + np.dot(r[0], r[2]) * n[1]
               + np.dot(r[1], r[2]) * n[0])
        total += 2.0 * np.arctan2(num, den)
    return total


def _panel_energy(cube, cone_deg: float, seen_from=POINT):
    """``(energy of the bright texels within the cone around the panel's direction from
    ``seen_from``, of all bright texels)``: bright = radiance over a tenth of the panel's (the
    walls are far darker)."""
    d = texel_directions(cube.shape[1])
    w = texel_solid_angles(cube.shape[1])
    to = np.asarray(PANEL) - np.asarray(seen_from)
    to /= np.linalg.norm(to)
    lum = np.asarray(cube, np.float64)[..., 0]
    bright = lum > 0.1 * LE
    inside = (d @ to) > np.cos(np.radians(cone_deg))
    return float((lum * w)[bright & inside].sum()), float((lum * w)[bright].sum())


@pytest.fixture(scope="module")
def panel_stores(tmp_path_factory):
    root = tmp_path_factory.mktemp("panel")
    scene = _panel_room()
    st = BakeSettings(**SETTINGS)
    two = bake(scene, GridSpec.from_counts((-0.6, 0.45, 0.0), (0.6, 0.45, 0.0), (2, 1, 1)),
               root / "two.probes", settings=st).store
    here = bake(scene, GridSpec.from_counts(POINT, POINT, (1, 1, 1)), root / "here.probes",
                settings=st).store
    return scene, two, here


def test_a_traced_point_sees_one_panel_of_its_solid_angle_where_the_blend_sees_two(
        panel_stores):
    scene, two, here = panel_stores
    field = ProbeField(two, scene=scene)
    assert field.trace_support() is None and field.map_method() == "trace"
    maps = field.point_maps(POINT)
    x, y, z = PANEL
    h = SIDE / 2
    omega = _solid_angle(POINT, [(x - h, y, z - h), (x + h, y, z - h), (x + h, y, z + h),
                                 (x - h, y, z + h)])
    # the traced incoming cube: one panel, all of its light within 20 degrees of its
    # direction (its corners are 15 degrees off), of the exact solid angle (the probe's direct
    # view is exact texel coverage)
    near, everywhere = _panel_energy(maps.incoming, 20.0)
    assert near == everywhere
    assert near == pytest.approx(LE * omega, rel=0.005)
    # the mirror level shows it alike
    near_s, every_s = _panel_energy(maps.specular[0], 20.0)
    assert near_s == every_s and near_s == pytest.approx(LE * omega, rel=0.005)
    # the blend of the two probes: none where the panel is, two copies where each probe sees it
    blended, _, used = field.cube_at(POINT, "specular", method="blend")
    assert used == "blend"
    near_b, every_b = _panel_energy(blended, 20.0)
    assert near_b == 0.0 and every_b > 0
    copies = [_panel_energy(blended, 20.0, seen_from=p)[0] for p in np.asarray(two["positions"])]
    assert min(copies) > 0.2 * every_b and sum(copies) == pytest.approx(every_b, rel=1e-6)
    # a probe baked at the point: the same maps up to the bake's noise
    baked_in = np.asarray(here["incoming"][0], np.float64)
    w = texel_solid_angles(16)[..., None]
    l1 = float((w * np.abs(maps.incoming - baked_in)).sum() / (w * baked_in).sum())
    assert l1 < 0.02
    baked_d = np.asarray(here["diffuse"][0], np.float64)
    w4 = texel_solid_angles(4)[..., None]
    assert float((w4 * np.abs(maps.diffuse - baked_d)).sum() / (w4 * baked_d).sum()) < 0.01
    blend_d, _, _ = field.cube_at(POINT, "diffuse", method="blend")
    assert float((w4 * np.abs(blend_d - baked_d)).sum() / (w4 * baked_d).sum()) > 0.03


def test_a_probe_traced_at_a_probe_is_that_probe_up_to_the_noise(panel_stores):
    """The bake's own estimator (``quality="reference"``) gives the probe up to its noise;
    the surface cache's (the default) reads the light reflected at the hits from a lattice of
    the bake's budget (64 vertices on this room of two probes of 6 x 16^2 rays): within 3 %."""
    scene, two, _ = panel_stores
    field = ProbeField(two, scene=scene)
    tracer = field.point_tracer("reference")
    pos = np.asarray(two["positions"][1])
    got = tracer.maps(pos)
    w = texel_solid_angles(4)[..., None]
    ref = np.asarray(two["diffuse"][1], np.float64)
    assert float((w * np.abs(got.diffuse - ref)).sum() / (w * ref).sum()) < 0.01
    cached = field.point_tracer().maps(pos)
    assert float((w * np.abs(cached.diffuse - ref)).sum() / (w * ref).sum()) < 0.03
    # the same point twice: the same bits (its random streams are keyed by the point)
    again = tracer.maps(pos)
    assert np.array_equal(again.incoming, got.incoming)


def test_the_bake_stores_the_grid_and_the_environment_the_tracer_reads(tmp_path):
    scene = _panel_room()
    rng = np.random.default_rng(3)
    faces = rng.random((6, 128, 128, 3)).astype(np.float32)
    env = Environment(faces=faces, intensity=0.5, rotation=0.3)
    st = BakeSettings(**{**SETTINGS, "bounces": 4, "store_incoming": False})
    s = bake(scene, GridSpec.from_counts((-0.6, 0.45, 0.0), (0.6, 0.45, 0.0), (2, 1, 1)),
             tmp_path / "env.probes", settings=st, environment=env).store
    assert {GRID_EXTRA, ENVIRONMENT_EXTRA} <= set(s.manifest.extras)
    np.testing.assert_array_equal(s[ENVIRONMENT_EXTRA], resample(faces, LIGHT_SIZE))
    g = s[GRID_EXTRA]
    assert g.shape == (2, 6, 10, 10, 3) and g.dtype == np.float32 and float(g.max()) > 0
    from probegrid.bake.point import MOMENTS_EXTRA
    from probegrid.core.ddgi import bordered_cubes

    np.testing.assert_array_equal(s[MOMENTS_EXTRA], bordered_cubes(s["moments"]))
    tracer0 = PointTracer.from_store(s, scene)
    assert tracer0.data.cubes is not None and not tracer0.data.cubes.flags.owndata  # mapped
    assert s.manifest.bake["environment"]["rotation_rad"] == 0.3
    tracer = PointTracer.from_store(s, scene)
    env_q = tracer.records.view.environment
    assert env_q.intensity == 0.5 and env_q.rotation == 0.3


def test_a_store_without_the_extras_is_answered_with_the_blend(panel_stores, tmp_path):
    import shutil

    scene, two, _ = panel_stores
    copy = tmp_path / "old.probes"
    shutil.copytree(two.path, copy)
    import json

    manifest = json.loads((copy / "manifest.json").read_text())
    del manifest["extras"][GRID_EXTRA]
    (copy / "manifest.json").write_text(json.dumps(manifest))
    field = ProbeField(open_store(copy), scene=scene)
    assert "no grid irradiance" in (field.trace_support() or "")
    assert field.map_method("trace") == "blend"
    got, w, used = field.cube_at(POINT, "diffuse")
    assert used == "blend"
    np.testing.assert_array_equal(got, field.cube(w, "diffuse")[0])
    with pytest.raises(ValueError, match="method must be one of"):
        field.map_method("nearest")  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def room_store(tmp_path_factory):
    """The sample room baked with its glTF kept in the store (what the service traces)."""
    from probegrid.jobs.samples import sample_room_glb_bytes

    root = tmp_path_factory.mktemp("room")
    glb = root / "room.glb"
    glb.write_bytes(sample_room_glb_bytes())
    st = BakeSettings(face_size=8, diffuse_size=4, moments_size=4, bounces=1, batch_size=4)
    grid = GridSpec.from_counts((-1.0, 1.0, -1.0), (1.0, 1.0, 1.0), (2, 1, 2))
    return bake(load_gltf(glb), grid, root / "room.probes", settings=st, scene_file=glb).store


def test_the_service_traces_maps_by_default_and_blends_on_request(room_store):
    from service.main import create_app

    app = create_app([room_store.path])
    point = {"x": "0.1", "y": "1.2", "z": "-0.3"}
    field = ProbeField(open_store(room_store.path))
    traced = field.point_maps(np.array([0.1, 1.2, -0.3]))

    async def fetch():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            url = "/v1/grids/room/maps/specular"
            return [await c.get(url, params={**point, "level": "0"}),
                    await c.get(url, params={**point, "level": "0", "method": "blend"}),
                    await c.get(url, params={**point, "method": "nearest"})]

    default, blend, bad = asyncio.run(fetch())
    assert default.status_code == 200 and default.headers["x-probegrid-method"] == "trace"
    import io

    got = np.load(io.BytesIO(default.content))
    np.testing.assert_array_equal(got, traced.specular[0])
    assert blend.headers["x-probegrid-method"] == "blend"
    w = field.weights(np.array([0.1, 1.2, -0.3]))
    np.testing.assert_array_equal(np.load(io.BytesIO(blend.content)),
                                  field.cube(w, "specular")[0])
    assert bad.status_code == 422


def test_the_client_passes_the_method_through():
    from probegrid.client import ProbeGridClient
    from probegrid.errors import ProbegridError

    call = ProbeGridClient._map_call("g", (0.0, 1.0, 2.0), None, "diffuse", 0, "blend")
    assert call.params["method"] == "blend"
    assert ProbeGridClient._map_call("g", (0.0, 1.0, 2.0), None, "diffuse", 0
                                     ).params["method"] == "trace"
    with pytest.raises(ProbegridError, match="method must be one of"):
        ProbeGridClient._map_call("g", (0.0, 1.0, 2.0), None, "diffuse", 0, "nearest")


def test_a_point_inside_a_solid_is_answered_with_the_blend(panel_stores):
    """Behind a single-sided wall (outside the room) half the traced rays meet its back: no
    probe would be valid there, and the blend answers."""
    scene, two, _ = panel_stores
    field = ProbeField(two, scene=scene)
    outside = np.array([1.05, 0.5, 0.0])
    assert field.point_maps(outside).backface_fraction > 0.4
    got, w, used = field.cube_at(outside, "diffuse")
    assert used == "blend"
    np.testing.assert_array_equal(got, field.cube(w, "diffuse")[0])
    assert field.cube_at(POINT, "diffuse")[2] == "trace"


def test_the_traced_point_reads_the_grid_the_final_pass_read(panel_stores):
    """With 4 bounces and 2 gather levels the final pass reads the grid of level 1 at the
    deepest gather hits: the tracer reads the stored one. Zeroing it darkens the point by the
    light reflected three times or more: with walls of albedo 0.2, under a percent of what the
    point receives (mostly the panel itself), but not nothing."""
    scene, two, _ = panel_stores
    tracer = ProbeField(two, scene=scene).point_tracer("reference")  # (the cache baked it in)
    assert tracer.level == 4 and tracer.data.cubes is not None
    lit = tracer.maps(POINT)
    import dataclasses

    tracer.data = dataclasses.replace(tracer.data, cubes=np.zeros_like(tracer.data.cubes))
    dark = tracer.maps(POINT)
    w = texel_solid_angles(4)[..., None]
    e_lit, e_dark = float((w * lit.diffuse).sum()), float((w * dark.diffuse).sum())
    assert 1e-4 < (e_lit - e_dark) / e_lit < 0.01


def test_concurrent_requests_for_one_point_share_its_trace(panel_stores):
    """A client fetching every level at once asks for one point several times together: one
    trace answers them all; two points are traced side by side."""
    from concurrent.futures import ThreadPoolExecutor

    scene, two, _ = panel_stores
    field = ProbeField(two, scene=scene)
    tracer = field.point_tracer()
    calls = []
    original = tracer.maps
    other_started = threading.Event()

    def counted(p):
        calls.append(tuple(p))
        if np.array_equal(p, POINT):  # the other point's trace runs meanwhile
            assert other_started.wait(20)
        else:
            other_started.set()
        return original(p)

    tracer.maps = counted  # type: ignore[method-assign]
    other = POINT + np.array([0.1, 0.0, 0.0])
    with ThreadPoolExecutor(6) as pool:
        first = [pool.submit(field.point_maps, POINT) for _ in range(5)]
        second = pool.submit(field.point_maps, other)
        got = [f.result() for f in first] + [second.result()]
    assert len(calls) == 2
    assert all(g is got[0] for g in got[:5]) and got[5] is not got[0]
    assert field.point_maps(POINT) is got[0]  # kept
    # traced side by side, each is what it is alone (its streams are keyed by the point)
    assert np.array_equal(got[5].incoming, original(other).incoming)
    assert np.array_equal(got[0].specular[0], original(POINT).specular[0])
