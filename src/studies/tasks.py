"""One run of a study: a plain function of plain data, so that any executor can run it.

:func:`run_task` takes a task (see :func:`studies.spec.expand`) and the study's directory, runs
it into ``runs/<task["run"]>``, and returns a plain summary, which it also writes there as
``summary.json`` (last, atomically: a run is finished exactly when its summary exists). A run
that raises leaves ``error.txt`` with the traceback and ``failed.json``, and returns a summary
with ``status: failed``; it never raises itself, so one broken run cannot stop a study. The same
task gives the same result on whichever machine runs it: every random draw is seeded by the
task's seed.

Kinds:

* ``evolved``: an evolved run on the engine (``surprise-master sim --engine fast``), its
  ``params`` an experiment file's content; the summary holds the best and the post-evaluation
  fitness, the behaviour metrics of the post-evaluation and the mean predicted and real value of
  each sensor.
* ``random``: one random network pair in a freshly reset arena (``surprise-master baseline``).
* ``grid-*``: the grid world's kinds (``gridworld.tasks``), when that package is installed. A
  relative ``genome_run`` (reruns and damage of an evolved genome) names another run of the
  study below its ``runs/``, e.g. ``evolved/size=16/seed-{seed}`` with the run's own seed.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import time
import traceback
from pathlib import Path
from typing import Any

from surprise.errors import ConfigError
from surprise.files import write_json

__all__ = [
    "ERROR",
    "FAILED",
    "KINDS",
    "RUNS",
    "SUMMARY",
    "check_task",
    "finished",
    "is_finished",
    "run_dir",
    "run_task",
]

#: The summary a finished run leaves in its directory.
SUMMARY = "summary.json"
#: What a failed run leaves in its directory: the traceback, and its summary (it is run again
#: when the study is).
ERROR = "error.txt"
FAILED = "failed.json"
#: Where a study's runs live, below its directory.
RUNS = "runs"


def _grid_kinds() -> tuple[str, ...]:
    try:
        from gridworld.tasks import GRID_KINDS
    except ImportError:
        return ()
    return tuple(GRID_KINDS)


#: Every run kind this installation can run.
KINDS: tuple[str, ...] = ("evolved", "random", *_grid_kinds())


def run_dir(root: str | Path, task: dict[str, Any]) -> Path:
    """Where ``task`` runs, below the study directory ``root``."""
    return Path(root) / RUNS / task["run"]


def is_finished(root: str | Path, task: dict[str, Any]) -> bool:
    """Whether ``task`` finished (its summary exists)."""
    return finished(run_dir(root, task))


def finished(directory: Path) -> bool:
    """Whether the run in ``directory`` finished: its summary is this module's, with status
    done. A grid run writes a summary of its own into the same directory first, so a run killed
    between the two is not taken for finished."""
    try:
        summary = json.loads((directory / SUMMARY).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(summary, dict) and summary.get("status") == "done"


def check_task(task: dict[str, Any]) -> None:
    """Decode ``task``'s parameters as its run would, running nothing: a
    :class:`~surprise.errors.ConfigError` naming the bad key (the key within ``params``)."""
    if task["kind"] in _KIND_RUNNERS:
        _experiment(task)
    else:
        from gridworld.tasks import check_params

        check_params(task["kind"], task["params"])


def run_task(task: dict[str, Any], root: str) -> dict[str, Any]:
    """Run ``task`` into its directory below ``root``; return (and write) its summary."""
    directory = run_dir(root, task)
    # A directory without a summary is what a killed run left: start it afresh.
    if directory.exists() and not finished(directory):
        shutil.rmtree(directory)
    directory.parent.mkdir(parents=True, exist_ok=True)
    base = {key: task[key] for key in ("group", "kind", "seed", "sweep", "run")}
    started = time.perf_counter()
    try:
        with _quiet():
            result = _KIND_RUNNERS.get(task["kind"], _run_grid)(task, directory)
        summary = {**base, "status": "done", **result}
    except BaseException as exc:
        if isinstance(exc, KeyboardInterrupt | SystemExit):
            raise
        directory.mkdir(parents=True, exist_ok=True)
        (directory / ERROR).write_text(traceback.format_exc(), encoding="utf-8")
        summary = {**base, "status": "failed", "error": f"{type(exc).__name__}: {exc}"}
    summary["seconds"] = time.perf_counter() - started
    summary["host"] = os.uname().nodename
    # the summary marks the run finished: written atomically, never left empty
    write_json(directory / (SUMMARY if summary["status"] == "done" else FAILED), summary)
    return summary


# --------------------------------------------------------------------------- the kinds


def _experiment(task: dict[str, Any]):
    from master_service.simulation_setup import simulation_experiment

    params = dict(task["params"])
    params.pop("plots", None)
    return simulation_experiment(data=params, seed=task["seed"])


def _run_evolved(task: dict[str, Any], directory: Path) -> dict[str, Any]:
    from master_service.engine_run import FastRun

    experiment = _experiment(task)
    result = FastRun(experiment).run(directory, plots=bool(task["params"].get("plots", True)))
    metrics = result.metrics
    post = metrics.get("post_evaluation") or {}
    sensors = post.get("sensors") or {}
    return {
        "scenario": experiment.scenario,
        "setting": experiment.setting,
        "robots": experiment.robots,
        "evaluations": result.summary.evaluations,
        "best_fitness": result.summary.best_fitness,
        "fitness": result.summary.best_fitness,
        "post_fitness": result.summary.post_evaluation_fitness,
        "behaviour": post.get("behaviour"),
        "sensors": list(sensors),
        "mean_sensors": [v["mean_real"] for v in sensors.values()],
        "mean_predictions": [v["mean_predicted"] for v in sensors.values()],
        "evaluations_file": "evaluations.csv",
    }


def _run_random(task: dict[str, Any], directory: Path) -> dict[str, Any]:
    from master_service.baseline import run_baseline

    experiment = _experiment(task)
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


_KIND_RUNNERS = {"evolved": _run_evolved, "random": _run_random}


@contextlib.contextmanager
def _quiet():
    # A study runs hundreds of runs: their per-evaluation logging stays in their own files.
    logger = logging.getLogger("master_service")
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)
