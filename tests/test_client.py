"""Tests of the Python client (probegrid.client) against a real uvicorn server on 127.0.0.1."""

from __future__ import annotations

import asyncio
import contextlib
import http.server
import json
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from live_server import free_port, serve
from probe_stores import GRID, linear_store

import probegrid.client as client_module
from probegrid.client import (
    AsyncProbeGridClient,
    BadRequestError,
    GridInfo,
    InvalidArgumentError,
    NotFoundError,
    ProbeGridClient,
    ProbeGridConnectionError,
    ProbeGridError,
    ProbeGridHTTPError,
    ProbeGridResponseError,
    ProbeGridTimeoutError,
    ServerError,
    SHSample,
)
from probegrid.core.cubemap import CubeMap
from probegrid.core.dfg import dfg_lut
from probegrid.core.lights import DirectionalLight, PointLight, light_maps
from probegrid.query import ProbeField
from probegrid.store import StoreManifest, open_store
from service.deps import DFG_SIZE

POS = (0.75, 0.25, 1.5)


@pytest.fixture(scope="module")
def store_path(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("client") / "lin.probes"
    linear_store(path)
    return path


@pytest.fixture(scope="module")
def field(store_path) -> ProbeField:
    return ProbeField(open_store(store_path))


@pytest.fixture(scope="module")
def server(store_path, tmp_path_factory):
    with serve([store_path], tmp_path_factory.mktemp("log") / "server.log",
               settings={"max_batch": 32}) as live:
        yield live


@pytest.fixture()
def pg(server):
    with ProbeGridClient(server.url, timeout=30.0) as c:
        yield c


def test_public_api_is_declared():
    assert set(client_module.__all__) == {
        "AsyncProbeGridClient", "BadRequestError", "GridInfo", "NotFoundError", "ProbeGridClient",
        "ProbeGridConnectionError", "ProbeGridError", "ProbeGridHTTPError",
        "ProbeGridTimeoutError", "SHSample", "ServerError", "InvalidArgumentError",
        "ProbeGridResponseError", "MapSample",
    }
    for name in ("ProbeGridConnectionError", "ProbeGridTimeoutError", "ProbeGridHTTPError"):
        assert issubclass(getattr(client_module, name), ProbeGridError)
    for cls in (BadRequestError, NotFoundError, ServerError):
        assert issubclass(cls, ProbeGridHTTPError)


# ------------------------------------------------------------------------------ results
def test_grids_and_manifest(pg):
    (info,) = pg.grids()
    assert isinstance(info, GridInfo) and info.name == "lin" and info.manifest is None
    assert info.counts == (3, 2, 3) and info.kinds == ("diffuse", "specular", "incoming")
    assert info.map_sizes["specular"] == (8, 4, 2, 1)
    full = pg.grid("lin")
    assert isinstance(full.manifest, StoreManifest)
    assert full.manifest.grid == GRID
    assert pg.healthz() is True


def test_sh_at_equals_the_library(pg, field):
    s = pg.sh_at("lin", POS, normal=(0.0, 1.0, 0.2))
    assert isinstance(s, SHSample)
    w = field.weights(POS, normals=(0.0, 1.0, 0.2))
    np.testing.assert_array_equal(s.coefficients, field.sh(w)[0])
    used = w.weights[0] > 0
    np.testing.assert_array_equal(s.probes, w.indices[0][used])
    np.testing.assert_array_equal(s.weights, w.weights[0][used])
    assert s.visibility and not s.outside and not s.unlit
    assert s.visibility_test == "moments" and s.sh == "deringed" and s.sh_source == "computed"
    raw = pg.sh_at("lin", POS, normal=(0.0, 1.0, 0.2), sh="raw")
    assert raw.sh == "raw" and raw.sh_source == "store"
    np.testing.assert_array_equal(raw.coefficients, field.sh(w, kind="raw")[0])
    with pytest.raises(InvalidArgumentError, match="sh must be one of"):
        pg.sh_at("lin", POS, sh="ringing")
    out = pg.sh_at("lin", (5.0, 0.5, 0.5))
    assert out.outside and out.sampled_position.tolist() == [2.25, 0.5, 0.5]  # a quarter cell out


def test_maps_at_returns_cubemaps_equal_to_the_library(pg, field):
    w = field.weights(POS)
    diffuse = pg.maps_at("lin", POS)
    assert isinstance(diffuse, CubeMap) and diffuse.kind == "diffuse" and diffuse.num_levels == 1
    np.testing.assert_array_equal(diffuse.faces, field.cube(w, "diffuse")[0])
    spec = pg.maps_at("lin", POS, kind="specular")
    assert spec.num_levels == 4 and spec.kind == "specular"
    for k in range(4):
        np.testing.assert_array_equal(spec.levels[k], field.cube(w, "specular", level=k)[0])
    one = pg.maps_at("lin", POS, kind="specular", level=2)
    assert one.num_levels == 1
    np.testing.assert_array_equal(one.faces, spec.levels[2])
    wn = field.weights(POS, normals=(1.0, 0.0, 0.0))
    inc = pg.maps_at("lin", POS, kind="incoming", normal=(1.0, 0.0, 0.0))
    np.testing.assert_array_equal(inc.faces, field.cube(wn, "incoming")[0])


def test_shade_in_batches_equals_the_library(pg, field):
    rng = np.random.default_rng(2)
    n = 70  # three requests of at most 32 points
    pts = GRID.lo + rng.random((n, 3)) * (GRID.hi - GRID.lo)
    nrm, views = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    albedo = rng.uniform(0, 1, (n, 3))
    rough = rng.uniform(0, 1, n)
    got = pg.shade("lin", pts, nrm, views, albedo=albedo, roughness=rough, batch_size=32)
    want, _ = field.shade(pts, nrm, views, albedo=albedo, roughness=rough, f0=[0.04] * 3,
                          dfg=dfg_lut(DFG_SIZE))
    assert got.shape == (n, 3) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, rtol=1e-6)
    same = pg.shade("lin", pts[:5], nrm[:5], views[:5], albedo=(0.5, 0.5, 0.5), roughness=0.2)
    want5, _ = field.shade(pts[:5], nrm[:5], views[:5], albedo=[0.5] * 3, roughness=0.2,
                           f0=[0.04] * 3, dfg=dfg_lut(DFG_SIZE))
    np.testing.assert_allclose(same, want5, rtol=1e-6)


def test_light_maps_equal_the_library(pg, field):
    lights = [PointLight(position=(1.0, 2.0, 1.0), color=(1.0, 0.8, 0.6), intensity=30.0),
              DirectionalLight(direction=(0.0, -1.0, -1.0), color=(1, 1, 1), intensity=2.0)]
    got = pg.light_maps(POS, lights, diffuse_size=8)
    want = light_maps(lights, POS, diffuse_size=8, specular_size=1, specular_levels=1)
    # the server re-normalises the (already unit) directions: equal to rounding
    np.testing.assert_allclose(got.faces, want["diffuse"].faces, rtol=1e-6, atol=1e-12)
    both = pg.light_maps(POS, lights, kind="specular", level=1, grid="lin")
    spec = light_maps(lights, POS, diffuse_size=1, specular_size=8, specular_levels=4)
    baked = field.cube(field.weights(POS), "specular", level=1)[0]
    np.testing.assert_allclose(both.faces, spec["specular"].levels[1] + baked, rtol=1e-6,
                               atol=1e-12)
    normal = (0.2, 0.9, -0.3)
    lit = pg.light_maps(POS, lights, kind="specular", level=1, grid="lin", normal=normal)
    baked = field.cube(field.weights(POS, normals=normal), "specular", level=1)[0]
    np.testing.assert_allclose(lit.faces, spec["specular"].levels[1] + baked, rtol=1e-6,
                               atol=1e-12)


# ------------------------------------------------------------------------------ async
def test_async_client_matches_the_blocking_one(server, pg):
    async def main():
        async with AsyncProbeGridClient(server.url, timeout=30.0) as apg:
            grids = await apg.grids()
            sh = await apg.sh_at("lin", POS)
            spec = await apg.maps_at("lin", POS, kind="specular")
            pts = np.array([POS, (1.2, 0.5, 0.3)])
            rgb = await apg.shade("lin", pts, [(0, 1, 0)] * 2, [(0, 0, 1)] * 2, batch_size=1)
            many = await asyncio.gather(*(apg.sh_at("lin", (0.1 * i, 0.5, 1.0))
                                          for i in range(20)))
            return grids, sh, spec, rgb, many

    grids, sh, spec, rgb, many = asyncio.run(main())
    assert grids == pg.grids()
    np.testing.assert_array_equal(sh.coefficients, pg.sh_at("lin", POS).coefficients)
    ref = pg.maps_at("lin", POS, kind="specular")
    for a, b in zip(spec.levels, ref.levels, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(
        rgb, pg.shade("lin", np.array([POS, (1.2, 0.5, 0.3)]), [(0, 1, 0)] * 2, [(0, 0, 1)] * 2))
    for i, s in enumerate(many):
        np.testing.assert_array_equal(s.coefficients,
                                      pg.sh_at("lin", (0.1 * i, 0.5, 1.0)).coefficients)


def test_concurrent_blocking_clients(server, field):
    results: dict[int, np.ndarray] = {}

    def work(i: int) -> None:
        with ProbeGridClient(server.url) as c:
            results[i] = c.maps_at("lin", (0.2 * i, 0.5, 0.5), kind="diffuse").faces

    threads = [threading.Thread(target=work, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for i in range(8):
        w = field.weights((0.2 * i, 0.5, 0.5))
        np.testing.assert_array_equal(results[i], field.cube(w, "diffuse")[0])


# ------------------------------------------------------------------------------ errors
def test_server_errors_carry_the_server_message(pg):
    with pytest.raises(NotFoundError) as e:
        pg.sh_at("nope", POS)
    assert e.value.status == 404 and e.value.code == "not_found"
    assert str(e.value) == e.value.message == "There is no grid 'nope'; served grids: 'lin'."
    assert e.value.method == "GET" and "/v1/grids/nope/sh" in e.value.url
    with pytest.raises(BadRequestError, match="out of range 0..3") as e:
        pg.maps_at("lin", POS, kind="specular", level=7)
    assert e.value.status == 422 and e.value.code == "invalid_request"
    with pytest.raises(NotFoundError, match="no 'phong' maps"):
        pg.maps_at("lin", POS, kind="phong")  # type: ignore[arg-type]
    with pytest.raises(BadRequestError, match="limit of 32"):
        pg.shade("lin", np.zeros((40, 3)), np.ones((40, 3)), np.ones((40, 3)), batch_size=40)


def test_bad_arguments_fail_before_any_request(pg):
    with pytest.raises(ValueError, match="finite"):
        pg.sh_at("lin", (np.nan, 0.0, 0.0))
    with pytest.raises(ValueError, match="shape"):
        pg.shade("lin", np.zeros((2, 3)), np.ones((2, 3)), np.ones((2, 3)), albedo=np.ones((3, 3)))
    with pytest.raises(ValueError, match="retries"):
        ProbeGridClient("http://127.0.0.1:1", retries=-1)
    with pytest.raises(TypeError):
        ProbeGridClient("http://127.0.0.1:1", 5.0)  # type: ignore[misc]  # keyword-only


def test_connection_errors_are_retried_with_backoff():
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    with ProbeGridClient(url, retries=2, backoff=0.05) as c:
        t = time.perf_counter()
        with pytest.raises(ProbeGridConnectionError, match="cannot reach the server"):
            c.grids()
        assert time.perf_counter() - t >= 0.05 + 0.1  # two back-offs slept

    async def main():
        async with AsyncProbeGridClient(url, retries=1, backoff=0.01) as ac:
            await ac.grids()

    with pytest.raises(ProbeGridConnectionError):
        asyncio.run(main())


def test_a_silent_server_times_out():
    with socket.socket() as listener:  # accepts connections (backlog) but never answers
        listener.bind(("127.0.0.1", 0))
        listener.listen(4)
        port = listener.getsockname()[1]
        with ProbeGridClient(f"http://127.0.0.1:{port}", timeout=0.2, retries=3) as c:
            t = time.perf_counter()
            with pytest.raises(ProbeGridTimeoutError, match="did not answer in time"):
                c.grids()
            assert time.perf_counter() - t < 2.0  # read timeouts are not retried


def _send_json(handler: http.server.BaseHTTPRequestHandler, status: int, body: bytes) -> None:
    handler.send_response(status)
    handler.send_header("Content-Type", "application/json")
    handler.send_header("Content-Length", str(len(body)))
    handler.end_headers()
    handler.wfile.write(body)


class _Answer503(http.server.BaseHTTPRequestHandler):
    """A real HTTP server that is "temporarily unavailable", in the service's words."""

    hits = 0

    def do_GET(self) -> None:
        type(self).hits += 1
        _send_json(self, 503, json.dumps({"error": "store_unavailable",
                   "message": "The grid's store cannot be read right now."}).encode())

    def log_message(self, *args: object) -> None:
        pass


class _Answer500(http.server.BaseHTTPRequestHandler):
    """A real HTTP server answering what the service's last resort sends for a server bug."""

    def do_GET(self) -> None:
        from service.errors import error_body

        _send_json(self, 500, error_body("internal_error", "The server could not process this "
                                         "request (reference abc123); the cause was logged."))

    def log_message(self, *args: object) -> None:
        pass


class _AnswerHtml(http.server.BaseHTTPRequestHandler):
    """A real HTTP server that is not the service: 200 and a web page."""

    def do_GET(self) -> None:
        body = b"<html>not an API</html>"
        self.send_response(200)
        self.send_header("Content-Type", "text/html")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args: object) -> None:
        pass


@contextlib.contextmanager
def _http_server(handler: type) -> Iterator[str]:
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_port}"
    finally:
        server.shutdown()
        server.server_close()


def test_503_is_retried_then_raised_with_the_server_message():
    with _http_server(_Answer503) as url, ProbeGridClient(url, retries=2, backoff=0.05) as c:
        t = time.perf_counter()
        with pytest.raises(ServerError) as e:
            c.sh_at("g", POS)
        assert time.perf_counter() - t >= 0.15  # two back-offs slept
    assert _Answer503.hits == 3  # 1 attempt + 2 retries
    assert e.value.status == 503 and e.value.code == "store_unavailable"
    assert e.value.message == "The grid's store cannot be read right now."


def test_a_server_bug_is_a_server_error():
    with (_http_server(_Answer500) as url, ProbeGridClient(url, retries=0) as c,
          pytest.raises(ServerError) as e):
        c.sh_at("g", POS)
    assert e.value.status == 500 and e.value.code == "internal_error"
    assert "reference abc123" in e.value.message


def test_everything_the_client_raises_is_a_probegrid_error():
    """A 200 from something that is not the service, and arguments refused before sending
    (those are ValueErrors too)."""
    with _http_server(_AnswerHtml) as url, ProbeGridClient(url, retries=0) as c:
        for call in (c.healthz, c.grids, lambda: c.sh_at("g", POS),
                     lambda: c.maps_at("g", POS, level=0)):
            with pytest.raises(ProbeGridResponseError, match="not the probegrid API"):
                call()
        for bad in (lambda: c.shade("g", np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))),
                    lambda: c.shade("g", [[0, 0, np.nan]], [[0, 1, 0]], [[0, 0, 1]]),
                    lambda: c.sh_at("g", (0, "x", 0)),
                    lambda: c.sh_at("g", POS, normal=(np.inf, 0, 0))):
            with pytest.raises(InvalidArgumentError) as e:
                bad()
            assert isinstance(e.value, ValueError)
    for url in ("http://[::1", "ftp://example.org", "not a url"):
        with pytest.raises(InvalidArgumentError, match="base_url"):
            ProbeGridClient(url)


# ----------------------------------------------------------------------- visibility and deringed SH
def test_results_say_which_visibility_test_and_which_sh(tmp_path):
    """Against a store with the scene's triangles (a wall at x = 0.5) and deringed SH, served
    in-process: SHSample and MapSample report 'segments', the probes behind the wall are
    absent, and sh_at gives the deringed SH by default and the raw one on request."""
    import httpx
    from probe_stores import WALL_X, walled_store

    from probegrid.client import MapSample
    from service.main import create_app

    store = walled_store(tmp_path / "walled.probes")
    field = ProbeField(open_store(store.path))
    behind = field.store.grid.positions()[:, 0] < WALL_X

    async def run() -> tuple:
        transport = httpx.ASGITransport(app=create_app([store.path]))
        async with AsyncProbeGridClient("http://t", transport=transport) as c:
            return (await c.sh_at("walled", POS), await c.sh_at("walled", POS, sh="raw"),
                    await c.sh_at("walled", POS, normal=(1, 0, 0)),
                    await c.map_at("walled", POS, kind="specular", level=1))

    der, raw, with_normal, m = asyncio.run(run())
    w = field.weights(POS)
    for s in (der, raw, with_normal):
        assert s.visibility_test == "segments" and not behind[s.probes].any()
    assert der.sh == "deringed" and der.sh_source == "store" and raw.sh == "raw"
    np.testing.assert_array_equal(der.coefficients, field.sh(w)[0])
    np.testing.assert_array_equal(raw.coefficients, field.sh(w, kind="raw")[0])
    assert isinstance(m, MapSample) and m.visibility_test == "segments"
    assert m.kind == "specular" and m.level == 1 and not m.outside and not m.unlit
    np.testing.assert_array_equal(m.probes, der.probes)
    np.testing.assert_array_equal(m.weights, der.weights)
    np.testing.assert_array_equal(m.faces, field.cube(w, "specular", level=1)[0])
