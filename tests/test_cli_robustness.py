"""The command line on the inputs users give it: argument parsing (face files by name,
negative comma lists, ``--environment`` and the scene), outputs staged into place (filter,
export), options and the output location checked before any work, and the messages of quietly
accepted input.

Everything runs in-process through :func:`probegrid.cli.main` (no subprocess start-up), on tiny
inputs."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import numpy as np
import pytest
from probe_stores import GRID, linear_arrays, write_store

from probegrid import imageio
from probegrid.cli import build_parser, main
from probegrid.core import specular
from probegrid.filter import FilterSettings
from probegrid.jobs import export as export_job
from probegrid.jobs.filter import run_filter

FACE_COLOURS = np.eye(6, 3, dtype=np.float32) + np.arange(6, dtype=np.float32)[:, None] / 8


def _faces(tmp_path: Path, names: list[str], n: int = 4) -> list[Path]:
    """Six constant faces, face f of colour FACE_COLOURS[f], written under ``names[f]``."""
    return [imageio.write_image(tmp_path / name, np.broadcast_to(FACE_COLOURS[f], (n, n, 3)),
                                half=False)
            for f, name in enumerate(names)]


def _error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    err = [ln for ln in err if ln.startswith("probegrid: error")]
    assert len(err) == 1, err
    assert "Traceback" not in err[0] and "array(" not in err[0]
    return err[0]


# ------------------------------------------------------------------------------ 3: face names
@pytest.mark.parametrize("names", [
    ["sky_px.exr", "sky_nx.exr", "sky_py.exr", "sky_ny.exr", "sky_pz.exr", "sky_nz.exr"],
    ["posx.exr", "negx.exr", "posy.exr", "negy.exr", "posz.exr", "negz.exr"],
    ["right.exr", "left.exr", "top.exr", "bottom.exr", "front.exr", "back.exr"],
    ["s_+X.exr", "s_-X.exr", "s_+Y.exr", "s_-Y.exr", "s_+Z.exr", "s_-Z.exr"],
    ["specular_0_px.exr", "specular_0_nx.exr", "specular_0_py.exr", "specular_0_ny.exr",
     "specular_0_pz.exr", "specular_0_nz.exr"],
])
def test_six_face_files_are_ordered_by_their_names(tmp_path, names):
    paths = _faces(tmp_path, names)
    shell_sorted = sorted(paths)  # what `probegrid filter sky_*.exr` receives
    assert imageio.order_face_files(shell_sorted) == paths
    cube = imageio.read_environment(shell_sorted)
    np.testing.assert_allclose(cube.mean(axis=(1, 2)), FACE_COLOURS, rtol=1e-6)


def test_the_filter_builds_the_same_cube_from_shell_sorted_faces(tmp_path, capsys):
    names = [f"env{s}.exr" for s in imageio.FACE_SUFFIXES]
    paths = _faces(tmp_path, names, n=8)
    out = tmp_path / "o"
    assert main(["filter", *map(str, sorted(paths)), "--out", str(out), "--no-previews",
                 "--lut-size", "4", "--specular-levels", "1", "--diffuse-size", "2"]) == 0
    spec = np.stack([imageio.read_image(out / f"specular_m0{s}.exr")
                     for s in imageio.FACE_SUFFIXES])
    np.testing.assert_allclose(spec.mean(axis=(1, 2)), FACE_COLOURS, rtol=1e-3)


def test_ambiguous_face_sets_are_refused(tmp_path):
    two_px = _faces(tmp_path, ["a_px.exr", "a_px2.exr", "a_py.exr", "a_ny.exr", "a_pz.exr",
                               "a_nz.exr"])
    two_px[1] = two_px[1].rename(tmp_path / "b_px.exr")
    with pytest.raises(ValueError, match="both name cube face \\+X"):
        imageio.order_face_files(two_px)
    mixed = _faces(tmp_path, ["m_px.exr", "m_nx.exr", "m_py.exr", "m_ny.exr", "m_pz.exr",
                              "mystery.exr"])
    with pytest.raises(ValueError, match="cannot tell which cube face 'mystery.exr'"):
        imageio.order_face_files(mixed)
    unnamed = [tmp_path / f"f{i}.exr" for i in range(6)]
    assert imageio.order_face_files(unnamed) == unnamed  # no face names: the order given


def test_help_states_the_face_order(capsys):
    for command in ("filter", "bake"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "+X, -X, +Y, -Y, +Z, -Z by their names" in text, command


# ------------------------------------------------------------------------------ 4, 5: arguments
@pytest.mark.parametrize("option, value", [
    ("--bounds", "-20,0.2,-20,20,2.4,20"), ("--bounds", "-.5,0,-1e-3,1,2,3"),
    ("--spacing", "-1,2,3"), ("--bounds", "-1,-2,-3,-0.5,0,0"), ("--margin", "-0.25"),
])
def test_negative_comma_lists_are_option_values(option, value):
    args = build_parser().parse_args(["bake", "scene.glb", "--out", "x.probes", option, value])
    assert getattr(args, option[2:].replace("-", "_")) == (
        float(value) if option == "--margin" else value)


def test_negative_probe_and_real_options_still_parse():
    args = build_parser().parse_args(["export", "s.probes", "--probe", "-1,0,0", "--out", "o"])
    assert args.probe == "-1,0,0"
    with pytest.raises(SystemExit):  # an unknown option is still an error
        build_parser().parse_args(["bake", "scene.glb", "--out", "x.probes", "--nope", "1"])


def test_environment_does_not_swallow_the_scene(tmp_path):
    p = build_parser()
    args = p.parse_args(["bake", "--environment", "sky.hdr", "scene.glb", "--out", "x.probes"])
    assert args.scene == Path("scene.glb") and args.environment == [Path("sky.hdr")]
    faces = [f"f_{s}.exr" for s in ("px", "nx", "py", "ny", "pz", "nz")]
    args = p.parse_args(["bake", "--environment-faces", *faces, "scene.glb", "--out", "x.p"])
    assert args.scene == Path("scene.glb") and args.environment == [Path(f) for f in faces]
    with pytest.raises(SystemExit):
        p.parse_args(["bake", "scene.glb", "--out", "x.probes", "--environment", "a.hdr",
                      "--environment-faces", *faces])


def test_bake_refuses_unnamed_faces_and_bad_colours_in_words(tmp_path, capsys):
    faces = _faces(tmp_path, ["a_px.exr", "a_nx.exr", "a_py.exr", "a_ny.exr", "a_pz.exr",
                              "what.exr"])
    assert main(["bake", str(tmp_path / "none.glb"), "--out", str(tmp_path / "x.probes"),
                 "--environment-faces", *map(str, faces)]) == 2
    assert "cannot tell which cube face 'what.exr'" in _error(capsys)
    with pytest.raises(SystemExit) as exc:
        main(["bake", "s.glb", "--out", "x.probes", "--environment-color", "-1,0,0"])
    assert exc.value.code == 2
    assert "finite numbers >= 0, got '-1,0,0'" in _error(capsys)


# ------------------------------------------------------------------------------ 2, 7: outputs
def _no_leftovers(parent: Path) -> None:
    left = [p.name for p in parent.rglob("*") if ".staging-" in p.name or ".tmp" in p.name]
    assert not left, left


def test_an_all_black_environment_gives_a_valid_black_result(tmp_path, capsys):
    black = imageio.write_image(tmp_path / "black.hdr", np.zeros((64, 128, 3), np.float32))
    out = tmp_path / "o"
    assert main(["filter", str(black), "--out", str(out), "--size", "8", "--diffuse-size", "4",
                 "--lut-size", "4"]) == 0
    m = json.loads((out / "manifest.json").read_text())  # strict JSON: no NaN in it
    q = m["quality"]
    assert q["energy"] == {"diffuse": 1.0, "specular": [1.0] * 4}
    assert q["sh_min_irradiance_over_pi"] == [0.0, 0.0, 0.0]
    for f in m["files"]:
        if f["kind"] in ("diffuse", "specular"):
            for p in f["path"]:
                assert not imageio.read_image(out / p).any()
    _no_leftovers(tmp_path)


def test_a_failed_filter_leaves_the_earlier_output_whole_and_no_staging(tmp_path, monkeypatch):
    out = tmp_path / "o"
    sky = imageio.write_image(tmp_path / "sky.hdr", np.ones((16, 32, 3), np.float32))
    base = ["filter", str(sky), "--out", str(out), "--size", "4", "--lut-size", "4"]
    assert main(base) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(imageio, "write_preview_png", interrupt)
    assert main([*base, "--diffuse-size", "2"]) == 130
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    _no_leftovers(tmp_path)
    fresh = tmp_path / "a" / "b" / "new"  # a failed first run leaves no directory at all
    assert main(["filter", str(sky), "--out", str(fresh), "--size", "4", "--lut-size", "4"]) == 130
    assert not (tmp_path / "a").exists()
    _no_leftovers(tmp_path)


def test_a_second_run_replaces_the_output_and_keeps_other_files(tmp_path):
    sky = imageio.write_image(tmp_path / "sky.hdr", np.ones((16, 32, 3), np.float32))
    out = tmp_path / "o"
    run_filter([sky], out, FilterSettings(size=4, lut_size=4, previews=False))
    (out / "notes.txt").write_text("mine")
    r = run_filter([sky], out, FilterSettings(size=4, lut_size=4, previews=False,
                                              diffuse_size=2))
    assert r.manifest["settings"]["diffuse_size"] == 2
    assert json.loads((out / "manifest.json").read_text())["settings"]["diffuse_size"] == 2
    assert imageio.read_image(out / "diffuse_px.exr").shape == (2, 2, 3)
    assert (out / "notes.txt").read_text() == "mine"
    _no_leftovers(tmp_path)


@pytest.mark.parametrize("extra, words", [
    (["--seam", "border", "--output-layout", "hcross"], "only --output-layout faces"),
    (["--samples", "16"], "--specular-method fis"),
    (["--diffuse-method", "sh", "--sh-window", "gauss"], "needs --sh-window-width"),
])
def test_option_combinations_are_refused_before_any_work(tmp_path, monkeypatch, capsys, extra,
                                                         words):
    def no_work(*a, **k):
        raise AssertionError("work started")

    monkeypatch.setattr(imageio, "read_image", no_work)
    monkeypatch.setattr(specular, "ggx_prefilter", no_work)
    assert main(["filter", str(tmp_path / "sky.hdr"), "--out", str(tmp_path / "o"),
                 *extra]) == 2
    assert words in _error(capsys)
    assert not (tmp_path / "o").exists()


def test_an_unwritable_output_location_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(specular, "ggx_prefilter",
                        lambda *a, **k: pytest.fail("work started"))
    sky = imageio.write_image(tmp_path / "sky.hdr", np.ones((16, 32, 3), np.float32))
    assert main(["filter", str(sky), "--out", "/proc/forbidden", "--size", "4"]) == 2
    line = _error(capsys)
    assert "/proc/forbidden" in line and "[Errno" not in line
    afile = tmp_path / "file"
    afile.write_text("x")
    assert main(["filter", str(sky), "--out", str(afile / "sub"), "--size", "4"]) == 2
    assert "cannot create the output directory" in _error(capsys)


# ------------------------------------------------------------------------------ 8: messages
def test_negative_pixels_are_counted_and_set_to_zero_by_default(tmp_path, capsys):
    img = np.ones((16, 32, 3), np.float32)
    img[2, 3] = -5.0
    neg = imageio.write_image(tmp_path / "neg.exr", img, half=False)
    common = ["--size", "4", "--lut-size", "4", "--no-previews"]
    assert main(["filter", str(neg), "--out", str(tmp_path / "a"), *common]) == 0
    assert "3 negative values set to 0" in capsys.readouterr().err
    m = json.loads((tmp_path / "a" / "manifest.json").read_text())
    assert m["input"]["negative_values"] == {"count": 3, "action": "set to 0"}
    assert m["input"]["source_size"] == [32, 16] and m["input"]["layout"] == "equirect"
    assert imageio.read_image(tmp_path / "a" / "specular_m0_px.exr").min() >= 0
    assert main(["filter", str(neg), "--out", str(tmp_path / "b"), *common,
                 "--keep-negative"]) == 0
    assert "3 negative values kept" in capsys.readouterr().err


@pytest.fixture()
def small_store(tmp_path) -> Path:
    arrays = linear_arrays(GRID)
    arrays["valid"][1] = False  # probe (0, 0, 1)
    write_store(tmp_path / "s.probes", GRID, arrays)
    return tmp_path / "s.probes"


def test_export_names_files_like_filter_and_says_when_a_probe_is_invalid(small_store, capsys):
    out = small_store.parent / "e"
    assert main(["export", str(small_store), "--probe", "0,0,1", "--out", str(out)]) == 0
    assert "probe 0,0,1 is invalid" in capsys.readouterr().err
    names = {p.name for p in out.iterdir()}
    assert {"specular_m0_px.exr", "specular_m3_nz.exr", "diffuse_px.exr"} <= names
    assert not any(n.startswith("specular_0") for n in names)
    m = json.loads((out / "manifest.json").read_text())
    listed = {p for f in m["files"] for p in (f["path"] if isinstance(f["path"], list)
                                             else [f["path"]])}
    assert listed | {"manifest.json"} == names
    assert main(["export", str(small_store), "--probe", "0,0,0", "--out", str(out)]) == 0
    assert "invalid" not in capsys.readouterr().err
    _no_leftovers(small_store.parent)


def test_export_refuses_half_hdr_and_leaves_nothing_on_failure(small_store, capsys, monkeypatch):
    out = small_store.parent / "e"
    assert main(["export", str(small_store), "--probe", "0,0,0", "--out", str(out),
                 "--format", "hdr", "--half"]) == 2
    assert "always RGBE" in _error(capsys) and not out.exists()

    real = imageio.write_cube
    calls = []

    def fail_late(*a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise OSError(28, "No space left on device")
        return real(*a, **k)

    monkeypatch.setattr(imageio, "write_cube", fail_late)
    assert main(["export", str(small_store), "--probe", "0,0,0", "--out", str(out)]) == 2
    assert "No space left" in _error(capsys)
    assert not out.exists()
    _no_leftovers(small_store.parent)
    assert export_job.EXPORT_FORMAT


# ------------------------------------------------------------------------------ 1: SIGINT
def test_sigint_tests_do_not_depend_on_the_inherited_handler(tmp_path, real_data):
    """The interrupt test of test_scene installs Python's handler itself: run with SIGINT
    ignored (as ``&``, nohup and CI runners start the suite) it still passes, and it leaves
    the handler it found."""
    import test_scene

    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with pytest.MonkeyPatch.context() as mp:
            test_scene.test_an_interrupt_during_trimesh_loading_is_not_swallowed(
                tmp_path, mp, real_data)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


# ------------------------------------------------------------------------------ 9: progress
class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _p(done: int, total: int = 1000):
    from probegrid.bake.executors import Progress

    return Progress(batches_done=done // 10, batches_total=total // 10, probes_done=done,
                    probes_total=total, elapsed=0.0)


def test_progress_prints_plain_lines_without_a_terminal_and_no_absurd_first_rate():
    import io

    from probegrid.jobs.progress import PLAIN_INTERVAL, BakeProgress

    clock, out = _Clock(), io.StringIO()
    bar = BakeProgress(stream=out, clock=clock)
    assert not bar.terminal  # a StringIO, like a log file
    bar("bounce 1/1 (final)", _p(10), 10**6)  # the first batch: no rate yet
    assert bar.rates(_p(10), 10**6) is None
    clock.t += 2.0
    bar("bounce 1/1 (final)", _p(210), 10**6 + 4 * 10**6)
    assert bar.rates(_p(210), 5 * 10**6) == pytest.approx((100.0, 2.0))  # 200 probes, 4 Mrays
    assert out.getvalue() == ""  # quiet between lines
    clock.t += PLAIN_INTERVAL
    bar("bounce 1/1 (final)", _p(500), 10**6 + 24 * 10**6)
    line = out.getvalue().strip()
    assert line.startswith("bake: bounce 1/1 (final): 500/1000 probes (50 %)")
    assert "Mrays/s" in line and "left" in line and "578524" not in line
    bar("bounce 1/1 (final)", _p(1000), 10**6 + 48 * 10**6)
    assert "done in" in out.getvalue().strip().splitlines()[-1]


def test_a_resumed_bake_says_from_where(tmp_path):
    from probegrid.jobs.progress import resume_note
    from probegrid.store import StoreWriter
    from probegrid.store.manifest import ArraySpec

    out = tmp_path / "r.probes"
    assert resume_note(out) is None
    w = StoreWriter.create(out, arrays={"sh": ArraySpec(shape=(9, 3), dtype="<f4")}, grid=GRID,
                           conventions={"frame": "test"}, scene_hash="x", bake={"test": 1})
    w.write(np.arange(5), {"sh": np.zeros((5, 9, 3), np.float32)})
    w.close()
    note = resume_note(out)
    assert note is not None and f"5 of {GRID.n_probes} probes already done" in note


def test_a_bake_environment_with_negative_pixels_is_clamped_and_reported(tmp_path):
    img = np.ones((16, 32, 3), np.float32)
    img[0, :4, 1] = -2.0
    path = imageio.write_image(tmp_path / "neg.exr", img, half=False)
    lines: list[str] = []
    cube = imageio.read_environment(path, size=4, report=lines.append)
    assert lines == ["note: 4 negative values of neg.exr set to 0 (radiance is never negative)"]
    assert cube.min() >= 0
    kept = imageio.read_environment(path, size=4, keep_negative=True, report=lines.append)
    assert kept.sum() < cube.sum() and len(lines) == 1  # the negatives pulled the mean down


def test_bake_refuses_an_unwritable_store_location_before_loading_the_scene(tmp_path, capsys,
                                                                           monkeypatch):
    import probegrid.scene

    monkeypatch.setattr(probegrid.scene, "load_gltf", lambda *a, **k: pytest.fail("loaded"))
    assert main(["bake", str(tmp_path / "none.glb"), "--out", "/proc/forbidden.probes"]) == 2
    line = _error(capsys)
    assert "cannot create the store /proc/forbidden.probes" in line and "[Errno" not in line
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("args, words", [
    (["--grid", "3x3"], "--grid: grid must be NXxNYxNZ"),
    (["--grid", "0x2x2"], "--grid: grid counts must be >= 1"),
    (["--grid", "9999x9999x9999"], "too large"),
    (["--spacing", "0"], "--spacing: spacing must be > 0"),
    (["--spacing", "1,2"], "--spacing: spacing must be one number or three"),
    (["--bounds", "1,2,3"], "--bounds: bounds must be six numbers"),
    (["--bounds", "1,0,0,0,1,1"], "--bounds: bounds are reversed on x"),
    (["--spacing", "1e-4", "--bounds", "0,0,0,10,10,10"], "too large"),
])
def test_bad_grid_options_are_refused_before_the_scene_loads(tmp_path, capsys, monkeypatch,
                                                             args, words):
    import probegrid.bake.executors
    import probegrid.scene

    monkeypatch.setattr(probegrid.scene, "load_gltf", lambda *a, **k: pytest.fail("loaded"))
    monkeypatch.setattr(probegrid.bake.executors, "make_executor",
                        lambda *a, **k: pytest.fail("workers started"))
    scene = Path(__file__).resolve().parents[1] / "data" / "sample_room.glb"
    assert main(["bake", str(scene), "--out", str(tmp_path / "s.probes"), *args]) == 2
    assert words in _error(capsys)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("args, words", [
    (["--size", "100"], "use --size 64 or --size 128 (the nearest powers of two)"),
    (["--size", "48", "--specular-method", "fis", "--specular-levels", "6"],
     "use --specular-levels 5 or less"),
])
def test_a_filter_size_the_chain_cannot_take_is_refused_before_reading(tmp_path, monkeypatch,
                                                                       capsys, args, words):
    monkeypatch.setattr(imageio, "read_image", lambda *a, **k: pytest.fail("read"))
    sky = imageio.write_image(tmp_path / "sky.hdr", np.ones((16, 32, 3), np.float32))
    assert main(["filter", str(sky), "--out", str(tmp_path / "o"), *args]) == 2
    assert words in _error(capsys)
    assert not (tmp_path / "o").exists()


def test_a_square_ldr_image_is_not_taken_as_an_angular_hdr_unless_asked(tmp_path, capsys,
                                                                       monkeypatch):
    ldr = imageio.write_image(tmp_path / "photo.png", np.full((16, 16, 3), 0.5, np.float32))
    small = ["--size", "4", "--diffuse-size", "2", "--lut-size", "4", "--no-previews"]
    with monkeypatch.context() as m:  # refused from the header, before the pixels are read
        m.setattr(imageio, "read_image", lambda *a, **k: pytest.fail("read"))
        assert main(["filter", str(ldr), "--out", str(tmp_path / "o"), *small]) == 2
        line = _error(capsys)
        assert "photo.png" in line and "LDR" in line and "--layout angular" in line
        assert not (tmp_path / "o").exists()
        assert main(["bake", str(Path(__file__).resolve().parents[1] / "data" /
                                 "sample_room.glb"), "--environment", str(ldr), "--out",
                     str(tmp_path / "s.probes")]) == 2
        assert "--environment-layout angular" in _error(capsys)
    # said explicitly, it is filtered as an angular map; a square HDR still is by default
    assert main(["filter", str(ldr), "--layout", "angular", "--out", str(tmp_path / "a"),
                 *small]) == 0
    hdr = imageio.write_image(tmp_path / "probe.hdr", np.full((16, 16, 3), 0.5, np.float32))
    assert main(["filter", str(hdr), "--out", str(tmp_path / "h"), *small]) == 0
    for out in ("a", "h"):
        assert json.loads((tmp_path / out / "manifest.json").read_text())["input"][
            "layout"] == "angular"
    capsys.readouterr()


def test_export_of_one_probe_writes_png_previews_like_all(small_store, capsys):
    out = small_store.parent / "one"
    assert main(["export", str(small_store), "--probe", "1,1,2", "--out", str(out)]) == 0
    m = json.loads((out / "manifest.json").read_text())
    shown = {f["of"]: f["path"] for f in m["files"] if f["kind"] == "preview"}
    assert shown == {"diffuse": "preview_diffuse.png", "specular": "preview_specular.png",
                     "incoming": "preview_incoming.png"}
    assert imageio.read_image(out / "preview_diffuse.png").shape[:2] == (12, 16)
    none = small_store.parent / "none"
    assert main(["export", str(small_store), "--probe", "1,1,2", "--out", str(none),
                 "--no-previews"]) == 0
    assert not list(none.glob("preview_*"))
    capsys.readouterr()


def test_version_and_every_option_says_what_it_means(capsys):
    from probegrid import __version__

    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out.strip() == f"probegrid {__version__}"
    parser = build_parser()
    commands = next(a for a in parser._actions if a.dest == "command").choices
    for name, sub in commands.items():
        assert sub.description, name
        for action in sub._actions:
            if action.dest != "help":
                assert action.help and len(action.help) > 10, (name, action.dest)


def test_filter_warns_when_the_sh_irradiance_is_negative(tmp_path, capsys):
    small = ["--size", "8", "--diffuse-size", "2", "--lut-size", "4", "--no-previews"]
    sun = np.full((16, 32, 3), 0.01, np.float32)
    sun[4, 8] = 5000.0  # one small bright source: its 9-coefficient SH rings negative
    sky = imageio.write_image(tmp_path / "sun.exr", sun, half=False)
    assert main(["filter", str(sky), "--out", str(tmp_path / "o"), *small]) == 0
    said = capsys.readouterr().out
    low = min(json.loads((tmp_path / "o" / "manifest.json").read_text())["quality"][
        "sh_min_irradiance_over_pi"])
    assert low < 0 and "warning:" in said and f"{low:.4g}" in said
    flat = imageio.write_image(tmp_path / "flat.exr", np.ones((16, 32, 3), np.float32),
                               half=False)
    assert main(["filter", str(flat), "--out", str(tmp_path / "f"), *small]) == 0
    assert "warning" not in capsys.readouterr().out


def test_the_demo_uses_the_repository_samples_and_stops_the_fork_server_before_serving(
        tmp_path, monkeypatch, capsys):
    import multiprocessing
    from multiprocessing import forkserver

    import probegrid.cli as cli
    from probegrid.jobs import demo

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    assert demo.sample_data_dir() == Path(__file__).resolve().parents[1] / "data"
    assert not (tmp_path / "cache").exists()  # nothing regenerated

    def fake_demo(out, **_):  # a bake's local executor leaves a fork server running
        ctx = multiprocessing.get_context("forkserver")
        p = ctx.Process(target=int)
        p.start()
        p.join()
        return "made"

    seen = []

    def fake_serve(*_):
        pid = forkserver._forkserver._forkserver_pid
        seen.append(pid)

    monkeypatch.setattr(demo, "run_demo", fake_demo)
    monkeypatch.setattr(cli, "_serve", fake_serve)
    assert main(["demo", "--out", str(tmp_path / "d")]) == 0
    assert seen == [None]  # no fork server while serving
    capsys.readouterr()


def test_os_errors_are_one_line_in_words():
    from probegrid.cli import _error_line

    assert _error_line(FileNotFoundError(2, "No such file or directory", "/a/b")) == (
        "/a/b: No such file or directory")
