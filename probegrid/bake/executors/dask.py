"""The Dask executor: batches on an existing ``dask.distributed`` cluster, by scheduler address.

The one module of the project that imports Dask, and only when a :class:`DaskExecutor` is made
(``distributed`` takes 0.4 s to import; local worker processes import the executors without it).

The worker context goes to the workers once per ``map`` call, as the result of a task (so a
worker lost at any moment, its copy with it, costs a recomputation, never the bake); a worker
plugin installed on every worker holds a lock and a cache keyed by the call, so ``setup()`` runs
once per worker process even when the worker has several threads (the state is then shared by
them and the task function must treat it as read-only). The cache is dropped when the call ends.
Workers may run on other machines: the executor does not share files with the caller.
"""

from __future__ import annotations

import contextlib
import functools
import threading
import uuid
from collections.abc import Iterable, Iterator
from typing import TYPE_CHECKING, Any, ClassVar, Final, TypeVar

from numpy.typing import ArrayLike

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
from probegrid.errors import ExecutorError

if TYPE_CHECKING:
    import distributed

__all__ = ["DASK_PLUGIN_NAME", "DaskExecutor"]

R = TypeVar("R")

DASK_PLUGIN_NAME: Final = "probegrid-worker-state"


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
                         f"tcp://HOST:PORT ({first_line(exc)})") from None
    if scheme not in ("tcp", "tls", "ws", "wss", "ucx") or not host or not 0 < port < 65536:
        raise ValueError(f"--scheduler {address!r} is not a Dask address such as tcp://HOST:PORT")




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

    (Local worker processes import the executors; ``distributed`` takes 0.4 s to import.) Dask
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


def _context(context: WorkerContext[Any]) -> WorkerContext[Any]:
    """The map call's context, as the result of a task (recomputed if its worker is lost)."""
    return context


def _dask_forget(token: str, dask_worker: Any = None) -> None:
    plugin = dask_worker.plugins.get(DASK_PLUGIN_NAME) if dask_worker is not None else None
    if plugin is not None:
        plugin.states.forget(token)


class DaskExecutor(Executor):
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
    retries : int
        Times a task that raised is run again (``client.submit(retries=...)``; tasks are
        idempotent: a batch's result depends only on the context and the batch, and a block
        whose records were lost with a worker is traced again). A task whose worker is lost is
        run again by the scheduler itself.

    Raises :class:`ExecutorError` (one line) when the scheduler cannot be reached or has no
    workers. Workers need probegrid (and whatever ``fn`` imports) installed.
    """

    #: Workers may be on other machines: grid-sized arrays travel with the context.
    shares_files: ClassVar[bool] = False

    def __init__(
        self,
        scheduler: str | distributed.Client,
        *,
        timeout: float = 10.0,
        max_in_flight_per_worker: int = 2,
        retries: int = 2,
    ) -> None:
        import distributed

        check_in_flight(max_in_flight_per_worker)
        if not (isinstance(timeout, (int, float)) and timeout > 0):
            raise ValueError(f"timeout must be a positive number of seconds, got {timeout!r}")
        self._per_worker = int(max_in_flight_per_worker)
        if not (isinstance(retries, int) and retries >= 0):
            raise ValueError(f"retries must be a non-negative integer, got {retries!r}")
        self._retries = retries
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
                    f"cannot connect to the Dask scheduler at {scheduler!r}: {first_line(exc)}"
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
                f"the Dask cluster at {self._address} is not usable: {first_line(exc)}"
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
        todo, _ = checked_work(fn, context, batches)
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
        # The context is a task's result, not scattered data: a worker lost at any moment takes
        # its copy with it and the scheduler computes it again from the task, where a scattered
        # copy would be gone for good (and a broadcast to a worker that just died waits
        # forever).
        try:
            ctx_future = client.submit(_context, context, key=f"probegrid-context-{token}",
                                       pure=False, retries=self._retries)
        except Exception as exc:
            raise ExecutorError(f"cannot send the worker context to {where}: "
                                f"{first_line(exc)}") from exc

        # as_completed on the client's loop (distributed.wait would need a *default* client)
        finished = distributed.as_completed(loop=client.loop, raise_errors=False)

        def submit(order: int, batch: Batch) -> distributed.Future:
            fut = client.submit(
                _dask_task, fn, token, ctx_future, batch, key=f"probegrid-{token}-{order}",
                pure=False, retries=self._retries,
            )
            finished.add(fut)
            return fut

        def wait_first(futs: list[distributed.Future]) -> list[distributed.Future]:
            return [next(finished), *finished.next_batch(block=False)]

        pipeline: Pipeline[R] = Pipeline(
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
