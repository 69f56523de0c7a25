"""Load benchmark of the map service: ``/sh`` and ``/maps`` next to the bare ``/healthz``.

Starts ``service.main.run`` (one uvicorn worker, as ``probegrid serve`` does) on 127.0.0.1 in a
subprocess, serving ``--store`` or, without it, a synthetic store written with
:class:`probegrid.store.StoreWriter` (8 x 4 x 8 probes, 16^2 diffuse cubes, a 64^2 GGX chain,
distance moments). A minimal asyncio HTTP/1.1 keep-alive load generator (raw sockets, so the
client costs far less than the server) then measures, after a warm-up, per endpoint:
``--requests`` requests on one connection (latency: p50, p99) and ``--requests`` more over
``--connections`` concurrent connections (throughput: requests per second). The requests are
sent in ``--rounds`` rounds that visit every endpoint in turn, so a change in the load of the
(shared) machine during the run falls on every endpoint alike instead of on the ratios:

* ``bare``: ``GET /healthz``, a fixed small JSON document from the same app (the reference);
* ``sh``: ``GET /v1/grids/G/sh?x=&y=&z=`` at positions spread over the grid box;
* ``sh+normal``: the same with ``nx, ny, nz`` (DDGI visibility weights);
* ``sh+normal[probes]``: the same with ``source=probes``: the probes' blend where the store
  has an SH field (``sh`` then interpolates the field; ``--store`` a bake's store to compare);
* ``maps``: ``GET /v1/grids/G/maps/diffuse?...&format=npy`` (the 16^2 diffuse cube);
* ``sh[seg]``, ``sh+normal[seg]``, ``maps[seg]`` (synthetic store only): the same queries of a
  second grid, the synthetic store plus the extras a bake writes (format 2): a scene of about
  20000 triangles (a closed room, two inner walls with doorways, a tessellated floor) whose
  point-to-probe segments every query casts through Embree (exact visibility), and
  the deringed SH. The ratio ``[seg]`` / plain is the cost of the exact visibility test.

It prints p50 / p99 latency and requests per second per endpoint and their ratios to the bare
endpoint (the figures; targets: ``sh`` p50 <= 1.5x and throughput >= 0.7x, ``maps`` p50 <= 2x),
then the server's resident memory before and after ``--rss-requests`` more mixed requests
(100000 shows a slow leak better; the default is bounded for a shared machine).

Every endpoint cycles through 512 random positions (and normals), so the figures are not those of
one cached query. The header line names uvicorn's HTTP parser and event loop (``auto``: httptools
and uvloop when installed, else h11 and asyncio): they change every figure.

Usage::

    .venv/bin/python benchmarks/bench_service.py [--store S.probes] [--requests 2000]
        [--connections 4] [--rounds 10] [--rss-requests 20000] [--max-seconds 300]
        [--in-process]

Besides requests per second it prints the server's CPU time per request of the throughput
phase and the bare endpoint's over it (on a shared machine requests per second follow the
machine's load; the CPU time a request costs the server much less), and with
``--in-process`` the CPU time per request through the app called in this process (no HTTP
server: what the routes themselves cost).

Loopback only; every phase is bounded in requests and in time.
"""

from __future__ import annotations

import argparse
import asyncio
import importlib.util
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil
import uvicorn

from probegrid.core.conventions import conventions
from probegrid.core.cubemap import mip_sizes
from probegrid.core.grid import GridSpec
from probegrid.store import ArraySpec, StoreWriter, open_store

REPO = Path(__file__).resolve().parents[1]


def synthetic_store(path: Path) -> Path:
    """A store of random positive maps (8 x 4 x 8 probes, 16^2 diffuse, 64^2 GGX chain)."""
    grid = GridSpec.from_counts((0.0, 0.0, 0.0), (7.0, 3.0, 7.0), (8, 4, 8))
    rng = np.random.default_rng(0)
    p = grid.n_probes
    arrays = {"sh": rng.random((p, 9, 3)).astype(np.float32),
              "diffuse": rng.random((p, 6, 16, 16, 3)).astype(np.float32)}
    for k, n in enumerate(mip_sizes(64)):
        arrays[f"specular_{k}"] = rng.random((p, 6, n, n, 3)).astype(np.float32)
    moments = np.empty((p, 6, 8, 8, 2), np.float32)
    moments[..., 0] = rng.uniform(0.5, 3.0, (p, 6, 8, 8))
    moments[..., 1] = moments[..., 0] ** 2 + 0.05
    arrays["moments"] = moments
    arrays["valid"] = np.ones(p, bool)
    arrays["positions"] = grid.positions().astype(np.float32)
    specs = {k: ArraySpec(shape=a.shape[1:], dtype=a.dtype.str) for k, a in arrays.items()}
    writer = StoreWriter.create(path, arrays=specs, grid=grid, conventions=conventions(),
                                scene_hash="bench-synthetic", bake={"synthetic": True})
    writer.write(np.arange(p), arrays)
    writer.finish(quality={})
    return path


def scene_extras(path: Path, source: Path) -> Path:
    """A copy of the synthetic store ``source`` with the extras of a bake (format 2): the
    deringed SH and a scene of ~20000 triangles inside and around its grid box (module
    docstring), so that its queries take the exact segment visibility test."""
    from probegrid.core.sh.dering import dering
    from probegrid.scene import box_mesh, quad_mesh

    store = open_store(source)
    grid = store.grid
    arrays = {k: np.asarray(store[k]) for k in store.names}
    specs = {k: ArraySpec(shape=a.shape[1:], dtype=a.dtype.str) for k, a in arrays.items()}
    writer = StoreWriter.create(path, arrays=specs, grid=grid, conventions=conventions(),
                                scene_hash="bench-synthetic-scene", bake={"synthetic": True})
    writer.write(np.arange(grid.n_probes), arrays)
    deringed, window, _ = dering(arrays["sh"].astype(np.float64))
    writer.add_extra("sh_deringed", deringed.astype(np.float32))
    writer.add_extra("sh_window", window.astype(np.float32))
    parts = [box_mesh(grid.lo - 0.5, grid.hi + 0.5, inward=True)[:2]]
    h = float(grid.hi[1] - grid.lo[1]) + 1.0
    for x in (2.3, 4.7):  # inner walls across z, a doorway 1 wide at z in [3, 4]
        z0, z1 = float(grid.lo[2]) - 0.5, float(grid.hi[2]) + 0.5
        parts.append(quad_mesh((x, -0.5, z0), (0.0, 0.0, 3.5 - z0), (0.0, h, 0.0))[:2])
        parts.append(quad_mesh((x, -0.5, 4.5), (0.0, 0.0, z1 - 4.5), (0.0, h, 0.0))[:2])
    n = 100  # a tessellated floor just above the room's: 2 n^2 triangles
    u = np.linspace(grid.lo[0] - 0.4, grid.hi[0] + 0.4, n + 1)
    w = np.linspace(grid.lo[2] - 0.4, grid.hi[2] + 0.4, n + 1)
    uu, ww = np.meshgrid(u, w, indexing="ij")
    verts = np.stack([uu, np.full_like(uu, -0.45) + 0.02 * np.sin(3 * uu) * np.cos(2 * ww),
                      ww], -1).reshape(-1, 3)
    i, k = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + k).ravel()
    tris = np.concatenate([np.stack([a, a + 1, a + n + 2], 1), np.stack([a, a + n + 2, a + n + 1], 1)])
    parts.append((verts, tris))
    vs, ts, base = [], [], 0
    for v, t in parts:
        vs.append(v)
        ts.append(np.asarray(t) + base)
        base += len(v)
    writer.add_extra("scene_vertices", np.concatenate(vs).astype(np.float32))
    writer.add_extra("scene_triangles", np.concatenate(ts).astype(np.int32))
    writer.finish(quality={})
    return path


def in_process_visibility_cost(plain: Path, seg: Path, lo: np.ndarray, hi: np.ndarray) -> str:
    """One line: the warm in-process cost of one point's weights without and with the exact
    segment test, and of the Embree segment query alone (best of 5 repeats of 2000 calls)."""
    import timeit

    from probegrid.query import ProbeField

    a, b = ProbeField(open_store(plain)), ProbeField(open_store(seg))
    pts = lo + np.random.default_rng(2).random((64, 3)) * (hi - lo)

    def best(fn) -> float:
        it = iter(range(1 << 62))
        return min(timeit.repeat(lambda: fn(pts[next(it) % 64]), number=2000, repeat=5)) / 2000

    t_plain = best(lambda p: a.weights(p))
    t_seg = best(lambda p: b.weights(p))
    ends = np.asarray(b.store["positions"], np.float64)[b.grid.corners(pts[:1])[0][0]]
    assert b.tracer is not None
    tracer = b.tracer
    t_cast = best(lambda p: tracer.segments_occluded(p, ends, margin=1e-4))
    return (f"in process, one point, warm: weights {t_plain * 1e6:.1f} us, with the exact "
            f"segment test {t_seg * 1e6:.1f} us ({t_seg / t_plain:.2f}x); the 8-segment "
            f"Embree query alone {t_cast * 1e6:.1f} us ({len(np.asarray(b.store['scene_triangles']))}"
            " triangles)")


def in_process(stores: list[Path], paths: dict[str, list[bytes]], requests: int, rounds: int
               ) -> dict[str, float]:
    """CPU microseconds per request of every endpoint through the app itself (ASGI calls in
    this process, no HTTP server or socket): the best of ``rounds`` rounds of ``requests``,
    the endpoints interleaved. The HTTP server's own cost per request (the same for every
    endpoint) is left out, and the CPU time of this process follows the machine's load far
    less than requests per second do."""
    from service.main import create_app

    app = create_app(stores)

    async def call(path: bytes) -> None:
        route, _, query = path.partition(b"?")
        scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1",
                 "method": "GET", "scheme": "http", "path": route.decode(), "raw_path": route,
                 "query_string": query, "root_path": "", "headers": [(b"host", b"bench")],
                 "client": ("127.0.0.1", 1), "server": ("127.0.0.1", 80), "state": {}}
        sent: list[dict] = []

        async def receive() -> dict:
            return {"type": "http.request", "body": b"", "more_body": False}

        async def send(message: dict) -> None:
            sent.append(message)

        await app(scope, receive, send)
        if sent[0]["status"] != 200:
            raise RuntimeError(f"{path!r}: status {sent[0]['status']}")

    async def run() -> dict[str, float]:
        best = dict.fromkeys(paths, float("inf"))
        async with app.router.lifespan_context(app):
            for key, p in paths.items():  # warm-up
                for k in range(min(200, requests)):
                    await call(p[k % len(p)])
            for _ in range(rounds):
                for key, p in paths.items():
                    t0 = time.process_time()
                    for k in range(requests):
                        await call(p[k % len(p)])
                    best[key] = min(best[key], (time.process_time() - t0) / requests * 1e6)
        return best

    return asyncio.run(run())


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_server(stores: list[Path], port: int, log: Path) -> subprocess.Popen[bytes]:
    code = ("import sys; from service.main import run; "
            "run(sys.argv[2:], host='127.0.0.1', port=int(sys.argv[1]), workers=1, "
            "log_level='warning')")
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    with open(log, "wb") as out:
        return subprocess.Popen([sys.executable, "-c", code, str(port), *map(str, stores)],
                                stdout=out, stderr=subprocess.STDOUT, env=env, cwd=REPO)


# ------------------------------------------------------------------------------ load generator
async def _read_response(reader: asyncio.StreamReader) -> int:
    head = await reader.readuntil(b"\r\n\r\n")
    status = int(head[9:12])
    length = 0
    for line in head.split(b"\r\n")[1:]:
        if line[:15].lower() == b"content-length:":
            length = int(line[15:])
    if length:
        await reader.readexactly(length)
    return status


async def _connection(port: int, paths: list[bytes], start: int, step: int, count: int,
                      latencies: list[float], statuses: dict[int, int], deadline: float,
                      ready: asyncio.Barrier | None = None) -> None:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        if ready is not None:
            await ready.wait()  # every connection is open before the clock starts
        for k in range(count):
            if time.monotonic() > deadline:
                break
            path = paths[(start + k * step) % len(paths)]
            t0 = time.perf_counter()
            writer.write(b"GET " + path + b" HTTP/1.1\r\nHost: bench\r\n\r\n")
            status = await _read_response(reader)
            latencies.append(time.perf_counter() - t0)
            statuses[status] = statuses.get(status, 0) + 1
    finally:
        writer.close()
        await writer.wait_closed()


async def load(port: int, paths: list[bytes], requests: int, connections: int,
               max_seconds: float, offset: int = 0) -> tuple[list[float], float]:
    """Send ``requests`` GETs over ``connections`` keep-alive connections, cycling through
    ``paths`` from ``offset``; the latencies (s) and the wall time once all were open (s)."""
    latencies: list[float] = []
    statuses: dict[int, int] = {}
    per = -(-requests // connections)
    deadline = time.monotonic() + max_seconds
    ready = asyncio.Barrier(connections + 1)
    tasks = [asyncio.create_task(_connection(port, paths, offset + c, connections, per,
                                             latencies, statuses, deadline, ready))
             for c in range(connections)]
    await ready.wait()
    t0 = time.perf_counter()
    await asyncio.gather(*tasks)
    wall = time.perf_counter() - t0
    if set(statuses) != {200}:
        raise RuntimeError(f"unexpected statuses {statuses}")
    return latencies, wall


def _cpu_seconds(server: psutil.Process | None) -> float:
    """The server process's CPU seconds so far (user + system; 0 without one)."""
    if server is None:
        return 0.0
    t = server.cpu_times()
    return float(t.user + t.system)


def measure(port: int, paths: dict[str, list[bytes]], requests: int, connections: int,
            rounds: int, max_seconds: float, server: psutil.Process | None = None
            ) -> dict[str, dict[str, float]]:
    """Latency (1 connection) and throughput (``connections``) of every endpoint, ``requests``
    of each per endpoint, in ``rounds`` interleaved rounds (module docstring), and the
    server's CPU time per request of the throughput phases (``server``'s: on a loaded
    machine the requests per second follow the machine's load, the CPU time a request costs
    the server much less)."""
    for p in paths.values():  # warm-up
        asyncio.run(load(port, p, min(300, requests), connections, 30))
    one: dict[str, list[float]] = {k: [] for k in paths}
    many: dict[str, list[float]] = {k: [] for k in paths}
    wall = dict.fromkeys(paths, 0.0)
    cpu = dict.fromkeys(paths, 0.0)
    deadline = time.monotonic() + max_seconds
    per = -(-requests // rounds)
    for r in range(rounds):
        if time.monotonic() > deadline:
            break
        for key, p in paths.items():
            one[key] += asyncio.run(load(port, p, per, 1, max_seconds, r * per))[0]
            c0 = _cpu_seconds(server)
            lat, w = asyncio.run(load(port, p, per, connections, max_seconds, r * per))
            cpu[key] += _cpu_seconds(server) - c0
            many[key] += lat
            wall[key] += w
    results = {}
    for key in paths:
        a, b = np.array(one[key]) * 1e3, np.array(many[key]) * 1e3
        results[key] = {"p50_ms": float(np.percentile(a, 50)),
                        "p99_ms": float(np.percentile(a, 99)),
                        "rps": b.size / wall[key], "requests": float(a.size),
                        "cpu_us": 1e6 * cpu[key] / max(b.size, 1),
                        "loaded_p50_ms": float(np.percentile(b, 50)),
                        "loaded_p99_ms": float(np.percentile(b, 99))}
    return results


def server_stack() -> str:
    """uvicorn's ``auto`` choices in this environment (what the server process uses)."""
    http = "httptools" if importlib.util.find_spec("httptools") else "h11"
    loop = "uvloop" if importlib.util.find_spec("uvloop") else "asyncio"
    return f"uvicorn {uvicorn.__version__} {http}/{loop}"


def endpoint_paths(grid: str, lo: np.ndarray, hi: np.ndarray, *, seg_grid: str | None = None
                   ) -> dict[str, list[bytes]]:
    rng = np.random.default_rng(1)
    pts = lo + rng.random((512, 3)) * (hi - lo)
    nrm = rng.normal(size=(512, 3))

    def q(p: np.ndarray) -> str:
        return f"x={p[0]:.6f}&y={p[1]:.6f}&z={p[2]:.6f}"

    def queries(g: str) -> dict[str, list[bytes]]:
        return {
            "sh": [f"/v1/grids/{g}/sh?{q(p)}".encode() for p in pts],
            "sh+normal": [f"/v1/grids/{g}/sh?{q(p)}&nx={n[0]:.4f}&ny={n[1]:.4f}&nz={n[2]:.4f}"
                          .encode() for p, n in zip(pts, nrm, strict=True)],
            # the probes' blend (the same as sh for a store without an SH field)
            "sh+normal[probes]": [f"/v1/grids/{g}/sh?{q(p)}&nx={n[0]:.4f}&ny={n[1]:.4f}"
                                  f"&nz={n[2]:.4f}&source=probes".encode()
                                  for p, n in zip(pts, nrm, strict=True)],
            "maps": [f"/v1/grids/{g}/maps/diffuse?{q(p)}&format=npy".encode() for p in pts],
        }

    paths = {"bare": [b"/healthz"], **queries(grid)}
    if seg_grid is not None:
        paths.update({f"{k}[seg]": v for k, v in queries(seg_grid).items()})
    return paths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", type=Path, help="store to serve (default: synthetic)")
    parser.add_argument("--requests", type=int, default=2000, help="requests per endpoint")
    parser.add_argument("--connections", type=int, default=4, help="keep-alive connections")
    parser.add_argument("--rounds", type=int, default=10,
                        help="interleaved rounds the requests are split into")
    parser.add_argument("--rss-requests", type=int, default=20000,
                        help="mixed requests between the two memory readings")
    parser.add_argument("--max-seconds", type=float, default=300.0,
                        help="time bound of each phase")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.add_argument("--in-process", action="store_true",
                        help="also measure the CPU time per request through the app in this "
                             "process (no HTTP server; see in_process)")
    parser.add_argument("--only", default="",
                        help="endpoints to measure besides bare (comma-separated names)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="bench-service-") as tmp:
        store = args.store or synthetic_store(Path(tmp) / "bench.probes")
        stores = [store]
        if args.store is None:
            stores.append(scene_extras(Path(tmp) / "benchseg.probes", store))
        grid = open_store(store).grid
        name = store.name.removesuffix(".probes")
        port = free_port()
        proc = start_server(stores, port, Path(tmp) / "server.log")
        try:
            deadline = time.monotonic() + 60
            while True:
                try:
                    socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                    break
                except OSError:
                    if proc.poll() is not None or time.monotonic() > deadline:
                        raise RuntimeError((Path(tmp) / "server.log").read_text()) from None
                    time.sleep(0.1)
            paths = endpoint_paths(name, grid.lo, grid.hi,
                                   seg_grid="benchseg" if len(stores) > 1 else None)
            if args.only:
                keep = {"bare", *args.only.split(",")}
                paths = {k: v for k, v in paths.items() if k in keep}
            results = measure(port, paths, args.requests, args.connections, args.rounds,
                              args.max_seconds, psutil.Process(proc.pid))
            print(f"{args.requests} requests per endpoint and measurement in {args.rounds} "
                  f"interleaved rounds, one uvicorn worker ({server_stack()}), store "
                  f"{store.name} ({grid.label}); latency on 1 connection, throughput on "
                  f"{args.connections}")
            print(f"{'endpoint':<18}{'p50 ms':>9}{'p99 ms':>9}{'req/s':>9}"
                  f"{'p50 x':>8}{'p99 x':>8}{'rps x':>8}{'cpu us':>9}{'1/cpu x':>9}")
            bare = results["bare"]
            for key, r in results.items():
                r.update(p50_ratio=r["p50_ms"] / bare["p50_ms"],
                         p99_ratio=r["p99_ms"] / bare["p99_ms"], rps_ratio=r["rps"] / bare["rps"],
                         cpu_ratio=bare["cpu_us"] / max(r["cpu_us"], 1e-9))
                print(f"{key:<18}{r['p50_ms']:9.3f}{r['p99_ms']:9.3f}{r['rps']:9.0f}"
                      f"{r['p50_ratio']:8.2f}{r['p99_ratio']:8.2f}{r['rps_ratio']:8.2f}"
                      f"{r['cpu_us']:9.0f}{r['cpu_ratio']:9.2f}")
            print("cpu us: the server's CPU time per request of the throughput phase; 1/cpu x: "
                  "the bare endpoint's over it (the throughput ratio of a server with a core "
                  "of its own)")

            for key in ("sh", "sh+normal", "maps"):
                if f"{key}[seg]" in results:
                    seg, plain = results[f"{key}[seg]"], results[key]
                    print(f"exact visibility ({key}[seg] / {key}): p50 "
                          f"{seg['p50_ms'] / plain['p50_ms']:.2f}x, req/s "
                          f"{seg['rps'] / plain['rps']:.2f}x, p50 "
                          f"{(seg['p50_ms'] - plain['p50_ms']) * 1e3:+.0f} us")

            if args.in_process:
                cost = in_process(stores, paths, max(200, args.requests // args.rounds),
                                  args.rounds)
                print("in process (the app's ASGI calls, no HTTP server), CPU us per request, "
                      "best of the rounds, and the bare endpoint's over it:")
                for key, us in cost.items():
                    print(f"  {key:<18}{us:9.1f}{cost['bare'] / us:8.2f}")
                    results[key]["in_process_cpu_us"] = us
            if len(stores) > 1:
                print(in_process_visibility_cost(stores[0], stores[1], grid.lo, grid.hi))

            server = psutil.Process(proc.pid)
            mixed = [u for k in ("sh", "sh+normal", "maps") for u in paths.get(k, [])]
            asyncio.run(load(port, mixed, 2000, args.connections, args.max_seconds))
            rss0 = server.memory_info().rss
            t0 = time.perf_counter()
            asyncio.run(load(port, mixed, args.rss_requests, args.connections, args.max_seconds))
            rss1 = server.memory_info().rss
            print(f"server RSS {rss0 / 2**20:.1f} MiB -> {rss1 / 2**20:.1f} MiB after "
                  f"{args.rss_requests} more mixed requests ({time.perf_counter() - t0:.0f} s): "
                  f"{(rss1 - rss0) / 2**20:+.1f} MiB")
            results["rss"] = {"before_mib": rss0 / 2**20, "after_mib": rss1 / 2**20,
                              "requests": float(args.rss_requests)}
            if args.json:
                args.json.write_text(json.dumps(results, indent=2))
        finally:
            proc.terminate()
            proc.wait(timeout=10)


if __name__ == "__main__":
    main()
