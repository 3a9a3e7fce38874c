"""The workers' Slurm jobs while a study runs: where they stand, and new ones for those that end.

:func:`~studies.slurm.start_slurm` submits the jobs and waits for the first worker; from then
on, Slurm ends jobs while the study still has runs for them (their walltime, a node's failure,
``scancel``), and each one that ends takes its workers with it. A :class:`JobKeeper`, a thread
of the :class:`~studies.slurm.SlurmExecutor`, submits a new job for each one that ends as long
as runs are left, no more than the runs left need, and says so in one line each time
(:func:`renewal_line`)::

    slurm: 2 jobs ended (walltime: 4711, 4712); submitted 2 new ones (4713, 4714)

It learns that a job is over from the Dask scheduler, whose workers leave at their lifetime,
just under the walltime (a look that is local and cheap, every :data:`KEEPER_POLL` seconds),
and from ``squeue``, which loads the controller that a cluster's users share: it is asked soon
after a worker has left, and otherwise less and less often (``SQUEUE_POLL``). The Slurm commands
run here (:func:`_slurm_command`: ``squeue``, and ``sbatch --test-only`` for
:mod:`studies.slurm`) each have :data:`ANSWER_TIMEOUT` seconds to answer; a failure is a
:class:`~minimize_surprise.errors.ClusterError` with what Slurm said in one line. A look that fails
does not stop the keeper: the study goes on on the jobs it has, and the next look tries again.

:mod:`studies.slurm` (the options, starting the cluster) imports this module, which imports
nothing of it but the options' type, for annotations.
"""

from __future__ import annotations

import math
import shutil
import subprocess
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any, NamedTuple, Protocol

from minimize_surprise.backoff import Backoff, BackoffConfig
from minimize_surprise.errors import ClusterError, ClusterTimeoutError
from minimize_surprise.text import plural


class JobShape(Protocol):
    """What the keeper needs of the study's Slurm options (:class:`studies.slurm.SlurmOptions`,
    which imports this module): how many jobs, their worker processes, their workers' lifetime."""

    @property
    def jobs(self) -> int:
        """Jobs to keep submitted."""

    @property
    def worker_processes(self) -> int:
        """Dask worker processes per job."""

    @property
    def lifetime(self) -> float | None:
        """Seconds a job's workers run before they leave (None: until the job ends)."""


__all__ = [
    "ANSWER_TIMEOUT",
    "ENDED_STATES",
    "KEEPER_POLL",
    "LEAVE_GRACE",
    "SQUEUE_POLL",
    "SUBMIT_TIMEOUT",
    "JobKeeper",
    "JobShape",
    "renewal_line",
    "walltime_seconds",
]

#: Seconds a Slurm command (``sbatch``, ``squeue``) may take: a controller answers in well
#: under a second; an unreachable one makes a client retry for a while (MessageTimeout, 10 s by
#: default, a few times) before it gives up with an error we can show.
ANSWER_TIMEOUT = 60.0
#: Seconds for dask-jobqueue to submit every job (one ``sbatch`` each, in the background).
SUBMIT_TIMEOUT = 120.0
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


# Here rather than in studies.slurm, which checks the study's walltime with it: squeue gives
# a job's elapsed time (%M) in the same format.
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

    def __init__(self, cluster: Any, options: JobShape, say: Callable[[str], None]) -> None:
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
            from distributed.core import Status

            for name in failed:
                # Never started, so never ended either: dask-jobqueue's Job.close leaves a job's
                # status as it is, and closing the cluster checks that every job it made and
                # that is still referenced (here, from the error's traceback, until Python's
                # collector frees it) has ended. Without this the study's close failed, now and
                # then, after a study whose sbatch had refused a job.
                cluster.workers[name].status = Status.failed
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
