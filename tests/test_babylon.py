"""``probegrid filter --format gltf`` in real Babylon.js: npm ``@babylonjs/core`` and
``@babylonjs/loaders`` (versions pinned in ``tests/js/package.json``) in Debian's Chromium,
WebGL2 through SwiftShader, driven by Playwright.

``tests/js/babylon_ibl.html`` loads the exported ``environment.gltf`` with Babylon's own glTF
loader (its ``EXT_lights_image_based`` extension makes the light the scene's
``environmentTexture``) and draws two unit spheres lit by it alone, read back from a float
render target with no image processing:

* a mirror (PBR, metallic 1, roughness 0), seen along each test direction: its centre pixel
  reflects the view back, so it shows the environment toward that direction;
* a matte one (PBR, metallic 0, roughness 1, F0 0): its centre pixel is ``albedo E(n) / pi``
  with Babylon's SH irradiance at the normal.

Directions are glTF-frame directions; the page maps them into Babylon's (left-handed) world
through the world matrix of the ``__root__`` node that Babylon's loader makes for a glTF, so
nothing of Babylon's conventions is re-implemented here. Both are compared with what probegrid
computed: the mirror with its specular mip 0 (the input cube, bilinear) and the matte sphere
with the irradiance of the SH in ``sh.json``. Measured: mirror within 0.5 % (RGBD's 8 bits and
bilinear filtering), matte within 1e-3; the same file with upright faces (as probegrid wrote
them before it flipped them for Babylon's ``invertY`` upload) reads 50-60 % off at the median.

Also checked: Babylon 9 loads this light with ``gammaSpace`` true and then raises the radiance
to the power 2.2 (the reason docs/engines.md says to set ``gammaSpace = false``).

Skipped, with the reason, without Chromium, playwright, or the npm packages
(``npm install --prefix tests/js``).
"""

from __future__ import annotations

import functools
import http.server
import json
import shutil
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from node_readers import JS_DIR, node_package_dir

from probegrid import imageio
from probegrid.cli import main
from probegrid.core import sh
from probegrid.core.cubemap import texel_directions
from probegrid.core.sampling import sample_bilinear

pytestmark = [pytest.mark.browser, pytest.mark.slow]  # ~35 s: Babylon is ~570 ES modules

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--ignore-gpu-blocklist", "--no-sandbox", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]
SUFFIXES = ("px", "nx", "py", "ny", "pz", "nz")
SIZE = 64

if not Path(CHROMIUM).is_file():
    pytest.skip("no Chromium: `apt-get install chromium` (Debian) to run the browser tests",
                allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api",
                               reason="no playwright: pip install -e '.[test]'")


def sky(d: np.ndarray) -> np.ndarray:
    """A smooth environment, different along every axis and brighter above: RGB
    ``(1 + 0.8 x, 1 + 0.8 y, 1 + 0.8 z) (1 + 2 max(y, 0)^2)`` (glTF frame)."""
    d = np.asarray(d, np.float64)
    boost = 1.0 + 2.0 * np.clip(d[..., 1:2], 0.0, 1.0) ** 2
    return (1.0 + 0.8 * d) * boost


def directions() -> np.ndarray:
    """The six axes, the eight cube corners and twelve directions in between (fixed seed)."""
    axes = np.vstack([np.eye(3), -np.eye(3)])
    corners = np.array([[a, b, c] for a in (1, -1) for b in (1, -1) for c in (1, -1)],
                       np.float64) / np.sqrt(3)
    rest = np.random.default_rng(27).normal(size=(12, 3))
    rest /= np.linalg.norm(rest, axis=1, keepdims=True)
    return np.vstack([axes, corners, rest])


class _Quiet(http.server.SimpleHTTPRequestHandler):
    protocol_version = "HTTP/1.1"  # keep-alive: the page imports ~570 modules

    def log_message(self, *args) -> None:
        pass


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """A directory served to the page: the page, Babylon from npm, and two exports of the same
    sky -- ``env/`` as probegrid writes it and ``upright/`` with every face PNG turned back
    upright (the layout probegrid wrote before)."""
    base = node_package_dir(tmp_path_factory, "@babylonjs/core")
    if not (base / "node_modules" / "@babylonjs" / "loaders" / "package.json").is_file():
        pytest.skip("no @babylonjs/loaders in node_modules: npm install --prefix tests/js")
    root = tmp_path_factory.mktemp("babylon")
    cube = sky(texel_directions(SIZE)).astype(np.float32)
    faces = []
    for f, s in enumerate(SUFFIXES):
        faces.append(root / f"{s}.exr")
        imageio.write_image(faces[-1], cube[f], half=False)
    assert main(["filter", *map(str, faces), "--layout", "faces", "--format", "gltf",
                 "--diffuse-size", "4", "--lut-size", "4", "--out", str(root / "env")]) == 0
    shutil.copytree(root / "env", root / "upright")
    from PIL import Image

    for png in (root / "upright" / "ibl").glob("*.png"):
        Image.open(png).transpose(Image.Transpose.FLIP_TOP_BOTTOM).save(png)
    (root / "node_modules").symlink_to(base / "node_modules", target_is_directory=True)
    for name in ("babylon_ibl.html", "babylon_ibl.mjs"):
        shutil.copy(JS_DIR / name, root / name)
    np.save(root / "cube.npy", cube)
    return root


class Page:
    """The Playwright page and what went wrong on it (console errors, page errors, HTTP >= 400)."""

    def __init__(self, pg, problems: list[str]) -> None:
        self.pg = pg
        self.problems = problems

    def evaluate(self, expression: str, arg=None):
        return self.pg.evaluate(expression, arg)


@pytest.fixture(scope="module")
def page(site) -> Iterator[Page]:
    handler = functools.partial(_Quiet, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    problems: list[str] = []
    try:
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            pg = browser.new_page()
            pg.on("pageerror", lambda e: problems.append(f"page error: {e}"))
            pg.on("console", lambda m: m.type == "error" and problems.append(m.text))
            pg.on("response", lambda r: r.status >= 400 and problems.append(
                f"HTTP {r.status} {r.url}"))
            pg.goto(f"http://127.0.0.1:{server.server_address[1]}/babylon_ibl.html")
            pg.wait_for_function("window.babylonIbl && window.babylonIbl.ready",
                                 timeout=120_000)
            yield Page(pg, problems)
            browser.close()
    finally:
        server.shutdown()
        server.server_close()


def look(page: Page, dirs: np.ndarray, kind: str) -> np.ndarray:
    return np.array(page.evaluate("([d, k]) => window.babylonIbl.look(d, k)",
                                [dirs.tolist(), kind]), np.float64)


def rel_error(got: np.ndarray, want: np.ndarray) -> np.ndarray:
    """Per direction: the largest channel error over the brightest channel."""
    return np.abs(got - want).max(axis=1) / want.max(axis=1)


@pytest.fixture(scope="module")
def loaded(page, site) -> dict:
    info = page.evaluate("window.babylonIbl.load('./env/environment.gltf')")
    assert page.problems == []
    return info


def test_babylon_loads_the_light_as_probegrid_describes_it(loaded, site):
    doc = json.loads((site / "env" / "environment.gltf").read_text())
    light = doc["extensions"]["EXT_lights_image_based"]["lights"][0]
    assert loaded["version"] == "9.28.0"  # the pinned package, not another copy
    assert loaded["isCube"] and loaded["size"] == light["specularImageSize"] == SIZE
    assert loaded["lodGenerationScale"] == pytest.approx(2 / np.log2(SIZE))  # 3 mips
    # glTF space in Babylon's default scene: x mirrored (the loader's __root__)
    np.testing.assert_allclose(np.reshape(loaded["root"], (4, 4)),
                               np.diag([-1.0, 1.0, 1.0, 1.0]), atol=1e-12)
    # Babylon 9 treats this light's texture as gamma-encoded: docs/engines.md says to reset it
    assert loaded["gammaSpace"] is True


def test_mirror_sphere_shows_probegrids_specular_map(page, loaded, site):
    dirs = directions()
    want = sample_bilinear(np.load(site / "cube.npy"), dirs).astype(np.float64)
    # as loaded (gammaSpace true) Babylon raises the radiance to the power 2.2 once more
    # (its PBR shader clamps the result at 30)
    gamma = look(page, dirs[:6], "mirror")
    np.testing.assert_allclose(gamma, np.minimum(want[:6] ** 2.2, 30.0), rtol=0.03)
    assert page.evaluate("window.babylonIbl.setGammaSpace(false)") is False
    got = look(page, dirs, "mirror")
    err = rel_error(got, want)
    print(f"\nBabylon mirror vs probegrid: median {np.median(err):.2e}, max {err.max():.2e}")
    assert np.median(err) < 0.01 and err.max() < 0.02, np.column_stack([dirs, got, want])
    assert page.problems == []


def test_matte_sphere_shows_probegrids_irradiance(page, loaded, site):
    dirs = directions()
    L = np.asarray(json.loads((site / "env" / "sh.json").read_text())["coefficients"])
    want = sh.irradiance(L, dirs) / np.pi
    got = look(page, dirs, "matte")
    err = rel_error(got, want)
    print(f"\nBabylon matte vs probegrid: median {np.median(err):.2e}, max {err.max():.2e}")
    assert err.max() < 2e-3, np.column_stack([dirs, got, want])
    assert page.problems == []


def test_upright_faces_read_upside_down_in_babylon(page, loaded, site):
    """The check above is not blind to the face rows: the same file with upright faces (the
    GL / KTX2 row order) is far off everywhere but at the face centres."""
    info = page.evaluate("window.babylonIbl.load('./upright/environment.gltf')")
    page.evaluate("window.babylonIbl.setGammaSpace(false)")
    dirs = directions()
    want = sample_bilinear(np.load(site / "cube.npy"), dirs).astype(np.float64)
    err = rel_error(look(page, dirs, "mirror"), want)
    print(f"\nupright faces in Babylon: median {np.median(err):.2e}")
    assert info["size"] == SIZE
    assert err[:6].max() < 0.02  # a face's centre stays where it is
    assert np.median(err) > 0.3
    assert page.problems == []
