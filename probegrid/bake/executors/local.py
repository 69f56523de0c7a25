"""The local executor: a pool of worker processes on this machine.

:class:`LocalExecutor` runs batches on a ``concurrent.futures.ProcessPoolExecutor`` of
``workers`` processes (default: every core the process may use, :func:`default_workers`),
started with ``forkserver`` (``spawn`` where there is none), so no worker inherits the caller's
threads or open files.

The processes outlive ``map`` calls (until :meth:`LocalExecutor.close`); each call writes its
pickled context to a temporary file and tags its tasks with a token, and a process runs
``setup()`` on its first task of a new token. The state sits in a per-process slot of this
module (the one piece of process-global state of the executors: a task function can only find
per-process state through one). A worker ends itself when the process that started the pool is
gone (:func:`_exit_with_caller`).
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
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, ClassVar, Final, TypeVar

import numpy as np
from numpy.typing import ArrayLike

from probegrid._machine import available_cores
from probegrid._types import StartMethod
from probegrid.bake.executors.base import (
    Batch,
    Executor,
    Pipeline,
    ProgressFn,
    TaskFn,
    WorkerContext,
    check_in_flight,
    checked_work,
    first_line,
)

__all__ = ["START_METHODS", "LocalExecutor", "default_workers", "stop_fork_server"]

R = TypeVar("R")

START_METHODS: Final[tuple[str, ...]] = ("forkserver", "spawn")


def stop_fork_server() -> None:
    """Stop this process's multiprocessing fork server, if one runs: :class:`LocalExecutor`
    starts its workers from one that has imported the bake (Embree, numba: ~300 MB), and it
    outlives the executor, which only stops the workers. Nothing else of this process uses it;
    a later bake would start a new one."""
    from multiprocessing import forkserver

    server = getattr(forkserver, "_forkserver", None)
    stop = getattr(server, "_stop", None)  # (CPython's own, since 3.8)
    if server is not None and stop is not None and \
            getattr(server, "_forkserver_pid", None) is not None:
        stop()


def default_workers() -> int:
    """Cores this process may run on (:func:`probegrid._machine.available_cores`), at least 1."""
    return available_cores()


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
        raise RuntimeError(f"setup() failed in the worker: {first_line(slot.error)}")
    return fn(slot.state, batch)


class LocalExecutor(Executor):
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

    shares_files: ClassVar[bool] = True

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
        check_in_flight(max_in_flight_per_worker)
        self._workers = int(workers)
        self._start_method = start_method
        self._per_worker = int(max_in_flight_per_worker)
        self._preload = tuple(str(m) for m in preload)
        self._pool: cf.ProcessPoolExecutor | None = None
        self._starting: threading.Thread | None = None
        self._asked: list[cf.Future[int]] = []  # (the first task of each process)

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
        todo, payload = checked_work(fn, context, batches)
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

        pipeline: Pipeline[R] = Pipeline(
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

            asked = self._asked = []

            def ask() -> None:
                with contextlib.suppress(RuntimeError):  # (closed before they started)
                    for _ in range(self._workers):  # one task each: every process starts now
                        asked.append(pool.submit(os.getpid))

            self._starting = threading.Thread(target=ask, name="probegrid-start-workers",
                                              daemon=True)
            self._starting.start()
            self._pool = pool
        return self._pool

    def wait_started(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for every worker process to run (their fork server's
        ``preload`` done: on a machine's first bake, the compiling of the kernels); returns
        whether they all do. Starts them if :meth:`start` has not."""
        self.start()
        starting = self._starting
        if starting is not None:
            starting.join(timeout)
            if starting.is_alive():
                return False
        pending = cf.wait(self._asked, timeout=timeout).not_done
        return not pending

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
