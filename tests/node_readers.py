"""Independent readers from npm, run under node by the tests: ``ktx-parse`` (KTX2).

They are looked for in ``tests/js/node_modules`` (``npm install --prefix tests/js``, which CI
runs); otherwise, when node and npm are on PATH, installed once per test run into a
temporary directory (versions pinned in ``tests/js/package.json``). Tests that need them skip
with the reason when neither works (no node, no npm, or no registry).
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

JS_DIR = Path(__file__).resolve().parent / "js"


def _installed(base: Path, package: str) -> bool:
    return (base / "node_modules" / package / "package.json").is_file()


def node_package_dir(tmp_path_factory: pytest.TempPathFactory, package: str) -> Path:
    """A directory whose ``node_modules`` holds ``package``; skips the test when there is none."""
    if shutil.which("node") is None:
        pytest.skip(f"node is not installed: the independent {package} check needs it")
    if _installed(JS_DIR, package):
        return JS_DIR
    if shutil.which("npm") is None:
        pytest.skip(f"npm is not installed and tests/js/node_modules has no {package} "
                    "(run: npm install --prefix tests/js)")
    base = tmp_path_factory.getbasetemp() / "node-readers"
    if not _installed(base, package):
        base.mkdir(exist_ok=True)
        shutil.copy(JS_DIR / "package.json", base / "package.json")
        try:
            run = subprocess.run(["npm", "install", "--prefix", str(base), "--no-audit",
                                  "--no-fund", "--loglevel=error"], capture_output=True,
                                 check=False,
                                 text=True, timeout=180)
        except subprocess.TimeoutExpired:
            pytest.skip(f"npm install of {package} timed out (no registry?)")
        if run.returncode != 0 or not _installed(base, package):
            line = (run.stderr.strip().splitlines() or ["?"])[-1]
            pytest.skip(f"npm could not install {package} ({line}); run: npm install "
                        "--prefix tests/js")
    return base


def ktx_parse_dump(base: Path, files: list[Path]) -> list[dict]:
    """Every file as ktx-parse reads it (see tests/js/ktx_dump.mjs)."""
    run = subprocess.run(["node", str(JS_DIR / "ktx_dump.mjs"), *map(str, files)],
                         capture_output=True, text=True, timeout=120, check=False,
                         env={"KTX_PARSE_DIR": str(base), "PATH": _path()})
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


def _path() -> str:
    import os

    return os.environ.get("PATH", "")
