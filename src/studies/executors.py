"""Where a study's tasks run: a pool of local worker processes, or a Dask cluster.

Both offer ``submit(function, *args)`` returning a future and ``as_completed(futures)``; a task
is a plain function of plain data (:func:`studies.tasks.run_task`), so the executor is swappable
and the same seed gives the same result on either.

* :class:`LocalPool`: ``concurrent.futures.ProcessPoolExecutor`` with one worker per core by
  default (processes started fresh, not forked, so no state leaks between the runner and them).
* :class:`DaskCluster`: a ``distributed.Client`` connected to a running scheduler (``dask
  scheduler`` and ``dask worker`` on the lab's machines, or a Slurm allocation through
  ``dask-jobqueue``; see the README), or to a ``distributed.LocalCluster`` it starts itself.
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import os
import signal
import sys
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from typing import Any, Protocol

__all__ = ["DaskCluster", "Executor", "LocalPool"]


class Executor(Protocol):
    """What the study runner needs from an executor."""

    #: How many tasks run at once (for the progress display).
    workers: int

    def submit(self, function: Callable[..., Any], *args: Any) -> Any:
        """Run ``function(*args)`` somewhere; a future of its result."""

    def as_completed(self, futures: Iterable[Any]) -> Iterator[Any]:
        """The futures as they complete."""

    def close(self) -> None:
        """Release the workers."""


def _die_with_parent() -> None:
    # In each worker, first thing: a study stopped by SIGKILL must not leave workers finishing
    # runs behind its back (its next start would find them half done or done twice).
    # PR_SET_PDEATHSIG (1) is Linux's; elsewhere workers end when they next ask for work.
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)


class LocalPool:
    """``workers`` local processes (default: one per core), which die with this process."""

    def __init__(self, workers: int | None = None) -> None:
        self.workers = workers or os.cpu_count() or 1
        self._pool = ProcessPoolExecutor(
            max_workers=self.workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_die_with_parent if sys.platform.startswith("linux") else None,
        )

    def submit(self, function: Callable[..., Any], *args: Any) -> Future[Any]:
        """Run ``function(*args)`` in a worker process."""
        return self._pool.submit(function, *args)

    def as_completed(self, futures: Iterable[Future[Any]]) -> Iterator[Future[Any]]:
        """The futures as they complete."""
        return as_completed(list(futures))

    def close(self) -> None:
        """Stop the workers (running tasks are abandoned)."""
        self._pool.shutdown(wait=False, cancel_futures=True)


class DaskCluster:
    """A Dask ``distributed`` cluster: the scheduler at ``address``, or a local cluster of
    ``workers`` processes when no address is given."""

    def __init__(self, address: str | None = None, *, workers: int | None = None) -> None:
        from distributed import Client, LocalCluster

        self._cluster = None
        if address is None:
            self._cluster = LocalCluster(
                n_workers=workers or os.cpu_count() or 1,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
            )
            address = self._cluster.scheduler_address
        self.client = Client(address)
        info = self.client.scheduler_info()
        self.workers = max(1, sum(w.get("nthreads", 1) for w in info["workers"].values()))

    def submit(self, function: Callable[..., Any], *args: Any) -> Any:
        """Run ``function(*args)`` on a worker (never cached: a task writes files)."""
        return self.client.submit(function, *args, pure=False)

    def as_completed(self, futures: Iterable[Any]) -> Iterator[Any]:
        """The futures as they complete."""
        from distributed import as_completed as dask_as_completed

        return iter(dask_as_completed(list(futures)))

    def close(self) -> None:
        """Disconnect (and stop the local cluster if this started one)."""
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()
