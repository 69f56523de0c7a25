"""Per-hit records kept between passes (probegrid.bake.records): what a worker holds in memory
is the block's files, never a stale copy of an earlier bake of the same store."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from probegrid.bake import records as rc
from probegrid.bake.records import schema, storage


def test_held_records_are_the_files_and_never_stale(tmp_path):
    path = rc.records_file(tmp_path, 0)
    first = {"kind": np.zeros(4, np.uint8), "probes": np.arange(2)}
    rc.save_records(path, first)
    assert rc.load_records(path) is first  # held: no read
    extra = {"weight": np.ones((4, 8), np.float32)}
    rc.save_records(path, extra)  # arrays added later join the held block and the files
    assert "weight" in rc.load_records(path)
    storage._drop(path)  # another process: reads the files
    again = rc.load_records(path)
    assert again is not first and set(again) == {"kind", "probes", "weight"}
    # the same store baked again: new files under the same name are not taken for the old
    rc.remove_records(path)
    assert rc.load_records(path) is None
    second = {"kind": np.ones(4, np.uint8), "probes": np.arange(2)}
    rc.save_records(path, second)
    storage._drop(path)
    assert rc.load_records(path)["kind"].tolist() == [1, 1, 1, 1]
    stale = rc.load_records(path)
    rc.remove_records(path)  # ... and a third bake in another process writes the same name
    third = {"kind": np.full(4, 2, np.uint8), "probes": np.arange(2)}
    path.mkdir(parents=True)
    for k, v in third.items():
        np.save(path / f"{k}.npy", v)
    (path / "complete").write_text("another token")
    storage._hold(("x", "y"), stale)  # (whatever this process still holds)
    assert rc.load_records(path)["kind"].tolist() == [2, 2, 2, 2]


def test_memory_held_is_bounded(tmp_path, monkeypatch):
    monkeypatch.setattr(storage, "RECORDS_MEMORY", 3000)
    for i in range(5):  # 5 blocks of 1,000 bytes: only the last 3 stay in memory
        rc.save_records(rc.records_file(tmp_path, i), {"a": np.zeros(1000, np.uint8)})
    held = [k for k in storage._held if k[0].startswith(str(tmp_path))]
    assert len(held) == 3 and storage._held_bytes[0] <= 3000
    assert rc.load_records(rc.records_file(tmp_path, 0))["a"].nbytes == 1000  # from its files


def test_records_kept_in_memory_alone_are_written_when_they_must_leave_it(tmp_path,
                                                                         monkeypatch):
    """save_records(files=False) (a bake's only worker process): nothing on disk while the
    block is held, its added arrays and drops in memory; a block pushed out of memory by the
    bound is written first, complete, and read back from its files; stale files of an earlier
    bake under the same name are never taken for it."""
    monkeypatch.setattr(storage, "RECORDS_MEMORY", 3000)
    stale = rc.records_file(tmp_path, 0)
    stale.mkdir(parents=True)
    np.save(stale / "a.npy", np.full(1000, 9, np.uint8))
    (stale / "complete").write_text("an earlier bake")
    rc.save_records(stale, {"a": np.zeros(1000, np.uint8)}, files=False)
    assert not stale.exists() and rc.load_records(stale)["a"].max() == 0
    rc.save_records(stale, {"b": np.ones(10, np.uint8)}, drop=("a",))
    assert set(rc.load_records(stale)) == {"b"} and not stale.exists()
    for i in range(1, 5):  # 4 more blocks of 1,000 bytes: block 0 and 1 must leave memory
        rc.save_records(rc.records_file(tmp_path, i), {"a": np.full(1000, i, np.uint8)},
                        files=False)
    assert storage._held_bytes[0] <= 3000
    for i in range(5):
        path = rc.records_file(tmp_path, i)
        assert path.exists() == (i < 2), i  # written only once pushed out
        got = rc.load_records(path)
        assert got is not None
        if i == 0:
            assert set(got) == {"b"} and got["b"].tolist() == [1] * 10
        else:
            assert got["a"].tolist() == [i] * 1000
    for i in range(5):
        rc.remove_records(rc.records_file(tmp_path, i))
        assert rc.load_records(rc.records_file(tmp_path, i)) is None
    assert not storage._memory_only
    # a block whose bake directory was deleted meanwhile is dropped, not written back
    gone = tmp_path / "deleted-bake" / "records"
    gone.mkdir(parents=True)
    rc.save_records(rc.records_file(gone, 0), {"a": np.zeros(2000, np.uint8)}, files=False)
    shutil.rmtree(tmp_path / "deleted-bake")
    for i in range(1, 3):
        rc.save_records(rc.records_file(tmp_path, 10 + i), {"a": np.zeros(1000, np.uint8)},
                        files=False)
    assert not (tmp_path / "deleted-bake").exists()
    assert rc.load_records(rc.records_file(gone, 0)) is None
    for i in range(1, 3):
        rc.remove_records(rc.records_file(tmp_path, 10 + i))


def test_a_subset_of_a_blocks_records_is_what_tracing_the_subset_gives():
    """A resumed or re-partitioned batch reads part of a block: every record (both gather
    levels, the probes' direct views of the emitters and lights, and their offsets) equals a
    trace of those probes alone."""
    from pathlib import Path

    from probegrid.bake.settings import BakeSettings, TraceGeometry
    from probegrid.jobs.bake import load_environment
    from probegrid.scene import load_gltf

    data = Path(__file__).resolve().parents[1] / "data"
    scene = load_gltf(data / "sample_room.glb")
    env = load_environment(data / "sample_sky.hdr")
    st = BakeSettings(face_size=4, moments_size=4, gather_samples=2, gather_depth=2)
    tracer = rc.RecordTracer(scene, env, st, TraceGeometry())
    pos = np.array([[0.0, 1.0, 0.0], [0.5, 2.5, 0.2], [-1.0, 0.8, 1.0]])
    idx = np.array([3, 5, 9])
    block, _, _ = tracer.trace(pos, idx)
    alone, _, _ = tracer.trace(pos[[0, 2]], idx[[0, 2]])
    picked = rc.select_probes(block, idx[[0, 2]])
    assert picked is not None and set(picked) == set(alone)
    assert rc.gather_depth(picked) == 2 and len(picked["lights_direction"]) > 0
    for k in alone:
        np.testing.assert_array_equal(np.asarray(picked[k]), np.asarray(alone[k]), err_msg=k)


@pytest.mark.parametrize("depth", [2, 3])
def test_record_bytes_bounds_the_records_of_a_closed_room(depth):
    """The bake's estimate of its records (record_bytes) against a block traced and weighted
    in a closed box, where every ray hits and each gather level is full: exact, the per-probe
    arrays aside; a gather level keeps no emission, the upper levels no position or normal."""
    from probegrid.bake.records import GridData
    from probegrid.bake.environment import Environment
    from probegrid.bake.settings import BakeSettings, TraceGeometry
    from probegrid.core.ddgi import bordered_cubes
    from probegrid.core.grid import GridSpec
    from probegrid.scene import Material, SceneBuilder

    b = SceneBuilder()
    b.add_box((-1, 0, -1), (1, 2, 1), material=b.add_material(Material.diffuse(0.5)),
              inward=True)
    scene = b.build()
    st = BakeSettings(face_size=4, moments_size=4, gather_samples=2, gather_depth=depth)
    tracer = rc.RecordTracer(scene, Environment(), st, TraceGeometry())
    pos = np.array([[0.0, 1.0, 0.0], [0.3, 0.5, -0.2]])
    rec, moments, _ = tracer.trace(pos, np.array([0, 1]))
    assert "gather_emission" not in rec and "gather_position" not in rec
    deepest = schema.LEVEL_PREFIXES[depth]
    assert rc.gather_depth(rec) == depth
    assert deepest + "position" in rec and deepest + "normal" in rec
    assert all(schema.LEVEL_PREFIXES[d] + "position" not in rec for d in range(1, depth))
    grid = GridSpec(bounds_min=(0.0, 1.0, 0.0), bounds_max=(0.3, 1.0, 0.0), counts=(2, 1, 1))
    mb = bordered_cubes(moments)
    data = GridData(grid, np.ones(2, bool), pos, np.ascontiguousarray(mb).reshape(-1, 2),
                    mb.shape[2] - 2, None)
    rec.update(rc.all_hit_weights(rec, data))
    primary = 2 * 6 * 4 * 4
    for d in range(1, depth + 1):  # (every gather ray hit the box)
        assert len(rec[schema.LEVEL_PREFIXES[d] + "kind"]) == 2 * primary
    per_ray = sum(v.nbytes for k, v in rec.items() if not k.startswith(("view", "lights"))
                  and np.ndim(v) and len(v) in (primary, 2 * primary))
    assert per_ray == rc.record_bytes(primary, 2, depth)
