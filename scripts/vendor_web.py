"""Vendor the viewer's and the API docs' JavaScript from npm into ``service/static/vendor/``.

The service serves everything its pages load from inside the Python package (nothing is fetched
from elsewhere at run time): three.js for the viewer at ``/``, Swagger UI for ``/docs`` and
ReDoc for ``/redoc``. This script is the only way those files get there:

    python scripts/vendor_web.py            # npm pack the pinned versions, extract, write HASHES
    python scripts/vendor_web.py --check    # check the vendored files against HASHES (no network)

Each package is fetched with ``npm pack NAME@VERSION`` (the registry's tarball, whose integrity
npm checks), and only the files listed in :data:`PACKAGES` are extracted, at their paths inside
the package, under ``service/static/vendor/NAME/``. ``HASHES`` lists ``sha256  path`` of every
vendored file; re-vendoring the same versions must reproduce it exactly (the script says which
file differs), and ``tests/test_viewer_api.py`` checks the files on disk against it.
"""

from __future__ import annotations

import argparse
import hashlib
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
VENDOR = REPO / "service" / "static" / "vendor"
HASHES = VENDOR / "HASHES"

#: npm package -> (version, files inside the package to keep)
PACKAGES: dict[str, tuple[str, tuple[str, ...]]] = {
    "three": ("0.187.0", (
        "LICENSE",
        "build/three.module.js",
        "build/three.core.js",
        "examples/jsm/controls/OrbitControls.js",
        "examples/jsm/loaders/GLTFLoader.js",
        "examples/jsm/utils/BufferGeometryUtils.js",  # GLTFLoader's imports
        "examples/jsm/utils/SkeletonUtils.js",
        "examples/jsm/lighting/LightProbeGridWebGL.js",  # for the three.js export comparison
        "examples/jsm/lighting/LightProbeGridUtils.js",
        # KTX2Loader and its imports: the browser test loads probegrid's .ktx2 files with it
        "examples/jsm/loaders/KTX2Loader.js",
        "examples/jsm/libs/ktx-parse.module.js",
        "examples/jsm/libs/zstddec.module.js",
        "examples/jsm/utils/WorkerPool.js",
        "examples/jsm/math/ColorSpaces.js",
    )),
    "swagger-ui-dist": ("5.35.0", (
        "LICENSE",
        "NOTICE",
        "swagger-ui-bundle.js",
        "swagger-ui.css",
        "favicon-32x32.png",
    )),
    "redoc": ("2.5.4", (
        "LICENSE",
        "bundles/redoc.standalone.js",
    )),
}


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def read_hashes() -> dict[str, str]:
    """``relative path -> sha256`` from HASHES (paths relative to ``vendor/``)."""
    out = {}
    for line in HASHES.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            digest, path = line.split(maxsplit=1)
            out[path] = digest
    return out


def check() -> list[str]:
    """Problems of the vendored files against HASHES (empty when all match)."""
    problems = []
    expected = read_hashes()
    for path, digest in expected.items():
        f = VENDOR / path
        if not f.is_file():
            problems.append(f"missing {path}")
        elif sha256(f.read_bytes()) != digest:
            problems.append(f"changed {path}")
    for f in sorted(VENDOR.rglob("*")):
        rel = f.relative_to(VENDOR).as_posix()
        if f.is_file() and rel != "HASHES" and rel not in expected:
            problems.append(f"not listed in HASHES: {rel}")
    return problems


def vendor() -> None:
    old = read_hashes() if HASHES.is_file() else {}
    new: dict[str, str] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, (version, files) in PACKAGES.items():
            out = subprocess.run(["npm", "pack", f"{name}@{version}", "--silent"], cwd=tmp,
                                 check=True, capture_output=True, text=True).stdout
            tgz = Path(tmp) / out.strip().splitlines()[-1]
            with tarfile.open(tgz) as tar:
                members = {m.name.removeprefix("package/"): m for m in tar.getmembers()}
                for rel in files:
                    member = members.get(rel)
                    if member is None or not member.isfile():
                        sys.exit(f"{name}@{version} has no file {rel}")
                    data = tar.extractfile(member).read()  # type: ignore[union-attr]
                    target = VENDOR / name / rel
                    target.parent.mkdir(parents=True, exist_ok=True)
                    target.write_bytes(data)
                    new[f"{name}/{rel}"] = sha256(data)
    lines = ["# sha256  path (relative to this directory); written by scripts/vendor_web.py"]
    for name, (version, _) in PACKAGES.items():
        lines.append(f"# {name}@{version}")
    lines += [f"{d}  {p}" for p, d in sorted(new.items())]
    HASHES.write_text("\n".join(lines) + "\n")
    changed = sorted(p for p in new if p in old and old[p] != new[p])
    for p in changed:
        print(f"changed: {p}")
    total = sum((VENDOR / p).stat().st_size for p in new)
    print(f"vendored {len(new)} files, {total / 1e6:.2f} MB, into {VENDOR.relative_to(REPO)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="check files against HASHES only")
    args = ap.parse_args()
    if args.check:
        problems = check()
        for p in problems:
            print(p)
        sys.exit(1 if problems else 0)
    vendor()


if __name__ == "__main__":
    main()
