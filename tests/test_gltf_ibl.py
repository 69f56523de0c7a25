"""``probegrid filter --format gltf`` (probegrid.export.gltf_ibl): a glTF with
EXT_lights_image_based, checked against Babylon.js' reading of it, re-implemented in numpy from
its source:

* the loader (``EXT_lights_image_based.ts``): ``lodGenerationScale = (mips - 1) /
  log2(specularImageSize)``; the PBR shader's ``getLodFromAlphaG``: ``lod = log2(size * alphaG)
  * scale``;
* ``fromRGBD`` (helperFunctions.fx): ``pow(rgb, 2.2) / a``;
* the glTF loader's root node in Babylon's default left-handed scene (rotation [0, 1, 0, 0],
  scale (1, 1, -1)): glTF direction ``(x, y, z)`` is looked up at ``(-x, y, z)`` in the cube
  (OpenGL face table; Babylon uploads each face with ``invertY``, so a PNG's first row is the
  face's ``t = 1`` row) and in the irradiance polynomial (``SH3ylmBasisConstants`` x
  ``SH3ylmBasisTrigonometricTerms``).

``tests/test_babylon.py`` runs real Babylon.js on the same kind of file.

PNG faces are read with OpenImageIO (unassociated alpha), not with the writer's Pillow; the file
is validated by the Khronos glTF validator (npm gltf-validator, skipped without node).
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
from node_readers import JS_DIR, node_package_dir

from probegrid import imageio
from probegrid.cli import main
from probegrid.core import sh
from probegrid.core.cubemap import texel_directions, texel_solid_angles
from probegrid.export import gltf_ibl

SUFFIXES = ("px", "nx", "py", "ny", "pz", "nz")
#: Babylon's SH3ylmBasisConstants (sphericalPolynomial.ts), order l00, l1-1, l10, l11, l2-2, ...
BABYLON_CONST = np.array([np.sqrt(1 / (4 * np.pi)), -np.sqrt(3 / (4 * np.pi)),
                          np.sqrt(3 / (4 * np.pi)), -np.sqrt(3 / (4 * np.pi)),
                          np.sqrt(15 / (4 * np.pi)), -np.sqrt(15 / (4 * np.pi)),
                          np.sqrt(5 / (16 * np.pi)), -np.sqrt(15 / (4 * np.pi)),
                          np.sqrt(15 / (16 * np.pi))])


def lopsided(n: int) -> np.ndarray:
    """Grey 0.2 plus a red lobe toward +X and a green one toward +Z (glTF frame)."""
    d = np.asarray(texel_directions(n), np.float64)
    red = 20 * np.clip(d[..., 0:1], 0, 1) ** 8 * np.array([1.0, 0, 0])
    green = 20 * np.clip(d[..., 2:3], 0, 1) ** 8 * np.array([0, 1.0, 0])
    return (0.2 + red + green).astype(np.float32)


def read_png_rgba(path: Path) -> np.ndarray:
    cfg = oiio.ImageSpec()
    cfg.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), cfg)
    assert inp is not None, oiio.geterror()
    try:
        assert inp.spec().nchannels == 4
        return np.asarray(inp.read_image(format="uint8"))
    finally:
        inp.close()


def from_rgbd(b: np.ndarray) -> np.ndarray:
    """helperFunctions.fx fromRGBD on 8-bit texels read as [0, 1]."""
    v = b.astype(np.float64) / 255.0
    return v[..., :3] ** 2.2 / v[..., 3:]


def rgbd_tol(x: np.ndarray) -> np.ndarray:
    """RGBD's 8-bit error bound per texel (see the RGBD test): 2.2 (0.5/255) / 0.73 of the
    brightest channel when it is >= 1, 2.2 (0.5/255) absolute below."""
    m = np.asarray(x, np.float64).max(axis=-1, keepdims=True)
    return np.where(m >= 1, 2.2 * 0.5 / 255 / 0.73 * m, 2.2 * 0.5 / 255) * (1 + 1e-6)


def gl_nearest(faces: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Nearest-texel OpenGL cube lookup (table 8.19) of directions ``d`` (..., 3)."""
    d = np.asarray(d, np.float64)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    ax, ay, az = np.abs(d).T if d.ndim == 1 else np.moveaxis(np.abs(d), -1, 0)
    xm = (ax >= ay) & (ax >= az)
    ym = ~xm & (ay >= az)
    face = np.where(xm, np.where(x > 0, 0, 1), np.where(ym, np.where(y > 0, 2, 3),
                                                         np.where(z > 0, 4, 5)))
    sc = np.choose(face, [-z, z, x, x, x, -x])
    tc = np.choose(face, [-y, -y, z, -z, -y, -y])
    ma = np.choose(face, [ax, ax, ay, ay, az, az])
    n = faces.shape[1]
    col = np.clip(np.floor(0.5 * (sc / ma + 1) * n), 0, n - 1).astype(int)
    row = np.clip(np.floor(0.5 * (tc / ma + 1) * n), 0, n - 1).astype(int)
    return faces[face, row, col]


def babylon_view(d: np.ndarray) -> np.ndarray:
    """glTF direction -> the direction Babylon's default (left-handed) scene looks it up at."""
    return np.asarray(d, np.float64) * np.array([-1.0, 1.0, 1.0])


@pytest.fixture(scope="module")
def gltf_out(tmp_path_factory) -> tuple[Path, np.ndarray]:
    tmp = tmp_path_factory.mktemp("gltf")
    cube = lopsided(32)
    faces = []
    for f, s in enumerate(SUFFIXES):
        faces.append(tmp / f"{s}.exr")
        imageio.write_image(faces[-1], cube[f], half=False)
    out = tmp / "out"
    assert main(["filter", *map(str, faces), "--layout", "faces", "--format", "gltf",
                 "--diffuse-size", "4", "--lut-size", "4", "--out", str(out)]) == 0
    return out, cube


def loaded_chain(out: Path) -> tuple[dict, list[np.ndarray]]:
    """The light and its mips, decoded and uploaded the way Babylon does (faces in slot order,
    rows in GL order: ``invertY`` puts a PNG's first row at ``t = 1``)."""
    doc = json.loads((out / "environment.gltf").read_text())
    light = doc["extensions"]["EXT_lights_image_based"]["lights"][0]
    mips = [np.stack([from_rgbd(read_png_rgba(out / doc["images"][i]["uri"]))[::-1]
                      for i in row])
            for row in light["specularImages"]]
    return light, mips


# ---------------------------------------------------------------------------------- mapping
def test_mip_alphas_are_where_babylon_samples_them():
    a = gltf_ibl.babylon_alphas(256)
    np.testing.assert_allclose(a, [0, 1 / 64, 1 / 16, 1 / 4, 1], rtol=1e-12)
    for size in (32, 64, 128, 256, 1024):
        alphas = gltf_ibl.babylon_alphas(size)
        mips = int(np.log2(size)) - 3  # down to 16^2
        scale = (mips - 1) / np.log2(size)  # the loader's lodGenerationScale
        lod = np.log2(size * alphas[1:]) * scale  # getLodFromAlphaG, then the scale
        np.testing.assert_allclose(lod, np.arange(1, mips), rtol=0, atol=1e-12)
        assert alphas[-1] == pytest.approx(1.0) and len(alphas) == mips
        # perceptual roughness r: Babylon's alphaG = r^2 reads mip k at r = sqrt(alpha_k)
        np.testing.assert_allclose(gltf_ibl.babylon_lod(alphas, size), np.arange(mips),
                                   atol=1e-12)
    for bad in (16, 48, 0):
        with pytest.raises(ValueError, match="power-of-two cube size of at least 32"):
            gltf_ibl.mip_count(bad)


def test_rgbd_bytes_match_babylons_torgbd_by_hand():
    enc = gltf_ibl.rgbd_encode(np.array([[1.0, 0.5, 0.25], [100.0, 0.0, 0.0],
                                         [0.001, 0.0, 0.0], [1000.0, 0.0, 0.0]]))
    # max 1: D = floor(255) / 255 = 1; rgb^(1/2.2)
    assert enc[0].tolist() == [255, round(0.5 ** (1 / 2.2) * 255),
                               round(0.25 ** (1 / 2.2) * 255), 255]
    # max 100: D = floor(2.55) / 255 = 2/255; r = (200/255)^(1/2.2)
    assert enc[1].tolist() == [round((200 / 255) ** (1 / 2.2) * 255), 0, 0, 2]
    assert enc[2][3] == 255 and enc[3].tolist() == [255, 0, 0, 1]  # D clamps; > 255 clips
    rng = np.random.default_rng(3)
    x = rng.uniform(0, 1, (2000, 3)) * 10.0 ** rng.uniform(-3, 2.3, (2000, 1))
    back = gltf_ibl.rgbd_decode(gltf_ibl.rgbd_encode(x))
    np.testing.assert_allclose(back, from_rgbd(gltf_ibl.rgbd_encode(x)), rtol=1e-6)
    # 8-bit gamma-2.2 quantisation, half a step: for max >= 1, D scales the brightest channel
    # into (0.5, 1] (gamma-coded > 0.73), relative error <= 2.2 (0.5/255) / 0.73; below 1,
    # D = 1 and the absolute error is <= 2.2 (0.5/255)
    m = x.max(axis=1)
    err = np.abs(back - x).max(axis=1)
    assert (err / m)[m >= 1].max() < 2.2 * 0.5 / 255 / 0.73
    assert err[m < 1].max() < 2.2 * 0.5 / 255


def ggx_dense(cube: np.ndarray, alpha: float, dirs: np.ndarray) -> np.ndarray:
    """The GGX prefilter at output directions ``dirs``, summed over every source texel:
    ``sum L D(h) max(0, cos) dw / sum D(h) max(0, cos) dw`` with ``h`` halfway between the
    lobe axis and the texel (the split-sum n = v = r prefilter)."""
    n = cube.shape[1]
    src = np.asarray(texel_directions(n), np.float64).reshape(-1, 3)
    dw = np.asarray(texel_solid_angles(n), np.float64).reshape(-1)
    c = np.clip(dirs @ src.T, -1, 1)
    nh2 = 0.5 * (1 + c)
    a2 = alpha * alpha
    k = a2 / (np.pi * (nh2 * (a2 - 1) + 1) ** 2) * np.maximum(c, 0) * dw
    return (k @ cube.reshape(-1, 3).astype(np.float64)) / k.sum(axis=1, keepdims=True)


def test_mips_are_the_ggx_lobes_babylon_asks_for():
    cube = lopsided(64)
    chain = gltf_ibl.specular_chain(cube)
    assert [lv.shape[1] for lv in chain] == [64, 32, 16]
    np.testing.assert_array_equal(chain[0], cube)
    rng = np.random.default_rng(4)
    for k, alpha in ((1, 0.125), (2, 1.0)):
        s = 64 >> k
        pick = rng.choice(6 * s * s, 300, replace=False)
        dirs = np.asarray(texel_directions(s), np.float64).reshape(-1, 3)[pick]
        ref = ggx_dense(cube, alpha, dirs)
        got = chain[k].reshape(-1, 3)[pick]
        np.testing.assert_allclose(got, ref, rtol=0, atol=5e-3 * ref.max())
        if k == 1:  # the k/(levels-1) mapping would put mip 1 at alpha 0.25: another lobe
            wrong = ggx_dense(cube, 0.25, dirs)
            assert np.abs(got - wrong).max() > 0.05 * wrong.max()


# ---------------------------------------------------------------------------------- the file
def test_babylon_reads_red_toward_x_and_green_toward_z(gltf_out):
    out, cube = gltf_out
    light, mips = loaded_chain(out)
    assert light["specularImageSize"] == 32 and len(mips) == 2
    assert light["intensity"] == 1.0 and light["rotation"] == [0, 0, 0, 1]
    red = gl_nearest(mips[0], babylon_view([1.0, 0, 0]))
    green = gl_nearest(mips[0], babylon_view([0, 0, 1.0]))
    assert red[0] > 15 and red[1] < 0.3 and green[1] > 15 and green[0] < 0.3
    assert gl_nearest(mips[0], babylon_view([-1.0, 0, 0]))[0] < 0.3
    assert gl_nearest(mips[0], babylon_view([0, 0, -1.0]))[1] < 0.3
    # every texel direction: Babylon's read of glTF direction w is the source's value at w
    w = np.asarray(texel_directions(32), np.float64)
    got = gl_nearest(mips[0], babylon_view(w))
    assert (np.abs(got - cube) <= rgbd_tol(cube)).all()
    # mip 1 (alpha 1): Babylon's read equals the dense GGX lobe at the same glTF direction
    w16 = np.asarray(texel_directions(16), np.float64).reshape(-1, 3)
    ref = ggx_dense(cube, 1.0, w16)
    got = gl_nearest(mips[1], babylon_view(w16))
    assert (np.abs(got - ref) <= rgbd_tol(ref) + 5e-3 * ref.max()).all()
    # the raw GL table (no mirror) would read the red lobe toward -X: the mirror is needed
    assert gl_nearest(mips[0], [-1.0, 0, 0])[0] > 15


def test_irradiance_coefficients_evaluate_to_the_irradiance_babylon_needs(gltf_out):
    out, cube = gltf_out
    light, _ = loaded_chain(out)
    c = np.asarray(light["irradianceCoefficients"], np.float64)
    assert c.shape == (9, 3)
    rng = np.random.default_rng(5)
    w = rng.normal(size=(64, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    x, y, z = babylon_view(w).T
    trig = np.stack([np.ones_like(x), y, z, x, x * y, y * z, 3 * z * z - 1, x * z,
                     x * x - y * y], -1)  # SH3ylmBasisTrigonometricTerms
    got = (trig * BABYLON_CONST) @ c
    want = sh.irradiance(sh.project_cube(cube), w)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    e_x = (np.array([1, 0, 0, -1, 0, 0, -1, 0, 1]) * BABYLON_CONST) @ c  # Babylon (-1, 0, 0)
    assert e_x[0] > 2 * e_x[1]  # glTF +X is the red side


@pytest.mark.slow
def test_gltf_validator_finds_no_errors(gltf_out, tmp_path_factory, tmp_path):
    out, _ = gltf_out
    base = node_package_dir(tmp_path_factory, "gltf-validator")

    def validate(path: Path) -> dict:
        run = subprocess.run(["node", str(JS_DIR / "gltf_validate.mjs"), str(path)],
                             capture_output=True, text=True, timeout=120, check=False,
                             env={"GLTF_VALIDATOR_DIR": str(base),
                                  "PATH": os.environ.get("PATH", "")})
        assert run.returncode == 0, run.stderr
        return json.loads(run.stdout)[0]

    report = validate(out / "environment.gltf")
    issues = report["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
    images = [r for r in report["info"]["resources"] if r["pointer"].startswith("/images/")]
    assert len(images) == 12 and all(r["image"]["format"] == "rgba" for r in images)
    # the validator reads the faces: a missing one is an error
    broken = tmp_path / "b"
    (broken / "ibl").mkdir(parents=True)
    for p in (out / "ibl").iterdir():
        if p.name != "specular_m1_nz.png":
            (broken / "ibl" / p.name).write_bytes(p.read_bytes())
    (broken / "environment.gltf").write_bytes((out / "environment.gltf").read_bytes())
    assert validate(broken / "environment.gltf")["issues"]["numErrors"] >= 1


def test_manifest_and_refusals(gltf_out, tmp_path, capsys):
    out, _ = gltf_out
    man = json.loads((out / "manifest.json").read_text())
    assert man["settings"]["format"] == "gltf"
    np.testing.assert_allclose(man["specular"]["roughness"], [0.0, 1.0])
    kinds = {f["kind"] for f in man["files"]}
    assert {"gltf", "specular", "sh", "preview"} <= kinds
    sky = tmp_path / "sky.exr"
    imageio.write_image(sky, np.ones((8, 16, 3), np.float32), half=False)
    for extra, words in ((["--size", "16"], "at least 32"),
                         (["--size", "32", "--specular-levels", "2"], "--specular-levels"),
                         (["--size", "32", "--output-layout", "hcross"], "--output-layout"),
                         (["--size", "32", "--specular-method", "exact"], "--specular-method"),
                         (["--size", "32", "--cube-convention", "bevy"], "--cube-convention")):
        capsys.readouterr()
        assert main(["filter", str(sky), "--format", "gltf", "--out", str(tmp_path / "o"),
                     *extra]) != 0
        err = capsys.readouterr().err.strip()
        assert words in err and len(err.splitlines()) == 1, err  # refused before any work
        assert not (tmp_path / "o").exists()
