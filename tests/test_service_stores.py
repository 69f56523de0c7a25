"""The service's trust in its stores and its OpenAPI document.

Stores are checked at open as ``probegrid export`` checks them (a NaN is refused, not served as
``null``); a store replaced on disk while served is opened, checked and swapped in whole (or
refused, saying so); ``/v1/grids/{grid}`` names the served bake by a content hash that changes
its ETag; a repeated query parameter is a 422; and the OpenAPI document states the limits and
cross-field rules the server enforces. In-process apps (httpx's ASGI transport), tiny stores.
"""

from __future__ import annotations

import asyncio
import io
import shutil
from pathlib import Path

import httpx
import numpy as np
import pytest
from probe_stores import GRID, linear_arrays, write_store

from probegrid.core.grid import GridSpec
from probegrid.query import ProbeField
from probegrid.store import StoreError, open_store
from service.main import NONZERO_VECTORS, create_app
from service.settings import Settings

POINT = {"x": "0.75", "y": "0.25", "z": "1.5"}
POS = np.array([0.75, 0.25, 1.5])
LIMITS = Settings(max_batch=64, max_lights=4, max_light_map_size=32, max_json_values=1000)


def _get(app, *urls: str, **kw) -> list[httpx.Response]:
    async def run() -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            return [await c.get(u, **kw) for u in urls]

    return asyncio.run(run())


@pytest.fixture(scope="module")
def lin(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("st") / "lin.probes"
    write_store(path, GRID, linear_arrays(GRID))
    return path


@pytest.mark.parametrize("name, bad", [("sh", np.nan), ("specular_2", np.inf),
                                       ("moments", -np.inf)])
def test_a_store_with_non_finite_values_is_refused_at_open(tmp_path, name, bad):
    arrays = linear_arrays(GRID)
    arrays[name].reshape(-1)[5] = bad
    write_store(tmp_path / "bad.probes", GRID, arrays)
    with pytest.raises(StoreError, match=f"non-finite values .*1 in '{name}'"):
        create_app([tmp_path / "bad.probes"])


def test_a_store_without_its_maps_is_refused_at_open(tmp_path):
    arrays = linear_arrays(GRID)
    del arrays["diffuse"]
    write_store(tmp_path / "nodiff.probes", GRID, arrays)
    with pytest.raises(StoreError, match="no 'diffuse' array"):
        create_app([tmp_path / "nodiff.probes"])


def _replace(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """What ``bake --overwrite`` does: the new store renamed over the served directory."""
    new = path.with_name("incoming.probes")
    write_store(new, GRID, arrays)
    shutil.rmtree(path)
    new.rename(path)


def test_a_replaced_store_is_swapped_in_whole_and_named_by_its_hash(lin, tmp_path):
    path = tmp_path / "swap.probes"
    shutil.copytree(lin, path)
    app = create_app([path], LIMITS)
    grids = app.state.probegrid.grids
    detail, sh_before = _get(app, "/v1/grids/swap", "/v1/grids/swap/sh?x=0.75&y=0.25&z=1.5")
    hash_before, etag_before = detail.json()["content_hash"], detail.headers["etag"]
    assert len(hash_before) == 64 and detail.json()["replaced_on_disk"] is None

    doubled = linear_arrays(GRID)
    for name in ("sh", "diffuse"):
        doubled[name] = doubled[name] * 2
    _replace(path, doubled)
    grids.wait_for_reloads()
    detail, sh_after = _get(app, "/v1/grids/swap", "/v1/grids/swap/sh?x=0.75&y=0.25&z=1.5")
    assert detail.json()["content_hash"] != hash_before
    assert detail.headers["etag"] != etag_before
    np.testing.assert_array_equal(np.array(sh_after.json()["coefficients"]),
                                  2 * np.array(sh_before.json()["coefficients"]))
    new = ProbeField(open_store(path))
    np.testing.assert_array_equal(np.array(sh_after.json()["coefficients"]),
                                  new.sh(new.weights(POS))[0])

    broken = linear_arrays(GRID)  # a damaged replacement is not served: the last good one is
    broken["sh"][0, 0, 0] = np.nan
    _replace(path, broken)
    grids.wait_for_reloads()
    detail, sh_kept = _get(app, "/v1/grids/swap", "/v1/grids/swap/sh?x=0.75&y=0.25&z=1.5")
    assert "cannot be served" in detail.json()["replaced_on_disk"]
    assert "non-finite" in detail.json()["replaced_on_disk"]
    assert sh_kept.json()["coefficients"] == sh_after.json()["coefficients"]


@pytest.mark.parametrize("query", ["x=1&x=2&y=0.5&z=1", "x=1&y=0.5&z=1&nx=0&ny=1&nz=0&ny=1",
                                   "x=1&y=0.5&z=1&level=0&level=1"])
@pytest.mark.parametrize("fastapi_path", [False, True])
def test_repeated_query_parameters_are_422_on_both_paths(lin, query, fastapi_path):
    app = create_app([lin], LIMITS)
    if fastapi_path:  # any override sends every request through FastAPI's resolution
        app.dependency_overrides[test_repeated_query_parameters_are_422_on_both_paths] = id
    for route in ("sh", "maps/specular"):
        (r,) = _get(app, f"/v1/grids/lin/{route}?{query}")
        assert r.status_code == 422, (route, r.text)
        assert "given more than once" in r.json()["message"]
    (ok,) = _get(app, "/v1/grids/lin/sh?x=1&y=0.5&z=1&other=1&other=2")  # unknown: ignored
    assert ok.status_code == 200


# ------------------------------------------------------------------------------ OpenAPI 3.1
def _walk(node, path=()):
    if isinstance(node, dict):
        yield path, node
        for k, v in node.items():
            yield from _walk(v, (*path, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _walk(v, (*path, i))


def test_openapi_is_valid_31_and_states_what_the_server_enforces(lin):
    app = create_app([lin], LIMITS)
    (r,) = _get(app, "/openapi.json")
    doc = r.json()
    assert doc["openapi"].startswith("3.1")
    for path, node in _walk(doc):  # 3.1 schema objects: `items` is one schema, never a list
        assert not isinstance(node.get("items", {}), list), path
        assert "prefixItems" not in node, path  # homogeneous tuples: fixed-length arrays
    s = doc["components"]["schemas"]
    bmax = s["GridSummary"]["properties"]["bounds_max"]
    assert bmax["items"] == {"type": "number"} and bmax["minItems"] == bmax["maxItems"] == 3
    for case in s["LightMapsRequest"]["anyOf"]:  # the requests the server takes, case by case
        maps = case["properties"]
        assert maps["lights"]["maxItems"] == 4
        for size in (maps[k] for k in ("diffuse_size", "specular_size") if k in maps):
            assert size.get("maximum", size.get("const")) <= 32
    assert s["ShadeRequest"]["properties"]["points"]["maxItems"] == 64
    for model, field in NONZERO_VECTORS:
        for obj in s[model].get("anyOf", [s[model]]):
            prop = obj["properties"][field]
            arr = next((a for a in prop.get("anyOf", []) if a.get("type") == "array"), prop)
            assert arr["contains"] == {"not": {"const": 0}}, (model, field)
    for route in ("/v1/grids/{grid}/sh", "/v1/grids/{grid}/maps/diffuse",
                  "/v1/grids/{grid}/maps/specular"):
        params = {p["name"]: p for p in doc["paths"][route]["get"]["parameters"]}
        assert {"nx", "ny", "nz"}.isdisjoint(params)  # one object: all three or none
        normal = params["normal"]
        assert normal["style"] == "form" and normal["explode"] is True
        assert set(normal["schema"]["properties"]) == {"nx", "ny", "nz"}


def _normal_schema_accepts(schema: dict, value: dict) -> bool:
    """The advertised normal schema, read by hand (no JSON Schema library here): properties
    numbers; anyOf [none of nx/ny/nz | all three and not all zero]."""
    none_branch, all_branch = schema["anyOf"]
    keys = {"nx", "ny", "nz"}
    none = not any(k in value for k in keys)
    assert none_branch == {"not": {"anyOf": [{"required": [k]} for k in ("nx", "ny", "nz")]}}
    assert all_branch["required"] == ["nx", "ny", "nz"]
    zero = all_branch["not"]["properties"]
    every = keys <= set(value) and not all(value[k] == zero[k]["const"] for k in keys)
    return none or every


@pytest.mark.parametrize("normal", [{}, {"nx": 1, "ny": 0, "nz": 0}, {"nx": 0, "ny": 0},
                                    {"nx": 0, "ny": 0, "nz": 0}, {"nz": 2.5}])
def test_the_normal_schema_and_the_server_agree(lin, normal):
    app = create_app([lin], LIMITS)
    (doc,) = _get(app, "/openapi.json")
    params = {p["name"]: p for p in doc.json()["paths"]["/v1/grids/{grid}/sh"]["get"]
              ["parameters"]}
    valid = _normal_schema_accepts(params["normal"]["schema"], normal)
    (r,) = _get(app, "/v1/grids/lin/sh", params={**POINT, **{k: str(v) for k, v in
                                                              normal.items()}})
    assert (r.status_code == 200) == valid, (normal, r.text)


def test_enforced_limits_match_the_advertised_ones(lin):
    app = create_app([lin], LIMITS)
    light = {"type": "point", "position": [0.0, 3.0, 0.0], "intensity": 1.0}

    async def post(body):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            return await c.post("/v1/lights/maps", json=body)

    base = {"position": [0.5, 0.5, 0.5], "lights": [light]}
    assert asyncio.run(post({**base, "diffuse_size": 32})).status_code == 200
    for body in ({**base, "diffuse_size": 33}, {**base, "specular_size": 33, "grid": "lin"},
                 {**base, "lights": [light] * 5}, {**base, "level": 1},
                 {**base, "level": True}, {**base, "diffuse_size": True}):
        r = asyncio.run(post(body))
        assert r.status_code == 422, (body, r.text)
    shade = {"points": [{"position": [0.5, 0.5, 0.5], "normal": [0, 1, 0], "view": [0, 1, 0]}],
             "material": {"roughness": False}}

    async def post_shade():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            return await c.post("/v1/grids/lin/shade", json=shade)

    assert asyncio.run(post_shade()).status_code == 422  # a boolean is not a roughness


def test_maps_take_the_cli_layout_name_and_a_cube_map_repr_is_one_line(lin):
    from probegrid.core.cubemap import CubeMap

    app = create_app([lin], LIMITS)
    cross, hcross = _get(app, *(f"/v1/grids/lin/maps/diffuse?x=1&y=0.5&z=1&format=npy&layout={v}"
                                for v in ("cross", "hcross")))
    assert hcross.status_code == 200 and hcross.content == cross.content
    cube = CubeMap.from_faces(np.zeros((6, 8, 8, 3), np.float32), kind="specular", mips=True)
    assert repr(cube) == ("CubeMap(kind='specular', size=8, levels=4, channels=3, "
                          "dtype=float32)")


def test_maps_and_light_maps_have_the_same_default_format(lin):
    app = create_app([lin], LIMITS)
    (maps,) = _get(app, "/v1/grids/lin/maps/diffuse?x=1&y=0.5&z=1")

    async def post():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            return await c.post("/v1/lights/maps", json={
                "position": [1, 0.5, 1], "lights": [
                    {"type": "point", "position": [0, 3, 0], "intensity": 1.0}]})

    lights = asyncio.run(post())
    assert maps.status_code == lights.status_code == 200
    assert maps.headers["content-type"] == lights.headers["content-type"]
    (doc,) = _get(app, "/openapi.json")
    params = {p["name"]: p for p in doc.json()["paths"]["/v1/grids/{grid}/maps/diffuse"]["get"]
              ["parameters"]}
    assert params["format"]["schema"]["default"] == doc.json()["components"]["schemas"][
        "LightMapsRequest"]["anyOf"][0]["properties"]["format"]["default"] == "npy"


# ------------------------------------------------------------------------- OpenAPI limits and rules
def _params(doc: dict, path: str) -> dict[str, dict]:
    return {p["name"]: p for p in doc["paths"][path]["get"]["parameters"]}


def test_each_map_kind_states_its_own_level_range(lin, tmp_path):
    """One OpenAPI operation per served kind (same URLs): specular's ``level`` maximum is the
    store's last level, diffuse and incoming have no ``level``; the server agrees at the
    bounds; with grids of different chains the description names each grid's range."""
    from service.main import MAPS_ROUTE

    levels = open_store(lin).manifest.arrays.keys()
    last = max(int(k.split("_")[1]) for k in levels if k.startswith("specular_"))
    app = create_app([lin], LIMITS)
    (r,) = _get(app, "/openapi.json")
    doc = r.json()
    assert MAPS_ROUTE not in doc["paths"]
    spec = _params(doc, "/v1/grids/{grid}/maps/specular")
    assert "kind" not in spec and spec["level"]["schema"]["maximum"] == last == 3
    assert spec["level"]["schema"]["minimum"] == 0
    for kind in ("diffuse", "incoming"):
        assert "level" not in _params(doc, f"/v1/grids/{{grid}}/maps/{kind}")
    ids = {doc["paths"][f"/v1/grids/{{grid}}/maps/{k}"]["get"]["operationId"]
           for k in ("diffuse", "specular", "incoming")}
    assert len(ids) == 3
    q = "x=1&y=0.5&z=1"
    ok, over, dif0, dif1, unknown = _get(
        app, f"/v1/grids/lin/maps/specular?{q}&level={last}",
        f"/v1/grids/lin/maps/specular?{q}&level={last + 1}",
        f"/v1/grids/lin/maps/diffuse?{q}&level=0", f"/v1/grids/lin/maps/diffuse?{q}&level=1",
        f"/v1/grids/lin/maps/glossy?{q}")
    assert ok.status_code == dif0.status_code == 200
    assert over.status_code == dif1.status_code == 422 and unknown.status_code == 404

    # a second grid with a longer chain and no incoming maps
    big = tmp_path / "big.probes"
    write_store(big, GRID, linear_arrays(GRID, specular_size=32, incoming_size=None))
    (r,) = _get(create_app([lin, big], LIMITS), "/openapi.json")
    doc = r.json()
    level = _params(doc, "/v1/grids/{grid}/maps/specular")["level"]
    assert level["schema"]["maximum"] == 5
    assert "big 0..5, lin 0..3" in level["description"]
    grid = _params(doc, "/v1/grids/{grid}/maps/incoming")["grid"]
    assert "stored by lin (404 for the others)" in grid["description"]


def test_query_coordinates_have_the_bodies_bound(lin):
    app = create_app([lin], LIMITS)
    (r,) = _get(app, "/openapi.json")
    x = _params(r.json(), "/v1/grids/{grid}/sh")["x"]["schema"]
    assert x["maximum"] == 1e12 == -x["minimum"]
    edge, over = _get(app, "/v1/grids/lin/sh?x=1e12&y=0&z=0&nx=1&ny=0&nz=0",
                      "/v1/grids/lin/sh?x=1.0000001e12&y=0&z=0&nx=1&ny=0&nz=0")
    assert edge.status_code == 200 and over.status_code == 422


def _light_maps(app, lights: list[dict]) -> httpx.Response:
    async def post() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            return await c.post("/v1/lights/maps", json={
                "position": [1.0, 0.0, 0.0], "lights": lights, "kind": "diffuse",
                "diffuse_size": 8})

    return asyncio.run(post())


def test_the_spot_cone_is_stated_as_outer_angle_and_penumbra(lin):
    """Any in-range (outer_cone_angle, penumbra) is a cone; penumbra p is inner = outer (1-p),
    0 a hard edge (the glTF formula's floor: the same map as any inner angle within it);
    glTF's inner_cone_angle is still taken, must stay below the outer angle, and is not
    listed in the document (a rule between two fields)."""
    app = create_app([lin], LIMITS)
    (r,) = _get(app, "/openapi.json")
    spot = r.json()["components"]["schemas"]["SpotLightIn"]
    assert "inner_cone_angle" not in spot["properties"]
    assert "inner_cone_angle" in spot["description"]
    pen = next(a for a in spot["properties"]["penumbra"]["anyOf"] if a["type"] == "number")
    assert pen["minimum"] == 0 and pen["maximum"] == 1

    base = {"type": "spot", "position": [0.0, 1.0, 0.0], "direction": [0.0, -1.0, 0.0],
            "intensity": 50.0, "outer_cone_angle": 1.2}

    def diffuse(**cone) -> np.ndarray:
        resp = _light_maps(app, [{**base, **cone}])
        assert resp.status_code == 200, resp.text
        return np.load(io.BytesIO(resp.content))

    half = diffuse(penumbra=0.5)
    np.testing.assert_array_equal(half, diffuse(inner_cone_angle=0.6))
    assert not np.array_equal(half, diffuse(penumbra=1.0))
    np.testing.assert_array_equal(diffuse(penumbra=1.0), diffuse())  # the default: inner 0
    hard = diffuse(penumbra=0.0)  # the point is 45 degrees off the axis, inside the cone
    np.testing.assert_array_equal(hard, diffuse(inner_cone_angle=1.2 - 1e-6))
    assert hard.max() > half.max() > diffuse(penumbra=1.0).max() > 0
    for cone in ({"inner_cone_angle": 1.2}, {"inner_cone_angle": 1.3},
                 {"inner_cone_angle": 0.1, "penumbra": 0.5}, {"penumbra": 1.5},
                 {"penumbra": -0.1}):
        assert _light_maps(app, [{**base, **cone}]).status_code == 422, cone


def test_a_ktx2_cross_is_the_cross_as_a_2d_texture(lin):
    """format=ktx2 with layout=cross: the cross image in a 2D KTX2 (was a cross-parameter 422,
    which the document cannot state)."""
    from probegrid.export.ktx2 import read_ktx2

    app = create_app([lin], LIMITS)
    q = "x=1&y=0.5&z=1"
    cross_npy, cross_ktx2, cube_ktx2 = _get(
        app, f"/v1/grids/lin/maps/specular?{q}&level=1&layout=cross",
        f"/v1/grids/lin/maps/specular?{q}&level=1&layout=cross&format=ktx2",
        f"/v1/grids/lin/maps/specular?{q}&level=1&format=ktx2")
    assert cross_ktx2.status_code == cube_ktx2.status_code == 200
    tex = read_ktx2(cross_ktx2.content)
    assert tex.kind == "2d" and read_ktx2(cube_ktx2.content).kind == "cube"
    image = np.load(io.BytesIO(cross_npy.content))
    np.testing.assert_array_equal(tex.levels[0][..., :3], image)
    r = _light_maps(app, [{"type": "point", "position": [0.0, 3.0, 0.0], "intensity": 1.0}])
    assert r.status_code == 200


def test_the_light_map_rules_in_the_document_are_the_servers(lin, tmp_path):
    """``/v1/lights/maps``: every combination of kind, level, sizes, specular_levels, grid and
    format=json is valid for the document's schema (its cases) exactly when the server answers
    200 (else 422)."""
    import itertools

    import jsonschema_rs

    nodiff = tmp_path / "nospec.probes"  # a grid without specular maps
    arrays = linear_arrays(GRID)
    for k in range(4):
        del arrays[f"specular_{k}"]
    write_store(nodiff, GRID, arrays)
    limits = Settings(max_batch=64, max_lights=4, max_light_map_size=32, max_json_values=2000)
    app = create_app([lin, nodiff], limits)
    (r,) = _get(app, "/openapi.json")
    doc = r.json()
    schema = {"$ref": "#/components/schemas/LightMapsRequest", "components": doc["components"]}
    validator = jsonschema_rs.Draft202012Validator(schema)
    light = {"type": "point", "position": [0.0, 3.0, 0.0], "intensity": 1.0}
    bodies = []
    kinds, levels_ = [None, "diffuse", "specular"], [None, 1, 3, 6]
    combos = [(k, lv, size, n, None, fmt) for k, lv, size, n, fmt in itertools.product(
        kinds, levels_, [None, 8, 12, 32], [None, 1, 3], [None, "json"])]
    combos += [(k, lv, None, None, g, fmt) for k, lv, g, fmt in itertools.product(
        kinds, levels_, ["lin", "nospec"], [None, "json"])]  # a grid's sizes: the store's
    for kind, level, size, levels, grid, fmt in combos:
        body: dict = {"position": [0.5, 0.5, 0.5], "lights": [light]}
        for key, value in (("kind", kind), ("level", level), ("specular_size", size),
                           ("diffuse_size", size), ("specular_levels", levels),
                           ("grid", grid), ("format", fmt)):
            if value is not None:
                body[key] = value
        bodies.append(body)

    async def post_all() -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            return [await c.post("/v1/lights/maps", json=b) for b in bodies]

    answers = asyncio.run(post_all())
    valid = 0
    for body, resp in zip(bodies, answers, strict=True):
        ok = validator.is_valid(body)
        valid += ok
        assert (resp.status_code == 200) == ok, (body, resp.status_code, resp.text[:200])
        assert resp.status_code in (200, 422), (body, resp.text[:200])
    assert 0 < valid < len(bodies)  # both kinds of answer were asked for


def test_light_directions_of_any_length_the_schema_allows(lin):
    """A light direction of 5e-324 (schema-valid: not the zero vector) is the direction +X,
    not a 422 from an underflowing normalisation (schemathesis found it)."""
    app = create_app([lin], LIMITS)
    for light in ({"type": "directional", "intensity": 2.0},
                  {"type": "spot", "position": [-1.0, 0.0, 0.0], "intensity": 5.0,
                   "outer_cone_angle": 1.0}):
        unit, tiny = (_light_maps(app, [{**light, "direction": d}])
                      for d in ([1.0, 0.0, 0.0], [5e-324, 0.0, 0.0]))
        assert unit.status_code == tiny.status_code == 200, tiny.text
        assert unit.content == tiny.content


# ---------------------------------------------------------------------------- what is served
SAMPLE_GLB = Path(__file__).parents[1] / "data" / "sample_room.glb"
EMBEDDED_GLTF = ('{"asset": {"version": "2.0"}, "buffers": [{"uri": '
                 '"data:application/octet-stream;base64,AAAA", "byteLength": 3}]}')


def _secret_behind_scene_link(path: Path, secret: Path) -> None:
    """Make the store's scene copy a link to ``secret``, with a manifest that states the
    target's size and hash (the store's author knows them), as a crafted store would."""
    import hashlib
    import json

    (path / "scene.glb").unlink()
    (path / "scene.glb").symlink_to(secret)
    raw = json.loads((path / "manifest.json").read_text())
    raw["scene_file"].update(bytes=secret.stat().st_size,
                             sha256=hashlib.sha256(secret.read_bytes()).hexdigest())
    (path / "manifest.json").write_text(json.dumps(raw))


def test_a_store_whose_scene_is_a_link_out_of_it_is_refused(tmp_path):
    secret = tmp_path / "shadow"
    secret.write_bytes(b"root:$6$secret-hash:19000:0:99999:7:::\n")
    path = tmp_path / "evil.probes"
    write_store(path, GRID, linear_arrays(GRID), scene=SAMPLE_GLB)
    _secret_behind_scene_link(path, secret)
    with pytest.raises(StoreError, match="scene.glb is a symbolic link") as info:
        create_app([path], LIMITS)
    assert "\n" not in str(info.value)

    # the same store arriving as a replacement of a served one is refused too
    served = tmp_path / "room.probes"
    write_store(served, GRID, linear_arrays(GRID), scene=SAMPLE_GLB)
    app = create_app([served], LIMITS)
    shutil.rmtree(served)
    path.rename(served)
    app.state.probegrid.grids.wait_for_reloads()
    detail, scene = _get(app, "/v1/grids/room", "/v1/grids/room/scene")
    assert "symbolic link" in detail.json()["replaced_on_disk"]
    assert scene.status_code == 200 and scene.content == SAMPLE_GLB.read_bytes()
    assert b"secret-hash" not in scene.content


def _three(app, name: str) -> tuple[httpx.Response, ...]:
    return tuple(_get(app, f"/v1/grids/{name}/probes", f"/v1/grids/{name}/export/threejs.json",
                      f"/v1/grids/{name}/export/threejs.bin?dtype=float32",
                      f"/v1/grids/{name}/scene"))


def test_every_route_follows_a_store_replaced_on_disk(tmp_path):
    from service.encoding import etag_of

    path = tmp_path / "room.probes"
    write_store(path, GRID, linear_arrays(GRID), scene=SAMPLE_GLB)
    app = create_app([path], LIMITS)
    before = _three(app, "room")
    assert before[3].headers["content-type"] == "model/gltf-binary"

    wider = GridSpec.from_counts((0.0, 0.0, 0.0), (4.0, 1.0, 2.0), GRID.counts)
    doubled = linear_arrays(wider)
    doubled["sh"] = doubled["sh"] * 2
    (tmp_path / "room.gltf").write_text(EMBEDDED_GLTF)
    new = tmp_path / "incoming.probes"
    write_store(new, wider, doubled, scene=tmp_path / "room.gltf")
    shutil.rmtree(path)
    new.rename(path)
    app.state.probegrid.grids.wait_for_reloads()
    after = _three(app, "room")
    for old, now in zip(before, after, strict=True):
        assert now.status_code == 200 and now.content != old.content
        assert now.headers["etag"] == etag_of(now.content) != old.headers["etag"]
    assert after[3].headers["content-type"] == "model/gltf+json"
    assert after[3].content == EMBEDDED_GLTF.encode()
    assert after[1].json()["size"] == [6.0, 2.0, 3.0] != before[1].json()["size"]
    sh = base64_f32(after[0].json()["sh"])
    np.testing.assert_array_equal(sh, doubled["sh"].reshape(-1))


def base64_f32(text: str) -> np.ndarray:
    import base64

    return np.frombuffer(base64.b64decode(text), "<f4")


def test_a_store_landing_file_by_file_is_served_only_once_complete(lin, tmp_path):
    path = tmp_path / "land.probes"
    shutil.copytree(lin, path)
    app = create_app([path], LIMITS)
    grids = app.state.probegrid.grids
    url = "/v1/grids/land/sh?x=0.75&y=0.25&z=1.5"
    (old,) = _get(app, url)

    tripled = linear_arrays(GRID)
    for name in ("sh", "diffuse", "specular_0"):
        tripled[name] = tripled[name] * 3
    new = tmp_path / "staging.probes"
    write_store(new, GRID, tripled)
    files = ["manifest.json"] + sorted(f.name for f in new.iterdir() if f.name != "manifest.json")
    for i, name in enumerate(files):  # manifest first, as a naive copy would
        shutil.copyfile(new / name, path / name)
        grids.wait_for_reloads()
        (now,) = _get(app, url)
        if i < len(files) - 1 and any(f in files[i + 1:] for f in ("sh.npy", "diffuse.npy")):
            assert now.json() == old.json()  # half landed: the old store, whole
            assert "SHA-256" in _get(app, "/v1/grids/land")[0].json()["replaced_on_disk"]
    (now,) = _get(app, url)
    field = ProbeField(open_store(path))
    np.testing.assert_array_equal(np.array(now.json()["coefficients"]),
                                  field.sh(field.weights(POS))[0])
    np.testing.assert_allclose(np.array(now.json()["coefficients"]),
                               3 * np.array(old.json()["coefficients"]), rtol=1e-12)
    assert _get(app, "/v1/grids/land")[0].json()["replaced_on_disk"] is None


def test_a_store_deleted_under_the_server_is_served_from_memory_and_healthz_says_so(lin,
                                                                                   tmp_path):
    path = tmp_path / "gone.probes"
    shutil.copytree(lin, path)
    app = create_app([path], LIMITS)
    url = "/v1/grids/gone/sh?x=0.75&y=0.25&z=1.5"
    health, before = _get(app, "/healthz", url)
    assert health.json() == {"status": "ok", "grids": 1}
    shutil.rmtree(path)
    app.state.probegrid.grids.wait_for_reloads()
    health, after = _get(app, "/healthz", url)
    assert health.status_code == 200  # alive: a restart would only lose the copy it serves
    assert health.json()["status"] == "degraded"
    assert "deleted from disk" in health.json()["problems"]["gone"]
    assert str(tmp_path) not in health.text  # no server path in a public answer
    assert after.status_code == 200 and after.content == before.content
    shutil.copytree(lin, path)  # a store is back at the path
    app.state.probegrid.grids.wait_for_reloads()
    assert _get(app, "/healthz")[0].json() == {"status": "ok", "grids": 1}


TRUNCATE_SCRIPT = """
import asyncio, os, sys
from pathlib import Path
import httpx
from service.main import create_app
path = Path(sys.argv[1])
app = create_app([path])
async def get(url):
    async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://t") as c:
        return (await c.get(url)).content
url = "/v1/grids/cut/maps/diffuse?x=0.75&y=0.25&z=1.5&format=npy"
before = asyncio.run(get(url))
for f in path.glob("*.npy"):
    os.truncate(f, 0)
print(asyncio.run(get(url)) == before)
"""


def test_truncating_a_served_stores_files_does_not_crash_the_server(lin, tmp_path):
    import subprocess
    import sys

    path = tmp_path / "cut.probes"
    shutil.copytree(lin, path)
    done = subprocess.run([sys.executable, "-c", TRUNCATE_SCRIPT, str(path)], text=True,
                          capture_output=True, cwd=Path(__file__).parents[1], timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]  # -7 (SIGBUS) with mapped arrays
    assert done.stdout.strip() == "True"


# ---------------------------------------------------------------------------- failed writes
MAPS_URL = "/v1/grids/lin/maps/diffuse?x=0.75&y=0.25&z=1.5&format="


def _assert_scratch_503(response: httpx.Response, scratch: Path) -> None:
    assert response.status_code == 503 and response.content
    assert response.json()["error"] == "scratch_unavailable"
    assert response.headers["retry-after"] == "5"
    assert str(scratch) not in response.text and "etag" not in response.headers


@pytest.mark.parametrize("fmt", ["exr", "hdr", "png"])
def test_a_failing_scratch_write_is_a_503_not_the_clients_fault(lin, monkeypatch, fmt):
    import errno

    import service.encoding

    def full(path, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(service.encoding, "write_image", full)
    app = create_app([lin], LIMITS)
    (r,) = _get(app, MAPS_URL + fmt)
    _assert_scratch_503(r, app.state.probegrid.scratch)


@pytest.mark.parametrize("fmt", ["exr", "hdr", "png"])
def test_a_full_scratch_file_system_is_a_503_with_no_empty_body(lin, full_fs, fmt):
    app = create_app([lin], LIMITS)
    app.state.probegrid.scratch = full_fs
    (r,) = _get(app, MAPS_URL + fmt)
    _assert_scratch_503(r, full_fs)
    assert sorted(p.name for p in full_fs.iterdir()) == ["fill"]


# ---------------------------------------------------------------------------- bounded cost
def _post(app, url: str, body: dict) -> httpx.Response:
    async def run() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            return await c.post(url, json=body)

    return asyncio.run(run())


def test_heavy_requests_beyond_the_cap_are_503_busy_with_retry_after(lin):
    app = create_app([lin], Settings(max_heavy_requests=1))
    state = app.state.probegrid
    shade = {"points": [{"position": [0.75, 0.25, 1.5], "normal": [0, 1, 0],
                         "view": [0, 1, 0]}]}
    light = {"position": [0.75, 0.25, 1.5], "kind": "diffuse", "diffuse_size": 4,
             "lights": [{"type": "point", "position": [1, 2, 1], "intensity": 5}]}
    with state.heavy():  # the one slot is taken (a long request under way)
        for r in (_post(app, "/v1/grids/lin/shade", shade), _post(app, "/v1/lights/maps", light)):
            assert r.status_code == 503 and r.json()["error"] == "busy"
            assert r.headers["retry-after"] == "1"
    assert _post(app, "/v1/grids/lin/shade", shade).status_code == 200
    assert _post(app, "/v1/lights/maps", light).status_code == 200
