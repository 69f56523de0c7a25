"""The viewer's server side: packaged static files (hashes, gzip, caching), offline docs, the
probes / scene / DFG routes, and the scene copy a store keeps (no browser; see test_viewer.py)."""

from __future__ import annotations

import base64
import gzip
import importlib.util
import io
import json
import re
import struct
from pathlib import Path

import httpx
import numpy as np
import pytest
from live_server import serve
from probe_stores import GRID, linear_arrays, write_store

from probegrid.core.dfg import dfg_lut
from probegrid.store import StoreError, StoreWriter, keepable_scene, open_store
from service.deps import DFG_SIZE
from service.webassets import STATIC_DIR

REPO = Path(__file__).resolve().parents[1]
SAMPLE_GLB = REPO / "data" / "sample_room.glb"


def _vendor_script():
    spec = importlib.util.spec_from_file_location("vendor_web", REPO / "scripts" / "vendor_web.py")
    module = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(module)
    return module


def _store_with_scene(path: Path, scene: Path | None, grid=GRID, arrays=None):
    arrays = linear_arrays(grid) if arrays is None else arrays
    from probe_stores import ArraySpec, conventions  # the helpers' own imports

    writer = StoreWriter.create(
        path, arrays={n: ArraySpec(a.shape[1:], a.dtype.str) for n, a in arrays.items()},
        grid=grid, conventions=conventions(), scene_hash="synthetic", bake={})
    writer.write(np.arange(grid.n_probes), arrays)
    return writer.finish(quality={}, scene_file=scene)


@pytest.fixture(scope="module")
def stores(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("viewer-stores")
    _store_with_scene(root / "kept.probes", SAMPLE_GLB)
    arrays = linear_arrays(GRID)
    arrays["valid"][[1, 5]] = False
    arrays["positions"][4] += np.float32(0.125)  # relocated
    write_store(root / "plain.probes", GRID, arrays)  # keeps no scene
    hot = linear_arrays(GRID)
    hot["sh"][7, 0, 1] = 1e5  # beyond half float
    write_store(root / "hot.probes", GRID, hot)
    return {"kept": root / "kept.probes", "plain": root / "plain.probes",
            "hot": root / "hot.probes"}


@pytest.fixture(scope="module")
def client(stores, tmp_path_factory):
    log = tmp_path_factory.mktemp("log") / "server.log"
    with serve(list(stores.values()), log) as live, \
            httpx.Client(base_url=live.url, timeout=30.0) as c:
        yield c


# ------------------------------------------------------------------------------ vendored files
def test_vendored_files_match_their_hashes():
    vendor = _vendor_script()
    assert vendor.check() == []
    listed = vendor.read_hashes()
    for name, (version, files) in vendor.PACKAGES.items():
        assert {f"{name}/{f}" for f in files} <= set(listed), name
    assert "three/build/three.module.js" in listed and "three/LICENSE" in listed
    assert "REVISION = '187'" in (STATIC_DIR / "vendor/three/build/three.core.js").read_text()


def test_viewer_page_uses_only_packaged_files(client):
    r = client.get("/", headers={"Accept-Encoding": "gzip"})
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert r.headers["cache-control"] == "no-cache" and r.headers["etag"]
    html = r.text
    imports = json.loads(re.search(r'<script type="importmap">(.*?)</script>', html, re.DOTALL)[1])
    urls = list(imports["imports"].values()) + re.findall(r'(?:src|href)="([^"]+)"', html)
    assert all(u.startswith(("/static/", "/docs", "/redoc")) for u in urls), urls
    for u in urls:
        if u.startswith("/static/") and not u.endswith("/"):
            assert client.get(u).status_code == 200, u
    assert client.get("/", headers={"If-None-Match": r.headers["etag"]}).status_code == 304


def test_static_files_are_gzipped_immutable_and_keyed_by_content(client):
    prefix = re.search(r'"three": "(/static/[0-9a-f]+)/', client.get("/").text)[1]
    url = prefix + "/vendor/three/build/three.module.js"
    raw = (STATIC_DIR / "vendor/three/build/three.module.js").read_bytes()
    with client.stream("GET", url, headers={"Accept-Encoding": "gzip"}) as r:
        body = b"".join(r.iter_raw())  # the bytes on the wire
        headers = r.headers
    assert headers["content-encoding"] == "gzip" and headers["vary"] == "Accept-Encoding"
    assert "immutable" in headers["cache-control"] and "max-age=31536000" in headers["cache-control"]
    assert gzip.decompress(body) == raw and len(body) < 0.3 * len(raw)
    plain = client.get(url, headers={"Accept-Encoding": "identity"})
    assert "content-encoding" not in plain.headers and plain.content == raw
    assert plain.headers["etag"] != headers["etag"]
    again = client.get(url, headers={"Accept-Encoding": "gzip", "If-None-Match": headers["etag"]})
    assert again.status_code == 304
    # another build's tag, or a path that is not a packaged file: a JSON 404, never a file read
    for bad in ("/static/0000000000000000/viewer.js", prefix + "/../../pyproject.toml",
                prefix + "/nope.js", prefix + "/%2e%2e/main.py"):
        r = client.get(bad)
        assert r.status_code == 404 and r.json()["error"] == "not_found", bad


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_load_nothing_from_elsewhere(client, page):
    r = client.get(page)
    assert r.status_code == 200
    urls = re.findall(r'(?:src|href|url)\s*[=:]\s*["\']([^"\']+)["\']', r.text)
    assert urls and all(u.startswith("/") for u in urls), urls
    assert "cdn" not in r.text.lower() and "fonts.googleapis" not in r.text
    for u in urls:
        if u.startswith("/static/"):
            assert client.get(u).status_code == 200, u


# ------------------------------------------------------------------------------ probes
def _b64(text: str, dtype: str) -> np.ndarray:
    return np.frombuffer(base64.b64decode(text), dtype=dtype)


def test_probes_route_returns_every_probe(client, stores):
    doc = client.get("/v1/grids/plain/probes").json()
    store = open_store(stores["plain"])
    n = store.n_probes
    assert doc["grid"] == "plain" and doc["probes"] == n and doc["counts"] == [3, 2, 3]
    np.testing.assert_array_equal(_b64(doc["positions"], "<f4").reshape(n, 3),
                                  np.asarray(store["positions"], np.float32))
    np.testing.assert_array_equal(_b64(doc["sh"], "<f4").reshape(n, 9, 3), store["sh"])
    valid = _b64(doc["valid"], "u1")
    assert valid.tolist() == np.asarray(store["valid"]).astype(int).tolist()
    assert np.flatnonzero(valid == 0).tolist() == [1, 5]
    assert np.flatnonzero(_b64(doc["relocated"], "u1")).tolist() == [4]
    r = client.get("/v1/grids/plain/probes", headers={"If-None-Match": '"x", ' + client.get(
        "/v1/grids/plain/probes").headers["etag"]})
    assert r.status_code == 304
    r = client.get("/v1/grids/nope/probes")
    assert r.status_code == 404 and "kept" in r.json()["message"]


# ------------------------------------------------------------------------------ scene
def test_scene_route_serves_the_kept_copy(client, stores):
    r = client.get("/v1/grids/kept/scene")
    assert r.status_code == 200 and r.headers["content-type"] == "model/gltf-binary"
    assert r.content == SAMPLE_GLB.read_bytes()
    kept = open_store(stores["kept"]).manifest.scene_file
    assert kept is not None and kept.source == "sample_room.glb" and kept.file == "scene.glb"
    assert client.get("/v1/grids/kept/scene",
                      headers={"If-None-Match": r.headers["etag"]}).status_code == 304
    r = client.get("/v1/grids/plain/scene")
    assert r.status_code == 404 and "keeps no copy" in r.json()["message"]
    assert open_store(stores["plain"]).manifest.scene_file is None


def test_keepable_scene_kinds(tmp_path):
    assert keepable_scene(SAMPLE_GLB) == "scene.glb"
    embedded = {"asset": {"version": "2.0"},
                "buffers": [{"uri": "data:application/octet-stream;base64,AAAA", "byteLength": 3}]}
    (tmp_path / "a.gltf").write_text(json.dumps(embedded))
    assert keepable_scene(tmp_path / "a.gltf") == "scene.gltf"
    external = {"asset": {"version": "2.0"}, "buffers": [{"uri": "mesh.bin", "byteLength": 3}]}
    (tmp_path / "b.gltf").write_text(json.dumps(external))
    assert keepable_scene(tmp_path / "b.gltf") is None
    (tmp_path / "c.gltf").write_bytes(b"\x00\x01not json")
    with pytest.raises(StoreError, match="not a readable glTF"):
        keepable_scene(tmp_path / "c.gltf")
    with pytest.raises(StoreError, match="not a readable glTF"):
        keepable_scene(tmp_path / "missing.glb")


def test_store_with_external_gltf_keeps_none_and_a_damaged_copy_is_refused(tmp_path):
    external = {"asset": {"version": "2.0"}, "buffers": [{"uri": "mesh.bin", "byteLength": 3}]}
    (tmp_path / "b.gltf").write_text(json.dumps(external))
    s = _store_with_scene(tmp_path / "ext.probes", tmp_path / "b.gltf")
    assert s.manifest.scene_file is None and not (s.path / "scene.gltf").exists()
    s = _store_with_scene(tmp_path / "k.probes", SAMPLE_GLB)
    with open(s.path / "scene.glb", "ab") as f:
        f.write(b"x")
    with pytest.raises(StoreError, match="scene.glb is missing or is not the"):
        open_store(s.path)


# ------------------------------------------------------------------------------ three.js export
def _three_texel(atlas: np.ndarray, counts, i: int, j: int, k: int) -> np.ndarray:
    """Probe (i, j, k)'s 27 SH floats read from the atlas by three's shader layout
    (lightprobes_pars_fragment r187: sub-volume t at slices t (nz + 2) + 1 + k, four per texel)."""
    nz = counts[2]
    flat = np.concatenate([atlas[t * (nz + 2) + 1 + k, j, i] for t in range(7)])
    assert flat[27] == 0
    return flat[:27].reshape(9, 3)


def test_threejs_export_route_is_the_store_sh_in_three_layout(client, stores):
    store = open_store(stores["plain"])  # probes 1 and 5 invalid
    nx, ny, nz = store.grid.counts
    head = client.get("/v1/grids/plain/export/threejs.json").json()
    # three places probe i at min + (i + 0.5) size / n: the store's lattice (0..2, 0..1, 0..2)
    assert head["resolution"] == [3, 2, 3] and head["size"] == [3.0, 2.0, 3.0]
    assert head["position"] == [1.0, 0.5, 1.0]
    assert head["min"] == [-0.5, -0.5, -0.5] and head["max"] == [2.5, 1.5, 2.5]
    assert head["atlas_size"] == [3, 2, 7 * (3 + 2)] and head["filled_invalid"] == 2
    r = client.get("/v1/grids/plain/export/threejs.bin")
    assert r.headers["content-type"] == "application/octet-stream"
    atlas = np.frombuffer(r.content, "<f2").reshape(7 * (nz + 2), ny, nx, 4).astype(np.float32)
    sh = np.asarray(store["sh"], np.float64)
    valid = np.asarray(store["valid"], bool)
    for p in range(store.n_probes):
        i, j, k = np.unravel_index(p, (nx, ny, nz))
        if valid[p]:
            want = sh[p]
        else:  # the mean of the valid face neighbours
            nb = [(i + a, j + b, k + c) for a, b, c in
                  [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]]
            idx = [np.ravel_multi_index(q, (nx, ny, nz)) for q in nb
                   if all(0 <= q[d] < (nx, ny, nz)[d] for d in range(3))]
            want = np.mean([sh[q] for q in idx if valid[q]], axis=0)
        # the decoded atlas is the store's SH after rounding to half float, exactly
        np.testing.assert_array_equal(_three_texel(atlas, (nx, ny, nz), i, j, k),
                                      want.astype(np.float16).astype(np.float32), err_msg=str(p))
    for t in range(7):  # one padding slice each end, a copy of the edge data slice
        base = t * (nz + 2)
        np.testing.assert_array_equal(atlas[base], atlas[base + 1])
        np.testing.assert_array_equal(atlas[base + nz + 1], atlas[base + nz])
    full = np.frombuffer(client.get("/v1/grids/plain/export/threejs.bin",
                                    params={"dtype": "float32"}).content, "<f4")
    full = full.reshape(atlas.shape)
    np.testing.assert_array_equal(_three_texel(full, (nx, ny, nz), 2, 1, 0),
                                  np.asarray(store["sh"], np.float32)[
                                      np.ravel_multi_index((2, 1, 0), (nx, ny, nz))])
    from probegrid.export.ktx2 import read_ktx2

    tex = read_ktx2(client.get("/v1/grids/plain/export/threejs.ktx2").content)
    assert tex.kind == "3d" and tex.vk_format == 97
    np.testing.assert_array_equal(tex.levels[0], atlas)
    assert client.get("/v1/grids/plain/export/threejs.bin", headers={
        "If-None-Match": r.headers["etag"]}).status_code == 304
    bad = client.get("/v1/grids/plain/export/threejs.bin", params={"dtype": "int8"})
    assert bad.status_code == 422 and "dtype" in bad.json()["message"]
    # a value beyond half float: the float16 forms refuse (one line), float32 carries it
    assert client.get("/v1/grids/hot/export/threejs.json").json()["float16_range_ok"] is False
    for form in ("threejs.bin", "threejs.ktx2"):
        r = client.get(f"/v1/grids/hot/export/{form}")
        assert r.status_code == 422 and "dtype=float32" in r.json()["message"], form
    hot = np.frombuffer(client.get("/v1/grids/hot/export/threejs.bin",
                                   params={"dtype": "float32"}).content, "<f4")
    assert hot.max() == 1e5
    missing = client.get("/v1/grids/nope/export/threejs.json")
    assert missing.status_code == 404 and "plain" in missing.json()["message"]


# ------------------------------------------------------------------------------ dfg
def test_dfg_route_is_the_library_table(client):
    r = client.get("/v1/dfg")
    assert r.headers["content-type"] == "application/x-npy"
    lut = np.load(io.BytesIO(r.content), allow_pickle=False)
    np.testing.assert_array_equal(lut, dfg_lut(DFG_SIZE).astype(np.float32))
    doc = client.get("/v1/dfg", params={"format": "json"}).json()
    assert doc["shape"] == [DFG_SIZE, DFG_SIZE, 2]
    assert client.get("/v1/dfg", params={"format": "exr"}).status_code == 422


def test_openapi_lists_the_viewer_routes_not_the_pages(client):
    paths = set(client.get("/openapi.json").json()["paths"])
    assert {"/v1/grids/{grid}/probes", "/v1/grids/{grid}/scene", "/v1/dfg",
            "/v1/grids/{grid}/export/threejs.json", "/v1/grids/{grid}/export/threejs.bin",
            "/v1/grids/{grid}/export/threejs.ktx2"} <= paths
    assert not {"/", "/docs", "/redoc"} & paths and not any(p.startswith("/static") for p in paths)


def test_glb_header_of_the_sample_scene():
    magic, version, length = struct.unpack("<4sII", SAMPLE_GLB.read_bytes()[:12])
    assert magic == b"glTF" and version == 2 and length == SAMPLE_GLB.stat().st_size
