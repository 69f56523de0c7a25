"""Running a function over batches of probes: in process, on local processes, or on Dask.

The bake splits the probes into batches (:func:`make_batches`), and an executor runs
``fn(state, batch)`` for each batch on some worker and streams ``(batch, result)`` back to the
caller, which writes the result into the grid store. Three executors share one interface
(:class:`Executor`):

* :class:`InlineExecutor` -- the calling process, one batch at a time (tests, debugging).
* :class:`LocalExecutor` -- a ``concurrent.futures.ProcessPoolExecutor`` of ``workers`` processes
  (default: every core the process may use), started with ``forkserver`` (``spawn`` where there
  is none), so no worker inherits the caller's threads or open files.
* :class:`DaskExecutor` -- an existing ``dask.distributed`` cluster, by scheduler address.

Per-process state
-----------------
Work that must happen once per process -- loading the scene, building the Embree BVH -- lives in
a :class:`WorkerContext`: a picklable object whose ``setup()`` returns the per-process *state*.
For each :meth:`Executor.map` call every worker process unpickles the context and calls
``setup()`` exactly once, before its first batch of that call, and passes the state to every
batch it runs: ``fn(state, batch)``.

* Local: the processes outlive ``map`` calls (until :meth:`LocalExecutor.close`); each call
  writes its pickled context to a temporary file and tags its tasks with a token, and a process
  runs ``setup()`` on its first task of a new token. The state sits in a per-process slot of
  this module (the one piece of process-global state here: a task function can only find
  per-process state through one).
* Dask: the context is scattered (broadcast) to the workers once; a worker plugin installed on
  every worker holds a lock and a cache keyed by the ``map`` call, so ``setup()`` runs once per
  worker process even when the worker has several threads (the state is then shared by them and
  ``fn`` must treat it as read-only). The cache is dropped when the ``map`` call ends.
* Inline: ``setup()`` runs once per ``map`` call in the caller, on a pickled copy of the context,
  so a context or function that would not survive the trip to a worker fails here too.

Flow control and determinism
----------------------------
At most ``max_in_flight_per_worker`` (default 2) batches per worker slot are submitted and not
yet handed back, so memory is bounded by a couple of batches per worker, not by the grid.
Results come back as they complete (the order varies); they must be written by probe index, and
``fn`` must draw its randomness from the probe indices (:func:`probe_rng`), never from the batch
or the worker. Then the bytes of a bake do not depend on the executor, the number of workers or
the batch size. A task that raises ends the map with an :class:`ExecutorError` naming the batch
and the original exception (chained as ``__cause__``; the worker's traceback is kept).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import functools
import multiprocessing
import os
import pickle
import select
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import (
    TYPE_CHECKING,
    Any,
    Final,
    Generic,
    Protocol,
    Self,
    TypeVar,
    runtime_checkable,
)

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid._types import StartMethod
from probegrid.errors import ExecutorError

if TYPE_CHECKING:
    import distributed

__all__ = [
    "DaskExecutor",
    "Executor",
    "ExecutorError",
    "InlineExecutor",
    "LocalExecutor",
    "Progress",
    "WorkerContext",
    "default_workers",
    "make_batches",
    "make_executor",
    "probe_rng",
]

R = TypeVar("R")
S = TypeVar("S")
Batch = NDArray[np.int64]
TaskFn = Callable[[Any, Batch], R]

DASK_PLUGIN_NAME: Final = "probegrid-worker-state"
START_METHODS: Final[tuple[str, ...]] = ("forkserver", "spawn")


@runtime_checkable
class WorkerContext(Protocol[S]):
    """Picklable description of the per-process state a task needs.

    ``setup()`` runs once per worker process per :meth:`Executor.map` call and returns the state
    passed as the first argument of every task in that process. Keep the context small (paths,
    settings, arrays the tasks need) and do the expensive work in ``setup``.
    """

    def setup(self) -> S:
        """Build the per-process state (e.g. load the scene and build the BVH)."""
        ...


@dataclass(frozen=True)
class Progress:
    """Progress of a :meth:`Executor.map` call, reported after every completed batch.

    Attributes
    ----------
    batches_done, batches_total : int
    probes_done, probes_total : int
    elapsed : float
        Seconds since the map started.
    """

    batches_done: int
    batches_total: int
    probes_done: int
    probes_total: int
    elapsed: float

    @property
    def eta(self) -> float | None:
        """Estimated seconds left (by probes done so far), or None before the first batch."""
        if self.probes_done == 0:
            return None
        return self.elapsed * (self.probes_total - self.probes_done) / self.probes_done


ProgressFn = Callable[[Progress], None]


@runtime_checkable
class Executor(Protocol):
    """Runs ``fn(state, batch)`` over batches; see the module docstring.

    An executor whose tasks run on the caller's machine has ``shares_files = True``: a context
    may then name files (e.g. memory-mappable ``.npy`` arrays) instead of carrying the data.
    """

    @property
    def workers(self) -> int:
        """Number of batches that can run at once (processes, or threads of a Dask cluster)."""
        ...

    @property
    def description(self) -> str:
        """Where the work runs, in words (for logs and progress bars)."""
        ...

    def map(
        self,
        fn: TaskFn[R],
        context: WorkerContext[Any],
        batches: Iterable[ArrayLike],
        *,
        progress: ProgressFn | None = None,
    ) -> Iterator[tuple[Batch, R]]:
        """Yield ``(batch, fn(state, batch))`` for every batch, in order of completion."""
        ...

    def start(self) -> object:
        """Get the workers ready now, so that their start-up overlaps the caller's own work
        (:meth:`map` does it otherwise)."""
        ...

    def close(self) -> None:
        """Release the executor's resources."""
        ...


# ---------------------------------------------------------------------------- helpers
def default_workers() -> int:
    """Cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def make_batches(
    probes: ArrayLike | int, *, batch_size: int, done: ArrayLike | None = None
) -> list[Batch]:
    """Split probes into batches of at most ``batch_size``.

    Parameters
    ----------
    probes : int or (N,) int
        An int ``P``: the fixed blocks ``[s, s + batch_size)`` of ``0..P-1``, minus the probes
        marked in ``done`` (blocks left empty are dropped). This partition is the same on every
        run, so a resumed bake (``done = StoreWriter.done``, written a whole batch at a time)
        recomputes exactly the batches an uninterrupted bake would have. An array: consecutive
        chunks of those indices, in the given order.
    batch_size : int >= 1
    done : (P,) bool, optional
        Probes already finished (only with an int ``probes``).

    Returns
    -------
    list of (B,) int64 arrays

    Notes
    -----
    Executors never change a batch, but a task whose per-probe arithmetic depends on the batch
    size (a BLAS product over the batch rounds differently for 1 row and for 8) ties the bits to
    the partition; keep per-probe results independent of the batch, or keep the partition fixed.
    """
    if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) or (
        batch_size < 1
    ):
        raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}")
    if isinstance(probes, (int, np.integer)) and not isinstance(probes, bool):
        if probes < 0:
            raise ValueError(f"the number of probes must be >= 0, got {probes}")
        blocks = [
            np.arange(s, min(s + batch_size, int(probes)), dtype=np.int64)
            for s in range(0, int(probes), batch_size)
        ]
        if done is None:
            return blocks
        mask = np.asarray(done)
        if mask.dtype != np.bool_ or mask.shape != (int(probes),):
            raise ValueError(f"done must be a ({probes},) bool mask, got {mask.dtype} {mask.shape}")
        kept = (b[~mask[b]] for b in blocks)
        return [b for b in kept if b.size]
    if done is not None:
        raise ValueError("done is only accepted with a probe count, not with explicit indices")
    idx = np.asarray(probes)
    if idx.ndim != 1 or (idx.size and not np.issubdtype(idx.dtype, np.integer)):
        raise ValueError(f"indices must be a 1-D integer array, got {idx.dtype} {idx.shape}")
    idx = idx.astype(np.int64)
    return [idx[s : s + batch_size] for s in range(0, idx.size, batch_size)]


def probe_rng(seed: int, index: int) -> np.random.Generator:
    """The random generator of one probe: ``SeedSequence(seed, spawn_key=(index,))``.

    This is exactly ``SeedSequence(seed).spawn(index + 1)[index]``: independent streams per
    probe that depend only on the bake seed and the probe's linear index, never on the batch,
    the worker or the executor.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 0:
        raise ValueError(f"probe index must be a non-negative integer, got {index!r}")
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(index),)))


def _as_batches(batches: Iterable[ArrayLike]) -> list[Batch]:
    out = []
    for b in batches:
        a = np.asarray(b)
        if a.ndim != 1 or (a.size and not np.issubdtype(a.dtype, np.integer)):
            raise ValueError(f"each batch must be a 1-D integer array, got {a.dtype} {a.shape}")
        out.append(a.astype(np.int64, copy=False))
    return out


def _batch_label(batch: Batch) -> str:
    if batch.size == 0:
        return "an empty batch"
    return f"the batch of {batch.size} probes {batch.min()}..{batch.max()}"


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def _check_picklable(obj: Any, what: str) -> bytes:
    try:
        return pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:  # pickle raises many types (PicklingError, TypeError, ...)
        reason = _first_line(exc)
        raise ValueError(f"the {what} must be picklable to run on workers: {reason}") from exc


class _Pipeline(Generic[R]):
    """Keeps at most ``limit`` batches submitted and not yet handed back, yielding as they finish.

    ``submit(batch) -> future``; ``wait_first(futures) -> done futures``; ``fetch(future)`` returns
    the result or raises the task's exception; ``cancel(futures)`` abandons the rest.
    """

    def __init__(
        self,
        *,
        submit: Callable[[int, Batch], Any],
        wait_first: Callable[[list[Any]], Iterable[Any]],
        fetch: Callable[[Any], R],
        cancel: Callable[[list[Any]], None],
        limit: int,
        where: str,
    ) -> None:
        self._submit, self._wait_first, self._fetch, self._cancel = submit, wait_first, fetch, cancel
        self._limit = max(1, limit)
        self._where = where

    def run(
        self, batches: Sequence[Batch], progress: ProgressFn | None
    ) -> Iterator[tuple[Batch, R]]:
        t0 = time.perf_counter()
        total = sum(int(b.size) for b in batches)
        pending: dict[Any, tuple[int, Batch]] = {}
        queue = iter(enumerate(batches))
        n_done = probes_done = 0

        def fill() -> None:
            while len(pending) < self._limit:
                item = next(queue, None)
                if item is None:
                    return
                order, batch = item
                pending[self._submit(order, batch)] = (order, batch)

        try:
            fill()
            while pending:
                done = self._wait_first(list(pending))
                for fut in sorted(done, key=lambda f: pending[f][0]):
                    _, batch = pending.pop(fut)
                    try:
                        result = self._fetch(fut)
                    except Exception as exc:
                        raise ExecutorError(
                            f"{_batch_label(batch)} failed on {self._where}: {_first_line(exc)}"
                        ) from exc
                    n_done += 1
                    probes_done += int(batch.size)
                    if progress is not None:
                        progress(
                            Progress(
                                n_done, len(batches), probes_done, total, time.perf_counter() - t0
                            )
                        )
                    yield batch, result
                    del result  # hand the memory back before submitting more work
                fill()
        finally:
            if pending:
                self._cancel(list(pending))


# ---------------------------------------------------------------------------- inline
class InlineExecutor:
    """Runs every batch in the calling process, in order (for tests and debugging).

    Parameters
    ----------
    check_pickle : bool
        Run on a pickled copy of the context and require ``fn`` to pickle, as the other
        executors do, so that a bake that works inline also works on workers.
    """

    #: Tasks run on this machine and can read its files.
    shares_files = True

    def __init__(self, *, check_pickle: bool = True) -> None:
        self._check_pickle = check_pickle

    @property
    def workers(self) -> int:
        return 1

    @property
    def description(self) -> str:
        return "the calling process"

    def map(
        self,
        fn: TaskFn[R],
        context: WorkerContext[Any],
        batches: Iterable[ArrayLike],
        *,
        progress: ProgressFn | None = None,
    ) -> Iterator[tuple[Batch, R]]:
        """See :meth:`Executor.map`; ``setup()`` runs once, lazily, before the first batch."""
        _check_context(context)
        todo = _as_batches(batches)
        if self._check_pickle:
            _check_picklable(fn, "task function")
            context = pickle.loads(_check_picklable(context, "worker context"))
        return self._run(fn, context, todo, progress)

    def _run(
        self,
        fn: TaskFn[R],
        context: WorkerContext[Any],
        todo: list[Batch],
        progress: ProgressFn | None,
    ) -> Iterator[tuple[Batch, R]]:
        state: list[Any] = []

        def submit(order: int, batch: Batch) -> cf.Future[R]:
            fut: cf.Future[R] = cf.Future()
            try:
                if not state:
                    state.append(context.setup())
                fut.set_result(fn(state[0], batch))
            except Exception as exc:  # noqa: BLE001 - handed to the caller through the future
                fut.set_exception(exc)
            return fut

        pipeline: _Pipeline[R] = _Pipeline(
            submit=submit,
            wait_first=lambda futs: futs[:1],
            fetch=lambda fut: fut.result(),
            cancel=lambda futs: None,
            limit=1,
            where=self.description,
        )
        yield from pipeline.run(todo, progress)

    def start(self) -> None:
        """Nothing to start: batches run in the caller."""

    def close(self) -> None:
        """Nothing to release."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _check_context(context: object) -> None:
    if not callable(getattr(context, "setup", None)):
        raise TypeError(
            f"context must be a WorkerContext (an object with a setup() method), "
            f"got {type(context).__name__}"
        )


def _checked_work(
    fn: TaskFn[Any], context: WorkerContext[Any], batches: Iterable[ArrayLike]
) -> tuple[list[Batch], bytes]:
    """Check a ``map`` call bound for worker processes: the batches, and that both pickle.

    Returns the batches as int64 arrays and the pickled context.
    """
    _check_context(context)
    todo = _as_batches(batches)
    _check_picklable(fn, "task function")
    return todo, _check_picklable(context, "worker context")


# ---------------------------------------------------------------------------- local processes
class _ProcessSlot:
    """The state of the current ``map`` call in a local worker process (or its setup error)."""

    def __init__(self) -> None:
        self.token: str | None = None
        self.state: Any = None
        self.error: BaseException | None = None


@functools.cache
def _process_slot() -> _ProcessSlot:
    """This process's slot (one per worker process, holding the state of one ``map`` call)."""
    return _ProcessSlot()


def _local_task(token: str, context_file: str, fn: TaskFn[R], batch: Batch) -> R:
    """Run one batch in a worker process, building the state of map call ``token`` first if
    this process has not yet: unpickle the context from ``context_file`` and call ``setup()``
    (the previous call's state is dropped first). A setup failure is kept and raised by every
    task of that call, so the caller sees the real error."""
    slot = _process_slot()
    if slot.token != token:
        slot.token, slot.state, slot.error = token, None, None
        try:
            with open(context_file, "rb") as fh:
                slot.state = pickle.loads(fh.read()).setup()
        except Exception as exc:  # noqa: BLE001 - re-raised by every task of this call
            slot.error = exc
    if slot.error is not None:
        raise RuntimeError(f"setup() failed in the worker: {_first_line(slot.error)}")
    return fn(slot.state, batch)


class LocalExecutor:
    """Runs batches on a pool of local worker processes.

    Parameters
    ----------
    workers : int, optional
        Number of processes (default: :func:`default_workers`, every usable core).
    start_method : {"forkserver", "spawn"}, optional
        How processes start; default ``forkserver`` where available, else ``spawn``.
    max_in_flight_per_worker : int
        Batches submitted and not yet handed back, per process (default 2).
    preload : sequence of str
        Modules the processes import before their first task: with ``forkserver`` the fork
        server imports them once and every worker starts with them (when this process has not
        started its fork server yet); with ``spawn`` each worker imports them as it starts.

    The worker processes start with :meth:`start` (to overlap their start-up with the caller's
    own work), else with the first :meth:`map` call, and serve every later one
    until :meth:`close` (or the end of a ``with`` block), so a bake's stages do not each pay for
    starting processes, importing the library and building the BVH
    (:meth:`probegrid.raytrace.RayTracer.shared`). Each call's context travels once, as a
    temporary file each process reads before its first batch of the call and runs
    ``setup()`` on. A call that fails or is abandoned shuts the processes down (pending batches
    are cancelled); the next call starts new ones.
    """

    #: Tasks run on this machine and can read its files.
    shares_files = True

    def __init__(
        self,
        workers: int | None = None,
        *,
        start_method: StartMethod | None = None,
        max_in_flight_per_worker: int = 2,
        preload: Sequence[str] = (),
    ) -> None:
        if workers is None:
            workers = default_workers()
        if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
            raise ValueError(f"workers must be a positive integer, got {workers!r}")
        available = multiprocessing.get_all_start_methods()
        if start_method is None:
            start_method = "forkserver" if "forkserver" in available else "spawn"
        if start_method not in START_METHODS:
            raise ValueError(
                f"start_method must be one of {', '.join(START_METHODS)}, got {start_method!r}"
            )
        if start_method not in available:
            raise ValueError(f"start method {start_method!r} is not available on this platform")
        _check_in_flight(max_in_flight_per_worker)
        self._workers = int(workers)
        self._start_method = start_method
        self._per_worker = int(max_in_flight_per_worker)
        self._preload = tuple(str(m) for m in preload)
        self._pool: cf.ProcessPoolExecutor | None = None
        self._starting: threading.Thread | None = None

    @property
    def workers(self) -> int:
        return self._workers

    @property
    def description(self) -> str:
        return f"{self._workers} local worker process{'es' if self._workers > 1 else ''}"

    def map(
        self,
        fn: TaskFn[R],
        context: WorkerContext[Any],
        batches: Iterable[ArrayLike],
        *,
        progress: ProgressFn | None = None,
    ) -> Iterator[tuple[Batch, R]]:
        """See :meth:`Executor.map`."""
        todo, payload = _checked_work(fn, context, batches)
        return self._run(fn, payload, todo, progress)

    def _run(
        self, fn: TaskFn[R], payload: bytes, todo: list[Batch], progress: ProgressFn | None
    ) -> Iterator[tuple[Batch, R]]:
        if not todo:
            return
        pool = self._started()
        token = uuid.uuid4().hex
        _remove_stale_context_files()
        fd, context_file = tempfile.mkstemp(prefix=f"{_CONTEXT_PREFIX}{os.getpid()}-",
                                            suffix=".pickle")
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)

        def wait_first(futs: list[cf.Future[R]]) -> set[cf.Future[R]]:
            return cf.wait(futs, return_when=cf.FIRST_COMPLETED).done

        def fetch(fut: cf.Future[R]) -> R:
            try:
                return fut.result()
            except cf.process.BrokenProcessPool as exc:
                raise RuntimeError(
                    "a worker process died (killed, out of memory, or its setup() failed)"
                ) from exc

        def submit(order: int, batch: Batch) -> cf.Future[R]:
            try:
                return pool.submit(_local_task, token, context_file, fn, batch)
            except cf.process.BrokenProcessPool as exc:  # a worker died before this submit
                fut: cf.Future[R] = cf.Future()
                fut.set_exception(exc)  # surfaces through fetch like any other death
                return fut

        pipeline: _Pipeline[R] = _Pipeline(
            submit=submit,
            wait_first=wait_first,
            fetch=fetch,
            cancel=lambda futs: [f.cancel() for f in futs],
            limit=min(self._workers, len(todo)) * self._per_worker,
            where=self.description,
        )
        finished = False
        try:
            yield from pipeline.run(todo, progress)
            finished = True
        finally:
            if not finished:  # failed or abandoned: stop the processes, cancel what is pending
                self.close()
            os.unlink(context_file)

    def start(self) -> cf.ProcessPoolExecutor:
        """Start the worker processes now, unless they run already, and return the pool
        without waiting for them: a thread of this process asks for them, so that their
        start-up (the fork server's ``preload`` included) overlaps the caller's own work.
        :meth:`map` waits for them."""
        if self._pool is None:
            ctx = multiprocessing.get_context(self._start_method)
            if self._start_method == "forkserver" and self._preload:
                ctx.set_forkserver_preload(list(self._preload))  # (a running server keeps its)
            pool = cf.ProcessPoolExecutor(
                max_workers=self._workers,
                mp_context=ctx,
                initializer=_start_worker,
                initargs=(os.getpid(), self._preload),
            )

            def ask() -> None:
                with contextlib.suppress(RuntimeError):  # (closed before they started)
                    for _ in range(self._workers):  # one task each: every process starts now
                        pool.submit(os.getpid)

            self._starting = threading.Thread(target=ask, name="probegrid-start-workers",
                                              daemon=True)
            self._starting.start()
            self._pool = pool
        return self._pool

    def _started(self) -> cf.ProcessPoolExecutor:
        """The pool, once :meth:`start` has asked for every process."""
        pool = self.start()
        self._join_starting()
        return pool

    def _join_starting(self) -> None:
        """Wait for :meth:`start`'s thread (if one still runs) to have asked for every
        process."""
        if self._starting is not None:
            self._starting.join()
            self._starting = None

    def close(self) -> None:
        """Stop the worker processes (waits for running batches; cancels pending ones)."""
        self._join_starting()
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _start_worker(pid: int, preload: tuple[str, ...]) -> None:
    """Worker initializer: :func:`_exit_with_caller`, then import the ``preload`` modules."""
    import importlib

    _exit_with_caller(pid)
    for name in preload:
        importlib.import_module(name)


def _exit_with_caller(pid: int) -> None:
    """End this worker when the process that started the pool is gone.

    A caller killed with SIGKILL (or crashing) cannot stop its workers; without this they would
    run on, orphaned, and keep the forkserver and resource tracker alive. A daemon thread waits
    on a pidfd of the caller (Linux 5.3+; polling its pid every second elsewhere) and exits the
    worker at once when it dies.
    """

    def watch() -> None:
        try:
            fd = os.pidfd_open(pid)
        except (AttributeError, OSError):  # no pidfd here, or the caller is already gone
            fd = None
        if fd is not None:
            select.select([fd], [], [])
        else:
            while True:
                time.sleep(1.0)
                try:
                    os.kill(pid, 0)
                except ProcessLookupError:
                    break
                except PermissionError:
                    continue
        os._exit(1)

    threading.Thread(target=watch, name="probegrid-exit-with-caller", daemon=True).start()


def _check_scheduler_address(address: str) -> None:
    """Refuse an address that is not ``[tcp|tls|ws|wss|ucx]://HOST:PORT`` (or ``HOST:PORT``)
    before distributed.Client sees it (its failed construction would leave a client whose
    clean-up waits 20 s at exit)."""
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
        host, port = parse_host_port(location)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"--scheduler {address!r} is not a Dask address such as "
                         f"tcp://HOST:PORT ({_first_line(exc)})") from None
    if scheme not in ("tcp", "tls", "ws", "wss", "ucx") or not host or not 0 < port < 65536:
        raise ValueError(f"--scheduler {address!r} is not a Dask address such as tcp://HOST:PORT")


#: Temporary context files are named ``probegrid-context-<pid of the caller>-<random>.pickle``.
_CONTEXT_PREFIX = "probegrid-context-"


def _remove_stale_context_files() -> None:
    """Delete context files left by callers that no longer run (killed before cleaning up)."""
    for path in Path(tempfile.gettempdir()).glob(f"{_CONTEXT_PREFIX}*-*.pickle"):
        pid = path.name[len(_CONTEXT_PREFIX):].split("-", 1)[0]
        if not pid.isdigit():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            with contextlib.suppress(OSError):
                path.unlink()
        except OSError:  # alive but another user's: not ours to remove
            continue


def _check_in_flight(n: int) -> None:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"max_in_flight_per_worker must be a positive integer, got {n!r}")


# ---------------------------------------------------------------------------- dask
class _DaskStates:
    """Per-process state of the running ``map`` calls on one Dask worker, keyed by call token."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._states: dict[str, Any] = {}

    def state(self, token: str, context: WorkerContext[Any]) -> Any:
        """The state of map call ``token``, built by ``context.setup()`` on first use."""
        with self._lock:  # one setup() per process even with several worker threads
            if token not in self._states:
                self._states[token] = context.setup()
            return self._states[token]

    def forget(self, token: str | None = None) -> None:
        """Drop one call's state (or all of it)."""
        with self._lock:
            if token is None:
                self._states.clear()
            else:
                self._states.pop(token, None)

    def __getstate__(self) -> dict[str, Any]:
        return {}  # a fresh, empty holder on the worker

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__()  # type: ignore[misc]


@functools.cache
def _dask_plugin_type() -> type:
    """The worker plugin class, defined on first use so this module imports without Dask.

    (Local worker processes import this module; ``distributed`` takes 0.4 s to import.) Dask
    ships the instance to the workers with cloudpickle, class included.
    """
    from distributed import WorkerPlugin

    class ProbegridStatePlugin(WorkerPlugin):  # type: ignore[misc]
        """Holds the per-process state of probegrid ``map`` calls on a worker."""

        idempotent = True

        def __init__(self) -> None:
            self.states = _DaskStates()

        def teardown(self, worker: Any) -> None:
            self.states.forget()

    return ProbegridStatePlugin


def _dask_task(fn: TaskFn[R], token: str, context: WorkerContext[Any], batch: Batch) -> R:
    from distributed import get_worker

    plugin = get_worker().plugins.get(DASK_PLUGIN_NAME)
    if plugin is None:
        raise RuntimeError(f"the Dask worker lacks the {DASK_PLUGIN_NAME!r} plugin")
    return fn(plugin.states.state(token, context), batch)


def _dask_forget(token: str, dask_worker: Any = None) -> None:
    plugin = dask_worker.plugins.get(DASK_PLUGIN_NAME) if dask_worker is not None else None
    if plugin is not None:
        plugin.states.forget(token)


class DaskExecutor:
    """Runs batches on an existing Dask distributed cluster.

    Parameters
    ----------
    scheduler : str or distributed.Client
        Scheduler address (``tcp://HOST:PORT``, ``tls://...``) or a connected client (then the
        caller keeps ownership of it).
    timeout : float
        Seconds to wait for the scheduler, and for at least one worker to appear.
    max_in_flight_per_worker : int
        Batches submitted and not yet handed back, per worker thread (default 2).

    Raises :class:`ExecutorError` (one line) when the scheduler cannot be reached or has no
    workers. Workers need probegrid (and whatever ``fn`` imports) installed.
    """

    #: Workers may be on other machines: grid-sized arrays travel with the context.
    shares_files = False

    def __init__(
        self,
        scheduler: str | distributed.Client,
        *,
        timeout: float = 10.0,
        max_in_flight_per_worker: int = 2,
    ) -> None:
        import distributed

        _check_in_flight(max_in_flight_per_worker)
        if not (isinstance(timeout, (int, float)) and timeout > 0):
            raise ValueError(f"timeout must be a positive number of seconds, got {timeout!r}")
        self._per_worker = int(max_in_flight_per_worker)
        if isinstance(scheduler, distributed.Client):
            self._client, self._owns_client = scheduler, False
        elif isinstance(scheduler, str) and scheduler.strip():
            _check_scheduler_address(scheduler.strip())
            try:
                self._client = distributed.Client(
                    scheduler.strip(), timeout=timeout, set_as_default=False
                )
            except Exception as exc:  # noqa: BLE001 - OSError, TimeoutError, bad scheme, ...
                raise ExecutorError(
                    f"cannot connect to the Dask scheduler at {scheduler!r}: {_first_line(exc)}"
                ) from None
            self._owns_client = True
        else:
            raise ValueError(
                f"scheduler must be an address such as tcp://HOST:PORT or a distributed.Client, "
                f"got {scheduler!r}"
            )
        self._address = str(self._client.scheduler.address)
        try:
            self._client.wait_for_workers(1, timeout=timeout)
            self._client.register_plugin(_dask_plugin_type()(), name=DASK_PLUGIN_NAME)
        except Exception as exc:  # noqa: BLE001 - reported as one line
            self.close()
            raise ExecutorError(
                f"the Dask cluster at {self._address} is not usable: {_first_line(exc)}"
            ) from None

    @property
    def client(self) -> distributed.Client:
        """The Dask client."""
        return self._client

    @property
    def workers(self) -> int:
        """Worker threads across the cluster (at this moment)."""
        return max(1, sum(self._client.nthreads().values()))

    @property
    def description(self) -> str:
        nthreads = self._client.nthreads()
        return (
            f"the Dask cluster at {self._address} ({sum(nthreads.values())} threads on "
            f"{len(nthreads)} workers)"
        )

    def map(
        self,
        fn: TaskFn[R],
        context: WorkerContext[Any],
        batches: Iterable[ArrayLike],
        *,
        progress: ProgressFn | None = None,
    ) -> Iterator[tuple[Batch, R]]:
        """See :meth:`Executor.map`."""
        todo, _ = _checked_work(fn, context, batches)
        return self._run(fn, context, todo, progress)

    def _run(
        self,
        fn: TaskFn[R],
        context: WorkerContext[Any],
        todo: list[Batch],
        progress: ProgressFn | None,
    ) -> Iterator[tuple[Batch, R]]:
        import distributed

        if not todo:
            return
        client = self._client
        token = uuid.uuid4().hex
        where = f"the Dask cluster at {self._address}"
        try:
            ctx_future = client.scatter(context, broadcast=True, hash=False)
        except Exception as exc:
            raise ExecutorError(f"cannot send the worker context to {where}: "
                                f"{_first_line(exc)}") from exc

        # as_completed on the client's loop (distributed.wait would need a *default* client)
        finished = distributed.as_completed(loop=client.loop, raise_errors=False)

        def submit(order: int, batch: Batch) -> distributed.Future:
            fut = client.submit(
                _dask_task, fn, token, ctx_future, batch, key=f"probegrid-{token}-{order}",
                pure=False,
            )
            finished.add(fut)
            return fut

        def wait_first(futs: list[distributed.Future]) -> list[distributed.Future]:
            return [next(finished), *finished.next_batch(block=False)]

        pipeline: _Pipeline[R] = _Pipeline(
            submit=submit,
            wait_first=wait_first,
            fetch=lambda fut: fut.result(),
            cancel=lambda futs: client.cancel(futs),
            limit=self.workers * self._per_worker,
            where=where,
        )
        try:
            yield from pipeline.run(todo, progress)
        finally:
            # Best effort: the cluster may be gone, and the state is only memory on the workers.
            with contextlib.suppress(Exception):
                client.run(_dask_forget, token)

    def start(self) -> None:
        """Nothing to start: the cluster's workers run already (the client connected when
        this executor was made)."""

    def close(self) -> None:
        """Close the client if this executor opened it."""
        if self._owns_client:
            self._client.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def make_executor(
    *, workers: int | None = None, scheduler: str | None = None, preload: Sequence[str] = ()
) -> LocalExecutor | DaskExecutor:
    """The executor the CLI's ``--workers N`` / ``--scheduler ADDRESS`` ask for.

    A scheduler address gives a :class:`DaskExecutor` (``workers`` must then be None); otherwise a
    :class:`LocalExecutor` with ``workers`` processes (default every usable core) that import
    the ``preload`` modules as they start.
    """
    if scheduler is not None:
        if workers is not None:
            raise ValueError("give either workers (local processes) or a Dask scheduler, not both")
        return DaskExecutor(scheduler)
    return LocalExecutor(workers, preload=preload)
