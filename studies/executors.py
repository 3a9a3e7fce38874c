"""Where a study's tasks run: a pool of local worker processes, or a Dask cluster.

Both offer ``submit(function, *args)`` returning a future and ``as_completed(futures)``; a task
is a plain function of plain data (:func:`studies.tasks.run_task`), so the executor is swappable
and the same seed gives the same result on either.

* :class:`LocalPool`: ``concurrent.futures.ProcessPoolExecutor`` with one worker per core by
  default (processes started fresh, not forked, so no state leaks between the runner and them).
* :class:`DaskCluster`: a ``distributed.Client`` connected to a running scheduler (``dask
  scheduler`` and ``dask worker`` on the lab's machines, or a Slurm allocation through
  ``dask-jobqueue``; see the README), or to a ``distributed.LocalCluster`` it starts itself.

``result(future)`` is where an executor's own failures become the project's: a Dask scheduler
that cannot be reached or is lost mid-study raises :class:`SchedulerUnreachableError` or
:class:`SchedulerLostError` (one line naming its address), never a run's failure.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import multiprocessing
import os
import signal
import sys
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import CancelledError, Future, ProcessPoolExecutor, as_completed
from typing import Any, Final, Protocol

from minimize_surprise.errors import ClusterError

__all__ = [
    "CLOSE_TIMEOUT",
    "SCHEDULER_CONNECT_TIMEOUT",
    "DaskCluster",
    "Executor",
    "LocalPool",
    "SchedulerLostError",
    "SchedulerUnreachableError",
]

#: Seconds to reach a Dask scheduler. One on the lab's network answers in milliseconds, and Dask
#: retries a refused connection until then, so one still starting up is found; an address with
#: nothing behind it is reported after this rather than after Dask's default of 30 s.
SCHEDULER_CONNECT_TIMEOUT: Final = 5.0
#: Seconds to let the client say goodbye to its scheduler when the study ends: leaving at once
#: is harmless (the scheduler drops a client that vanished), waiting long for a lost one is not.
CLOSE_TIMEOUT: Final = 5.0
#: Client states in which it has no scheduler: it lost it and is trying again, or gave up.
_NO_SCHEDULER: Final = frozenset({"connecting", "closing", "closed", "failed"})
#: Why Dask cancels every future of a client that lost its scheduler.
_LOST_REASON: Final = "scheduler-connection-lost"


class SchedulerUnreachableError(ClusterError, ConnectionError):
    """No Dask scheduler answered at ``address`` within ``timeout`` seconds."""

    def __init__(self, address: str, timeout: float) -> None:
        self.address = address
        self.timeout = timeout
        super().__init__(
            f"no Dask scheduler answers at {address} within {timeout:g} s: "
            f"start `dask scheduler` there, or check the address given to --scheduler"
        )


class SchedulerLostError(ClusterError, ConnectionError):
    """The Dask scheduler at ``address`` went away mid-study (it was stopped, or its machine or
    the network to it failed). Every run it had not finished stays pending."""

    def __init__(self, address: str) -> None:
        self.address = address
        super().__init__(
            f"lost the Dask scheduler at {address}: start a scheduler and its workers and run "
            f"the same command again (with the new scheduler's address) to finish the study"
        )


class Executor(Protocol):
    """What the study runner needs from an executor."""

    #: How many tasks run at once (for the progress display).
    workers: int

    def submit(self, function: Callable[..., Any], *args: Any) -> Any:
        """Run ``function(*args)`` somewhere; a future of its result."""

    def as_completed(self, futures: Iterable[Any]) -> Iterator[Any]:
        """The futures as they complete."""

    def result(self, future: Any) -> Any:
        """The completed ``future``'s result; raises what the task raised, or the executor's own
        failure (e.g. :class:`SchedulerLostError`)."""

    def cancel(self, futures: Iterable[Any]) -> None:
        """Give up the tasks of ``futures`` that have not started (running ones may go on)."""

    def runs_left(self, count: int) -> None:
        """Hear how many runs the study still waits for (the Slurm executor keeps its jobs only
        while there are some)."""

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

    def result(self, future: Future[Any]) -> Any:
        """The completed ``future``'s result (or what its task raised)."""
        return future.result()

    def cancel(self, futures: Iterable[Future[Any]]) -> None:
        """Give up the tasks that have not started."""
        for future in futures:
            future.cancel()

    def runs_left(self, count: int) -> None:
        """Nothing to do: the pool's workers stay until :meth:`close`."""

    def close(self) -> None:
        """Stop the workers (running tasks are abandoned)."""
        self._pool.shutdown(wait=False, cancel_futures=True)


class DaskCluster:
    """A Dask ``distributed`` cluster: the scheduler at ``address``, or a local cluster of
    ``workers`` processes when no address is given, or ``cluster``: a cluster object started
    elsewhere (dask-jobqueue's ``SLURMCluster``, :mod:`studies.slurm`), which :meth:`close`
    closes."""

    def __init__(
        self, address: str | None = None, *, workers: int | None = None, cluster: Any = None
    ) -> None:
        from distributed import LocalCluster

        self._cluster = cluster
        if cluster is not None:
            address = cluster.scheduler_address
        elif address is None:
            self._cluster = LocalCluster(
                n_workers=workers or os.cpu_count() or 1,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
            )
            address = self._cluster.scheduler_address
        self.address = str(address)
        self.client = _connect(self.address)
        info = self.client.scheduler_info()
        self.workers = max(1, sum(w.get("nthreads", 1) for w in info["workers"].values()))

    def submit(self, function: Callable[..., Any], *args: Any) -> Any:
        """Run ``function(*args)`` on a worker (never cached: a task writes files);
        :class:`SchedulerLostError` once the scheduler is gone (the task would wait for ever)."""
        if self.scheduler_lost():
            raise SchedulerLostError(self.address)
        return self.client.submit(function, *args, pure=False)

    def as_completed(self, futures: Iterable[Any]) -> Iterator[Any]:
        """The futures as they complete."""
        from distributed import as_completed as dask_as_completed

        return iter(dask_as_completed(list(futures)))

    def result(self, future: Any) -> Any:
        """The completed ``future``'s result; :class:`SchedulerLostError` if it ended because
        the scheduler went away (Dask cancels every future then: no run failed)."""
        try:
            return future.result()
        except Exception as exc:
            if self.scheduler_lost(exc):
                raise SchedulerLostError(self.address) from None
            raise

    def scheduler_lost(self, exc: BaseException | None = None) -> bool:
        """Whether the client has lost its scheduler (``exc``: an error a future ended with)."""
        if isinstance(exc, CancelledError) and getattr(exc, "reason", None) == _LOST_REASON:
            return True
        return self.client.status in _NO_SCHEDULER

    def cancel(self, futures: Iterable[Any]) -> None:
        """Give up the tasks that have not started (with no scheduler, there is nothing to
        tell)."""
        futures = list(futures)
        if futures and not self.scheduler_lost():
            with contextlib.suppress(Exception):  # it may go at any moment: nothing to save
                self.client.cancel(futures)

    def runs_left(self, count: int) -> None:
        """Nothing to do: the workers are the cluster's (a Slurm executor keeps its jobs)."""

    def close(self) -> None:
        """Disconnect (and stop the local cluster if this started one)."""
        with _quiet_if(self.scheduler_lost(), "distributed", "distributed.client"):
            # A lost scheduler: Dask logs a traceback when its attempts to reconnect are
            # stopped; the study has said what happened in one line.
            self.client.close(timeout=CLOSE_TIMEOUT)
        if self._cluster is not None:
            self._cluster.close()


def _connect(address: str) -> Any:
    # A client of the scheduler at ``address``, or one line naming it if none answers in time.
    from distributed import Client

    try:
        return Client(address, timeout=SCHEDULER_CONNECT_TIMEOUT)
    except (OSError, TimeoutError) as exc:
        raise SchedulerUnreachableError(address, SCHEDULER_CONNECT_TIMEOUT) from exc


@contextlib.contextmanager
def _quiet_if(quiet: bool, *logger_names: str) -> Iterator[None]:
    # Only errors worse than ERROR from these loggers while the block runs, when ``quiet``.
    # Each by name: Dask gives some of its loggers a level of their own.
    loggers = [logging.getLogger(name) for name in logger_names]
    levels = [logger.level for logger in loggers]
    if quiet:
        for logger in loggers:
            logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for logger, level in zip(loggers, levels, strict=True):
            logger.setLevel(level)
