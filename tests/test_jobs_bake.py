"""The ``probegrid bake`` job: no silent black, the estimate before work, the refusals before
any worker starts, the manifest's inputs (probegrid.jobs.bake, probegrid.bake.nolight,
probegrid.bake.estimate)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from probegrid.bake.environment import Environment
from probegrid.bake.estimate import estimate
from probegrid.bake.executors import InlineExecutor
from probegrid.bake.nolight import NO_LIGHT, light_sources
from probegrid.bake.settings import BakeSettings
from probegrid.cli import EXIT_BAD_INPUT, main
from probegrid.core.lights import PointLight
from probegrid.jobs.bake import BakeJob, run_bake
from probegrid.scene import Material, SceneBuilder
from probegrid.store import StoreError, open_store, partial_path

FAST = ["--face-size", "8", "--diffuse-size", "4", "--bounces", "0", "--no-progress"]


@pytest.fixture
def scene_file(monkeypatch, tmp_path_factory):
    """Bake Python-built scenes through the CLI: ``use(scene)`` makes the job's glTF loader
    return ``scene`` (the file it names is a minimal glTF document, which the store keeps a copy
    of); batches run in the test's process."""
    import probegrid.scene as scenes
    from probegrid.bake import executors

    monkeypatch.setattr(executors, "make_executor",
                        lambda **kw: InlineExecutor(check_pickle=False))

    file = tmp_path_factory.mktemp("scene") / "scene.gltf"
    file.write_text('{"asset": {"version": "2.0"}}')

    def use(scene):
        monkeypatch.setattr(scenes, "load_gltf", lambda path, **kw: scene)
        return str(file)

    return use


def _one_line(capsys, *, only: bool = True) -> str:
    """The error line on stderr: its only line for a refusal before work, else its last."""
    err = capsys.readouterr().err.strip().splitlines()
    assert err and err[-1].startswith("probegrid: error:"), err
    assert len(err) == 1 or not only, err
    return err[-1]


def _dark_room(*, light=False, boxed_light=False):
    b = SceneBuilder()
    m = b.add_material(Material.diffuse(0.5))
    b.add_box((-2, 0, -2), (2, 3, 2), material=m, inward=True)
    if boxed_light:  # a light shut in a closed (single-sided, outward) box: reaches nothing
        b.add_box((-0.3, 1.2, -0.3), (0.3, 1.8, 0.3), material=m)
    if light or boxed_light:
        b.add_light(PointLight((0.0, 1.5, 0.0), (1.0, 1.0, 1.0), 10.0))
    return b.build()


def test_a_scene_without_light_is_refused_before_any_work(tmp_path, scene_file, capsys):
    out = tmp_path / "dark.probes"
    code = main(["bake", scene_file(_dark_room()), "--out", str(out), "--grid", "2x2x2", *FAST])
    assert code == EXIT_BAD_INPUT
    line = _one_line(capsys)
    assert "no light" in line and "--allow-black" in line
    assert not list(tmp_path.iterdir())  # nothing written, not even a work directory
    assert light_sources(_dark_room(), Environment()) == []
    assert light_sources(_dark_room(light=True), Environment()) == ["1 punctual light"]
    assert light_sources(_dark_room(), Environment(color=(0.1, 0.1, 0.1))) == ["the environment"]
    # asked for, a black bake is made, and its quality figures read "no light", never NaN
    assert main(["bake", scene_file(_dark_room()), "--out", str(out), "--grid", "2x2x2",
                 "--allow-black", *FAST]) == 0
    store = open_store(out)
    q = store.manifest.quality
    assert q["light"] == NO_LIGHT and q["lit_probes"] == 0
    assert q["energy_max_error"] == NO_LIGHT
    assert not any(isinstance(v, float) and math.isnan(v) for v in q.values())
    text = (out / "manifest.json").read_text()
    assert "NaN" not in text and json.loads(text)
    assert "nan" not in capsys.readouterr().out


def test_an_all_black_bake_exits_non_zero_and_leaves_nothing(tmp_path, scene_file, capsys):
    """The scene has a light, but it is shut in a box: every valid probe stays black. The
    bake stops before finishing the store, with the reason, and leaves no store, partial
    store or work files; --allow-black bakes it black."""
    scene = scene_file(_dark_room(boxed_light=True))
    out = tmp_path / "black.probes"
    args = ["bake", scene, "--out", str(out), "--grid", "2x2x2", *FAST]
    assert main(args) == EXIT_BAD_INPUT
    line = _one_line(capsys, only=False)  # after the estimate and the bake's own lines
    assert "came out black" in line and "none of the 8 valid probes" in line
    assert "--allow-black" in line
    with pytest.raises(StoreError):
        open_store(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no .partial, no .work
    assert main([*args, "--allow-black"]) == 0
    assert "resumed" not in capsys.readouterr().out
    q = open_store(out).manifest.quality
    assert q["light"] == NO_LIGHT and q["energy_max_error"] == NO_LIGHT
    # the same room with the light in the open: lit, finished, figures are numbers
    lit = tmp_path / "lit.probes"
    assert main(["bake", scene_file(_dark_room(light=True)), "--out", str(lit), "--grid",
                 "2x2x2", *FAST]) == 0
    q = open_store(lit).manifest.quality
    assert q["light"] == "lit" and q["lit_probes"] == 8 and q["energy_max_error"] < 1e-2


def _du(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def test_the_estimate_matches_the_store_and_is_printed(tmp_path, scene_file, capsys):
    scene = _dark_room(light=True)
    out = tmp_path / "e.probes"
    assert main(["bake", scene_file(scene), "--out", str(out), "--grid", "3x3x3",
                 "--face-size", "16", "--diffuse-size", "4", "--bounces", "1",
                 "--no-progress"]) == 0
    err = capsys.readouterr().err
    st = BakeSettings(face_size=16, diffuse_size=4, bounces=1)
    store = open_store(out)
    est = estimate(st, store.grid, scene)
    real = _du(out)
    assert abs(est.store_bytes - real) <= 0.05 * real, (est.store_bytes, real)
    assert "estimate: 27 probes" in err and "store " in err and "peak worker memory" in err
    assert est.primary_rays == 27 * 6 * 16 * 16  # cast once: the bounces replay the records
    # two from every hit; at --bounces 1 a second level would carry no light and is not cast
    assert st.gather_levels() == 1 and est.gather_rays == 2 * est.primary_rays
    deep = estimate(BakeSettings(face_size=16, diffuse_size=4), store.grid, scene)
    assert deep.gather_rays == 4 * deep.primary_rays  # converging: one more from each of theirs
    assert [BakeSettings(bounces=b).gather_levels() for b in (0, 1, 2, 5)] == [0, 1, 2, 2]
    assert BakeSettings(gather_samples=0).gather_levels() == 0
    # one light: a shadow ray per hit (the gather rays' hits too) at most, and one per probe
    assert est.shadow_rays == est.primary_rays + est.gather_rays + 27


def test_a_store_that_does_not_fit_on_the_disk_is_refused_with_the_figures(
        tmp_path, scene_file, capsys, monkeypatch):
    import shutil

    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage",
                        lambda p: real(p)._replace(free=100_000))  # 100 kB free
    out = tmp_path / "big.probes"
    code = main(["bake", scene_file(_dark_room(light=True)), "--out", str(out), "--grid",
                 "4x4x4", *FAST])
    assert code == EXIT_BAD_INPUT
    line = _one_line(capsys)  # (and only that line: the estimate is printed once checked)
    assert "not enough disk space" in line and "97.7 KiB free" in line and "store" in line
    assert not list(tmp_path.iterdir())


def test_the_job_refuses_a_dark_scene_from_python_too(tmp_path, monkeypatch, scene_file):
    import probegrid.scene as scenes

    monkeypatch.setattr(scenes, "load_gltf", lambda path: _dark_room())
    with pytest.raises(ValueError, match="the scene has no light"):
        run_bake(BakeJob(scene=Path(scene_file(_dark_room())), out=tmp_path / "d.probes",
                         grid="2x2x2"))


def test_the_manifest_records_six_faces_in_face_order_and_a_colour(tmp_path, scene_file,
                                                                    capsys):
    """``--environment-faces`` given in shell order is recorded in face order
    (+X, -X, +Y, -Y, +Z, -Z) with its pixel size; ``--environment-color`` as a colour;
    a format-2 store written before ``inputs`` existed still opens and prints."""
    from probegrid.imageio import write_image
    from probegrid.jobs.export import describe_store

    names = ["sky_px.exr", "sky_nx.exr", "sky_py.exr", "sky_ny.exr", "sky_pz.exr", "sky_nz.exr"]
    for f, name in enumerate(names):
        write_image(tmp_path / name, np.full((4, 4, 3), 0.1 * (f + 1), np.float32))
    shell = sorted(names)  # nx, ny, nz, px, py, pz: what `sky_*.exr` gives
    b = SceneBuilder()  # a floor under the open sky
    b.add_quad((-2, 0, 2), (4, 0, 0), (0, 0, -4), material=b.add_material(Material.diffuse(0.5)))
    scene = scene_file(b.build())
    box = ["--bounds", "-1,0.5,-1,1,1.5,1"]
    out = tmp_path / "faces.probes"
    assert main(["bake", scene, "--out", str(out), "--grid", "2x2x2", *FAST, *box,
                 "--environment-faces", *(str(tmp_path / n) for n in shell)]) == 0
    env = open_store(out).manifest.inputs.environment
    assert env.layout == "faces" and list(env.files) == names
    assert env.pixel_size == (4, 4)
    assert env.bytes == sum((tmp_path / n).stat().st_size for n in names)
    info = describe_store(out)
    assert f"environment as given: faces {', '.join(names)} (+X, -X, +Y, -Y, +Z, -Z; 4x4 each" \
        in info

    col = tmp_path / "col.probes"
    assert main(["bake", scene, "--out", str(col), "--grid", "2x2x2", *FAST, *box,
                 "--environment-color", "0.25,0.5,1", "--environment-intensity", "2"]) == 0
    m = open_store(col).manifest
    env = m.inputs.environment
    assert env.layout == "color" and env.color == (0.25, 0.5, 1.0) and env.files == ()
    assert env.intensity == 2.0 and env.pixel_size is None
    assert m.inputs.scene.name == "scene.gltf" and m.inputs.scene.meshes == 0
    assert m.inputs.scene.triangles == 2 and m.inputs.scene.punctual_lights == 0
    assert m.inputs.scene.materials == 1 and m.inputs.scene.emissive_materials == 0
    assert "environment as given: color 0.25,0.5,1, intensity 2" in describe_store(col)

    # a store of the same format without the record (written before it existed)
    doc = json.loads((col / "manifest.json").read_text())
    del doc["inputs"]
    (col / "manifest.json").write_text(json.dumps(doc))
    old = open_store(col)
    assert old.manifest.format_version == 2 and old.manifest.inputs is None
    text = describe_store(col)
    assert "scene hash:" in text and "as given" not in text
    capsys.readouterr()


@pytest.mark.parametrize("content", [None, b"glTF\x02\x00\x00\x00\xff\xff\x00\x00rest", b"{}"])
def test_a_missing_or_truncated_scene_is_refused_before_any_worker_starts(tmp_path,
                                                                         monkeypatch, capsys,
                                                                         content):
    """``probegrid bake`` starts its worker processes before it loads the scene (to overlap
    them); a scene file that is missing, truncated by its own header or not binary glTF is
    refused first, in one line, with no process started."""
    from probegrid.bake import executors

    def no_workers(**_: object) -> None:
        raise AssertionError("workers were started for a scene that cannot load")

    monkeypatch.setattr(executors, "make_executor", no_workers)
    scene = tmp_path / "s.glb"
    if content is not None:
        scene.write_bytes(content)
    code = main(["bake", str(scene), "--out", str(tmp_path / "x.probes")])
    assert code == EXIT_BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("probegrid: error: ")
    assert ("not found" in err[0] if content is None else
            "truncated" in err[0] if content.startswith(b"glTF") else "bad magic" in err[0])


def test_bake_reads_files_outside_the_scene_folder_only_under_allow_path(tmp_path, monkeypatch,
                                                                           capsys):
    from probegrid.bake import executors

    monkeypatch.setattr(executors, "make_executor",
                        lambda **kw: InlineExecutor(check_pickle=False))
    (tmp_path / "shared").mkdir()
    (tmp_path / "scene").mkdir()
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    (tmp_path / "shared" / "mesh.bin").write_bytes(pos.tobytes())
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"mesh": 0}], "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
           "buffers": [{"uri": "../shared/mesh.bin", "byteLength": pos.nbytes}],
           "bufferViews": [{"buffer": 0, "byteLength": pos.nbytes}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}]}
    scene = tmp_path / "scene" / "room.gltf"
    scene.write_text(json.dumps(doc))
    args = ["bake", str(scene), "--out", str(tmp_path / "r.probes"), "--grid", "2x2x2", *FAST]
    assert main(args) == EXIT_BAD_INPUT
    line = _one_line(capsys, only=False)
    assert "outside the scene's folder" in line and "--allow-path" in line
    assert main([*args, "--allow-path", str(tmp_path / "shared")]) != 0
    line = _one_line(capsys, only=False)  # loaded: the unlit triangle is what stops it now
    assert "no light" in line


def _interrupt_final_pass(monkeypatch) -> None:
    """The next bake is interrupted (as by Ctrl-C) in its final pass, once the earlier
    stages are done; later bakes run whole."""
    from probegrid.bake import driver

    real = driver.final_task
    calls = []

    def final_task(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(driver, "final_task", final_task)


def test_a_rerun_with_other_settings_says_it_starts_clean_and_never_resumes(tmp_path,
                                                                            scene_file, capsys,
                                                                            monkeypatch):
    """An interrupted bake re-run with another grid starts clean and says so, instead of
    "resuming" and failing; the same command again resumes."""
    from probegrid.cli import EXIT_INTERRUPTED

    scene = scene_file(_dark_room(boxed_light=True))
    out = tmp_path / "black.probes"
    args = ["bake", scene, "--out", str(out), *FAST]
    _interrupt_final_pass(monkeypatch)
    assert main([*args, "--grid", "2x2x2", "--allow-black"]) == EXIT_INTERRUPTED
    assert out.with_name("black.probes.work").is_dir()  # interrupted: kept, resumable
    capsys.readouterr()
    assert main([*args, "--grid", "3x2x2", "--allow-black"]) == 0
    got = capsys.readouterr()
    assert "resum" not in got.err and "resumed" not in got.out
    assert "had another scene, grid or other settings" in got.err and "starts clean" in got.err
    assert open_store(out).grid.n_probes == 12
    assert main([*args, "--grid", "2x2x2"]) == EXIT_BAD_INPUT  # (the store exists)
    _interrupt_final_pass(monkeypatch)
    assert main([*args, "--grid", "2x2x2", "--overwrite", "--allow-black"]) == EXIT_INTERRUPTED
    capsys.readouterr()
    assert main([*args, "--grid", "2x2x2", "--overwrite", "--allow-black"]) == 0
    got = capsys.readouterr()
    assert "resuming the interrupted bake" in got.err
    assert "starts clean" not in got.err


def test_a_required_extension_not_honoured_is_refused_then_baked_ignored_and_named(
        tmp_path, monkeypatch, capsys):
    """A glTF requiring an extension the bake does not honour is refused before any work, the
    one line naming it and ``--ignore-extension``; with the option it bakes, and the summary,
    the manifest and ``info`` name what was not honoured."""
    import base64

    from probegrid.bake import executors

    monkeypatch.setattr(executors, "make_executor",
                        lambda **kw: InlineExecutor(check_pickle=False))
    pos = np.array([[-2, 0, 2], [2, 0, 2], [2, 0, -2], [-2, 0, -2]], np.float32)
    idx = np.array([0, 1, 2, 0, 2, 3], np.uint32)
    blob = pos.tobytes() + idx.tobytes()
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1,
                                       "material": 0}]}],
           "materials": [{"extensions": {"KHR_materials_sheen": {"sheenRoughnessFactor": 1}}}],
           "extensionsUsed": ["KHR_materials_sheen"],
           "extensionsRequired": ["KHR_materials_sheen"],
           "buffers": [{"byteLength": len(blob), "uri": "data:application/octet-stream;base64,"
                        + base64.b64encode(blob).decode()}],
           "bufferViews": [{"buffer": 0, "byteLength": pos.nbytes},
                           {"buffer": 0, "byteOffset": pos.nbytes, "byteLength": idx.nbytes}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3"},
                         {"bufferView": 1, "componentType": 5125, "count": 6, "type": "SCALAR"}]}
    scene = tmp_path / "sheen.gltf"
    scene.write_text(json.dumps(doc))
    out = tmp_path / "s.probes"
    args = ["bake", str(scene), "--out", str(out), "--grid", "1x1x1", "--bounds",
            "0,1,0,0,1,0", "--environment-color", "1,1,1", *FAST]
    assert main(args) == EXIT_BAD_INPUT
    line = _one_line(capsys, only=False)
    assert "KHR_materials_sheen" in line and "--ignore-extension KHR_materials_sheen" in line
    assert not out.exists()
    assert main([*args, "--ignore-extension", "KHR_materials_sheen"]) == 0
    printed = capsys.readouterr()
    summary = [ln for ln in printed.out.splitlines() if "not honoured" in ln]
    assert summary and "KHR_materials_sheen" in summary[0]
    assert "metallic-roughness" in summary[0]
    manifest = json.loads((out / "manifest.json").read_text())
    assert any("KHR_materials_sheen" in x for x in manifest["inputs"]["scene"]["unhonoured"])
    assert main(["info", str(out)]) == 0
    assert "not honoured by the bake" in capsys.readouterr().out
