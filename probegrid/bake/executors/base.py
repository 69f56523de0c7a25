"""The executor interface: run ``fn(state, batch)`` over batches of probes, somewhere.

The bake splits the probes into batches (:func:`make_batches`), and an executor runs
``fn(state, batch)`` for each batch on some worker and streams ``(batch, result)`` back to the
caller, which writes the result into the grid store. Every executor derives from
:class:`Executor` and declares its capabilities there (:attr:`Executor.shares_files`); the
implementations live one per module beside this one (``inline``, ``local``, ``dask``).

Per-process state
-----------------
Work that must happen once per process -- loading the scene, building the Embree BVH -- lives in
a :class:`WorkerContext`: a picklable object whose ``setup()`` returns the per-process *state*.
For each :meth:`Executor.map` call every worker process unpickles the context and calls
``setup()`` exactly once, before its first batch of that call, and passes the state to every
batch it runs: ``fn(state, batch)``. How each executor keeps that promise is told in its module.

Flow control and determinism
----------------------------
At most ``max_in_flight_per_worker`` (default 2) batches per worker slot are submitted and not
yet handed back (:class:`Pipeline`), so memory is bounded by a couple of batches per worker,
not by the grid. Results come back as they complete (the order varies); they must be written by
probe index, and ``fn`` must draw its randomness from the probe indices (:func:`probe_rng`),
never from the batch or the worker. Then the bytes of a bake do not depend on the executor, the
number of workers or the batch size. A task that raises ends the map with an
:class:`ExecutorError` naming the batch and the original exception (chained as ``__cause__``;
the worker's traceback is kept).
"""

from __future__ import annotations

import abc
import pickle
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Generic, Protocol, Self, TypeVar, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from probegrid.errors import ExecutorError

__all__ = [
    "Batch",
    "Executor",
    "ExecutorError",
    "Pipeline",
    "Progress",
    "ProgressFn",
    "TaskFn",
    "WorkerContext",
    "as_batches",
    "batch_label",
    "check_context",
    "check_in_flight",
    "check_picklable",
    "checked_work",
    "first_line",
    "make_batches",
    "probe_rng",
]

R = TypeVar("R")
S = TypeVar("S")
Batch = NDArray[np.int64]
TaskFn = Callable[[Any, Batch], R]


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


class Executor(abc.ABC):
    """Runs ``fn(state, batch)`` over batches; see the module docstring.

    Capabilities are declared on the class, so that a caller reads them instead of probing
    the executor it was given:

    * :attr:`shares_files` -- the tasks run on the caller's machine and can read its files: a
      context may then name files (e.g. memory-mappable ``.npy`` arrays) instead of carrying
      the data. False (the safe choice) unless an executor says otherwise.
    """

    #: Tasks run on the caller's machine and can read its files.
    shares_files: ClassVar[bool] = False

    @property
    @abc.abstractmethod
    def workers(self) -> int:
        """Number of batches that can run at once (processes, or threads of a Dask cluster)."""

    @property
    @abc.abstractmethod
    def description(self) -> str:
        """Where the work runs, in words (for logs and progress bars)."""

    @abc.abstractmethod
    def map(
        self,
        fn: TaskFn[R],
        context: WorkerContext[Any],
        batches: Iterable[ArrayLike],
        *,
        progress: ProgressFn | None = None,
    ) -> Iterator[tuple[Batch, R]]:
        """Yield ``(batch, fn(state, batch))`` for every batch, in order of completion."""

    @abc.abstractmethod
    def start(self) -> object:
        """Get the workers ready now, so that their start-up overlaps the caller's own work
        (:meth:`map` does it otherwise)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the executor's resources."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------------- batches
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


def as_batches(batches: Iterable[ArrayLike]) -> list[Batch]:
    """The batches as 1-D int64 arrays (ValueError for anything else)."""
    out = []
    for b in batches:
        a = np.asarray(b)
        if a.ndim != 1 or (a.size and not np.issubdtype(a.dtype, np.integer)):
            raise ValueError(f"each batch must be a 1-D integer array, got {a.dtype} {a.shape}")
        out.append(a.astype(np.int64, copy=False))
    return out


def batch_label(batch: Batch) -> str:
    """A batch in words, for error messages."""
    if batch.size == 0:
        return "an empty batch"
    return f"the batch of {batch.size} probes {batch.min()}..{batch.max()}"


def first_line(exc: BaseException) -> str:
    """An exception as one line: its type and the first line of its message."""
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def check_picklable(obj: Any, what: str) -> bytes:
    """``obj`` pickled, or a one-line ValueError naming ``what`` when it cannot be."""
    try:
        return pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:  # pickle raises many types (PicklingError, TypeError, ...)
        reason = first_line(exc)
        raise ValueError(f"the {what} must be picklable to run on workers: {reason}") from exc


def check_context(context: object) -> None:
    """Refuse a context without a ``setup()`` method (TypeError)."""
    if not callable(getattr(context, "setup", None)):
        raise TypeError(
            f"context must be a WorkerContext (an object with a setup() method), "
            f"got {type(context).__name__}"
        )


def checked_work(
    fn: TaskFn[Any], context: WorkerContext[Any], batches: Iterable[ArrayLike]
) -> tuple[list[Batch], bytes]:
    """Check a ``map`` call bound for worker processes: the batches, and that both pickle.

    Returns the batches as int64 arrays and the pickled context.
    """
    check_context(context)
    todo = as_batches(batches)
    check_picklable(fn, "task function")
    return todo, check_picklable(context, "worker context")


def check_in_flight(n: int) -> None:
    """Refuse a ``max_in_flight_per_worker`` that is not a positive integer (ValueError)."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"max_in_flight_per_worker must be a positive integer, got {n!r}")


class Pipeline(Generic[R]):
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
                            f"{batch_label(batch)} failed on {self._where}: {first_line(exc)}"
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


