"""Workers from Slurm: ``surprise-study run STUDY --out DIR --slurm``.

dask-jobqueue's ``SLURMCluster`` runs the Dask scheduler in the ``surprise-study`` process (on the
login node) and submits ``jobs`` batch jobs with ``sbatch``; each job runs ``processes`` Dask
worker processes of this very Python (the study's venv, on a file system the nodes share), which
connect back to the scheduler and take runs until the study ends, when the jobs are cancelled.
The workers' logs go to ``DIR/slurm/``.

Jobs end while the study runs (their walltime, a node's failure, ``scancel``): a
:class:`JobKeeper` submits new ones in their place for as long as runs are left. The workers
leave a margin before the walltime (Dask's worker ``--lifetime``, :attr:`SlurmOptions.lifetime`),
so that they hand their runs back in good order rather than being killed, and the new job is
submitted as soon as they have left.

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
worker is up. Every failure is a :class:`~surprise.errors.ClusterError` with one line that says
what happened and where to look.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Annotated, Any, NamedTuple

import msgspec

from studies.executors import DaskCluster
from surprise.backoff import Backoff, BackoffConfig
from surprise.config import Strict, decode
from surprise.errors import ClusterError, ClusterTimeoutError, ConfigError
from surprise.text import plural

__all__ = [
    "ANSWER_TIMEOUT",
    "JOB_NAME",
    "KEEPER_POLL",
    "LEAVE_GRACE",
    "LOG_DIRECTORY",
    "MEMORY_PER_CORE",
    "START_TIMEOUT",
    "WALLTIME_MARGIN",
    "WALLTIME_MARGIN_SHARE",
    "JobKeeper",
    "SlurmExecutor",
    "SlurmOptions",
    "cluster_options",
    "renewal_line",
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
#: Seconds a Slurm command (``sbatch``, ``squeue``) may take: a controller answers in well
#: under a second; an unreachable one makes a client retry for a while (MessageTimeout, 10 s by
#: default, a few times) before it gives up with an error we can show.
ANSWER_TIMEOUT = 60.0
#: Seconds for dask-jobqueue to submit every job (one ``sbatch`` each, in the background).
SUBMIT_TIMEOUT = 120.0
#: Seconds between looks at the scheduler while waiting for the first worker (cheap, local).
WORKER_POLL = 0.2
#: Seconds between asking Slurm about the jobs while waiting: soon at first (a job that fails
#: does so in its first seconds), then less and less often, as ``squeue`` loads the controller
#: that a cluster's users share.
SQUEUE_POLL = BackoffConfig(initial=1.0, max=30.0, jitter=0.0)
#: Job states after which a job runs no worker any more (``squeue --states=all``).
ENDED_STATES = frozenset(
    {
        "BOOT_FAIL", "CANCELLED", "COMPLETED", "DEADLINE", "FAILED", "NODE_FAIL",
        "OUT_OF_MEMORY", "PREEMPTED", "REVOKED", "SPECIAL_EXIT", "TIMEOUT",
    }
)  # fmt: skip
#: Seconds before the walltime at which a job's workers leave, when the study file gives no
#: ``walltime_margin``: the workers' lifetime starts once the job has run its ``prologue`` and
#: loaded Python (a minute or more from a busy shared file system), and leaving takes up to 30 s
#: (a worker waits that long for the run it hands back, which may finish meanwhile).
WALLTIME_MARGIN = 300.0
#: ... and at most this share of the walltime, so that a short one (minutes) keeps most of its
#: time for runs.
WALLTIME_MARGIN_SHARE = 0.1
#: Seconds between looks at the scheduler's workers while the study runs (local and cheap): a
#: worker that leaves makes the keeper ask Slurm about the jobs soon, not at its slow pace.
KEEPER_POLL = 1.0
#: Seconds a job that had workers may have none before the keeper takes it for over, when they
#: did not leave at their lifetime: a worker process that died (out of memory) is started again
#: by its nanny within seconds, and the job goes on.
LEAVE_GRACE = 10.0
#: Seconds to wait for the keeper to stop when the study ends: it may be waiting for ``squeue``
#: or ``sbatch`` (:data:`ANSWER_TIMEOUT`); it is told not to submit anything more meanwhile.
KEEPER_STOP_TIMEOUT = ANSWER_TIMEOUT + 5.0
#: SpecCluster cancels a job this long after its workers left and forgets it (one-process jobs
#: only); the keeper does that itself, by job id, and it must not find a job gone under it.
_NEVER = "3650 days"
#: Why a job ended, by its final state, in the line that says it was replaced.
_WHY_ENDED = {
    "TIMEOUT": "walltime",
    "CANCELLED": "cancelled",
    "NODE_FAIL": "node failure",
    "BOOT_FAIL": "node failure",
    "PREEMPTED": "preempted",
    "OUT_OF_MEMORY": "out of memory",
    "FAILED": "failed",
    "DEADLINE": "deadline",
}

# Slurm's time formats: minutes, minutes:seconds, hours:minutes:seconds, days-hours,
# days-hours:minutes, days-hours:minutes:seconds.
_WALLTIME = re.compile(r"^(\d+(:\d{1,2}){0,2}|\d+-\d+(:\d{1,2}){0,2})$")
_Positive = Annotated[int, msgspec.Meta(ge=1)]


class SlurmOptions(Strict):
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


def walltime_seconds(walltime: str) -> float:
    """Seconds of a Slurm time (``sbatch -t``): ``minutes``, ``minutes:seconds``,
    ``hours:minutes:seconds``, ``days-hours``, ``days-hours:minutes`` or
    ``days-hours:minutes:seconds``; ``0`` is no limit."""
    days, _, clock = walltime.rpartition("-")
    parts = [int(part) for part in clock.split(":")]
    if days:  # days-hours[:minutes[:seconds]]
        hours, minutes, seconds = [*parts, 0, 0][:3]
        hours += int(days) * 24
    elif len(parts) == 1:  # minutes
        hours, minutes, seconds = 0, parts[0], 0
    else:  # minutes:seconds, hours:minutes:seconds
        hours, minutes, seconds = [0, *parts][-3:]
    return float(hours * 3600 + minutes * 60 + seconds)


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


def _slurm_command(args: list[str]) -> subprocess.CompletedProcess[str]:
    try:
        return subprocess.run(
            args, capture_output=True, text=True, timeout=ANSWER_TIMEOUT, stdin=subprocess.DEVNULL
        )
    except subprocess.TimeoutExpired:
        raise ClusterTimeoutError(
            f"Slurm did not answer `{' '.join(args[:2])}` within {ANSWER_TIMEOUT:g} s",
            timeout=ANSWER_TIMEOUT,
        ) from None
    except OSError as exc:
        raise ClusterError(f"cannot run {args[0]}: {exc.strerror or exc}") from None


def _error_text(result: subprocess.CompletedProcess[str]) -> str:
    # What a Slurm command said, in one line: it may say why in more than one ("sbatch: error:
    # invalid partition specified: x", then "allocation failure: Invalid partition name ...").
    lines = [line.strip() for line in (result.stderr + result.stdout).splitlines() if line.strip()]
    return "; ".join(lines) or f"exit status {result.returncode}"


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


class _Listed(NamedTuple):
    """A job as ``squeue`` lists it."""

    state: str  # RUNNING, TIMEOUT, ...
    reason: str  # why it waits or ended ("Resources", "NonZeroExitCode", "None"), or ""
    elapsed: float  # seconds it has run


def _squeue(jobs: list[str]) -> dict[str, _Listed]:
    """The jobs Slurm still lists, by id (it forgets ended ones after a while: MinJobAge);
    :class:`ClusterError` if squeue fails."""
    if not jobs:  # an empty --jobs= would list every job
        return {}
    squeue = shutil.which("squeue") or "squeue"
    result = _slurm_command(
        [squeue, "--noheader", "--states=all", f"--jobs={','.join(jobs)}", "--format=%i %T %M %r"]
    )
    if result.returncode != 0:
        error = _error_text(result)
        if "invalid job id" in error.lower():  # none of them is listed any more
            return {}
        raise ClusterError(f"squeue cannot tell where the workers' jobs stand: {error}")
    listed = {}
    for line in result.stdout.splitlines():
        job, state, elapsed, *reason = line.split()
        try:
            seconds = walltime_seconds(elapsed)  # %M: the same format as a walltime
        except ValueError:
            seconds = 0.0
        listed[job] = _Listed(state, " ".join(reason), seconds)
    return listed


def _job_states(jobs: list[str]) -> dict[str, str]:
    """Job id -> state and reason (``PENDING (Resources)``) of the jobs Slurm still lists."""
    return {
        job: found.state + (f" ({found.reason})" if found.reason else "")
        for job, found in _squeue(jobs).items()
    }


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
    whose :class:`JobKeeper` (``keeper``, started once the first worker is up) replaces the jobs
    that end while runs are left."""

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


class JobKeeper:
    """Keeps the study's Slurm jobs: a thread that submits a new job for each one that ends
    (its walltime, a node's failure, ``scancel``) as long as runs are left, no more than the
    runs left need, and says so in one line each time (:func:`renewal_line`).

    A job is over once Slurm says it ended, or once the workers it had have all left the
    scheduler: at their lifetime, just under the walltime, or :data:`LEAVE_GRACE` seconds ago
    (lost with their node, or their network). Its replacement is submitted then, while Slurm
    may still be ending it: a leaving worker gives the run it hands back up to 30 s to finish,
    and the keeper does not cut that short (it cancels no job). A job whose workers come back
    counts again.

    Slurm (``squeue``) is asked soon after a worker leaves the scheduler (1 s, then less and
    less often) and otherwise every ``SQUEUE_POLL.max`` seconds, which also finds jobs that
    ended before a worker connected.

    dask-jobqueue's own way, ``cluster.adapt(minimum_jobs=N, maximum_jobs=N)``, is not used: it
    replaces a job only if the job runs a single worker process (SpecCluster looks a leaving
    worker's name up among the jobs', and the workers of a job of several are named
    ``<job>-<i>``), only 15 s after its worker left and by cancelling the job, and silently.
    """

    def __init__(self, cluster: Any, options: SlurmOptions, say: Callable[[str], None]) -> None:
        self._cluster = cluster
        self._options = options
        self._say = say
        #: The runs the study still waits for; None until the runner says.
        self.runs_left: int | None = None
        self._jobs: dict[str, str] = {}  # the jobs that give workers: dask-jobqueue name -> id
        self._leaving: dict[str, str] = {}  # replaced, their workers gone, until Slurm ends them
        self._seen: set[str] = set()  # ids of the jobs that have had a worker
        self._gone_since: dict[str, float] = {}  # job id -> since when it has had none
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._trouble: str | None = None  # what the last look failed with, said once
        self._config: Any = None

    def start(self) -> None:
        """Take the jobs submitted so far in hand and start watching them."""
        import dask.config

        self._jobs = _jobs_of(self._cluster)
        self._note_workers(self._connected_jobs())
        # SpecCluster would cancel and forget a one-process job 15 s after its worker left;
        # the keeper does it, by job id, and must not find a job gone, or named anew, under it.
        self._config = dask.config.set({"distributed.deploy.lost-worker-timeout": _NEVER})
        self._thread = threading.Thread(target=self._watch, name="slurm-jobs", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop watching (no job is submitted after this returns, or after its timeout)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(KEEPER_STOP_TIMEOUT)
            self._thread = None
        if self._config is not None:
            self._config.__exit__(None, None, None)
            self._config = None

    def wanted(self) -> int:
        """How many jobs the runs left need: ``jobs``, fewer once they would leave workers
        idle, none once no run is left."""
        if self.runs_left is None:
            return self._options.jobs
        return min(self._options.jobs, math.ceil(self.runs_left / self._options.worker_processes))

    def _watch(self) -> None:
        looks = Backoff(SQUEUE_POLL)
        next_look = time.monotonic() + looks.next_delay()
        workers = self._worker_count()
        while not self._stop.wait(KEEPER_POLL):
            self._note_workers(self._connected_jobs())
            count = self._worker_count()
            if count < workers:  # a worker left: its job may be over
                looks.reset()
                next_look = min(next_look, time.monotonic() + looks.next_delay())
            workers = count
            if time.monotonic() >= next_look and self.runs_left != 0:
                self._look()
                next_look = time.monotonic() + looks.next_delay()

    def _look(self) -> None:
        try:
            self.check()
        except Exception as exc:
            # The keeper must outlive a look that failed (a controller that does not answer
            # for a while): the study goes on on the jobs it has, and the next look tries again.
            message = str(exc) or type(exc).__name__
            if message != self._trouble:
                self._say(f"slurm: cannot look after the workers' jobs for now: {message}")
            self._trouble = message
        else:
            self._trouble = None

    def check(self) -> None:
        """Look at the jobs once: set aside those that are over, submit as many new ones as
        the runs left need, forget the jobs Slurm has ended, and say what changed."""
        listed = _squeue([*self._jobs.values(), *self._leaving.values()])
        connected = self._connected_jobs()
        for name in [name for name in self._leaving if name in connected]:
            self._jobs[name] = self._leaving.pop(name)  # its workers are back
        self._note_workers(connected)
        over = {
            name: job
            for name, job in self._jobs.items()
            if self._is_over(job, listed.get(job), name in connected)
        }
        for name, job in over.items():
            del self._jobs[name]
            self._leaving[name] = job
        ended = {
            name: job
            for name, job in self._leaving.items()
            if _has_ended(listed.get(job), name in connected)
        }
        new = max(0, self.wanted() - len(self._jobs))
        if not (over or ended or new) or self._stop.is_set():
            return
        for name, job in ended.items():
            del self._leaving[name]
            self._seen.discard(job)
            self._gone_since.pop(job, None)
        jobs, refused = self._cluster.sync(
            _renew, self._cluster, ended, new, callback_timeout=SUBMIT_TIMEOUT
        )
        submitted = {n: j for n, j in jobs.items() if n not in self._jobs | self._leaving}
        self._jobs.update(submitted)
        if over or new:
            self._say(
                renewal_line(
                    {
                        job: _why_over(listed.get(job), self._options.lifetime)
                        for job in over.values()
                    },
                    _in_order(submitted.values()),
                    wanted=new,
                    refused=refused,
                    runs_left=self.runs_left,
                )
            )

    def _is_over(self, job: str, listed: _Listed | None, connected: bool) -> bool:
        """Whether a job gives the study no workers any more: Slurm ended it, or the workers
        it had have all left, at their lifetime or :data:`LEAVE_GRACE` ago (a job that never
        had one may be starting them)."""
        if _has_ended(listed, connected):
            return True
        if connected or job not in self._gone_since:
            return False
        lifetime = self._options.lifetime
        if listed is not None and lifetime is not None and listed.elapsed >= lifetime:
            return True
        return time.monotonic() - self._gone_since[job] >= LEAVE_GRACE

    def _note_workers(self, connected: set[str]) -> None:
        # By job id: dask-jobqueue may give a new job the name of one it forgot.
        now = time.monotonic()
        for name, job in self._jobs.items():
            if name in connected:
                self._seen.add(job)
                self._gone_since.pop(job, None)
            elif job in self._seen:
                self._gone_since.setdefault(job, now)

    def _worker_count(self) -> int:
        return len(self._cluster.scheduler_info["workers"])

    def _connected_jobs(self) -> set[str]:
        # The jobs (dask-jobqueue's names) with a worker connected: a job of one process names
        # its worker as itself, one of several ``<job>-<i>``.
        workers = list(self._cluster.scheduler_info["workers"].values())
        names = [str(worker.get("name")) for worker in workers]
        return set(names) | {name.rsplit("-", 1)[0] for name in names}


def _in_order(jobs: Iterable[str]) -> list[str]:
    """Job ids in the order Slurm gave them (by number, without taking them for one)."""
    return sorted(jobs, key=lambda job: (len(job), job))


def _jobs_of(cluster: Any) -> dict[str, str]:
    """dask-jobqueue's name -> Slurm job id of the jobs it submitted (that sbatch took)."""
    return {name: job.job_id for name, job in list(cluster.workers.items()) if job.job_id}


def _has_ended(listed: _Listed | None, connected: bool) -> bool:
    """Whether Slurm has ended a job (None: it lists the job no more, and so, unless a worker
    of it is still connected, has ended it)."""
    if listed is None:
        return not connected
    return listed.state in ENDED_STATES


def _why_over(listed: _Listed | None, lifetime: float | None) -> str:
    """Why a job is over, in a word or two (``lifetime``: of its workers, in seconds)."""
    if listed is None:
        return "gone"
    if lifetime is not None and listed.elapsed >= lifetime and listed.state not in _WHY_ENDED:
        # Its workers left by themselves at their lifetime, just under the walltime, and the
        # job ends (COMPLETED) or is ending (RUNNING) with them.
        return "walltime"
    if listed.state not in ENDED_STATES:
        return "workers lost"  # gone from the scheduler while the job runs: its node, its net
    return _WHY_ENDED.get(listed.state, listed.state.lower())


async def _renew(
    cluster: Any, ended: dict[str, str], new: int
) -> tuple[dict[str, str], str | None]:
    """On the cluster's event loop: forget the jobs ``ended`` (name -> job id) and submit
    ``new`` ones; the jobs then (name -> id), and what sbatch said if it refused some (those are
    forgotten too: the next look submits them again)."""
    gone = [
        name
        for name, job in ended.items()
        if name not in cluster.workers or cluster.workers[name].job_id == job
    ]
    if gone:
        await cluster.scale_down(gone)  # scancel, a no-op for an ended job, and forget it
    # Not cluster.scale(): it submits in a callback of its own, whose failure we would not see.
    for _ in range(new):
        cluster.worker_spec.update(cluster.new_worker_spec())
    refused = None
    if new:
        try:
            await cluster
        except (RuntimeError, ValueError, OSError) as exc:  # sbatch failed, or gave no job id
            refused = _sbatch_error(exc)
        failed = [name for name, job in cluster.workers.items() if not job.job_id]
        if failed:
            await cluster.scale_down(failed)
    return _jobs_of(cluster), refused


def _sbatch_error(exc: BaseException) -> str:
    # dask-jobqueue's message of a failed command ends with "stderr:" and the command's.
    text = str(exc)
    if "stderr:" in text:
        text = text.rsplit("stderr:", 1)[1]
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return "; ".join(lines) or type(exc).__name__


def renewal_line(
    ended: dict[str, str],
    submitted: list[str],
    *,
    wanted: int,
    refused: str | None = None,
    runs_left: int | None = None,
) -> str:
    """What the study prints when jobs are replaced: ``ended`` (job id -> why), the jobs
    ``submitted`` in their place, out of ``wanted``, and what sbatch said if it refused some.

    ``slurm: 2 jobs ended (walltime: 4711, 4712); submitted 2 new ones (4713, 4714)``
    """
    parts = []
    if ended:
        by_why: dict[str, list[str]] = {}
        for job, why in ended.items():
            by_why.setdefault(why, []).append(job)
        whys = "; ".join(f"{why}: {', '.join(jobs)}" for why, jobs in by_why.items())
        parts.append(f"{plural(len(ended), 'job')} ended ({whys})")
    noun = "new one" if ended else "new job"
    if submitted:
        text = f"submitted {plural(len(submitted), noun, noun + 's')} ({', '.join(submitted)})"
        if len(submitted) < len(ended) and refused is None and runs_left is not None:
            text += f", enough for the {plural(runs_left, 'run')} left"
        parts.append(text)
    elif refused is None:
        left = f" for the {plural(runs_left, 'run')} left" if runs_left is not None else ""
        parts.append(f"no new ones: the other jobs are enough{left}")
    if refused is not None and wanted > len(submitted):
        missing = plural(wanted - len(submitted), noun, noun + "s")
        parts.append(f"sbatch refused {missing} ({refused}); trying again soon")
    return f"slurm: {'; '.join(parts)}"
