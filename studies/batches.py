"""Runs of a study stepped together: a batch is a plain list of tasks, run by one worker.

Evolved runs whose swarms have the same shape (robots, sensors, network, safety rules and
evaluation length; arenas, boxes and seeds may differ) are run as one batch
(:func:`run_tasks`): one process evolves them side by side and evaluates all their swarms in one
compiled call per evaluation, their networks as lanes of one set of arrays
(:func:`master_service.experiments.engine_run.run_batch`). Each run keeps its own seed,
evolution, checkpoints, directory, lock and summary, and ends exactly as it would alone. Any
other task is a batch of one. :func:`plan_batches` makes the batches of a study's stage.

A run's ``seconds`` in a batch is its share of the batch's time (the batch's divided by its
runs), its ``batch`` the number of runs stepped with it.
"""

from __future__ import annotations

import contextlib
import json
import math
import shutil
import time
from pathlib import Path
from typing import Any, Final

import msgspec

from minimize_surprise.events import RobotsJoin, RobotsLeave
from studies.tasks import (
    evolved_summary,
    failed_summary,
    naming_full_disk,
    quiet,
    run_dir,
    run_lock,
    run_plots,
    run_task,
    stored_summary,
    task_base,
    task_experiment,
    write_summary,
)

__all__ = ["BATCH_RUNS", "batch_key", "plan_batches", "run_tasks"]

#: The events that change a swarm's size (runs of one batch must share them).
_SWARM_EVENTS = (RobotsLeave, RobotsJoin)

#: Runs per batch at most, by default: four runs of ten robots fill five vectors of eight lanes
#: exactly, and four of four robots two; more lanes gain little (benchmarks/engine.py).
BATCH_RUNS: Final = 4


def batch_key(task: dict[str, Any]) -> str | None:
    """What runs of one batch share, as text; None for a task that runs alone (not evolved, or
    its parameters do not decode: it fails alone with its own error)."""
    if task["kind"] != "evolved":
        return None
    from master_service.experiments.simulation_setup import simulated_safety, world_config
    from minimize_surprise.network import spec_from_config

    try:
        experiment = task_experiment(task)
        sensors = world_config(experiment).sensors
        safety = simulated_safety(experiment)
    except Exception:
        return None
    shape = (
        repr(spec_from_config(experiment)),
        experiment.robots,
        list(sensors),
        repr(safety),
        experiment.evaluation_steps,
        experiment.post_evaluation_steps,
        run_plots(task),
        # The swarm's size changes with these: at the same evaluations in every run of a batch.
        [msgspec.to_builtins(e) for e in experiment.events if isinstance(e, _SWARM_EVENTS)],
    )
    if any(e.seconds is not None for e in experiment.events if isinstance(e, _SWARM_EVENTS)):
        return None  # when is the wall clock's: alone
    return json.dumps(shape)


def plan_batches(
    tasks: list[dict[str, Any]], workers: int, size: int = BATCH_RUNS
) -> list[list[dict[str, Any]]]:
    """``tasks`` in batches of compatible runs, at most ``size`` each, and no larger than keeps
    every one of ``workers`` busy; the batches of several runs first (the long ones), then the
    runs alone (a study's random pairs, a tenth of a second each), each in the order of their
    first task. With more than twice as many batches of several runs as workers, the last
    ``workers`` of them are split into runs alone: at the end of a study the workers then
    finish within a run of each other, not a batch."""
    groups: dict[str | None, list[dict[str, Any]]] = {}
    alone: list[list[dict[str, Any]]] = []
    order: list[tuple[int, list[dict[str, Any]]]] = []
    for index, task in enumerate(tasks):
        key = batch_key(task) if size > 1 else None
        if key is None:
            alone.append([task])
            order.append((index, alone[-1]))
            continue
        if key not in groups:
            groups[key] = []
            order.append((index, groups[key]))
        groups[key].append(task)
    batches: list[list[dict[str, Any]]] = []
    for _, group in sorted(order, key=lambda item: item[0]):
        width = max(1, min(size, math.ceil(len(group) / max(1, workers))))
        batches += [group[i : i + width] for i in range(0, len(group), width)]
    several = [b for b in batches if len(b) > 1]
    alone = [b for b in batches if len(b) == 1]
    if len(several) <= 2 * workers:
        return several + alone
    cut = len(several) - workers
    return several[:cut] + [[task] for batch in several[cut:] for task in batch] + alone


def run_tasks(tasks: list[dict[str, Any]], root: str) -> list[dict[str, Any]]:
    """Run a batch of tasks (see the module docstring) into their directories below ``root``;
    their summaries, in order. A finished run is not run again; a run that fails fails alone.
    Raises only :class:`~studies.tasks.DiskFullError` (the runs stay pending)."""
    if len(tasks) == 1 or tasks[0]["kind"] != "evolved":
        return [run_task(task, root) for task in tasks]
    directories = [run_dir(root, task) for task in tasks]
    with contextlib.ExitStack() as stack:
        for directory in directories:
            stack.enter_context(naming_full_disk(directory))
            stack.enter_context(run_lock(directory))
        summaries: list[dict[str, Any] | None] = [stored_summary(d) for d in directories]
        todo = [i for i, summary in enumerate(summaries) if summary is None]
        for i, summary in zip(todo, _run_evolved_batch(tasks, directories, todo), strict=True):
            summaries[i] = summary
    return [summary for summary in summaries if summary is not None]


def _run_evolved_batch(
    tasks: list[dict[str, Any]], directories: list[Path], todo: list[int]
) -> list[dict[str, Any]]:
    from master_service.experiments.engine_run import FastRun, run_batch

    started = time.perf_counter()
    runs, experiments, ready, summaries = [], [], [], {}
    for i in todo:
        if directories[i].exists():  # what a killed run left: start it afresh
            shutil.rmtree(directories[i])
        try:
            experiment = task_experiment(tasks[i])
            runs.append((FastRun(experiment), directories[i]))
        except Exception as exc:
            summaries[i] = failed_summary(tasks[i], directories[i], exc)
            continue
        experiments.append(experiment)
        ready.append(i)
    with quiet():
        outcomes = run_batch(runs, plots=run_plots(tasks[todo[0]])) if runs else []
    for i, experiment, outcome in zip(ready, experiments, outcomes, strict=True):
        task, directory = tasks[i], directories[i]
        try:
            if isinstance(outcome, BaseException):
                raise outcome
            result = evolved_summary(task, experiment, directory, outcome)
            summaries[i] = {**task_base(task), "status": "done", **result, "batch": len(ready)}
        except Exception as exc:
            summaries[i] = failed_summary(task, directory, exc)
    share = (time.perf_counter() - started) / max(1, len(ready))
    return [write_summary(directories[i], summaries[i], share) for i in todo]
