"""Per-hit records kept between passes (probegrid.bake.records): what a worker holds in memory
is the block's files, never a stale copy of an earlier bake of the same store."""

from __future__ import annotations

import numpy as np

from probegrid.bake import records as rc


def test_held_records_are_the_files_and_never_stale(tmp_path):
    path = rc.records_file(tmp_path, 0)
    first = {"kind": np.zeros(4, np.uint8), "probes": np.arange(2)}
    rc.save_records(path, first)
    assert rc.load_records(path) is first  # held: no read
    extra = {"weight": np.ones((4, 8), np.float32)}
    rc.save_records(path, extra)  # arrays added later join the held block and the files
    assert "weight" in rc.load_records(path)
    rc._drop(path)  # another process: reads the files
    again = rc.load_records(path)
    assert again is not first and set(again) == {"kind", "probes", "weight"}
    # the same store baked again: new files under the same name are not taken for the old
    rc.remove_records(path)
    assert rc.load_records(path) is None
    second = {"kind": np.ones(4, np.uint8), "probes": np.arange(2)}
    rc.save_records(path, second)
    rc._drop(path)
    assert rc.load_records(path)["kind"].tolist() == [1, 1, 1, 1]
    stale = rc.load_records(path)
    rc.remove_records(path)  # ... and a third bake in another process writes the same name
    third = {"kind": np.full(4, 2, np.uint8), "probes": np.arange(2)}
    path.mkdir(parents=True)
    for k, v in third.items():
        np.save(path / f"{k}.npy", v)
    (path / "complete").write_text("another token")
    rc._hold(("x", "y"), stale)  # (whatever this process still holds)
    assert rc.load_records(path)["kind"].tolist() == [2, 2, 2, 2]


def test_memory_held_is_bounded(tmp_path, monkeypatch):
    monkeypatch.setattr(rc, "RECORDS_MEMORY", 3000)
    for i in range(5):  # 5 blocks of 1,000 bytes: only the last 3 stay in memory
        rc.save_records(rc.records_file(tmp_path, i), {"a": np.zeros(1000, np.uint8)})
    held = [k for k in rc._held if k[0].startswith(str(tmp_path))]
    assert len(held) == 3 and rc._held_bytes[0] <= 3000
    assert rc.load_records(rc.records_file(tmp_path, 0))["a"].nbytes == 1000  # from its files
