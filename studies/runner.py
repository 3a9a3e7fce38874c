"""Run a study: every task on an executor, the finished ones skipped, progress on the terminal.

The study's directory holds ``study.yaml`` (the study file as it was run: running another study
into the same directory is refused), ``tasks.json`` (every run, in order) and ``runs/`` (one
directory per run). A study killed and run again skips the runs whose summary exists and runs
the others afresh, so each run is done once. A failed run is recorded (``failed.json`` and
``error.txt`` in its directory) and does not stop the others; it is run again next time. Groups
that use other groups' runs (``after``) are submitted once those have ended. The recorded runs
of a study (:mod:`studies.recorded`) may differ between its starts: a run the lab recorded since
joins it in the same directory.

What a cluster loses, the runner does not take for a failed run:

* a worker: Dask runs its tasks again elsewhere; a run that had finished is not run again (the
  task returns its stored summary), and a result once read is released, so Dask does not
  compute it again to restore it;
* the scheduler: :class:`~studies.executors.SchedulerLostError`, every run not finished left
  pending, for the same command to finish once a scheduler is back;
* a full disk: :class:`~studies.tasks.DiskFullError` naming the path, the runs left pending;
* the study itself (killed while its tasks still run on the cluster): started again, it waits
  for those tasks through the runs' locks and takes their results (``on_notice`` says so).
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from minimize_surprise.errors import ConfigError
from minimize_surprise.files import write_json
from minimize_surprise.text import plural
from studies.batches import BATCH_RUNS, plan_batches, run_tasks
from studies.executors import Executor, SchedulerLostError
from studies.recorded import RECORDED
from studies.spec import expand, load_study, task_stages
from studies.tasks import (
    FAILED,
    DiskFullError,
    finished,
    is_finished,
    naming_full_disk,
    run_busy,
    run_dir,
    run_lock,
    stored_summary,
)

__all__ = [
    "STUDY_FILE",
    "TASKS_FILE",
    "Counts",
    "find_study",
    "prepare",
    "run_study",
    "shipped_studies",
    "study_status",
]

STUDY_FILE = "study.yaml"
TASKS_FILE = "tasks.json"


@dataclass
class Counts:
    """Where a study stands: runs in all, done, running, failed (this session), left."""

    total: int
    done: int = 0
    running: int = 0
    failed: int = 0
    skipped: int = 0
    failures: list[dict[str, Any]] = field(default_factory=list)

    @property
    def left(self) -> int:
        """Runs neither done nor failed yet."""
        return self.total - self.done - self.failed

    def add(self, summary: dict[str, Any]) -> None:
        """Count a run that ended with ``summary``."""
        if summary.get("status") == "done":
            self.done += 1
        else:
            self.failed += 1
            self.failures.append(summary)


def shipped_studies() -> dict[str, Path]:
    """The study files that come with the project, by name."""
    folder = Path(__file__).resolve().parent / "files"
    return {path.stem: path for path in sorted(folder.glob("*.yaml"))}


def find_study(name: str | Path) -> Path:
    """A study file's path: ``name`` itself, or the shipped study of that name."""
    path = Path(name)
    if path.is_file():
        return path
    shipped = shipped_studies()
    if str(name) in shipped:
        return shipped[str(name)]
    raise ConfigError(
        f"no study file {name}; the shipped studies are: {', '.join(shipped) or 'none'}",
        file=str(name),
    )


def prepare(study_path: str | Path, out: str | Path) -> list[dict[str, Any]]:
    """Check the study, set up its directory, and return its tasks.

    ``study_path`` is a file or the name of a shipped study (:func:`shipped_studies`). Raises
    :class:`ConfigError` for a bad study file, or when ``out`` holds another study.
    """
    study_path, out = find_study(study_path), Path(out)
    study = load_study(study_path, find_runs=True)
    tasks = expand(study)
    kept = out / STUDY_FILE
    if kept.exists() and not _same_runs(out, tasks, study_path):
        raise ConfigError(
            f"{out} holds another study (its {STUDY_FILE} asks for other runs): choose another "
            "--out",
            file=str(study_path),
        )
    with naming_full_disk(out):
        out.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(study_path, kept)
        # Atomic: `status`, a rerun and its orphans read it while a start may be writing it.
        write_json(out / TASKS_FILE, tasks)
    return tasks


def _same_runs(out: Path, tasks: list[dict[str, Any]], study_path: Path) -> bool:
    """Whether the study kept in ``out`` asks for the same runs as ``tasks``: where it runs (its
    ``slurm`` section), comments and the like may change between starts, the runs may not."""
    kept_tasks = out / TASKS_FILE
    if not kept_tasks.exists():  # stopped between its two files: compare the study files
        kept = (out / STUDY_FILE).read_text(encoding="utf-8")
        return kept == study_path.read_text(encoding="utf-8")
    try:
        before = json.loads(kept_tasks.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    # Recorded runs aside: a lab that recorded another run goes on in the same directory.
    return _run(before) == _run(json.loads(json.dumps(tasks)))


def _run(tasks: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The tasks that run something (not those reading a recorded run)."""
    return [task for task in tasks if task.get("kind") != RECORDED]


def run_study(
    study_path: str | Path,
    out: str | Path,
    executor: Executor,
    *,
    on_update: Callable[[Counts, float], None] | None = None,
    on_notice: Callable[[str], None] | None = None,
    batch: int = BATCH_RUNS,
) -> Counts:
    """Run every unfinished task of the study into ``out``; the counts at the end.

    Compatible evolved runs go to the workers in batches of up to ``batch``, stepped together
    (:mod:`studies.batches`; 1: each run alone).

    ``on_update(counts, elapsed_s)`` is called after every completed run, ``on_notice(line)``
    with what the study waits for. Raises :class:`SchedulerLostError` or :class:`DiskFullError`
    when it cannot go on; the runs not finished then stay pending.
    """
    out = Path(out)
    tasks = prepare(study_path, out)
    counts = Counts(total=len(tasks))
    pending = [task for task in tasks if not is_finished(out, task)]
    counts.done = counts.skipped = len(tasks) - len(pending)
    busy = [task["run"] for task in pending if run_busy(run_dir(out, task))]
    if busy and on_notice is not None:
        them = "it" if len(busy) == 1 else "them"
        on_notice(
            f"{plural(len(busy), 'run')} still running from an earlier start of this study "
            f"({busy[0]}{', ...' if len(busy) > 1 else ''}): waiting for {them}, not running "
            f"{them} twice"
        )
    started = time.monotonic()
    counts.running = min(len(pending), executor.workers)

    def update() -> None:
        counts.running = min(counts.left, executor.workers)
        executor.runs_left(counts.left)
        if on_update is not None:
            on_update(counts, time.monotonic() - started)

    executor.runs_left(counts.left)
    if on_update is not None:
        on_update(counts, 0.0)
    # A group that uses other groups' runs (``after``) starts once they have all ended.
    for stage in task_stages(pending):
        _run_stage(stage, out, executor, counts, update, batch)
    return counts


def _run_stage(
    stage: list[dict[str, Any]],
    out: Path,
    executor: Executor,
    counts: Counts,
    update: Callable[[], None],
    batch: int,
) -> None:
    batches = plan_batches(stage, executor.workers, batch)
    futures = {executor.submit(run_tasks, tasks, str(out)): tasks for tasks in batches}
    try:
        for future in executor.as_completed(list(futures)):
            # Forgotten once read: a Dask cluster losing the worker that holds a result still
            # wanted would run that task again just to restore it.
            for summary in _outcomes(executor, futures.pop(future), future, out):
                counts.add(summary)
            del future
            update()
    except (SchedulerLostError, DiskFullError):
        executor.cancel(futures)  # the runs not started stay pending
        raise


def _outcomes(
    executor: Executor, tasks: list[dict[str, Any]], future: Any, out: Path
) -> list[dict[str, Any]]:
    # The summaries a batch ended with. A worker that died under it (killed, out of memory)
    # more often than the executor retries is its runs' failure, unless a run finished anyway.
    try:
        return list(executor.result(future))
    except (SchedulerLostError, DiskFullError):
        raise
    except Exception as exc:
        return [_lost(task, exc, out) for task in tasks]


def _lost(task: dict[str, Any], exc: Exception, out: Path) -> dict[str, Any]:
    directory = run_dir(out, task)
    stored = stored_summary(directory)
    if stored is not None:
        return stored
    summary = {"run": task["run"], "status": "failed", "error": f"worker: {exc!r}"}
    with naming_full_disk(directory), run_lock(directory, wait=False) as held:
        if held:  # else another process is running it: its summary will tell
            directory.mkdir(parents=True, exist_ok=True)
            write_json(directory / FAILED, summary)
    return summary


def study_status(out: str | Path) -> dict[str, Any]:
    """Where the study in ``out`` stands, per group: runs, done, failed, not yet run."""
    out = Path(out)
    tasks_file = out / TASKS_FILE
    if not tasks_file.is_file():
        raise ConfigError(f"{out} is not a study directory: {TASKS_FILE} is missing")
    tasks = json.loads(tasks_file.read_text(encoding="utf-8"))
    groups: dict[str, dict[str, int]] = {}
    for task in tasks:
        entry = groups.setdefault(
            task["group"], {"kind": task["kind"], "runs": 0, "done": 0, "failed": 0}
        )
        entry["runs"] += 1
        directory = run_dir(out, task)
        if finished(directory):
            entry["done"] += 1
        elif (directory / FAILED).is_file():
            entry["failed"] += 1
    total = {key: sum(g[key] for g in groups.values()) for key in ("runs", "done", "failed")}
    return {"groups": groups, **total}
