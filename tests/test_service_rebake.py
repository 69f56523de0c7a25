"""Stores published again and again under a live server while clients query every route.

A real uvicorn server serves ``g.probes``; four client threads loop over every route (``/sh``,
``/maps`` in three formats, ``/probes``, the three.js export, the scene's bytes, ``/v1/grids``,
``/healthz``, ``/shade``, ``/v1/dfg``) while the store at the path is replaced by the library's
publishing (:func:`probegrid._fs.publish_directory`, as ``probegrid bake --overwrite``
publishes) with three versions in turn: other values, another grid box, another scene.

Expected: no 5xx; every response's bytes are exactly those one version's server answers alone
(precomputed by an app serving each version), its ETag is that answer's, and ``/v1/grids/g``
names that version's content hash: a response is wholly the old store's or wholly the new one's,
never a mix. And every version is seen, so the test did exercise the swaps.
"""

from __future__ import annotations

import asyncio
import shutil
import threading
import time
from pathlib import Path

import httpx
import pytest
from live_server import serve
from probe_stores import GRID, linear_arrays, write_store

from probegrid._fs import publish_directory
from probegrid.core.grid import GridSpec
from service.main import create_app

REPO = Path(__file__).resolve().parents[1]
SCENES = [REPO / "data" / "sample_room.glb", REPO / "tests" / "data" / "gltf" / "Cubes.glb",
          REPO / "tests" / "data" / "gltf" / "CornellBox.glb"]
P = "x=0.75&y=0.25&z=1.5"
GETS = [
    "/healthz", "/v1/grids", "/v1/grids/g", f"/v1/grids/g/sh?{P}",
    f"/v1/grids/g/sh?{P}&nx=0&ny=1&nz=0&sh=raw",
    f"/v1/grids/g/maps/diffuse?{P}", f"/v1/grids/g/maps/specular?{P}&level=1&format=exr",
    f"/v1/grids/g/maps/diffuse?{P}&format=json&method=blend",
    "/v1/grids/g/probes", "/v1/grids/g/scene", "/v1/grids/g/export/threejs.json",
    "/v1/grids/g/export/threejs.bin?dtype=float32", "/v1/grids/g/export/threejs.ktx2",
    "/v1/dfg",
]
SHADE = {"points": [{"position": [0.75, 0.25, 1.5], "normal": [0, 1, 0], "view": [0, 1, 1]},
                    {"position": [1.25, 0.5, 0.5], "normal": [1, 0, 0], "view": [1, 1, 0]}]}
ROUTES = [("GET", u) for u in GETS] + [("POST", "/v1/grids/g/shade")]


def _version(root: Path, v: int) -> Path:
    """Version ``v`` of the store ``g.probes``, in its own folder: values times ``v + 1``, a
    grid box ``v`` cells wider and scene ``v``."""
    grid = GridSpec.from_counts((0.0, 0.0, 0.0), (2.0 + v, 1.0, 2.0), GRID.counts)
    arrays = linear_arrays(grid)
    for name in ("sh", "diffuse", "specular_0", "specular_1"):
        if name in arrays:
            arrays[name] = arrays[name] * (v + 1)
    path = root / f"v{v}" / "g.probes"
    path.parent.mkdir(parents=True)
    write_store(path, grid, arrays, scene=SCENES[v])
    return path


def _answers(store: Path) -> dict[tuple[str, str], tuple[int, bytes, str | None]]:
    """What an app serving ``store`` alone answers on every route: status, body, ETag."""
    app = create_app([store])

    async def run():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            out = {}
            for method, url in ROUTES:
                r = await (c.get(url) if method == "GET" else c.post(url, json=SHADE))
                out[(method, url)] = (r.status_code, r.content, r.headers.get("etag"))
            return out

    return asyncio.run(run())


@pytest.mark.slow
def test_every_route_answers_wholly_one_store_while_stores_are_published(tmp_path):
    versions = [_version(tmp_path / "versions", v) for v in range(3)]
    expected = [_answers(p) for p in versions]
    for key in expected[0]:  # every route tells the versions apart but healthz and dfg
        if key[1] not in ("/healthz", "/v1/dfg"):
            assert len({e[key][1] for e in expected}) == 3, key
    hashes = [create_app([p]).state.probegrid.grids["g"].summary["content_hash"]
              for p in versions]
    served = tmp_path / "served" / "g.probes"
    served.parent.mkdir()
    shutil.copytree(versions[0], served)

    stop = threading.Event()
    problems: list[str] = []
    seen: dict[tuple[str, str], set[int]] = {key: set() for key in expected[0]}
    counts = [0]

    def client(url: str, offset: int) -> None:
        with httpx.Client(base_url=url, timeout=30.0) as c:
            i = offset
            while not stop.is_set():
                method, route = ROUTES[i % len(ROUTES)]
                i += 1
                r = (c.get(route) if method == "GET" else c.post(route, json=SHADE))
                counts[0] += 1
                match = [v for v, e in enumerate(expected)
                         if e[(method, route)][:2] == (r.status_code, r.content)]
                if r.status_code >= 500:
                    problems.append(f"{method} {route}: {r.status_code} {r.text[:200]}")
                elif not match:
                    problems.append(f"{method} {route}: {r.status_code}, the bytes of no "
                                    f"version ({len(r.content)} bytes)")
                else:
                    v = match[0]
                    seen[(method, route)].add(v)
                    if r.headers.get("etag") != expected[v][(method, route)][2]:
                        problems.append(f"{method} {route}: ETag {r.headers.get('etag')} "
                                        f"for the bytes of version {v}")
                    if route == "/v1/grids/g" and r.json()["content_hash"] != hashes[v]:
                        problems.append(f"{route}: content hash of another version")

    with serve([served], tmp_path / "server.log", settings={"max_heavy_requests": 8}) as live:
        threads = [threading.Thread(target=client, args=(live.url, 4 * k)) for k in range(4)]
        for t in threads:
            t.start()
        try:
            step, deadline = 0, time.monotonic() + 300.0
            # v1, v2, v0, v1, ... each published whole, until every route was asked 8 times
            while (step < 9 or counts[0] < 8 * len(ROUTES)) and time.monotonic() < deadline:
                step += 1
                staged = tmp_path / "served" / f"g.probes.staged-{step}"
                shutil.copytree(versions[step % 3], staged)
                publish_directory(staged, served)
                time.sleep(1.5)  # clients see it (the server looks every second)
        finally:
            stop.set()
            for t in threads:
                t.join()
        log = live.log_text()
    assert problems == [], problems[:10]
    assert counts[0] >= 8 * len(ROUTES)
    assert {v for s in seen.values() for v in s} == {0, 1, 2}, log[-3000:]  # each one served
    assert "internal_error" not in log and "Traceback" not in log
