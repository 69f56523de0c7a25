"""The command line: ``probegrid filter`` outputs and manifest, bad input, interrupted runs,
``bake`` / ``info`` / ``export`` (probegrid.cli, probegrid.jobs.filter, probegrid.jobs.export)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from probegrid import imageio
from probegrid.cli import main
from probegrid.core.cubemap import texel_solid_angles

REPO = Path(__file__).resolve().parents[1]
SKY = REPO / "data" / "sample_sky.hdr"


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "probegrid.cli", *map(str, args)],
                          check=False, capture_output=True, text=True, timeout=600)


@pytest.fixture()
def cli(capfd):
    """``probegrid`` in this process, its output captured at the file descriptors (so a C
    library's message would show as it does in a terminal): ``cli(*args)`` returns what
    :func:`run_cli` returns, without a new interpreter's start-up."""

    def run(*args: str) -> subprocess.CompletedProcess:
        capfd.readouterr()
        try:
            code = main([str(a) for a in args])
        except SystemExit as exc:  # argparse's errors
            code = exc.code
        out, err = capfd.readouterr()
        return subprocess.CompletedProcess(args, code, out, err)

    return run


@pytest.fixture(scope="module")
def filtered(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("filter")
    r = run_cli("filter", SKY, "--out", out, "--size", "32", "--diffuse-size", "8",
                "--seam", "average")
    assert r.returncode == 0, r.stderr
    assert "manifest.json" in r.stdout
    return out


def test_filter_writes_every_file_in_the_manifest(filtered):
    m = json.loads((filtered / "manifest.json").read_text())
    kinds = {f["kind"] for f in m["files"]}
    assert kinds == {"diffuse", "specular", "sh", "lut", "preview"}
    for f in m["files"]:
        for p in f["path"] if isinstance(f["path"], list) else [f["path"]]:
            assert (filtered / p).is_file(), p
    spec = sorted((f for f in m["files"] if f["kind"] == "specular"), key=lambda f: f["level"])
    assert [f["level"] for f in spec] == list(range(6))  # 32 -> 1
    assert [f["roughness"] for f in spec] == pytest.approx([k / 5 for k in range(6)])
    assert [f["face_size"] for f in spec] == [32, 16, 8, 4, 2, 1]
    conv = m["conventions"]
    assert conv["cube_face_order"] == ["+X", "-X", "+Y", "-Y", "+Z", "-Z"]
    assert "irradiance / pi" in conv["diffuse_map"]
    sh = json.loads((filtered / "sh.json").read_text())
    assert np.array(sh["coefficients"]).shape == (9, 3)
    assert all(abs(e - 1) < 0.03 for e in m["quality"]["energy"]["specular"])
    assert abs(m["quality"]["energy"]["diffuse"] - 1) < 1e-3
    assert m["quality"]["seam_score"]["diffuse"] < 1e-6  # average mode


def test_filter_outputs_read_back_and_carry_conventions(filtered):
    faces = np.stack([imageio.read_image(filtered / f"diffuse{s}.exr")
                      for s in imageio.FACE_SUFFIXES])
    assert faces.shape == (6, 8, 8, 3)
    meta = imageio.read_metadata(filtered / "diffuse_px.exr")
    assert json.loads(meta["probegrid:conventions"])["cube_face_order"][0] == "+X"
    # L00 of sh.json = integral of the input; the diffuse map's mean = the input's mean
    sh = np.array(json.loads((filtered / "sh.json").read_text())["coefficients"])
    w = texel_solid_angles(8)[..., None]
    mean_diffuse = (faces * w).sum((0, 1, 2)) / (4 * np.pi)
    # mean radiance = L00 * Y00 (the projection of a constant); diffuse conserves it
    np.testing.assert_allclose(mean_diffuse, sh[0] / (2 * np.sqrt(np.pi)), rtol=2e-3)
    lut = imageio.read_image(filtered / "dfg_lut.exr")
    assert lut.shape == (128, 128, 3) and 0 <= lut.min() and lut[..., :2].sum(-1).max() <= 1.0001


@pytest.mark.parametrize("layout", ["hcross", "equirect"])
def test_filter_output_layouts_and_hdr(tmp_path, layout):
    r = run_cli("filter", SKY, "--out", tmp_path, "--size", "16", "--diffuse-size", "4",
                "--output-layout", layout, "--format", "hdr", "--no-previews")
    assert r.returncode == 0, r.stderr
    img = imageio.read_image(tmp_path / "diffuse.hdr")
    assert img.shape == ((12, 16, 3) if layout == "hcross" else (8, 16, 3))


def test_filter_six_face_files_round_trip(tmp_path, filtered):
    faces = [filtered / f"specular_m0{s}.exr" for s in imageio.FACE_SUFFIXES]
    r = run_cli("filter", *faces, "--out", tmp_path, "--diffuse-size", "8", "--no-previews")
    assert r.returncode == 0, r.stderr
    m = json.loads((tmp_path / "manifest.json").read_text())
    assert m["input"]["layout"] == "faces" and m["input"]["cube_size"] == 32


def _one_error_line(r: subprocess.CompletedProcess) -> str:
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    lines = [ln for ln in lines if not ln.startswith("libpng")]
    assert len(lines) == 1 and lines[0].startswith("probegrid: error:"), r.stderr
    assert "Traceback" not in r.stderr
    return lines[0]


def test_bad_input_gives_one_line_errors(tmp_path, cli):
    assert "no such file" in _one_error_line(cli("filter", tmp_path / "x.hdr", "--out",
                                                     tmp_path / "o"))
    trunc = tmp_path / "t.hdr"
    trunc.write_bytes(SKY.read_bytes()[:2000])
    assert "truncated" in _one_error_line(cli("filter", trunc, "--out", tmp_path / "o"))
    _one_error_line(cli("filter", SKY, "--out", tmp_path / "o", "--layout", "nope"))
    _one_error_line(cli("filter", SKY, "--out", tmp_path / "o", "--size", "-3"))
    odd = tmp_path / "odd.exr"
    imageio.write_image(odd, np.ones((10, 17, 3), np.float32))
    assert "layout" in _one_error_line(cli("filter", odd, "--out", tmp_path / "o"))
    assert not (tmp_path / "o" / "manifest.json").exists()


def test_filter_settings_check_every_field(tmp_path, cli):
    from probegrid.errors import SettingsError
    from probegrid.filter import FilterSettings

    s = FilterSettings(size=np.int64(64), clamp=2, half=np.bool_(False))
    assert (s.size, s.clamp, s.half) == (64, 2.0, False)
    assert type(s.size) is int and type(s.clamp) is float and type(s.half) is bool
    assert s.as_dict()["size"] == 64 and len(s.as_dict()) == 22
    for bad, reason in (({"size": 0}, "must be >= 1, got 0"),
                        ({"lut_size": 2000}, "must be <= 1024, got 2000"),
                        ({"clamp": 0}, "must be > 0, got 0.0"),
                        ({"diffuse_size": 4.5}, "expected an integer, got 4.5"),
                        ({"diffuse_size": True}, "expected an integer, got True"),
                        ({"previews": "yes"}, "expected true or false, got 'yes'"),
                        ({"format": "png"}, "expected one of 'exr', 'hdr', 'ktx2', 'gltf'")):
        with pytest.raises(SettingsError) as err:
            FilterSettings(**bad)
        assert err.value.option == next(iter(bad)) and reason in err.value.reason
        assert isinstance(err.value, ValueError)
    with pytest.raises(TypeError):
        FilterSettings(sise=4)  # a misspelt option is no silent default
    line = _one_error_line(cli("filter", SKY, "--out", tmp_path / "o", "--lut-size", "1"))
    assert line == "probegrid: error: --lut-size: must be >= 2, got 1"
    assert not (tmp_path / "o").exists()


def test_the_filter_command_loads_only_what_it_needs(tmp_path):
    # no pydantic (its import and a model take ~0.09 s of the command's start-up), no store
    # models; OpenBLAS started with one thread (its thread pool costs 50 ms at start-up) and
    # the variable gone again once numpy is in
    code = f"""
import json, os, sys
from probegrid.cli import main
code = main(["filter", {str(SKY)!r}, "--out", {str(tmp_path / "o")!r}, "--size", "8",
             "--diffuse-size", "4", "--lut-size", "4", "--no-previews"])
from threadpoolctl import threadpool_info
print(json.dumps({{"code": code, "modules": sorted(sys.modules),
                   "blas": [p["num_threads"] for p in threadpool_info()
                            if p["user_api"] == "blas"],
                   "env": "OPENBLAS_NUM_THREADS" in os.environ}}))
"""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    r = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True,
                       env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["code"] == 0 and (tmp_path / "o" / "manifest.json").is_file()
    assert not [m for m in got["modules"] if m.split(".")[0] in ("pydantic", "pydantic_core")]
    assert "probegrid.store.manifest" not in got["modules"]
    assert "probegrid.store.names" in got["modules"]
    assert got["blas"] and set(got["blas"]) == {1} and not got["env"]


def test_nonfinite_pixels_are_counted_or_clamped(tmp_path, cli):
    img = np.ones((16, 32, 3), np.float32)
    img[3, 4, 0] = np.nan
    img[5, 6] = np.inf
    bad = tmp_path / "bad.exr"
    imageio.write_image(bad, img, half=False)
    line = _one_error_line(cli("filter", bad, "--out", tmp_path / "o"))
    assert "2 pixels" in line and "--clamp" in line
    r = cli("filter", bad, "--out", tmp_path / "o", "--clamp", "10", "--size", "8",
                "--no-previews")
    assert r.returncode == 0, r.stderr
    m = json.loads((tmp_path / "o" / "manifest.json").read_text())
    assert m["input"]["nonfinite_values_replaced"] == 4


def test_interrupted_filter_leaves_no_manifest(tmp_path, monkeypatch):
    out = tmp_path / "o"
    assert main(["filter", str(SKY), "--out", str(out), "--size", "8", "--no-previews"]) == 0
    assert (out / "manifest.json").exists()

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    before = {p.name: p.read_bytes() for p in out.iterdir()}
    monkeypatch.setattr(imageio, "write_preview_png", interrupt)
    assert main(["filter", str(SKY), "--out", str(out), "--size", "8"]) == 130
    # the run wrote into a staging folder, removed on the interrupt: the earlier output is
    # left whole (its manifest still describes every file) and nothing temporary remains
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert not list(out.glob(".*tmp*")) and not list(tmp_path.glob(".*staging*"))


@pytest.fixture(scope="module")
def cli_bake(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """The sample room baked once by the CLI (3x2x3 probes, faces 8, one bounce): the store and
    the run."""
    store = tmp_path_factory.mktemp("cli_bake") / "room.probes"
    r = run_cli("bake", REPO / "data" / "sample_room.glb", "--out", store, "--grid", "3x2x3",
                "--face-size", "8", "--diffuse-size", "4", "--bounces", "1",
                "--environment", SKY, "--store-incoming", "--workers", "1")
    return store, r


@pytest.mark.slow
def test_bake_info_export_on_the_sample_room(tmp_path, cli_bake):
    store, r = cli_bake
    assert r.returncode == 0, r.stderr
    assert "baked 18 probes" in r.stdout
    kept = json.loads((store / "manifest.json").read_text())["scene_file"]  # for the viewer
    assert kept["file"] == "scene.glb" and kept["source"] == "sample_room.glb"
    assert (store / "scene.glb").read_bytes() == (REPO / "data" / "sample_room.glb").read_bytes()
    info = run_cli("info", store)
    assert info.returncode == 0 and "3x2x3 = 18 probes" in info.stdout
    _check_inputs_as_given(store, info.stdout)
    assert "scene copy: scene.glb" in info.stdout and "from sample_room.glb" in info.stdout
    assert "irradiance / pi" in info.stdout and "specular_3" in info.stdout
    assert "specular filter: exact sum over every incoming texel" in info.stdout
    again = run_cli("bake", REPO / "data" / "sample_room.glb", "--out", store)
    assert "exists" in _one_error_line(again)
    exp = tmp_path / "probe"
    r = run_cli("export", store, "--probe", "1,1,1", "--out", exp, "--layout", "hcross")
    assert r.returncode == 0, r.stderr
    m = json.loads((exp / "manifest.json").read_text())
    assert m["probe"]["ijk"] == [1, 1, 1] and m["probe"]["index"] == 1 * 6 + 1 * 3 + 1
    assert {f["kind"] for f in m["files"]} == {"diffuse", "specular", "incoming", "sh",
                                                "preview"}
    # one probe's export carries PNG previews too, as --probe all does
    assert {f["of"] for f in m["files"] if f["kind"] == "preview"} == {
        "diffuse", "specular", "incoming"}
    n = next(f["face_size"] for f in m["files"] if f["kind"] == "diffuse")
    assert imageio.read_image(exp / "preview_diffuse.png").shape[:2] == (3 * n, 4 * n)
    cross = imageio.read_image(exp / "diffuse.exr")
    assert cross.shape == (12, 16, 3)
    assert "outside the grid" in _one_error_line(run_cli("export", store, "--probe", "3,0,0",
                                                         "--out", exp))


def _glb_mesh_count(path: Path) -> int:
    """The meshes of a .glb's JSON chunk, read here with struct (not probegrid's parser)."""
    import struct

    data = path.read_bytes()
    length, kind = struct.unpack_from("<II", data, 12)
    assert data[:4] == b"glTF" and kind == 0x4E4F534A
    return len(json.loads(data[20:20 + length])["meshes"])


def _check_inputs_as_given(store: Path, info: str) -> None:
    """The manifest and ``info`` record the scene and environment as given:
    names without directories, sizes, the detected layout, the counts, each one's hash."""
    import hashlib

    from probegrid.scene import load_gltf

    room = REPO / "data" / "sample_room.glb"
    m = json.loads((store / "manifest.json").read_text())
    scene, env = m["inputs"]["scene"], m["inputs"]["environment"]
    loaded = load_gltf(room)
    assert scene["name"] == "sample_room.glb" and scene["bytes"] == room.stat().st_size
    assert scene["triangles"] == loaded.n_triangles and scene["materials"] == len(loaded.materials)
    assert scene["meshes"] == _glb_mesh_count(room)
    assert scene["punctual_lights"] == len(loaded.lights) == 1
    assert scene["emissive_materials"] == 1  # the room's lamp panel
    h, w = imageio.read_image(SKY).shape[:2]
    assert env["layout"] == "equirect" and env["files"] == ["sample_sky.hdr"]
    assert env["pixel_size"] == [w, h] and env["bytes"] == SKY.stat().st_size
    assert env["color"] is None and env["intensity"] == 1.0
    # the store's scene hash is made of the two hashes recorded beside it
    both = hashlib.sha256((scene["content_hash"] + env["content_hash"]).encode()).hexdigest()
    assert m["scene_hash"] == both
    assert (f"scene as given: sample_room.glb ({room.stat().st_size:,} bytes): "
            f"{loaded.n_triangles} triangles, {scene['meshes']} meshes, "
            f"{len(loaded.materials)} materials, 1 emissive material, 1 punctual light; "
            f"hash {scene['content_hash']}") in info
    assert (f"environment as given: sample_sky.hdr (equirect {w}x{h}, "
            f"{SKY.stat().st_size:,} bytes); hash {env['content_hash']}") in info
    assert str(REPO) not in json.dumps(m["inputs"]) and str(REPO) not in info
    # the service's /v1/grids/{grid} shows the same record
    import asyncio

    import httpx

    from service.main import create_app

    async def get() -> dict:
        transport = httpx.ASGITransport(app=create_app([store]))
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            return (await c.get("/v1/grids/room")).json()

    doc = asyncio.run(get())
    assert doc["manifest"]["inputs"] == m["inputs"]


@pytest.mark.slow
def test_serve_refuses_bad_stores_and_settings_before_announcing(tmp_path, cli_bake):
    import socket

    with socket.socket() as free:  # a port nothing listens on (not 8000, which may be busy)
        free.bind(("127.0.0.1", 0))
        port = str(free.getsockname()[1])
    r = run_cli("serve", tmp_path / "nope.probes", "--port", port)
    assert "not a probe store" in _one_error_line(r) and "serving" not in r.stdout
    env = {**os.environ, "PROBEGRID_MAX_BATCH": "abc"}
    r = subprocess.run([sys.executable, "-m", "probegrid.cli", "serve", tmp_path / "x.probes",
                        "--port", port],
                       check=False, capture_output=True, text=True, timeout=600, env=env)
    assert "PROBEGRID_MAX_BATCH" in _one_error_line(r) and "serving" not in r.stdout

    store, r = cli_bake  # a valid store
    assert r.returncode == 0, r.stderr
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        r = run_cli("serve", store, "--port", str(busy.getsockname()[1]))
    assert "cannot listen on 127.0.0.1" in _one_error_line(r) and "serving" not in r.stdout


def test_bad_scenes_give_one_line_errors(tmp_path, cli):
    glb = tmp_path / "t.glb"
    glb.write_bytes((REPO / "data" / "sample_room.glb").read_bytes()[:500])
    _one_error_line(cli("bake", glb, "--out", tmp_path / "t.probes"))
    _one_error_line(cli("bake", tmp_path / "none.glb", "--out", tmp_path / "t.probes"))
    _one_error_line(cli("bake", REPO / "data" / "sample_room.glb", "--out",
                            tmp_path / "t.probes", "--grid", "0x1x1"))


@pytest.mark.slow  # Dask tries to connect for 10 s before it gives up
def test_an_unreachable_scheduler_is_a_one_line_error(tmp_path):
    _one_error_line(run_cli("bake", REPO / "data" / "sample_room.glb", "--out",
                            tmp_path / "t.probes", "--scheduler", "tcp://127.0.0.1:9"))


def test_sh_diffuse_with_auto_window_reports_and_removes_negative_irradiance(tmp_path,
                                                                             real_data):
    studio = real_data / "hdr" / "studio_small_03_1k.hdr"
    r = run_cli("filter", studio, "--out", tmp_path, "--size", "32", "--diffuse-size", "8",
                "--diffuse-method", "sh", "--sh-window", "auto", "--no-previews")
    assert r.returncode == 0, r.stderr
    q = json.loads((tmp_path / "manifest.json").read_text())["quality"]
    assert min(q["sh_min_irradiance_over_pi"]) < 0  # band-2 ringing of the raw projection
    after = q["diffuse_sh_window"]
    assert after["window"] == "hanning" and after["width"] > 2
    assert min(after["min_irradiance_over_pi_after_window"]) >= 0
    faces = np.stack([imageio.read_image(tmp_path / f"diffuse{s}.exr")
                      for s in imageio.FACE_SUFFIXES])
    assert faces.min() >= -1e-3  # half-float rounding of values near 0


def test_default_cube_size_follows_the_input_with_a_cap():
    from probegrid.filter import DEFAULT_MAX_SIZE, default_cube_size

    assert default_cube_size(512, 1024, "equirect") == 256
    assert default_cube_size(750, 1500, "equirect") == 256 == DEFAULT_MAX_SIZE
    assert default_cube_size(4096, 8192, "equirect") == 256
    assert default_cube_size(256, 512, "equirect") == 128
    assert default_cube_size(300, 400, "hcross") == 64
    assert default_cube_size(100, 100, "faces") == 64
    assert default_cube_size(1000, 1000, "angular") == 256
    assert default_cube_size(2, 4, "equirect") == 1


def test_filter_says_which_cube_size_it_chose(tmp_path):
    r = run_cli("filter", SKY, "--out", tmp_path, "--diffuse-size", "4", "--no-previews")
    assert r.returncode == 0, r.stderr
    m = json.loads((tmp_path / "manifest.json").read_text())
    n = m["input"]["cube_size"]
    assert f"to a {n}^2 cube (default:" in r.stderr
