"""Output safety of ``export`` / ``filter`` / ``info`` and of the store writer
(probegrid.jobs.export, probegrid.jobs.filter.prepare_output_dir, probegrid.store.create_npy):

* an ``--out`` directory that holds a store, an unfinished bake or another kind of output is
  refused (and left untouched); an earlier output of the same kind is replaced;
* store array files have their disk blocks reserved when created, so a full disk is a clean
  ``OSError(ENOSPC)``, not ``SIGBUS``;
* tampered stores (missing arrays, non-finite data, non-contiguous specular levels, manifest
  fields of the wrong type) give one-line errors; ``info .`` works inside a store.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from probe_stores import linear_store

from probegrid import imageio
from probegrid.cli import main
from probegrid.core.grid import GridSpec
from probegrid.filter import FilterSettings
from probegrid.jobs.export import describe_store, export_probe
from probegrid.jobs.filter import run_filter
from probegrid.store import ArraySpec, StoreError, StoreWriter, open_store, partial_path

REPO = Path(__file__).resolve().parents[1]
FAST_FILTER = FilterSettings(size=4, diffuse_size=2, lut_size=4, previews=False)


@pytest.fixture
def store(tmp_path) -> Path:
    """A finished 3x2x3 store (sh, diffuse, specular_0..3 of 8^2..1^2, incoming, ...)."""
    path = tmp_path / "s.probes"
    linear_store(path).close()
    return path


@pytest.fixture
def sky(tmp_path) -> Path:
    """A tiny equirect environment (8x16, constant 0.5)."""
    path = tmp_path / "sky.exr"
    imageio.write_image(path, np.full((8, 16, 3), 0.5, np.float32), half=False)
    return path


def _edit_manifest(store: Path, edit) -> None:
    m = json.loads((store / "manifest.json").read_text())
    edit(m)
    (store / "manifest.json").write_text(json.dumps(m))


def _cli_error(capsys, *args: str) -> str:
    """Run the CLI in-process; it must fail with exit code 2 and exactly one stderr line."""
    assert main([str(a) for a in args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("probegrid: error: "), err
    return err[0]


def _snapshot(directory: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir()) if p.is_file()}


# ---------------------------------------------------------------------------- 1. output dirs
def test_export_into_a_store_is_refused_and_the_store_survives(store, tmp_path):
    before = _snapshot(store)
    r = subprocess.run([sys.executable, "-m", "probegrid.cli", "export", str(store), "--probe",
                        "0,0,0", "--out", str(store)],
                       check=False, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "probe grid store" in lines[0], r.stderr
    assert _snapshot(store) == before
    open_store(store).close()
    # the same store under a name without .probes is recognised by its manifest
    plain = tmp_path / "plain"
    shutil.copytree(store, plain)
    with pytest.raises(ValueError, match="probe grid store's manifest.json"):
        export_probe(store, "0,0,0", plain)
    with pytest.raises(ValueError, match="probe grid store's manifest.json"):
        run_filter(tmp_path / "never-read.exr", plain, FAST_FILTER)
    assert _snapshot(plain) == before


@pytest.mark.parametrize("name", ["new.probes", "x.probes.partial", "x.probes.work"])
def test_outputs_refuse_store_and_bake_directory_names(store, sky, tmp_path, name):
    out = tmp_path / name
    with pytest.raises(ValueError, match="store or bake directory"):
        export_probe(store, "0,0,0", out)
    with pytest.raises(ValueError, match="store or bake directory"):
        run_filter(sky, out, FAST_FILTER)
    assert not out.exists()


def test_outputs_refuse_an_unfinished_bake(store, sky, tmp_path):
    out = tmp_path / "bakedir"
    out.mkdir()
    (out / "_bake.json").write_text("{}")
    with pytest.raises(ValueError, match="store or bake directory"):
        export_probe(store, "0,0,0", out)
    with pytest.raises(ValueError, match="store or bake directory"):
        run_filter(sky, out, FAST_FILTER)
    assert sorted(p.name for p in out.iterdir()) == ["_bake.json"]


def test_outputs_refuse_other_kinds_of_output_and_replace_their_own(store, sky, tmp_path,
                                                                    capsys):
    exp, fil, junk = tmp_path / "exp", tmp_path / "fil", tmp_path / "junk"
    export_probe(store, "0,0,0", exp)
    run_filter(sky, fil, FAST_FILTER)
    junk.mkdir()
    (junk / "manifest.json").write_text("not json")
    snaps = {d: _snapshot(d) for d in (exp, fil, junk)}
    with pytest.raises(ValueError, match="'probegrid.filter' output's manifest.json"):
        export_probe(store, "0,0,0", fil)
    with pytest.raises(ValueError, match="'probegrid.probe-export' output's manifest.json"):
        run_filter(sky, exp, FAST_FILTER)
    with pytest.raises(ValueError, match="unreadable or unknown manifest.json"):
        export_probe(store, "0,0,0", junk)
    with pytest.raises(ValueError, match="unreadable or unknown manifest.json"):
        run_filter(sky, junk, FAST_FILTER)
    assert "refusing to overwrite" in _cli_error(capsys, "export", store, "--probe", "0,0,0",
                                                  "--out", fil)
    for d, snap in snaps.items():
        assert _snapshot(d) == snap, d
    # an earlier output of the same kind is replaced, as before
    export_probe(store, "1,1,2", exp)
    m = json.loads((exp / "manifest.json").read_text())
    assert m["format"] == "probegrid.probe-export" and m["probe"]["ijk"] == [1, 1, 2]
    run_filter(sky, fil, FilterSettings(size=4, diffuse_size=1, lut_size=4, previews=False))
    assert json.loads((fil / "manifest.json").read_text())["settings"]["diffuse_size"] == 1
    # a directory with other files but no manifest is still fine
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    export_probe(store, "0,0,0", other)
    assert (other / "notes.txt").read_text() == "mine"


@pytest.mark.slow
def test_a_rerun_removes_what_the_previous_run_wrote_and_nothing_else(store, tmp_path):
    """filter into its earlier output: the earlier chain's extra levels (and previews) go, the
    user's files stay; the same for a many-probe export and an engine export."""
    from probegrid.jobs.engine_export import export_grid
    from probegrid.jobs.export import export_probes

    sky = tmp_path / "sky.exr"
    imageio.write_image(sky, np.full((16, 32, 3), 0.5, np.float32), half=False)
    out = tmp_path / "fil"
    run_filter(sky, out, FilterSettings(size=16, diffuse_size=2, lut_size=4, previews=True))
    assert {p.name for p in out.glob("specular_m4*")}  # five levels: 16 .. 1
    (out / "notes.txt").write_text("mine")
    (out / "specular_m9.exr").write_text("not listed by the earlier manifest")
    run_filter(sky, out, FilterSettings(size=16, specular_levels=3, diffuse_size=2, lut_size=4,
                                        previews=False))
    man = json.loads((out / "manifest.json").read_text())
    listed = {q for f in man["files"] for q in ([f["path"]] if isinstance(f["path"], str)
                                                  else f["path"])}
    assert {p.name for p in out.iterdir()} == listed | {"manifest.json", "notes.txt",
                                                        "specular_m9.exr"}
    assert not list(out.glob("specular_m3*")) and not list(out.glob("preview_*"))
    # a many-probe export: the probes of the earlier, larger box go with their folders
    many = tmp_path / "many"
    export_probes(store, "all", many, previews=False)
    (many / "0_0_0" / "mine.txt").write_text("mine")
    export_probes(store, "0,0,0:0,1,1", many, previews=False)
    assert sorted(p.name for p in many.iterdir()) == ["0_0_0", "0_0_1", "0_1_0", "0_1_1",
                                                      "manifest.json"]
    assert (many / "0_0_0" / "mine.txt").read_text() == "mine"
    # an engine export: ktx2 of every probe, then of one probe, then the same again
    eng = tmp_path / "eng"
    export_grid(store, eng, target="ktx2")
    (eng / "extra.bin").write_bytes(b"x")
    m = json.loads((eng / "manifest.json").read_text())
    m["files"].append({"path": "old_level.ktx2"})  # as if an earlier version wrote it
    (eng / "manifest.json").write_text(json.dumps(m))
    (eng / "old_level.ktx2").write_bytes(b"old")
    export_grid(store, eng, target="ktx2", probe="1,0,1")
    assert sorted(p.name for p in eng.iterdir()) == ["diffuse.ktx2", "extra.bin",
                                                     "manifest.json", "sh.json",
                                                     "specular.ktx2"]


# ---------------------------------------------------------------------------- 2. full disk
GRID = GridSpec.from_counts((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))


def _create(path: Path, per_probe: tuple[int, ...] = (256, 512)) -> StoreWriter:
    return StoreWriter.create(path, arrays={"big": ArraySpec(per_probe, "<f4")}, grid=GRID,
                              conventions={"test": True}, scene_hash="h")


def test_store_arrays_have_their_blocks_reserved_at_creation(tmp_path):
    w = _create(tmp_path / "r.probes")  # 8 probes x 512 KiB = 4 MiB
    for name in ("big.npy", "_done.npy"):
        st = (w.partial_path / name).stat()
        assert st.st_blocks * 512 >= st.st_size, name  # not sparse
    w.close()


def test_full_disk_is_a_one_line_enospc_at_creation(tmp_path, monkeypatch):
    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "posix_fallocate", full)
    with pytest.raises(OSError) as info:
        _create(tmp_path / "f.probes")
    assert info.value.errno == errno.ENOSPC
    assert "big.npy" in str(info.value) and "\n" not in str(info.value)
    assert not partial_path(tmp_path / "f.probes").exists()  # space given back


@pytest.mark.parametrize("code", [errno.EOPNOTSUPP, errno.EINVAL])
def test_file_systems_without_fallocate_keep_working(tmp_path, monkeypatch, code):
    def unsupported(fd, offset, length):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(os, "posix_fallocate", unsupported)
    w = _create(tmp_path / "u.probes", (3,))
    w.write(np.arange(8), {"big": np.ones((8, 3), np.float32)})
    with w.finish() as s:
        assert float(np.asarray(s["big"]).sum()) == 24.0


FULL_TMPFS = textwrap.dedent(
    """
    import errno, sys
    import numpy as np
    from probegrid.core.grid import GridSpec
    from probegrid.store import ArraySpec, StoreWriter
    grid = GridSpec.from_counts((0, 0, 0), (1, 1, 1), (2, 2, 2))
    try:
        w = StoreWriter.create(sys.argv[1], arrays={"big": ArraySpec((256, 512), "<f4")},
                               grid=grid, conventions={"test": True}, scene_hash="h")
        w.write(np.arange(8), {"big": np.ones((8, 256, 512), np.float32)})
        w.finish()
        print("written")
    except OSError as exc:
        print("errno", exc.errno)
    """
)


def test_a_really_full_file_system_gives_enospc_not_sigbus(tmp_path):
    """4 MiB of arrays on a 1 MiB tmpfs (mounted in a user namespace; skipped without one)."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    script = (f"mount -t tmpfs -o size=1m tmpfs {mnt} && cd {REPO} && "
              f'exec "{sys.executable}" -c "$0" {mnt}/x.probes')
    try:
        r = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c",
                            script, FULL_TMPFS], check=False, capture_output=True, text=True,
                           timeout=120)
    except FileNotFoundError:
        pytest.skip("no unshare(1)")
    if "mount" in r.stderr and r.returncode != 0 and not r.stdout:
        pytest.skip(f"cannot mount a tmpfs in a user namespace: {r.stderr.strip()}")
    assert r.returncode == 0, f"rc {r.returncode} (-7 is SIGBUS): {r.stderr[-500:]}"
    assert r.stdout.split() == ["errno", str(errno.ENOSPC)]


# ---------------------------------------------------------------------------- 3. tampered
@pytest.mark.parametrize("name", ["sh", "diffuse"])
def test_export_names_a_missing_required_array(store, tmp_path, capsys, name):
    _edit_manifest(store, lambda m: m["arrays"].pop(name))
    (store / f"{name}.npy").unlink()
    with pytest.raises(StoreError, match=f"no '{name}' array"):
        export_probe(store, "0,0,0", tmp_path / "out")
    assert not (tmp_path / "out").exists()
    assert f"no '{name}' array" in _cli_error(capsys, "export", store, "--probe", "0,0,0",
                                              "--out", tmp_path / "out")


def _rehash(store: Path, name: str) -> None:
    """Record array ``name``'s file's SHA-256 as it now is in the store's manifest."""
    data = (store / f"{name}.npy").read_bytes()
    _edit_manifest(store, lambda m: m["arrays"][name].update(
        sha256=hashlib.sha256(data).hexdigest()))


@pytest.mark.parametrize("name, value", [("sh", np.nan), ("diffuse", np.inf),
                                         ("specular_2", -np.inf), ("incoming", np.nan)])
def test_export_refuses_non_finite_data_of_the_probe(store, tmp_path, capsys, name, value):
    index = open_store(store).probe_index(1, 0, 2)
    arr = np.load(store / f"{name}.npy", mmap_mode="r+")
    arr[index].flat[0] = value
    arr.flush()
    del arr
    _rehash(store, name)  # as a writer that wrote the value would have recorded it
    out = tmp_path / "out"
    with pytest.raises(StoreError, match=f"non-finite values .*1 in '{name}'"):
        export_probe(store, "1,0,2", out)
    assert not out.exists()  # nothing written
    assert "non-finite" in _cli_error(capsys, "export", store, "--probe", "1,0,2", "--out", out)
    export_probe(store, "0,0,0", out)  # the other probes are fine
    for f in json.loads((out / "manifest.json").read_text())["files"]:
        for p in f["path"] if isinstance(f["path"], list) else [f["path"]]:
            if p.endswith(".exr"):
                assert np.isfinite(imageio.read_image(out / p)).all()


def _drop_level(k: int):
    def damage(store: Path) -> None:
        _edit_manifest(store, lambda m: m["arrays"].pop(f"specular_{k}"))
    return damage


def _extra_level(store: Path) -> None:
    np.save(store / "specular_9.npy", np.zeros((18, 6, 1, 1, 3), "<f4"))
    _edit_manifest(store, lambda m: m["arrays"].update(specular_9={
        "file": "specular_9.npy", "dtype": "<f4", "shape": [18, 6, 1, 1, 3]}))


def _wrong_size(store: Path) -> None:
    np.save(store / "specular_4.npy", np.zeros((18, 6, 1, 1, 3), "<f4"))  # after 8, 4, 2, 1
    _edit_manifest(store, lambda m: m["arrays"].update(specular_4={
        "file": "specular_4.npy", "dtype": "<f4", "shape": [18, 6, 1, 1, 3]}))


@pytest.mark.parametrize("damage, pattern", [
    (_drop_level(1), r"specular levels \[0, 2, 3\] are not 0..2"),
    (_drop_level(0), r"specular levels \[1, 2, 3\] are not 0..2"),
    (_extra_level, r"specular levels \[0, 1, 2, 3, 9\] are not 0..4"),
    (_wrong_size, r"'specular_4' has per-probe shape \(6, 1, 1, 3\), expected no such level"),
], ids=["no-level-1", "no-level-0", "extra-level-9", "level-4-too-small"])
def test_non_contiguous_specular_levels_are_refused(store, tmp_path, capsys, damage, pattern):
    damage(store)
    with pytest.raises(StoreError, match=pattern):
        describe_store(store)
    with pytest.raises(StoreError, match=pattern):
        export_probe(store, "0,0,0", tmp_path / "out")
    assert not (tmp_path / "out").exists()
    _cli_error(capsys, "info", store)


def test_info_survives_manifest_fields_of_the_wrong_type(store):
    def edit(m):
        m["bake"] = {"settings": "x", "filters": ["a"], "environment": 3}
        m["conventions"]["cube_face_order"] = [1, 2, None]
    _edit_manifest(store, edit)
    text = describe_store(store)
    assert 'bake settings: "x"' in text and 'filters: ["a"]' in text
    assert "cube face order: 1, 2, None" in text


def test_info_of_dot_inside_a_store(store, monkeypatch, capsys):
    monkeypatch.chdir(store)
    assert describe_store(".").startswith("probe grid store .")
    assert main(["info", "."]) == 0
    assert "3x2x3 = 18 probes" in capsys.readouterr().out


def test_manifests_record_half_or_float_per_file(store, tmp_path):
    """Half EXR files fall back to float where a value exceeds 65504 (a sun); the filter's and
    export's manifests record the pixel type each file really has."""
    sun = np.full((8, 16, 3), 0.5, np.float32)
    sun[2, 5] = 2e5
    path = tmp_path / "sun.exr"
    imageio.write_image(path, sun, half=False)
    run_filter(path, tmp_path / "f", FAST_FILTER)
    files = json.loads((tmp_path / "f" / "manifest.json").read_text())["files"]
    spec0 = next(f for f in files if f.get("kind") == "specular" and f.get("level") == 0)
    dif = next(f for f in files if f.get("kind") == "diffuse")
    assert spec0["dtype"] == "float" and dif["dtype"] == "half"
    for f in (spec0, dif):
        for p in ([f["path"]] if isinstance(f["path"], str) else f["path"]):
            assert imageio.stored_pixel_type(tmp_path / "f" / p) == f["dtype"]
            assert np.isfinite(imageio.read_image(tmp_path / "f" / p)).all()
    export_probe(store, (0, 0, 0), tmp_path / "e", half=True)
    files = json.loads((tmp_path / "e" / "manifest.json").read_text())["files"]
    assert {f["dtype"] for f in files if "dtype" in f} == {"half"}
