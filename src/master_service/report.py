"""What a run amounts to: ``metrics.json``, plots, and the one-screen status.

Plots (``plots/``): ``best_fitness.png`` (best and swarm fitness over evaluations),
``robot_fitness.png`` (each robot's fitness over evaluations), ``predictions.png`` (from the
post-evaluation: mean predicted against mean real value per sensor) and, when the traces hold poses
(simulation), ``trajectories.png``.

Behaviour metrics from the post-evaluation traces, when they hold poses (simulation): the paper's
d_R, c_o, mean cluster size and their classes, computed by :mod:`sim_stub.metrics`
(docs/method.md, "Behaviour metrics and classes"), with the box displacement d_B when the run
directory holds ``simulation.json`` (written by ``surprise-master sim``). Per robot: its path
length and its rotation.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import msgspec
import numpy as np

from master_service.master import LIVE_INTERVAL, format_duration
from master_service.rundir import (
    LIVE,
    METRICS,
    PLOTS,
    POST_EVALUATION,
    SIMULATION_FILE,
    RunDir,
    write_atomic,
)
from sim_stub import metrics as sim_metrics
from surprise.config import ExperimentConfig
from surprise.errors import ConfigError
from surprise.text import plural

__all__ = ["compute_metrics", "status_text", "write_report"]


#: A live.json older than this many refresh periods means the master is gone.
_STALE_PERIODS: Final = 5


def _rows(run: RunDir, limit: int | None) -> tuple[list[dict[str, Any]], list[str]]:
    # Rows past the checkpoint's count belong to an unfinished commit (resume drops them); the
    # last of them may be torn, so they are cut before being parsed.
    rows = run.read_rows()[:limit]
    robots = []
    if rows:
        robots = [key[len("fitness_") :] for key in rows[0] if key.startswith("fitness_")]
    typed = []
    for row in rows:
        typed.append(
            {
                "evaluation": int(row["evaluation"]),
                "kind": row["kind"],
                "fitness": float(row["fitness"]),
                "best_fitness": float(row["best_fitness"]),
                "accepted": row["accepted"] == "true",
                "attempts": int(row["attempts"]),
                "duration_s": float(row["duration_s"]),
                "robots": {robot: float(row[f"fitness_{robot}"]) for robot in robots},
            }
        )
    return typed, robots


def _traces(run: RunDir, post: dict[str, Any] | None) -> dict[str, dict[str, np.ndarray]]:
    traces: dict[str, dict[str, np.ndarray]] = {}
    if post is None:
        return traces
    for robot, entry in post.get("robots", {}).items():
        if entry.get("trace"):
            with np.load(run.path / entry["trace"]) as data:
                traces[robot] = {key: data[key] for key in data.files}
    return traces


def _post_metrics(
    post: dict[str, Any],
    traces: dict[str, dict[str, np.ndarray]],
    sensors: list[str],
    simulation: dict[str, Any] | None,
    dt: float,
) -> dict[str, Any]:
    robots: dict[str, Any] = {}
    predicted: list[np.ndarray] = []
    real: list[np.ndarray] = []
    poses: dict[str, np.ndarray] = {}
    for robot, entry in post.get("robots", {}).items():
        info: dict[str, Any] = {"fitness": entry["fitness"], "stats": entry["stats"]}
        trace = traces.get(robot)
        if trace is not None:
            steps = len(trace["sensors"])
            info["steps"] = steps
            info["safety_steps"] = int(np.count_nonzero(trace["safety"] != ""))
            if steps >= 2:
                # The prediction made at t is for the reading at t + 1.
                predicted.append(trace["predictions"][:-1])
                real.append(trace["sensors"][1:])
            if "poses" in trace and steps >= 2:
                poses[robot] = trace["poses"]
                one = trace["poses"][:, None, :]  # the metrics take (T, N, 3)
                info["path_length"] = sim_metrics.distance_covered(one)
                info["rotation"] = sim_metrics.rotation(one, sim_metrics.default_window(one, dt))
        robots[robot] = info
    metrics: dict[str, Any] = {
        "steps": post.get("steps"),
        "genome_fitness": post.get("genome_fitness"),
        "swarm_fitness": post.get("swarm_fitness"),
        "robots": robots,
    }
    if predicted:
        p = np.concatenate(predicted)
        s = np.concatenate(real)
        metrics["sensors"] = {
            name: {
                "mean_predicted": float(p[:, i].mean()),
                "mean_real": float(s[:, i].mean()),
                "mean_abs_error": float(np.abs(p[:, i] - s[:, i]).mean()),
            }
            for i, name in enumerate(sensors)
            if i < p.shape[1]
        }
    if poses:
        steps = min(len(p) for p in poses.values())
        stacked = np.stack([p[:steps] for p in poses.values()], axis=1)
        boxes = (simulation or {}).get("post_evaluation_boxes") or {}
        behaviour = sim_metrics.behaviour_metrics(
            stacked, boxes.get("start"), boxes.get("end"), dt=dt
        )
        metrics["behaviour"] = msgspec.to_builtins(behaviour)
    return metrics


@dataclass
class _Run:
    """Everything a report reads from a run directory, read once."""

    run: RunDir
    experiment: ExperimentConfig
    checkpoint: dict[str, Any]
    rows: list[dict[str, Any]]
    robots: list[str]
    post: dict[str, Any] | None
    traces: dict[str, dict[str, np.ndarray]]
    simulation: dict[str, Any] | None


def _load(path: str | Path) -> _Run:
    run = RunDir(path)
    config = run.load_config()
    assert config.experiment is not None
    checkpoint = run.read_checkpoint_data() or {}
    rows, robots = _rows(run, checkpoint.get("csv_rows"))
    post = run.read_json(POST_EVALUATION)
    simulation = run.read_json(SIMULATION_FILE)
    return _Run(
        run, config.experiment, checkpoint, rows, robots, post, _traces(run, post), simulation
    )


def compute_metrics(path: str | Path) -> dict[str, Any]:
    """The metrics of the run in ``path`` as plain data (what ``metrics.json`` holds)."""
    return _metrics(_load(path))


def _metrics(data: _Run) -> dict[str, Any]:
    run, checkpoint, rows, robots = data.run, data.checkpoint, data.rows, data.robots
    metrics: dict[str, Any] = {
        "run_id": checkpoint.get("run_id", run.path.resolve().name),
        "phase": checkpoint.get("phase", "evolution"),
        "evaluations": len(rows),
        "evaluations_planned": data.experiment.evolution.evaluations,
        "robots": robots,
    }
    if rows:
        fitness = np.array([r["fitness"] for r in rows])
        offspring = [r for r in rows if r["kind"] == "offspring"]
        metrics.update(
            best_fitness=rows[-1]["best_fitness"],
            max_fitness=float(fitness.max()),
            mean_fitness=float(fitness.mean()),
            offspring=len(offspring),
            accepted_offspring=sum(r["accepted"] for r in offspring),
            reevaluations=sum(r["kind"] == "reevaluation" for r in rows),
            attempts=sum(r["attempts"] for r in rows),
            failed_attempts=checkpoint.get("failed_attempts"),
            duration_s=float(sum(r["duration_s"] for r in rows)),
            robot_fitness={
                robot: {
                    "mean": float(np.mean([r["robots"][robot] for r in rows])),
                    "max": float(np.max([r["robots"][robot] for r in rows])),
                }
                for robot in robots
            },
        )
    metrics["post_evaluation"] = (
        None
        if data.post is None
        else _post_metrics(
            data.post,
            data.traces,
            list(data.experiment.sensors),
            data.simulation,
            data.experiment.step_period,
        )
    )
    return metrics


def _baseline_metrics(metrics: dict[str, Any], baseline: dict[str, Any]) -> dict[str, Any]:
    random_fitness = [pair["fitness"] for pair in baseline["pairs"]]
    return {
        "scenario": baseline["scenario"],
        "random_pairs": len(random_fitness),
        "random_fitness": random_fitness,
        "random_median_fitness": float(np.median(random_fitness)),
        "random_max_fitness": float(np.max(random_fitness)),
        "evolved_best_fitness": metrics.get("best_fitness"),
        "random_behaviour": {
            key: sum(pair["behaviour"][key] == value for pair in baseline["pairs"])
            for key, value in (("motion", "stopped"), ("grouping", "grouped"))
        },
    }


def write_report(
    path: str | Path, *, baseline: str | Path | None = None, plots: bool = True
) -> dict[str, Any]:
    """Write ``metrics.json`` and (with ``plots``) the plots of the run in ``path``; return the
    metrics.

    ``baseline`` names a ``surprise-master baseline`` directory: the metrics then compare the
    evolved best fitness with the random pairs' fitness (``baseline`` key), with a plot.
    """
    data = _load(path)
    metrics = _metrics(data)
    if baseline is not None:
        from master_service.baseline import load_baseline

        try:
            loaded = load_baseline(baseline)
        except (OSError, ValueError, KeyError) as exc:
            raise ConfigError(f"not a baseline: {exc}", file=str(baseline)) from None
        if loaded["scenario"] != data.experiment.scenario:
            raise ConfigError(
                f"the baseline is of the {loaded['scenario']} scenario, the run of "
                f"{data.experiment.scenario}",
                file=str(baseline),
                key="scenario",
            )
        metrics["baseline"] = _baseline_metrics(metrics, loaded)
    write_atomic(data.run.file(METRICS), json.dumps(metrics, indent=2).encode("utf-8"))
    if plots:
        _plot(data, metrics)
    return metrics


def _plot(data: _Run, metrics: dict[str, Any]) -> None:
    # The object-oriented API only: no pyplot, no global backend switch in the caller's process.
    from matplotlib.figure import Figure

    rows, robots = data.rows, data.robots
    plots = data.run.file(PLOTS)
    plots.mkdir(exist_ok=True)
    if rows:
        x = [r["evaluation"] for r in rows]
        fig = Figure(figsize=(8, 4.5))
        ax = fig.add_subplot()
        for kind, marker in (("initial", "s"), ("offspring", "."), ("reevaluation", "x")):
            pts = [(r["evaluation"], r["fitness"]) for r in rows if r["kind"] == kind]
            if pts:
                ax.scatter(*zip(*pts, strict=True), s=12, marker=marker, label=f"{kind} fitness")
        ax.plot(x, [r["best_fitness"] for r in rows], color="black", label="best fitness")
        ax.set(xlabel="evaluation", ylabel="fitness", title="Fitness over evaluations")
        ax.legend(loc="lower right")
        fig.savefig(plots / "best_fitness.png", dpi=100)

        fig = Figure(figsize=(8, 4.5))
        ax = fig.add_subplot()
        for robot in robots:
            ax.plot(x, [r["robots"][robot] for r in rows], linewidth=0.8, label=robot)
        ax.set(xlabel="evaluation", ylabel="fitness", title="Fitness of each robot")
        ax.legend(loc="lower right", fontsize="small")
        fig.savefig(plots / "robot_fitness.png", dpi=100)

    post = metrics.get("post_evaluation") or {}
    sensors = post.get("sensors")
    if sensors:
        names = list(sensors)
        idx = np.arange(len(names))
        fig = Figure(figsize=(max(6, len(names) * 0.8), 4.5))
        ax = fig.add_subplot()
        ax.bar(idx - 0.2, [sensors[n]["mean_predicted"] for n in names], 0.4, label="predicted")
        ax.bar(idx + 0.2, [sensors[n]["mean_real"] for n in names], 0.4, label="real")
        ax.set_xticks(idx, names, rotation=45, ha="right")
        ax.set(ylabel="mean value", title="Post-evaluation: mean predicted and real value")
        ax.legend()
        fig.tight_layout()
        fig.savefig(plots / "predictions.png", dpi=100)

    comparison = metrics.get("baseline")
    if comparison and comparison["evolved_best_fitness"] is not None:
        fig = Figure(figsize=(5, 4.5))
        ax = fig.add_subplot()
        ax.boxplot([comparison["random_fitness"]], positions=[0], widths=0.5)
        ax.plot([1], [comparison["evolved_best_fitness"]], "o", color="black")
        ax.set_xticks([0, 1], [f"{comparison['random_pairs']} random pairs", "evolved (best)"])
        ax.set(ylabel="fitness", title="Evolved against random pairs", xlim=(-0.6, 1.6))
        fig.savefig(plots / "evolved_vs_random.png", dpi=100)

    poses = {robot: t["poses"] for robot, t in data.traces.items() if "poses" in t}
    if poses:
        fig = Figure(figsize=(6, 6))
        ax = fig.add_subplot()
        for robot, pose in poses.items():
            ax.plot(pose[:, 0], pose[:, 1], linewidth=0.8, label=robot)
            ax.plot(pose[-1, 0], pose[-1, 1], "o", markersize=3, color="black")
        ax.set(xlabel="x", ylabel="y", title="Post-evaluation trajectories", aspect="equal")
        ax.legend(fontsize="small")
        fig.savefig(plots / "trajectories.png", dpi=100)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def status_text(path: str | Path) -> str:
    """Where the run in ``path`` stands, in a few lines."""
    run = RunDir(path)
    config = run.load_config()
    assert config.experiment is not None
    planned = config.experiment.evolution.evaluations
    checkpoint = run.read_checkpoint_data()
    lines = [f"run {run.path.resolve().name} ({run.path})"]
    if checkpoint is None:
        lines.append(f"phase: not started, 0/{planned} evaluations")
    else:
        optimizer = checkpoint.get("optimizer", {})
        best = optimizer.get("best_fitness")
        lines.append(
            f"phase: {checkpoint['phase']}, {optimizer.get('evaluations', 0)}/{planned} "
            f"evaluations counted, "
            f"{plural(checkpoint.get('failed_attempts', 0), 'failed attempt')}"
        )
        lines.append("best fitness: " + ("-" if best is None else f"{best:.4f}"))
        rows = run.read_rows()[: checkpoint.get("csv_rows", 0)]
        if rows:
            last = rows[-1]
            lines.append(
                f"last evaluation: {last['evaluation']} {last['kind']}, fitness "
                f"{float(last['fitness']):.4f}, accepted {last['accepted']}"
            )
        lines.append(f"served for {format_duration(float(checkpoint.get('elapsed_s', 0.0)))}")
    live = run.read_json(LIVE)
    fresh = (
        isinstance(live, dict)
        and live.get("running")
        and time.time() - float(live.get("updated_at", 0)) < _STALE_PERIODS * LIVE_INTERVAL
        and _alive(int(live.get("pid", -1)))
    )
    if fresh:
        robots = live.get("robots", [])
        lines.append(
            f"master: running (pid {live['pid']}, {live['host']}:{live['port']}), "
            f"robots connected {len(robots)}/{config.robot_count}: {', '.join(robots) or '-'}"
        )
        if live.get("time_left_s") is not None:
            lines.append(f"time left: ~{format_duration(live['time_left_s'])}")
    elif checkpoint is None or checkpoint.get("phase") != "done":
        lines.append(f"master: not running; continue with `surprise-master resume {run.path}`")
    else:
        lines.append("master: not running; the run is complete")
    post = run.read_json(POST_EVALUATION)
    if post is not None:
        fitness = post.get("swarm_fitness")
        lines.append(
            "post-evaluation: done, swarm fitness "
            + ("-" if fitness is None else f"{fitness:.4f}")
            + f", traces of {len(post.get('robots', {}))} robots"
        )
    return "\n".join(lines)
