"""The inline executor: every batch in the calling process, in order (tests, debugging).

``setup()`` runs once per :meth:`~probegrid.bake.executors.base.Executor.map` call in the
caller, on a pickled copy of the context (with ``check_pickle``), so that a context or task
function that would not survive the trip to a worker process fails here too.
"""

from __future__ import annotations

import concurrent.futures as cf
import pickle
from collections.abc import Iterable, Iterator
from typing import Any, ClassVar, TypeVar

from numpy.typing import ArrayLike

from probegrid.bake.executors.base import (
    Batch,
    Executor,
    Pipeline,
    ProgressFn,
    TaskFn,
    WorkerContext,
    as_batches,
    check_context,
    check_picklable,
)

__all__ = ["InlineExecutor"]

R = TypeVar("R")


class InlineExecutor(Executor):
    """Runs every batch in the calling process, in order (for tests and debugging).

    Parameters
    ----------
    check_pickle : bool
        Run on a pickled copy of the context and require ``fn`` to pickle, as the other
        executors do, so that a bake that works inline also works on workers.
    """


    shares_files: ClassVar[bool] = True

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
        check_context(context)
        todo = as_batches(batches)
        if self._check_pickle:
            check_picklable(fn, "task function")
            context = pickle.loads(check_picklable(context, "worker context"))
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

        pipeline: Pipeline[R] = Pipeline(
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
