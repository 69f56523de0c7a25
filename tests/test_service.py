"""Tests of the map service against a real uvicorn server on 127.0.0.1 (service/)."""

from __future__ import annotations

import io
import json
import socket
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import hypothesis
import numpy as np
import OpenImageIO as oiio  # tests read the served images back directly
import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, given, settings
from live_server import serve
from probe_stores import GRID, linear_arrays, linear_store, write_store
from schemathesis import GenerationMode

from probegrid.core.dfg import dfg_lut
from probegrid.core.grid import GridSpec
from probegrid.core.layouts import faces_to_cross
from probegrid.core.lights import PointLight, SpotLight, light_maps
from probegrid.imageio import linear_to_srgb
from probegrid.query import ProbeField
from probegrid.store import StoreError, open_store
from service.deps import DFG_SIZE
from service.main import create_app, example_usage
from service.registry import grid_name

LIMITS = {
    "max_batch": 64,
    "max_lights": 4,
    "max_light_map_size": 32,
    "max_body_bytes": 65536,
    "max_json_values": 1000,
}
POINT = {"x": "0.75", "y": "0.25", "z": "1.5"}
POS = np.array([0.75, 0.25, 1.5])


@pytest.fixture(scope="module")
def stores(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("stores")
    linear_store(root / "lin.probes")
    # a second grid: no incoming map, no moments, one invalid probe
    grid = GridSpec.from_counts((-1.0, 0.0, -1.0), (1.0, 2.0, 1.0), (2, 2, 2))
    arrays = linear_arrays(grid, incoming_size=None)
    del arrays["moments"]
    arrays["valid"][0] = False
    write_store(root / "second.probes", grid, arrays)
    return {"lin": root / "lin.probes", "second": root / "second.probes"}


@pytest.fixture(scope="module")
def server(stores, tmp_path_factory):
    log = tmp_path_factory.mktemp("log") / "server.log"
    with serve(list(stores.values()), log, settings=LIMITS) as live:
        yield live


@pytest.fixture(scope="module")
def http(server):
    with httpx.Client(base_url=server.url, timeout=30.0) as client:
        yield client


@pytest.fixture(scope="module")
def field(stores) -> ProbeField:
    return ProbeField(open_store(stores["lin"]))


def _npy(content: bytes) -> np.ndarray:
    return np.load(io.BytesIO(content), allow_pickle=False)


def _image(content: bytes, suffix: str, tmp_path: Path, fmt=oiio.FLOAT) -> np.ndarray:
    path = tmp_path / f"served{suffix}"
    path.write_bytes(content)
    buf = oiio.ImageBuf(str(path))
    assert not buf.has_error, buf.geterror()
    return np.asarray(buf.get_pixels(fmt))


# ------------------------------------------------------------------------------ grids
def test_health_and_grid_listing(http, stores):
    assert http.get("/healthz").json() == {"status": "ok", "grids": 2}
    grids = {g["name"]: g for g in http.get("/v1/grids").json()["grids"]}
    assert set(grids) == {"lin", "second"}
    lin = grids["lin"]
    assert lin["counts"] == [3, 2, 3] and lin["probes"] == 18 and lin["valid_probes"] == 18
    assert lin["kinds"] == ["diffuse", "specular", "incoming"]
    assert lin["map_sizes"] == {"diffuse": [4], "specular": [8, 4, 2, 1], "incoming": [4]}
    assert lin["visibility"] is True
    assert grids["second"]["kinds"] == ["diffuse", "specular"]
    assert grids["second"]["valid_probes"] == 7 and grids["second"]["visibility"] is False


def test_grid_detail_carries_the_manifest_and_conventions(http):
    doc = http.get("/v1/grids/lin").json()
    conv = doc["manifest"]["conventions"]
    assert conv["cube_face_order"] == ["+X", "-X", "+Y", "-Y", "+Z", "-Z"]
    assert "Condon-Shortley" in conv["sh_basis"]
    assert doc["manifest"]["grid"]["counts"] == [3, 2, 3]
    assert doc["bounds_max"] == [2.0, 1.0, 2.0] and doc["spacing"] == [1.0, 1.0, 1.0]


def test_docs_and_openapi_are_served(http):
    assert http.get("/docs").status_code == 200
    paths = http.get("/openapi.json").json()["paths"]
    assert {"/healthz", "/v1/grids", "/v1/grids/{grid}", "/v1/grids/{grid}/sh",
            "/v1/grids/{grid}/maps/diffuse", "/v1/grids/{grid}/maps/specular",
            "/v1/grids/{grid}/maps/incoming", "/v1/grids/{grid}/shade",
            "/v1/lights/maps"} <= set(paths)


# ------------------------------------------------------------------------------ sh
@pytest.mark.parametrize("normal", [None, (0.3, -0.8, 0.5)])
def test_sh_equals_the_library(http, field, normal):
    params = dict(POINT)
    if normal is not None:
        params.update(nx=str(normal[0]), ny=str(normal[1]), nz=str(normal[2]))
    doc = http.get("/v1/grids/lin/sh", params=params).json()
    w = field.weights(POS, normals=normal)
    np.testing.assert_array_equal(np.array(doc["coefficients"]), field.sh(w)[0])
    used = w.weights[0] > 0
    assert [p["index"] for p in doc["probes"]] == w.indices[0][used].tolist()
    assert [p["weight"] for p in doc["probes"]] == w.weights[0][used].tolist()
    assert doc["flags"] == {"outside": False, "unlit": False, "visibility": normal is not None,
                            "visibility_test": "none" if normal is None else "moments"}
    assert doc["sh"] == "deringed" and doc["sh_source"] == "computed"  # a format-1 store
    raw = http.get("/v1/grids/lin/sh", params={**params, "sh": "raw"}).json()
    assert raw["sh"] == "raw" and raw["sh_source"] == "store"
    np.testing.assert_array_equal(np.array(raw["coefficients"]), field.sh(w, kind="raw")[0])


def test_sh_outside_is_extrapolated_a_quarter_cell_and_flagged(http):
    doc = http.get("/v1/grids/lin/sh", params={"x": "-5", "y": "0.5", "z": "9"}).json()
    assert doc["flags"]["outside"] is True
    assert doc["position"] == [-5.0, 0.5, 9.0] and doc["sampled_position"] == [-0.25, 0.5, 2.25]
    assert min(p["weight"] for p in doc["probes"]) < 0  # the extrapolation's far layer
    assert abs(sum(p["weight"] for p in doc["probes"]) - 1) < 1e-12


def test_sh_unlit_where_only_invalid_probes_weigh(http):
    doc = http.get("/v1/grids/second/sh", params={"x": "-1", "y": "0", "z": "-1"}).json()
    assert doc["flags"]["unlit"] is True and doc["probes"] == []
    assert np.all(np.array(doc["coefficients"]) == 0)


# ------------------------------------------------------------------------------ maps
def test_map_npy_is_bit_exact(http, field):
    w = field.weights(POS)
    for kind, level in (("diffuse", 0), ("specular", 0), ("specular", 2), ("incoming", 0)):
        r = http.get(f"/v1/grids/lin/maps/{kind}",
                     params={**POINT, "level": level, "format": "npy"})
        assert r.status_code == 200 and r.headers["content-type"] == "application/x-npy"
        want = field.cube(w, kind, level=level)[0]
        got = _npy(r.content)
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, want)
        cross = _npy(http.get(f"/v1/grids/lin/maps/{kind}", params={
            **POINT, "level": level, "format": "npy", "layout": "cross"}).content)
        np.testing.assert_array_equal(cross, faces_to_cross(want, "hcross"))
    r = http.get("/v1/grids/lin/maps/specular", params={**POINT, "level": 1, "format": "npy"})
    assert r.headers["x-probegrid-roughness"] == repr(1 / 3)
    assert r.headers["x-probegrid-outside"] == "false"
    pairs = [p.split(":") for p in r.headers["x-probegrid-probes"].split(",")]
    used = w.weights[0] > 0
    assert [int(i) for i, _ in pairs] == w.indices[0][used].tolist()
    np.testing.assert_array_equal([float(x) for _, x in pairs], w.weights[0][used])


def test_map_exr_read_back_equals_the_interpolation(http, field, tmp_path):
    w = field.weights(POS, normals=(0.0, 1.0, 0.0))
    params = {**POINT, "nx": "0", "ny": "1", "nz": "0", "format": "exr"}
    want = field.cube(w, "diffuse")[0]
    r = http.get("/v1/grids/lin/maps/diffuse", params=params)
    assert r.headers["content-type"] == "image/x-exr"
    np.testing.assert_array_equal(_image(r.content, ".exr", tmp_path), want.reshape(24, 4, 3))
    r = http.get("/v1/grids/lin/maps/diffuse", params={**params, "layout": "cross"})
    np.testing.assert_array_equal(_image(r.content, ".exr", tmp_path),
                                  faces_to_cross(want, "hcross"))


def test_map_hdr_and_png_decode(http, field, tmp_path):
    want = field.cube(field.weights(POS), "incoming")[0].reshape(24, 4, 3)
    r = http.get("/v1/grids/lin/maps/incoming", params={**POINT, "format": "hdr"})
    assert r.headers["content-type"] == "image/vnd.radiance"
    got = _image(r.content, ".hdr", tmp_path)
    assert np.all(np.abs(got - want) <= want.max(axis=-1, keepdims=True) / 128)  # RGBE: 8 bits
    r = http.get("/v1/grids/lin/maps/incoming", params={**POINT, "format": "png"})
    assert r.headers["content-type"] == "image/png"
    got8 = _image(r.content, ".png", tmp_path, oiio.UINT8).astype(int)
    np.testing.assert_array_equal(got8, np.rint(linear_to_srgb(want) * 255).astype(int))


def test_map_json(http, field):
    doc = http.get("/v1/grids/lin/maps/specular",
                   params={**POINT, "level": 1, "format": "json"}).json()
    want = field.cube(field.weights(POS), "specular", level=1)[0]
    assert doc["shape"] == [6, 4, 4, 3] and doc["kind"] == "specular" and doc["level"] == 1
    np.testing.assert_array_equal(np.array(doc["data"], dtype=np.float32), want)
    assert doc["roughness"] == pytest.approx(1 / 3) and len(doc["probes"]) == 8


# ------------------------------------------------------------------------------ caching
def test_same_query_same_bytes_strong_etag_and_304(http):
    url, params = "/v1/grids/lin/maps/specular", {**POINT, "level": 1, "format": "exr"}
    a, b = http.get(url, params=params), http.get(url, params=params)
    assert a.content == b.content and a.headers["etag"] == b.headers["etag"]
    etag = a.headers["etag"]
    assert etag.startswith('"') and not etag.startswith("W/")
    for inm in (etag, f'"nope", {etag}', f"W/{etag}", "*"):
        r = http.get(url, params=params, headers={"If-None-Match": inm})
        assert r.status_code == 304 and r.content == b"" and r.headers["etag"] == etag
    r = http.get(url, params=params, headers={"If-None-Match": '"other"'})
    assert r.status_code == 200
    other = http.get(url, params={**params, "x": "0.8"})
    assert other.headers["etag"] != etag
    sh = http.get("/v1/grids/lin/sh", params=POINT)
    assert http.get("/v1/grids/lin/sh", params=POINT,
                    headers={"If-None-Match": sh.headers["etag"]}).status_code == 304


def test_stores_are_read_into_memory_by_the_server_not_mapped(http, server):
    # a mapped store file truncated under the server would kill it with SIGBUS
    http.get("/v1/grids/lin/maps/diffuse", params={**POINT, "format": "npy"})
    maps = Path(f"/proc/{server.process.pid}/maps").read_text()
    assert "lin.probes/" not in maps


# ------------------------------------------------------------------------------ shade, lights
def test_shade_equals_the_library(http, field):
    rng = np.random.default_rng(7)
    n = 20
    pts = GRID.lo + rng.random((n, 3)) * (GRID.hi - GRID.lo)
    nrm, views = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    albedo = rng.uniform(0, 1, size=(n, 3))
    body = {
        "points": [{"position": p.tolist(), "normal": q.tolist(), "view": v.tolist(),
                    "material": {"albedo": a.tolist(), "roughness": 0.3}}
                   for p, q, v, a in zip(pts, nrm, views, albedo, strict=True)],
        "material": {"roughness": 0.9},  # overridden by every point's own material
    }
    doc = http.post("/v1/grids/lin/shade", json=body).json()
    want, w = field.shade(pts, nrm, views, albedo=albedo, roughness=0.3, f0=[0.04] * 3,
                          dfg=dfg_lut(DFG_SIZE))
    np.testing.assert_allclose(np.array(doc["rgb"]), want, rtol=1e-6)
    assert doc["outside"] == w.outside.tolist() and doc["unlit"] == w.unlit.tolist()


def test_light_maps_equal_the_library_and_add_to_a_grid(http, field):
    lights = [
        {"type": "point", "position": [1.0, 2.0, 0.5], "color": [1.0, 0.5, 0.25],
         "intensity": 40.0, "range": 10.0},
        {"type": "spot", "position": [0.0, 3.0, 0.0], "direction": [0.0, -1.0, 0.0],
         "intensity": 100.0, "outer_cone_angle": 0.6},
    ]
    lib = [PointLight(position=(1.0, 2.0, 0.5), color=(1.0, 0.5, 0.25), intensity=40.0,
                      range=10.0),
           SpotLight(position=(0.0, 3.0, 0.0), direction=(0.0, -1.0, 0.0), color=(1, 1, 1),
                     intensity=100.0, outer_cone_angle=0.6)]
    r = http.post("/v1/lights/maps", json={"position": POS.tolist(), "lights": lights,
                                            "diffuse_size": 8})
    want = light_maps(lib, POS, diffuse_size=8, specular_size=1, specular_levels=1)["diffuse"]
    np.testing.assert_array_equal(_npy(r.content), want.faces)
    r = http.post("/v1/lights/maps", json={"position": POS.tolist(), "lights": lights,
                                            "grid": "lin", "kind": "specular", "level": 1})
    spec = light_maps(lib, POS, diffuse_size=1, specular_size=8, specular_levels=4)["specular"]
    baked = field.cube(field.weights(POS), "specular", level=1)[0]
    np.testing.assert_array_equal(_npy(r.content), spec.levels[1] + baked)
    normal = (0.3, -0.8, 0.5)  # with a normal: the grid's visibility-aware blend, as /maps
    r = http.post("/v1/lights/maps", json={"position": POS.tolist(), "lights": lights,
                                            "grid": "lin", "normal": list(normal)})
    size = field.map_size("diffuse")
    want = light_maps(lib, POS, diffuse_size=size, specular_size=1, specular_levels=1)["diffuse"]
    baked = field.cube(field.weights(POS, normals=normal), "diffuse")[0]
    np.testing.assert_array_equal(_npy(r.content), want.faces + baked)


def test_shade_takes_normals_and_views_of_any_length(http, field):
    """A normal or view of length 1e-200 is a direction like any other."""
    base = {"position": POS.tolist(), "normal": [0.0, 1.0, 0.0], "view": [0.6, 0.8, 0.0]}
    tiny = {"position": POS.tolist(), "normal": [0.0, 1e-200, 0.0], "view": [6e-200, 8e-200, 0.0]}
    a, b = (http.post("/v1/grids/lin/shade", json={"points": [p]}) for p in (base, tiny))
    assert a.status_code == b.status_code == 200, b.text
    assert a.json()["rgb"] == b.json()["rgb"]


# ------------------------------------------------------------------------------ bad input
BAD_REQUESTS = [
    ("GET", "/v1/grids/lin/sh?y=0&z=0", None, 422, "query x"),
    ("GET", "/v1/grids/lin/sh?x=nan&y=0&z=0", None, 422, "finite"),
    ("GET", "/v1/grids/lin/sh?x=inf&y=0&z=0", None, 422, "finite"),
    ("GET", "/v1/grids/lin/sh?x=abc&y=0&z=0", None, 422, "query x"),
    ("GET", "/v1/grids/lin/sh?x=0&y=0&z=0&nx=1&ny=0", None, 422, "all three"),
    ("GET", "/v1/grids/lin/sh?x=0&y=0&z=0&nx=0&ny=0&nz=0", None, 422, "zero vector"),
    # beyond the body's coordinate bound (schemathesis: a normal made the float32 segment test
    # refuse x=2e134 with "segment end points must be finite")
    ("GET", "/v1/grids/lin/sh?x=2e134&y=0&z=0&nx=1&ny=0&nz=0", None, 422, "largest coordinate"),
    ("GET", "/v1/grids/lin/maps/diffuse?x=0&y=-1e13&z=0", None, 422, "query y"),
    ("GET", "/v1/grids/nope/sh?x=0&y=0&z=0", None, 404, "no grid 'nope'"),
    ("GET", "/v1/grids/..%2F..%2Fetc%2Fpasswd/sh?x=0&y=0&z=0", None, 404, ""),
    ("GET", "/v1/grids/lin.probes/sh?x=0&y=0&z=0", None, 404, "no grid"),
    ("GET", "/v1/grids/lin/maps/phong?x=0&y=0&z=0", None, 404, "no 'phong' maps"),
    ("GET", "/v1/grids/second/maps/incoming?x=0&y=0&z=0", None, 404, "no 'incoming' maps"),
    ("GET", "/v1/grids/lin/maps/specular?x=0&y=0&z=0&level=4", None, 422, "out of range 0..3"),
    ("GET", "/v1/grids/lin/maps/diffuse?x=0&y=0&z=0&level=1", None, 422, "out of range 0..0"),
    ("GET", "/v1/grids/lin/maps/diffuse?x=0&y=0&z=0&level=-1", None, 422, "level"),
    ("GET", "/v1/grids/lin/maps/diffuse?x=0&y=0&z=0&format=jpg", None, 422, "format"),
    ("GET", "/v1/grids/lin/maps/diffuse?x=0&y=0&z=0&layout=vcross", None, 422, "layout"),
    ("GET", "/v1/grids/lin/maps/specular?x=0&y=0&z=0&format=json", None, 422, "limit of 1000"),
    ("GET", "/v1/nothing", None, 404, "no route"),
    ("DELETE", "/v1/grids/lin", None, 405, "not allowed"),
    ("POST", "/v1/grids/lin/shade", b'{"points": [[0, 0', 400, "not valid JSON"),
    ("POST", "/v1/grids/lin/shade", b"[]", 422, ""),
    ("POST", "/v1/grids/lin/shade", {"points": []}, 422, "at least 1"),
    ("POST", "/v1/grids/lin/shade",
     {"points": [{"position": [0, 0, 0], "normal": [0, 1, 0]}]}, 422, "view"),
    ("POST", "/v1/grids/lin/shade",
     {"points": [{"position": [0, 0, 0], "normal": [0, 0, 0], "view": [0, 0, 1]}]}, 422,
     "zero vector"),
    ("POST", "/v1/grids/lin/shade",
     {"points": [{"position": [0, 0, 0], "normal": [0, 1, 0], "view": [0, 0, 1]}],
      "material": {"roughness": 2}}, 422, "roughness"),
    ("POST", "/v1/grids/lin/shade",
     {"points": [{"position": [0, 0, 1e300], "normal": [0, 1, 0], "view": [0, 0, 1]}]}, 422,
     "position"),
    ("POST", "/v1/grids/lin/shade",
     {"points": [{"position": [0, 0, 0], "normal": [0, 1, 0], "view": [0, 0, 1]}] * 65},
     413, "limit of 64"),
    ("POST", "/v1/grids/lin/shade", b"[" + b"0," * 40000 + b"0]", 413, "65536 bytes"),
    ("POST", "/v1/lights/maps", {"position": [0, 0, 0], "lights": []}, 422, "lights"),
    ("POST", "/v1/lights/maps",
     {"position": [0, 1.5, 0], "lights": [{"type": "point", "position": [0, 1.5, 1e-16],
                                           "intensity": 1e12}]}, 422, "overflows"),
    ("POST", "/v1/lights/maps",
     {"position": [0, 1.5, 0], "lights": [{"type": "point", "position": [0, 1.5, 1e-160],
                                           "intensity": 1}]}, 422, "almost exactly"),
    ("POST", "/v1/lights/maps",
     {"position": [0, 0, 0], "grid": "lin", "normal": [0, 0, 0],
      "lights": [{"type": "point", "position": [1, 1, 1], "intensity": 1}]}, 422, "zero vector"),
    ("POST", "/v1/grids/lin/shade",
     b'{"points": [{"position": [0, NaN, 0], "normal": [0, 1, 0], "view": [0, 0, 1]}]}',
     422, "finite"),
    ("POST", "/v1/lights/maps",
     {"position": [0, 0, 0], "lights": [{"type": "laser", "intensity": 1}]}, 422, "lights"),
    ("POST", "/v1/lights/maps",
     {"position": [0, 0, 0], "lights": [{"type": "point", "position": [1, 1, 1],
                                         "intensity": 1}] * 5}, 422, "limit of 4"),
    ("POST", "/v1/lights/maps",
     {"position": [0, 0, 0], "diffuse_size": 64,
      "lights": [{"type": "point", "position": [1, 1, 1], "intensity": 1}]}, 422, "limit of 32"),
    ("POST", "/v1/lights/maps",
     {"position": [0, 0, 0], "kind": "specular", "specular_size": 12,
      "lights": [{"type": "point", "position": [1, 1, 1], "intensity": 1}]}, 422, "power-of-two"),
    ("POST", "/v1/lights/maps",
     {"position": [0, 0, 0], "grid": "../lin",
      "lights": [{"type": "point", "position": [1, 1, 1], "intensity": 1}]}, 404, "no grid"),
]


@pytest.mark.parametrize(("method", "url", "body", "status", "words"), BAD_REQUESTS,
                         ids=[f"{m} {u[:48]} {s}" for m, u, _, s, _ in BAD_REQUESTS])
def test_bad_input_gets_a_clear_4xx_json_error(http, method, url, body, status, words):
    kw = {"content": body} if isinstance(body, bytes) else {"json": body}
    if isinstance(body, bytes):
        kw["headers"] = {"Content-Type": "application/json"}
    r = http.request(method, url, **kw)
    assert r.status_code == status, r.text
    doc = r.json()
    assert set(doc) >= {"error", "message"} and doc["message"].endswith(".")
    assert words.lower() in doc["message"].lower(), doc["message"]
    assert http.get("/healthz").status_code == 200  # and the server keeps serving


def test_bodies_must_be_json(http):
    body = json.dumps({"points": [{"position": [0, 0, 0], "normal": [0, 1, 0],
                                   "view": [0, 0, 1]}]})
    for url in ("/v1/grids/lin/shade", "/v1/lights/maps"):
        r = http.post(url, content=body, headers={"Content-Type": "text/plain"})
        assert r.status_code == 415 and r.json()["error"] == "unsupported_media_type", r.text
        assert "application/json" in r.json()["message"]
    ok = http.post("/v1/grids/lin/shade", content=body,
                   headers={"Content-Type": "application/json; charset=utf-8"})
    assert ok.status_code == 200, ok.text


def test_declared_oversized_body_is_refused_before_reading(server):
    host, port = server.url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=10) as sock:
        sock.sendall(b"POST /v1/lights/maps HTTP/1.1\r\nHost: x\r\n"
                     b"Content-Type: application/json\r\nContent-Length: 10000000\r\n\r\n")
        reply = b""
        while b"\r\n\r\n" not in reply or not reply.rstrip().endswith(b"}"):
            chunk = sock.recv(4096)
            if not chunk:
                break
            reply += chunk
    head, _, body = reply.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 413")
    assert json.loads(body)["error"] == "too_large"


# ------------------------------------------------------------------------------ concurrency
def test_concurrent_clients_get_consistent_answers(server, field):
    rng = np.random.default_rng(11)
    pts = GRID.lo + rng.random((16, 3)) * (GRID.hi - GRID.lo)
    want_sh = field.sh(field.weights(pts))
    want_map = field.cube(field.weights(pts), "diffuse")
    errors: list[str] = []
    lock = threading.Lock()

    def worker(seed: int) -> int:
        done = 0
        with httpx.Client(base_url=server.url, timeout=30.0) as c:
            for k in range(12):
                i = (seed * 7 + k) % len(pts)
                q = {"x": str(float(pts[i, 0])), "y": str(float(pts[i, 1])), "z": str(float(pts[i, 2]))}
                sh = np.array(c.get("/v1/grids/lin/sh", params=q).json()["coefficients"])
                m = _npy(c.get("/v1/grids/lin/maps/diffuse",
                               params={**q, "format": "npy"}).content)
                if not (np.array_equal(sh, want_sh[i]) and np.array_equal(m, want_map[i])):
                    with lock:
                        errors.append(f"point {i}")
                done += 1
        return done

    with ThreadPoolExecutor(max_workers=8) as pool:
        assert sum(pool.map(worker, range(8))) == 96
    assert errors == []


# ------------------------------------------------------------------------------ fuzzing
def _fuzz_strategies(schema, grids: list[str]):
    """(label, strategy) pairs: free generation plus the served grid names and map kinds."""
    for result in schema.get_all_operations():
        op = result.ok()
        params = [p.name for p in op.path_parameters]
        variants = [None]
        if "grid" in params:
            variants = [None] + [{"grid": g} for g in grids]
            if "kind" in params:
                variants += [{"grid": "lin", "kind": k} for k in ("diffuse", "specular",
                                                                  "incoming")]
        for mode in GenerationMode:
            for path in variants:
                kw = {} if path is None else {"path_parameters": path}
                yield f"{op.label} {mode.value} {path}", op.as_strategy(mode, **kw)


def _fuzz_check(label: str, strategy, url: str, seen: dict[int, int]):
    @given(case=strategy)
    @settings(max_examples=20, deadline=None, database=None, derandomize=True,
              suppress_health_check=list(HealthCheck), phases=[Phase.explicit, Phase.generate])
    def check(case):
        r = case.call(base_url=url, timeout=30)
        seen[r.status_code] = seen.get(r.status_code, 0) + 1
        assert r.status_code < 500, (label, case.method, case.formatted_path, case.query,
                                     r.status_code, r.text[:300])
        if r.status_code >= 400:
            assert set(json.loads(r.text)) >= {"error", "message"}

    return check


@pytest.mark.slow
def test_fuzz_openapi_never_gives_5xx(server):
    schema = schemathesis.openapi.from_url(server.url + "/openapi.json")
    seen: dict[int, int] = {}
    ran = 0
    for label, strategy in _fuzz_strategies(schema, ["lin", "second"]):
        try:
            _fuzz_check(label, strategy, server.url, seen)()
            ran += 1
        except hypothesis.errors.Unsatisfiable:  # e.g. no invalid input for /healthz
            continue
    assert ran >= 20 and sum(seen.values()) > 300, (ran, seen)
    assert all(s < 500 for s in seen) and 200 in seen and 422 in seen
    assert "internal_error" not in server.log_text()  # the last resort never fired


# ------------------------------------------------------------------------------ fast path
FAST_PATH_QUERIES = [
    "/v1/grids/lin/sh?x=0.75&y=0.25&z=1.5",
    "/v1/grids/lin/sh?x=0.75&y=0.25&z=1.5&nx=0.3&ny=-0.8&nz=0.5",
    "/v1/grids/lin/sh?x=-3&y=9&z=1e3",
    "/v1/grids/second/sh?x=-0.9&y=0.1&z=-0.9",
    "/v1/grids/lin/sh?x=1&y=1&z=1&x=0.5",
    "/v1/grids/lin/sh?x=1&y=1&z=1&&extra=&flag",
    "/v1/grids/lin/sh?x=0%2E75&y=0.25&z=1.5",
    "/v1/grids/lin/sh?x=+0.75&y=0.25&z=1.5",
    "/v1/grids/lin/sh?x=1&y=1",
    "/v1/grids/lin/sh?x=nan&y=1&z=1",
    "/v1/grids/lin/sh?x=abc&y=1&z=1",
    "/v1/grids/lin/sh?x=1&y=1&z=1&nx=1",
    "/v1/grids/lin/sh?x=1&y=1&z=1&nx=0&ny=0&nz=0",
    "/v1/grids/lin/sh?x=1&y=1&z=1&sh=raw",
    "/v1/grids/lin/sh?x=1&y=1&z=1&sh=deringed&nx=0&ny=1&nz=0",
    "/v1/grids/lin/sh?x=1&y=1&z=1&sh=ringing",
    "/v1/grids/lin/sh?x=1&y=1&z=1&sh=",
    "/v1/grids/nope/sh?x=nan",
    "/v1/grids/lin/maps/diffuse?x=0.75&y=0.25&z=1.5&format=npy",
    "/v1/grids/lin/maps/diffuse?x=0.75&y=0.25&z=1.5&format=npy&nx=0&ny=1&nz=0&layout=cross",
    "/v1/grids/lin/maps/specular?x=0.75&y=0.25&z=1.5&format=json&level=2",
    "/v1/grids/lin/maps/incoming?x=0.75&y=0.25&z=1.5&format=png",
    "/v1/grids/lin/maps/diffuse?x=0.75&y=0.25&z=1.5",
    "/v1/grids/lin/maps/specular?x=0&y=0&z=0&format=npy&level=02",
    "/v1/grids/lin/maps/specular?x=0&y=0&z=0&format=npy&level=+1",
    "/v1/grids/lin/maps/specular?x=0&y=0&z=0&format=npy&level=",
    "/v1/grids/lin/maps/specular?x=0&y=0&z=0&format=npy&level=64",
    "/v1/grids/lin/maps/specular?x=0&y=0&z=0&format=npy&level=65",
    "/v1/grids/lin/maps/specular?x=0&y=0&z=0&format=npy&level=-1",
    "/v1/grids/lin/maps/specular?x=0&y=0&z=0&format=npy&level=1.0",
    "/v1/grids/lin/maps/diffuse?x=0&y=0&z=0&format=gif",
    "/v1/grids/lin/maps/diffuse?x=0&y=0&z=0&format=NPY",
    "/v1/grids/lin/maps/diffuse?x=0&y=0&z=0&layout=vcross",
    "/v1/grids/lin/maps/bogus?x=0&y=0&z=0&format=npy",
    "/v1/grids/second/maps/incoming?x=0&y=0&z=0&format=npy",
    "/v1/grids/lin/maps/specular?x=0&y=0&z=0&format=json",
    "/v1/grids/lin/maps/diffuse?x=nan&y=0&z=0&level=-1",
    "/v1/grids/lin/maps/diffuse?y=0&z=0&format=gif",
]


async def _force_fastapi() -> None:
    """A dependency override that nothing uses: while it is set, every route resolves its
    arguments through FastAPI (service.fastroute)."""


def test_fast_path_answers_exactly_as_fastapi(stores, monkeypatch):
    """The resolvers of /sh and /maps give the same status, headers and bytes as FastAPI's own
    argument resolution, for good queries and every kind of bad one."""
    import asyncio

    import service.routers.maps as maps_router
    import service.routers.sh as sh_router
    from service.settings import Settings

    app = create_app([stores["lin"], stores["second"]], Settings(**LIMITS))
    resolved = []
    for module in (sh_router, maps_router):  # count the fast path's resolutions
        real = module.plain_query
        monkeypatch.setattr(module, "plain_query",
                            lambda request, real=real: resolved.append(1) or real(request))

    async def fetch_all() -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            return [await c.get(url) for url in FAST_PATH_QUERIES]

    fast = asyncio.run(fetch_all())
    assert len(resolved) == len(FAST_PATH_QUERIES)
    app.dependency_overrides[_force_fastapi] = _force_fastapi
    slow = asyncio.run(fetch_all())
    assert len(resolved) == len(FAST_PATH_QUERIES)  # no fast path while overrides are set
    for url, a, b in zip(FAST_PATH_QUERIES, fast, slow, strict=True):
        assert (a.status_code, a.headers.multi_items(), a.content) == (
            b.status_code, b.headers.multi_items(), b.content), url
        assert a.status_code < 500, url
    statuses = {r.status_code for r in fast}
    assert statuses == {200, 404, 422}


def test_plain_query_reads_what_starlette_reads():
    from starlette.requests import Request

    from service.deps import plain_query

    for raw in (b"", b"x=1", b"x=1&y=2&x=3", b"x=1&&y=&z", b"=1&a==b&c=d=e", b"x=1;y=2",
                b"x=\xe9", b"x=%31", b"x=+1", b"a+b=1"):
        request = Request({"type": "http", "query_string": raw})
        got = plain_query(request)
        names = [k for k, _ in request.query_params.multi_items()]
        if b"%" in raw or b"+" in raw or len(names) != len(set(names)):
            assert got is None  # FastAPI's handler decides (a repeated name is a 422)
        else:
            assert got == {k: request.query_params[k] for k in request.query_params}, raw


def test_fast_path_route_refuses_what_it_would_bypass():
    from fastapi import APIRouter, Depends, Response

    from service.fastroute import FastPathRoute, fast_path

    router = APIRouter(route_class=FastPathRoute)
    with pytest.raises(ValueError, match="dependencies"):
        @router.get("/a", dependencies=[Depends(_force_fastapi)])
        @fast_path(lambda request: None)
        async def a() -> Response:
            return Response()
    with pytest.raises(ValueError, match="async endpoint"):
        @router.get("/b")
        @fast_path(lambda request: None)
        def b() -> Response:
            return Response()


def test_npy_bodies_are_numpy_save_bytes_and_exr_bodies_carry_no_date(tmp_path):
    from service.encoding import encode_cube

    rng = np.random.default_rng(7)
    for n in (1, 4, 16):
        faces = rng.random((6, n, n, 3)).astype(np.float32)
        for layout in ("faces", "cross"):
            buf = io.BytesIO()
            img = faces if layout == "faces" else faces_to_cross(faces, "hcross")
            np.save(buf, img, allow_pickle=False)
            assert encode_cube(faces, fmt="npy", layout=layout, scratch=tmp_path) == \
                buf.getvalue()
    exr = encode_cube(faces, fmt="exr", layout="faces", scratch=tmp_path)
    assert exr[:4] == b"v/1\x01" and b"capDate" not in exr  # no time stamp: same bytes later


# ------------------------------------------------------------------------------ app building
def test_a_store_replaced_on_disk_is_served_whole_from_the_old_files(stores, tmp_path):
    """A new bake renamed over a served store (``--overwrite``) is served whole from the old
    files until the registry has opened and checked the new one (then whole from the new;
    test_service_stores.py), never as a mix, not even for arrays no request had touched."""
    import asyncio
    import shutil

    from service.settings import Settings

    path = tmp_path / "swap.probes"
    shutil.copytree(stores["lin"], path)
    app = create_app([path], Settings(**LIMITS))
    arrays = linear_arrays(GRID)
    for name in ("sh", "diffuse", "positions"):
        arrays[name] = arrays[name] * 2
    arrays["moments"][..., 0] = 0.01  # every probe now sees a wall at 1 cm
    new = tmp_path / "new.probes"
    write_store(new, GRID, arrays)
    shutil.rmtree(path)
    new.rename(path)

    async def fetch() -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            q = {**POINT, "nx": "0", "ny": "1", "nz": "0"}
            return [await c.get("/v1/grids/swap/sh", params=q),
                    await c.get("/v1/grids/swap/maps/diffuse", params={**q, "format": "npy"})]

    app.state.probegrid.grids._watch["swap"].next_check = float("inf")  # no reload yet
    sh_r, map_r = asyncio.run(fetch())
    old = ProbeField(open_store(stores["lin"]))
    w = old.weights(POS, normals=(0.0, 1.0, 0.0))
    np.testing.assert_array_equal(np.array(sh_r.json()["coefficients"]), old.sh(w)[0])
    np.testing.assert_array_equal(_npy(map_r.content), old.cube(w, "diffuse")[0])


def test_create_app_refuses_bad_stores(stores, tmp_path):
    with pytest.raises(StoreError):
        create_app([tmp_path / "missing.probes"])
    with pytest.raises(ValueError, match="served as 'lin'"):
        create_app([stores["lin"], stores["lin"]])
    with pytest.raises(ValueError, match="grid name"):
        grid_name(tmp_path / "bad name!.probes")
    assert grid_name("/a/b/atrium.probes") == "atrium"


@pytest.mark.slow
def test_multiple_workers_share_the_stores(stores, tmp_path):
    with (
        serve([stores["lin"]], tmp_path / "w2.log", workers=2, settings=LIMITS) as live,
        httpx.Client(base_url=live.url) as c,
    ):
        bodies = {c.get("/v1/grids/lin/sh", params=POINT).content for _ in range(20)}
        assert len(bodies) == 1
        assert c.get("/v1/grids").json()["grids"][0]["name"] == "lin"


def test_last_resort_turns_a_bug_into_a_logged_500(stores, caplog):
    """The mechanism the fuzz run proves idle: an unexpected exception is logged with its
    traceback and a reference, and answered 500 ``internal_error`` with a JSON body (a server bug
    is a server error; in-process app, a route that fails on purpose). The client maps it to
    its ServerError."""
    app = create_app([stores["lin"]])

    @app.get("/fail")
    async def fail() -> None:
        raise RuntimeError("a bug")

    async def main():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            return await c.get("/fail"), await c.get("/healthz")

    import asyncio

    with caplog.at_level("ERROR", logger="probegrid.service"):
        bad, ok = asyncio.run(main())
    assert bad.status_code == 500 and bad.json()["error"] == "internal_error"
    assert bad.headers["content-type"] == "application/json"
    ref = bad.json()["message"].split("reference ")[1].split(")")[0]
    assert any(ref in r.getMessage() and r.exc_info for r in caplog.records)
    assert ok.status_code == 200


def test_example_usage_names_a_working_query(http, stores, server):
    text = example_usage(stores["lin"], server.url)
    url = text.split("'")[1]
    assert url == f"{server.url}/v1/grids/lin/sh?x=1&y=0.5&z=1"
    assert http.get(url.removeprefix(server.url)).status_code == 200
    assert "ProbeGridClient(" in text and ".sh_at('lin', (1, 0.5, 1))" in text


# ----------------------------------------------------------------------- visibility and deringed SH
def test_sh_and_maps_say_which_visibility_test_and_which_sh(tmp_path):
    """A store with the scene's triangles (a wall at x = 0.5) and deringed SH: the probes
    behind the wall get no weight, with or without a normal, and the responses say
    'segments'; /sh gives the stored deringed SH by default and the raw SH on request."""
    from probe_stores import WALL_X, walled_store

    from service.settings import Settings

    store = walled_store(tmp_path / "walled.probes")
    field = ProbeField(open_store(store.path))
    app = create_app([store.path], Settings(**LIMITS))
    behind = field.store.grid.positions()[:, 0] < WALL_X
    client = _InProcess(app)
    for extra in ({}, {"nx": "1", "ny": "0", "nz": "0"}):
        params = {**POINT, **extra}
        doc = client.get("/v1/grids/walled/sh", params=params).json()
        assert doc["flags"]["visibility_test"] == "segments"
        assert doc["sh"] == "deringed" and doc["sh_source"] == "store"
        assert doc["probes"] and not any(behind[p["index"]] for p in doc["probes"])
        assert sum(p["weight"] for p in doc["probes"]) == pytest.approx(1.0, abs=1e-15)
        nrm = None if not extra else np.array([1.0, 0.0, 0.0])
        w = field.weights(POS, normals=nrm)
        np.testing.assert_array_equal(np.array(doc["coefficients"]), field.sh(w)[0])
        np.testing.assert_array_equal(
            np.array(doc["coefficients"]),
            np.einsum("k,kic->ic", w.weights[0],
                      np.asarray(field.store["sh_deringed"], np.float64)[w.indices[0]]))
        raw = client.get("/v1/grids/walled/sh", params={**params, "sh": "raw"}).json()
        assert raw["sh"] == "raw"
        np.testing.assert_array_equal(np.array(raw["coefficients"]),
                                      field.sh(w, kind="raw")[0])
        assert not np.array_equal(raw["coefficients"], doc["coefficients"])  # it rings
        r = client.get("/v1/grids/walled/maps/diffuse",
                       params={**params, "format": "npy"})
        assert r.headers["x-probegrid-visibility"] == "segments"
        np.testing.assert_array_equal(_npy(r.content), field.cube(w, "diffuse")[0])
        probes = [int(p.split(":")[0]) for p in r.headers["x-probegrid-probes"].split(",")]
        assert not behind[probes].any()
        meta = client.get("/v1/grids/walled/maps/diffuse",
                          params={**params, "format": "json"}).json()
        assert meta["flags"]["visibility_test"] == "segments"
    bad = client.get("/v1/grids/walled/sh", params={**POINT, "sh": "ringing"})
    assert bad.status_code == 422 and "sh" in bad.text


class _InProcess:
    """Blocking GETs to an app in this process (httpx.ASGITransport, one event loop each)."""

    def __init__(self, app) -> None:
        self.app = app

    def get(self, url: str, params: dict[str, str] | None = None) -> httpx.Response:
        import asyncio

        async def fetch() -> httpx.Response:
            transport = httpx.ASGITransport(app=self.app)
            async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
                return await c.get(url, params=params)

        return asyncio.run(fetch())
