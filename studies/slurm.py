"""Workers from Slurm: ``surprise-study run STUDY --out DIR --slurm``.

dask-jobqueue's ``SLURMCluster`` runs the Dask scheduler in the ``surprise-study`` process (on the
login node) and submits ``jobs`` batch jobs with ``sbatch``; each job runs ``processes`` Dask
worker processes of this very Python (the study's venv, on a file system the nodes share), which
connect back to the scheduler and take runs until the study ends, when the jobs are cancelled.
The workers' logs go to ``DIR/slurm/``.

Jobs end while the study runs (their walltime, a node's failure, ``scancel``): a
:class:`~studies.slurm_jobs.JobKeeper` (:mod:`studies.slurm_jobs`) submits new ones in their
place for as long as runs are left. The workers leave a margin before the walltime (Dask's
worker ``--lifetime``, :attr:`SlurmOptions.lifetime`), so that they hand their runs back in good
order rather than being killed, and the new job is submitted as soon as they have left.

The settings come from the study file's ``slurm:`` section (:class:`SlurmOptions`), each of which
a ``--slurm-*`` option overrides::

    slurm:
      queue: short          # the partition (sbatch -p)
      jobs: 10              # batch jobs
      cores: 4              # cores per job: 4 worker processes of one thread
      memory: 8GB           # per job
      walltime: "04:00:00"
      walltime_margin: 300  # the workers leave 5 minutes before the walltime

Before any job is submitted, ``sbatch --test-only`` checks that Slurm answers and would take
the jobs as asked; then :func:`start_slurm` waits (at most ``start_timeout``) until the first
worker is up. Every failure is a :class:`~minimize_surprise.errors.ClusterError` with one line that
says what happened and where to look.
"""

from __future__ import annotations

import os
import re
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import msgspec

from minimize_surprise.backoff import Backoff
from minimize_surprise.config import Strict, decode
from minimize_surprise.errors import ClusterError, ClusterTimeoutError, ConfigError
from studies.executors import DaskCluster
from studies.slurm_jobs import (
    ENDED_STATES,
    SQUEUE_POLL,
    SUBMIT_TIMEOUT,
    JobKeeper,
    _error_text,
    _in_order,
    _job_states,
    _slurm_command,
    walltime_seconds,
)

__all__ = [
    "JOB_NAME",
    "LOG_DIRECTORY",
    "MEMORY_PER_CORE",
    "START_TIMEOUT",
    "WALLTIME_MARGIN",
    "WALLTIME_MARGIN_SHARE",
    "SlurmExecutor",
    "SlurmOptions",
    "cluster_options",
    "slurm_job_id",
    "start_slurm",
    "walltime_seconds",
    "with_overrides",
]

#: The name of the workers' jobs (``squeue -n surprise-study``) and of their log files.
JOB_NAME = "surprise-study"
#: Where the workers' logs go, below the study's directory (``JOB_NAME-JOBID.out``/``.err``).
LOG_DIRECTORY = "slurm"
#: Memory per job, per core, when the study gives none: a run needs well under 1 GB (the
#: compiled simulator and one run's traces), a worker process about 150 MB more.
MEMORY_PER_CORE = 2 * 1024**3
#: Seconds by default for the first worker to come up. A busy cluster may keep jobs pending for
#: a long time; a study that never gets a worker should still end, and say why, not wait on.
START_TIMEOUT = 3600.0
#: Seconds between looks at the scheduler while waiting for the first worker (cheap, local).
WORKER_POLL = 0.2
#: Seconds before the walltime at which a job's workers leave, when the study file gives no
#: ``walltime_margin``: the workers' lifetime starts once the job has run its ``prologue`` and
#: loaded Python (a minute or more from a busy shared file system), and leaving takes up to 30 s
#: (a worker waits that long for the run it hands back, which may finish meanwhile).
WALLTIME_MARGIN = 300.0
#: ... and at most this share of the walltime, so that a short one (minutes) keeps most of its
#: time for runs.
WALLTIME_MARGIN_SHARE = 0.1

# Slurm's time formats: minutes, minutes:seconds, hours:minutes:seconds, days-hours,
# days-hours:minutes, days-hours:minutes:seconds.
_WALLTIME = re.compile(r"^(\d+(:\d{1,2}){0,2}|\d+-\d+(:\d{1,2}){0,2})$")
_Positive = Annotated[int, msgspec.Meta(ge=1)]


class SlurmOptions(Strict, frozen=True):
    """The ``slurm:`` section of a study file: where and how ``--slurm`` starts the workers.
    Every key has a ``--slurm-*`` option too (``--slurm-queue``, ...), which overrides it."""

    #: the partition the jobs go to (``sbatch -p``); `null`: the cluster's default partition
    queue: str | None = None
    #: the account the jobs are charged to (``sbatch -A``); `null`: the user's default
    account: str | None = None
    #: how many batch jobs to submit: the study runs on ``jobs`` x ``cores`` cores
    jobs: _Positive = 1
    #: cores of each job (``--cpus-per-task``); a run keeps one core busy
    cores: _Positive = 1
    #: Dask worker processes per job, which share its cores (``cores`` must be a multiple);
    #: `null`: one single-threaded process per core, which keeps each run's compiled simulator
    #: caches apart
    processes: _Positive | None = None
    #: memory of each job (``--mem``), e.g. ``8GB``; `null`: 2 GiB per core
    memory: str | None = None
    #: the longest a job may run (``sbatch -t``: ``minutes``, ``hours:minutes:seconds``,
    #: ``days-hours``, ...); a job that ends is replaced by a new one while runs are left, the
    #: runs it was running starting again on the other workers: give it well over a run's time
    walltime: str = "01:00:00"
    #: seconds before the walltime at which a job's workers leave (Dask's worker lifetime):
    #: they hand their running runs back, to start again elsewhere, and a new job is submitted;
    #: it covers the job's start (``prologue``, loading Python) and up to 30 s of leaving;
    #: `null`: a tenth of the walltime, at most 300
    walltime_margin: Annotated[float, msgspec.Meta(gt=0)] | None = None
    #: more ``#SBATCH`` options for the jobs, e.g. ``["--qos=short", "--constraint=intel"]``
    directives: list[str] = msgspec.field(default_factory=list)
    #: shell lines the job script runs before the workers start, e.g. ``module load gcc``;
    #: the workers run this very Python, so the study's venv needs no activating
    prologue: list[str] = msgspec.field(default_factory=list)
    #: the network interface the scheduler and the workers use (``ib0``, ``eth0``; ``lo`` on
    #: a one-machine cluster); `null`: the scheduler listens on every interface and each worker
    #: on its node's main address
    interface: str | None = None
    #: seconds to wait for the first worker (the jobs may be pending); then the study fails
    start_timeout: Annotated[float, msgspec.Meta(gt=0)] = START_TIMEOUT

    def __post_init__(self) -> None:
        if self.processes is not None and self.cores % self.processes:
            raise ValueError(
                f"`processes`: {self.processes} processes cannot share {self.cores} cores "
                "evenly; give a divisor of `cores`"
            )
        if self.memory is not None:
            from dask.utils import parse_bytes

            try:
                parse_bytes(self.memory)
            except ValueError:
                raise ValueError(
                    f"`memory`: expected an amount such as 4GB or 500MB, got {self.memory!r}"
                ) from None
        if not _WALLTIME.match(self.walltime):
            raise ValueError(
                "`walltime`: expected Slurm's time, e.g. 90 (minutes), 04:00:00 or 2-00:00:00, "
                f"got {self.walltime!r}"
            )
        limit = walltime_seconds(self.walltime)
        if self.walltime_margin is not None and limit and self.walltime_margin >= limit:
            raise ValueError(
                f"`walltime_margin`: {self.walltime_margin:g} s leaves the workers nothing of "
                f"the walltime {self.walltime} ({limit:g} s); give less, or a longer walltime"
            )
        for line in self.directives:
            if not line.startswith("-"):
                raise ValueError(f"`directives`: expected an sbatch option like --qos=x: {line!r}")

    @property
    def worker_processes(self) -> int:
        """Dask worker processes per job."""
        return self.processes or self.cores

    @property
    def job_memory(self) -> str:
        """The memory of each job, as dask-jobqueue takes it."""
        return self.memory or f"{self.cores * MEMORY_PER_CORE // 1024**2}MiB"

    @property
    def lifetime(self) -> float | None:
        """Seconds a job's workers run before they leave: the walltime less its margin (None
        with no walltime, ``0``)."""
        limit = walltime_seconds(self.walltime)
        if not limit:
            return None
        margin = self.walltime_margin
        if margin is None:
            margin = min(WALLTIME_MARGIN, limit * WALLTIME_MARGIN_SHARE)
        return limit - margin


def with_overrides(
    options: SlurmOptions | None, overrides: dict[str, Any], *, file: str | Path | None = None
) -> SlurmOptions:
    """``options`` (the study file's ``slurm:`` section, or the defaults) with ``overrides``
    (option name -> value; ``None``: not given) in place; a bad value is a
    :class:`ConfigError` naming its ``--slurm-*`` option, or the file's key."""
    given = {key: value for key, value in overrides.items() if value is not None}
    data = msgspec.to_builtins(options or SlurmOptions()) | given
    try:
        return decode(data, SlurmOptions)
    except ConfigError as exc:
        key = (exc.key or "").split(".")[0].split("[")[0]
        if key in given:
            raise ConfigError(exc.reason, key=f"--slurm-{key.replace('_', '-')}") from None
        raise ConfigError(
            exc.reason, file=str(file) if file else None, key=f"slurm.{exc.key}"
        ) from None


def cluster_options(options: SlurmOptions, logs: Path) -> dict[str, Any]:
    """The keyword arguments of ``dask_jobqueue.SLURMCluster`` for ``options``, the workers'
    logs going to ``logs``."""
    return {
        "queue": options.queue,
        "account": options.account,
        "cores": options.cores,
        "processes": options.worker_processes,
        "memory": options.job_memory,
        "walltime": options.walltime,
        "job_name": JOB_NAME,
        "log_directory": str(logs),
        # The workers run the interpreter that runs the study: the same packages, the same
        # version, as the same seed must give the same run everywhere.
        "python": sys.executable,
        "interface": options.interface,
        "job_extra_directives": list(options.directives),
        "job_script_prologue": list(options.prologue),
        # Dask's dashboards would listen on every address (the scheduler's on :8787); nobody
        # needs them here (the study shows its own progress), so they stay on loopback.
        "scheduler_options": {"dashboard_address": "127.0.0.1:0"},
        "worker_extra_args": ["--dashboard-address", "127.0.0.1:0", *_lifetime_args(options)],
    }


def _lifetime_args(options: SlurmOptions) -> list[str]:
    # The workers leave by themselves before Slurm ends their job: Dask then takes them off
    # gracefully (their runs go elsewhere at once, and a run interrupted so does not count
    # towards the failures after which Dask gives it up, as one killed with its job does).
    # No --lifetime-stagger: it draws a lifetime per worker process, and a job's cores would
    # stay idle from its first worker's leaving until its last one's, when the job ends.
    lifetime = options.lifetime
    return [] if lifetime is None else ["--lifetime", f"{lifetime:g}s"]


def start_slurm(
    options: SlurmOptions, out: str | Path, *, say: Callable[[str], None] | None = None
) -> DaskCluster:
    """Start the workers of a study in ``out`` as Slurm jobs; the executor once one is up.

    ``say`` is told what happens (the jobs submitted, the first worker up). Raises
    :class:`ClusterError` when Slurm is missing, does not answer or refuses the jobs, or the
    jobs end before a worker connects, and :class:`ClusterTimeoutError` when no worker is up
    within ``options.start_timeout``.
    """
    say = say or (lambda message: None)
    sbatch = shutil.which("sbatch")
    if sbatch is None:
        raise ClusterError(
            "--slurm: sbatch is not on PATH; run the study on a Slurm cluster's login node"
        )
    conf = os.environ.get("SLURM_CONF")
    if conf and not Path(conf).is_file():
        # Slurm's clients would retry reading it for a minute before they say so.
        raise ClusterError(f"--slurm: SLURM_CONF names no file: {conf}")
    try:
        from dask_jobqueue import SLURMCluster
    except ImportError:
        raise ClusterError("--slurm needs dask-jobqueue: pip install -e '.[studies]'") from None
    logs = Path(out).resolve() / LOG_DIRECTORY
    logs.mkdir(parents=True, exist_ok=True)
    try:
        cluster = SLURMCluster(**cluster_options(options, logs))
    except (ValueError, RuntimeError) as exc:  # e.g. an interface this machine does not have
        raise ClusterError(f"--slurm: the Dask scheduler cannot start: {exc}") from None
    try:
        _test_submit(sbatch, cluster.job_script(), options)
        executor = SlurmExecutor(cluster, options, say)
    except BaseException:
        cluster.close()
        raise
    try:
        cluster.scale(jobs=options.jobs)
        jobs = _submitted(cluster, options.jobs)
        say(
            f"slurm: submitted {options.jobs} job{'s' if options.jobs > 1 else ''} "
            f"({', '.join(jobs)}); waiting for the first worker (at most "
            f"{options.start_timeout:g} s); worker logs in {logs}"
        )
        started = time.monotonic()
        job = _wait_for_a_worker(executor, jobs, options.start_timeout, logs)
        say(f"slurm: the first worker is up (job {job}) after {time.monotonic() - started:.1f} s")
        executor.keeper.start()
    except BaseException:
        executor.close()
        raise
    # What runs at once once every job runs (for the progress display): one run per thread.
    executor.workers = options.jobs * options.cores
    return executor


def _test_submit(sbatch: str, script: str, options: SlurmOptions) -> None:
    # sbatch --test-only asks the controller whether it would take the job as written (the
    # partition, account, cores, memory, time) without submitting it: a refusal is one clear
    # line now, instead of jobs that fail in dask-jobqueue's background.
    with tempfile.NamedTemporaryFile("w", suffix=".sh", prefix="surprise-study-") as file:
        file.write(script)
        file.flush()
        result = _slurm_command([sbatch, "--test-only", file.name])
    if result.returncode != 0:
        error = _error_text(result)
        if "contact slurm controller" in error.lower():
            raise ClusterError(f"Slurm's controller does not answer (SLURM_CONF?): {error}")
        asked = (
            f"{options.cores} cores, {options.job_memory}, {options.walltime} each, "
            f"partition {options.queue or '(default)'}"
        )
        raise ClusterError(f"Slurm refuses the workers' jobs ({asked}): {error}")


def _submitted(cluster: Any, count: int) -> list[str]:
    # dask-jobqueue submits in its event loop; a job enters cluster.workers once every sbatch of
    # the batch has returned, with a job id if Slurm took it.
    deadline = time.monotonic() + SUBMIT_TIMEOUT
    while len(cluster.workers) < count:
        if time.monotonic() > deadline:
            raise ClusterTimeoutError(
                f"dask-jobqueue did not submit the {count} jobs within {SUBMIT_TIMEOUT:g} s",
                timeout=SUBMIT_TIMEOUT,
            )
        time.sleep(WORKER_POLL)
    jobs = [job.job_id for job in cluster.workers.values()]
    taken = _in_order([job for job in jobs if job])
    if len(taken) < count:
        raise ClusterError(f"sbatch refused {count - len(taken)} of the {count} workers' jobs")
    return taken


def _wait_for_a_worker(executor: Any, jobs: list[str], timeout: float, logs: Path) -> str:
    """Wait until a worker is up; the job it runs in."""
    deadline = time.monotonic() + timeout
    next_look = time.monotonic()
    polls = Backoff(SQUEUE_POLL)
    states: dict[str, str] = {}
    while True:
        workers = executor.client.scheduler_info()["workers"]
        if workers:
            job = _job_of(executor, next(iter(workers)))
            return job or "?"
        now = time.monotonic()
        if now >= next_look:
            next_look = now + polls.next_delay()
            states = _job_states(jobs)
            running = [s for j, s in states.items() if s.split()[0] not in ENDED_STATES]
            if not running:
                ended = ", ".join(f"{job} {states.get(job, 'gone')}" for job in jobs)
                raise ClusterError(
                    f"the Slurm jobs ended before a worker connected ({ended}); "
                    f"see their logs in {logs}"
                )
        if now > deadline:
            where = ", ".join(f"{job} {states.get(job, 'gone')}" for job in jobs)
            raise ClusterTimeoutError(
                f"no Slurm job started a worker within {timeout:g} s (jobs {where}); "
                "give slurm.start_timeout more time or ask for less",
                timeout=timeout,
            )
        time.sleep(WORKER_POLL)


def _job_of(executor: Any, worker: str) -> str | None:
    """The Slurm job a worker runs in."""
    return executor.client.run(slurm_job_id, workers=[worker]).get(worker)


def slurm_job_id() -> str | None:
    """The Slurm job this process runs in (``SLURM_JOB_ID``), or None; run on a worker."""
    return os.environ.get("SLURM_JOB_ID")


class SlurmExecutor(DaskCluster):
    """The study's executor on Slurm: a :class:`DaskCluster` of dask-jobqueue's ``cluster``
    whose :class:`~studies.slurm_jobs.JobKeeper` (``keeper``, started once the first worker is
    up) replaces the jobs that end while runs are left."""

    def __init__(self, cluster: Any, options: SlurmOptions, say: Callable[[str], None]) -> None:
        super().__init__(cluster=cluster)
        self.keeper = JobKeeper(cluster, options, say)

    def runs_left(self, count: int) -> None:
        """The runs the study still waits for: the keeper submits no more jobs than they need,
        and none once there are none."""
        self.keeper.runs_left = count

    def close(self) -> None:
        """Stop replacing jobs, disconnect, and cancel the jobs (``scancel``)."""
        self.keeper.stop()
        super().close()
