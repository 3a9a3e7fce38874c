"""Run a study: every task on an executor, the finished ones skipped, progress on the terminal.

The study's directory holds ``study.yaml`` (the study file as it was run: running another study
into the same directory is refused), ``tasks.json`` (every run, in order) and ``runs/`` (one
directory per run). A study killed and run again skips the runs whose summary exists and runs
the others afresh, so each run is done once. A failed run is recorded (``failed.json`` and
``error.txt`` in its directory) and does not stop the others; it is run again next time. Groups
that use other groups' runs (``after``) are submitted once those have ended.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from studies.executors import Executor
from studies.spec import expand, load_study, task_stages
from studies.tasks import FAILED, finished, is_finished, run_dir, run_task
from surprise.errors import ConfigError
from surprise.files import write_json

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
    study = load_study(study_path)
    text = study_path.read_text(encoding="utf-8")
    kept = out / STUDY_FILE
    if kept.exists() and kept.read_text(encoding="utf-8") != text:
        raise ConfigError(
            f"{out} holds another study (its {STUDY_FILE} differs): choose another --out",
            file=str(study_path),
        )
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(study_path, kept)
    tasks = expand(study)
    (out / TASKS_FILE).write_text(json.dumps(tasks, indent=1), encoding="utf-8")
    return tasks


def run_study(
    study_path: str | Path,
    out: str | Path,
    executor: Executor,
    *,
    on_update: Callable[[Counts, float], None] | None = None,
) -> Counts:
    """Run every unfinished task of the study into ``out``; the counts at the end.

    ``on_update(counts, elapsed_s)`` is called after every completed run.
    """
    out = Path(out)
    tasks = prepare(study_path, out)
    counts = Counts(total=len(tasks))
    pending = []
    for task in tasks:
        if is_finished(out, task):
            counts.done += 1
            counts.skipped += 1
        else:
            pending.append(task)
    started = time.monotonic()
    left = len(pending)
    counts.running = min(left, executor.workers)
    if on_update is not None:
        on_update(counts, 0.0)
    # A group that uses other groups' runs (``after``) starts once they have all ended.
    for stage in task_stages(pending):
        futures = {executor.submit(run_task, task, str(out)): task for task in stage}
        for future in executor.as_completed(futures):
            task = futures[future]
            left -= 1
            try:
                summary = future.result()
            except Exception as exc:  # the worker itself died (killed, out of memory)
                summary = {"run": task["run"], "status": "failed", "error": f"worker: {exc!r}"}
                directory = run_dir(out, task)
                directory.mkdir(parents=True, exist_ok=True)
                write_json(directory / FAILED, summary)
            if summary.get("status") == "done":
                counts.done += 1
            else:
                counts.failed += 1
                counts.failures.append(summary)
            counts.running = min(left, executor.workers)
            if on_update is not None:
                on_update(counts, time.monotonic() - started)
    return counts


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
