"""Tests of the grid store (probegrid.store): round trip, memory maps, atomicity, resume."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from probegrid.core.grid import GridSpec
from probegrid.store import (
    FORMAT_VERSION,
    ArraySpec,
    StoreError,
    StoreWriter,
    open_store,
    partial_path,
    partial_progress,
    read_manifest,
)

GRID = GridSpec.from_counts((-1.0, 0.0, -2.0), (1.0, 2.0, 2.0), (3, 2, 4))  # P = 24
CONVENTIONS = {"cube_face_order": ["+X", "-X", "+Y", "-Y", "+Z", "-Z"], "version": 1}
ARRAYS = {
    "sh": ArraySpec((9, 3), "float32", "SH radiance coefficients"),
    "diffuse": ArraySpec((6, 2, 2, 3), "float16", "irradiance / pi"),
    "valid": ArraySpec((), "bool", "probe is outside geometry"),
    "positions": ArraySpec((3,), "float64", "probe position, metres"),
}
BAKE = {"face_size": 2, "bounces": 2, "seed": 7}


def make_values(indices) -> dict[str, np.ndarray]:
    """Deterministic per-probe values (depend only on the probe index)."""
    i = np.asarray(indices, dtype=np.int64)
    f = i.astype(np.float64)
    return {
        "sh": (np.sin(f[:, None, None] + np.arange(27).reshape(9, 3))).astype(np.float32),
        "diffuse": np.broadcast_to(
            (f / 7.0)[:, None, None, None, None] + np.linspace(0, 1, 3), (i.size, 6, 2, 2, 3)
        ).astype(np.float32),  # stored as float16 (same_kind cast)
        "valid": i % 5 != 0,
        "positions": GRID.positions()[i],
    }


def writer_kwargs(**over):
    kw = {
        "arrays": ARRAYS, "grid": GRID, "conventions": CONVENTIONS, "scene_hash": "abc123",
        "bake": BAKE,
    }
    kw.update(over)
    return kw


def bake_all(path: Path, batches, **kw) -> None:
    w = StoreWriter.create(path, **writer_kwargs(**kw))
    for b in batches:
        w.write(b, make_values(b))
    w.finish(quality={"invalid_probes": 5, "furnace_error": 1e-6})


def data_bytes(store_dir: Path) -> dict[str, bytes]:
    return {f.name: f.read_bytes() for f in sorted(store_dir.glob("*.npy"))}


# ---------------------------------------------------------------------------- round trip
def test_round_trip(tmp_path):
    path = tmp_path / "room.probes"
    order = np.random.default_rng(1).permutation(GRID.n_probes)
    bake_all(path, np.array_split(order, 5))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["room.probes"]
    assert sorted(p.name for p in path.iterdir()) == [
        "diffuse.npy", "manifest.json", "positions.npy", "sh.npy", "valid.npy"
    ]
    store = open_store(path)
    m = store.manifest
    assert m.format == "probegrid.store" and m.format_version == FORMAT_VERSION
    assert m.grid == GRID and store.grid.n_probes == 24
    assert m.scene_hash == "abc123" and m.bake == BAKE and m.conventions == CONVENTIONS
    assert m.quality == {"invalid_probes": 5, "furnace_error": 1e-6}
    assert m.arrays["diffuse"].dtype == "<f2" and m.arrays["diffuse"].shape == (24, 6, 2, 2, 3)
    assert m.arrays["valid"].shape == (24,) and m.arrays["valid"].description
    assert m.created >= m.bake_started
    expected = make_values(np.arange(24))
    for name, spec in ARRAYS.items():
        got = store[name]
        assert got.dtype == np.dtype(spec.dtype)
        np.testing.assert_array_equal(got, expected[name].astype(got.dtype))
    assert store.probe_index(2, 1, 3) == (2 * 2 + 1) * 4 + 3 == 23
    p = store.probe(int(store.probe_index(1, 0, 2)))
    np.testing.assert_array_equal(p["positions"], GRID.positions()[10])
    np.testing.assert_allclose(p["positions"], [0.0, 0.0, 2.0 / 3.0], rtol=0, atol=1e-15)
    with pytest.raises(KeyError, match="no array 'nope'"):
        store["nope"]
    with pytest.raises(ValueError, match="probe index"):
        store.probe(24)
    # the manifest is plain JSON a non-Python reader can use
    raw = json.loads((path / "manifest.json").read_text())
    assert raw["grid"]["counts"] == [3, 2, 4] and raw["arrays"]["sh"]["file"] == "sh.npy"
    assert read_manifest(path) == m


def test_arrays_are_lazy_read_only_memory_maps(tmp_path):
    path = tmp_path / "a.probes"
    bake_all(path, [np.arange(24)])
    store = open_store(path)
    assert store.arrays.mapped() == []  # opening maps nothing
    sh = store.arrays["sh"]
    assert isinstance(sh, np.memmap) and Path(sh.filename) == (path / "sh.npy").resolve()
    assert not sh.flags.writeable
    assert store.arrays.mapped() == ["sh"]
    assert store.arrays["sh"] is sh  # mapped once
    with pytest.raises(ValueError, match="read-only"):
        sh[0] = 1
    rows = store.arrays["sh"][[3, 17]]  # fancy indexing copies only those probes
    assert type(rows) is np.ndarray and rows.shape == (2, 9, 3)
    np.testing.assert_array_equal(rows, make_values([3, 17])["sh"])
    with open_store(path) as other:
        assert other.arrays["valid"].sum() == make_values(np.arange(24))["valid"].sum()


def test_other_processes_read_the_same_store(tmp_path):
    path = tmp_path / "shared.probes"
    bake_all(path, [np.arange(24)])
    code = (
        "import sys; from probegrid.store import open_store; s = open_store(sys.argv[1]); "
        "print(float(s['sh'][[5, 6]].astype('float64').sum()))"
    )
    procs = [
        subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True,
                       check=True, cwd=Path(__file__).parents[1])
        for _ in range(2)
    ]
    expected = float(make_values([5, 6])["sh"].astype(np.float64).sum())
    assert all(float(p.stdout) == expected for p in procs)


# ---------------------------------------------------------------------------- atomicity, resume
def test_interrupted_bake_leaves_nothing_loadable_and_resumes_bit_identical(tmp_path):
    ref = tmp_path / "ref.probes"
    bake_all(ref, np.array_split(np.arange(24), 6))

    path = tmp_path / "room.probes"
    batches = np.array_split(np.arange(24), 6)
    w = StoreWriter.create(path, **writer_kwargs())
    for b in batches[:3]:
        w.write(b, make_values(b))
    del w  # the process "stops": no finish, no close

    with pytest.raises(StoreError, match="no such directory"):
        open_store(path)
    with pytest.raises(StoreError, match="unfinished bake"):
        open_store(partial_path(path))
    renamed = tmp_path / "renamed.probes"  # even under another name: no manifest, plan present
    os.rename(partial_path(path), renamed)
    with pytest.raises(StoreError, match="unfinished bake"):
        open_store(renamed)
    os.rename(renamed, partial_path(path))
    with pytest.raises(StoreError, match="unfinished bake exists"):
        StoreWriter.create(path, **writer_kwargs())

    assert partial_progress(path) == (12, 24)
    assert partial_progress(ref) is None
    w = StoreWriter.resume(path, **writer_kwargs())
    np.testing.assert_array_equal(w.remaining(), np.arange(12, 24))
    assert w.n_done == 12
    for b in batches[3:]:
        w.write(b, make_values(b))
    store = w.finish(quality={"invalid_probes": 5, "furnace_error": 1e-6})
    assert not partial_path(path).exists()
    assert data_bytes(path) == data_bytes(ref)  # bit for bit, headers included
    assert store.manifest.model_dump(exclude={"created", "bake_started"}) == open_store(
        ref
    ).manifest.model_dump(exclude={"created", "bake_started"})


def test_resume_refuses_other_settings(tmp_path):
    path = tmp_path / "room.probes"
    w = StoreWriter.create(path, **writer_kwargs())
    w.write([0, 1], make_values([0, 1]))
    w.close()
    cases = [
        ({"scene_hash": "other"}, "scene_hash"),
        ({"bake": {**BAKE, "seed": 8}}, r"bake settings \(seed\)"),
        ({"grid": GridSpec.from_counts((0, 0, 0), (1, 1, 1), (3, 2, 4))}, "grid"),
        ({"arrays": {**ARRAYS, "sh": ArraySpec((9, 3), "float16")}}, r"arrays \(sh\)"),
        ({"conventions": {"version": 2}}, "conventions"),
    ]
    for over, pattern in cases:
        with pytest.raises(StoreError, match=pattern) as info:
            StoreWriter.resume(path, **writer_kwargs(**over))
        assert "\n" not in str(info.value) and "overwrite=True" in str(info.value)
        with pytest.raises(StoreError, match=pattern):
            StoreWriter.create_or_resume(path, **writer_kwargs(**over))
    # the refused attempts changed nothing: the original bake still resumes
    w = StoreWriter.create_or_resume(path, **writer_kwargs())
    assert w.n_done == 2
    w.close()
    # overwrite starts again from scratch
    w = StoreWriter.create(path, **writer_kwargs(scene_hash="other"), overwrite=True)
    assert w.n_done == 0
    w.close()
    with pytest.raises(StoreError, match="no unfinished bake"):
        StoreWriter.resume(tmp_path / "none.probes", **writer_kwargs())


def test_one_writer_at_a_time(tmp_path):
    path = tmp_path / "room.probes"
    w = StoreWriter.create(path, **writer_kwargs())
    with pytest.raises(StoreError, match="another process is writing"):
        StoreWriter.resume(path, **writer_kwargs())
    with pytest.raises(StoreError, match="another process is writing"):
        StoreWriter.create(path, **writer_kwargs(), overwrite=True)
    w.close()
    StoreWriter.resume(path, **writer_kwargs()).close()


def test_finish_needs_every_probe_and_overwrite(tmp_path):
    path = tmp_path / "room.probes"
    with StoreWriter.create(path, **writer_kwargs()) as w:
        w.write(np.arange(20), make_values(np.arange(20)))
        with pytest.raises(StoreError, match="4 of 24 probes are not written"):
            w.finish()
    w = StoreWriter.resume(path, **writer_kwargs())
    w.write(w.remaining(), make_values(w.remaining()))
    w.finish()
    with pytest.raises(StoreError, match="already exists.*overwrite"):
        StoreWriter.create(path, **writer_kwargs())
    old = open_store(path)
    old_sh = old["sh"]
    expected_old = np.array(old_sh)
    w = StoreWriter.create(path, **writer_kwargs(scene_hash="new"), overwrite=True)
    assert open_store(path).manifest.scene_hash == "abc123"  # old store served until finish
    w.write(np.arange(24), {k: v[::-1] for k, v in make_values(np.arange(24)).items()})
    new = w.finish()
    assert new.manifest.scene_hash == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["room.probes"]
    np.testing.assert_array_equal(old_sh, expected_old)  # a reader's old map stays valid
    np.testing.assert_array_equal(new["sh"], make_values(np.arange(24))["sh"][::-1])


def test_overwrite_replaces_a_file_in_the_way_without_leftovers(tmp_path):
    path = tmp_path / "room.probes"
    path.write_text("not a store")
    w = StoreWriter.create(path, **writer_kwargs(), overwrite=True)
    w.write(np.arange(24), make_values(np.arange(24)))
    w.finish()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["room.probes"]
    assert open_store(path).n_probes == 24


def test_killed_during_finish_resumes_into_the_rename(tmp_path, monkeypatch):
    from probegrid.store import writer as store_mod

    path = tmp_path / "room.probes"
    w = StoreWriter.create(path, **writer_kwargs())
    w.write(np.arange(24), make_values(np.arange(24)))

    def dies(src, dst):
        raise OSError("killed before the rename")

    monkeypatch.setattr(store_mod.os, "rename", dies)
    with pytest.raises(OSError, match="killed"):
        w.finish(quality={"q": 1})
    monkeypatch.undo()
    w.close()
    assert (partial_path(path) / "manifest.json").is_file()
    assert partial_progress(path) == (24, 24)
    with pytest.raises(StoreError, match="unfinished bake"):
        open_store(partial_path(path))
    w = StoreWriter.create_or_resume(path, **writer_kwargs())
    assert w.n_done == 24 and w.remaining().size == 0
    store = w.finish()
    assert store.manifest.quality == {"q": 1}
    np.testing.assert_array_equal(store["sh"], make_values(np.arange(24))["sh"])


def test_write_checks_everything_before_writing(tmp_path):
    w = StoreWriter.create(tmp_path / "x.probes", **writer_kwargs())
    good = make_values([0, 1])
    bad_cases = [
        ([0, 1], {k: v for k, v in good.items() if k != "sh"}, r"missing \['sh'\]"),
        ([0, 1], {**good, "extra": good["sh"]}, r"unknown \['extra'\]"),
        ([0, 1], {**good, "sh": good["sh"][:, :4]}, r"needs shape \(2, 9, 3\)"),
        ([0, 1], {**good, "valid": np.array([0.5, 1.0])}, "cannot store float64"),
        ([0, 0], good, "distinct"),
        ([0, 24], good, r"0\.\.23"),
        ([[0, 1]], good, "1-D integer"),
    ]
    for idx, values, pattern in bad_cases:
        with pytest.raises(ValueError, match=pattern):
            w.write(idx, values)
    assert w.n_done == 0
    assert not np.any(w.array("sh"))
    w.write(np.array([], dtype=np.int64), make_values([]))  # an empty batch is a no-op
    w.write([5, 3], make_values([5, 3]))
    assert w.done.nonzero()[0].tolist() == [3, 5]
    np.testing.assert_array_equal(w.array("sh")[[3, 5]], make_values([3, 5])["sh"])
    w.close()
    with pytest.raises(StoreError, match="closed"):
        w.write([0], make_values([0]))


def test_declarations_are_checked(tmp_path):
    with pytest.raises(ValueError, match="little-endian bool, int, uint or float"):
        ArraySpec((3,), "complex64")
    with pytest.raises(ValueError, match="little-endian"):
        ArraySpec((3,), ">f4")
    with pytest.raises(ValueError, match="positive integers"):
        ArraySpec((0, 3), "float32")
    assert ArraySpec((2,), np.float16).dtype == "<f2"
    for name in ("Sh", "2x", "a/b", "../x", "_done"):
        with pytest.raises(ValueError, match="array name"):
            StoreWriter.create(tmp_path / "n.probes",
                               **writer_kwargs(arrays={name: ArraySpec((1,), "f4")}))
    with pytest.raises(ValueError, match="JSON-serialisable"):
        StoreWriter.create(tmp_path / "n.probes", **writer_kwargs(bake={"x": object()}))
    with pytest.raises(ValueError, match="finite"):
        StoreWriter.create(tmp_path / "n.probes", **writer_kwargs(bake={"x": float("nan")}))
    with pytest.raises(ValueError, match="NAME.probes"):
        StoreWriter.create(tmp_path / "n.probes.partial", **writer_kwargs())
    assert not (tmp_path / "n.probes.partial").exists()


# ---------------------------------------------------------------------------- damaged stores
@pytest.fixture
def good_store(tmp_path) -> Path:
    path = tmp_path / "good.probes"
    bake_all(path, [np.arange(24)])
    return path


def _edit_manifest(path: Path, edit) -> None:
    raw = json.loads((path / "manifest.json").read_text())
    edit(raw)
    (path / "manifest.json").write_text(json.dumps(raw))


def _append(file: Path, data: bytes) -> None:
    with file.open("ab") as f:
        f.write(data)


@pytest.mark.parametrize(
    "damage, pattern",
    [
        (lambda p: (p / "manifest.json").write_text('{"format": "probegrid.store", '),
         "not valid JSON"),
        (lambda p: (p / "manifest.json").unlink(), "no manifest.json"),
        (lambda p: _edit_manifest(p, lambda m: m.update(format_version=FORMAT_VERSION + 1)),
         f"format version {FORMAT_VERSION + 1}, written by a newer probegrid; probegrid .* "
         "reads version 1, 2: upgrade probegrid"),
        (lambda p: _edit_manifest(p, lambda m: m.update(format_version=0)),
         "format version 0; probegrid .* reads version 1, 2$"),
        (lambda p: _edit_manifest(p, lambda m: m.update(format_version="2")),
         "format version '2'; probegrid .* reads version 1, 2$"),
        (lambda p: _edit_manifest(p, lambda m: m.update(format="other")), "not a probegrid"),
        (lambda p: _edit_manifest(p, lambda m: m.pop("scene_hash")), "scene_hash: Field required"),
        (lambda p: _edit_manifest(p, lambda m: m["grid"].update(counts=[3, 2, 5])),
         "24 entries for a grid of 30"),
        (lambda p: _edit_manifest(p, lambda m: m["arrays"]["sh"].update(file="../sh.npy")),
         "must live in sh.npy"),
        (lambda p: _edit_manifest(p, lambda m: m["arrays"]["sh"].update(dtype="<f8")),
         "has dtype <f4, the manifest says <f8"),
        (lambda p: _edit_manifest(p, lambda m: m["arrays"]["valid"].update(shape=[24, 1])),
         r"has shape \(24,\), the manifest says \(24, 1\)"),
        (lambda p: os.truncate(p / "diffuse.npy", (p / "diffuse.npy").stat().st_size - 10),
         "is truncated"),
        (lambda p: os.truncate(p / "diffuse.npy", 20), "not a valid .npy"),
        (lambda p: _append(p / "sh.npy", b"xx"), "too long"),
        (lambda p: (p / "valid.npy").unlink(), "missing its file valid.npy"),
        (lambda p: (p / "_bake.json").write_text("{}"), "unfinished bake"),
        (lambda p: os.link(p / "sh.npy", p.parent / "sh-elsewhere.npy"),
         "sh.npy has 2 hard links; a store's files must be its own"),
    ],
)
def test_damaged_store_is_refused_in_one_line(good_store, damage, pattern):
    damage(good_store)
    with pytest.raises(StoreError, match=pattern) as info:
        open_store(good_store)
    assert "\n" not in str(info.value)


# ---------------------------------------------------------------------------- a real kill
CHILD = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    sys.path.insert(0, sys.argv[2])
    from test_store import make_values, writer_kwargs
    from probegrid.store import StoreWriter
    w = StoreWriter.create_or_resume(sys.argv[1], **writer_kwargs(), durable=sys.argv[3] == "1")
    for b in np.array_split(w.remaining(), 12):
        w.write(b, make_values(b))
        print(w.n_done, flush=True)
        time.sleep(0.05)
    """
)


@pytest.mark.parametrize("durable", [True, False])
def test_sigkilled_bake_is_not_loadable_and_resumes(tmp_path, durable):
    ref = tmp_path / "ref.probes"
    bake_all(ref, [np.arange(24)])
    path = tmp_path / "killed.probes"
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path), str(Path(__file__).parent), str(int(durable))],
        stdout=subprocess.PIPE, text=True, cwd=Path(__file__).parents[1],
    )
    try:
        seen = [int(proc.stdout.readline()) for _ in range(3)]
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL and seen == [2, 4, 6]
    for candidate in (path, partial_path(path)):
        with pytest.raises(StoreError):
            open_store(candidate)
    t0 = time.perf_counter()
    w = StoreWriter.resume(path, **writer_kwargs())  # the dead writer's lock is gone with it
    assert time.perf_counter() - t0 < 5
    assert 6 <= w.n_done < 24
    np.testing.assert_array_equal(
        w.array("sh")[w.done], make_values(np.flatnonzero(w.done))["sh"]
    )
    rest = w.remaining()
    w.write(rest, make_values(rest))
    w.finish(quality={"invalid_probes": 5, "furnace_error": 1e-6})
    assert data_bytes(path) == data_bytes(ref)


# ---------------------------------------------------------------------------- self-contained
def test_finish_records_each_files_sha256(good_store):
    import hashlib

    raw = json.loads((good_store / "manifest.json").read_text())
    for name, info in raw["arrays"].items():
        data = (good_store / f"{name}.npy").read_bytes()
        assert info["sha256"] == hashlib.sha256(data).hexdigest()


@pytest.mark.parametrize("name", ["sh.npy", "manifest.json"])
def test_a_store_whose_file_is_a_symlink_is_refused_wherever_it_points(good_store, tmp_path,
                                                                       name):
    # the link's target has exactly the bytes the manifest records: only the link is wrong
    outside = tmp_path / f"outside-{name}"
    outside.write_bytes((good_store / name).read_bytes())
    (good_store / name).unlink()
    (good_store / name).symlink_to(outside)
    with pytest.raises(StoreError, match=f"{name} is a symbolic link") as info:
        open_store(good_store)
    assert "\n" not in str(info.value)


def test_a_store_whose_file_is_not_a_regular_file_is_refused(good_store):
    (good_store / "valid.npy").unlink()
    os.mkfifo(good_store / "valid.npy")  # a reader would block on it forever
    with pytest.raises(StoreError, match="valid.npy is not a regular file"):
        open_store(good_store)


def test_a_same_size_rewrite_fails_the_sha256(good_store):
    data = bytearray((good_store / "sh.npy").read_bytes())
    data[-1] ^= 0x40
    (good_store / "sh.npy").write_bytes(bytes(data))
    with pytest.raises(StoreError, match="sh.npy does not have the SHA-256 the manifest records"):
        open_store(good_store)
    open_store(good_store, verify=False)  # sizes and headers are still right


def test_files_are_hashed_once_per_process_while_unchanged(good_store, monkeypatch):
    import hashlib

    open_store(good_store)  # hashed (or already, by finish)
    calls = []
    real = hashlib.file_digest
    monkeypatch.setattr(hashlib, "file_digest", lambda *a, **k: calls.append(a) or real(*a, **k))
    open_store(good_store)
    assert calls == []
    data = (good_store / "valid.npy").read_bytes()
    (good_store / "valid.npy").write_bytes(data)  # same bytes, a new modification time
    open_store(good_store)
    assert len(calls) == 1


def test_loaded_arrays_survive_their_files_being_truncated(good_store):
    store = open_store(good_store, load=True)
    assert store.in_memory and not isinstance(store["sh"], np.memmap)
    assert not store["sh"].flags.writeable
    for f in good_store.glob("*.npy"):
        os.truncate(f, 0)  # a map of these would fault with SIGBUS
    np.testing.assert_array_equal(store["sh"], make_values(np.arange(24))["sh"])
    np.testing.assert_array_equal(store["positions"], GRID.positions())


def test_a_lazy_map_of_a_file_changed_since_open_is_refused(good_store):
    store = open_store(good_store)
    data = (good_store / "diffuse.npy").read_bytes()
    (good_store / "diffuse.npy").unlink()
    (good_store / "diffuse.npy").write_bytes(data)  # another file now
    with pytest.raises(StoreError, match="diffuse.npy changed on disk since the store was opened"):
        store["diffuse"]
