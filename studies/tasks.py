"""One run of a study: a plain function of plain data, so that any executor can run it.

:func:`run_task` takes a task (see :func:`studies.spec.expand`) and the study's directory, runs
it into ``runs/<task["run"]>``, and returns a plain summary, which it also writes there as
``summary.json`` (last, atomically: a run is finished exactly when its summary exists). A run
that raises leaves ``error.txt`` with the traceback and ``failed.json``, and returns a summary
with ``status: failed``; it never raises itself, so one broken run cannot stop a study. The same
task gives the same result on whichever machine runs it: every random draw is seeded by the
task's seed.

A run happens once, whoever asks for it how often. Its task holds the run's lock (``flock`` on
``.seed-N.lock`` next to the run's directory) while it runs; the kernel releases it when the
process holding it ends, however it ends. A second task of the same run (a study started again
while the tasks of a killed one still run on a Dask cluster, or Dask computing again a result
it lost with a worker) waits for the lock, and then takes the stored summary as its result
instead of running the run again. Only a full file system raises (:class:`DiskFullError`): that
is not the run's fault, so the run is left pending rather than failed.

Kinds:

* ``evolved``: an evolved run on the engine (``surprise-master sim --engine fast``), its
  ``params`` an experiment file's content; the summary holds the best and the post-evaluation
  fitness, the behaviour metrics of the post-evaluation and the mean predicted and real value of
  each sensor.
* ``qd``: a MAP-Elites run on the engine (``surprise-master sim --optimizer map-elites``), its
  ``params`` an experiment file's content (its ``optimizer`` section the grid; left out, the
  default grid); the summary holds the archive's figures, the classes it holds and each class's
  best elite with its post-evaluation (docs/quality-diversity.md).
* ``random``: one random network pair in a freshly reset arena (``surprise-master baseline``).
* ``recorded``: a finished run directory read, not run (the lab's real-robot runs;
  :mod:`studies.recorded`): its summary is the run's, with ``source`` saying where it is.
* ``grid-*``: the grid world's kinds (``gridworld.tasks``), when that package is installed. A
  relative ``genome_run`` (reruns and damage of an evolved genome) names another run of the
  study below its ``runs/``, e.g. ``evolved/size=16/seed-{seed}`` with the run's own seed.

Any other kind (or a grid kind without the grid world installed) is a
:class:`~minimize_surprise.errors.ConfigError` naming it and :data:`KINDS`: checking the task
raises it, running the task fails the run with it.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import logging
import os
import shutil
import time
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Final

from minimize_surprise.errors import ConfigError, FileWriteError
from minimize_surprise.files import write_json
from studies.recorded import RECORDED, read_recorded

__all__ = [
    "ERROR",
    "FAILED",
    "KINDS",
    "RUNS",
    "SUMMARY",
    "DiskFullError",
    "check_task",
    "disk_full",
    "finished",
    "is_finished",
    "lock_path",
    "naming_full_disk",
    "run_busy",
    "run_dir",
    "run_lock",
    "run_task",
    "stored_summary",
]

log = logging.getLogger(__name__)

#: The summary a finished run leaves in its directory.
SUMMARY = "summary.json"
#: What a failed run leaves in its directory: the traceback, and its summary (it is run again
#: when the study is).
ERROR = "error.txt"
FAILED = "failed.json"
#: Where a study's runs live, below its directory.
RUNS = "runs"

#: The errors that say a file system cannot take more data: full, or the user's quota used up.
_FULL_DISK: Final = frozenset({errno.ENOSPC, errno.EDQUOT})


class DiskFullError(FileWriteError):
    """The file system holding ``path`` is full (or the quota is used up), so ``path`` could not
    be written. Not a run's fault: the runs not finished stay pending, and running the study
    again once there is room goes on with them."""

    def __init__(
        self, path: str | Path, errno_: int = errno.ENOSPC, strerror: str | None = None
    ) -> None:
        super().__init__(str(path), errno_, strerror or os.strerror(errno_))

    def __str__(self) -> str:
        return (
            f"cannot write {self.path}: {str(self.strerror).lower()}; free space on its file "
            f"system (or raise the quota) and run the same command again"
        )

    def __reduce__(self) -> tuple[Any, ...]:
        # Crosses process boundaries (a worker's error, pickled to the study): rebuild it from
        # its fields, not from OSError's arguments.
        return type(self), (self.path, self.errno, self.strerror)


def disk_full(exc: BaseException, path: str | Path) -> DiskFullError | None:
    """A :class:`DiskFullError` if ``exc`` or an error it was raised from says the disk is full
    (naming the file the OS named, else ``path``); None for any other error."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, DiskFullError):
            return current
        if isinstance(current, OSError) and current.errno in _FULL_DISK:
            return DiskFullError(current.filename or path, current.errno)
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return None


@contextlib.contextmanager
def naming_full_disk(path: str | Path) -> Iterator[None]:
    """Turn a full disk met inside the block into a :class:`DiskFullError` naming ``path`` (or
    the file the OS named): the bare ``OSError`` of a failed ``write()`` names none."""
    try:
        yield
    except Exception as exc:
        full = disk_full(exc, path)
        if full is None or full is exc:
            raise
        raise full from None


def _grid_kinds() -> tuple[str, ...]:
    try:
        from gridworld.tasks import GRID_KINDS
    except ImportError:
        return ()
    return tuple(GRID_KINDS)


#: Every run kind this installation can run.
KINDS: tuple[str, ...] = ("evolved", "random", "qd", RECORDED, *_grid_kinds())


def run_dir(root: str | Path, task: dict[str, Any]) -> Path:
    """Where ``task`` runs, below the study directory ``root``."""
    return Path(root) / RUNS / task["run"]


def is_finished(root: str | Path, task: dict[str, Any]) -> bool:
    """Whether ``task`` finished (its summary exists)."""
    return finished(run_dir(root, task))


def finished(directory: Path) -> bool:
    """Whether the run in ``directory`` finished (see :func:`stored_summary`)."""
    return stored_summary(directory) is not None


def stored_summary(directory: Path) -> dict[str, Any] | None:
    """The summary of the run in ``directory`` if it finished, else None.

    Finished means this module's summary is there, with status done and the host it ran on
    (added last). It is written atomically as the run's last file, so a run still running or
    killed half-way has none. A grid run writes a summary of its own into the same directory
    first (without either field), so a run killed between the two is not taken for finished."""
    try:
        summary = json.loads((directory / SUMMARY).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(summary, dict) or summary.get("status") != "done" or "host" not in summary:
        return None
    return summary


def lock_path(directory: Path) -> Path:
    """The run lock of the run in ``directory``: beside it, not in it, as the run's directory
    must start empty (a run refuses a directory holding anything) and is wiped when the run
    starts afresh. It is never removed: removing a lock file others may wait on is racy."""
    return directory.with_name(f".{directory.name}.lock")


#: What ``flock`` raises on a file system that does not offer it (Lustre mounted without
#: ``flock``, NFS without its lock daemon): the run goes on unlocked rather than failing.
_NO_LOCKS: Final = frozenset({errno.ENOLCK, errno.ENOSYS, errno.EOPNOTSUPP, errno.EINVAL})
_warned_no_locks = False


def _flock(fd: int, operation: int) -> bool:
    """``flock``; False (and a warning, once per process) where the file system has none."""
    global _warned_no_locks
    try:
        fcntl.flock(fd, operation)
    except BlockingIOError:
        raise
    except OSError as exc:
        if exc.errno not in _NO_LOCKS:
            raise
        if not _warned_no_locks:
            _warned_no_locks = True
            log.warning(
                "the study's file system offers no locks (%s): runs go on unlocked, so a run "
                "asked for twice at once (the study started twice, a lost Dask result) may "
                "run twice; its result is the same either way",
                exc.strerror or exc,
            )
        return False
    return True


@contextlib.contextmanager
def run_lock(directory: Path, *, wait: bool = True) -> Iterator[bool]:
    """Hold the run lock of ``directory`` for the block; yields whether it is held.

    ``wait=True`` waits while another process holds it (however long its run takes: that
    process is running this very run) and always yields True; ``wait=False`` yields False at
    once instead. ``flock``, not ``fcntl`` record locks: two threads of one Dask worker exclude
    each other too, as each opens the file for itself. The kernel releases the lock when its
    holder ends, so a killed worker leaves no run locked.
    """
    path = lock_path(directory)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDONLY | os.O_CREAT | os.O_CLOEXEC, 0o666)
    try:
        try:
            _flock(fd, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        yield True
    finally:
        os.close(fd)  # releases the lock


def run_busy(directory: Path) -> bool:
    """Whether another process holds the run lock of ``directory`` now (is running that run)."""
    try:
        fd = os.open(lock_path(directory), os.O_RDONLY | os.O_CLOEXEC)
    except FileNotFoundError:
        return False  # never started
    try:
        _flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False


def check_task(task: dict[str, Any]) -> None:
    """Decode ``task``'s parameters as its run would, running nothing: a
    :class:`~minimize_surprise.errors.ConfigError` naming the bad key (the key within
    ``params``), or naming the kind when it is none of :data:`KINDS`."""
    kind = task["kind"]
    _runner(kind)
    if kind == RECORDED:
        return  # its params are checked with the study file (studies.spec), its run when read
    if kind == "qd":
        from master_service.experiments.qd_run import qd_experiment

        qd_experiment(task_experiment(task))
    elif kind in _KIND_RUNNERS:
        experiment = task_experiment(task)
        if kind == "evolved" and experiment.evolution.evaluations is None:
            # An endless run (docs/changing-arenas.md) is for a person to stop; a study would
            # wait for it forever.
            raise ConfigError(
                "a study's run needs a number of evaluations: an endless run never ends",
                file="<task>",
                key="evolution.evaluations",
            )
    else:
        from gridworld.tasks import check_params

        check_params(kind, task["params"])


def run_task(task: dict[str, Any], root: str) -> dict[str, Any]:
    """Run ``task`` into its directory below ``root``; return (and write) its summary.

    A run that finished is not run again: its stored summary is the result. Raises only
    :class:`DiskFullError` (the run stays pending).
    """
    directory = run_dir(root, task)
    with naming_full_disk(directory), run_lock(directory):
        stored = stored_summary(directory)
        if stored is not None:
            return stored
        return _run_afresh(task, directory)


def task_base(task: dict[str, Any]) -> dict[str, Any]:
    """The fields of a task every summary of its run repeats."""
    return {key: task[key] for key in ("group", "kind", "seed", "sweep", "run")}


def _run_afresh(task: dict[str, Any], directory: Path) -> dict[str, Any]:
    # A directory without a summary is what a killed run left: start it afresh.
    if directory.exists():
        shutil.rmtree(directory)
    started = time.perf_counter()
    try:
        with quiet():
            result = _runner(task["kind"])(task, directory)
        summary = {**task_base(task), "status": "done", **result}
    except BaseException as exc:
        if isinstance(exc, KeyboardInterrupt | SystemExit):
            raise
        summary = failed_summary(task, directory, exc)
    return write_summary(directory, summary, time.perf_counter() - started)


def failed_summary(task: dict[str, Any], directory: Path, exc: BaseException) -> dict[str, Any]:
    """The summary of a run that raised ``exc``, its traceback written to ``error.txt``; a full
    disk is raised again instead (not the run's fault: it stays pending, not failed)."""
    if disk_full(exc, directory):
        raise exc
    directory.mkdir(parents=True, exist_ok=True)
    text = "".join(traceback.format_exception(exc))
    (directory / ERROR).write_text(text, encoding="utf-8")
    return {**task_base(task), "status": "failed", "error": f"{type(exc).__name__}: {exc}"}


def write_summary(directory: Path, summary: dict[str, Any], seconds: float) -> dict[str, Any]:
    """``summary`` with its ``seconds`` and ``host``, written as the run's last file:
    ``summary.json`` when done (atomically, never left empty: it marks the run finished),
    ``failed.json`` when failed."""
    summary |= {"seconds": seconds, "host": os.uname().nodename}
    write_json(directory / (SUMMARY if summary["status"] == "done" else FAILED), summary)
    return summary


# --------------------------------------------------------------------------- the kinds


#: An evolved run's options beside its experiment: ``plots`` (draw its pictures; default
#: false) and ``traces`` (keep its post-evaluation traces; default true).
_RUN_OPTIONS = ("plots", "traces")


def task_experiment(task: dict[str, Any]) -> Any:
    """The experiment of an evolved or random task (its ``params`` decoded, its seed)."""
    from master_service.experiments.simulation_setup import simulation_experiment

    params = dict(task["params"])
    for key in _RUN_OPTIONS:  # the study's, not the experiment's
        if not isinstance(params.pop(key, False), bool):
            raise ConfigError("expected true or false", key=key)
    return simulation_experiment(data=params, seed=task["seed"])


def _run_evolved(task: dict[str, Any], directory: Path) -> dict[str, Any]:
    from master_service.experiments.engine_run import FastRun

    experiment = task_experiment(task)
    # No pictures per run unless asked: they cost a run about 4 s of its 20 to 30 (the study's
    # report draws its own figures; `surprise-master report RUN` draws any run's).
    result = FastRun(experiment).run(directory, plots=run_plots(task))
    return evolved_summary(task, experiment, directory, result)


def run_plots(task: dict[str, Any]) -> bool:
    """Whether an evolved run draws its pictures (its ``plots`` option; default false)."""
    return bool(task["params"].get("plots", False))


def evolved_summary(
    task: dict[str, Any], experiment: Any, directory: Path, result: Any
) -> dict[str, Any]:
    """What an evolved run's summary holds, from its :class:`~master_service.experiments.
    simulation_setup.SimulatedRun` ``result``; drops the traces if the task says so."""
    from runfiles.schema import TRACES

    if result is None:  # only when told to stop, and nothing here tells it to
        raise RuntimeError(f"the evolved run in {directory} stopped before its end")
    if not task["params"].get("traces", True):
        # The summary below keeps what the study's report needs; the traces (11 MB a run of 10
        # robots, 1.1 GB of 1000) only serve `surprise-master report RUN` and replays of the
        # post-evaluation's behaviour. A crash before the summary is written reruns the run.
        shutil.rmtree(directory / TRACES, ignore_errors=True)
    metrics = result.metrics
    post = metrics.get("post_evaluation") or {}
    sensors = post.get("sensors") or {}
    safety = metrics.get("safety") or {}
    return {
        "scenario": experiment.scenario,
        "setting": experiment.setting,
        "robots": experiment.robots,
        "evaluations": result.summary.evaluations,
        "best_fitness": result.summary.best_fitness,
        "fitness": result.summary.best_fitness,
        "post_fitness": result.summary.post_evaluation_fitness,
        "behaviour": post.get("behaviour"),
        # How much the safety layer drove, as a recorded run's summary says it (a feature of the
        # study's clustering).
        "safety_share": safety.get("post_evaluation_share"),
        "evolution_safety_share": safety.get("evolution_mean_share"),
        "sensors": list(sensors),
        "mean_sensors": [v["mean_real"] for v in sensors.values()],
        "mean_predictions": [v["mean_predicted"] for v in sensors.values()],
        "evaluations_file": "evaluations.csv",
        # Fitness around each change of the arena (none: it never changed).
        "recovery": metrics.get("recovery"),
    }


def _run_random(task: dict[str, Any], directory: Path) -> dict[str, Any]:
    from master_service.experiments.baseline import run_baseline

    experiment = task_experiment(task)
    data = run_baseline(experiment, 1, directory)
    (pair,) = data["pairs"]
    return {
        "scenario": experiment.scenario,
        "setting": experiment.setting,
        "robots": experiment.robots,
        "best_fitness": pair["fitness"],
        "fitness": pair["fitness"],
        "post_fitness": pair["post_fitness"],
        "behaviour": pair["behaviour"],
        "sensors": list(experiment.sensors),
        "mean_sensors": pair["mean_sensors"],
        "mean_predictions": pair["mean_predictions"],
    }


def _run_qd(task: dict[str, Any], directory: Path) -> dict[str, Any]:
    from master_service.experiments.qd_run import QDRun

    experiment = task_experiment(task)
    result = QDRun(experiment).run(directory, plots=run_plots(task))
    assert result is not None, "nothing tells a study's run to stop"
    s = result.summary
    elites = s.classes
    return {
        "scenario": experiment.scenario,
        "setting": experiment.setting,
        "robots": experiment.robots,
        "evaluations": s.evaluations,
        "best_fitness": max((e.fitness for e in elites.values()), default=None),
        "fitness": max((e.fitness for e in elites.values()), default=None),
        "cells": s.cells,
        "coverage": s.coverage,
        "qd_score": s.qd_score,
        "classes": {
            name: {"fitness": e.fitness, "post_fitness": e.post_fitness, "post_class": e.post_class}
            for name, e in elites.items()
        },
    }


def _run_grid(task: dict[str, Any], directory: Path) -> dict[str, Any]:
    from gridworld.tasks import run_task as run_grid_task

    params = dict(task["params"])
    if isinstance(params.get("genome_run"), str):
        params["genome_run"] = str(_study_run(task, directory, params["genome_run"]))
    summary = run_grid_task(task["kind"], params, task["seed"], directory)
    summary.pop("seed", None)
    summary.pop("kind", None)
    return summary


def _study_run(task: dict[str, Any], directory: Path, name: str) -> Path:
    # Another run of the same study, named below its runs/ folder; {seed} is this run's seed.
    # An absolute path is any run's directory.
    try:
        name = name.format(seed=task["seed"])
    except (KeyError, IndexError, ValueError) as exc:
        raise ConfigError(
            f"{name!r}: only {{seed}} may be filled in ({exc})", file="<params>", key="genome_run"
        ) from None
    runs_root = directory.parents[len(Path(task["run"]).parts) - 1]
    return runs_root / name


def _run_recorded(task: dict[str, Any], directory: Path) -> dict[str, Any]:
    # Reads the run where it is and writes nothing there; this directory keeps the summary.
    directory.mkdir(parents=True, exist_ok=True)
    return read_recorded(task["params"]["source"])


_KIND_RUNNERS = {
    "evolved": _run_evolved,
    "random": _run_random,
    "qd": _run_qd,
    RECORDED: _run_recorded,
}


def _runner(kind: str) -> Callable[[dict[str, Any], Path], dict[str, Any]]:
    # The function running a task of this kind; an unknown kind is a ConfigError naming the
    # kinds this installation knows (the grid world's only when gridworld is installed).
    if kind not in KINDS:
        raise ConfigError(
            f"unknown run kind {kind!r}; expected one of: {', '.join(KINDS)}",
            file="<task>",
            key="kind",
        )
    return _KIND_RUNNERS.get(kind, _run_grid)


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """The master's per-evaluation logging kept in each run's own files: a study runs hundreds
    of runs."""
    logger = logging.getLogger("master_service")
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)
