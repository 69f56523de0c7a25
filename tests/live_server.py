"""A real uvicorn server in a subprocess, on 127.0.0.1 and a free port, for the service tests.

:func:`serve` starts ``service.main.run`` (the same entry point as ``probegrid serve``) with the
given stores and ``PROBEGRID_*`` settings, waits until ``/healthz`` answers, and stops the process
(SIGINT, then SIGKILL) when the context exits. The server's output goes to a log file, which the
tests read to check that no request ever reached the last-resort error handler.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class LiveServer:
    url: str
    process: subprocess.Popen[bytes]
    log: Path

    def log_text(self) -> str:
        return self.log.read_text(errors="replace")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def serve(
    stores: Sequence[Path],
    log: Path,
    *,
    workers: int = 1,
    settings: dict[str, object] | None = None,
    startup_timeout: float = 60.0,
) -> Iterator[LiveServer]:
    """Run the service on a free port until the block exits."""
    port = free_port()
    env = dict(os.environ)
    env.update({f"PROBEGRID_{k.upper()}": json.dumps(v) for k, v in (settings or {}).items()})
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    code = (
        "import sys, json; from service.main import run; "
        "run(json.loads(sys.argv[1]), host='127.0.0.1', port=int(sys.argv[2]), "
        "workers=int(sys.argv[3]), log_level='warning')"
    )
    args = [sys.executable, "-c", code, json.dumps([str(p) for p in stores]), str(port),
            str(workers)]
    with open(log, "wb") as out:
        proc = subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=REPO)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + startup_timeout
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"the server exited ({proc.returncode}):\n{log.read_text()}")
            try:
                if httpx.get(url + "/healthz", timeout=1.0).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"the server did not start in {startup_timeout} s")
            time.sleep(0.1)
        yield LiveServer(url=url, process=proc, log=log)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
