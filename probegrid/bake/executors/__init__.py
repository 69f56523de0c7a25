"""Running a function over batches of probes: in process, on local processes, or on Dask.

One interface (:class:`Executor`, :mod:`.base`) and one module per implementation:

* :class:`InlineExecutor` (:mod:`.inline`) -- the calling process, one batch at a time (tests,
  debugging).
* :class:`LocalExecutor` (:mod:`.local`) -- a ``concurrent.futures.ProcessPoolExecutor`` of
  ``workers`` processes (default: every core the process may use), started with
  ``forkserver`` (``spawn`` where there is none).
* :class:`DaskExecutor` (:mod:`.dask`, the one Dask importer) -- an existing
  ``dask.distributed`` cluster, by scheduler address.

:func:`make_executor` picks one from the CLI's ``--workers`` / ``--scheduler``. Importing this
package is cheap (numpy and the standard library; no numba, Embree, pydantic or Dask): a bake
starts its worker processes before it loads the rest of the library.
"""

from __future__ import annotations

from collections.abc import Sequence

from probegrid.bake.executors.base import (
    Executor,
    ExecutorError,
    Progress,
    WorkerContext,
    make_batches,
    probe_rng,
)
from probegrid.bake.executors.dask import DaskExecutor
from probegrid.bake.executors.inline import InlineExecutor
from probegrid.bake.executors.local import LocalExecutor, default_workers

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
