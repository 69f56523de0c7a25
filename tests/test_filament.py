"""``probegrid filter --format filament`` (probegrid.export.filament): KTX1 files for Filament's
``IndirectLight``, checked against Filament's own tool.

``cmgen`` (Debian ``libfilament-tools``) run on probegrid's cross of the same sky with
``--format=ktx --no-mirror --sh-window=no`` writes the file Filament's loader is made for; the
test parses both the way ``Ktx1Bundle`` does (header, key/value pairs with 4-byte padding, one
``imageSize`` per mip, six faces) and compares: the same header fields, the same keys, the same
mip sizes, mip 0's texels within R11F_G11F_B10F rounding, the SH key within 1e-5, and the
rougher mips filtered at the roughness Filament reads them with (cmgen's importance sampling
against probegrid's exact GGX sums; probegrid's own ``r = k / (levels - 1)`` would be far off).
Skipped, with the reason, without cmgen.
"""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from probegrid import imageio
from probegrid.cli import main
from probegrid.core import layouts
from probegrid.core import sh as shlib
from probegrid.core.cubemap import texel_directions
from probegrid.core.specular import ggx_filter
from probegrid.export import filament, shforms

SIZE = 64
MAGIC = bytes([0xAB, 0x4B, 0x54, 0x58, 0x20, 0x31, 0x31, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A])
HEADER = ("endianness glType glTypeSize glFormat glInternalFormat glBaseInternalFormat "
          "pixelWidth pixelHeight pixelDepth numberOfArrayElements numberOfFaces "
          "numberOfMipmapLevels bytesOfKeyValueData").split()


def read_ktx1(path: Path) -> tuple[dict, dict, list[np.ndarray]]:
    """(header, key/values, mips as (6, s, s) uint32 words), read as ``Ktx1Bundle`` reads."""
    b = path.read_bytes()
    assert b[:12] == MAGIC
    head = dict(zip(HEADER, struct.unpack("<13I", b[12:64]), strict=True))
    p, end, kv = 64, 64 + head["bytesOfKeyValueData"], {}
    while p < end:
        (n,) = struct.unpack("<I", b[p:p + 4])
        body = b[p + 4:p + 4 + n]
        key, value = body.split(b"\0", 1)  # the key must be NUL-terminated
        kv[key.decode()] = value
        p += 4 + n + 3 - (n + 3) % 4
    assert p == end
    mips = []
    for k in range(head["numberOfMipmapLevels"]):
        (face,) = struct.unpack("<I", b[p:p + 4])
        s = head["pixelWidth"] >> k
        assert face == 4 * s * s  # one face's bytes: a non-array cube map
        mips.append(np.frombuffer(b[p + 4:p + 4 + 6 * face], "<u4").reshape(6, s, s))
        p += 4 + 6 * face
    assert p == len(b)
    return head, kv, mips


def parse_sh(value: bytes) -> np.ndarray:
    """``Ktx1Bundle::getSphericalHarmonics``: 27 whitespace-separated numbers."""
    nums = [float(x) for x in value.decode().split()]
    assert len(nums) == 27
    return np.array(nums).reshape(9, 3)


def sky(n: int) -> np.ndarray:
    """Smooth light, different along every axis, brighter above, plus a sharp bright lobe
    (so that the mips' roughness matters)."""
    d = np.asarray(texel_directions(n), np.float64)
    base = (1.0 + 0.8 * d) * (1.0 + 2.0 * np.clip(d[..., 1:2], 0, 1) ** 2)
    lobe = 30.0 * np.clip(0.6 * d[..., 0:1] + 0.8 * d[..., 1:2], 0, 1) ** 40
    return (base + lobe).astype(np.float32)


def test_roughness_inverts_filaments_lod():
    r = filament.filament_roughness(5)
    np.testing.assert_allclose(filament.filament_lod(r, 5), np.arange(5), atol=1e-12)
    assert r[0] == 0 and r[-1] == 1
    np.testing.assert_allclose(r[1], 1 - np.sqrt(0.75))  # 0.134, not 0.25
    assert [filament.mip_count(s) for s in (32, 64, 256)] == [2, 3, 5]
    for bad in (16, 48):
        with pytest.raises(ValueError, match="at least 32"):
            filament.check_size(bad)


def test_r11g11b10_words():
    w = filament.encode_r11g11b10(np.array([[1.0, 1.0, 1.0], [0.0, 2.0, 0.5],
                                            [-3.0, np.nan, 1e9]]))
    assert w[0] == (15 << 6) | (15 << 6) << 11 | (15 << 5) << 22
    assert w[1] == 0 | (16 << 6) << 11 | (14 << 5) << 22
    assert w[2] == 0 | 0 << 11 | ((30 << 5) | 31) << 22  # < 0 and NaN -> 0, too big -> max
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 1, (5000, 3)) * 10.0 ** rng.uniform(-3, 4, (5000, 1))
    back = filament.decode_r11g11b10(filament.encode_r11g11b10(x)).astype(np.float64)
    err = np.abs(back - x)
    normal = x >= 2.0 ** -14  # half a unit in the last place (6 and 5 mantissa bits)
    assert (err / x)[:, :2][normal[:, :2]].max() <= 2.0 ** -7 * 1.0001
    assert (err / x)[:, 2][normal[:, 2]].max() <= 2.0 ** -6 * 1.0001
    assert err[:, :2][~normal[:, :2]].max() <= 2.0 ** -21 and err[~normal].max() <= 2.0 ** -20


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, np.ndarray]:
    tmp = tmp_path_factory.mktemp("filament")
    cube = sky(SIZE)
    imageio.write_image(tmp / "cross.exr", layouts.faces_to_cross(cube, "hcross"), half=False)
    assert main(["filter", str(tmp / "cross.exr"), "--format", "filament",
                 "--diffuse-size", "4", "--lut-size", "4", "--out", str(tmp / "out")]) == 0
    return tmp, cube


def test_file_holds_the_chain_and_sh_filament_reads(exported):
    tmp, cube = exported
    head, kv, mips = read_ktx1(tmp / "out" / filament.IBL_FILE)
    assert (head["glType"], head["glTypeSize"], head["glFormat"], head["glInternalFormat"],
            head["glBaseInternalFormat"]) == (0x8C3A, 1, 0x1907, 0x8C3A, 0x8C3A)
    assert head["numberOfFaces"] == 6 and head["numberOfMipmapLevels"] == 3
    assert set(kv) == {"sh"}
    np.testing.assert_allclose(parse_sh(kv["sh"]),
                               shforms.filament_prescaled(shlib.project_cube(cube)),
                               rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(filament.decode_r11g11b10(mips[0]), cube, rtol=2.0 ** -6)
    r = filament.filament_roughness(3)
    np.testing.assert_allclose(filament.decode_r11g11b10(mips[1]),
                               ggx_filter(cube, float(r[1] ** 2), SIZE // 2),
                               rtol=2.0 ** -6, atol=1e-6)
    sky_head, sky_kv, sky_mips = read_ktx1(tmp / "out" / filament.SKYBOX_FILE)
    assert sky_head["numberOfMipmapLevels"] == 1 and sky_kv == {}
    np.testing.assert_array_equal(sky_mips[0], mips[0])
    man = json.loads((tmp / "out" / "manifest.json").read_text())
    entry = next(f for f in man["files"] if f["path"] == filament.IBL_FILE)
    assert entry["format"] == "ktx1" and entry["sh_key"] == "sh"
    np.testing.assert_allclose(entry["roughness"], r)
    assert "1 - sqrt(1 - k/(levels-1))" in entry["conventions"]
    np.testing.assert_allclose(man["specular"]["roughness"], r)


@pytest.fixture(scope="module")
def cmgen_out(exported) -> Path:
    exe = shutil.which("cmgen")
    if exe is None:
        pytest.skip("no cmgen: `apt-get install libfilament-tools` (Debian) for the check "
                    "against Filament's own tool")
    tmp, _ = exported
    run = subprocess.run([exe, "--quiet", "--no-mirror", "--sh-window=no", "--format=ktx",
                          f"--size={SIZE}", f"--deploy={tmp / 'cmgen'}", str(tmp / "cross.exr")],
                         capture_output=True, text=True, timeout=300, check=False)
    assert run.returncode == 0, run.stderr
    (ibl,) = (tmp / "cmgen").glob("*_ibl.ktx")
    return ibl


def test_file_matches_what_cmgen_writes_of_the_same_sky(exported, cmgen_out):
    tmp, cube = exported
    head, kv, mips = read_ktx1(tmp / "out" / filament.IBL_FILE)
    c_head, c_kv, c_mips = read_ktx1(cmgen_out)
    strip = {"bytesOfKeyValueData"}  # (the SH's decimal digits differ)
    assert {k: v for k, v in head.items() if k not in strip} == \
           {k: v for k, v in c_head.items() if k not in strip}
    assert set(kv) == set(c_kv) == {"sh"}
    assert [m.shape for m in mips] == [m.shape for m in c_mips]
    # the SH: cmgen prints 6 digits
    ours, theirs = parse_sh(kv["sh"]), parse_sh(c_kv["sh"])
    np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-5 * np.abs(theirs).max())
    # mip 0: the same input, rounded to R11F_G11F_B10F by both (face order and rows included)
    a, b = (filament.decode_r11g11b10(m[0]).astype(np.float64) for m in (mips, c_mips))
    assert np.abs(a - b).max() <= 2.0 ** -5 * b.max()
    assert np.median(np.abs(a - b) / b) < 1e-3
    # mip 1: cmgen filters at Filament's roughness too; probegrid's k/(levels-1) would not match
    a, b = (filament.decode_r11g11b10(m[1]).astype(np.float64) for m in (mips, c_mips))
    err = np.abs(a - b) / b.max()
    wrong = np.abs(ggx_filter(cube, 0.5 ** 2, SIZE // 2) - b) / b.max()
    print(f"\nmip 1 vs cmgen: median {np.median(err):.2e}, max {err.max():.2e}; "
          f"at r = 1/2: max {wrong.max():.2e}")
    assert np.median(err) < 3e-3 and err.max() < 0.1
    assert wrong.max() > 0.3
    # mip 2 (r = 1): cmgen's importance sampling against probegrid's sums
    a, b = (filament.decode_r11g11b10(m[2]).astype(np.float64) for m in (mips, c_mips))
    assert np.median(np.abs(a - b) / b.max()) < 0.03


def test_refusals(tmp_path, capsys):
    src = tmp_path / "sky.exr"
    imageio.write_image(src, np.ones((8, 16, 3), np.float32), half=False)
    for extra, words in ((["--size", "16"], "at least 32"),
                         (["--size", "32", "--specular-levels", "2"], "--specular-levels"),
                         (["--size", "32", "--output-layout", "hcross"], "--output-layout")):
        capsys.readouterr()
        assert main(["filter", str(src), "--format", "filament", "--out",
                     str(tmp_path / "o"), *extra]) != 0
        err = capsys.readouterr().err.strip()
        assert words in err and "filament" in err.lower(), err
        assert len(err.splitlines()) == 1 and not (tmp_path / "o").exists()


# --- export --target filament: a store's probe, filtered again at Filament's roughness --------

def _store_with_incoming(path: Path, cube: np.ndarray, *, incoming: bool = True):
    """A 2-probe store whose probe (1, 0, 0) saw ``cube`` (its raw SH the cube's projection);
    probe (0, 0, 0) a dimmer copy. The chain arrays are probegrid's (``r = k / (levels - 1)``)."""
    from probegrid.core.cubemap import mip_sizes
    from probegrid.core.grid import GridSpec
    from probegrid.core.specular import ggx_prefilter
    from probe_stores import write_store

    grid = GridSpec.from_counts((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (2, 1, 1))
    cubes = np.stack([0.5 * cube, cube]).astype(np.float32)
    arrays = {"sh": np.stack([shlib.project_cube(c) for c in cubes]).astype(np.float32),
              "diffuse": np.ones((2, 6, 4, 4, 3), np.float32),
              "valid": np.ones(2, dtype=bool),
              "positions": grid.positions().astype(np.float32)}
    chains = [ggx_prefilter(c, levels=len(mip_sizes(cube.shape[1]))) for c in cubes]
    for k in range(len(chains[0])):
        arrays[f"specular_{k}"] = np.stack([ch[k] for ch in chains]).astype(np.float32)
    if incoming:
        arrays["incoming"] = cubes
    return write_store(path, grid, arrays)


def test_export_target_filament_writes_what_filter_writes_of_the_probe(exported, tmp_path):
    tmp, cube = exported
    _store_with_incoming(tmp_path / "s.probes", cube)
    assert main(["export", str(tmp_path / "s.probes"), "--target", "filament", "--probe",
                 "1,0,0", "--sh", "raw", "--out", str(tmp_path / "f")]) == 0
    ours = read_ktx1(tmp_path / "f" / filament.IBL_FILE)
    theirs = read_ktx1(tmp / "out" / filament.IBL_FILE)  # filter --format filament, same cube
    strip = {"bytesOfKeyValueData"}  # (the SH's last digits: the store keeps float32 SH)
    assert {k: v for k, v in ours[0].items() if k not in strip} == \
           {k: v for k, v in theirs[0].items() if k not in strip}
    assert set(ours[1]) == set(theirs[1]) == {"sh"}
    assert [m.shape for m in ours[2]] == [m.shape for m in theirs[2]]
    for a, b in zip(ours[2], theirs[2], strict=True):  # the chain at Filament's roughness
        np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(parse_sh(ours[1]["sh"]), parse_sh(theirs[1]["sh"]), rtol=1e-6,
                               atol=1e-7)
    # not the store's own chain (probegrid's r = k / (levels - 1)): mip 1 differs
    store_m1 = ggx_filter(cube, 0.5 ** 2, SIZE // 2)
    assert np.abs(filament.decode_r11g11b10(ours[2][1]) - store_m1).max() > 0.05 * cube.max()
    assert read_ktx1(tmp_path / "f" / filament.SKYBOX_FILE)[2][0].shape == (6, SIZE, SIZE)
    man = json.loads((tmp_path / "f" / "manifest.json").read_text())
    assert man["target"] == "filament" and man["probe"] == [1, 0, 0]
    assert man["sh"]["kind"] == "raw" and "IndirectLight" in man["consumer"]


def test_export_target_filament_refusals(tmp_path, capsys):
    cube = sky(32)
    _store_with_incoming(tmp_path / "none.probes", cube, incoming=False)
    _store_with_incoming(tmp_path / "small.probes", sky(16))
    _store_with_incoming(tmp_path / "ok.probes", cube)
    for store, extra, words in (
            ("none", ["--probe", "0,0,0"], "--store-incoming"),
            ("small", ["--probe", "0,0,0"], "--face-size 32"),
            ("ok", [], "--probe I,J,K"),
            ("ok", ["--probe", "0,0,0", "--zstd"], "KTX1"),
            ("ok", ["--probe", "5,0,0"], "outside the grid")):
        capsys.readouterr()
        assert main(["export", str(tmp_path / f"{store}.probes"), "--target", "filament",
                     "--out", str(tmp_path / "o"), *extra]) != 0
        err = capsys.readouterr().err.strip()
        assert words in err, err
        assert len(err.splitlines()) == 1 and not (tmp_path / "o").exists()
