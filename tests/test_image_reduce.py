"""Large environments in bounded memory: read reduced, a band of rows at a time, to what the
cube needs; the pixel limit names its option (probegrid.imageio, probegrid.jobs.filter)."""

from __future__ import annotations

import numpy as np
import pytest

from probegrid import imageio as io
from probegrid.cli import EXIT_BAD_INPUT, main
from probegrid.core import sh
from probegrid.core.cubemap import solid_angle_integral
from probegrid.core.layouts import to_cube
from probegrid.core.reduce import area_average, area_edges


def _sky(h: int, w: int) -> np.ndarray:
    """A smooth sky with a bright small sun and some noise, linear float32."""
    rng = np.random.default_rng(h)
    t = (np.arange(h) + 0.5) / h
    img = np.empty((h, w, 3), np.float32)
    img[...] = (np.array([0.3, 0.5, 1.0]) * (1.2 - t[:, None]))[:, None, :]
    img *= 1 + 0.2 * rng.random((h, w, 1)).astype(np.float32)
    img[h // 4: h // 4 + 3, w // 3: w // 3 + 5] = 500.0
    return img


def test_the_reduced_environment_shape_is_twice_what_the_cube_needs():
    assert io.reduced_environment_shape(4096, 8192, "equirect", 256) == (1024, 2048)
    assert io.reduced_environment_shape(8192, 16384, "equirect", 256) == (1024, 2048)
    assert io.reduced_environment_shape(1024, 2048, "equirect", 256) is None  # not larger
    assert io.reduced_environment_shape(1000, 2048, "equirect", 64) is None  # not 2:1
    assert io.reduced_environment_shape(3072, 4096, "hcross", 128) == (768, 1024)
    assert io.reduced_environment_shape(4096, 4096, "angular", 128) == (805, 805)
    assert io.reduced_environment_shape(1024, 1024, "faces", 64) == (128, 128)


def test_a_reduced_read_is_the_area_average_of_the_whole_read(tmp_path, monkeypatch):
    """Read at 1/8 (and at a non-integer ratio), band by band: the area average of the image
    read whole, and its mean kept; a cube from the reduced read carries the same light."""
    img = _sky(256, 512)
    f = tmp_path / "sky.exr"
    io.write_image(f, img, half=False)
    whole = io.read_image(f)
    for shape in ((32, 64), (50, 100)):
        red = io.read_image(f, shape=shape)
        assert red.shape == (*shape, 3)
        ref = area_average(area_average(whole, 0, area_edges(256, shape[0])), 1,
                           area_edges(512, shape[1]))
        np.testing.assert_allclose(red, ref, rtol=1e-5)
        np.testing.assert_allclose(red.astype(np.float64).mean(axis=(0, 1)),
                                   whole.astype(np.float64).mean(axis=(0, 1)), rtol=1e-6)
    # the bands really are bands: bands of 2^11 pixels (4 rows) give the same output
    default = io.read_image(f, shape=(50, 100))
    monkeypatch.setattr(io, "BAND_PIXELS", 1 << 11)
    np.testing.assert_allclose(io.read_image(f, shape=(50, 100)), default, rtol=1e-6)
    # the environment reader reduces a 512 x 256 equirect for a 16^2 cube to 128 x 64: the
    # cube's light (its solid-angle integral) is that of the cube from the whole image
    cube = io.read_environment(f, size=16)
    full = to_cube(whole, "equirect", 16)
    # (rows weighted by their solid angle: averaged unweighted, the sun's light spread over
    # 4 rows toward the equator would grow by 0.2 %)
    np.testing.assert_allclose(solid_angle_integral(cube).sum(0),
                               solid_angle_integral(full).sum(0), rtol=5e-4)
    # and the same low-frequency light (band-2 SH, what the diffuse map keeps) to 0.2 %, within the
    # resampler's own change from a 16^2 to a 32^2 cube
    a, b = sh.project_cube(cube), sh.project_cube(full)
    assert np.abs(a - b).max() < 2e-3 * np.abs(b).max()
    assert np.abs(a - b).max() < np.abs(b - sh.project_cube(to_cube(whole, "equirect", 32))).max()


def test_the_filter_refuses_an_input_over_its_pixel_limit_naming_the_option(tmp_path, capsys):
    f = tmp_path / "sky.hdr"
    io.write_image(f, _sky(64, 128))
    out = tmp_path / "maps"
    assert main(["filter", str(f), "--out", str(out), "--max-pixels", "4000"]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "128x64 is 8192 pixels, over the limit of 4000" in err[0]
    assert "--max-pixels N raises it" in err[0]
    assert not out.exists()
    with pytest.raises(io.ImageError, match="--max-pixels N raises it"):
        io.read_image(f, max_pixels=100, option="--max-pixels")


def test_the_bake_refuses_an_environment_over_its_pixel_limit_and_an_option_raises_it(
        tmp_path, capsys, monkeypatch):
    from pathlib import Path

    from probegrid.bake import executors
    from probegrid.bake.executors import InlineExecutor
    from probegrid.jobs.bake import load_environment

    monkeypatch.setattr(executors, "make_executor",
                        lambda **kw: InlineExecutor(check_pickle=False))
    f = tmp_path / "sky.hdr"
    sky = _sky(64, 128)
    io.write_image(f, sky)
    room = Path(__file__).resolve().parents[1] / "data" / "sample_room.glb"
    out = tmp_path / "room.probes"
    args = ["bake", str(room), "--out", str(out), "--grid", "2x2x2", "--environment", str(f),
            "--no-progress"]
    assert main([*args, "--max-environment-pixels", "4000"]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("probegrid: error:") and "128x64 is 8192 pixels" in err[-1]
    assert "over the limit of 4000" in err[-1] and "--max-environment-pixels N raises it" in err[-1]
    assert main([*args, "--max-environment-pixels", "0"]) == EXIT_BAD_INPUT
    assert "max_environment_pixels" in capsys.readouterr().err.replace("-", "_")
    assert not out.exists()
    # the default limit refuses the image; the option raises it, and the light read is the same
    reference = load_environment([f]).faces
    monkeypatch.setattr(io, "MAX_PIXELS", 4000)
    with pytest.raises(io.ImageError, match="--max-environment-pixels N raises it"):
        load_environment([f])
    raised = load_environment([f], max_pixels=8192).faces
    np.testing.assert_array_equal(raised, reference)
    assert float(raised.mean()) > 0
