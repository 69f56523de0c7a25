"""The environment filter as a library (probegrid.filter): its physics on synthetic environments,
its independence of the thread count, that it touches no file, and that ``probegrid filter``
writes exactly its arrays."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import probegrid
from probegrid import imageio
from probegrid._machine import available_cores
from probegrid.core import dfg, sh
from probegrid.filter import FilterSettings, filter_environment
from probegrid.jobs.filter import run_filter

REPO = Path(__file__).resolve().parents[1]
SKY = REPO / "data" / "sample_sky.hdr"
RADIANCE = np.array([0.5, 1.0, 2.0], np.float32)
#: Small and quick: a 16^2 cube (the dense sums), a 4^2 diffuse map, an 8^2 table.
SMALL = FilterSettings(size=16, diffuse_size=4, lut_size=8, previews=False)


def constant_cube(n: int = 16) -> np.ndarray:
    return np.broadcast_to(RADIANCE, (6, n, n, 3)).astype(np.float32)


@pytest.mark.parametrize("settings", [
    SMALL,  # the one pass of dense sums
    FilterSettings(size=16, diffuse_size=4, lut_size=8, diffuse_method="sh"),  # separate stages
    FilterSettings(size=16, diffuse_size=4, lut_size=8, specular_method="fis", samples=16),
])
def test_a_constant_environment_gives_constant_maps(settings):
    env = filter_environment(constant_cube(), settings=settings, workers=2)
    assert env.layout == "faces" and env.cube_size == 16 and env.source_size == (16, 16)
    # the diffuse map (irradiance / pi) of a constant radiance is that radiance (the exact sum
    # to the midpoint rule's error on a 16^2 cube), and so is every level of the normalised
    # GGX chain
    assert env.diffuse.shape == (6, 4, 4, 3) and env.diffuse.dtype == np.float32
    np.testing.assert_allclose(env.diffuse, np.broadcast_to(RADIANCE, env.diffuse.shape),
                               rtol=5e-4)
    assert [lv.shape[1] for lv in env.specular] == [16, 8, 4, 2, 1] == [
        lv.shape[1] for lv in env.specular_export]
    for lv in env.specular:
        np.testing.assert_allclose(lv, np.broadcast_to(RADIANCE, lv.shape), rtol=2e-5)
    assert env.roughness == [0.0, 0.25, 0.5, 0.75, 1.0]
    # SH (core.sh's basis): L_00 = 2 sqrt(pi) L, every other coefficient 0; irradiance pi L
    assert env.sh.shape == (9, 3) and env.sh9 is env.sh
    np.testing.assert_allclose(env.sh[0], 2 * np.sqrt(np.pi) * RADIANCE, rtol=1e-5)
    np.testing.assert_allclose(env.sh[1:], 0.0, atol=1e-5)
    np.testing.assert_allclose(env.sh_min_irradiance, np.pi * RADIANCE, rtol=1e-5)
    np.testing.assert_allclose(env.energy["diffuse"], 1.0, rtol=5e-4)
    np.testing.assert_allclose(env.energy["specular"], 1.0, rtol=2e-5)
    np.testing.assert_allclose(env.seam_score["specular"], 0.0, atol=1e-5)
    assert env.nonfinite == 0 and env.negative == 0
    # the table depends on its size alone
    np.testing.assert_array_equal(env.dfg_lut, dfg.dfg_lut(8))


def test_sh_at_more_bands_and_the_consumers_band_2():
    cube = constant_cube()
    env = filter_environment(cube, settings=FilterSettings(size=16, diffuse_size=4, lut_size=8,
                                                           sh_bands=5))
    assert env.sh.shape == (25, 3) and env.sh9.shape == (9, 3)
    np.testing.assert_allclose(env.sh[0], 2 * np.sqrt(np.pi) * RADIANCE, rtol=1e-5)
    np.testing.assert_allclose(env.sh[1:16], 0.0, atol=1e-5)
    # band 4 holds a function of the cube's symmetry (the cubic harmonic), which the midpoint
    # rule on the cube's texels does not integrate to 0 exactly
    assert np.abs(env.sh[16:]).max() < 1e-2 * env.sh[0].max()
    np.testing.assert_array_equal(env.sh9, sh.project_cube(env.cube))


def test_an_image_in_any_layout_is_detected_and_checked():
    equirect = np.broadcast_to(RADIANCE, (16, 32, 3)).astype(np.float32)
    env = filter_environment(equirect, settings=SMALL)
    assert env.layout == "equirect" and env.source_size == (32, 16)
    np.testing.assert_allclose(env.cube, np.broadcast_to(RADIANCE, env.cube.shape), rtol=1e-5)
    np.testing.assert_allclose(env.diffuse, np.broadcast_to(RADIANCE, env.diffuse.shape),
                               rtol=5e-4)
    # the default size: the input's resolution rounded down to a power of two
    assert filter_environment(equirect, settings=FilterSettings(lut_size=4)).cube_size == 8

    bad = equirect.copy()
    bad[2, 3] = np.nan
    with pytest.raises(ValueError, match=r"^sky\.exr: 1 pixels have non-finite values"):
        filter_environment(bad, settings=SMALL, name="sky.exr")
    env = filter_environment(bad, settings=FilterSettings(size=16, diffuse_size=4, lut_size=8,
                                                          clamp=4.0))
    assert env.nonfinite == 3 and np.isfinite(env.cube).all()
    negative = equirect.copy()
    negative[0, 0] = -1.0
    zeroed = filter_environment(negative, settings=SMALL)
    assert zeroed.negative == 3 and zeroed.negative_action == "set to 0"
    kept = filter_environment(negative, settings=FilterSettings(
        size=16, diffuse_size=4, lut_size=8, keep_negative=True))
    assert kept.negative == 3 and kept.negative_action == "kept"
    assert kept.cube.min() < zeroed.cube.min()
    with pytest.raises(ValueError, match="needs six faces"):
        filter_environment(equirect, settings=FilterSettings(layout="faces"))
    with pytest.raises(ValueError, match="six faces need layout 'auto' or 'faces'"):
        filter_environment(constant_cube(), settings=FilterSettings(layout="equirect"))
    with pytest.raises(ValueError, match="an environment is an"):
        filter_environment(np.ones((4, 4), np.float32))
    with pytest.raises(ValueError, match="workers must be a positive integer"):
        filter_environment(constant_cube(), settings=SMALL, workers=0)
    with pytest.raises(ValueError, match="--samples applies to --specular-method fis"):
        filter_environment(constant_cube(), settings=FilterSettings(samples=8))


def test_an_all_black_environment_gives_black_maps_and_finite_figures():
    env = filter_environment(np.zeros((6, 8, 8, 3), np.float32), settings=SMALL)
    assert not env.diffuse.any() and not any(lv.any() for lv in env.specular)
    assert env.energy == {"diffuse": 1.0, "specular": [1.0] * env.levels}


def test_the_maps_do_not_depend_on_the_thread_count():
    image = imageio.read_image(SKY)
    for settings in (SMALL, FilterSettings(size=256, diffuse_size=8, lut_size=8,
                                           specular_levels=2)):
        one = filter_environment(image, settings=settings, workers=1)
        three = filter_environment(image, settings=settings, workers=3)
        for a, b in [(one.diffuse, three.diffuse), (one.cube, three.cube), (one.sh, three.sh),
                     *zip(one.specular, three.specular, strict=True)]:
            np.testing.assert_array_equal(a, b)
    assert available_cores() >= 1


def test_the_library_reads_and_writes_no_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PROBEGRID_CACHE_DIR", str(tmp_path / "cache"))  # (the DFG table's)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    env = filter_environment(constant_cube(8), settings=FilterSettings(format="ktx2", lut_size=4))
    assert env.levels == 4 and list(tmp_path.iterdir()) == []


def test_the_command_writes_the_library_arrays_bit_for_bit(tmp_path):
    settings = FilterSettings(size=16, diffuse_size=4, lut_size=8, half=False, previews=False,
                              sh_bands=4)
    run_filter(SKY, tmp_path / "out", settings, workers=1)
    # (the command reads the 512 x 256 sky reduced to twice what a 16^2 cube needs)
    w, h = imageio.image_size(SKY)
    shape = imageio.reduced_environment_shape(h, w, "equirect", 16)
    assert (w, h) == (512, 256) and shape == (64, 128)
    env = filter_environment(imageio.read_image(SKY, shape=shape, equirect=True),
                             settings=settings)
    out = tmp_path / "out"
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["input"]["source_size"] == [128, 64]
    assert manifest["input"]["file_size"] == [512, 256]

    def faces(stem: str) -> np.ndarray:
        return np.stack([imageio.read_image(out / f"{stem}{s}.exr")
                         for s in imageio.FACE_SUFFIXES])

    np.testing.assert_array_equal(faces("diffuse"), env.diffuse_export)
    assert manifest["specular"]["levels"] == env.levels == 5
    for k, lv in enumerate(env.specular_export):
        np.testing.assert_array_equal(faces(f"specular_m{k}"), lv)
    doc = json.loads((out / "sh.json").read_text())
    np.testing.assert_array_equal(np.array(doc["coefficients"]), env.sh)
    lut = imageio.read_image(out / "dfg_lut.exr")
    np.testing.assert_array_equal(lut[..., :2], env.dfg_lut)
    assert manifest["quality"]["energy"] == env.energy
    assert manifest["quality"]["seam_score"] == env.seam_score
    assert manifest["specular"]["roughness"] == env.roughness


def test_the_package_face_hands_on_the_filter():
    assert probegrid.filter_environment is filter_environment
    assert probegrid.FilterSettings is FilterSettings


@pytest.mark.parametrize("name", ["studio_small_03_1k.hdr", "venice_sunset_1k.hdr"])
def test_previews_are_tone_mapped_with_almost_no_clipped_pixel(tmp_path, real_data, name):
    """Each preview by its own exposure and white point: at most 1 % of its pixels at 255 (a
    studio's diffuse preview exposed like its input was a third white), and the manifest says
    how previews are made."""
    out = tmp_path / "o"
    run_filter(real_data / "hdr" / name, out, FilterSettings(size=64, diffuse_size=16,
                                                               lut_size=4))
    man = json.loads((out / "manifest.json").read_text())
    assert man["previews"]["tone_mapping"] == imageio.PREVIEW_TONE_MAPPING
    for what in ("input", "diffuse", "specular"):
        png = imageio.read_image(out / f"preview_{what}.png")  # (decoded from sRGB: 1 = 255)
        faces = png.max(axis=-1) > 0
        clipped = (png >= 1.0).any(axis=-1)
        assert clipped.mean() <= 0.01, (what, clipped.mean())
        assert np.median(png.max(axis=-1)[faces]) > 0.05  # and not dark either
