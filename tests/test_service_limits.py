"""The service's bounds on one request: a cost model checked before any work, and deadlines for
a request's headers and body.

* ``POST /v1/lights/maps`` and ``/shade`` are estimated from the request (:mod:`service.cost`)
  and refused over ``request_budget`` with ``422 over_budget`` before the library is called
  (counted, not timed); the light maps' model counts exactly the texels and kernel evaluations
  :func:`probegrid.core.lights.light_maps` makes.
* A client that sends its headers or its body slowly (slowloris) is answered ``408`` and cut
  off after ``header_timeout`` / ``body_timeout`` (a raw socket that sends a partial request
  and waits), while other clients are served meanwhile.
"""

from __future__ import annotations

import asyncio
import json
import select
import socket
import threading
import time
from pathlib import Path

import httpx
import pytest
from live_server import serve
from probe_stores import GRID, linear_arrays, write_store

import probegrid.core.lights as lights_module
from probegrid.core.lights import PointLight, light_maps, light_maps_work
from probegrid.query import ProbeField
from service.cost import light_maps_estimate, shade_estimate
from service.main import create_app
from service.settings import Settings


@pytest.fixture(scope="module")
def lin(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("st") / "lin.probes"
    write_store(path, GRID, linear_arrays(GRID))
    return path


def _post(app, url: str, body: dict) -> httpx.Response:
    async def run() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            return await c.post(url, json=body)

    return asyncio.run(run())


# ---------------------------------------------------------------------------- the cost model
@pytest.mark.parametrize("n_lights, diffuse, specular, levels", [
    (1, 16, 1, 1), (3, 7, 1, 1), (2, 1, 16, None), (4, 1, 24, 4), (1, 1, 32, 3)])
def test_the_light_maps_model_counts_what_light_maps_computes(monkeypatch, n_lights, diffuse,
                                                              specular, levels):
    """Every cube light_maps fills is made from texel_directions(fine): 6 fine^2 texels, each
    evaluated once per lit light. The model's count equals that sum, from the arguments alone."""
    sizes: list[int] = []
    real = lights_module.texel_directions

    def counting(n: int):
        sizes.append(n)
        return real(n)

    monkeypatch.setattr(lights_module, "texel_directions", counting)
    lights = [PointLight(position=(1.0 + i, 2.0, 3.0), color=(1.0, 1.0, 1.0), intensity=5.0) for i in range(n_lights)]
    light_maps(lights, (0.0, 0.0, 0.0), diffuse_size=diffuse, specular_size=specular,
               specular_levels=levels)
    work = light_maps_work(n_lights, diffuse_size=diffuse, specular_size=specular,
                           specular_levels=levels)
    evaluated = sum(6 * n * n for n in sizes)
    assert work.evaluations == evaluated * n_lights
    assert work.texels >= evaluated  # plus the delta level's texels, splatted without a kernel


def _counting(monkeypatch, target, name: str) -> list[int]:
    calls: list[int] = []
    real = getattr(target, name)

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(target, name, counted)
    return calls


LIGHTS = [{"type": "point", "position": [1.0 + i, 2.0, 1.0], "intensity": 5.0} for i in range(4)]
SPECULAR = {"position": [0.75, 0.25, 1.5], "kind": "specular", "specular_size": 16,
            "lights": LIGHTS}


def test_a_light_map_request_over_the_budget_is_refused_before_any_work(lin, monkeypatch):
    import service.routers.lights as route

    calls = _counting(monkeypatch, route, "light_maps")
    cost = light_maps_estimate(4, diffuse_size=1, specular_size=16, specular_levels=None).seconds
    just_over = create_app([lin], Settings(request_budget=cost * 0.999))
    r = _post(just_over, "/v1/lights/maps", SPECULAR)
    assert r.status_code == 422 and r.json()["error"] == "over_budget"
    message = r.json()["message"]
    for words in ("request_budget", "--request-budget", "lights", "specular_size",
                  f"{cost:.3g} s"):
        assert words in message
    assert calls == []  # refused from the request alone: light_maps never ran
    just_under = create_app([lin], Settings(request_budget=cost * 1.001))
    r = _post(just_under, "/v1/lights/maps", SPECULAR)
    assert r.status_code == 200 and calls == [1]


def test_a_light_map_request_is_priced_at_the_grids_sizes(lin, monkeypatch):
    """With a grid, the maps are made at the grid's sizes, whatever the request's sizes say."""
    import service.routers.lights as route

    calls = _counting(monkeypatch, route, "light_maps")
    body = {**SPECULAR, "grid": "lin", "specular_size": 1}
    sizes = create_app([lin]).state.probegrid.grids["lin"].field
    cost = light_maps_estimate(4, diffuse_size=1, specular_size=sizes.map_size("specular"),
                               specular_levels=sizes.map_levels("specular")).seconds
    r = _post(create_app([lin], Settings(request_budget=cost * 0.999)), "/v1/lights/maps", body)
    assert r.status_code == 422 and r.json()["error"] == "over_budget" and calls == []
    r = _post(create_app([lin], Settings(request_budget=cost * 1.001)), "/v1/lights/maps", body)
    assert r.status_code == 200 and calls == [1]


def test_a_shade_batch_over_the_budget_is_refused_before_any_work(lin, monkeypatch):
    calls = _counting(monkeypatch, ProbeField, "shade")
    point = {"position": [0.75, 0.25, 1.5], "normal": [0, 1, 0], "view": [0, 1, 0]}
    body = {"points": [point] * 10}
    cost = shade_estimate(10).seconds
    r = _post(create_app([lin], Settings(request_budget=cost * 0.999)), "/v1/grids/lin/shade",
              body)
    assert r.status_code == 422 and r.json()["error"] == "over_budget"
    assert "points" in r.json()["message"] and calls == []
    r = _post(create_app([lin], Settings(request_budget=cost * 1.001)), "/v1/grids/lin/shade",
              body)
    assert r.status_code == 200 and calls == [1]


def test_the_default_budget_serves_the_default_light_maps_and_refuses_the_largest():
    default = Settings().request_budget
    assert light_maps_estimate(16, diffuse_size=16, specular_size=32,
                               specular_levels=None).seconds <= default
    assert light_maps_estimate(1, diffuse_size=1, specular_size=256,
                               specular_levels=None).seconds <= default
    largest = light_maps_estimate(Settings().max_lights, diffuse_size=1,
                                  specular_size=Settings().max_light_map_size,
                                  specular_levels=None)
    assert largest.seconds > default  # 16 lights' full chain of 256: refused
    assert shade_estimate(Settings().max_batch).seconds <= default


# ---------------------------------------------------------------------------- deadlines
TIMEOUT = 1.5


@pytest.fixture(scope="module")
def timed(lin, tmp_path_factory):
    log = tmp_path_factory.mktemp("log") / "server.log"
    settings = {"header_timeout": TIMEOUT, "body_timeout": TIMEOUT}
    with serve([lin], log, settings=settings) as live:
        yield live


def _connect(url: str) -> socket.socket:
    host, port = url.removeprefix("http://").split(":")
    s = socket.create_connection((host, int(port)), timeout=10.0)
    return s


def _read_until_closed(s: socket.socket, limit: float) -> tuple[bytes, float]:
    """Everything the server sends until it closes, and when it closed (monotonic)."""
    s.settimeout(limit)
    data = b""
    while True:
        try:
            chunk = s.recv(65536)
        except (ConnectionResetError, TimeoutError):
            break
        if not chunk:
            break
        data += chunk
    return data, time.monotonic()


def _assert_timed_out(data: bytes, start: float, end: float) -> None:
    assert data.startswith(b"HTTP/1.1 408"), data[:80]
    assert json.loads(data.split(b"\r\n\r\n", 1)[1])["error"] == "request_timeout"
    assert TIMEOUT * 0.9 <= end - start <= TIMEOUT + 2.0


def test_slow_headers_are_cut_off_while_others_are_served(timed):
    """Ten connections each send half a request line and wait (or trickle a byte at a time,
    which does not restart the clock): each gets a 408 and is closed after header_timeout;
    meanwhile a normal client is answered at once."""
    socks, start = [], time.monotonic()
    for _ in range(10):
        s = _connect(timed.url)
        s.sendall(b"GET /healthz HT")
        socks.append(s)
    trickler = _connect(timed.url)
    stop = threading.Event()

    def trickle() -> None:
        for byte in b"GET /healthz HTTP/1.1\r\nHost: x\r\n":
            if stop.wait(0.2):
                return
            try:
                trickler.send(bytes([byte]))
            except OSError:
                return

    thread = threading.Thread(target=trickle)
    thread.start()
    try:
        assert httpx.get(timed.url + "/healthz", timeout=5.0).status_code == 200
        # served while the slow ones are still waiting (not queued until they were cut off)
        readable, _, _ = select.select(socks, [], [], 0)
        assert readable == []
        for s in [*socks, trickler]:
            data, end = _read_until_closed(s, TIMEOUT + 5.0)
            _assert_timed_out(data, start, end)
    finally:
        stop.set()
        thread.join()
        for s in [*socks, trickler]:
            s.close()


def test_a_slow_body_is_cut_off_and_the_next_request_on_a_connection_has_a_deadline(timed):
    s = _connect(timed.url)
    try:
        s.sendall(b"POST /v1/grids/lin/shade HTTP/1.1\r\nHost: x\r\n"
                  b"Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{\"points\"")
        start = time.monotonic()
        data, end = _read_until_closed(s, TIMEOUT + 5.0)
        _assert_timed_out(data, start, end)
    finally:
        s.close()
    s = _connect(timed.url)  # keep-alive: a first request answered, then a partial second one
    try:
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        s.settimeout(5.0)
        first = b""
        while b"}" not in first:  # the whole first response: headers and its JSON body
            first += s.recv(65536)
        assert first.startswith(b"HTTP/1.1 200")
        start = time.monotonic()
        s.sendall(b"GET /heal")
        data, end = _read_until_closed(s, TIMEOUT + 5.0)
        _assert_timed_out(data, start, end)
    finally:
        s.close()
    assert httpx.get(timed.url + "/healthz", timeout=5.0).status_code == 200


def test_requests_in_time_are_served_whole(timed):
    """A body sent in pieces within the deadline is read whole and answered."""
    body = json.dumps({"points": [{"position": [0.75, 0.25, 1.5], "normal": [0, 1, 0],
                                   "view": [0, 1, 0]}]}).encode()
    s = _connect(timed.url)
    try:
        s.sendall(b"POST /v1/grids/lin/shade HTTP/1.1\r\nHost: x\r\nConnection: close\r\n"
                  b"Content-Type: application/json\r\nContent-Length: "
                  + str(len(body)).encode() + b"\r\n\r\n")
        for piece in (body[:10], body[10:]):
            time.sleep(TIMEOUT / 4)
            s.sendall(piece)
        data, _ = _read_until_closed(s, 10.0)
    finally:
        s.close()
    assert data.startswith(b"HTTP/1.1 200")
    assert len(json.loads(data.split(b"\r\n\r\n", 1)[1])["rgb"]) == 1
    assert "Traceback" not in timed.log_text()


def test_serve_options_set_the_budget_and_deadlines(lin, monkeypatch, capsys):
    import service.main
    from live_server import free_port

    from probegrid.cli import main

    seen: dict = {}
    monkeypatch.setattr(service.main, "run", lambda stores, **kw: seen.update(kw))
    assert main(["serve", str(lin), "--port", str(free_port()), "--request-budget", "0.5",
                 "--header-timeout", "3", "--body-timeout", "7"]) == 0
    assert seen["overrides"] == {"request_budget": 0.5, "header_timeout": 3.0,
                                 "body_timeout": 7.0}
    for bad in (["--request-budget", "0"], ["--header-timeout", "-1"],
                ["--body-timeout", "nan"]):
        with pytest.raises(SystemExit) as info:
            main(["serve", str(lin), *bad])
        assert info.value.code == 2
        assert "expected a" in capsys.readouterr().err


def test_a_chunked_body_over_the_limit_is_413_without_reading_the_rest(timed):
    """No Content-Length to refuse up front: the body is read up to max_body_bytes (1 MiB by
    default), then answered 413 and the connection closed, the rest never read."""
    s = _connect(timed.url)
    try:
        s.sendall(b"POST /v1/grids/lin/shade HTTP/1.1\r\nHost: x\r\n"
                  b"Content-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\n")
        piece = b" " * 65536
        for _ in range(17):  # 1.06 MiB, and no last chunk: the body never ends
            s.sendall(b"%x\r\n" % len(piece) + piece + b"\r\n")
        data, _ = _read_until_closed(s, 10.0)
    finally:
        s.close()
    assert data.startswith(b"HTTP/1.1 413"), data[:80]
    assert json.loads(data.split(b"\r\n\r\n", 1)[1])["error"] == "too_large"
