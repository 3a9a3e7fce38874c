"""Recorded runs: finished run directories (the lab's real-robot runs) as a study's group.

A group of kind ``recorded`` runs nothing. Its ``params`` name run directories made by
``surprise-master run`` on the robots (or any finished run), as paths or globs relative to the
study file::

    - name: real
      kind: recorded
      params: {runs: ["../lab-runs/run-*"]}

Each directory it matches is one task of the study (:func:`studies.spec.expand`): the task
reads the directory and returns a summary shaped like an evolved run's (:func:`read_recorded`),
so that the report's tables, statistics and figures take the group like any other. The
directory is only read, never written: the study's own ``runs/<group>/<name>/`` holds the
summary, whose ``source`` says where the run is. The study's report reads the run again
(:func:`refreshed`), so that a class added later by ``surprise-master report RUN --positions
TRACKER.csv`` shows without running the study again.

A run that is missing, unfinished (no post-evaluation) or unreadable (a newer format, no
``config.yaml``) is a :class:`RecordedRunError` naming the directory and the reason: its task
fails alone, and the report says so in one line.
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
import re
from pathlib import Path
from typing import Any, Final

from minimize_surprise.config import Strict
from minimize_surprise.errors import ConfigError, SurpriseError
from runfiles import schema
from runfiles.schema import (
    EVALUATIONS,
    METRICS,
    Checkpoint,
    PostEvaluation,
    RunDirError,
    Simulation,
)

__all__ = [
    "RECORDED",
    "RecordedParams",
    "RecordedRunError",
    "absolute_patterns",
    "matching_runs",
    "read_recorded",
    "refreshed",
    "source_names",
]

#: The kind of a group of recorded runs.
RECORDED: Final = "recorded"

#: Why a real run has no class, when neither it nor its metrics.json holds positions: what to do.
_TRACK_IT: Final = (
    "no positions: track the post-evaluation and run `surprise-master report RUN --positions "
    "TRACKER.csv`, which writes metrics.json with the class"
)


class RecordedParams(Strict, frozen=True):
    """The ``params`` of a ``recorded`` group: which run directories it reads."""

    #: run directories, as paths or globs (``run-*``, ``**/run-*``) relative to the study file
    #: (at least one); each must match at least one directory when the study runs
    runs: list[str]

    def __post_init__(self) -> None:
        if not self.runs:
            raise ValueError("`runs`: give at least one run directory (a path or a glob)")


class RecordedRunError(SurpriseError, RuntimeError):
    """A recorded run cannot stand in the study: ``source`` the directory, ``reason`` why
    (missing, unfinished, unreadable)."""

    def __init__(self, source: str | Path, reason: str) -> None:
        self.source = str(source)
        self.reason = reason
        super().__init__(f"recorded run {source} is {reason}")

    def __reduce__(self) -> tuple[Any, ...]:
        # Crosses process boundaries (a worker's error): rebuild it from its fields.
        return type(self), (self.source, self.reason)


def absolute_patterns(runs: list[str], base: Path) -> list[str]:
    """The paths or globs ``runs`` with a relative one taken relative to ``base`` (the study
    file's directory) and ``~`` expanded: so a study copied elsewhere still finds them."""
    out = []
    for pattern in runs:
        path = Path(os.path.expanduser(pattern))
        # Normalised: `studies/../lab-runs/run-1` and `lab-runs/run-1` are one source.
        out.append(os.path.normpath(path if path.is_absolute() else base.resolve() / path))
    return out


def matching_runs(pattern: str) -> list[Path]:
    """The directories ``pattern`` (a path or a glob, ``**`` included) matches, sorted."""
    return sorted(Path(p) for p in glob.glob(pattern, recursive=True) if Path(p).is_dir())


def source_names(sources: list[Path]) -> list[str]:
    """A name below the group's directory for each source: its directory's name, made safe as a
    path, and made unique by a hash of its whole path where two sources share a name. It
    depends only on the source, so a run keeps its name when the lab adds others."""
    safe = [re.sub(r"[^A-Za-z0-9._=,-]", "_", p.name) or "run" for p in sources]
    names = []
    for path, name in zip(sources, safe, strict=True):
        if safe.count(name) > 1:
            name += "-" + hashlib.sha1(str(path).encode()).hexdigest()[:8]
        names.append(name)
    return names


def read_recorded(source: str | Path) -> dict[str, Any]:
    """What the study's report needs of the finished run in ``source``, as an evolved run's
    summary holds it: scenario, setting, robots, evaluations, the best fitness (the last row of
    ``evaluations.csv``), the post-evaluation's fitness, the behaviour metrics (or
    ``behaviour_missing``, why there are none), the sensors' mean prediction and reading, the
    safety layer's share, whether the run was real (no ``simulation.json``), and ``source``.

    The metrics are computed as ``surprise-master report`` computes them, without writing; a
    real run's behaviour comes from its ``metrics.json`` when a report with a tracker's
    positions wrote one. Raises :class:`RecordedRunError` naming the directory and the reason.
    """
    from reporting.report import compute_metrics

    source = Path(source)
    if not source.is_dir():
        raise RecordedRunError(source, "missing: no such directory")
    try:
        config = schema.read_config(source)
        checkpoint = schema.read(source, Checkpoint)
        post = schema.read(source, PostEvaluation)
    except (RunDirError, ConfigError, OSError) as exc:
        raise RecordedRunError(source, f"unreadable: {exc}") from None
    experiment = config.experiment
    if experiment is None:
        raise RecordedRunError(source, "unreadable: its config.yaml names no experiment")
    if post is None:
        done = "no evaluation" if checkpoint is None else f"{checkpoint.evaluations} evaluations"
        raise RecordedRunError(
            source,
            f"unfinished: no post-evaluation yet ({done} of {experiment.evolution.evaluations})",
        )
    try:
        metrics = compute_metrics(source)
    except (RunDirError, ConfigError, OSError, ValueError, KeyError) as exc:
        raise RecordedRunError(source, f"unreadable: {exc}") from None
    if metrics.get("best_fitness") is None:
        raise RecordedRunError(source, f"unreadable: its {EVALUATIONS} holds no evaluation")
    evaluated = metrics["post_evaluation"] or {}
    behaviour, positions = evaluated.get("behaviour"), None
    real = not (source / Simulation.FILE).is_file()
    if behaviour is None:
        behaviour, positions = _tracked_behaviour(source)
    sensors = evaluated.get("sensors") or {}
    safety = metrics.get("safety") or {}
    summary: dict[str, Any] = {
        "source": str(source),
        "real": real,
        "run_id": metrics["run_id"],
        "scenario": experiment.scenario,
        "setting": experiment.setting,
        "robots": len(post.robots) or experiment.robots,
        "evaluations": metrics["evaluations"],
        "best_fitness": metrics["best_fitness"],
        "fitness": metrics["best_fitness"],
        "post_fitness": post.swarm_fitness,
        "behaviour": behaviour,
        "sensors": list(sensors),
        "mean_sensors": [v["mean_real"] for v in sensors.values()],
        "mean_predictions": [v["mean_predicted"] for v in sensors.values()],
        "safety_share": safety.get("post_evaluation_share"),
        "evolution_safety_share": safety.get("evolution_mean_share"),
        # Absolute: the study's report reads the curve where the run is.
        "evaluations_file": str(source / EVALUATIONS),
    }
    if positions is not None:
        summary["positions"] = positions
    if behaviour is None:
        summary["behaviour_missing"] = _TRACK_IT if real else evaluated.get("behaviour_missing")
    return summary


def _tracked_behaviour(source: Path) -> tuple[dict[str, Any] | None, str | None]:
    # A real run's behaviour, from the metrics.json a report with a tracker's file wrote (the
    # run's traces hold no positions; the tracker's file is the lab's, not found here).
    try:
        stored = json.loads((source / METRICS).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None, None
    post = stored.get("post_evaluation") if isinstance(stored, dict) else None
    if not isinstance(post, dict) or not isinstance(post.get("behaviour"), dict):
        return None, None
    tracked = post.get("positions")
    return post["behaviour"], tracked.get("file") if isinstance(tracked, dict) else None


def refreshed(task: dict[str, Any], stored: dict[str, Any]) -> dict[str, Any]:
    """The summary of a recorded ``task`` read again from its run (the study's report does: a
    class may have been added since), over the ``stored`` one; a run that cannot be read now is
    failed with the reason, unless it was read before and has since gone (a study archived
    without the lab's disk): then the stored summary stands."""
    base = {key: task[key] for key in ("group", "kind", "seed", "sweep", "run")}
    kept: dict[str, Any] = {key: stored[key] for key in ("seconds", "host") if key in stored}
    try:
        return {**base, "status": "done", **read_recorded(task["params"]["source"]), **kept}
    except RecordedRunError as exc:
        if stored.get("status") == "done" and not Path(exc.source).exists():
            return stored
        return {**base, "status": "failed", "error": str(exc), **kept}
