"""Tests of the batch executors (probegrid.bake.executors): same bits everywhere, setup once, errors."""

from __future__ import annotations

import os
import socket
import tempfile
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from probegrid.bake import executors as ex
from probegrid.bake.executors.base import Pipeline

P = 37  # probes; not a multiple of the batch sizes used below
SEED = 20240917


# ---------------------------------------------------------------------------- task and context
@dataclass(frozen=True)
class NoiseContext:
    """Builds a per-process 'expensive' state once and records every setup() as a file."""

    seed: int
    log_dir: str

    def setup(self) -> dict:
        setup_id = uuid.uuid4().hex
        Path(self.log_dir, f"setup-{os.getpid()}-{setup_id}").touch()
        # stands in for a BVH: a matrix the tasks use
        mixing = np.linalg.qr(np.random.default_rng(self.seed).standard_normal((16, 16)))[0]
        return {"pid": os.getpid(), "setup_id": setup_id, "mixing": mixing, "seed": self.seed}


def noise_task(state: dict, batch: np.ndarray) -> dict:
    """Per-probe random draws keyed by probe index, pushed through the per-process state.

    Row-independent arithmetic on purpose: a BLAS product ``draws @ mixing`` rounds differently
    for different batch sizes (gemv for one row, blocked gemm for more), which would tie the
    bits to the batch partition.
    """
    draws = np.stack([ex.probe_rng(state["seed"], int(i)).standard_normal(16) for i in batch])
    mixed = (draws[:, :, None] * state["mixing"][None]).sum(axis=1)
    values = np.sin(mixed) * np.exp(draws[:, :1])
    return {"values": values, "pid": state["pid"], "setup_id": state["setup_id"]}


def failing_task(state: dict, batch: np.ndarray) -> dict:
    if 13 in batch:
        raise ValueError("probe 13 is cursed\nsecond line of detail")
    return noise_task(state, batch)


def dying_task(state: dict, batch: np.ndarray) -> dict:
    if 13 in batch:
        os._exit(3)
    return noise_task(state, batch)


@dataclass(frozen=True)
class BrokenContext:
    def setup(self) -> dict:
        raise FileNotFoundError("scene.glb not found")


def run_all(executor, context, batches, task=noise_task):
    out = np.full((P, 16), np.nan)
    seen: list[tuple[int, str]] = []
    progress: list[ex.Progress] = []
    for batch, result in executor.map(task, context, batches, progress=progress.append):
        out[batch] = result["values"]
        seen.append((result["pid"], result["setup_id"]))
    return out, seen, progress


def setups_per_pid(log_dir: Path) -> dict[int, int]:
    counts: dict[int, int] = {}
    for f in log_dir.iterdir():
        pid = int(f.name.split("-")[1])
        counts[pid] = counts.get(pid, 0) + 1
    return counts


@pytest.fixture
def reference(tmp_path):
    """The expected values, computed directly, no executor involved."""
    ctx = NoiseContext(SEED, str(tmp_path))
    state = ctx.setup()
    return noise_task(state, np.arange(P))["values"]


# ---------------------------------------------------------------------------- helpers
def test_make_batches():
    b = ex.make_batches(10, batch_size=4)
    assert [x.tolist() for x in b] == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9]]
    assert all(x.dtype == np.int64 for x in b)
    b = ex.make_batches(np.array([9, 3, 5], dtype=np.int32), batch_size=2)
    assert [x.tolist() for x in b] == [[9, 3], [5]]
    assert ex.make_batches(np.array([], dtype=np.int64), batch_size=3) == []
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="batch_size"):
            ex.make_batches(10, batch_size=bad)
    with pytest.raises(ValueError, match="1-D integer"):
        ex.make_batches(np.zeros((2, 2), dtype=int), batch_size=1)


def test_make_batches_partition_is_resume_stable():
    done = np.zeros(10, dtype=bool)
    done[[0, 1, 2, 3, 5]] = True  # block 0 finished; block 1 partly (only after a size change)
    b = ex.make_batches(10, batch_size=4, done=done)
    assert [x.tolist() for x in b] == [[4, 6, 7], [8, 9]]
    full = ex.make_batches(10, batch_size=4)
    done = np.zeros(10, dtype=bool)
    done[full[1]] = True
    assert [x.tolist() for x in ex.make_batches(10, batch_size=4, done=done)] == [
        full[0].tolist(), full[2].tolist()
    ]
    with pytest.raises(ValueError, match=r"\(10,\) bool"):
        ex.make_batches(10, batch_size=4, done=np.zeros(9, dtype=bool))
    with pytest.raises(ValueError, match="only accepted with a probe count"):
        ex.make_batches(np.arange(4), batch_size=2, done=np.zeros(4, dtype=bool))


def test_probe_rng_is_seedsequence_spawn():
    children = np.random.SeedSequence(7).spawn(5)
    for i in range(5):
        a = ex.probe_rng(7, i).random(4)
        b = np.random.default_rng(children[i]).random(4)
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(ex.probe_rng(7, 1).random(4), ex.probe_rng(7, 2).random(4))
    with pytest.raises(ValueError, match="seed"):
        ex.probe_rng(-1, 0)
    with pytest.raises(ValueError, match="probe index"):
        ex.probe_rng(1, -2)


def test_pipeline_bounds_in_flight():
    """No more than `limit` batches are submitted and not yet handed back."""
    submitted: list[int] = []
    handed = [0]

    def submit(order, batch):
        submitted.append(order)
        assert len(submitted) - handed[0] <= 3
        return order

    pipe = Pipeline(
        submit=submit,
        wait_first=lambda futs: futs[-1:],  # completes out of order
        fetch=lambda fut: fut * 10,
        cancel=lambda futs: None,
        limit=3,
        where="test",
    )
    batches = ex.make_batches(20, batch_size=2)
    got = []
    for batch, result in pipe.run(batches, None):
        handed[0] += 1
        got.append((int(batch[0]) // 2, result))
    assert sorted(got) == [(i, 10 * i) for i in range(10)]
    assert [g[0] for g in got] != list(range(10))  # really out of order


# ---------------------------------------------------------------------------- inline and local
def test_inline_matches_reference(tmp_path, reference):
    log = tmp_path / "log"
    log.mkdir()
    out, seen, progress = run_all(
        ex.InlineExecutor(), NoiseContext(SEED, str(log)), ex.make_batches(P, batch_size=5)
    )
    np.testing.assert_array_equal(out, reference)
    assert setups_per_pid(log) == {os.getpid(): 1}
    assert len({s for _, s in seen}) == 1
    assert [p.batches_done for p in progress] == list(range(1, 9))
    assert progress[-1].probes_done == progress[-1].probes_total == P
    assert progress[-1].eta == 0.0


def test_local_two_processes_bit_identical_and_setup_once(tmp_path, reference):
    log = tmp_path / "log"
    log.mkdir()
    with ex.LocalExecutor(2) as executor:
        assert executor.workers == 2
        out, seen, progress = run_all(
            executor, NoiseContext(SEED, str(log)), ex.make_batches(P, batch_size=3)
        )
    np.testing.assert_array_equal(out, reference)  # bit for bit
    counts = setups_per_pid(log)
    assert len(counts) <= 2 and all(c == 1 for c in counts.values())
    assert os.getpid() not in counts
    pids = {pid for pid, _ in seen}
    assert pids <= set(counts)
    for pid in pids:  # one state per process
        assert len({s for p, s in seen if p == pid}) == 1
    assert progress[-1].probes_done == P and progress[-1].batches_total == 13


def test_local_task_error_surfaces(tmp_path):
    executor = ex.LocalExecutor(2)
    with pytest.raises(ex.ExecutorError) as info:
        run_all(executor, NoiseContext(SEED, str(tmp_path)), ex.make_batches(P, batch_size=4),
                task=failing_task)
    msg = str(info.value)
    assert "\n" not in msg
    assert "12..15" in msg and "ValueError: probe 13 is cursed" in msg
    assert isinstance(info.value.__cause__, ValueError)


def test_local_worker_death_surfaces(tmp_path):
    with pytest.raises(ex.ExecutorError, match="worker process died"):
        run_all(ex.LocalExecutor(2), NoiseContext(SEED, str(tmp_path)),
                ex.make_batches(P, batch_size=4), task=dying_task)


def test_inline_error_and_pickle_check(tmp_path):
    with pytest.raises(ex.ExecutorError, match=r"12\.\.15 failed .*ValueError: probe 13"):
        run_all(ex.InlineExecutor(), NoiseContext(SEED, str(tmp_path)),
                ex.make_batches(P, batch_size=4), task=failing_task)
    with pytest.raises(ValueError, match="task function must be picklable"):
        ex.InlineExecutor().map(lambda s, b: b, NoiseContext(SEED, str(tmp_path)), [[0]])
    with pytest.raises(TypeError, match="WorkerContext"):
        ex.InlineExecutor().map(noise_task, object(), [[0]])


@pytest.mark.parametrize("executor", [ex.InlineExecutor(), ex.LocalExecutor(2)])
def test_setup_error_surfaces(executor):
    with pytest.raises(ex.ExecutorError, match="FileNotFoundError: scene.glb not found"):
        run_all(executor, BrokenContext(), ex.make_batches(P, batch_size=10))


def test_abandoned_iteration_stops_the_pool(tmp_path):
    it = ex.LocalExecutor(2).map(
        noise_task, NoiseContext(SEED, str(tmp_path)), ex.make_batches(P, batch_size=1)
    )
    batch, _ = next(it)
    assert batch.size == 1
    it.close()  # must not hang; pool shut down, pending batches cancelled
    assert len(list(tmp_path.iterdir())) <= 2


def test_executor_arguments():
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match="workers"):
            ex.LocalExecutor(bad)
    with pytest.raises(ValueError, match="forkserver, spawn"):
        ex.LocalExecutor(1, start_method="fork")
    with pytest.raises(ValueError, match="either workers"):
        ex.make_executor(workers=2, scheduler="tcp://127.0.0.1:1")
    assert ex.LocalExecutor().workers == ex.default_workers() >= 1
    assert isinstance(ex.make_executor(workers=1), ex.LocalExecutor)
    for executor in (ex.InlineExecutor(), ex.LocalExecutor(1)):
        assert isinstance(executor, ex.Executor)
    assert isinstance(NoiseContext(1, "."), ex.WorkerContext)


# ---------------------------------------------------------------------------- dask
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_dask_unreachable_scheduler_is_one_line():
    address = f"tcp://127.0.0.1:{_free_port()}"
    with pytest.raises(ex.ExecutorError) as info:
        ex.DaskExecutor(address, timeout=1)
    assert "\n" not in str(info.value) and address in str(info.value)
    for bad in ("nosuchscheme://127.0.0.1:1", "garbage", "tcp://:1", "tcp://host"):
        t = time.perf_counter()
        with pytest.raises(ValueError, match="is not a Dask address"):
            ex.DaskExecutor(bad, timeout=1)
        assert time.perf_counter() - t < 1.0  # refused before any connection attempt
    with pytest.raises(ValueError, match="scheduler must be"):
        ex.DaskExecutor("", timeout=1)


@pytest.fixture(scope="module")
def dask_cluster():
    distributed = pytest.importorskip("distributed")
    cluster = distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
        worker_dashboard_address=None,
    )
    try:
        yield cluster
    finally:
        cluster.close()


def test_dask_bit_identical_setup_once_and_errors(tmp_path, reference, dask_cluster):
    log = tmp_path / "log"
    log.mkdir()
    with ex.DaskExecutor(dask_cluster.scheduler_address, timeout=20) as executor:
        assert executor.workers == 2
        assert "2 workers" in executor.description
        out, seen, progress = run_all(
            executor, NoiseContext(SEED, str(log)), ex.make_batches(P, batch_size=4)
        )
        np.testing.assert_array_equal(out, reference)  # bit for bit with inline and local
        counts = setups_per_pid(log)
        assert len(counts) <= 2 and all(c == 1 for c in counts.values())
        for pid in {pid for pid, _ in seen}:
            assert len({s for p, s in seen if p == pid}) == 1
        assert progress[-1].probes_done == P

        # a second map call builds its state afresh (new context), once per process again
        log2 = tmp_path / "log2"
        log2.mkdir()
        out2, _, _ = run_all(executor, NoiseContext(SEED, str(log2)), ex.make_batches(P, batch_size=7))
        np.testing.assert_array_equal(out2, reference)
        assert all(c == 1 for c in setups_per_pid(log2).values())

        with pytest.raises(ex.ExecutorError) as info:
            run_all(executor, NoiseContext(SEED, str(log)), ex.make_batches(P, batch_size=4),
                    task=failing_task)
        assert "\n" not in str(info.value)
        assert "ValueError: probe 13 is cursed" in str(info.value)


def test_local_processes_serve_successive_maps(tmp_path):
    """The processes outlive a map call; each call's context is set up anew in each process."""
    log1, log2 = tmp_path / "a", tmp_path / "b"
    log1.mkdir()
    log2.mkdir()
    mine = f"probegrid-context-{os.getpid()}-*"  # other processes on the machine may bake too
    before = set(Path(tempfile.gettempdir()).glob(mine))
    with ex.LocalExecutor(2) as executor:
        out1, _, _ = run_all(executor, NoiseContext(SEED, str(log1)),
                                 ex.make_batches(P, batch_size=3))
        out2, _, _ = run_all(executor, NoiseContext(SEED, str(log2)),
                                 ex.make_batches(P, batch_size=5))
    np.testing.assert_array_equal(out1, out2)
    c1, c2 = setups_per_pid(log1), setups_per_pid(log2)
    assert all(c == 1 for c in c1.values()) and all(c == 1 for c in c2.values())
    assert set(c2) & set(c1)  # the same processes served the second call
    assert set(Path(tempfile.gettempdir()).glob(mine)) <= before  # removed


def test_context_files_of_dead_callers_are_removed(tmp_path):
    tmp = Path(tempfile.gettempdir())
    dead = subprocess_pid_that_exited()
    stale = tmp / f"probegrid-context-{dead}-test.pickle"
    mine = tmp / f"probegrid-context-{os.getpid()}-test.pickle"
    stale.write_bytes(b"x")
    mine.write_bytes(b"x")
    try:
        with ex.LocalExecutor(1) as executor:
            run_all(executor, NoiseContext(SEED, str(tmp_path)), ex.make_batches(4, batch_size=4))
        assert not stale.exists()  # its caller is gone
        assert mine.exists()  # a running caller's file stays
    finally:
        stale.unlink(missing_ok=True)
        mine.unlink(missing_ok=True)


def subprocess_pid_that_exited() -> int:
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


_ORPHAN_SCRIPT = """
import os, sys, time
from probegrid.bake import executors as ex

class Ctx:
    def setup(self):
        return None

def task(state, batch):
    time.sleep(0.5)
    return os.getpid()

if __name__ == "__main__":
    with ex.LocalExecutor(2) as pool:
        for _, pid in pool.map(task, Ctx(), ex.make_batches(400, batch_size=1)):
            print(pid, flush=True)
"""


def test_workers_exit_when_their_caller_is_killed(tmp_path):
    """SIGKILL of the process that owns a LocalExecutor leaves no worker running (they watch it)."""
    import signal
    import subprocess
    import sys

    script = tmp_path / "orphans.py"
    script.write_text(_ORPHAN_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True,
                            cwd=Path(__file__).resolve().parents[1])
    workers: set[int] = set()
    while len(workers) < 2:  # both workers have run a task
        line = proc.stdout.readline()
        assert line, "the script ended early"
        workers.add(int(line))
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    proc.stdout.close()
    deadline = time.time() + 10
    alive = set(workers)
    while alive and time.time() < deadline:
        for pid in list(alive):
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                alive.discard(pid)
        time.sleep(0.1)
    assert not alive, f"workers {alive} outlived their caller"


def modules_task(state: dict, batch: np.ndarray) -> dict:
    import sys

    return {"pid": os.getpid(), "has": "colorsys" in sys.modules}


def test_started_processes_import_the_preload_before_any_task(tmp_path):
    """start() brings every process up at once (before any map) with the preload modules
    imported; map then runs on those processes."""
    import multiprocessing

    before = {p.pid for p in multiprocessing.active_children()}  # (other tests' processes)
    with ex.LocalExecutor(2, preload=("colorsys",)) as executor:
        pool = executor.start()
        assert executor.start() is pool  # once
        deadline = time.monotonic() + 60
        started: set[int] = set()
        while len(started) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
            started = {p.pid for p in multiprocessing.active_children()} - before
        assert len(started) == 2
        out = [r for _, r in executor.map(modules_task, NoiseContext(SEED, str(tmp_path)),
                                          ex.make_batches(6, batch_size=1))]
    assert all(r["has"] for r in out)
    assert {r["pid"] for r in out} <= started
    # without a preload a spawned process imports nothing extra (a fork server keeps what it
    # preloaded for every later pool of this process)
    with ex.LocalExecutor(1, start_method="spawn") as executor:
        out = [r for _, r in executor.map(modules_task, NoiseContext(SEED, str(tmp_path)),
                                          ex.make_batches(2, batch_size=1))]
    assert not any(r["has"] for r in out)
